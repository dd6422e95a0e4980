"""Validation of a C3D file before ezc3d reads it: header, parameter section, data size.

ezc3d (1.7) trusts what a file says, and a corrupt file can make it crash the
process, allocate without bound or read for ever:

* it requires every parameter-section entry to end exactly where the previous
  entry's offset points, reads description lengths as signed bytes (a negative
  one becomes a 4 GiB string) and indexes the dimensions of a character
  parameter without checking there is one;
* it reads ``POINT:USED``, ``RATE``, ``FRAMES``, ``SCALE``, ``ANALOG:USED``,
  ``RATE``, ``GEN_SCALE``, ``SCALE``, ``OFFSET`` (and the ``ROTATION`` group)
  with fixed types and takes their first value (or one per analog channel)
  without checking there is one;
* the data block it reads is sized by those parameters, not by the header:
  ``POINT:FRAMES`` frames, ``POINT:USED`` points (float when ``POINT:SCALE`` < 0),
  ``ANALOG:USED`` channels × ``ANALOG:RATE / POINT:RATE`` samples per frame (float
  when the header scale < 0), and it only checks for the end of the file between
  frames.

So the header and parameter section are walked here in pure Python with the same
rules, and the data ezc3d will read is checked against the file size before
anything is allocated.  Every failure is one :class:`C3DError` naming the file
and the field (header word, parameter or data block).
"""

from __future__ import annotations

import math
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["C3DError", "Layout", "check_file"]

_BLOCK = 512
_TYPE_NAMES = {-1: "character", 1: "byte", 2: "integer", 4: "float"}
#: Types ezc3d reads these parameters as, and whether it takes their first value.
_SCHEMA: list[tuple[str, str, bool]] = [
    (r"POINT:(USED|DATA_START)", "int", True),
    (r"POINT:FRAMES", "int", True),
    (r"POINT:(RATE|SCALE)", "float", True),
    (r"POINT:SCALE\d+", "float", False),
    (r"(POINT|ANALOG):(LABELS|DESCRIPTIONS|UNITS)\d*|ANALOG:FORMAT", "char", False),
    (r"ANALOG:USED", "int", True),
    (r"ANALOG:(RATE|GEN_SCALE)", "float", True),
    (r"ANALOG:SCALE\d*", "float", False),
    (r"ANALOG:(OFFSET\d*|BITS)", "int", False),
    (r"FORCE_PLATFORM:(USED|TYPE|ZERO|CHANNEL)", "int", False),
    (r"FORCE_PLATFORM:(CORNERS|ORIGIN|CAL_MATRIX)", "float", False),
    (r"ROTATION:(USED|DATA_START|RATIO)", "int", True),
    (r"ROTATION:RATE", "float", True),
]
_MAX_RATIO = 0xFFFF


class C3DError(ValueError):
    """A C3D file is empty, truncated, corrupt or not supported (the message names it)."""


@dataclass(frozen=True)
class Layout:
    """What ezc3d will read from the data block (sizes as its own rules make them)."""

    n_points: int
    n_analog_per_frame: int
    first_frame: int
    n_frames: int
    word: int
    data_start: int
    processor: int
    #: Analog words per frame the header declares (word 3) and the bytes of the data
    #: block: what :func:`~mocapflow.stages.motion.formats.c3d._read_points` checks the
    #: frames ezc3d read against.
    header_analog_words: int = 0
    data_bytes: int = 0


@dataclass(frozen=True)
class _Param:
    """A parameter's type (-1, 1, 2, 4), dimensions and, when numeric, its first values."""

    ptype: int
    dims: tuple[int, ...]
    values: list

    @property
    def count(self) -> int:
        """Number of elements (bytes for character data; a scalar has no dimensions)."""
        return int(np.prod(self.dims, dtype=np.int64))


def _fail(path: Path, msg: str) -> C3DError:
    return C3DError(f"{path}: {msg}")


def _reader(buf: bytes, processor: int):
    """Return ``(u16, i16, f32)`` unpackers for the file's processor type."""
    if processor == 86:  # MIPS, big-endian
        return (
            lambda o: struct.unpack_from(">H", buf, o)[0],
            lambda o: struct.unpack_from(">h", buf, o)[0],
            lambda o: struct.unpack_from(">f", buf, o)[0],
        )

    def f32(o: int) -> float:
        if processor == 85:  # DEC (VAX F-float): swap 16-bit words, divide by 4
            b = buf[o : o + 4]
            return struct.unpack("<f", b[2:4] + b[0:2])[0] / 4.0
        return struct.unpack_from("<f", buf, o)[0]

    return (
        lambda o: struct.unpack_from("<H", buf, o)[0],
        lambda o: struct.unpack_from("<h", buf, o)[0],
        f32,
    )


# --------------------------------------------------------------------------- parameters


