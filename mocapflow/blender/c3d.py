"""A small C3D reader for the Blender add-on: the standard library only, no ezc3d, no NumPy.

Blender 3.4 has no C3D importer, the add-on must not import mocapflow (nor ezc3d)
into Blender's Python, and Debian's Blender runs on the system Python, which may
lack NumPy; so the add-on reads C3D files itself with :mod:`struct` and
:mod:`array`: the header, the parameter section and the point data (float or
integer, Intel, DEC or MIPS processor), with the residual of each sample.  Files
mocapflow writes (:func:`mocapflow.stages.motion.formats.c3d.write_c3d`) say per
sample whether it was measured, merged or filled (``MOCAPFLOW`` group), which
:func:`sample_state` decodes.  Analog data is not read.

Pure Python, so it is tested outside Blender too.
"""

from __future__ import annotations

import math
import struct
import sys
from array import array
from dataclasses import dataclass, field

__all__ = ["FILLED", "MEASURED", "MERGED", "MISSING", "STATE_NAMES", "C3DFile",
           "C3DReadError", "read_c3d_points", "sample_state"]

#: Sample states (:func:`sample_state`).
MEASURED, MERGED, FILLED, MISSING = 0, 1, 2, 3
STATE_NAMES = ("measured", "merged", "filled", "missing")

#: Metres per POINT:UNITS unit.
_UNITS = {"mm": 1e-3, "cm": 1e-2, "dm": 1e-1, "m": 1.0, "in": 0.0254, "ft": 0.3048}
_BLOCK = 512
_NAN = float("nan")


class C3DReadError(ValueError):
    """A file that is not a C3D file this reader understands (the message names it)."""


@dataclass
class C3DFile:
    """The points of a C3D file.

    Attributes
    ----------
    labels : list of str
        ``P`` point labels (``POINT:LABELS``, ``LABELS2`` … joined).
    positions : list of F lists of P (x, y, z) tuples
        Metres (``POINT:UNITS`` converted), NaN coordinates where a sample is missing.
    residuals : list of F lists of P floats
        Residual byte times ``|POINT:SCALE|`` (file units; :func:`_residual_byte`),
        -1 where missing.
    rate : float
        ``POINT:RATE`` (frames per second).
    first_frame : int
        The header's first frame (as the file numbers its frames, usually from 1).
    unit : str
        ``POINT:UNITS`` as written.
    parameters : dict
        ``"GROUP:NAME" -> list`` (strings for character parameters, numbers else).
    """

    labels: list[str]
    positions: list
    residuals: list
    rate: float
    first_frame: int
    unit: str
    parameters: dict = field(default_factory=dict)


def _fail(path: str, msg: str) -> C3DReadError:
    return C3DReadError(f"{path}: {msg}")


def _numbers(raw: bytes, code: str, processor: int) -> array:
    """``raw`` as an array of ``code`` ("f" float32, "h" int16, "H" uint16) in the
    processor's byte order (84 Intel, 85 DEC: floats with 16-bit words swapped / 4,
    86 MIPS big-endian), as this machine reads it."""
    if code == "f" and processor == 85:
        b = bytearray(len(raw))
        b[0::4], b[1::4], b[2::4], b[3::4] = raw[2::4], raw[3::4], raw[0::4], raw[1::4]
        raw = bytes(b)
    a = array(code)
    a.frombytes(raw[: len(raw) - len(raw) % a.itemsize])
    if (processor == 86) != (sys.byteorder == "big"):
        a.byteswap()
    if code == "f" and processor == 85:
        a = array("f", (x / 4.0 for x in a))
    return a


def _parameters(buf: bytes, start: int, processor: int, path: str) -> dict[str, list]:
    """``"GROUP:NAME" -> values`` of the parameter section at byte ``start``."""
    groups: dict[int, str] = {}
    raw: list[tuple[int, str, list]] = []
    pos = start + 4
    while pos + 2 <= len(buf):
        nchar = struct.unpack_from("b", buf, pos)[0]
        if nchar == 0:
            break
        gid = struct.unpack_from("b", buf, pos + 1)[0]
        n = abs(nchar)
        name = buf[pos + 2:pos + 2 + n].decode("latin-1").upper()
        off_at = pos + 2 + n
        if off_at + 2 > len(buf):
            raise _fail(path, "truncated parameter section")
        offset = _numbers(buf[off_at:off_at + 2], "H", processor)[0]
        q = off_at + 2
        if gid < 0:
            groups[-gid] = name
        else:
            ptype = struct.unpack_from("b", buf, q)[0]
            ndim = buf[q + 1]
            dims = list(buf[q + 2:q + 2 + ndim])
            q += 2 + ndim
            count = math.prod(dims) if dims else 1
            size = abs(ptype) * count
            data = buf[q:q + size]
            if len(data) < size:
                raise _fail(path, f"parameter {name} runs past the file")
            raw.append((gid, name, _values(data, ptype, dims, processor)))
        if offset == 0:
            break
        pos = off_at + offset
    return {f"{groups.get(g, g)}:{name}": v for g, name, v in raw}


def _values(data: bytes, ptype: int, dims: list[int], processor: int) -> list:
    """A parameter's values: strings for characters (one per column), numbers else."""
    if ptype == -1:
        if len(dims) <= 1:
            return [data.decode("latin-1").strip()]
        width = dims[0]
        if width == 0:
            return []
        return [data[k:k + width].decode("latin-1").strip()
                for k in range(0, len(data), width)]
    if ptype == 1:
        return list(data)
    if ptype == 2:
        return list(_numbers(data, "h", processor))
    if ptype == 4:
        return list(_numbers(data, "f", processor))
    return []


