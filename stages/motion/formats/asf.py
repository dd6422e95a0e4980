"""Acclaim ASF (skeleton) and AMC (motion) read, as used by the CMU motion database.

Model (Acclaim / CMU convention, column vectors)
-----------------------------------------------
Every bone has a rest ``direction`` (unit vector, global rest frame), a
``length`` and an ``axis`` (three angles and their order, e.g. ``0 0 20 XYZ``)
that define its local frame ``C = R_Z(az) R_Y(ay) R_X(ax)`` (for order ``XYZ``: the
rotation about the first letter is applied first).  An AMC frame gives the dof
values ``M = ... R_b(b) R_a(a)`` with the rotations applied in the order of the
bone's ``dof`` line (``rx ry rz`` -> ``R_Z R_Y R_X``), and the bone's world
rotation is ``L = L_parent C M C^-1``.  The bone starts where its parent ends
and ends at ``start + length * L direction``.

Mapping to :class:`~mocapflow.stages.motion.datatypes.Skeleton`: joint 0 is the root, then
one joint per bone (depth-first over ``:hierarchy``, children in file order),
placed at the bone's *start*; a joint's offset is its parent bone's
``direction * length`` (zero for the root's children), its local rotation is
``C M C^-1``.  Bones without children get an End Site at their own
``direction * length``.  This is the joint layout of the CMU BVH conversions.

Units: lengths ``x`` in the file are ``x / length_unit`` inches (the CMU files
say ``length 0.45``: 0.056444 m per unit); ``angle deg|rad``.  AMC ``:DEGREES``
/ ``:RADIANS`` headers override the ASF angle unit.
"""

from __future__ import annotations

import math
import os
import re
from typing import Any

import numpy as np

from mocapflow.stages.motion.datatypes import Motion, Skeleton
from mocapflow.stages.motion.formats import MAX_DISTANCE_M
from mocapflow.stages.motion.formats.bvh import MAX_DEPTH
from mocapflow.stages.motion.formats.text import read_text
from mocapflow.stages.motion.rotations import (
    euler_to_quat,
    padded_order,
    quat_conjugate,
    quat_continuity,
    quat_identity,
    quat_multiply,
)

__all__ = ["AMCError", "ASFError", "amc_dofs", "asf_amc_to_dofs", "read_amc", "read_asf"]

_INCH = 0.0254
_ROT_DOFS = ("rx", "ry", "rz")


class ASFError(ValueError):
    """An ASF or AMC file cannot be parsed; the message names the file and line."""


class AMCError(ASFError):
    """An AMC file cannot be parsed or does not fit its skeleton."""


# --------------------------------------------------------------------------- helpers


def _acclaim_quat(angles: np.ndarray, order: str) -> np.ndarray:
    """Quaternion of rotations applied in ``order`` (first letter first).

    Parameters
    ----------
    angles : (..., 3) float ndarray
        Radians, ``angles[..., k]`` about ``order[k]``.
    order : str
        E.g. ``"XYZ"`` meaning ``R_Z @ R_Y @ R_X``.
    """
    angles = np.asarray(angles, dtype=np.float64)
    return euler_to_quat(angles[..., ::-1], order[::-1])


def _read_lines(path: str) -> list[str]:
    return read_text(path).splitlines()


def _floats(tokens: list[str], path: str, line: int, what: str, n: int = 1) -> list[float]:
    """The first ``n`` of ``tokens`` as finite floats (an error naming ``what`` otherwise)."""
    try:
        vals = [float(t) for t in tokens[:n]]
    except ValueError:
        raise ASFError(f"{path}:{line}: bad number in {what}: {' '.join(tokens)!r}") from None
    if len(vals) < n:
        raise ASFError(f"{path}:{line}: {what} needs {n} numbers, got {' '.join(tokens)!r}")
    if not all(math.isfinite(v) for v in vals):
        raise ASFError(f"{path}:{line}: {what} is not finite: {' '.join(tokens[:n])!r}")
    return vals


# --------------------------------------------------------------------------- ASF


