"""BVH (Biovision Hierarchy) read and write.

Reading
-------
Any per-joint channel layout is accepted: position channels on any joint
(non-root ones go to :attr:`Motion.translations`), 0-3 rotation channels in any
order, channel names in any letter case (``ZPosition``), End Sites (named ones,
``End Site NAME``, too: the name is dropped), tabs, CRLF/CR line ends, scientific
notation.  Writing uses the canonical spelling (``Zposition``, ``End Site``).  Rotations
follow the BVH convention ``R = R_first @ R_second @ R_third`` for the rotation
channels in file order (intrinsic), angles in degrees, and are stored as unit
quaternions made sign-continuous along frames.  Where the root has position
channels they give its world position (its OFFSET is kept but not added, as in
Blender and bvhio); without them the root sits at its OFFSET.

Units
-----
Lengths are stored in metres; ``motion.attrs["source_unit"]`` and
``["source_scale"]`` (metres per file unit) record the file's unit so
:func:`write_bvh` writes it back unchanged.  ``unit="auto"`` picks, among
:data:`BVH_UNITS`, the unit that makes the rest-pose extent (largest axis-aligned
extent of joints and End Sites at zero rotation, i.e. about the body height)
closest to 1.7 m on a log scale.  The CMU conversions use "cmu" units
(inches / 0.45, the ASF ``length 0.45`` convention: 0.056444 m).

Frame Time
----------
``motion.rate`` is ``1 / Frame Time``, snapped to the nearest integer when the
written Frame Time equals ``1 / n`` to its printed precision (``.0083333`` ->
120).  The exact text is kept in ``attrs["frame_time_text"]`` and written back
when the rate is unchanged.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mocapflow.stages.motion.datatypes import UNIT_SCALE, Motion, Skeleton
from mocapflow.stages.motion.formats import MAX_DISTANCE_M
from mocapflow.stages.motion.formats.text import read_text
from mocapflow.stages.motion.rotations import (
    euler_to_quat,
    padded_order,
    quat_continuity,
    quat_to_euler,
)

__all__ = ["BVH_UNITS", "BVHError", "guess_unit", "read_bvh", "rest_extent", "write_bvh"]

#: Metres per file unit for the units ``read_bvh`` understands (``unit=``): those of
#: :data:`~mocapflow.stages.motion.datatypes.UNIT_SCALE`, ``cmu`` included.
BVH_UNITS: dict[str, float] = dict(UNIT_SCALE)

#: Candidates of ``unit="auto"``, checked against a 1.7 m body.
_AUTO_UNITS = ("m", "dm", "cmu", "in", "cm", "mm")
_TYPICAL_HEIGHT_M = 1.7

#: Channel names, lower case (read case-insensitively, as Blender does) -> the canonical
#: spelling written back (``ZPosition`` -> ``Zposition``).
_CHANNELS = {f"{a}{k}": f"{a.upper()}{k}" for a in "xyz" for k in ("position", "rotation")}

#: Deepest joint nesting :func:`read_bvh` accepts (real skeletons nest 5-30 deep).
MAX_DEPTH = 256


class BVHError(ValueError):
    """A BVH file cannot be parsed or written; the message names the file and line."""


# --------------------------------------------------------------------------- parsing


@dataclass
class _Joint:
    name: str
    parent: int
    line: int
    offset: np.ndarray | None = None
    channels: list[str] = field(default_factory=list)


class _Tokens:
    """Token stream over the hierarchy lines, with line numbers."""

    def __init__(self, lines: list[str], path: str, start: int) -> None:
        self.path = path
        self.toks: list[tuple[str, int]] = []
        for i, line in enumerate(lines):
            for t in line.split():
                self.toks.append((t, start + i))
        self.i = 0
        self.last_line = start + max(len(lines) - 1, 0)

    def error(self, msg: str, line: int | None = None) -> BVHError:
        return BVHError(f"{self.path}:{line or self.last_line}: {msg}")

    def peek(self) -> tuple[str, int] | None:
        return self.toks[self.i] if self.i < len(self.toks) else None

    def next(self, what: str) -> tuple[str, int]:
        if self.i >= len(self.toks):
            raise self.error(f"truncated hierarchy: file ends where {what} was expected")
        tok = self.toks[self.i]
        self.i += 1
        return tok

    def expect(self, word: str, where: str) -> int:
        tok, line = self.next(f"{word!r} of {where}")
        if tok != word:
            raise self.error(f"{where}: expected {word!r}, found {tok!r}", line)
        return line

    def rest_of_line(self, line: int) -> list[str]:
        out = []
        while self.i < len(self.toks) and self.toks[self.i][1] == line:
            out.append(self.toks[self.i][0])
            self.i += 1
        return out

    def number(self, what: str) -> float:
        tok, line = self.next(what)
        try:
            return float(tok)
        except ValueError:
            raise self.error(f"bad number {tok!r} in {what}", line) from None


def _parse_hierarchy(tk: _Tokens) -> tuple[list[_Joint], list[tuple[int, np.ndarray]]]:
    """Joints (parents before children, depth first) and End Sites ``(joint, offset)``.

    Iterative, with the open joints on a stack: nesting deeper than
    :data:`MAX_DEPTH` joints is an error naming the joint, and two joints with
    one name are an error naming both lines.
    """
    tok, line = tk.next("'HIERARCHY'")
    if tok.upper() != "HIERARCHY":
        raise tk.error(f"expected 'HIERARCHY', found {tok!r}", line)
    tok, line = tk.next("'ROOT'")
    if tok.upper() != "ROOT":
        raise tk.error(f"expected 'ROOT' after HIERARCHY, found {tok!r}", line)
    joints: list[_Joint] = []
    ends: list[tuple[int, np.ndarray]] = []
    seen: dict[str, int] = {}
    stack = [_open_joint(tk, joints, seen, parent=-1, line=line)]
    while stack:
        j = stack[-1]
        name = joints[j].name
        tok, tline = tk.next(f"'}}' closing joint {name!r} (opened line {joints[j].line})")
        word = tok.upper()
        if word == "}":
            stack.pop()
        elif word == "JOINT":
            if len(stack) >= MAX_DEPTH:
                raise tk.error(
                    f"JOINT inside joint {name!r}: the hierarchy nests deeper than "
                    f"{MAX_DEPTH} joints",
                    tline,
                )
            stack.append(_open_joint(tk, joints, seen, parent=j, line=tline))
        elif word == "END":
            site = tk.next("'Site'")
            if site[0].upper() != "SITE":
                raise tk.error(f"expected 'End Site', found 'End {site[0]}'", site[1])
            _name_on_line(tk, site[1])  # "End Site NAME": the name is dropped (as Blender)
            tk.expect("{", f"End Site of {name!r}")
            ends.append((j, _parse_offset(tk, f"End Site of {name!r}")))
            tk.expect("}", f"End Site of {name!r}")
        else:
            raise tk.error(
                f"expected 'JOINT', 'End Site' or '}}' in joint {name!r}, found {tok!r}", tline
            )
    nxt = tk.peek()
    if nxt is not None:
        raise tk.error(
            f"hierarchy: unexpected {nxt[0]!r} after the root joint's closing brace", nxt[1]
        )
    return joints, ends


def _name_on_line(tk: _Tokens, line: int) -> str:
    """The rest of ``line`` up to a final ``{`` (left in the stream): ``JOINT name {``,
    ``End Site NAME {``."""
    words = tk.rest_of_line(line)
    if words and words[-1] == "{":
        tk.i -= 1
        words = words[:-1]
    return " ".join(words)


def _joint_name(tk: _Tokens, line: int) -> str:
    name = _name_on_line(tk, line)
    if not name:
        raise tk.error("JOINT without a name", line)
    return name


def _parse_offset(tk: _Tokens, what: str) -> np.ndarray:
    line = tk.expect("OFFSET", what)
    off = np.array([tk.number(f"{what} OFFSET") for _ in range(3)])
    if not np.isfinite(off).all():
        raise tk.error(f"OFFSET of {what} is not finite: {' '.join(map(str, off))}", line)
    return off


def _open_joint(
    tk: _Tokens, joints: list[_Joint], seen: dict[str, int], parent: int, line: int
) -> int:
    """Read a joint's name, ``{``, OFFSET and CHANNELS; append it; return its index."""
    name = _joint_name(tk, line)
    if name in seen:
        raise tk.error(f"JOINT name {name!r} is used twice (lines {seen[name]} and {line})", line)
    seen[name] = line
    joint = _Joint(name, parent, line)
    joints.append(joint)
    tk.expect("{", f"joint {name!r}")
    joint.offset = _parse_offset(tk, f"joint {name!r}")
    tok = tk.peek()
    if tok is not None and tok[0].upper() == "CHANNELS":
        _parse_channels(tk, joint)
    return len(joints) - 1


def _parse_channels(tk: _Tokens, joint: _Joint) -> None:
    name = joint.name
    tk.next("CHANNELS")
    count_line = tk.peek()[1] if tk.peek() else tk.last_line
    n = tk.number(f"joint {name!r} CHANNELS count")
    if not (math.isfinite(n) and n == int(n) and 0 <= n <= 6):
        raise tk.error(
            f"bad CHANNELS count {n} for joint {name!r} (0 to 6: X/Y/Z position and rotation)",
            count_line,
        )
    for _ in range(int(n)):
        ch, ch_line = tk.next(f"a channel name of joint {name!r}")
        if ch.lower() not in _CHANNELS:
            raise tk.error(
                f"unknown channel {ch!r} of joint {name!r} (expected X/Y/Z position or rotation)",
                ch_line,
            )
        joint.channels.append(_CHANNELS[ch.lower()])
    rot = "".join(c[0] for c in joint.channels if c.endswith("rotation"))
    if len(set(rot)) != len(rot):
        raise tk.error(
            f"unknown rotation order {rot!r} of joint {name!r} (an axis repeats)", count_line
        )
    pos = [c for c in joint.channels if c.endswith("position")]
    if len(set(pos)) != len(pos):
        raise tk.error(f"repeated position channel in joint {name!r}", count_line)


def _snap_rate(frame_time: float, text: str) -> float:
    """``1 / frame_time``, snapped to an integer when the text is ``1/n`` rounded."""
    rate = 1.0 / frame_time
    n = round(rate)
    if n > 0:
        mant = text.lower().split("e")[0]
        decimals = len(mant.split(".")[1]) if "." in mant else 0
        exp = int(text.lower().split("e")[1]) if "e" in text.lower() else 0
        half_ulp = 0.5 * 10.0 ** (exp - decimals)
        if abs(frame_time - 1.0 / n) <= half_ulp * (1 + 1e-9):
            return float(n)
    return rate


def _rest_extent(parents: np.ndarray, offsets: np.ndarray, ends: list[tuple[int, np.ndarray]]):
    pos = np.zeros_like(offsets)
    pos[0] = offsets[0]
    for j in range(1, len(parents)):
        pos[j] = pos[parents[j]] + offsets[j]
    pts = [pos] + [pos[p][None] + o[None] for p, o in ends]
    pts = np.concatenate(pts, axis=0)
    return float(np.max(pts.max(0) - pts.min(0)))


def rest_extent(skeleton: Skeleton) -> float:
    """Largest extent of ``skeleton``'s rest pose, joints and End Sites, in its length
    unit (the quantity :func:`guess_unit` judges)."""
    return _rest_extent(skeleton.parents, skeleton.offsets,
                        list(zip(skeleton.end_parents, skeleton.end_offsets)))


def guess_unit(extent: float) -> str:
    """The :data:`BVH_UNITS` name under which ``extent`` file units is nearest 1.7 m.

    Parameters
    ----------
    extent : float
        Rest-pose extent (about the body height) in file units.

    Returns
    -------
    str
        One of ``m, dm, cmu, in, cm, mm`` (``m`` for a zero extent).
    """
    if not extent > 0:
        return "m"
    return min(
        _AUTO_UNITS,
        key=lambda u: abs(math.log(extent * BVH_UNITS[u] / _TYPICAL_HEIGHT_M)),
    )


def _resolve_unit(unit: str | float, extent: float, path: str) -> tuple[str, float]:
    if isinstance(unit, int | float) and not isinstance(unit, bool):
        if not (unit > 0 and math.isfinite(unit)):
            raise BVHError(f"{path}: unit scale must be a finite number > 0, got {unit}")
        return f"{float(unit)!r} m", float(unit)
    u = str(unit)
    if u == "auto":
        u = guess_unit(extent)
    if u not in BVH_UNITS:
        raise BVHError(
            f"{path}: unknown unit {unit!r}; expected 'auto', a number or one of "
            f"{', '.join(BVH_UNITS)}"
        )
    return u, BVH_UNITS[u]


def read_bvh(path: str | os.PathLike, *, unit: str | float = "auto") -> Motion:
    """Read a BVH file.

    Parameters
    ----------
    path : str or path-like
    unit : {"auto", "m", "dm", "cm", "mm", "in", "ft", "cmu"} or float
        Unit of the file's lengths, or metres per file unit; ``"auto"`` guesses
        it from the rest-pose extent (see module docstring).

    Returns
    -------
    Motion
        ``F`` frames; ``rotations (F, J, 4)``, ``root_position (F, 3)`` in metres;
        ``translations (F, J, 3)`` when a non-root joint has position channels
        (joints without them hold their offset).  ``attrs``: ``source_file`` (the name),
        ``source_format``, ``source_unit``, ``source_scale``, ``frame_time``,
        ``frame_time_text``.

    Raises
    ------
    BVHError
        Empty or truncated file, bad numbers, unknown channels or rotation
        orders, frame lines with the wrong number of values; the message names
        the file and line.
    """
    p = os.fspath(path)
    lines, joints, ends, motion_at = _read_hierarchy(p)
    n_frames, frame_time, frame_time_text, k = _motion_header(lines, motion_at, p)
    _check_budget(p, joints, n_frames, k - 1)
    data = _parse_frames(lines, k, n_frames, sum(len(j.channels) for j in joints), p)
    skeleton = _skeleton(joints, ends, unit, p)
    with np.errstate(over="ignore", invalid="ignore"):
        root_position, rotations, translations = _channels_to_motion(
            skeleton, data, skeleton.attrs["source_scale"]
        )
    _check_positions_finite(p, root_position, translations, k)
    attrs = {
        "source_file": os.path.basename(p),  # no path in outputs
        "source_format": "bvh",
        "source_unit": skeleton.attrs["source_unit"],
        "source_scale": skeleton.attrs["source_scale"],
        "frame_time": frame_time,
        "frame_time_text": frame_time_text,
    }
    return Motion(
        skeleton=skeleton,
        root_position=root_position,
        rotations=rotations,
        rate=_snap_rate(frame_time, frame_time_text),
        translations=translations,
        attrs=attrs,
    )


def _read_hierarchy(p: str) -> tuple[list[str], list[_Joint], list[tuple[int, np.ndarray]], int]:
    """The file's lines, its joints and End Sites, and the index of the ``MOTION`` line."""
    text = read_text(p)
    lines = text.splitlines()
    if not text.strip():
        raise BVHError(f"{p}:1: empty file")
    motion_at = next(
        (i for i, ln in enumerate(lines) if ln.strip().upper().startswith("MOTION")), None
    )
    hier_lines = lines if motion_at is None else lines[:motion_at]
    tk = _Tokens(hier_lines, p, start=1)
    joints, ends = _parse_hierarchy(tk)
    if motion_at is None:
        raise BVHError(f"{p}:{len(lines)}: truncated file: no MOTION section after the hierarchy")
    if lines[motion_at].strip().upper() != "MOTION":
        raise BVHError(f"{p}:{motion_at + 1}: expected 'MOTION', found {lines[motion_at]!r}")
    return lines, joints, ends, motion_at


def _motion_header(lines: list[str], motion_at: int, p: str) -> tuple[int, float, str, int]:
    """``Frames:`` and ``Frame Time:`` after the ``MOTION`` line (blank lines skipped).

    Returns the frame count, the frame time (s), its text as written, and the
    index of the line after the header (where the frames start).  The count must
    be positive and fit in the lines that follow (checked before anything is
    allocated); ``1 / Frame Time`` must be a finite rate.
    """
    k = motion_at + 1
    header: list[tuple[list[str], int]] = []
    while len(header) < 2 and k < len(lines):
        if lines[k].strip():
            header.append((lines[k].split(), k + 1))
        k += 1
    if len(header) < 2:
        raise BVHError(f"{p}:{len(lines)}: truncated file: 'Frames:' and 'Frame Time:' expected")
    (ftoks, fline), (ttoks, tline) = header
    if len(ftoks) != 2 or ftoks[0].lower() != "frames:":
        raise BVHError(f"{p}:{fline}: expected 'Frames: <count>', found {' '.join(ftoks)!r}")
    try:
        n_frames = int(ftoks[1])
    except ValueError:
        raise BVHError(f"{p}:{fline}: Frames: bad frame count {ftoks[1]!r}") from None
    if n_frames <= 0:
        raise BVHError(f"{p}:{fline}: Frames: {n_frames}: a BVH motion needs at least one frame")
    if n_frames > len(lines) - k:
        raise BVHError(
            f"{p}:{len(lines)}: truncated motion: 'Frames: {n_frames}' but only "
            f"{len(lines) - k} lines after the header"
        )
    if len(ttoks) != 3 or [t.lower() for t in ttoks[:2]] != ["frame", "time:"]:
        raise BVHError(f"{p}:{tline}: expected 'Frame Time: <seconds>', found {' '.join(ttoks)!r}")
    try:
        frame_time = float(ttoks[2])
    except ValueError:
        frame_time = math.nan
    if not (frame_time > 0 and math.isfinite(frame_time)):
        raise BVHError(f"{p}:{tline}: Frame Time: bad frame time {ttoks[2]!r}")
    if not math.isfinite(1.0 / frame_time):
        raise BVHError(
            f"{p}:{tline}: Frame Time: {ttoks[2]} s is too small (its rate is not finite)"
        )
    return n_frames, frame_time, ttoks[2], k


def _check_budget(p: str, joints: list[_Joint], n_frames: int, fline: int) -> None:
    """Refuse ``Frames:`` × channel-less joints the file's bytes do not back.

    Joints with channels are backed by their values (at least two bytes each per
    frame, checked by :func:`_parse_frames`); joints without channels cost memory
    (``(F, J, 4)`` rotations) without any bytes, so ``F`` × their number may not
    exceed the file size plus 2**20.
    """
    idle = sum(1 for j in joints if not j.channels)
    size = os.path.getsize(p)
    if n_frames * idle > size + (1 << 20):
        raise BVHError(
            f"{p}:{fline}: Frames: {n_frames} frames of {idle} joints without CHANNELS make "
            f"{n_frames * idle} joint samples, more than a {size}-byte file can describe"
        )


def _check_positions_finite(
    p: str, root_position: np.ndarray, translations: np.ndarray | None, start: int
) -> None:
    """Position channels that are not finite in metres, or put a joint farther than
    :data:`MAX_DISTANCE_M` from its parent, are an error naming the frame."""
    far = np.abs(root_position).max(axis=1)
    if translations is not None:
        far = np.maximum(far, np.abs(translations).max(axis=(1, 2)))
    bad = ~(far <= MAX_DISTANCE_M)
    if bad.any():
        f = int(np.flatnonzero(bad)[0])
        raise BVHError(
            f"{p}: frame {f}: a position channel is {far[f]:.3g} m (beyond {MAX_DISTANCE_M:g} m: "
            f"a wrong unit?); frames start at line {start + 1}"
        )


def _skeleton(
    joints: list[_Joint], ends: list[tuple[int, np.ndarray]], unit: str | float, p: str
) -> Skeleton:
    """The parsed hierarchy as a :class:`Skeleton` in metres (``unit`` resolved, see module
    docstring); ``attrs`` ``source_unit`` and ``source_scale`` (metres per file unit)."""
    names = [j.name for j in joints]
    parents = np.array([j.parent for j in joints], dtype=np.int64)
    offsets = np.stack([j.offset for j in joints])
    with np.errstate(over="ignore", invalid="ignore"):
        extent = _rest_extent(parents, offsets, ends)
        unit_name, scale = _resolve_unit(unit, extent if math.isfinite(extent) else 1.0, p)
        end_offsets = np.array([e[1] for e in ends]).reshape(-1, 3) * scale
        offsets = offsets * scale
    far = np.abs(offsets).max(axis=1)
    if not (
        math.isfinite(extent)
        and (far <= MAX_DISTANCE_M).all()
        and (np.abs(end_offsets) <= MAX_DISTANCE_M).all()
    ):
        j = int(np.argmax(~(far <= MAX_DISTANCE_M))) if not (far <= MAX_DISTANCE_M).all() else 0
        raise BVHError(
            f"{p}:{joints[j].line}: OFFSET values too large: the rest pose spans {extent:g} "
            f"file units ({extent * scale:g} m; at most {MAX_DISTANCE_M:g} m per OFFSET)"
        )
    return Skeleton(
        names=names,
        parents=parents,
        offsets=offsets,
        channels=[j.channels for j in joints],
        end_parents=np.array([e[0] for e in ends], dtype=np.int64),
        end_offsets=end_offsets,
        attrs={"source_unit": unit_name, "source_scale": scale},
    )


def _parse_frames(lines: list[str], start: int, n_frames: int, n_ch: int, p: str) -> np.ndarray:
    if n_ch == 0:
        return np.zeros((n_frames, 0))
    tokens: list[str] = []
    frame_lines: list[int] = []
    k = start
    while len(frame_lines) < n_frames and k < len(lines):
        toks = lines[k].split()
        if toks:
            if len(toks) != n_ch:
                raise BVHError(
                    f"{p}:{k + 1}: frame {len(frame_lines)} has {len(toks)} values, "
                    f"expected {n_ch} (one per channel)"
                )
            tokens.extend(toks)
            frame_lines.append(k + 1)
        k += 1
    if len(frame_lines) < n_frames:
        raise BVHError(
            f"{p}:{len(lines)}: truncated motion: 'Frames: {n_frames}' but only "
            f"{len(frame_lines)} frame lines"
        )
    extra = sum(1 for ln in lines[k:] if ln.strip())
    if extra:
        warnings.warn(
            f"{p}:{k + 1}: {extra} lines after the {n_frames} frames declared were ignored",
            stacklevel=3,
        )
    try:
        data = np.array(tokens, dtype=np.float64)
    except ValueError:
        for f, ln in enumerate(frame_lines):
            for t in lines[ln - 1].split():
                try:
                    float(t)
                except ValueError:
                    raise BVHError(f"{p}:{ln}: bad number {t!r} in frame {f}") from None
        raise
    data = data.reshape(n_frames, n_ch)
    if not np.isfinite(data).all():
        f = int(np.flatnonzero(~np.isfinite(data).all(1))[0])
        raise BVHError(f"{p}:{frame_lines[f]}: non-finite value in frame {f}")
    return data


def _channels_to_motion(
    skeleton: Skeleton, data: np.ndarray, scale: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    F = data.shape[0]
    J = skeleton.n_joints
    euler = np.zeros((F, J, 3))
    orders: list[str] = []
    trans = np.broadcast_to(skeleton.offsets, (F, J, 3)).copy()
    has_pos = np.zeros(J, dtype=bool)
    col = 0
    for j, chans in enumerate(skeleton.channels):
        rot = "".join(c[0] for c in chans if c.endswith("rotation"))
        order = padded_order(rot)
        orders.append(order)
        for c in chans:
            if c.endswith("position"):
                trans[:, j, "XYZ".index(c[0])] = data[:, col] * scale
                has_pos[j] = True
            else:
                euler[:, j, order.index(c[0])] = data[:, col]
            col += 1
    rotations = np.empty((F, J, 4))
    for order in set(orders):
        idx = [j for j, o in enumerate(orders) if o == order]
        rotations[:, idx] = euler_to_quat(euler[:, idx], order, degrees=True)
    rotations = quat_continuity(rotations, axis=0)
    root_position = trans[:, 0].copy()
    translations = trans if has_pos[1:].any() else None
    return root_position, rotations, translations


# --------------------------------------------------------------------------- writing


def _children_of(parents: np.ndarray) -> dict[int, list[int]]:
    """Children of every joint (``-1``: the root), in joint order."""
    children: dict[int, list[int]] = {}
    for j, p in enumerate(parents):
        children.setdefault(int(p), []).append(j)
    return children


def _dfs_order(parents: np.ndarray) -> list[int]:
    """Joints in the depth-first order of the hierarchy (the order of the frame columns)."""
    children = _children_of(parents)
    order: list[int] = []
    stack = [0]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed(children.get(j, [])))
    return order


def _check_positions(motion: Motion, j: int, chans: list[str], p: Path) -> None:
    """Refuse to drop a joint translation that its position channels cannot hold."""
    sk = motion.skeleton
    if j == 0:
        src = motion.root_position
    elif motion.translations is not None:
        src = np.where(
            np.isfinite(motion.translations[:, j]), motion.translations[:, j], sk.offsets[j]
        )
    else:
        return
    have = {c[0] for c in chans if c.endswith("position")}
    for k, axis in enumerate("XYZ"):
        if axis not in have and src.shape[0]:
            lost = np.abs(src[:, k] - sk.offsets[j, k]).max()
            if lost > 1e-6:
                raise BVHError(
                    f"{p}: joint {sk.names[j]!r} moves along {axis} (up to {lost:.3g} m from "
                    f"its offset) but has no {axis}position channel; add position channels"
                )


def _fmt(v: float, precision: int) -> str:
    s = f"{v:.{precision}f}"
    return "0" if float(s) == 0 else s


def _frame_time_text(motion: Motion) -> str:
    text = motion.attrs.get("frame_time_text")
    if text is not None:
        try:
            ft = float(text)
            if ft > 0 and _snap_rate(ft, str(text)) == motion.rate:
                return str(text)
        except ValueError:
            pass
    return f"{1.0 / motion.rate:.10g}"


def write_bvh(
    motion: Motion,
    path: str | os.PathLike,
    *,
    unit: str | float | None = None,
    precision: int = 6,
) -> Path:
    """Write a motion as a BVH file.

    Parameters
    ----------
    motion : Motion
        ``F`` frames; its skeleton's channels give the layout and rotation orders
        (a joint without channels gets none; a skeleton with no channels at all
        gets BVH's usual 6 root / 3 joint channels in ZXY order).  A static root
        that :func:`~mocapflow.stages.motion.ingest.ingest_bvh` dropped
        (``attrs["dropped_root_joint"]``, the motion's or its skeleton's; Bandai-Namco's
        ``joint_Root``) is written
        back around the root, with its offset, channels and constant values, so the
        file has the source's hierarchy.
    path : str or path-like
    unit : str or float, optional
        Unit written (a :data:`BVH_UNITS` name or metres per unit); default the
        source unit in ``motion.attrs["source_scale"]``, else in
        ``motion.skeleton.attrs["source_scale"]`` (stages that make new motions on
        the source skeleton keep it there), else centimetres.
    precision : int
        Decimal places of every value.

    Returns
    -------
    Path
        The written file.

    Raises
    ------
    BVHError
        A joint's rotation cannot be expressed by its (fewer than 3) rotation
        channels, or a unit is unknown.
    """
    p = Path(path)
    sk = motion.skeleton
    if unit is None:
        scale = float(
            motion.attrs.get("source_scale", sk.attrs.get("source_scale", BVH_UNITS["cm"]))
        )
    else:
        _, scale = _resolve_unit(unit, 1.0, str(p))
    channels = sk.channels
    if not any(channels):
        channels = [
            (["Xposition", "Yposition", "Zposition"] if j == 0 else [])
            + ["Zrotation", "Xrotation", "Yrotation"]
            for j in range(sk.n_joints)
        ]
    F = motion.n_frames
    static = _static_root(motion)
    shift = None if static is None else np.asarray(static["position"], dtype=float)
    data = _frame_columns(motion, channels, scale, p, root_shift=shift)
    lines = _hierarchy_lines(sk, channels, scale, precision, root_shift=shift)
    if static is not None:  # the static root ingest dropped, back around the root
        values = [shift["XYZ".index(c[0])] / scale if c.endswith("position") else 0.0
                  for c in static["channels"]]  # fmt: skip
        data = np.concatenate([np.tile(values, (F, 1)), data], axis=1)
        offset = " ".join(_fmt(x / scale, precision) for x in static["offset"])
        head = [f"ROOT {static['name']}", "{", f"\tOFFSET {offset}"]
        if static["channels"]:
            head.append(f"\tCHANNELS {len(static['channels'])} {' '.join(static['channels'])}")
        lines = [*head, "\tJOINT" + lines[0][len("ROOT"):],
                 *("\t" + line for line in lines[1:]), "}"]  # fmt: skip
    out = ["HIERARCHY", *lines]
    out += ["MOTION", f"Frames: {F}", f"Frame Time: {_frame_time_text(motion)}"]
    with open(p, "w", newline="\n") as f:
        f.write("\n".join(out) + "\n")
        if F and data.shape[1]:
            np.savetxt(f, data, fmt=f"%.{precision}f", delimiter=" ")
        elif F:
            f.write("\n" * F)
    return p


def _static_root(motion: Motion) -> dict | None:
    """The static root joint that :func:`~mocapflow.stages.motion.ingest.ingest_bvh` dropped
    (``motion.attrs["dropped_root_joint"]``, else its skeleton's: name, offset, channels,
    position in metres), when the motion's root is still the joint that replaced it, else None."""
    joint = motion.attrs.get("dropped_root_joint",
                             motion.skeleton.attrs.get("dropped_root_joint"))  # fmt: skip
    if not isinstance(joint, dict) or joint.get("name") in motion.skeleton.names:
        return None
    return joint


def _frame_columns(motion: Motion, channels: list[list[str]], scale: float, p: Path, *,
                   root_shift: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """``(F, C)`` frame values, one column per channel in hierarchy order.

    Positions in file units (metres / ``scale``), angles in degrees (unwrapped
    along frames); raises :class:`BVHError` where the channels cannot hold the
    joint's rotation or translation.  ``root_shift`` (3,): taken off the root's
    positions (a static root put back around it holds it).
    """
    sk = motion.skeleton
    F = motion.n_frames
    columns: list[np.ndarray] = []
    trans = motion.translations
    for j in _dfs_order(sk.parents):
        chans = channels[j]
        rot = "".join(c[0] for c in chans if c.endswith("rotation"))
        padded = padded_order(rot)
        angles = _joint_angles(motion, j, rot, padded, p)
        _check_positions(motion, j, chans, p)
        for c in chans:
            if c.endswith("position"):
                if j == 0:
                    src = motion.root_position if root_shift is None else (
                        motion.root_position - root_shift)  # fmt: skip
                elif trans is not None:
                    src = trans[:, j]
                else:
                    src = np.broadcast_to(sk.offsets[j], (F, 3))
                columns.append(src[:, "XYZ".index(c[0])] / scale)
            else:
                columns.append(angles[:, padded.index(c[0])])
    return np.stack(columns, axis=1) if columns else np.zeros((F, 0))


def _joint_angles(motion: Motion, j: int, rot: str, padded: str, p: Path) -> np.ndarray | None:
    """``(F, 3)`` Euler angles (degrees, ``padded`` order) of joint ``j``, unwrapped.

    ``None`` for a joint without rotation channels (``rot == ""``).  Raises
    :class:`BVHError` when the rotation needs axes the channels ``rot`` lack.
    """
    sk = motion.skeleton
    F = motion.n_frames
    if rot:
        angles = quat_to_euler(motion.rotations[:, j], padded, degrees=True)
        if len(rot) < 3 and F:
            lost = np.abs(angles[:, len(rot) :]).max()
            if lost > 1e-6:
                raise BVHError(
                    f"{p}: rotation of joint {sk.names[j]!r} needs axes its channels "
                    f"{rot!r} lack (up to {lost:.3g} deg); add rotation channels"
                )
        return np.unwrap(angles, period=360.0, axis=0) if F else angles
    if F:
        w = np.abs(motion.rotations[:, j, 0])
        lost = np.degrees(2 * np.arccos(np.clip(w, 0.0, 1.0))).max()
        if lost > 1e-6:
            raise BVHError(
                f"{p}: joint {sk.names[j]!r} rotates (up to {lost:.3g} deg) but has no "
                "rotation channels; add rotation channels"
            )
    return None


def _hierarchy_lines(
    sk: Skeleton, channels: list[list[str]], scale: float, precision: int, *,
    root_shift: np.ndarray | None = None,
) -> list[str]:
    """The ``ROOT`` … ``End Site`` lines (tab-indented, offsets in file units; the root's
    offset less ``root_shift`` (3,), metres)."""
    ends: dict[int, list[np.ndarray]] = {}
    for e, j in enumerate(sk.end_parents):
        ends.setdefault(int(j), []).append(sk.end_offsets[e])
    children = _children_of(sk.parents)
    out: list[str] = []

    def vec(v: np.ndarray) -> str:
        return " ".join(_fmt(x / scale, precision) for x in v)

    stack = [(0, 0, False)]  # (joint, depth, closing): iterative, any depth
    while stack:
        j, depth, closing = stack.pop()
        ind = "\t" * depth
        if closing:
            for off in ends.get(j, []):
                out.extend(
                    [f"{ind}\tEnd Site", f"{ind}\t{{", f"{ind}\t\tOFFSET {vec(off)}", f"{ind}\t}}"]
                )
            out.append(f"{ind}}}")
            continue
        out.append(f"{ind}{'ROOT' if j == 0 else 'JOINT'} {sk.names[j]}")
        out.append(f"{ind}{{")
        off = sk.offsets[j] if j or root_shift is None else sk.offsets[j] - root_shift
        out.append(f"{ind}\tOFFSET {vec(off)}")
        out.append(f"{ind}\tCHANNELS {len(channels[j])} {' '.join(channels[j])}".rstrip())
        stack.append((j, depth, True))
        stack.extend((c, depth + 1, False) for c in reversed(children.get(j, [])))
    return out
