"""OpenSim TRC marker files (track row column): what OpenSim's marker-based tools read.

A TRC file is tab-separated text: a ``PathFileType 4 (X/Y/Z) <name>`` line, a
header of ``DataRate CameraRate NumFrames NumMarkers Units OrigDataRate
OrigDataStartFrame OrigNumFrames`` and its values, the ``Frame# Time`` row of
marker labels (each over its three columns), the ``X1 Y1 Z1 X2 …`` row, a blank
line and one row per frame.  Missing samples are empty fields, which OpenSim's
``TRCFileAdapter`` reads as NaN.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from mocapflow.stages.motion.datatypes import UNIT_SCALE, Markers
from mocapflow.stages.motion.formats.c3d import publish

__all__ = ["write_trc"]


def _number(x: float) -> str:
    return "" if not np.isfinite(x) else f"{x:.12g}"


def write_trc(markers: Markers, path: str | os.PathLike, *, unit: str = "mm") -> Path:
    """Write the labelled markers to an OpenSim TRC file.

    Parameters
    ----------
    markers : Markers
        ``positions (F, M, 3)`` metres, NaN where missing (written as empty
        fields); fragments are not written (OpenSim matches markers by label).
    path : str or path-like
        Output file (``.trc``).
    unit : str
        ``Units`` of the file (a key of ``UNIT_SCALE``: ``"mm"``, ``"m"`` …).

    Returns
    -------
    Path
        The file written, mode ``0666 & ~umask``.  ``DataRate``, ``CameraRate`` and
        ``OrigDataRate`` are the markers' rate; ``Frame#`` counts from
        ``first_frame + 1`` (C3D's 1-based numbering, ``OrigDataStartFrame``) and
        ``Time`` is ``(first_frame + i) / rate`` seconds.  The header names the file,
        not its directory.
    """
    if unit not in UNIT_SCALE:
        raise ValueError(f"write_trc: unknown unit {unit!r} (known: {sorted(UNIT_SCALE)})")
    path = Path(path)
    F, M = markers.n_frames, markers.n_markers
    rate = markers.rate
    xyz = markers.positions.reshape(F, 3 * M) / UNIT_SCALE[unit]
    frames = markers.first_frame + 1 + np.arange(F)
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
        "OrigDataStartFrame\tOrigNumFrames",
        f"{rate:.10g}\t{rate:.10g}\t{F}\t{M}\t{unit}\t{rate:.10g}\t{frames[0] if F else 1}\t{F}",
        "\t".join(["Frame#", "Time"] + [f"{lb}\t\t" for lb in markers.labels]).rstrip("\t"),
        "\t".join(["", ""] + [f"{a}{j + 1}" for j in range(M) for a in "XYZ"]),
        "",
    ]
    for i in range(F):
        row = [str(frames[i]), f"{(frames[i] - 1) / rate:.10g}"]
        row += [_number(v) for v in xyz[i]]
        lines.append("\t".join(row))
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".trc", prefix=f".{path.stem}-", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as fh:
            fh.write("\n".join(lines) + "\n")
        publish(tmp, path)
    except Exception:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
