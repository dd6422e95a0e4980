"""Inverse-kinematics clean-up of sampled variants (Lau, Bar-Joseph & Kuffner 2009, §7).

Per limb (leg or arm) and frame with constraints, the limb's joint-angle DOFs
``q`` minimise (Lau Eq. 7; paper and default weights w₁ = 1, w₂ = 5)

    w₁ ‖q − q̄‖² + w₂ ‖q − 2 q₋₁ + q₋₂‖²

subject to every constrained end effector of the limb lying at its target
(SLSQP, initialised from the sample ``q̄``; ``q₋₁, q₋₂`` are the cleaned
previous frames; :func:`_solve_frame`).  Frames without constraints keep the
sample; after a contact the correction eases back to it (raised cosine over
``blend`` seconds).  The ``ik`` stage detects the contacts of each
clip (:func:`_clip_constraints`) and cleans every limb frame by frame
(:func:`_clean_limb`).

Limbs and targets
    The limb of an effector joint is the chain of its ancestors up to (not
    including) the first joint with several children or the root; only the
    chain's varying DOFs move.  Foot contacts are detected automatically per
    effector (ankle and toe of each foot): height below the floor (5th
    percentile) + ``height_threshold`` and horizontal speed below
    ``speed_threshold``; each contact run's target is the position of
    the effector at the run's first frame in the cleaned pose (so a contact
    starts without a jump).  Of the detected contacts of one limb only the
    deepest effector is held (the toe while it touches, else the ankle), so
    the foot rolls about its ball through heel-off; contacts given in the
    config are always held.  The config can replace the detection
    (``contacts``: frame ranges per joint) or give explicit targets
    (``targets``: ``[frame, x, y, z]`` rows per joint, e.g. for hands).
Frame numbers
    The variants are at the model's rate (the ingest ``rate``) and are exported
    at the output rate: ``attrs["output_rate"]`` (the ``output_rate`` param),
    else the source file's rate (:func:`export_rate`, what
    :func:`~mocapflow.stages.variation.clips.export_clips` writes).  Frames of
    ``contacts`` and ``targets`` count at the output rate, 0-based, as in the
    exported BVH; they are rounded to the nearest model frame
    (``round(frame * rate / output_rate)``; a range keeps at least one frame).
    The report gives frames at the output rate too (a model frame ``t`` is
    exported frame ``round(t * output_rate / rate)``; a range of model frames,
    the exported frames in its time span), with the model frames under
    ``model_frame`` keys.
Loopable variants
    The ``sample`` stage's ``loop`` variants (``attrs["loop"]``) are consecutive
    cycles of one stream; they are cleaned as the one clip they make played in
    order (:func:`_played_in_order`), so the smoothness term and the contacts
    run across the joins, and split back.  Their ``contacts`` and ``targets``
    frames count along that chain; the report has one entry for it
    (``variants``: the variant names).
Unreachable targets
    When SLSQP cannot meet a target within ``tolerance`` the limb takes the
    pose that minimises the target distance (best effort) and a warning names
    the variant, frame, effector and the remaining error.  A detected contact
    missed by more than ``release`` ends there (the foot lifts off early).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from mocapflow.pipeline import Context, stage
from mocapflow.stages.motion.contacts import foot_joint, true_runs
from mocapflow.stages.motion.datatypes import Skeleton
from mocapflow.stages.motion.kinematics import forward_kinematics
from mocapflow.stages.motion.rotations import quat_to_matrix
from mocapflow.stages.variation.clips import Clips, clips_to_motions, export_rate
from mocapflow.stages.variation.dofs import padded_order

__all__ = [
    "IKError",
    "Limb",
    "ik",
    "limb_of",
]

class IKError(ValueError):
    """Bad IK request (unknown effector joint, malformed targets)."""


@dataclass
class Limb:
    """A kinematic chain moved by IK.

    Attributes
    ----------
    joints : list of int
        Chain joints, top (nearest the body) first.
    top_parent : int
        Parent of the chain's top joint (fixed during IK).
    effectors : list of int
        Effector joints (children of chain joints).
    dof_columns : (V,) int ndarray
        Columns of the full DOF vector that IK varies.
    dof_slots : list of (int, int)
        ``(chain joint position, Euler slot)`` of each varied DOF.
    """

    joints: list[int]
    top_parent: int
    effectors: list[int]
    dof_columns: np.ndarray
    dof_slots: list[tuple[int, int]]


def limb_of(skeleton: Skeleton, effector: int) -> list[int]:
    """The chain of joints that moves ``effector`` (top first).

    Parameters
    ----------
    skeleton : Skeleton
    effector : int
        Joint index.

    Returns
    -------
    list of int
        Ancestors of ``effector`` from its parent up to (not including) the
        first joint with more than one child or the root.
    """
    chain = []
    j = int(skeleton.parents[effector])
    while j > 0 and len(skeleton.children(j)) <= 1:
        chain.append(j)
        j = int(skeleton.parents[j])
    if j > 0 and not chain:
        chain.append(j)
    return chain[::-1]


def _make_limb(clips: Clips, effectors: list[int]) -> Limb:
    sk = clips.skeleton
    deepest = max(effectors, key=lambda e: len(limb_of(sk, e)))
    joints = limb_of(sk, deepest)
    for e in effectors:
        if not set(limb_of(sk, e)) <= set(joints) and limb_of(sk, e):
            raise IKError(f"effectors {[sk.names[x] for x in effectors]} are not on one limb")
    col = {n: i for i, n in enumerate(clips.dof_names)}
    cols, slots = [], []
    for pos, j in enumerate(joints):
        order = sk.rotation_order(j)
        for slot, a in enumerate(order):
            name = f"{sk.names[j]}:{a}rotation"
            c = col.get(name)
            if c is not None and clips.varying[c]:
                cols.append(c)
                slots.append((pos, slot))
    if not joints:
        raise IKError(f"effector {sk.names[deepest]!r} has no joint chain to move")
    return Limb(
        joints=joints,
        top_parent=int(sk.parents[joints[0]]),
        effectors=effectors,
        dof_columns=np.asarray(cols, dtype=np.int64),
        dof_slots=slots,
    )


class _ChainFK:
    """Forward kinematics of one limb at one frame, batched over candidate DOF vectors.

    Rotation matrices from :class:`scipy.spatial.transform.Rotation` (upper-case
    order = intrinsic, the convention of
    :func:`~mocapflow.stages.motion.kinematics.euler_to_quat`).
    """

    def __init__(self, sk: Skeleton, limb: Limb, angles: np.ndarray, gpar: np.ndarray,
                 ppar: np.ndarray):
        self.sk, self.limb = sk, limb
        self.angles = angles  # (J_c, 3) Euler angles of the chain at this frame
        self.Gpar = quat_to_matrix(gpar)  # (3, 3) global rotation of the top parent
        self.ppar = ppar
        self.orders = [padded_order(sk.rotation_order(j)) for j in limb.joints]
        self.offsets = sk.offsets[limb.joints]
        self.eff_parent = [limb.joints.index(int(sk.parents[e])) for e in limb.effectors]
        self.eff_offset = sk.offsets[limb.effectors]

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """Effector positions ``(Q, E, 3)`` for DOF vectors ``q (Q, V)``."""
        q = np.atleast_2d(q)
        Q = q.shape[0]
        ang = np.broadcast_to(self.angles, (Q,) + self.angles.shape).copy()
        for v, (pos, slot) in enumerate(self.limb.dof_slots):
            ang[:, pos, slot] = q[:, v]
        G = np.broadcast_to(self.Gpar, (Q, 3, 3))
        p = np.broadcast_to(self.ppar, (Q, 3))
        gl, pl = [], []
        for k in range(len(self.orders)):
            p = p + G @ self.offsets[k]
            G = G @ Rotation.from_euler(self.orders[k], ang[:, k]).as_matrix()
            gl.append(G)
            pl.append(p)
        return np.stack(
            [pl[k] + gl[k] @ off for k, off in zip(self.eff_parent, self.eff_offset)], axis=1
        )


@dataclass(frozen=True)
class _Solver:
    """Settings of the per-frame solve (the ``ik`` stage's params; ``n_blend`` in frames)."""

    w1: float
    w2: float
    tolerance: float
    release: float
    max_change: float
    max_iter: int
    n_blend: int


def _solve_frame(
    fk: _ChainFK,
    qbar: np.ndarray,
    qprev: np.ndarray | None,
    target: np.ndarray,
    active: np.ndarray,
    solver: _Solver,
) -> tuple[np.ndarray, float, bool]:
    """One limb, one frame: Lau Eq. 7 by SLSQP, with a best-effort fallback.

    Parameters
    ----------
    fk : _ChainFK
        The limb's forward kinematics at this frame.
    qbar : (V,) float ndarray
        Sampled DOFs of the limb.
    qprev : (V,) float ndarray or None
        ``2 q₋₁ − q₋₂`` of the cleaned previous frames (``q₋₁`` at frame 1,
        ``None`` at frame 0).
    target : (E, 3) float ndarray
        Effector targets (rows ``active`` are constrained).
    active : (E,) bool ndarray
    solver : _Solver

    Returns
    -------
    q : (V,) float ndarray
    error : float
        Largest remaining target distance, metres.
    reached : bool
        ``error <= tolerance``.
    """
    w1, w2, tolerance = solver.w1, solver.w2, solver.tolerance
    max_iter, max_change = solver.max_iter, solver.max_change
    pred = None if qprev is None else qprev  # 2 q₋₁ − q₋₂ (or None)

    def obj(q):
        r = w1 * ((q - qbar) ** 2).sum()
        if pred is not None:
            r += w2 * ((q - pred) ** 2).sum()
        return r

    def obj_grad(q):
        g = 2 * w1 * (q - qbar)
        if pred is not None:
            g += 2 * w2 * (q - pred)
        return g

    h = 1e-7

    def cons(q):
        return (fk(q[None])[0, active] - target[active]).ravel()

    def cons_jac(q):
        V = len(q)
        Qs = np.concatenate([q[None], q[None] + h * np.eye(V)])
        P = fk(Qs)[:, active].reshape(V + 1, -1)
        return ((P[1:] - P[0]) / h).T

    q0 = qbar.copy()
    bounds = list(zip(qbar - max_change, qbar + max_change))
    res = minimize(
        obj, q0, jac=obj_grad, method="SLSQP", bounds=bounds,
        constraints=[{"type": "eq", "fun": cons, "jac": cons_jac}],
        options={"maxiter": max_iter, "ftol": 1e-12},
    )
    q = np.clip(res.x, qbar - max_change, qbar + max_change) if np.all(
        np.isfinite(res.x)) else q0
    err = float(np.linalg.norm(cons(q).reshape(-1, 3), axis=1).max())
    if err <= tolerance:
        return q, err, True
    # best effort: the objective plus a stiff penalty on the target distance
    rho = 1e5  # per m²: 1 cm off costs as much as 0.3 rad of w1-weighted change

    def dist(q):
        c = cons(q)
        return rho * (c * c).sum() + obj(q)

    def dist_grad(q):
        return 2 * rho * cons_jac(q).T @ cons(q) + obj_grad(q)

    best = min((q, q0), key=lambda x: dist(x))
    res2 = minimize(dist, best, jac=dist_grad, method="SLSQP", bounds=bounds,
                    options={"maxiter": max_iter, "ftol": 1e-12})
    q2 = res2.x if dist(res2.x) < dist(best) else best
    err2 = float(np.linalg.norm(cons(q2).reshape(-1, 3), axis=1).max())
    return q2, err2, err2 <= tolerance


@dataclass(frozen=True)
class _Frames:
    """Frame numbers at the model's ``rate`` and at the export's ``output_rate``."""

    rate: float
    output_rate: float

    @property
    def same(self) -> bool:
        """The export is at the model's rate (not resampled)."""
        return abs(self.output_rate - self.rate) <= 1e-9 * self.rate

    def n_exported(self, n_model: int) -> int:
        """Exported frames of a clip of ``n_model`` model frames (as the resampler makes)."""
        if self.same or n_model == 0:
            return n_model
        return int(np.floor((n_model - 1) * self.output_rate / self.rate + 1e-9)) + 1

    def to_model(self, frame: float) -> int:
        """Nearest model frame of exported frame ``frame``."""
        return int(frame) if self.same else int(round(frame * self.rate / self.output_rate))

    def to_exported(self, t: int) -> int:
        """Nearest exported frame of model frame ``t``."""
        return int(t) if self.same else int(round(t * self.output_rate / self.rate))

    def span(self, t0: int, t1: int) -> tuple[int, int]:
        """``[start, stop)`` of the exported frames in the time of model frames ``t0..t1``
        (the nearest exported frame when none falls in it)."""
        if self.same:
            return int(t0), int(t1) + 1
        k = self.output_rate / self.rate
        a, b = math.ceil(t0 * k - 1e-9), math.floor(t1 * k + 1e-9) + 1
        if b <= a:
            a = self.to_exported(t0)
            b = a + 1
        return a, b

    def note(self) -> str:
        """``" (frames at 120 fps)"`` when the export is resampled, else ``""``."""
        return "" if self.same else f" (frames at {self.output_rate:g} fps)"


def _auto_effectors(sk: Skeleton) -> list[list[int]]:
    """Per foot: [ankle, toe] joints that exist (one limb each)."""
    limbs = []
    for side in ("left", "right"):
        f = foot_joint(sk, side)
        if f < 0:
            continue
        eff = [f]
        toes = [c for c in sk.children(f) if "toe" in sk.names[c].lower()]
        if toes:
            eff.append(toes[0])
        limbs.append(eff)
    return limbs


@stage("ik", outputs=("variants", "report"))
def ik(
    variants: Clips,
    *,
    w1: float = 1.0,
    w2: float = 5.0,
    effectors: list[str] | None = None,
    contacts: dict[str, list[list[int]]] | None = None,
    targets: dict[str, list[list[float]]] | None = None,
    height_threshold: float = 0.05,
    speed_threshold: float | None = None,
    tolerance: float = 1e-3,
    release: float = 0.02,
    max_change: float = 0.5,
    blend: float = 0.15,
    max_iter: int = 100,
    mode: Literal["auto", "off"] = "auto",
    output_rate: float | None = None,
    ctx: Context,
) -> dict:
    """IK clean-up of sampled variants: planted feet (and configured targets), Lau §7.

    Parameters
    ----------
    variants : Clips
        Sampled variants (pen strokes pass through unchanged).
    w1, w2 : float
        Closeness and smoothness weights of Lau Eq. 7 (paper: w₁ = 1, w₂ = 5).
    effectors : list of str, optional
        Effector joint names for automatic contact detection (default the
        ankle and toe joints of both feet; joints named only in ``contacts`` or
        ``targets`` are not detected).
    contacts : dict, optional
        ``joint -> [[start, stop], ...]`` contact frame ranges (``stop``
        excluded) replacing the detection for that joint (all clips, clipped to
        each clip).  Frames count at the output rate (the exported BVH's 0-based
        frame numbers) and are rounded to the nearest model frame, a range
        keeping at least one.
    targets : dict, optional
        ``joint -> [[frame, x, y, z], ...]`` explicit targets (metres), added
        to the detected ones (all clips).  ``frame`` is an exported frame number
        (0-based, at the output rate; outside the exported clip: IKError), held
        at the nearest model frame, so exactly met at the exported frames that
        are model frames (every 4th at 30 -> 120 fps).
    height_threshold : float
        Metres above the effector's floor (5th percentile of its height).
    speed_threshold : float, optional
        Horizontal speed (m/s) below which an effector may be in contact;
        default the larger of 0.5 m/s and its median speed.
    tolerance : float
        Metres; a constraint met within it counts as reached, others are reported.
    release : float
        Metres; a detected contact whose target is missed by more than this
        ends at that frame (the foot lifts off early); contacts given in
        ``contacts`` are held to the end.
    max_change : float
        Radians; each DOF stays within this of its sampled value (keeps the
        knee and elbow on the sampled side of full extension).
    blend : float
        Seconds over which the correction of a limb eases back to the sample
        after its last constrained frame (raised cosine).
    max_iter : int
        SLSQP iterations per frame.
    mode : {"auto", "off"}
        ``off`` passes the variants through.
    output_rate : float, optional
        Frames per second the variants are exported at (``attrs["output_rate"]``);
        default the source file's rate, so the BVH keeps the input's ``Frame Time``.
        The variants stay at the model's rate; the exporter resamples them by a
        C² rotation spline.
    ctx : Context
        Warnings.

    Returns
    -------
    dict
        ``variants`` (Clips, ``attrs["ik"]`` set) and ``report`` (JSON; frame
        numbers at the output rate, model frames under ``model_frame``): per
        clip ``output_frames``, ``constrained`` (per effector ``[start, stop]``
        ranges of exported frames in the time of the constrained model frames),
        ``constrained_frames`` (their count), max / mean error (m), max error
        over the frames whose targets were reached, ``targets`` (each given
        target: ``effector``, ``frame`` as given, ``model_frame``,
        ``exported_frame`` where it is held, ``error`` m (null: its limb has
        no varying DOF), ``reached``) and
        ``unreachable`` (``frame``, ``model_frame``, ``effectors``, ``error``);
        the limbs, ``rate`` (model), ``output_rate`` and the thresholds used.
    """
    if variants.kind != "motion":
        why = f"kind {variants.kind!r} has no skeleton"
        return {"variants": variants, "report": {"skipped": why}}
    if output_rate is not None:
        if not (isinstance(output_rate, (int, float)) and 0 < output_rate < math.inf):
            raise IKError(f"output_rate: must be a number > 0 or null, got {output_rate!r}")
        variants = variants.replace(attrs={**variants.attrs, "output_rate": float(output_rate)})
    if mode == "off":
        return {"variants": variants, "report": {"skipped": "off"}}
    sk = variants.skeleton
    up = "xyz".index(variants.attrs.get("up", "y"))
    groups = _effector_groups(sk, effectors, contacts, targets)
    limbs = [_make_limb(variants, g) for g in groups]
    solver = _Solver(w1=w1, w2=w2, tolerance=tolerance, release=release, max_change=max_change,
                     max_iter=max_iter, n_blend=max(1, int(round(blend * variants.rate))))
    eff_all = sorted({e for g in groups for e in g})
    frames = _Frames(rate=float(variants.rate), output_rate=export_rate(variants))
    out_trajs = []
    report: dict[str, Any] = {"clips": [], "limbs": [[sk.names[e] for e in g] for g in groups]}
    solved = _played_in_order(variants)
    for c, motion in enumerate(clips_to_motions(solved)):
        pos, grot = forward_kinematics(
            sk, motion.rotations, motion.root_position, translations=motion.translations
        )
        runs_of, fixed, given = _clip_constraints(
            sk, pos, eff_all, rate=variants.rate, up=up, effectors=effectors, contacts=contacts,
            targets=targets, height_threshold=height_threshold, speed_threshold=speed_threshold,
            frames=frames, clip=solved.names[c],
        )
        traj, clip_report = _clean_clip(solved, c, pos, grot, limbs, eff_all, runs_of, fixed,
                                        given, contacts=contacts, solver=solver, frames=frames,
                                        ctx=ctx)
        out_trajs.append(traj)
        report["clips"].append(clip_report)
    if solved is not variants:  # the loop's cycles back as the variants they are
        out_trajs = np.split(out_trajs[0], np.cumsum(variants.lengths)[:-1])
        report["clips"][0]["variants"] = list(variants.names)
    report.update(
        {"w1": w1, "w2": w2, "height_threshold": height_threshold,
         "speed_threshold": speed_threshold, "tolerance": tolerance,
         "rate": frames.rate, "output_rate": frames.output_rate}
    )
    cleaned = variants.replace(trajectories=out_trajs, attrs={**variants.attrs, "ik": True})
    return {"variants": cleaned, "report": report}


def _played_in_order(variants: Clips) -> Clips:
    """Loopable variants (``attrs["loop"]``, the ``sample`` stage's ``loop``) as one clip.

    They are consecutive cycles of one stream, each origin where the previous
    cycle ends, so they are cleaned as the one motion they make played in
    order: a contact across a join is one contact and the smoothness term of
    Lau Eq. 7 runs across the joins (cleaned one by one, the joins of 5 cycles
    jumped to 20.7 × the inputs' jerk p99).  Other variants are returned as they are.
    """
    if not variants.attrs.get("loop") or variants.n_clips < 2:
        return variants
    return variants.replace(trajectories=[np.concatenate(variants.trajectories, axis=0)],
                            origins=variants.origins[:1], names=["+".join(variants.names)])


def _join_limb_group(groups: list[list[int]], sk: Skeleton, j: int) -> None:
    """Add effector ``j`` to the group of a shared limb, or start a group."""
    for g in groups:
        if set(limb_of(sk, j)) & set(limb_of(sk, g[0])):
            g.append(j)
            break
    else:
        groups.append([j])


def _effector_groups(
    sk: Skeleton,
    effectors: list[str] | None,
    contacts: dict[str, list[list[int]]] | None,
    targets: dict[str, list[list[float]]] | None,
) -> list[list[int]]:
    """Effector joints grouped by limb: the given or automatic ones, then constrained joints."""
    if effectors is None:
        groups = _auto_effectors(sk)
    else:
        groups = []
        for name in effectors:
            try:
                j = sk.index(name)
            except KeyError as e:
                raise IKError(f"ik.effectors: {e.args[0]}") from None
            _join_limb_group(groups, sk, j)
    for name in list(contacts or {}) + list(targets or {}):
        try:
            j = sk.index(name)
        except KeyError as e:
            raise IKError(f"ik: {e.args[0]}") from None
        if not any(j in g for g in groups):
            _join_limb_group(groups, sk, j)
    return groups


def _clip_constraints(
    sk: Skeleton,
    pos: np.ndarray,
    eff_all: list[int],
    *,
    rate: float,
    up: int,
    effectors: list[str] | None,
    contacts: dict[str, list[list[int]]] | None,
    targets: dict[str, list[list[float]]] | None,
    height_threshold: float,
    speed_threshold: float | None,
    frames: _Frames | None = None,
    clip: str = "clip",
) -> tuple[dict[int, list[tuple[int, int]]], dict[int, np.ndarray], list[tuple[int, int, int]]]:
    """Contact runs and explicit targets of each effector in one clip, at model frames.

    Parameters
    ----------
    sk : Skeleton
    pos : (F, J, 3) float ndarray
        Joint positions of the sampled clip.
    eff_all : list of int
        Effector joints.
    rate : float
    up : int
        Up axis index.
    effectors, contacts, targets, height_threshold, speed_threshold
        As in the ``ik`` stage (``contacts`` and ``targets`` frames at the output rate).
    frames : _Frames, optional
        The model and output rates (default: both ``rate``).
    clip : str
        Clip name, for errors.

    Returns
    -------
    runs_of : dict
        ``effector -> [(start, stop), ...]`` contact model-frame ranges (given or detected).
    fixed : dict
        ``effector -> (F, 3)`` explicit targets at model frames (NaN where none).
    given : list of (int, int, int)
        ``(effector, exported frame as given, model frame)`` of each explicit target.

    Raises
    ------
    IKError
        Malformed rows, a target frame outside the exported clip, two targets of one
        effector on one model frame.
    """
    frames = frames or _Frames(rate=float(rate), output_rate=float(rate))
    F = pos.shape[0]
    n_out = frames.n_exported(F)
    given: list[tuple[int, int, int]] = []
    auto = {j for g in _auto_effectors(sk) for j in g}  # detected by default: feet only
    hz = [a for a in range(3) if a != up]
    runs_of: dict[int, list[tuple[int, int]]] = {}
    fixed = {e: np.full((F, 3), np.nan) for e in eff_all}
    for e in eff_all:
        name = sk.names[e]
        p = pos[:, e]
        if contacts and name in contacts:
            runs = [_contact_run(row, name, frames, F) for row in contacts[name]]
        elif name in effectors if effectors is not None else e in auto:
            floor = float(np.percentile(p[:, up], 5))
            v = (np.linalg.norm(np.gradient(p[:, hz], axis=0), axis=1) * rate
                 if F > 1 else np.zeros(F))
            s_thr = (max(0.5, float(np.median(v))) if speed_threshold is None
                     else speed_threshold)
            runs = true_runs((p[:, up] < floor + height_threshold) & (v < s_thr),
                             min_length=2)
        else:
            runs = []
        runs_of[e] = [(a, b) for a, b in runs if b > a]
        if targets and name in targets:
            for row in targets[name]:
                if len(row) != 4:
                    raise IKError(f"ik.targets.{name}: rows must be [frame, x, y, z]")
                fr = int(row[0])
                if fr != row[0]:
                    raise IKError(f"ik.targets.{name}: frame {row[0]} is not a frame number")
                if not 0 <= fr < n_out:
                    raise IKError(
                        f"ik.targets.{name}: frame {fr} outside {clip}'s exported frames "
                        f"0..{n_out - 1}{frames.note()}"
                    )
                t = frames.to_model(fr)
                if np.isfinite(fixed[e][t]).all():
                    other = next(g for j, g, u in given if j == e and u == t)
                    raise IKError(
                        f"ik.targets.{name}: frames {other} and {fr} fall on one model frame "
                        f"{t} (model {frames.rate:g} fps, export {frames.output_rate:g} fps)"
                    )
                fixed[e][t] = row[1:4]
                given.append((e, fr, t))
    return runs_of, fixed, given


def _contact_run(row: Any, name: str, frames: _Frames, F: int) -> tuple[int, int]:
    """A given ``[start, stop]`` of exported frames as a model-frame range clipped to ``F``.

    Both ends go to the nearest model frame; a non-empty range keeps at least one.
    """
    if not (isinstance(row, (list, tuple)) and len(row) == 2):
        raise IKError(f"ik.contacts.{name}: ranges must be [start, stop], got {row!r}")
    a, b = int(row[0]), int(row[1])
    ma, mb = frames.to_model(a), frames.to_model(b)
    if b > a:
        mb = max(mb, ma + 1)
    return max(0, ma), min(F, mb)


def _clean_clip(
    clips: Clips,
    c: int,
    pos: np.ndarray,
    grot: np.ndarray,
    limbs: list[Limb],
    eff_all: list[int],
    runs_of: dict[int, list[tuple[int, int]]],
    fixed: dict[int, np.ndarray],
    given: list[tuple[int, int, int]],
    *,
    contacts: dict[str, list[list[int]]] | None,
    solver: _Solver,
    frames: _Frames,
    ctx: Context,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Clip ``c`` with every limb cleaned; its varying DOFs ``(F, D)`` and its report entry
    (frame numbers at the output rate, see the ``ik`` stage)."""
    sk = clips.skeleton
    full = clips.full(c)
    errs: dict[str, list[float]] = {sk.names[e]: [] for e in eff_all}
    reached: dict[str, list[float]] = {sk.names[e]: [] for e in eff_all}
    held: dict[str, list[int]] = {sk.names[e]: [] for e in eff_all}
    target_errors: dict[tuple[int, int], tuple[float | None, bool]] = {}
    unreachable: list[dict[str, Any]] = []
    new = full.copy()
    for limb in limbs:
        if limb.dof_columns.size == 0:
            ctx.warn(f"limb {[sk.names[e] for e in limb.effectors]} has no varying DOF")
            continue
        manual = [bool(contacts) and sk.names[e] in contacts for e in limb.effectors]
        angles = _chain_angles(sk, limb, clips.dof_names, full)
        _clean_limb(sk, limb, full, new, angles, pos, grot, runs_of, fixed, manual, solver,
                    errs=errs, reached=reached, unreachable=unreachable, held=held,
                    target_errors=target_errors)
    unreachable = sorted(
        ({"frame": frames.to_exported(u["model_frame"]), **u} for u in unreachable),
        key=lambda u: (u["model_frame"], u["effectors"]),
    )
    if unreachable:
        ctx.warn(_unreachable_summary(clips.names[c], unreachable, frames))
    ranges = {k: _exported_ranges(v, frames) for k, v in held.items()}
    report = {
        "name": clips.names[c],
        "output_frames": frames.n_exported(full.shape[0]),
        "constrained": ranges,
        "constrained_frames": {k: sum(b - a for a, b in v) for k, v in ranges.items()},
        "max_error": {k: (max(v) if v else 0.0) for k, v in errs.items()},
        "max_error_reached": {k: (max(v) if v else 0.0) for k, v in reached.items()},
        "mean_error": {k: (float(np.mean(v)) if v else 0.0) for k, v in errs.items()},
        "targets": [
            {"effector": sk.names[e], "frame": fr, "model_frame": t,
             "exported_frame": frames.to_exported(t),
             "error": target_errors.get((e, t), (None, False))[0],
             "reached": target_errors.get((e, t), (None, False))[1]}
            for e, fr, t in given
        ],
        "unreachable": unreachable,
    }
    return new[:, clips.varying], report


def _exported_ranges(model_frames: list[int], frames: _Frames) -> list[list[int]]:
    """Runs of model frames as ``[start, stop]`` exported-frame ranges (``stop`` excluded).

    A run ``t0..t1`` covers the exported frames in its time span (:meth:`_Frames.span`;
    at a higher output rate those between model frames are interpolated from
    constrained ones); ranges that touch or overlap at the output rate are joined.
    """
    ts = np.unique(np.asarray(model_frames, dtype=np.int64))
    if ts.size == 0:
        return []
    cut = np.flatnonzero(np.diff(ts) > 1) + 1
    out: list[list[int]] = []
    for r in np.split(ts, cut):
        a, b = frames.span(int(r[0]), int(r[-1]))
        if out and a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return out


def _limb_run_ids(limb: Limb, runs_of: dict[int, list[tuple[int, int]]], F: int) -> np.ndarray:
    """``(F, E)`` index of each effector's contact run at each frame (-1: none)."""
    run_id = np.full((F, len(limb.effectors)), -1)
    for k, e in enumerate(limb.effectors):
        for r, (a, b) in enumerate(runs_of[e]):
            run_id[a:b, k] = r
    return run_id


def _frame_targets(
    limb: Limb,
    t: int,
    run_id: np.ndarray,
    depth: list[int],
    manual: list[bool],
    fixed: dict[int, np.ndarray],
    planted: dict[tuple[int, int], np.ndarray],
) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Targets ``(E, 3)`` of the limb's effectors at frame ``t`` (NaN: free) and new contacts.

    Explicit targets are all held; of the detected contacts only the deepest
    (toe over ankle) is, so the foot can roll about it; manual contacts are
    always held.  A contact run not yet planted is returned as pending
    ``(effector, run)`` (planted where the effector ends up this frame).
    """
    T = np.full((len(limb.effectors), 3), np.nan)
    pending = []
    touching = [k for k in range(len(limb.effectors)) if run_id[t, k] >= 0]
    held = max(touching, key=lambda k: depth[k]) if touching else -1
    for k, e in enumerate(limb.effectors):
        if np.isfinite(fixed[e][t]).all():
            T[k] = fixed[e][t]
        elif run_id[t, k] >= 0 and (k == held or manual[k]):
            key = (k, int(run_id[t, k]))
            if key in planted:
                T[k] = planted[key]
            else:
                pending.append(key)
    return T, pending


def _lift_off(run_id: np.ndarray, t: int, active: np.ndarray, manual: list[bool]) -> None:
    """End the detected contact runs of the ``active`` effectors after frame ``t``."""
    for k in np.flatnonzero(active):
        r = run_id[t, k]
        if r >= 0 and not manual[k]:
            run_id[t + 1 :, k] = np.where(run_id[t + 1 :, k] == r, -1, run_id[t + 1 :, k])


def _clean_limb(
    sk: Skeleton,
    limb: Limb,
    full: np.ndarray,
    new: np.ndarray,
    angles: np.ndarray,
    pos: np.ndarray,
    grot: np.ndarray,
    runs_of: dict[int, list[tuple[int, int]]],
    fixed: dict[int, np.ndarray],
    manual: list[bool],
    solver: _Solver,
    *,
    errs: dict[str, list[float]],
    reached: dict[str, list[float]],
    unreachable: list[dict[str, Any]],
    held: dict[str, list[int]] | None = None,
    target_errors: dict[tuple[int, int], tuple[float, bool]] | None = None,
) -> None:
    """Solve one limb frame by frame into ``new`` (Lau Eq. 7), easing back after contacts.

    Parameters
    ----------
    sk : Skeleton
    limb : Limb
    full : (F, D_all) float ndarray
        Sampled DOFs of the clip.
    new : (F, D_all) float ndarray
        Cleaned DOFs, updated in place (the limb's columns).
    angles : (F, J_c, 3) float ndarray
        Sampled Euler angles of the chain (:func:`_chain_angles`).
    pos, grot : (F, J, 3), (F, J, 4) float ndarray
        Sampled joint positions and global rotations.
    runs_of, fixed
        From :func:`_clip_constraints`.
    manual : list of bool
        Per effector: its contacts were given (never lifted off).
    solver : _Solver
    errs, reached, unreachable
        Per-effector errors, errors on reached frames and unreachable frames
        (``model_frame``, ``effectors``, ``error``), appended to.
    held : dict, optional
        Per effector name: its constrained model frames, appended to.
    target_errors : dict, optional
        ``(effector, model frame) -> (error, reached)`` of the explicit targets, set.
    """
    held = {} if held is None else held
    target_errors = {} if target_errors is None else target_errors
    cols = limb.dof_columns
    F = full.shape[0]
    depth = [len(limb_of(sk, e)) for e in limb.effectors]
    run_id = _limb_run_ids(limb, runs_of, F)
    planted: dict[tuple[int, int], np.ndarray] = {}  # (effector, run) -> target
    offset, since = None, 0
    n_blend = solver.n_blend
    for t in range(F):
        qbar = full[t, cols]
        qprev = None
        if t >= 2:
            qprev = 2 * new[t - 1, cols] - new[t - 2, cols]
        elif t == 1:
            qprev = new[0, cols]
        T, pending = _frame_targets(limb, t, run_id, depth, manual, fixed, planted)
        act = np.isfinite(T).all(axis=-1)
        if not act.any() and not pending:
            # after a contact: ease the correction back to the sample
            if offset is not None and since < n_blend:
                since += 1
                new[t, cols] = qbar + offset * 0.5 * (1 + np.cos(np.pi * since / n_blend))
            continue
        fk = _ChainFK(sk, limb, angles[t], grot[t, limb.top_parent], pos[t, limb.top_parent])
        if act.any():
            q, err, ok = _solve_frame(fk, qbar, qprev, T, act, solver)
            if not ok:
                names = [sk.names[e] for k, e in enumerate(limb.effectors) if act[k]]
                unreachable.append({"model_frame": t, "effectors": names, "error": err})
                if err > solver.release:  # lift off: end these detected contacts here
                    _lift_off(run_id, t, act, manual)
        else:
            w1, w2 = solver.w1, solver.w2
            q = qbar if qprev is None else (w1 * qbar + w2 * qprev) / (w1 + w2)
            ok = True
        new[t, cols] = q
        P = fk(q[None])[0]
        offset, since = new[t, cols] - qbar, 0
        for key in pending:  # a contact starts: plant where the effector is now
            planted[key] = P[key[0]].copy()
            errs[sk.names[limb.effectors[key[0]]]].append(0.0)
            reached[sk.names[limb.effectors[key[0]]]].append(0.0)
            held.setdefault(sk.names[limb.effectors[key[0]]], []).append(t)
        for k, e in enumerate(limb.effectors):
            if act[k]:
                err_k = float(np.linalg.norm(P[k] - T[k]))
                errs[sk.names[e]].append(err_k)
                held.setdefault(sk.names[e], []).append(t)
                if ok:
                    reached[sk.names[e]].append(err_k)
                if np.isfinite(fixed[e][t]).all():
                    target_errors[(e, t)] = (err_k, err_k <= solver.tolerance)


def _chain_angles(sk: Skeleton, limb: Limb, names: list[str], full: np.ndarray) -> np.ndarray:
    """Euler angles ``(F, J_c, 3)`` of the chain joints (padded channel order)."""
    col = {n: i for i, n in enumerate(names)}
    F = full.shape[0]
    out = np.zeros((F, len(limb.joints), 3))
    for k, j in enumerate(limb.joints):
        for s, a in enumerate(sk.rotation_order(j)):
            c = col.get(f"{sk.names[j]}:{a}rotation")
            if c is not None:
                out[:, k, s] = full[:, c]
    return out


def _frame_ranges(model_frames: list[int], frames: _Frames | None = None) -> str:
    """``[3, 4, 5, 9]`` → ``"frames 3-5, frame 9"`` (runs of model frames, named by their
    first and last exported frame numbers when ``frames`` is given)."""
    out = frames.to_exported if frames is not None else int
    ranges = _exported_ranges(model_frames, _Frames(1.0, 1.0))
    return ", ".join(
        f"frame {out(a)}" if b == a + 1 else f"frames {out(a)}-{out(b - 1)}" for a, b in ranges
    )


def _unreachable_summary(name: str, unreachable: list[dict[str, Any]],
                         frames: _Frames | None = None) -> str:
    """One warning per clip: the unreachable frames per effector set (exported frame
    numbers) and the worst miss."""
    by_effectors: dict[str, list[dict[str, Any]]] = {}
    for u in unreachable:
        by_effectors.setdefault(", ".join(u["effectors"]), []).append(u)
    parts = [
        f"{eff} at {_frame_ranges([u['model_frame'] for u in us], frames)} "
        f"(up to {max(u['error'] for u in us) * 1000:.1f} mm off)"
        for eff, us in by_effectors.items()
    ]
    note = frames.note() if frames is not None else ""
    return f"{name}: target unreachable, best effort: {'; '.join(parts)}{note}"