def _parse_limits(tokens: list[str], path: str, line: int) -> list[list[float | None]]:
    text = " ".join(tokens).replace("(", " ( ").replace(")", " ) ")
    pairs = re.findall(r"\(\s*(\S+)\s+(\S+)\s*\)", text)
    out: list[list[float | None]] = []
    for lo, hi in pairs:
        vals: list[float | None] = []
        for v in (lo, hi):
            try:
                x = float(v)
            except ValueError:
                raise ASFError(f"{path}:{line}: bad limit {v!r}") from None
            if math.isnan(x):
                raise ASFError(f"{path}:{line}: limits: NaN limit {v!r}")
            vals.append(None if np.isinf(x) else x)
        out.append(vals)
    return out


def read_asf(path: str | os.PathLike) -> Skeleton:
    """Read an Acclaim ASF skeleton.

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    Skeleton
        ``J = 1 + bones`` joints in metres (layout in the module docstring);
        BVH-style channels (root: 3 positions + ``Z Y X`` rotations, bones:
        ``Z Y X`` rotations).  ``attrs["asf"]`` keeps everything needed to
        interpret AMC files: ``units``, ``root`` (``order``, ``axis``,
        ``position``, ``orientation``), ``bones`` (per name: ``id``,
        ``direction``, ``length``, ``axis``, ``axis_order``, ``dof``, ``limits``)
        and the joint ``names`` in ASF spelling.

    Raises
    ------
    ASFError
        Missing sections, unknown bones in ``:hierarchy``, bad numbers; the
        message names the file and line.
    """
    p = os.fspath(path)
    lines = _read_lines(p)
    if not any(ln.strip() for ln in lines):
        raise ASFError(f"{p}:1: empty file")
    asf = _ASFReader(p)
    for i, raw in enumerate(lines, start=1):
        asf.read_line(i, raw)
    asf.finish(len(lines))
    return _build_skeleton(p, asf.units, asf.root, asf.bones, asf.hierarchy)


