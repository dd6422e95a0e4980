"""Exporters used by ``mocapflow export``: markers → C3D, motion → BVH, strokes → CSV.

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

__all__ = [
    "export_markers_c3d",
    "export_motion_bvh",
    "export_strokes_csv",
]


def export_markers_c3d(markers: Markers, path: str | Path, *, unit: str | None = None) -> Path:
    """Write markers to a C3D file.

    Parameters
    ----------
    markers : Markers
    path : str or Path
    unit : str, optional
        POINT:UNITS of the file; default the source unit (``attrs["source_unit"]``)
        when it is a known unit, else ``"mm"``.
    """
    if unit is None:
        unit = markers.attrs.get("source_unit", "mm")
        unit = unit if unit in UNIT_SCALE else "mm"
    return write_c3d(markers, path, unit=unit)


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
    return [export_markers_c3d(obj, Path(directory) / f"{stem}.c3d", unit=options.get("unit"))]


@exporter("motion")
def _export_motion(obj: Motion, directory: Path, stem: str, **options: Any) -> list[Path]:
    return [export_motion_bvh(obj, Path(directory) / f"{stem}.bvh")]


@exporter("strokes")
def _export_strokes(obj: Strokes, directory: Path, stem: str, **options: Any) -> list[Path]:
    return [export_strokes_csv(obj, Path(directory) / f"{stem}.csv")]


@exporter("strokes_set")
def _export_strokes_set(obj: list, directory: Path, stem: str, **options: Any) -> list[Path]:
    return [export_strokes_csv(list(obj), Path(directory) / f"{stem}.csv")]