def _joined(params: dict[str, list], name: str) -> list[str]:
    """``POINT:NAME``, ``NAME2``, ``NAME3`` … joined (C3D's 255-entry rule)."""
    out = list(params.get(f"POINT:{name}", []))
    k = 2
    while f"POINT:{name}{k}" in params:
        out += params[f"POINT:{name}{k}"]
        k += 1
    return out


def _residual_byte(word: float) -> int:
    """The residual byte of a sample's 4th word: its high byte, as ezc3d (which
    mocapflow reads and writes with) has it (the low byte: camera mask)."""
    return (int(abs(word)) >> 8) & 0xFF


def read_c3d_points(path: str) -> C3DFile:
    """Read the points of a C3D file (positions in metres, residuals, labels, rate).

    Parameters
    ----------
    path : str

    Returns
    -------
    C3DFile

    Raises
    ------
    C3DReadError
        Not a C3D file, an unknown processor type or unit, or a data block shorter
        than the header and parameters say.
    """
    with open(path, "rb") as fh:
        buf = fh.read()
    if len(buf) < 2 * _BLOCK or buf[1] != 0x50:
        raise _fail(path, "not a C3D file (byte 2 of the header is not 0x50)")
    pstart = (buf[0] - 1) * _BLOCK
    processor = buf[pstart + 3] if 0 <= pstart < len(buf) - 3 else 0
    if processor not in (84, 85, 86):
        raise _fail(path, f"unknown processor type {processor} (84 Intel, 85 DEC, 86 MIPS)")
    head = _numbers(buf[:24], "H", processor)
    n_points, n_analog, first, last, data_block = head[1], head[2], head[3], head[4], head[8]
    params = _parameters(buf, pstart, processor, path)
    n_points = int(params.get("POINT:USED", [n_points])[0]) & 0xFFFF
    scale = float(params.get("POINT:SCALE", [_numbers(buf[12:16], "f", processor)[0]])[0])
    rate = float(params.get("POINT:RATE", [_numbers(buf[20:24], "f", processor)[0]])[0])
    frames = last - first + 1
    if "POINT:FRAMES" in params:  # int16 in the file, read unsigned
        frames = max(int(params["POINT:FRAMES"][0]) & 0xFFFF, frames)
    if "POINT:DATA_START" in params:
        data_block = int(params["POINT:DATA_START"][0]) & 0xFFFF
    unit = ((params.get("POINT:UNITS") or ["mm"])[0].strip().lower()) or "mm"
    if unit not in _UNITS:
        raise _fail(path, f"unknown POINT:UNITS {unit!r} (known: {sorted(_UNITS)})")
    word = 4 if scale < 0 else 2
    stride = 4 * n_points + n_analog  # words per frame
    start = (data_block - 1) * _BLOCK
    need = start + frames * stride * word
    if frames < 0 or need > len(buf):
        raise _fail(path, f"data block truncated: {frames} frames of {n_points} points need "
                          f"{need} bytes, the file has {len(buf)}")
    values = _numbers(buf[start:need], "f" if word == 4 else "h", processor)
    k = _UNITS[unit] * (1.0 if word == 4 else scale)
    positions, residuals = [], []
    for f in range(frames):
        row_p, row_r = [], []
        base = f * stride
        for p in range(n_points):
            x, y, z, w = values[base + 4 * p:base + 4 * p + 4]
            if w < 0 or not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
                row_p.append((_NAN, _NAN, _NAN))
                row_r.append(-1.0)
            else:
                row_p.append((x * k, y * k, z * k))
                row_r.append(_residual_byte(w) * abs(scale))
        positions.append(row_p)
        residuals.append(row_r)
    labels = _joined(params, "LABELS")[:n_points]
    labels += [f"point{i + 1}" for i in range(len(labels), n_points)]
    return C3DFile(labels=labels, positions=positions, residuals=residuals, rate=rate,
                   first_frame=first, unit=unit, parameters=params)


def sample_state(c3d: C3DFile) -> list[list[int]]:
    """Per frame and point: measured, merged, filled or missing (the constants above).

    A file mocapflow cleaned (``MOCAPFLOW:CLEANED`` = 1) encodes them in the
    residuals: measured > 0, merged and filled 0, the filled ones listed in
    ``MOCAPFLOW:FILLED`` (point 1-based, first and last frame of each run,
    counted from 0 like ezc3d's first frame, inclusive; ``FILLED2`` … beyond 255
    runs).  Any other file: every valid sample is measured.
    """
    cleaned = int((c3d.parameters.get("MOCAPFLOW:CLEANED") or [0])[0]) == 1
    state = [[MISSING if r < 0 else (MERGED if cleaned and r == 0 else MEASURED) for r in row]
             for row in c3d.residuals]
    if not cleaned:
        return state
    f0 = max(c3d.first_frame - 1, 0)
    k = 1
    while (runs := c3d.parameters.get("MOCAPFLOW:FILLED" if k == 1
                                      else f"MOCAPFLOW:FILLED{k}")) is not None:
        # dimensions (3, N), the first varying fastest: (point, first, last) per run
        for i in range(0, len(runs) - 2, 3):
            p, a, b = int(runs[i]) - 1, int(runs[i + 1]) - f0, int(runs[i + 2]) - f0
            for f in range(max(a, 0), min(b + 1, len(state))):
                if state[f][p] != MISSING:
                    state[f][p] = FILLED
        k += 1
    return state