class _ASFReader:
    """An ASF read line by line: what the sections said so far, and the bone being read."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.units: dict[str, Any] = {"mass": 1.0, "length": 1.0, "angle": "deg"}
        self.root: dict[str, Any] = {
            "order": ["TX", "TY", "TZ", "RX", "RY", "RZ"],
            "axis": "XYZ",
            "position": [0.0, 0.0, 0.0],
            "orientation": [0.0, 0.0, 0.0],
        }
        self.bones: dict[str, dict[str, Any]] = {}
        self.hierarchy: list[tuple[str, list[str], int]] = []
        self.section: str | None = None
        self.bone: dict[str, Any] | None = None
        self.bone_line = 0
        self.last_key: str | None = None
        self.seen: set[str] = set()

    def read_line(self, i: int, raw: str) -> None:
        """Line ``i`` (1-based): a ``:section`` header or an entry of the current section."""
        p = self.path
        line = raw.split("#", 1)[0].strip()
        if not line:
            return
        if line.startswith(":"):
            toks = line.split()
            self.section = toks[0][1:].lower()
            self.seen.add(self.section)
            if self.bone is not None:
                raise ASFError(f"{p}:{i}: bone starting line {self.bone_line} has no 'end'")
            return
        toks = line.split()
        key = toks[0].lower()
        if self.section == "units":
            self._units(i, toks, key)
        elif self.section == "root":
            self._root(i, toks, key)
        elif self.section == "bonedata":
            self._bonedata(i, toks, key)
        elif self.section == "hierarchy":
            if key in ("begin", "end"):
                return
            self.hierarchy.append((toks[0], toks[1:], i))

    def _units(self, i: int, toks: list[str], key: str) -> None:
        p = self.path
        if len(toks) < 2:
            raise ASFError(f"{p}:{i}: units entry without a value")
        if key in ("mass", "length"):
            self.units[key] = _floats(toks[1:2], p, i, f"units {key}")[0]
            if key == "length" and not self.units[key] > 0:
                raise ASFError(f"{p}:{i}: units length must be > 0, got {toks[1]!r}")
        elif key == "angle":
            if toks[1].lower() not in ("deg", "rad"):
                raise ASFError(f"{p}:{i}: unknown angle unit {toks[1]!r} (deg or rad)")
            self.units["angle"] = toks[1].lower()

    def _root(self, i: int, toks: list[str], key: str) -> None:
        p, root = self.path, self.root
        if key == "order":
            root["order"] = [t.upper() for t in toks[1:]]
            bad = [t for t in root["order"] if t not in ("TX", "TY", "TZ", "RX", "RY", "RZ")]
            if bad:
                raise ASFError(f"{p}:{i}: unknown root order entries {bad}")
            if len(set(root["order"])) != len(root["order"]):
                raise ASFError(f"{p}:{i}: root order repeats an entry: {' '.join(root['order'])}")
        elif key == "axis":
            if len(toks) < 2:
                raise ASFError(f"{p}:{i}: root axis needs an order such as XYZ")
            root["axis"] = toks[1].upper()
            _check_axis_order(root["axis"], p, i)
        elif key in ("position", "orientation"):
            root[key] = _floats(toks[1:4], p, i, f"root {key}", 3)

    def _bonedata(self, i: int, toks: list[str], key: str) -> None:
        p, bone = self.path, self.bone
        if key == "begin":
            self.bone = {"dof": [], "limits": [], "axis": [0.0, 0.0, 0.0], "axis_order": "XYZ"}
            self.bone_line = i
        elif key == "end":
            if bone is None:
                raise ASFError(f"{p}:{i}: 'end' without 'begin'")
            if "name" not in bone or "direction" not in bone or "length" not in bone:
                raise ASFError(f"{p}:{self.bone_line}: bone needs name, direction and length")
            if bone["name"] in self.bones or bone["name"] == "root":
                raise ASFError(f"{p}:{self.bone_line}: bone name {bone['name']!r} is used twice")
            self.bones[bone["name"]] = bone
            self.bone = None
        elif bone is None:
            raise ASFError(f"{p}:{i}: {toks[0]!r} outside a bone's begin/end")
        elif key == "id":
            v = _floats(toks[1:2], p, i, "id")[0]
            if v != int(v):
                raise ASFError(f"{p}:{i}: id must be an integer, got {toks[1]!r}")
            bone["id"] = int(v)
        elif key == "name":
            if len(toks) < 2:
                raise ASFError(f"{p}:{i}: name without a value")
            bone["name"] = toks[1]
        elif key == "direction":
            bone["direction"] = _floats(toks[1:4], p, i, "direction", 3)
        elif key == "length":
            bone["length"] = _floats(toks[1:2], p, i, "length")[0]
            if bone["length"] < 0:
                raise ASFError(f"{p}:{i}: length must not be negative, got {toks[1]!r}")
        elif key == "axis":
            if len(toks) < 5:
                raise ASFError(f"{p}:{i}: axis needs 3 angles and an order")
            bone["axis"] = _floats(toks[1:4], p, i, "axis", 3)
            bone["axis_order"] = toks[4].upper()
            _check_axis_order(bone["axis_order"], p, i)
        elif key == "dof":
            dof = [t.lower() for t in toks[1:]]
            bad = [d for d in dof if d not in _ROT_DOFS]
            if bad:
                raise ASFError(
                    f"{p}:{i}: unsupported dof {bad} (only rotational rx ry rz are read)"
                )
            if len(set(dof)) != len(dof):
                raise ASFError(f"{p}:{i}: dof repeats an axis: {' '.join(dof)}")
            bone["dof"] = dof
        elif key == "limits":
            bone["limits"] = _parse_limits(toks[1:], p, i)
            self.last_key = "limits"
            return
        elif key.startswith("(") and self.last_key == "limits":
            bone["limits"] += _parse_limits(toks, p, i)
            return
        # bodymass, cofmass, ... are not needed
        self.last_key = key

    def finish(self, n_lines: int) -> None:
        """Check that the file did not end inside a bone and had the needed sections."""
        p = self.path
        if self.bone is not None:
            raise ASFError(
                f"{p}:{n_lines}: truncated file: bone starting line {self.bone_line} has no 'end'"
            )
        for need in ("bonedata", "hierarchy"):
            if need not in self.seen:
                raise ASFError(f"{p}:{n_lines}: no :{need} section")


def _check_axis_order(order: str, path: str, line: int) -> None:
    if sorted(order) != ["X", "Y", "Z"]:
        raise ASFError(f"{path}:{line}: unknown rotation order {order!r}")


def _bone_offsets(p: str, names: list[str], parents: list[int], bones: dict, scale: float):
    """Joint offsets ``(J, 3)`` (root's left zero) and End Sites of the leaf bones, metres.

    A bone farther than :data:`MAX_DISTANCE_M` from its parent is an error naming it.
    """
    offsets = np.zeros((len(names), 3))
    ends_p, ends_o = [], []
    has_child = set(parents)
    for j, name in enumerate(names):
        if j == 0:
            continue
        for bone, k in ((names[parents[j]], None), (name, j)):
            if bone == "root" or (k is not None and j in has_child):
                continue
            b = bones[bone]
            with np.errstate(over="ignore", invalid="ignore"):
                off = np.asarray(b["direction"]) * b["length"] * scale
            if not (np.abs(off) <= MAX_DISTANCE_M).all():
                raise ASFError(
                    f"{p}: :bonedata: bone {bone!r} (length {b['length']:g}) ends "
                    f"{np.abs(off).max():.3g} m from its start (beyond {MAX_DISTANCE_M:g} m: a "
                    "wrong :units length?)"
                )
            if k is None:
                offsets[j] = off
            else:
                ends_p.append(j)
                ends_o.append(off)
    return offsets, ends_p, ends_o


def _build_skeleton(p, units, root, bones, hierarchy) -> Skeleton:
    children: dict[str, list[str]] = {}
    for parent, kids, line in hierarchy:
        for name in [parent, *kids]:
            if name != "root" and name not in bones:
                raise ASFError(f"{p}:{line}: :hierarchy names unknown bone {name!r}")
        children.setdefault(parent, []).extend(kids)
    names = ["root"]
    parents = [-1]
    depth = [0]
    placed = {"root"}
    stack = [(k, 0) for k in reversed(children.get("root", []))]
    while stack:
        name, par = stack.pop()
        if name in placed:
            raise ASFError(f"{p}: :hierarchy: bone {name!r} appears twice")
        placed.add(name)
        if depth[par] >= MAX_DEPTH:
            raise ASFError(f"{p}: :hierarchy: bone {name!r} nests deeper than {MAX_DEPTH} bones")
        names.append(name)
        parents.append(par)
        depth.append(depth[par] + 1)
        j = len(names) - 1
        stack.extend((k, j) for k in reversed(children.get(name, [])))
    missing = sorted(set(bones) - placed)
    if missing:
        raise ASFError(f"{p}: bones not connected to the root in :hierarchy: {missing}")
    scale = _INCH / float(units["length"])
    if not math.isfinite(scale):
        raise ASFError(f"{p}: :units length {units['length']!r} is too small (scale not finite)")
    offsets, ends_p, ends_o = _bone_offsets(p, names, parents, bones, scale)
    offsets[0] = np.asarray(root["position"]) * scale
    if not (np.abs(offsets[0]) <= MAX_DISTANCE_M).all():
        raise ASFError(
            f"{p}: :root position is {offsets[0].tolist()} m (beyond "
            f"{MAX_DISTANCE_M:g} m: a wrong :units length?)"
        )
    unit_name = "cmu" if abs(float(units["length"]) - 0.45) < 1e-12 else f"in/{units['length']}"
    channels = [["Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation"]]
    channels += [["Zrotation", "Yrotation", "Xrotation"] for _ in names[1:]]
    return Skeleton(
        names=names,
        parents=np.array(parents),
        offsets=offsets,
        channels=channels,
        end_parents=np.array(ends_p, dtype=np.int64),
        end_offsets=np.array(ends_o).reshape(-1, 3),
        attrs={
            "source_file": os.path.basename(p),  # no path in outputs
            "source_format": "asf",
            "source_unit": unit_name,
            "source_scale": scale,
            "asf": {"units": units, "root": root, "bones": bones, "names": names},
        },
    )


# --------------------------------------------------------------------------- AMC


def _asf_info(skeleton: Skeleton, path: str) -> dict[str, Any]:
    info = skeleton.attrs.get("asf")
    if not info:
        raise AMCError(f"{path}: the skeleton was not read from an ASF file (no attrs['asf'])")
    return info


def _dof_layout(info: dict[str, Any]) -> dict[str, list[str]]:
    layout = {"root": [o.lower() for o in info["root"]["order"]]}
    for name in info["names"][1:]:
        layout[name] = list(info["bones"][name]["dof"])
    return layout


def _parse_amc(path: str, info: dict[str, Any]):
    """Frames of raw dof values: ``(values per bone, frame numbers, angle unit)``."""
    lines = _read_lines(path)
    if not any(ln.strip() for ln in lines):
        raise AMCError(f"{path}:1: empty file")
    layout = _dof_layout(info)
    angle = info["units"]["angle"]
    order: list[str] = []  # bone order of the first frame
    frames: list[dict[str, list[str]]] = []
    frame_lines: list[int] = []
    numbers: list[int] = []
    cur: dict[str, list[str]] | None = None
    for i, raw in enumerate(lines, start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        if s.startswith(":"):
            key = s[1:].split()[0].upper() if s[1:].split() else ""
            if key == "DEGREES":
                angle = "deg"
            elif key == "RADIANS":
                angle = "rad"
            continue
        toks = s.split()
        if len(toks) == 1 and toks[0].lstrip("-").isdigit():
            if cur is not None:
                _check_frame(cur, layout, path, frame_lines[-1])
            if abs(int(toks[0])) >= 1 << 31:
                raise AMCError(f"{path}:{i}: frame number {toks[0]} is too large")
            cur = {}
            frames.append(cur)
            frame_lines.append(i)
            numbers.append(int(toks[0]))
            continue
        if cur is None:
            raise AMCError(f"{path}:{i}: {toks[0]!r} before the first frame number")
        name = toks[0]
        if name not in layout:
            raise AMCError(f"{path}:{i}: unknown bone {name!r} (not in the ASF skeleton)")
        if len(toks) - 1 != len(layout[name]):
            raise AMCError(
                f"{path}:{i}: bone {name!r} has {len(toks) - 1} values, expected "
                f"{len(layout[name])} ({' '.join(layout[name]) or 'no dof'})"
            )
        if name in cur:
            raise AMCError(f"{path}:{i}: bone {name!r} given twice in frame {numbers[-1]}")
        cur[name] = toks[1:]
        cur[f"@{name}"] = [str(i)]
        if len(frames) == 1:
            order.append(name)
    if cur is not None:
        _check_frame(cur, layout, path, frame_lines[-1])
    if not frames:
        raise AMCError(f"{path}:{len(lines)}: no frames")
    return frames, numbers, angle, layout, order


def _check_frame(cur: dict, layout: dict, path: str, line: int) -> None:
    missing = [b for b, d in layout.items() if d and b not in cur]
    if missing:
        raise AMCError(
            f"{path}:{line}: frame starting here lacks bones {missing} (truncated file?)"
        )


def _dof_matrix(path: str, info: dict[str, Any]):
    frames, numbers, angle, layout, order = _parse_amc(path, info)
    cols: list[str] = []
    bones_in_order = [b for b in order if layout[b]] + [
        b for b in layout if layout[b] and b not in order
    ]
    for b in bones_in_order:
        cols += [f"{b}.{d}" for d in layout[b]]
    tokens: list[str] = []
    for fr in frames:
        for b in bones_in_order:
            tokens.extend(fr[b])
    try:
        data = np.array(tokens, dtype=np.float64).reshape(len(frames), len(cols))
    except ValueError:
        data = None
    if data is None or not np.isfinite(data).all():
        for fr in frames:
            for b in bones_in_order:
                for t in fr[b]:
                    try:
                        ok = math.isfinite(float(t))
                    except ValueError:
                        ok = False
                    if not ok:
                        line = fr[f"@{b}"][0]
                        raise AMCError(f"{path}:{line}: bad number {t!r} for bone {b!r}")
    if data is None:  # pragma: no cover - every frame was checked to hold every bone
        raise AMCError(
            f"{path}: the frames hold {len(tokens)} values, not {len(frames)} x {len(cols)}"
        )
    return data, cols, numbers, angle


def _check_budget(path: str, info: dict[str, Any], n_frames: int) -> None:
    """Refuse frames x dof-less bones the AMC's bytes do not back (memory of ``(F, J, 4)``).

    Bones with dofs have a line per frame; bones without cost memory without bytes,
    so ``F`` x their number may not exceed the AMC size plus 2**20.
    """
    idle = sum(1 for n in info["names"][1:] if not info["bones"][n]["dof"])
    size = os.path.getsize(path)
    if n_frames * idle > size + (1 << 20):
        raise AMCError(
            f"{path}: {n_frames} frames of {idle} bones without dof make {n_frames * idle} "
            f"bone samples, more than a {size}-byte file can describe"
        )


def amc_dofs(path: str | os.PathLike, skeleton: Skeleton) -> tuple[np.ndarray, list[str]]:
    """The raw degrees of freedom of an AMC file as a matrix.

    Parameters
    ----------
    path : str or path-like
    skeleton : Skeleton
        From :func:`read_asf` (its ``attrs["asf"]`` gives each bone's dofs).

    Returns
    -------
    dofs : (F, D) float ndarray
        One row per frame, values as in the file (root translation in file
        units, angles in the file's angle unit); ``D = 62`` for CMU skeletons.
    names : list of str
        ``D`` column names ``"bone.dof"`` (``"root.tx"``, ``"lfemur.rx"``, ...), bones
        in the order of the file's first frame, dofs in ASF ``dof`` order.
    """
    p = os.fspath(path)
    data, cols, _, _ = _dof_matrix(p, _asf_info(skeleton, p))
    return data, cols


def asf_amc_to_dofs(
    asf_path: str | os.PathLike, amc_path: str | os.PathLike
) -> tuple[np.ndarray, list[str]]:
    """:func:`amc_dofs` of an AMC file with the skeleton of an ASF file.

    Parameters
    ----------
    asf_path, amc_path : str or path-like

    Returns
    -------
    dofs : (F, D) float ndarray
    names : list of str
    """
    return amc_dofs(amc_path, read_asf(asf_path))


def read_amc(path: str | os.PathLike, skeleton: Skeleton, *, rate: float = 120.0) -> Motion:
    """Read an AMC motion for an ASF skeleton.

    Parameters
    ----------
    path : str or path-like
    skeleton : Skeleton
        From :func:`read_asf`.
    rate : float
        Frames per second (AMC files do not store it; CMU captures are 120 Hz).

    Returns
    -------
    Motion
        ``F`` frames in metres; local rotations ``C M C^-1`` (module docstring);
        ``attrs``: ``source_file``, ``source_format``, ``source_unit``,
        ``source_scale``, ``first_frame`` (the first AMC frame number).

    Raises
    ------
    AMCError
        Unknown bones, wrong value counts, bad numbers, truncated frames; the
        message names the file and line.
    """
    p = os.fspath(path)
    info = _asf_info(skeleton, p)
    data, cols, numbers, angle = _dof_matrix(p, info)
    F = data.shape[0]
    _check_budget(p, info, F)
    to_rad = np.pi / 180.0 if angle == "deg" else 1.0
    asf_to_rad = np.pi / 180.0 if info["units"]["angle"] == "deg" else 1.0
    scale = float(skeleton.attrs.get("source_scale", _INCH / float(info["units"]["length"])))
    col = {c: k for k, c in enumerate(cols)}
    names = info["names"]
    J = len(names)
    rotations = np.empty((F, J, 4))
    root_position = np.zeros((F, 3))
    for j, name in enumerate(names):
        if j == 0:
            order = [o.lower() for o in info["root"]["order"]]
            axis_angles = np.asarray(info["root"]["orientation"]) * asf_to_rad
            axis_order = info["root"]["axis"]
            for k, a in enumerate("xyz"):
                if f"t{a}" in order:
                    root_position[:, k] = data[:, col[f"root.t{a}"]] * scale
            dofs = [d for d in order if d.startswith("r")]
        else:
            b = info["bones"][name]
            axis_angles = np.asarray(b["axis"]) * asf_to_rad
            axis_order = b["axis_order"]
            dofs = b["dof"]
        C = _acclaim_quat(axis_angles, axis_order)
        if dofs:
            vals = np.stack([data[:, col[f"{name}.{d}"]] for d in dofs], axis=1) * to_rad
            rot_order = padded_order("".join(d[1].upper() for d in dofs))
            vals = np.concatenate([vals, np.zeros((F, 3 - len(dofs)))], axis=1)
            M = _acclaim_quat(vals, rot_order)
        else:
            M = quat_identity((F,))
        rotations[:, j] = quat_multiply(quat_multiply(C, M), quat_conjugate(C))
    rotations = quat_continuity(rotations, axis=0)
    return Motion(
        skeleton=skeleton,
        root_position=root_position,
        rotations=rotations,
        rate=rate,
        attrs={
            "source_file": os.path.basename(p),  # no path in outputs
            "source_format": "amc",
            "source_unit": skeleton.attrs.get("source_unit", "cmu"),
            "source_scale": scale,
            "first_frame": int(numbers[0]),
        },
    )
