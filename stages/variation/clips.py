"""Input clips of the variation graph (Lau, Bar-Joseph & Kuffner 2009, §4 and §9).

The method learns from a few *similar* examples of one motion type, each a
trajectory of degrees of freedom (DOFs).  This module turns motions and pen
strokes into such DOF trajectories and back, cuts a long cyclic take into
cycles, and selects similar inputs.

DOFs of a motion
    Every joint with rotation channels contributes its Euler angles (radians) in
    the joint's BVH channel order, made continuous over time (2π unwrapping and
    the choice between the two equivalent Euler triples).  With
    ``root="heading"`` (default) the root is made independent of where the
    subject walks: the heading angle ψ about the up axis enters as its rate
    (``heading_rate``), the rest of the root orientation as a 2-component
    swing rotation vector, the horizontal root translation as a per-frame
    velocity expressed in the heading frame (``velocity_*``) and the height as
    is.  ``root="absolute"`` keeps root position and Euler angles as they are.
    DOFs constant over every clip are dropped from the trajectories and
    restored on the way back.
DOFs of pen strokes
    ``x`` and ``y`` of the pen (pen-up breaks are joined in drawing order).

Cutting a take into cycles
    ``feet``: gait cycles start at the heel strikes of the left foot (contact
    onsets: foot height in the lowest quarter of its range *and* horizontal
    speed below 30 % of its 90th percentile).  ``period``: the period of the
    summed autocorrelation of the standardised DOFs, with cuts placed at the
    frames most like a reference pose one period apart.  Cycles of outlying
    duration or shape (start / stop of a take) are dropped.

Similar-input selection (§9)
    :func:`likelihood_threshold` takes the 10th percentile of the held-out
    log-likelihoods of train-on-6 / test-on-2 splits of a trusted set;
    :func:`select_similar` removes the least likely clip while it is below the
    threshold.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context, stage
from mocapflow.pipeline.codecs import Encoded, codec, decode, encode, exporter
from mocapflow.stages.motion.contacts import foot_joint, true_runs
from mocapflow.stages.motion.datatypes import Motion, Skeleton, Strokes
from mocapflow.stages.motion.kinematics import (
    euler_continuity,
    euler_to_quat,
    forward_kinematics,
    quat_conjugate,
    quat_continuity,
    quat_from_rotvec,
    quat_multiply,
    quat_rotate,
    quat_to_euler,
    quat_to_rotvec,
)

__all__ = [
    "ClipError",
    "Clips",
    "autocorrelation_period",
    "clips",
    "clips_from_motions",
    "clips_from_strokes",
    "clips_to_motions",
    "clips_to_strokes",
    "cut_cycles",
    "dofs_to_motion",
    "foot_joint",
    "heel_strikes",
    "likelihood_threshold",
    "make_clips",
    "merge_clips",
    "motion_to_dofs",
    "period_cuts",
    "select_similar",
]

_AXES = "XYZ"


class ClipError(ValueError):
    """Input clips that cannot be used (empty, mismatched, too short)."""


# --------------------------------------------------------------------------- the Clips type


@dataclass(eq=False)
class Clips:
    """Similar examples of one motion type as DOF trajectories.

    Parameters
    ----------
    trajectories : list of (T_c, D) float ndarray
        One trajectory per clip, *varying* DOFs only (columns ``varying``).
    dof_names : list of str
        ``D_all`` names of all DOFs, e.g. ``"LeftLeg:Xrotation"``.
    varying : (D_all,) bool ndarray
        Which DOFs vary (are columns of the trajectories).
    constant_values : (D_all,) float ndarray
        Value of each constant DOF (ignored where ``varying``).
    rate : float
        Frames per second.
    kind : {"motion", "strokes", "dofs"}
        What the DOFs describe.
    cyclic : bool
        The clips are cycles of a periodic motion (the transition network wraps
        the end of each clip onto its start; streams may be arbitrarily long).
    origins : (C, 4) float ndarray
        Per clip the root heading ψ₀ (radians) and position p₀ (metres) of its
        first frame (``root="heading"``); zeros otherwise.
    skeleton : Skeleton, optional
        Skeleton of the motions (``kind == "motion"``).
    names : list of str
        ``C`` clip labels (source and frame range).
    attrs : dict
        ``root`` (``"heading"`` / ``"absolute"``), ``up`` axis, ``translations``
        (constant non-root joint translations), cut report, sources.
    """

    trajectories: list[np.ndarray]
    dof_names: list[str]
    varying: np.ndarray
    constant_values: np.ndarray
    rate: float
    kind: str = "dofs"
    cyclic: bool = False
    origins: np.ndarray | None = None
    skeleton: Skeleton | None = None
    names: list[str] = field(default_factory=list)
    attrs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.dof_names = [str(n) for n in self.dof_names]
        self.varying = np.asarray(self.varying, dtype=bool).reshape(-1)
        self.constant_values = np.asarray(self.constant_values, dtype=np.float64).reshape(-1)
        D_all = len(self.dof_names)
        if self.varying.shape != (D_all,) or self.constant_values.shape != (D_all,):
            raise ClipError("clips: dof_names, varying and constant_values disagree in length")
        D = int(self.varying.sum())
        trajs = []
        for c, t in enumerate(self.trajectories):
            a = np.asarray(t, dtype=np.float64)
            if a.ndim == 1 and D == 1:
                a = a[:, None]
            if a.ndim != 2 or a.shape[1] != D:
                raise ClipError(f"clips: trajectory {c} has shape {a.shape}, expected (T, {D})")
            trajs.append(a)
        self.trajectories = trajs
        C = len(trajs)
        if self.origins is None:
            self.origins = np.zeros((C, 4))
        self.origins = np.asarray(self.origins, dtype=np.float64).reshape(C, 4)
        if not self.names:
            self.names = [f"clip{c}" for c in range(C)]
        self.names = [str(n) for n in self.names]
        if len(self.names) != C:
            raise ClipError(f"clips: {len(self.names)} names for {C} trajectories")
        if self.kind not in ("motion", "strokes", "dofs"):
            raise ClipError(f"clips: unknown kind {self.kind!r}")
        if self.kind == "motion" and self.skeleton is None:
            raise ClipError("clips: kind 'motion' needs a skeleton")
        self.rate = float(self.rate)
        self.cyclic = bool(self.cyclic)

    @property
    def n_clips(self) -> int:
        """Number of clips ``C``."""
        return len(self.trajectories)

    @property
    def n_dofs(self) -> int:
        """Number of varying DOFs ``D``."""
        return int(self.varying.sum())

    @property
    def labels(self) -> list[str]:
        """Names of the ``D`` varying DOFs (trajectory columns)."""
        return [n for n, v in zip(self.dof_names, self.varying) if v]

    @property
    def lengths(self) -> np.ndarray:
        """``(C,)`` int frame counts."""
        return np.array([len(t) for t in self.trajectories], dtype=np.int64)

    def full(self, c: int) -> np.ndarray:
        """Trajectory ``c`` with the constant DOFs restored, ``(T_c, D_all)``."""
        t = self.trajectories[c]
        out = np.broadcast_to(self.constant_values, (len(t), len(self.dof_names))).copy()
        out[:, self.varying] = t
        return out

    def replace(self, **changes: Any) -> Clips:
        """A copy with some fields replaced (``origins``/``names`` reset with new trajectories)."""
        kw = dict(
            trajectories=self.trajectories,
            dof_names=self.dof_names,
            varying=self.varying,
            constant_values=self.constant_values,
            rate=self.rate,
            kind=self.kind,
            cyclic=self.cyclic,
            origins=self.origins,
            skeleton=self.skeleton,
            names=self.names,
            attrs=dict(self.attrs),
        )
        if "trajectories" in changes and len(changes["trajectories"]) != self.n_clips:
            kw["origins"] = None
            kw["names"] = []
        kw.update(changes)
        return Clips(**kw)


def _encode_clips(c: Clips) -> Encoded:
    data = (
        np.concatenate(c.trajectories, axis=0) if c.trajectories else np.zeros((0, c.n_dofs))
    )
    arrays: dict[str, tuple[np.ndarray, tuple[str, ...]]] = {
        "data": (data, ("frame", "dof")),
        "lengths": (c.lengths, ("clip",)),
        "varying": (c.varying, ("dof_all",)),
        "constant_values": (c.constant_values, ("dof_all",)),
        "origins": (c.origins, ("clip", "origin")),
    }
    sk_attrs = None
    if c.skeleton is not None:
        e = encode(c.skeleton)
        for name, (arr, dims) in e.arrays.items():
            arrays[f"skeleton_{name}"] = (arr, dims)
        sk_attrs = e.attrs
    return Encoded(
        "clips",
        arrays,
        {
            "dof_names": c.dof_names,
            "rate": c.rate,
            "kind": c.kind,
            "cyclic": c.cyclic,
            "names": c.names,
            "skeleton": sk_attrs,
            "attrs": c.attrs,
        },
    )


def _decode_clips(e: Encoded) -> Clips:
    a = e.attrs
    data = e.arrays["data"][0]
    lengths = np.asarray(e.arrays["lengths"][0], dtype=np.int64)
    trajs = np.split(data, np.cumsum(lengths)[:-1]) if len(lengths) else []
    skeleton = None
    if a.get("skeleton") is not None:
        arrs = {
            k[len("skeleton_") :]: v for k, v in e.arrays.items() if k.startswith("skeleton_")
        }
        skeleton = decode(Encoded("skeleton", arrs, a["skeleton"]))
    return Clips(
        trajectories=list(trajs),
        dof_names=a["dof_names"],
        varying=e.arrays["varying"][0],
        constant_values=e.arrays["constant_values"][0],
        rate=a["rate"],
        kind=a["kind"],
        cyclic=a["cyclic"],
        origins=e.arrays["origins"][0],
        skeleton=skeleton,
        names=a["names"],
        attrs=a.get("attrs", {}),
    )


codec("clips", encode=_encode_clips, decode=_decode_clips)(Clips)


def make_clips(
    full_trajectories: list[np.ndarray],
    dof_names: list[str],
    *,
    rate: float,
    kind: str = "dofs",
    cyclic: bool = False,
    origins: np.ndarray | None = None,
    skeleton: Skeleton | None = None,
    names: list[str] | None = None,
    attrs: dict | None = None,
    constant_tol: float = 1e-8,
) -> Clips:
    """Build :class:`Clips` from full DOF trajectories, dropping constant DOFs.

    Parameters
    ----------
    full_trajectories : list of (T_c, D_all) float ndarray
    dof_names : list of str
        ``D_all`` names.
    rate : float
    kind, cyclic, origins, skeleton, names, attrs
        See :class:`Clips`.
    constant_tol : float
        A DOF whose range over every frame of every clip is at most this is
        constant.

    Returns
    -------
    Clips
        ``attrs["constant_dofs"]`` lists the dropped names.

    Raises
    ------
    ClipError
        No clip, an empty clip, NaN values, or DOF counts that disagree.
    """
    if not full_trajectories:
        raise ClipError("no input clip")
    D_all = len(dof_names)
    trajs = []
    for c, t in enumerate(full_trajectories):
        a = np.asarray(t, dtype=np.float64)
        label = names[c] if names else f"clip {c}"
        if a.ndim != 2 or a.shape[1] != D_all:
            raise ClipError(f"{label}: expected (T, {D_all}) DOFs, got {a.shape}")
        if a.shape[0] == 0:
            raise ClipError(f"{label}: empty clip")
        if not np.isfinite(a).all():
            bad = [dof_names[d] for d in np.flatnonzero(~np.isfinite(a).all(axis=0))[:5]]
            raise ClipError(f"{label}: non-finite values in DOFs {bad}")
        trajs.append(a)
    stacked = np.concatenate(trajs, axis=0)
    rng = stacked.max(axis=0) - stacked.min(axis=0)
    varying = rng > constant_tol
    const_vals = np.where(varying, 0.0, stacked[0])
    attrs = dict(attrs or {})
    attrs["constant_dofs"] = [n for n, v in zip(dof_names, varying) if not v]
    return Clips(
        trajectories=[t[:, varying] for t in trajs],
        dof_names=list(dof_names),
        varying=varying,
        constant_values=const_vals,
        rate=rate,
        kind=kind,
        cyclic=cyclic,
        origins=origins,
        skeleton=skeleton,
        names=list(names) if names else [],
        attrs=attrs,
    )


def merge_clips(parts: list[Clips]) -> Clips:
    """Concatenate the clips of several :class:`Clips` of the same layout.

    Parameters
    ----------
    parts : list of Clips
        Same ``kind``, ``dof_names`` and ``rate``.

    Returns
    -------
    Clips
        Constant DOFs recomputed over the union.
    """
    parts = [p for p in parts if p is not None]
    if not parts:
        raise ClipError("no input clip")
    if len(parts) == 1:
        return parts[0]
    first = parts[0]
    for p in parts[1:]:
        if p.kind != first.kind or p.dof_names != first.dof_names:
            raise ClipError(
                f"cannot merge clips {p.names[:1]} with {first.names[:1]}: different DOF layouts"
            )
        if not math.isclose(p.rate, first.rate, rel_tol=1e-9):
            raise ClipError(
                f"cannot merge clips at {p.rate} and {first.rate} frames/s; resample on ingest"
            )
    fulls = [p.full(c) for p in parts for c in range(p.n_clips)]
    return make_clips(
        fulls,
        first.dof_names,
        rate=first.rate,
        kind=first.kind,
        cyclic=all(p.cyclic for p in parts),
        origins=np.concatenate([p.origins for p in parts]),
        skeleton=first.skeleton,
        names=[n for p in parts for n in p.names],
        attrs=first.attrs,
    )


def flatten_clips(value: Any) -> Clips:
    """A :class:`Clips` from a ``Clips`` or a (nested) list of them (gather inputs)."""
    if isinstance(value, Clips):
        return value
    if isinstance(value, (list, tuple)):
        items = [flatten_clips(v) for v in value]
        return merge_clips(items)
    raise ClipError(f"expected clips, got {type(value).__name__}")


# --------------------------------------------------------------------------- Euler helpers


def _padded_order(rot: str) -> str:
    return rot + "".join(a for a in _AXES if a not in rot)


# --------------------------------------------------------------------------- motion <-> DOFs


def _twist(psi: np.ndarray, up: int) -> np.ndarray:
    q = np.zeros(np.shape(psi) + (4,))
    q[..., 0] = np.cos(0.5 * psi)
    q[..., 1 + up] = np.sin(0.5 * psi)
    return q


def motion_to_dofs(
    motion: Motion, *, root: Literal["heading", "absolute"] = "heading", up: str = "y"
) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray]:
    """Joint-angle DOF trajectory of a motion.

    Parameters
    ----------
    motion : Motion
        ``F`` frames, ``J`` joints.
    root : {"heading", "absolute"}
        Root representation (see module docstring).
    up : {"y", "z"}
        Up axis of the skeleton's world.

    Returns
    -------
    dofs : (F, D_all) float ndarray
        Radians for angles, metres (per frame for velocities).
    names : list of str
        ``D_all`` DOF names ``"<joint>:<channel>"``.
    heading : (F,) float ndarray
        Unwrapped root heading ψ (zeros for ``root="absolute"``).
    position : (F, 3) float ndarray
        Root position.
    """
    u = _AXES.lower().index(up.lower())
    hz = [a for a in range(3) if a != u]
    sk = motion.skeleton
    F = motion.n_frames
    rot = quat_continuity(motion.rotations, axis=0)
    cols: list[np.ndarray] = []
    names: list[str] = []
    psi = np.zeros(F)
    pos = motion.root_position
    rname = sk.names[0]
    if root == "heading":
        q = rot[:, 0]
        psi = np.unwrap(2.0 * np.arctan2(q[:, 1 + u], q[:, 0]))
        swing = quat_multiply(quat_conjugate(_twist(psi, u)), q)
        rv = quat_to_rotvec(swing)
        dpsi = np.zeros(F)
        dp = np.zeros((F, 3))
        if F > 1:
            dpsi[1:] = np.diff(psi)
            dpsi[0] = dpsi[1]
            dp[1:] = np.diff(pos, axis=0)
            dp[0] = dp[1]
        local = quat_rotate(quat_conjugate(_twist(psi, u)), dp)
        cols += [dpsi[:, None], rv[:, hz], local[:, hz], pos[:, u : u + 1]]
        names += [f"{rname}:heading_rate"]
        names += [f"{rname}:swing_{_AXES[a]}" for a in hz]
        names += [f"{rname}:velocity_{_AXES[a]}" for a in hz]
        names += [f"{rname}:{_AXES[u]}position"]
        joints = range(1, sk.n_joints)
    elif root == "absolute":
        cols.append(pos)
        names += [f"{rname}:{a}position" for a in _AXES]
        joints = range(sk.n_joints)
    else:
        raise ClipError(f"unknown root representation {root!r}")
    orders = [(j, sk.rotation_order(j)) for j in joints]
    orders = [(j, o) for j, o in orders if o]
    if orders:
        js = [j for j, _ in orders]
        eul = np.stack(
            [quat_to_euler(rot[:, j], _padded_order(o)) for j, o in orders], axis=1
        )  # (F, J', 3)
        proper = np.array([_padded_order(o)[0] == _padded_order(o)[2] for _, o in orders])
        eul = euler_continuity(eul, proper)
        for k, (_, o) in enumerate(orders):
            cols.append(eul[:, k, : len(o)])
            names += [f"{sk.names[js[k]]}:{a}rotation" for a in o]
    dofs = np.concatenate(cols, axis=1) if cols else np.zeros((F, 0))
    return dofs, names, psi, np.array(pos, dtype=np.float64)


def dofs_to_motion(
    dofs: np.ndarray,
    names: list[str],
    skeleton: Skeleton,
    *,
    rate: float,
    origin: np.ndarray | None = None,
    root: str = "heading",
    up: str = "y",
    translations: np.ndarray | None = None,
    attrs: dict | None = None,
) -> Motion:
    """Inverse of :func:`motion_to_dofs`.

    Parameters
    ----------
    dofs : (F, D_all) float ndarray
    names : list of str
        ``D_all`` DOF names as produced by :func:`motion_to_dofs`.
    skeleton : Skeleton
    rate : float
    origin : (4,) float ndarray, optional
        Heading ψ₀ and root position p₀ of frame 0 (``root="heading"``).
    root, up : str
        As in :func:`motion_to_dofs`.
    translations : (J, 3) float ndarray, optional
        Constant local translations of joints with position channels.
    attrs : dict, optional

    Returns
    -------
    Motion
    """
    dofs = np.asarray(dofs, dtype=np.float64)
    F = dofs.shape[0]
    col = {n: i for i, n in enumerate(names)}
    u = _AXES.lower().index(up.lower())
    hz = [a for a in range(3) if a != u]
    J = skeleton.n_joints
    rot = np.zeros((F, J, 4))
    rot[..., 0] = 1.0
    rname = skeleton.names[0]
    origin = np.zeros(4) if origin is None else np.asarray(origin, dtype=np.float64)
    pos = np.zeros((F, 3))

    def get(n: str) -> np.ndarray:
        return dofs[:, col[n]] if n in col else np.zeros(F)

    if root == "heading":
        dpsi = get(f"{rname}:heading_rate")
        psi = origin[0] + np.concatenate([[0.0], np.cumsum(dpsi[1:])])[:F]
        tw = _twist(psi, u)
        rv = np.zeros((F, 3))
        vel = np.zeros((F, 3))
        for a in hz:
            rv[:, a] = get(f"{rname}:swing_{_AXES[a]}")
            vel[:, a] = get(f"{rname}:velocity_{_AXES[a]}")
        rot[:, 0] = quat_multiply(tw, quat_from_rotvec(rv))
        dp = quat_rotate(tw, vel)
        pos[:] = origin[1:]
        if F > 1:
            pos[1:, hz] += np.cumsum(dp[1:, hz], axis=0)
        pos[:, u] = get(f"{rname}:{_AXES[u]}position")
        joints = range(1, J)
    else:
        for a in range(3):
            pos[:, a] = get(f"{rname}:{_AXES[a]}position")
        joints = range(J)
    for j in joints:
        o = skeleton.rotation_order(j)
        if not o:
            continue
        ang = np.zeros((F, 3))
        for k, a in enumerate(o):
            ang[:, k] = get(f"{skeleton.names[j]}:{a}rotation")
        rot[:, j] = euler_to_quat(ang, _padded_order(o))
    trans = None
    if translations is not None:
        trans = np.broadcast_to(np.asarray(translations, dtype=np.float64), (F, J, 3)).copy()
    return Motion(
        skeleton=skeleton,
        root_position=pos,
        rotations=rot,
        rate=rate,
        translations=trans,
        attrs=dict(attrs or {}),
    )


def _source_name(obj: Any, default: str) -> str:
    src = getattr(obj, "attrs", {}).get("source_file")
    return os.path.basename(str(src)) if src else default


def clips_from_motions(
    motions: list[Motion],
    *,
    cuts: list[np.ndarray | None] | None = None,
    root: Literal["heading", "absolute"] = "heading",
    up: str = "y",
    cyclic: bool = False,
    names: list[str] | None = None,
) -> Clips:
    """DOF clips of motions, optionally each cut at given frames.

    Parameters
    ----------
    motions : list of Motion
        Same skeleton (joint names and channels) and rate.
    cuts : list of (K,) int ndarray or None, optional
        Per motion, increasing cut frames; clip ``i`` is frames
        ``cuts[i] .. cuts[i+1] - 1``.  ``None``: the whole motion is one clip.
    root, up, cyclic
        See :func:`motion_to_dofs` and :class:`Clips`.
    names : list of str, optional
        Labels of the motions (default their source file names).

    Returns
    -------
    Clips
    """
    if not motions:
        raise ClipError("no input motion")
    names = names or [_source_name(m, f"motion{i}") for i, m in enumerate(motions)]
    sk = motions[0].skeleton
    for m, n in zip(motions[1:], names[1:]):
        if m.skeleton.names != sk.names or m.skeleton.channels != sk.channels:
            raise ClipError(f"{n}: skeleton differs from {names[0]}'s (joint names or channels)")
        if not math.isclose(m.rate, motions[0].rate, rel_tol=1e-6):
            raise ClipError(
                f"{n}: {m.rate} frames/s but {names[0]} has {motions[0].rate}; "
                "resample on ingest (ingest rate param)"
            )
    cuts = cuts or [None] * len(motions)
    fulls, origins, labels = [], [], []
    dof_names: list[str] = []
    for m, n, cut in zip(motions, names, cuts):
        dofs, dof_names, psi, pos = motion_to_dofs(m, root=root, up=up)
        bounds = [0, m.n_frames] if cut is None else list(np.asarray(cut, dtype=int))
        for a, b in zip(bounds[:-1], bounds[1:]):
            fulls.append(dofs[a:b])
            origins.append([psi[a], *pos[a]])
            labels.append(n if cut is None else f"{n}[{a}:{b}]")
    fulls = _align_periods(fulls, dof_names)
    translations = None
    if motions[0].translations is not None:
        translations = np.nanmean(motions[0].translations, axis=0).tolist()
    return make_clips(
        fulls,
        dof_names,
        rate=motions[0].rate,
        kind="motion",
        cyclic=cyclic,
        origins=np.asarray(origins),
        skeleton=sk,
        names=labels,
        attrs={"root": root, "up": up, "translations": translations},
    )


def _align_periods(trajs: list[np.ndarray], names: list[str]) -> list[np.ndarray]:
    """Shift each clip's angle DOFs by multiples of 2π towards the first clip's mean."""
    if len(trajs) < 2:
        return trajs
    ang = np.array([n.endswith("rotation") for n in names])
    if not ang.any():
        return trajs
    ref = trajs[0][:, ang].mean(axis=0)
    out = [trajs[0]]
    for t in trajs[1:]:
        t = t.copy()
        shift = np.round((t[:, ang].mean(axis=0) - ref) / (2 * np.pi)) * 2 * np.pi
        t[:, ang] -= shift
        out.append(t)
    return out


def clips_to_motions(clips: Clips) -> list[Motion]:
    """The motions of motion clips (constant DOFs restored, root integrated).

    Parameters
    ----------
    clips : Clips
        ``kind == "motion"``.

    Returns
    -------
    list of Motion
        One per clip, starting at the clip's origin.
    """
    if clips.kind != "motion":
        raise ClipError(f"clips of kind {clips.kind!r} are not motions")
    a = clips.attrs
    trans = a.get("translations")
    return [
        dofs_to_motion(
            clips.full(c),
            clips.dof_names,
            clips.skeleton,
            rate=clips.rate,
            origin=clips.origins[c],
            root=a.get("root", "heading"),
            up=a.get("up", "y"),
            translations=None if trans is None else np.asarray(trans),
            attrs={"clip": clips.names[c]},
        )
        for c in range(clips.n_clips)
    ]


def clips_from_strokes(strokes: list[Strokes], *, names: list[str] | None = None) -> Clips:
    """One clip of pen positions ``(x, y)`` per written example.

    Parameters
    ----------
    strokes : list of Strokes
        Same rate.
    names : list of str, optional

    Returns
    -------
    Clips
        ``kind == "strokes"``, DOFs ``["x", "y"]``; ``attrs["pen_up_joined"]``
        lists examples whose pen-up breaks were joined.
    """
    if not strokes:
        raise ClipError("no input strokes")
    names = names or [
        f"{s.attrs.get('letter', 'strokes')}{s.attrs.get('example', i)}"
        for i, s in enumerate(strokes)
    ]
    rate = strokes[0].rate
    for s, n in zip(strokes, names):
        if not math.isclose(s.rate, rate, rel_tol=1e-6):
            raise ClipError(f"{n}: {s.rate} samples/s but {names[0]} has {rate}")
        if len(s.points) < 2:
            raise ClipError(f"{n}: fewer than 2 pen samples")
    joined = [n for s, n in zip(strokes, names) if len(s.stroke_starts) > 1]
    return make_clips(
        [s.points for s in strokes],
        ["x", "y"],
        rate=rate,
        kind="strokes",
        names=names,
        attrs={"pen_up_joined": joined, "letter": strokes[0].attrs.get("letter")},
    )


def clips_to_strokes(clips: Clips) -> list[Strokes]:
    """Pen strokes of stroke clips (one stroke per clip).

    Parameters
    ----------
    clips : Clips
        ``kind == "strokes"``.

    Returns
    -------
    list of Strokes
    """
    if clips.kind != "strokes":
        raise ClipError(f"clips of kind {clips.kind!r} are not strokes")
    ix, iy = clips.dof_names.index("x"), clips.dof_names.index("y")
    out = []
    for c in range(clips.n_clips):
        f = clips.full(c)
        out.append(
            Strokes(
                points=f[:, [ix, iy]],
                stroke_starts=[0],
                rate=clips.rate,
                attrs={"letter": clips.attrs.get("letter"), "example": clips.names[c]},
            )
        )
    return out


# --------------------------------------------------------------------------- cycle cutting


def heel_strikes(
    positions: np.ndarray,
    foot: int,
    rate: float,
    *,
    up: str = "y",
    height_fraction: float = 0.25,
    speed_fraction: float = 0.3,
    min_gap: float = 0.05,
) -> np.ndarray:
    """Frames where a foot comes into contact with the floor.

    Contact: the foot's height is in the lowest ``height_fraction`` of its
    5–95 % range and its horizontal speed is below ``speed_fraction`` of its
    90th percentile.  Contact runs separated by less than ``min_gap`` seconds
    are merged, runs shorter than ``min_gap`` dropped, and an onset counts
    only if the foot rose above the middle of its height range since the
    previous onset (a swing).

    Parameters
    ----------
    positions : (F, J, 3) float ndarray
        Joint world positions, metres.
    foot : int
        Joint index of the foot (ankle).
    rate : float
    up : {"y", "z"}
    height_fraction, speed_fraction, min_gap : float

    Returns
    -------
    (K,) int ndarray
        Contact onsets (frames), increasing; a contact already under way at
        frame 0 is not an onset.
    """
    u = _AXES.lower().index(up.lower())
    p = np.asarray(positions, dtype=np.float64)[:, foot]
    F = len(p)
    if F < 3:
        return np.zeros(0, dtype=np.int64)
    h = p[:, u]
    lo, hi = np.percentile(h, [5, 95])
    low = h < lo + height_fraction * (hi - lo)
    hz = [a for a in range(3) if a != u]
    sp = np.linalg.norm(np.gradient(p[:, hz], axis=0), axis=1) * rate
    slow = sp < speed_fraction * np.percentile(sp, 90)
    contact = low & slow
    gap = max(1, int(round(min_gap * rate)))
    # close short gaps, then drop short runs
    for a, b in true_runs(~contact):
        if a > 0 and b < F and b - a < gap:
            contact[a:b] = True
    for a, b in true_runs(contact):
        if b - a < gap:
            contact[a:b] = False
    # an onset needs a real swing (foot above mid-range) since the previous one
    onsets: list[int] = []
    mid = lo + 0.5 * (hi - lo)
    for a, _ in true_runs(contact):
        if a == 0:
            continue
        if onsets and h[onsets[-1] : a].max() < mid:
            continue
        onsets.append(int(a))
    return np.array(onsets, dtype=np.int64)


def autocorrelation_period(dofs: np.ndarray, *, min_lag: int = 3) -> int:
    """Period (frames) of a multichannel signal from its summed autocorrelation.

    Parameters
    ----------
    dofs : (F, D) float ndarray
    min_lag : int
        Smallest period considered.

    Returns
    -------
    int
        The first autocorrelation peak (after the first drop below zero, in
        ``[min_lag, F // 2]``) that reaches 90 % of the highest; 0 when there
        is none.
    """
    x = np.asarray(dofs, dtype=np.float64)
    F = x.shape[0]
    s = x.std(axis=0)
    x = (x[:, s > 0] - x[:, s > 0].mean(axis=0)) / s[s > 0]
    if x.shape[1] == 0 or F < 2 * min_lag + 2:
        return 0
    n = 1 << int(np.ceil(np.log2(2 * F)))
    spec = np.fft.rfft(x, n=n, axis=0)
    r = np.fft.irfft((spec * spec.conj()).real, n=n, axis=0)[:F].sum(axis=1)
    r = r / (F - np.arange(F)) / (r[0] / F)
    half = F // 2
    below = np.flatnonzero(r[min_lag:half] < 0)
    if below.size == 0:
        return 0
    start = min_lag + below[0]
    if start >= half:
        return 0
    seg = r[start:half]
    # the first local maximum reaching 90 % of the highest one (not a multiple of it)
    peaks = [i for i in range(1, len(seg) - 1) if seg[i] >= seg[i - 1] and seg[i] >= seg[i + 1]]
    peaks = peaks or [int(np.argmax(seg))]
    top = max(seg[i] for i in peaks)
    if top <= 0:
        return 0
    return int(start + next(i for i in peaks if seg[i] >= 0.9 * top))


def period_cuts(dofs: np.ndarray, period: int, *, reference: int | None = None) -> np.ndarray:
    """Cut frames one period apart, each at the pose closest to a reference pose.

    Parameters
    ----------
    dofs : (F, D) float ndarray
    period : int
        Frames per cycle.
    reference : int, optional
        Reference frame (default the middle of the take).

    Returns
    -------
    (K,) int ndarray
        Increasing cut frames covering the take.
    """
    x = np.asarray(dofs, dtype=np.float64)
    F = x.shape[0]
    s = x.std(axis=0)
    s[s == 0] = 1.0
    z = (x - x.mean(axis=0)) / s
    r = F // 2 if reference is None else int(reference)
    dist = np.linalg.norm(z - z[r], axis=1)
    lo, hi = max(1, int(round(0.75 * period))), max(2, int(round(1.25 * period)))
    cuts = [r]
    c = r
    while c + lo < F:
        w = np.arange(c + lo, min(F, c + hi + 1))
        c = int(w[np.argmin(dist[w])])
        cuts.append(c)
    c = r
    while c - lo > 0:
        w = np.arange(max(0, c - hi), c - lo + 1)
        c = int(w[np.argmin(dist[w])])
        cuts.insert(0, c)
    return np.array(cuts, dtype=np.int64)


def _shape_outliers(dofs: np.ndarray, cuts: np.ndarray, factor: float) -> np.ndarray:
    """Keep-mask of cycles whose shape and duration are not outliers."""
    n = len(cuts) - 1
    if n < 3:
        return np.ones(n, dtype=bool)
    dur = np.diff(cuts).astype(float)
    med = np.median(dur)
    keep = (dur >= med / 1.5) & (dur <= med * 1.5)
    s = dofs.std(axis=0)
    s[s == 0] = 1.0
    grid = np.linspace(0.0, 1.0, 32)
    shapes = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        seg = (dofs[a:b] - dofs.mean(axis=0)) / s
        tt = np.linspace(0.0, 1.0, len(seg))
        shapes.append(np.stack([np.interp(grid, tt, seg[:, d]) for d in range(seg.shape[1])], 1))
    shapes = np.stack(shapes)
    ref = np.median(shapes[keep] if keep.sum() >= 2 else shapes, axis=0)
    dist = np.sqrt(((shapes - ref) ** 2).mean(axis=(1, 2)))
    mdist = np.median(dist[keep]) if keep.any() else np.median(dist)
    keep &= dist <= factor * max(mdist, 1e-12)
    return keep


def cut_cycles(
    motion: Motion | None = None,
    *,
    dofs: np.ndarray | None = None,
    rate: float | None = None,
    method: Literal["auto", "feet", "period"] = "auto",
    up: str = "y",
    outlier: float = 2.5,
) -> tuple[list[tuple[int, int]], dict[str, Any]]:
    """Cut a cyclic take into cycles.

    Parameters
    ----------
    motion : Motion, optional
        A take with feet (``feet`` method) — or pass ``dofs``.
    dofs : (F, D) float ndarray, optional
        Generic cyclic signal (``period`` method); computed from ``motion``
        when not given.
    rate : float, optional
        Frames per second (default ``motion.rate``).
    method : {"auto", "feet", "period"}
        ``auto``: heel strikes when the skeleton has a left foot and at least
        two cycles are found, else the autocorrelation period.
    up : {"y", "z"}
    outlier : float
        Cycles whose shape distance to the median cycle exceeds ``outlier``
        times the median distance (or whose duration is off by more than
        1.5×) are dropped.

    Returns
    -------
    cycles : list of (int, int)
        ``[start, stop)`` frame ranges of the kept cycles, in order.
    report : dict
        ``method``, ``cuts``, ``period`` (frames), ``dropped`` ranges.
    """
    if dofs is None:
        if motion is None:
            raise ClipError("cut_cycles needs a motion or a DOF matrix")
        dofs = motion_to_dofs(motion, up=up)[0]
    dofs = np.asarray(dofs, dtype=np.float64)
    rate = float(rate if rate is not None else (motion.rate if motion is not None else 1.0))
    F = dofs.shape[0]
    used = None
    cuts = np.zeros(0, dtype=np.int64)
    if method in ("auto", "feet") and motion is not None:
        foot = foot_joint(motion.skeleton, "left")
        if foot >= 0:
            pos, _ = forward_kinematics(
                motion.skeleton,
                motion.rotations,
                motion.root_position,
                translations=motion.translations,
            )
            cuts = heel_strikes(pos, foot, rate, up=up)
            used = "feet"
        elif method == "feet":
            raise ClipError("cut_cycles: the skeleton has no left foot/ankle joint")
    if method == "period" or (method == "auto" and len(cuts) < 3):
        period = autocorrelation_period(dofs, min_lag=max(3, int(0.2 * rate)))
        if period > 0:
            cuts = period_cuts(dofs, period)
            used = "period"
    if len(cuts) < 2:
        return [], {"method": used, "cuts": cuts.tolist(), "period": 0, "dropped": []}
    keep = _shape_outliers(dofs, cuts, outlier)
    cycles = [(int(a), int(b)) for (a, b), k in zip(zip(cuts[:-1], cuts[1:]), keep) if k]
    dropped = [(int(a), int(b)) for (a, b), k in zip(zip(cuts[:-1], cuts[1:]), keep) if not k]
    period = float(np.median([b - a for a, b in cycles])) if cycles else 0.0
    _ = F
    return cycles, {"method": used, "cuts": cuts.tolist(), "period": period, "dropped": dropped}


def _typicality(trajs: list[np.ndarray], samples: int = 32) -> np.ndarray:
    """RMS distance of each clip (standardised, resampled) to the elementwise median clip."""
    X = np.concatenate(trajs, axis=0)
    mean, std = X.mean(axis=0), X.std(axis=0)
    std = np.where(std > 0, std, 1.0)
    grid = np.linspace(0.0, 1.0, samples)
    shapes = []
    for t in trajs:
        z = (t - mean) / std
        tt = np.linspace(0.0, 1.0, len(z))
        shapes.append(np.stack([np.interp(grid, tt, z[:, d]) for d in range(z.shape[1])], 1))
    shapes = np.stack(shapes)
    med = np.median(shapes, axis=0)
    return np.sqrt(((shapes - med) ** 2).mean(axis=(1, 2)))


def _cycles_to_cuts(cycles: list[tuple[int, int]]) -> list[list[tuple[int, int]]]:
    """Group cycles into contiguous runs."""
    runs: list[list[tuple[int, int]]] = []
    for a, b in cycles:
        if runs and runs[-1][-1][1] == a:
            runs[-1].append((a, b))
        else:
            runs.append([(a, b)])
    return runs


# --------------------------------------------------------------------------- similar inputs (§9)


def likelihood_threshold(
    trusted: Clips,
    *,
    n_train: int = 6,
    n_test: int = 2,
    splits: int = 20,
    percentile: float = 10.0,
    seed: int = 0,
    k: int = 15,
    kernel_width: float | None = None,
) -> float:
    """Log-likelihood threshold for similar inputs from a trusted set (§9).

    Random train-on-``n_train`` / test-on-``n_test`` splits of the trusted
    clips; each test clip's per-frame log-likelihood (median over frames) under
    the transition network trained on the split's training clips; the
    threshold is the ``percentile`` of those values.

    Parameters
    ----------
    trusted : Clips
        At least 3 clips known to be similar (8 for the paper's 6/2 splits;
        with fewer, ``n_train = C - n_test``).
    n_train, n_test, splits : int
    percentile : float
    seed : int
    k, kernel_width
        Kernel regression parameters (as in :func:`~mocapflow.stages.variation.learn.learn`).

    Returns
    -------
    float
        Per-frame log-likelihood threshold.
    """
    from mocapflow.stages.variation.learn import heldout_log_likelihood

    C = trusted.n_clips
    if C < 3:
        raise ClipError(f"likelihood_threshold: need at least 3 trusted clips, got {C}")
    n_test = min(n_test, C - 2)
    n_train = min(n_train, C - n_test)
    rng = np.random.default_rng(seed)
    values: list[float] = []
    for _ in range(splits):
        perm = rng.permutation(C)
        train = [trusted.trajectories[i] for i in perm[:n_train]]
        test = [trusted.trajectories[i] for i in perm[n_train : n_train + n_test]]
        values += list(
            heldout_log_likelihood(
                train, test, cyclic=trusted.cyclic, k=k, kernel_width=kernel_width
            )
        )
    return float(np.percentile(values, percentile))


def select_similar(
    clips: Clips,
    threshold: float,
    *,
    min_clips: int = 2,
    k: int = 15,
    kernel_width: float | None = None,
) -> tuple[Clips, list[dict[str, Any]]]:
    """Iteratively remove the least likely clip while it falls below ``threshold`` (§9).

    Each clip is scored by its per-frame log-likelihood (median over frames)
    under the transition network trained on the other remaining clips.

    Parameters
    ----------
    clips : Clips
    threshold : float
        From :func:`likelihood_threshold`.
    min_clips : int
        Never go below this many clips.
    k, kernel_width
        Kernel regression parameters.

    Returns
    -------
    kept : Clips
    removed : list of dict
        ``name`` and ``log_likelihood`` of each removed clip, in removal order.
    """
    from mocapflow.stages.variation.learn import heldout_log_likelihood

    idx = list(range(clips.n_clips))
    removed: list[dict[str, Any]] = []
    while len(idx) > min_clips:
        scores = []
        for i in idx:
            train = [clips.trajectories[j] for j in idx if j != i]
            scores.append(
                heldout_log_likelihood(
                    train,
                    [clips.trajectories[i]],
                    cyclic=clips.cyclic,
                    k=k,
                    kernel_width=kernel_width,
                )[0]
            )
        worst = int(np.argmin(scores))
        if scores[worst] >= threshold:
            break
        removed.append({"name": clips.names[idx[worst]], "log_likelihood": float(scores[worst])})
        idx.pop(worst)
    kept = clips.replace(
        trajectories=[clips.trajectories[i] for i in idx],
        origins=clips.origins[idx],
        names=[clips.names[i] for i in idx],
    )
    return kept, removed


# --------------------------------------------------------------------------- the stage


def _flatten_sources(value: Any, out: list) -> list:
    if isinstance(value, (list, tuple)):
        for v in value:
            _flatten_sources(v, out)
    elif isinstance(value, dict) and "strokes" in value:
        _flatten_sources(value["strokes"], out)
    elif value is not None:
        out.append(value)
    return out


@stage("clips", outputs=("clips", "report"))
def clips(
    sources: Any,
    *,
    cut: Literal["auto", "feet", "period", "none"] = "auto",
    cyclic: bool | None = None,
    root: Literal["heading", "absolute"] = "heading",
    up: Literal["y", "z"] = "y",
    outlier: float = 2.5,
    min_cycles: int = 2,
    letter: str | None = None,
    max_clips: int | None = None,
    similar_threshold: float | None = None,
    ctx: Context,
) -> dict:
    """Make the DOF clips the ``learn`` stage trains on, from ingested parts.

    With one motion part (a long take) and ``cut`` not ``"none"``, the take is
    cut into cycles (:func:`cut_cycles`).  With several parts each part is one
    example.  Each pen-stroke example is one clip.

    Parameters
    ----------
    sources : Motion, Strokes, Clips or list of them
        The ingested parts (a gather input is a list ordered by part).
    cut : {"auto", "feet", "period", "none"}
        Cycle cutting of a single take (``auto``: heel strikes, else period).
    cyclic : bool, optional
        Mark the clips as cycles (default: true exactly when a take was cut).
    root : {"heading", "absolute"}
        Root DOFs (see module docstring).
    up : {"y", "z"}
        World up axis.
    outlier : float
        Shape-outlier factor for dropping cycles.
    min_cycles : int
        Fewer cycles than this: the take is used whole, with a warning.
    letter : str, optional
        Keep only strokes whose ``attrs["letter"]`` equals it.
    max_clips : int, optional
        Keep at most this many clips, the most typical ones (smallest
        distance to the median clip, all resampled to 32 frames), in order.
    similar_threshold : float, optional
        Run :func:`select_similar` with this per-frame log-likelihood
        threshold (from :func:`likelihood_threshold` on a trusted set).
    ctx : Context

    Returns
    -------
    dict
        ``clips`` (:class:`Clips`) and ``report`` (JSON: clip names and
        lengths, cut method and frames, dropped constant DOFs, removed clips).
    """
    items = _flatten_sources(sources, [])
    if not items:
        raise ClipError("clips: no input part")
    kinds = {type(x).__name__ for x in items}
    report: dict[str, Any] = {}
    if all(isinstance(x, Clips) for x in items):
        out = merge_clips(items)
    elif all(isinstance(x, Strokes) for x in items):
        if letter is not None:
            items = [s for s in items if s.attrs.get("letter") == letter]
            if not items:
                raise ClipError(f"clips: no strokes of letter {letter!r}")
        out = clips_from_strokes(items)
        if cyclic:
            out = out.replace(cyclic=True)
        if out.attrs.get("pen_up_joined"):
            ctx.warn(f"pen-up breaks joined in {out.attrs['pen_up_joined']}")
    elif all(isinstance(x, Motion) for x in items):
        if len(items) == 1 and cut != "none":
            m = items[0]
            name = _source_name(m, "take")
            cycles, rep = cut_cycles(m, method=cut, up=up, outlier=outlier)
            report["cut"] = rep
            if len(cycles) < min_cycles:
                ctx.warn(
                    f"{name}: found {len(cycles)} cycle(s) (< {min_cycles}); "
                    "using the whole take as one clip"
                )
                out = clips_from_motions(items, root=root, up=up, cyclic=bool(cyclic))
            else:
                bounds = sorted({x for c in cycles for x in c})
                out = clips_from_motions(
                    items,
                    cuts=[np.array(bounds)],
                    root=root,
                    up=up,
                    cyclic=True if cyclic is None else cyclic,
                )
                keep = [i for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:]))
                        if (a, b) in set(cycles)]
                out = out.replace(
                    trajectories=[out.trajectories[i] for i in keep],
                    origins=out.origins[keep],
                    names=[out.names[i] for i in keep],
                )
        else:
            out = clips_from_motions(items, root=root, up=up, cyclic=bool(cyclic))
    else:
        raise ClipError(f"clips: mixed or unsupported inputs {sorted(kinds)}")
    if max_clips is not None and out.n_clips > max_clips:
        if max_clips < 1:
            raise ClipError(f"clips.max_clips must be at least 1, got {max_clips}")
        keep = np.sort(np.argsort(_typicality(out.trajectories), kind="stable")[:max_clips])
        report["dropped_atypical"] = [out.names[i] for i in range(out.n_clips) if i not in keep]
        out = out.replace(
            trajectories=[out.trajectories[i] for i in keep],
            origins=out.origins[keep],
            names=[out.names[i] for i in keep],
        )
    if similar_threshold is not None:
        out, removed = select_similar(out, similar_threshold)
        report["removed"] = removed
        for r in removed:
            ctx.warn(f"clip {r['name']} removed: log-likelihood {r['log_likelihood']:.3g} "
                     f"< threshold {similar_threshold:.3g}")
    lengths = out.lengths
    if out.n_clips > 1 and lengths.max() > 2 * lengths.min():
        ctx.warn(
            f"clip lengths differ a lot ({lengths.min()}–{lengths.max()} frames); "
            "the prior network draws more start frames from the long ones"
        )
    if out.attrs.get("constant_dofs"):
        report["constant_dofs"] = out.attrs["constant_dofs"]
    report.update(
        {
            "n_clips": out.n_clips,
            "names": out.names,
            "lengths": lengths.tolist(),
            "n_dofs": out.n_dofs,
            "cyclic": out.cyclic,
            "kind": out.kind,
        }
    )
    return {"clips": out, "report": report}


# --------------------------------------------------------------------------- export


@exporter("clips")
def export_clips(obj: Clips, directory: Path, stem: str) -> list[Path]:
    """Write each clip as a file: BVH for motions, CSV for strokes and DOFs.

    Parameters
    ----------
    obj : Clips
    directory : Path
    stem : str
        File name stem; clip ``i`` goes to ``<stem>_<i>.bvh`` / ``.csv``.

    Returns
    -------
    list of Path
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    if obj.kind == "motion":
        from mocapflow.stages.motion.formats.bvh import write_bvh

        for i, m in enumerate(clips_to_motions(obj)):
            paths.append(write_bvh(m, directory / f"{stem}_{i:02d}.bvh"))
        return paths
    for i in range(obj.n_clips):
        p = directory / f"{stem}_{i:02d}.csv"
        f = obj.full(i)
        header = ",".join(obj.dof_names)
        np.savetxt(p, f, delimiter=",", header=header, comments="", fmt="%.9g")
        paths.append(p)
    return paths