def walk_parameters(
    buf: bytes, path: Path, start: int, end: int, processor: int
) -> tuple[dict[str, _Param], set[str]]:
    """Walk the parameter section; return ``{"GROUP:NAME": _Param}`` and the group names.

    Raises :class:`C3DError` when an entry runs past the section, does not end where
    its offset says the next one starts, has an invalid name, type, dimensions or
    description length.  A parameter whose group id no group entry defines is left out
    (ezc3d files it under a group named ``""``, which :func:`~.c3d.read_c3d` drops with
    a note); ezc3d reads none of them.
    """
    try:
        return _walk(buf[:end], path, start, end, processor)
    except (IndexError, struct.error):
        raise _fail(path, "truncated or corrupt parameter section") from None


def _walk(
    buf: bytes, path: Path, start: int, end: int, processor: int
) -> tuple[dict[str, _Param], set[str]]:
    u16, i16, f32 = _reader(buf, processor)
    groups: dict[int, str] = {}
    raw: list[tuple[int, str, _Param]] = []
    pos = start + 4
    for _ in range(100_000):
        if pos + 1 > end:
            raise _fail(path, f"parameter section truncated at byte {pos}")
        nchar = struct.unpack_from("b", buf, pos)[0]
        if nchar == 0:  # the terminator: one byte (it may be the section's last)
            break
        if pos + 2 > end:
            raise _fail(path, f"parameter section truncated at byte {pos}")
        gid = struct.unpack_from("b", buf, pos + 1)[0]
        n = abs(nchar)
        name_b = buf[pos + 2 : pos + 2 + n]
        off_at = pos + 2 + n
        if off_at + 3 > end:
            raise _fail(path, f"parameter section truncated in entry at byte {pos}")
        if gid == 0 or any(c < 32 for c in name_b):
            raise _fail(path, f"corrupt parameter section: invalid entry at byte {pos}")
        name = name_b.decode("latin-1").upper()
        offset = u16(off_at)
        q = off_at + 2
        if gid < 0:
            if -gid in groups and groups[-gid] != name:
                raise _fail(path, f"corrupt parameter section: group id {-gid} defined twice")
            groups[-gid] = name
            what = f"group {name!r}"
        else:
            what = f"parameter {groups.get(gid, f'(group {gid})')}:{name}"
            param, q = _read_param(buf, path, what, q, end, (u16, i16, f32))
            raw.append((gid, name, param))
        if buf[q] > 127:  # ezc3d reads it as a signed byte: a negative length
            raise _fail(
                path,
                f"corrupt parameter section: {what} has description length {buf[q]} (at most 127)",
            )
        q += 1 + buf[q]
        if q > end:
            raise _fail(path, f"{what} runs past the parameter section")
        if offset == 0:
            break
        if off_at + offset != q:  # ezc3d requires the next entry to start right here
            raise _fail(
                path,
                f"corrupt parameter section: {what} at byte {pos} ends at byte {q} but its "
                f"offset points to byte {off_at + offset}",
            )
        pos = q
    else:  # pragma: no cover - bounded by the section size anyway
        raise _fail(path, "corrupt parameter section: too many entries")
    if "POINT" not in groups.values():
        holds = sorted(set(groups.values()) & {"ANALOG", "FORCE_PLATFORM", "ROTATION"})
        points = u16(2)  # the header's (word 2)
        if points:  # c3d.org sample20 (PhaseSpace): 40 points, no POINT group
            raise _fail(path, f"no POINT group in the parameter section: the header's "
                        f"{points} points have no labels, rate or unit to read them with")
        raise _fail(path, "no POINT group in the parameter section: no marker data"
                    + (f" (the file holds {', '.join(holds)} only)" if holds else ""))
    params: dict[str, _Param] = {}
    for gid, name, param in raw:
        if gid in groups:
            params[f"{groups[gid]}:{name}"] = param
    return params, set(groups.values())


def _read_param(buf: bytes, path: Path, what: str, q: int, end: int, readers) -> tuple:
    """The parameter whose type byte is at ``q`` (``what``: "parameter GROUP:NAME"); returns
    it and where its description starts."""
    u16, i16, f32 = readers
    ptype = struct.unpack_from("b", buf, q)[0]
    if ptype not in _TYPE_NAMES:
        raise _fail(path, f"corrupt {what}: unknown data type {ptype}")
    ndim = buf[q + 1]
    if ndim > 7 or q + 2 + ndim > end:
        raise _fail(path, f"corrupt {what}: {ndim} dimensions")
    if ptype == -1 and ndim == 0:  # ezc3d indexes dimension[0] of a character parameter
        raise _fail(path, f"corrupt {what}: character data without dimensions")
    dims = tuple(buf[q + 2 : q + 2 + ndim])
    at = q + 2 + ndim
    count = int(np.prod(dims, dtype=np.int64))
    q = at + abs(ptype) * count
    if q + 1 > end:
        raise _fail(path, f"{what} runs past the parameter section")
    k = min(count, 4)
    if ptype == 1:
        values: list = [buf[at + i] for i in range(k)]
    elif ptype == 2:
        values = [i16(at + 2 * i) for i in range(k)]
    elif ptype == 4:
        values = [f32(at + 4 * i) for i in range(k)]
    else:
        values = []
    return _Param(ptype, dims, values), q


