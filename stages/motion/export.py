"""Exporters used by ``mocapflow export``: markers → C3D + TRC, motion → BVH, strokes → CSV.

Each is registered for a stored type name with :func:`mocapflow.pipeline.codecs.exporter`
and has the signature ``fn(obj, directory, stem, **options) -> list[Path]``.  The
``export_*`` functions are plain: usable from scripts and tests as well.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mocapflow.pipeline.codecs import exporter
from mocapflow.stages.motion.datatypes import UNIT_SCALE, Markers, Motion, Strokes
from mocapflow.stages.motion.formats.bvh import write_bvh
from mocapflow.stages.motion.formats.c3d import write_c3d
from mocapflow.stages.motion.formats.strokes import write_strokes_csv
from mocapflow.stages.motion.formats.trc import write_trc

__all__ = [
    "export_markers_c3d",
    "export_markers_trc",
    "export_motion_bvh",
    "export_strokes_csv",
]


def _unit(markers: Markers, unit: str | None) -> str:
    """``unit``, else the source unit (``attrs["source_unit"]``) when known, else ``"mm"``."""
    if unit is None:
        unit = markers.attrs.get("source_unit", "mm")
        unit = unit if unit in UNIT_SCALE else "mm"
    return unit


def export_markers_c3d(markers: Markers, path: str | Path, *, unit: str | None = None) -> Path:
    """Write markers to a C3D file with the source's analogs and parameter groups.

    Parameters
    ----------
    markers : Markers
    path : str or Path
    unit : str, optional
        POINT:UNITS of the file; default the source unit (``attrs["source_unit"]``)
        when it is a known unit, else ``"mm"``.

    Returns
    -------
    Path
        See :func:`~mocapflow.stages.motion.formats.c3d.write_c3d` for what is kept
        and how the residuals encode measured / merged / filled samples.
    """
    return write_c3d(markers, path, unit=_unit(markers, unit))


def export_markers_trc(markers: Markers, path: str | Path, *, unit: str | None = None) -> Path:
    """Write the labelled markers to an OpenSim TRC file (units and rate in its header).

    Parameters
    ----------
    markers : Markers
    path : str or Path
    unit : str, optional
        ``Units`` of the file; default as :func:`export_markers_c3d`.
    """
    return write_trc(markers, path, unit=_unit(markers, unit))


def export_motion_bvh(motion: Motion, path: str | Path) -> Path:
    """Write a motion to a BVH file (skeleton, channel order and Frame Time kept)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    out = write_bvh(motion, path)
    return Path(out) if out is not None else path


def export_strokes_csv(strokes: Strokes | list[Strokes], path: str | Path) -> Path:
    """Write one or several Strokes to a mocapflow strokes CSV (exact round trip)."""
    items = [strokes] if isinstance(strokes, Strokes) else list(strokes)
    return write_strokes_csv(items, path)


@exporter("markers")
def _export_markers(obj: Markers, directory: Path, stem: str, **options: Any) -> list[Path]:
    unit = options.get("unit")
    return [
        export_markers_c3d(obj, Path(directory) / f"{stem}.c3d", unit=unit),
        export_markers_trc(obj, Path(directory) / f"{stem}.trc", unit=unit),
    ]


@exporter("motion")
def _export_motion(obj: Motion, directory: Path, stem: str, **options: Any) -> list[Path]:
    return [export_motion_bvh(obj, Path(directory) / f"{stem}.bvh")]


@exporter("strokes")
def _export_strokes(obj: Strokes, directory: Path, stem: str, **options: Any) -> list[Path]:
    return [export_strokes_csv(obj, Path(directory) / f"{stem}.csv")]


@exporter("strokes_set")
def _export_strokes_set(obj: list, directory: Path, stem: str, **options: Any) -> list[Path]:
    return [export_strokes_csv(list(obj), Path(directory) / f"{stem}.csv")]
