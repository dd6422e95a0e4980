"""DOF clips, the data of the variation graph (Lau, Bar-Joseph & Kuffner 2009, §4).

The method learns from a few *similar* examples of one motion type, each a
trajectory of degrees of freedom (DOFs).  This module holds the
:class:`Clips` type (codec and exporter) and makes clips of motions (through
:mod:`~mocapflow.stages.variation.dofs`) and of pen strokes, and back.  Cutting
a take into cycles is in
:mod:`~mocapflow.stages.variation.cycles`, the selection of similar inputs
(Lau §9) in :mod:`~mocapflow.stages.variation.similar`, and the ``clips`` stage
that makes the training clips from ingested parts in
:mod:`~mocapflow.stages.variation.inputs`.

DOFs of a motion
    Joint Euler angles and a root representation (``root="heading"``: heading
    rate, swing, velocity in the heading frame and height; ``"absolute"``), see
    :mod:`~mocapflow.stages.variation.dofs`.  Each clip keeps the heading and
    position of its first frame as its origin.  DOFs constant over every clip
    are dropped from the trajectories and restored on the way back.
DOFs of pen strokes
    ``x`` and ``y`` of the pen (pen-up breaks are joined in drawing order).
Source rate and units
    Motion clips keep their first source's file unit, scale, ``Frame Time`` and
    rate (``attrs["source"]``, :func:`source_attrs`); the motions made back
    (:func:`clips_to_motions`) carry them, and :func:`export_clips` writes each
    variant at the source rate (or ``attrs["output_rate"]``, set by the ``ik``
    stage), resampled from the model's rate by a C² rotation spline, in the
    source unit: the input's exact ``Frame Time`` text and skeleton size.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline.codecs import Encoded, codec, decode, encode, exporter
from mocapflow.stages.motion.datatypes import Motion, Skeleton, Strokes
from mocapflow.stages.motion.formats.bvh import write_bvh
from mocapflow.stages.motion.kinematics import resample_motion
from mocapflow.stages.variation.dofs import ClipError, dofs_to_motion, motion_to_dofs

__all__ = [
    "ClipError",
    "Clips",
    "clips_from_motions",
    "clips_from_strokes",
    "clips_to_motions",
    "clips_to_strokes",
    "export_clips",
    "export_rate",
    "flatten_clips",
    "make_clips",
    "merge_clips",
    "source_attrs",
    "source_name",
]

#: Motion attrs describing the source file that clips carry to their motions.
SOURCE_KEYS = ("source_format", "source_unit", "source_scale", "frame_time", "frame_time_text")


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

    def __repr__(self) -> str:
        """One line: clips, frames, varying of all DOFs, rate, cyclic (never the data)."""
        frames = sum(t.shape[0] for t in self.trajectories)
        cyc = ", cyclic" if self.cyclic else ""
        return (f"Clips({self.n_clips} {self.kind} clips, {frames} frames, {self.n_dofs} of "
                f"{len(self.dof_names)} DOFs varying @ {self.rate:.4g} Hz{cyc})")

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

    def subset(self, indices: list[int] | np.ndarray) -> Clips:
        """The clips ``indices``, in that order, with their origins and names.

        Parameters
        ----------
        indices : (K,) int sequence

        Returns
        -------
        Clips
        """
        return self.replace(
            trajectories=[self.trajectories[i] for i in indices],
            origins=self.origins[indices],
            names=[self.names[i] for i in indices],
        )

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
    coords: dict[str, tuple[np.ndarray, tuple[str, ...]]] = {}
    if c.skeleton is not None:
        e = encode(c.skeleton)
        for name, (arr, dims) in e.arrays.items():
            arrays[f"skeleton_{name}"] = (arr, dims)
        sk_attrs = e.attrs
        coords.update(e.coords)  # joint / end_site / xyz labels
    names = [str(n) for n in c.dof_names]
    varying = [n for n, v in zip(names, np.asarray(c.varying, bool)) if v]
    coords["dof_all"] = (np.array(names, dtype=str), ("dof_all",))
    if len(varying) == data.shape[1]:
        coords["dof"] = (np.array(varying, dtype=str), ("dof",))
    if len(c.names) == len(c.lengths) and len(c.names):
        coords["clip"] = (np.array([str(n) for n in c.names], dtype=str), ("clip",))
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
        coords,
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


# --------------------------------------------------------------------------- motion <-> DOFs


def source_name(obj: Any, default: str) -> str:
    """Base name of ``obj.attrs["source_file"]``, or ``default``."""
    src = getattr(obj, "attrs", {}).get("source_file")
    return os.path.basename(str(src)) if src else default


def source_attrs(motion: Motion) -> dict[str, Any]:
    """The source file's unit, scale, Frame Time and rate of a motion.

    Parameters
    ----------
    motion : Motion

    Returns
    -------
    dict
        The :data:`SOURCE_KEYS` present in ``motion.attrs`` and ``source_rate``
        (``attrs["resampled_from_rate"]``, the rate the file was read at, else
        ``motion.rate``).
    """
    out = {k: motion.attrs[k] for k in SOURCE_KEYS if k in motion.attrs}
    out["source_rate"] = float(motion.attrs.get("resampled_from_rate", motion.rate))
    return out


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
        See :func:`~mocapflow.stages.variation.dofs.motion_to_dofs` and :class:`Clips`.
    names : list of str, optional
        Labels of the motions (default their source file names).

    Returns
    -------
    Clips
        ``attrs["source"]``: :func:`source_attrs` of the first motion.
    """
    if not motions:
        raise ClipError("no input motion")
    names = names or [source_name(m, f"motion{i}") for i, m in enumerate(motions)]
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
        attrs={
            "root": root,
            "up": up,
            "translations": translations,
            "source": source_attrs(motions[0]),
        },
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
        One per clip, starting at the clip's origin, at ``clips.rate``; ``attrs``
        ``clip`` (its name) and the source's unit, scale and Frame Time
        (``attrs["source"]``, see :func:`source_attrs`).
    """
    if clips.kind != "motion":
        raise ClipError(f"clips of kind {clips.kind!r} are not motions")
    a = clips.attrs
    trans = a.get("translations")
    src = {k: v for k, v in (a.get("source") or {}).items() if k in SOURCE_KEYS}
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
            attrs={**src, "clip": clips.names[c]},
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


# --------------------------------------------------------------------------- export


def export_rate(clips: Clips) -> float:
    """Frames per second the variants are exported at.

    ``attrs["output_rate"]`` when set, else the source file's rate
    (``attrs["source"]["source_rate"]``), else ``clips.rate``: the rate
    :func:`export_clips` writes and ``ik`` numbers constraint frames in.
    """
    rate = clips.attrs.get("output_rate") or (clips.attrs.get("source") or {}).get("source_rate")
    return float(rate) if rate else float(clips.rate)


@exporter("clips")
def export_clips(obj: Clips, directory: Path, stem: str) -> list[Path]:
    """Write each clip as a file: BVH for motions, CSV for strokes and DOFs.

    Motions are written at ``attrs["output_rate"]`` when set, else at the source
    rate (``attrs["source"]["source_rate"]``; the clips' own rate without one),
    resampled by a C² rotation spline
    (:func:`~mocapflow.stages.motion.kinematics.resample_motion`), in the source unit.

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
        rate = export_rate(obj)
        for i, m in enumerate(clips_to_motions(obj)):
            if abs(rate - m.rate) > 1e-9 * m.rate:
                m = resample_motion(m, rate, method="spline")
            paths.append(write_bvh(m, directory / f"{stem}_{i:02d}.bvh"))
        return paths
    for i in range(obj.n_clips):
        p = directory / f"{stem}_{i:02d}.csv"
        f = obj.full(i)
        header = ",".join(obj.dof_names)
        np.savetxt(p, f, delimiter=",", header=header, comments="", fmt="%.9g")
        paths.append(p)
    return paths
