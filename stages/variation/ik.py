"""Inverse-kinematics clean-up of sampled variants (Lau, Bar-Joseph & Kuffner 2009, §7).

Every DOF track ``q`` of a clip minimises, summed over its frames (Lau Eq. 7;
paper and default weights w₁ = 1, w₂ = 5)

    w₁ ‖q − q̄‖² + w₂ ‖q − 2 q₋₁ + q₋₂‖²

with ``q̄`` the network's predicted mean of each frame (the ``sample`` stage's
``predicted`` output, wired as the ``predicted`` input; unwired: the sample
itself), every rotation DOF within joint limits learned from the inputs, and
each limb's effectors at their targets.  The numerics are in
:mod:`~mocapflow.stages.variation.ik_solver`: the DOFs without constraints by
:func:`~mocapflow.stages.variation.ik_solver.eq7_track`, each constrained limb
over the whole clip by :func:`~mocapflow.stages.variation.ik_solver.solve_limb`
(targets as stiff penalties, ``stiffness``).  The ``ik`` stage detects the
contacts of each clip (:func:`_clip_constraints`) and cleans it
(:func:`_clean_clip`).

Departures from the paper, stated
    The paper solves frame by frame; here the sum over the clip is minimised
    at once, so the smoothness term sees both sides of a frame and a contact
    eases in and out without ringing (frame by frame, IK doubled the sample's
    jerk).  Joint limits are added as bounds: each Euler channel of a non-root
    joint stays within the inputs' range (``attrs["input_range"]``, set by
    the ``sample`` stage) widened by ``range_margin`` (at most ``range_fraction``
    of the DOF's own range, so a channel the inputs hold still stays still),
    which keeps a knee from bending backwards.  ``w₂`` weighs second differences of frames at 60 fps
    (the paper's rate) and is scaled to the model's rate (:data:`W2_RATE`).
Limbs and targets
    The limb of an effector joint is the chain of its ancestors up to (not
    including) the first joint with several children or the root; only the
    chain's varying DOFs move for its targets (the rest of the body is the
    unconstrained solve).  Foot contacts are detected automatically per
    effector (ankle and toe of each foot) on the unconstrained solve: height
    below the floor + ``height_threshold`` and horizontal speed below
    ``speed_threshold``, the floor being the 5th percentile of the effector's
    height over its frames below that speed (over all frames, a swing that
    dips low set it: the figure-8 walk's variants lost whole toe stances);
    runs closer than ``contact_gap`` are one stance and runs shorter than
    ``min_contact`` are dropped.  Each contact is held over its whole run at
    one target, the effector's mean position over the run, so the foot stays
    planted for the stance and rolls about the toe once the ankle's run ends;
    the toe then continues along the floor from where the heel's target put
    it, at its own mean height over its run (held at its height at the switch,
    the toe of a foot not yet flat stayed up to 11 cm in the air for the
    stance).  A detected contact keeps the frames the leg reaches: frames it
    misses by more than :data:`DETECTED_WARN` are released and the limb solved
    again, up to ``reach_passes`` times (the report's ``released``; figure-8
    walk, 15 variants: without the release 14 warned of misses up to 92 mm,
    with it 4 of at most 18 mm).  The config can replace the detection
    (``contacts``: frame ranges per joint) or give explicit targets
    (``targets``: ``[frame, x, y, z]`` rows per joint, e.g. for hands), which
    take precedence over a contact on their frame.
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
    run across the joins, and split back; their origins are chained again
    from the cleaned root DOFs (each cycle starts where the one before ends).
    Their ``contacts`` and ``targets`` frames count along that chain; the
    report has one entry for it (``variants``: the variant names).
Unreachable targets
    A target the solve misses by more than ``tolerance`` is reported (the
    limb takes the pose of least cost, best effort; ``given``: a given contact
    or target).  A warning names the variant, frames, effectors and the worst
    miss of the given ones and of detected contacts missed by more than
    :data:`DETECTED_WARN` (1 cm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context, stage
from mocapflow.stages.metrics.quality import jerk_per_frame
from mocapflow.stages.motion.contacts import foot_joint, true_runs
from mocapflow.stages.motion.datatypes import Skeleton
from mocapflow.stages.motion.kinematics import forward_kinematics, motion_positions
from mocapflow.stages.variation.clips import Clips, clips_to_motions, export_rate
from mocapflow.stages.variation.ik_solver import ChainFK, eq7_track, solve_limb
from mocapflow.stages.variation.sample import chain_origins

W2_RATE = 60.0
"""Frames per second at which ``w2`` weighs second differences (the paper's rate): at
``rate`` the weight is ``w2 · (rate / 60)⁴``, the same smoothing in time at any rate."""

GIVEN_WEIGHT = 100.0
"""Weight of a given contact or explicit target relative to a detected contact."""

DETECTED_WARN = 0.01
"""Metres: a detected contact missed by more than this is warned about (all misses beyond
``tolerance`` are in the report)."""

__all__ = [
    "DETECTED_WARN",
    "GIVEN_WEIGHT",
    "IKError",
    "RANGE_FRACTION",
    "Limb",
    "W2_RATE",
    "ik",
    "joint_limits",
    "limb_of",
    "stance_runs",
]

RANGE_FRACTION = 0.5
"""The default ``range_fraction`` of :func:`ik`: a joint limit widens the inputs' range of a DOF
by at most this fraction of that range (:func:`joint_limits`)."""


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



@dataclass(frozen=True)
class _Solver:
    """Settings of the limb solves (the ``ik`` stage's params)."""

    w1: float
    w2: float
    w_ease: float
    tolerance: float
    stiffness: float
    max_iter: int
    reach_passes: int


def joint_limits(
    clips: Clips, margin: float, *, fraction: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of each varying DOF: the inputs' range widened by ``margin``.

    The widening of a DOF is at most ``fraction`` of its own range: a channel
    the inputs hold (nearly) still stays so (the hip twist of the procedural
    walk spans 0.001 rad, ~10 of its standard deviations; widened by 0.025 rad
    the IK turned it 25 ranges out to place the feet, PC1 of the variants' Fig. 6
    at ±45 for inputs within ±6).

    Parameters
    ----------
    clips : Clips
        Variants; their ``attrs["input_range"]`` (from the ``sample`` stage)
        gives the inputs' range; without it (clips not sampled) nothing is bounded.
    margin : float
        Radians added on both sides.
    fraction : float or None
        At most this fraction of the DOF's range is added (``None``: ``margin``
        for every DOF).

    Returns
    -------
    low, high : (D,) float ndarray
        Per trajectory column; ``±inf`` for the root's DOFs and other
        non-rotation DOFs.
    """
    labels = clips.labels
    rng = clips.attrs.get("input_range") or {"dofs": [], "low": [], "high": []}
    lo_of = dict(zip(rng["dofs"], rng["low"]))
    hi_of = dict(zip(rng["dofs"], rng["high"]))
    root = clips.skeleton.names[0] if clips.skeleton is not None else None
    low, high = np.full(len(labels), -np.inf), np.full(len(labels), np.inf)
    for i, n in enumerate(labels):
        joint = n.partition(":")[0]
        if n.endswith("rotation") and joint != root and n in lo_of:
            m = margin if fraction is None else min(margin, fraction * (hi_of[n] - lo_of[n]))
            low[i], high[i] = lo_of[n] - m, hi_of[n] + m
    return low, high


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
    predicted: Clips | None = None,
    *,
    w1: float = 1.0,
    w2: float = 5.0,
    effectors: list[str] | None = None,
    contacts: dict[str, list[list[int]]] | None = None,
    targets: dict[str, list[list[float]]] | None = None,
    height_threshold: float = 0.05,
    speed_threshold: float | None = None,
    min_contact: float = 0.05,
    contact_gap: float = 0.05,
    ease: float = 0.5,
    range_margin: float = 0.025,
    range_fraction: float | None = RANGE_FRACTION,
    stiffness: float = 1e6,
    tolerance: float = 1e-3,
    max_iter: int = 50,
    reach_passes: int = 2,
    mode: Literal["auto", "off"] = "auto",
    output_rate: float | None = None,
    ctx: Context,
) -> dict:
    """IK clean-up of sampled variants: Lau Eq. 7 over each clip, planted feet, joint limits.

    Parameters
    ----------
    variants : Clips
        Sampled variants (pen strokes pass through unchanged).
    predicted : Clips, optional
        The network's predicted mean of every frame (the ``sample`` stage's
        ``predicted``), the ``q̄`` of Lau Eq. 7; same clips and layout as
        ``variants``.  Unwired: ``q̄`` is the sample itself.
    w1, w2 : float
        Closeness and smoothness weights of Lau Eq. 7 (paper: w₁ = 1, w₂ = 5).
        ``w2`` weighs second differences of frames at 60 fps (the paper's
        rate); at another model rate it is scaled by ``(rate / 60)⁴``
        (:data:`W2_RATE`), so it smooths the same in time (at 120 fps, the
        per-frame weight let the sample's noise through: jerk 1.72 × the
        input's after IK on cmu_131_02, 0.68 × scaled).
    effectors : list of str, optional
        Effector joint names for automatic contact detection (default the
        ankle and toe joints of both feet; joints named only in ``contacts`` or
        ``targets`` are not detected).
    contacts : dict, optional
        ``joint -> [[start, stop], ...]`` contact frame ranges (``stop``
        excluded) replacing the detection for that joint (all clips, clipped to
        each clip), each held at the joint's mean position over it.  Frames
        count at the output rate (the exported BVH's 0-based frame numbers) and
        are rounded to the nearest model frame, a range keeping at least one.
    targets : dict, optional
        ``joint -> [[frame, x, y, z], ...]`` explicit targets (metres), added
        to the detected ones (all clips).  ``frame`` is an exported frame number
        (0-based, at the output rate; outside the exported clip: IKError), held
        at the nearest model frame, so exactly met at the exported frames that
        are model frames (every 4th at 30 -> 120 fps).
    height_threshold : float
        Metres above the effector's floor (5th percentile of its height over
        its frames slower than the speed threshold).
    speed_threshold : float, optional
        Horizontal speed (m/s) below which an effector may be in contact;
        default the larger of 0.5 m/s and its median speed.
    min_contact : float
        Seconds; shorter detected contact runs are dropped.
    contact_gap : float
        Seconds; detected runs of one effector closer than this are one contact.
    ease : float
        Seconds over which the correction a target makes eases in and out: the
        correction from the unconstrained solve gets the smoothness weight
        ``w1 · (ease · rate)⁴`` (:func:`~.ik_solver.solve_limb`); 0 is the
        paper's Eq. 7 alone.  The default 0.5 s keeps the jerk of the planted
        feet at the input's (figure-8 walk, ``benchmarks/variation.py``
        sections 2-3: at 0.25 s jerk p99 1.41 x the input's, the joins of 5
        chained cycles 1.54 x; at 0.5 s 1.02 x and 1.35 x); detected contacts
        are then met within a few millimetres rather than one or two.
    range_margin : float
        Radians; each Euler channel of a non-root joint stays within the inputs'
        range widened by this (:func:`joint_limits`).  The default 0.025 keeps the
        exported channels within 0.05 of the inputs' range also for a joint
        near gimbal lock, whose file channels are the other Euler triple of its
        DOFs (``RThumb`` of ``cmu_131_02.bvh``: 0.046 rad; at 0.03: 0.051).
    range_fraction : float or None
        The widening of a DOF is at most this fraction of the inputs' range of
        it (:func:`joint_limits`): a channel the inputs hold still is not used
        to reach the targets (default :data:`RANGE_FRACTION`); ``None``:
        ``range_margin`` for every DOF.
    stiffness : float
        Weight of a detected contact's squared target distance (per m²) against
        Eq. 7's terms: the default 1e6 makes 1 mm off cost as much as 1 rad off
        ``q̄``.  Given ``contacts`` and ``targets`` weigh :data:`GIVEN_WEIGHT`
        (100) times more, so they are met where reachable.
    tolerance : float
        Metres; a constraint met within it counts as reached, others are reported.
    max_iter : int
        Gauss–Newton steps of each limb's solve at most.
    reach_passes : int
        Re-solves of a limb without the frames of detected contacts it missed
        by more than :data:`DETECTED_WARN` (0: every detected frame is held
        however far the leg is from it); given contacts and targets are never
        released.
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
        ``constrained_frames`` (their count), ``released`` (per effector, the
        ranges of detected contact frames released as out of reach; see
        ``reach_passes``), max / mean error (m), max error
        over the frames whose targets were reached, ``targets`` (each given
        target: ``effector``, ``frame`` as given, ``model_frame``,
        ``exported_frame`` where it is held, ``error`` m (null: its limb has
        no varying DOF), ``reached``) and
        ``unreachable`` (``frame``, ``model_frame``, ``effectors``, ``error``,
        ``given``);
        ``jerk_p99`` (m/s³, joint positions pooled over the clips: ``sampled``
        and ``cleaned``), ``qbar`` (``"predicted"`` or ``"sample"``), the
        limbs, ``rate`` (model), ``output_rate`` and the thresholds used.
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
    _check_weights(w1=w1, stiffness=stiffness, w2=w2, ease=ease, range_margin=range_margin,
                   **({} if range_fraction is None else {"range_fraction": range_fraction}))
    if isinstance(reach_passes, bool) or not isinstance(reach_passes, int) or reach_passes < 0:
        raise IKError(f"reach_passes: must be an integer >= 0, got {reach_passes!r}")
    if predicted is not None:
        _check_predicted(variants, predicted)
    sk = variants.skeleton
    up = "xyz".index(variants.attrs.get("up", "y"))
    groups = _effector_groups(sk, effectors, contacts, targets)
    limbs = [_make_limb(variants, g) for g in groups]
    w2_model = w2 * (float(variants.rate) / W2_RATE) ** 4  # the same smoothing in time
    solver = _Solver(w1=w1, w2=w2_model, w_ease=w1 * (ease * float(variants.rate)) ** 4,
                     tolerance=tolerance, stiffness=stiffness, max_iter=max_iter,
                     reach_passes=reach_passes)
    eff_all = sorted({e for g in groups for e in g})
    frames = _Frames(rate=float(variants.rate), output_rate=export_rate(variants))
    rate = float(variants.rate)
    report: dict[str, Any] = {"clips": [], "limbs": [[sk.names[e] for e in g] for g in groups]}
    low, high = joint_limits(variants, range_margin, fraction=range_fraction)
    solved = _played_in_order(variants)
    means = solved if predicted is None else _played_in_order(predicted)
    # Eq. 7 without constraints: every DOF, within its limits
    smooth = solved.replace(trajectories=[eq7_track(t, low, high, w1=w1, w2=w2_model)
                                          for t in means.trajectories])
    lim_all = np.full((2, len(variants.dof_names)), np.inf) * np.array([[-1.0], [1.0]])
    lim_all[:, variants.varying] = low, high
    out_trajs = []
    for c, motion in enumerate(clips_to_motions(smooth)):
        pos, grot = forward_kinematics(
            sk, motion.rotations, motion.root_position, translations=motion.translations
        )
        runs_of, fixed, given = _clip_constraints(
            sk, pos, eff_all, rate=rate, up=up, effectors=effectors, contacts=contacts,
            targets=targets, height_threshold=height_threshold, speed_threshold=speed_threshold,
            min_contact=min_contact, contact_gap=contact_gap, frames=frames,
            clip=solved.names[c],
        )
        traj, clip_report = _clean_clip(smooth, means, c, pos, grot, limbs, eff_all, runs_of,
                                        fixed, given, lim_all, contacts=contacts,
                                        solver=solver, frames=frames, ctx=ctx, up=up)
        out_trajs.append(traj)
        report["clips"].append(clip_report)
    origins = variants.origins
    if solved is not variants:  # the loop's cycles back as the variants they are
        out_trajs = np.split(out_trajs[0], np.cumsum(variants.lengths)[:-1])
        report["clips"][0]["variants"] = list(variants.names)
        # the root DOFs moved: each cycle starts where the cleaned one before it ends
        chained = chain_origins(variants, out_trajs)
        origins = variants.origins if chained is None else chained
    cleaned = variants.replace(trajectories=out_trajs, origins=origins,
                               attrs={**variants.attrs, "ik": True})
    report.update(
        {"w1": w1, "w2": w2, "w2_per_model_frame": w2_model, "height_threshold": height_threshold,
         "speed_threshold": speed_threshold, "min_contact": min_contact,
         "contact_gap": contact_gap, "ease": ease, "range_margin": range_margin,
         "range_fraction": range_fraction, "reach_passes": reach_passes,
         "stiffness": stiffness,
         "tolerance": tolerance, "rate": frames.rate, "output_rate": frames.output_rate,
         "qbar": "sample" if predicted is None else "predicted",
         "jerk_p99": {"sampled": _jerk_p99(solved), "cleaned": _jerk_p99(
             _played_in_order(cleaned))}}
    )
    _key_figures(report, cleaned, ctx)
    return {"variants": cleaned, "report": report}


def _key_figures(report: dict[str, Any], cleaned: Clips, ctx: Context) -> None:
    """The run summary's figures of the clean-up (``ctx.figure``; never in an output)."""
    clips = report["clips"]
    errs = [e for c in clips for e in c["max_error_reached"].values()]
    ctx.figure("variants", cleaned.n_clips)
    ctx.figure("constrained frames", sum(sum(c["constrained_frames"].values()) for c in clips))
    ctx.figure("unreached", sum(len(c["unreachable"]) for c in clips))
    if errs:
        ctx.figure("max reached error mm", round(1000.0 * max(errs), 2))
    j = report["jerk_p99"]
    if j["sampled"] > 0:
        ctx.figure("jerk cleaned/sampled", round(j["cleaned"] / j["sampled"], 3))


def _check_weights(**values: float) -> None:
    """``w1`` and ``stiffness`` finite and > 0, the others finite and >= 0 (else IKError)."""
    for name, v in values.items():
        positive = name in ("w1", "stiffness")
        if not (math.isfinite(v) and (v > 0 if positive else v >= 0)):
            raise IKError(f"{name}: must be a finite number {'>' if positive else '>='} 0, "
                          f"got {v!r}")


def _check_predicted(variants: Clips, predicted: Clips) -> None:
    """``predicted`` has the clips and DOF layout of ``variants`` (else one-line IKError)."""
    if predicted.dof_names != variants.dof_names or predicted.n_clips != variants.n_clips \
            or not np.array_equal(predicted.lengths, variants.lengths):
        raise IKError(
            f"predicted: {predicted.n_clips} clips of {np.asarray(predicted.lengths).tolist()} "
            f"frames and {len(predicted.dof_names)} DOFs do not match the variants' "
            f"{variants.n_clips} of {np.asarray(variants.lengths).tolist()} and "
            f"{len(variants.dof_names)} (wire the same "
            f"sample node's variants and predicted)"
        )


def _jerk_p99(clips: Clips) -> float:
    """p99 of the per-frame joint-position jerk pooled over the clips, m/s³."""
    js = [jerk_per_frame(motion_positions(m), clips.rate) for m in clips_to_motions(clips)]
    j = np.concatenate(js) if js else np.zeros(0)
    j = j[np.isfinite(j)]
    return float(np.percentile(j, 99)) if j.size else 0.0


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
    min_contact: float = 0.0,
    contact_gap: float = 0.0,
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
    effectors, contacts, targets, height_threshold, speed_threshold, min_contact, contact_gap
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
            v = (np.linalg.norm(np.gradient(p[:, hz], axis=0), axis=1) * rate
                 if F > 1 else np.zeros(F))
            s_thr = (max(0.5, float(np.median(v))) if speed_threshold is None
                     else speed_threshold)
            slow = v < s_thr  # the floor of the stances: a fast swing dipping low is not one
            floor = float(np.percentile(p[slow if slow.any() else slice(None), up], 5))
            runs = stance_runs((p[:, up] < floor + height_threshold) & (v < s_thr),
                               gap=int(round(contact_gap * rate)),
                               min_length=max(2, int(round(min_contact * rate))))
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


def stance_runs(mask: np.ndarray, *, gap: int, min_length: int) -> list[tuple[int, int]]:
    """Contact runs of a per-frame contact mask, held as whole stances.

    Parameters
    ----------
    mask : (F,) bool ndarray
        Frames where the effector may be in contact.
    gap : int
        Runs separated by at most this many frames are joined (a noisy stance
        that flickers is one contact).
    min_length : int
        Joined runs shorter than this are dropped.

    Returns
    -------
    list of (int, int)
        Half-open frame ranges, in order.
    """
    runs = true_runs(mask)
    joined: list[tuple[int, int]] = []
    for a, b in runs:
        if joined and a - joined[-1][1] <= gap:
            joined[-1] = (joined[-1][0], b)
        else:
            joined.append((a, b))
    return [(a, b) for a, b in joined if b - a >= min_length]


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
    smooth: Clips,
    means: Clips,
    c: int,
    pos: np.ndarray,
    grot: np.ndarray,
    limbs: list[Limb],
    eff_all: list[int],
    runs_of: dict[int, list[tuple[int, int]]],
    fixed: dict[int, np.ndarray],
    given: list[tuple[int, int, int]],
    limits: np.ndarray,
    *,
    contacts: dict[str, list[list[int]]] | None,
    solver: _Solver,
    frames: _Frames,
    ctx: Context,
    up: int = 1,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Clip ``c`` with every constrained limb solved; its varying DOFs ``(F, D)`` and its
    report entry (frame numbers at the output rate, see the ``ik`` stage).

    Parameters
    ----------
    smooth : Clips
        The unconstrained Eq. 7 solve (:func:`eq7_track`) of every clip.
    means : Clips
        The ``q̄`` of every clip.
    c : int
    pos, grot : (F, J, 3), (F, J, 4) float ndarray
        Joint positions and global rotations of ``smooth``'s clip ``c``.
    limbs : list of Limb
    eff_all : list of int
    runs_of, fixed, given
        From :func:`_clip_constraints`.
    limits : (2, D_all) float ndarray
        Joint limits of every DOF (:func:`joint_limits`; ``±inf`` for constants).
    contacts : dict or None
        The ``ik`` stage's ``contacts`` (joints whose contacts were given).
    solver : _Solver
    frames : _Frames
    ctx : Context
    up : int
        Up axis index.
    """
    sk = smooth.skeleton
    full, qbar = smooth.full(c), means.full(c)
    errs: dict[str, list[float]] = {sk.names[e]: [] for e in eff_all}
    reached: dict[str, list[float]] = {sk.names[e]: [] for e in eff_all}
    held: dict[str, list[int]] = {sk.names[e]: [] for e in eff_all}
    released: dict[str, list[int]] = {sk.names[e]: [] for e in eff_all}
    target_errors: dict[tuple[int, int], tuple[float | None, bool]] = {}
    unreachable: list[dict[str, Any]] = []
    new = full.copy()
    for limb in limbs:
        manual = [bool(contacts) and sk.names[e] in contacts for e in limb.effectors]
        fr, ef, tg, wt = _limb_constraints(sk, limb, pos, runs_of, fixed, manual, up=up)
        if limb.dof_columns.size == 0:
            ctx.warn(f"limb {[sk.names[e] for e in limb.effectors]} has no varying DOF")
            continue
        if fr.size == 0:
            continue
        cols = limb.dof_columns
        fk = ChainFK(sk, limb.joints, limb.dof_slots, limb.effectors,
                     _chain_angles(sk, limb, smooth.dof_names, full),
                     grot[:, limb.top_parent], pos[:, limb.top_parent])
        res = solve_limb(fk, full[:, cols], qbar[:, cols], limits[0, cols], limits[1, cols],
                         fr, ef, tg, wt, w1=solver.w1, w2=solver.w2, w_ease=solver.w_ease,
                         stiffness=solver.stiffness,
                         max_iter=solver.max_iter)
        for _ in range(solver.reach_passes):
            # a detected contact keeps the frames the leg reaches: frames missed by more than
            # DETECTED_WARN are released and the limb solved again without them
            drop = (res.error > DETECTED_WARN) & (wt < GIVEN_WEIGHT)
            if not drop.any():
                break
            for k, t in zip(ef[drop].tolist(), fr[drop].tolist()):
                released[sk.names[limb.effectors[k]]].append(t)
            fr, ef, tg, wt = fr[~drop], ef[~drop], tg[~drop], wt[~drop]
            res = solve_limb(fk, full[:, cols], qbar[:, cols], limits[0, cols],
                             limits[1, cols], fr, ef, tg, wt, w1=solver.w1, w2=solver.w2,
                             w_ease=solver.w_ease, stiffness=solver.stiffness,
                             max_iter=solver.max_iter)
        new[:, cols] = res.q
        ok = res.error <= solver.tolerance
        for k, e in enumerate(limb.effectors):
            name, mine = sk.names[e], ef == k
            errs[name] += res.error[mine].tolist()
            held[name] += fr[mine].tolist()
            reached[name] += res.error[mine & ok].tolist()
            explicit = mine & np.isfinite(fixed[e][fr]).all(axis=1)
            for t, err, good in zip(fr[explicit].tolist(), res.error[explicit].tolist(),
                                    ok[explicit].tolist()):
                target_errors[(e, t)] = (err, good)
        for t in np.unique(fr[~ok]).tolist():
            at = fr == t
            unreachable.append({"model_frame": t,
                                "effectors": [sk.names[limb.effectors[k]] for k in ef[at]],
                                "error": float(res.error[at].max()),
                                "given": bool((wt[at] >= GIVEN_WEIGHT).any())})
    unreachable = sorted(
        ({"frame": frames.to_exported(u["model_frame"]), **u} for u in unreachable),
        key=lambda u: (u["model_frame"], u["effectors"]),
    )
    # a detected contact is best effort: misses under DETECTED_WARN are reported, not warned
    loud = [u for u in unreachable if u["given"] or u["error"] > DETECTED_WARN]
    if loud:
        ctx.warn(_unreachable_summary(smooth.names[c], loud, frames),
                 hint="the variant keeps the nearest pose it reaches (its report lists each "
                      "miss); if a foot slides visibly, check ik.contacts / ik.targets at "
                      "those frames or lower the sampling sigma")
    ranges = {k: _exported_ranges(v, frames) for k, v in held.items()}
    report = {
        "name": smooth.names[c],
        "output_frames": frames.n_exported(full.shape[0]),
        "constrained": ranges,
        "constrained_frames": {k: sum(b - a for a, b in v) for k, v in ranges.items()},
        "released": {k: _exported_ranges(v, frames) for k, v in released.items()},
        "max_error": {k: (max(v) if v else 0.0) for k, v in errs.items()},
        "max_error_reached": {k: (max(v) if v else 0.0) for k, v in reached.items()},
        "mean_error": {k: (float(np.mean(v)) if v else 0.0) for k, v in errs.items()},
        "targets": [
            {"effector": sk.names[e], "frame": fr_, "model_frame": t,
             "exported_frame": frames.to_exported(t),
             "error": target_errors.get((e, t), (None, False))[0],
             "reached": target_errors.get((e, t), (None, False))[1]}
            for e, fr_, t in given
        ],
        "unreachable": unreachable,
    }
    return new[:, smooth.varying], report


def _limb_constraints(
    sk: Skeleton,
    limb: Limb,
    pos: np.ndarray,
    runs_of: dict[int, list[tuple[int, int]]],
    fixed: dict[int, np.ndarray],
    manual: list[bool],
    up: int = 1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The constraints of one limb: frames ``(N,)``, effector slots ``(N,)``, targets
    ``(N, 3)`` and weights ``(N,)`` (1 for a detected contact, :data:`GIVEN_WEIGHT` for a
    given contact or target).

    Of the detected contacts of the limb, each frame holds only the deepest
    touching effector (the toe while it touches, else the ankle), so the foot
    rolls about its heel and then its ball; each stretch of frames holding
    one effector in one run holds it at its mean position over the stretch
    (in ``pos``), except a stretch that takes over from another effector's
    without a gap: its target is where the last target put the foot (its
    position in ``pos`` at the switch, moved as the last effector was) along
    the floor, at its mean height over the stretch (axis ``up``).
    Given contacts (``manual``) are held over their whole run at its mean;
    an explicit target replaces a contact on its frame.
    """
    F = pos.shape[0]
    E = len(limb.effectors)
    depth = np.array([len(limb_of(sk, e)) for e in limb.effectors])
    run_id = np.full((F, E), -1)
    explicit = np.zeros((F, E), dtype=bool)
    for k, e in enumerate(limb.effectors):
        for r, (a, b) in enumerate(runs_of[e]):
            run_id[a:b, k] = r
        explicit[:, k] = np.isfinite(fixed[e]).all(axis=1)
    detected = (run_id >= 0) & ~np.asarray(manual, dtype=bool)[None, :]
    deepest = np.where(detected, depth[None, :], -1)
    keep = detected & (deepest == deepest.max(axis=1, keepdims=True))
    keep &= np.cumsum(keep, axis=1) == 1  # one effector per frame (the first of equal depth)
    held = (keep | ((run_id >= 0) & ~detected)) & ~explicit
    stretches = []  # (start, stop, effector slot): one effector held in one run
    for k in range(E):
        for a, b in true_runs(held[:, k]):
            cuts = np.flatnonzero(np.diff(run_id[a:b, k])) + 1 + a
            stretches += [(int(u), int(v), k) for u, v in zip(np.r_[a, cuts], np.r_[cuts, b])]
    fr, ef, tg, wt = [], [], [], []
    last: tuple[int, int, np.ndarray] | None = None  # (stop, slot, target) of the last stretch
    for u, v, k in sorted(stretches):
        e = limb.effectors[k]
        if last is not None and last[0] == u and last[1] != k:
            # the foot rolls onto another effector: its target continues the last one's
            # (the foot at the switch as the last target put it), so nothing jumps along
            # the floor, ...
            prev = limb.effectors[last[1]]
            target = pos[u - 1, e] + last[2] - pos[u - 1, prev]
            target[up] = pos[u:v, e, up].mean()  # ... on the effector's stance height
        else:
            target = pos[u:v, e].mean(axis=0)
        fr.append(np.arange(u, v))
        ef.append(np.full(v - u, k))
        tg.append(np.broadcast_to(target, (v - u, 3)))
        wt.append(np.full(v - u, GIVEN_WEIGHT if manual[k] else 1.0))
        last = (v, k, target)
    for k, e in enumerate(limb.effectors):
        t = np.flatnonzero(explicit[:, k])
        fr.append(t)
        ef.append(np.full(t.size, k))
        tg.append(fixed[e][t])
        wt.append(np.full(t.size, GIVEN_WEIGHT))
    if not fr:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
    return (np.concatenate(fr).astype(np.int64), np.concatenate(ef).astype(np.int64),
            np.concatenate(tg).reshape(-1, 3), np.concatenate(wt))


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
    """``[3, 4, 5, 9]`` → ``"frames 3-5, frame 9"``: runs of model frames as the exported
    frames in their time span when ``frames`` is given (:func:`_exported_ranges`; runs that
    meet at the output rate are one)."""
    ranges = _exported_ranges(model_frames, frames or _Frames(1.0, 1.0))
    return ", ".join(f"frame {a}" if b == a + 1 else f"frames {a}-{b - 1}" for a, b in ranges)


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