def _check_schema(path: Path, params: dict[str, _Param]) -> None:
    """The parameters ezc3d reads with a fixed type have it, and a first value where taken."""
    for key, p in params.items():
        for pattern, kind, first in _SCHEMA:
            if not re.fullmatch(pattern, key):
                continue
            ok = {"int": p.ptype in (1, 2), "float": p.ptype == 4, "char": p.ptype == -1}[kind]
            if not ok:
                raise _fail(
                    path,
                    f"{key} is stored as {_TYPE_NAMES[p.ptype]} data; a C3D {kind} parameter "
                    "was expected",
                )
            if first and p.count == 0:
                raise _fail(path, f"{key} has no value")
            break


def _total(params: dict[str, _Param], key: str) -> int:
    """Elements of ``key`` joined with ``key2``, ``key3`` … (the C3D > 255 entries rule)."""
    n, k = 0, 2
    p = params.get(key)
    while p is not None:
        n += p.count
        p, k = params.get(f"{key}{k}"), k + 1
    return n


# --------------------------------------------------------------------------- layout


def _first(params: dict[str, _Param], key: str, default):
    p = params.get(key)
    return p.values[0] if p is not None and p.values else default


def _analog_per_frame(path: Path, params: dict, header: dict, shadow: bool) -> tuple[int, int]:
    """``(channels, samples per channel and frame)`` as ezc3d's ``updateHeader`` sets them
    (``shadow``: the file has a SHADOW group, whose analog defaults ezc3d fills in)."""
    point_rate = float(_first(params, "POINT:RATE", 0.0))
    analog_rate = float(_first(params, "ANALOG:RATE", 0.0))
    for key, v in (("POINT:RATE", point_rate), ("ANALOG:RATE", analog_rate)):
        if not (math.isfinite(v) and v >= 0):
            raise _fail(path, f"{key} is {v}: a rate must be finite and not negative")
    per_frame = header["analog_per_frame"]
    if point_rate < 1:
        per_frame = 1 if per_frame != 1 else per_frame
    else:
        ratio = analog_rate / point_rate
        if ratio > _MAX_RATIO:
            raise _fail(
                path,
                f"ANALOG:RATE {analog_rate:g} / POINT:RATE {point_rate:g} is {ratio:.3g} "
                f"analog samples per frame (at most {_MAX_RATIO})",
            )
        if int(ratio) != per_frame and not (per_frame == 1 and shadow):
            per_frame = int(ratio)
    used = _first(params, "ANALOG:USED", 0) & 0xFFFF
    channels = used if per_frame else 0
    if channels:
        for key in ("ANALOG:SCALE", "ANALOG:OFFSET"):
            n = _total(params, key)
            if n < channels and not (shadow and n == 0):
                raise _fail(
                    path,
                    f"{key} has {_total(params, key)} entries for {channels} analog "
                    "channels (ANALOG:USED)",
                )
    return channels, per_frame


def _frame_count(path: Path, params: dict, header: dict) -> tuple[int, int]:
    """``(first frame, frames)`` as ezc3d reads them (0-based, ``POINT:FRAMES`` first)."""
    first, last = header["first"], header["last"]
    first0 = first - 1 if first else 0
    last0 = last - 1 if (last and first) else last
    n_frames = last0 - first0 + 1
    frames = params.get("POINT:FRAMES")
    if frames is not None and frames.values and frames.values[0] != 0:
        n_frames = int(frames.values[0]) & 0xFFFF  # ezc3d reads a negative int16 unsigned
    elif n_frames < 1:
        raise _fail(path, f"corrupt C3D header: last frame {last} before first frame {first}")
    return first0, n_frames


def _header(buf: bytes, path: Path) -> tuple[dict, int]:
    """The header words ezc3d uses, and the processor type (from the parameter section)."""
    size = len(buf)
    if size == 0:
        raise _fail(path, "file size 0 bytes: empty file, not a C3D file")
    if size < _BLOCK:
        raise _fail(path, f"truncated C3D file: {size} bytes, shorter than the 512-byte header")
    if buf[1] != 0x50:
        raise _fail(path, "not a C3D file (header key byte is not 0x50)")
    pblock = buf[0]
    if pblock < 2:
        raise _fail(path, f"not a C3D file (header parameter block number {pblock})")
    pstart = (pblock - 1) * _BLOCK
    if pstart + 4 > size:
        raise _fail(path, f"truncated C3D file: parameter section at byte {pstart} is missing")
    processor = buf[pstart + 3]
    if processor not in (84, 85, 86):
        raise _fail(path, f"corrupt C3D file: unknown processor type {processor}")
    if processor == 86:
        raise _fail(path, "unsupported C3D file: processor type 86 (MIPS), which ezc3d refuses")
    u16, _, f32 = _reader(buf, processor)
    scale = f32(12)
    if not np.isfinite(scale) or scale == 0:
        raise _fail(path, f"corrupt C3D header: POINT scale {scale}")
    header = {
        "points": u16(2),
        "analogs": u16(4),
        "first": u16(6),
        "last": u16(8),
        "scale": scale,
        "data_start": u16(16),
        "analog_per_frame": u16(18),
        "pstart": pstart,
    }
    if header["data_start"] < 2:
        raise _fail(path, f"corrupt C3D header: data start block {header['data_start']}")
    return header, processor


def check_file(path: Path) -> Layout:
    """Validate header, parameter section and data size of a C3D file (no ezc3d).

    Returns
    -------
    Layout
        What ezc3d will read.

    Raises
    ------
    C3DError
        Naming the file and the header word, parameter or data block at fault.
    """
    try:
        buf = path.read_bytes()
    except OSError as e:
        raise _fail(path, f"cannot read C3D file ({e.strerror or e})") from None
    header, processor = _header(buf, path)
    size, pblock, data_start = len(buf), buf[0], header["data_start"]
    pend = min(size, (data_start - 1) * _BLOCK) if data_start > pblock else size
    params, groups = walk_parameters(buf, path, header["pstart"], pend, processor)
    _check_schema(path, params)
    n_points = header["points"]
    used = _first(params, "POINT:USED", None)
    if used is not None and (used & 0xFFFF) != n_points:
        raise _fail(
            path, f"corrupt C3D file: header says {n_points} points, POINT:USED {used & 0xFFFF}"
        )
    channels, per_frame = _analog_per_frame(path, params, header, "SHADOW" in groups)
    first0, n_frames = _frame_count(path, params, header)
    if not (n_points or channels or "ROTATION" in groups):
        raise _fail(
            path,
            f"no frames: {n_points} points and {channels} analog channels "
            "(header, POINT:USED, ANALOG:USED)",
        )
    point_scale = float(_first(params, "POINT:SCALE", -1.0)) if n_points else -1.0
    if not math.isfinite(point_scale) or point_scale == 0:
        raise _fail(path, f"POINT:SCALE is {point_scale}: the points cannot be scaled")
    word = 4 if point_scale < 0 else 2
    analog_word = 4 if header["scale"] < 0 else 2
    frame_bytes = 4 * n_points * word + channels * per_frame * analog_word
    need = (data_start - 1) * _BLOCK + n_frames * frame_bytes
    if size < need:
        have = max(size - (data_start - 1) * _BLOCK, 0) // frame_bytes if frame_bytes else 0
        raise _fail(
            path,
            f"truncated C3D file: {size} bytes, the data block needs {need} "
            f"({n_frames} frames of {n_points} points; only {have} complete frames present)",
        )
    if "ROTATION" in groups:
        _check_rotations(
            path, params, n_frames, size=size, point_rate=float(_first(params, "POINT:RATE", 0.0))
        )
    return Layout(n_points, channels * per_frame, first0, n_frames, word, data_start, processor,
                  header["analogs"], size - (data_start - 1) * _BLOCK)  # fmt: skip


def _check_rotations(
    path: Path, params: dict, n_frames: int, *, point_rate: float, size: int
) -> None:
    """A ``ROTATION`` group: its parameters are there and its data fits in the file."""
    for key in ("ROTATION:DATA_START", "ROTATION:USED"):
        if key not in params:
            raise _fail(path, f"{key} is missing (the file has a ROTATION group)")
    if "ROTATION:RATIO" in params:
        ratio = float(params["ROTATION:RATIO"].values[0])
    elif "ROTATION:RATE" in params and point_rate > 0:
        ratio = float(params["ROTATION:RATE"].values[0]) / point_rate
    else:
        raise _fail(path, "ROTATION:RATIO or a ROTATION:RATE with a POINT:RATE is needed")
    if not (math.isfinite(ratio) and 0 <= ratio <= _MAX_RATIO):
        raise _fail(path, f"ROTATION:RATIO (or RATE) gives {ratio} rotations per frame")
    start = params["ROTATION:DATA_START"].values[0] & 0xFFFF
    used = params["ROTATION:USED"].values[0] & 0xFFFF
    need = (max(start, 1) - 1) * _BLOCK + n_frames * used * int(ratio) * 17 * 4
    if size < need:
        raise _fail(path, f"truncated C3D file: {size} bytes, the ROTATION data block needs {need}")
