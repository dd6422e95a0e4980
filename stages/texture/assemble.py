"""A motion from a source track: copy, smooth the seams, place the root, pin the feet.

:func:`assemble_motion` turns the finest source track of the synthesis (the
input frame copied into each output frame) into a motion on the input skeleton:

1. the joint rotations and root features (yaw rate, heading-frame velocity,
   height, translations) of each source frame are copied from level 0 of the
   pyramid (:func:`_input_features`);
2. each seam is cross-faded between the two input lines it joins
   (:func:`~mocapflow.stages.texture.smoothing.transition_blend`, ``transition_blend``
   seconds; an addition to the thesis), then the seams are smoothed adaptively
   (:func:`_smooth_seams` →
   :func:`~mocapflow.stages.texture.smoothing.adaptive_smoothing`, Moradoff
   §3.8); seam accelerations below ``ACCEL_FLOOR`` × the input's median
   acceleration pass the test, and — an addition to the thesis' test — seams
   also fail while their jerk exceeds ``jerk_tolerance`` × the input's p99 jerk;
3. the root velocity is corrected so that stance toes move as in the input
   (:func:`_planted_velocity` → :func:`~mocapflow.stages.texture.root.plant_feet`);
4. the root is integrated, the first constraint (else output frame 0) placed
   at its input frame's world position and heading, or steered along a path
   (:func:`_place_root` → :func:`~mocapflow.stages.texture.root.integrate_root`,
   :func:`~mocapflow.stages.texture.root.follow_path`, Moradoff §3.10; a loop
   on a closed path paced to whole laps, a warning beyond ``PACE_TOLERANCE``);
5. the residual slide of stance toes is pinned by two-bone leg IK
   (:func:`_foot_ik` → :func:`~mocapflow.stages.texture.root.foot_corrections`,
   :func:`~mocapflow.stages.texture.root.apply_foot_ik`); on a path with the
   :data:`PATH_IK` weights (the legs take up the turned, paced root);
6. the errors at the constrained frames are measured (:func:`_constraint_errors`).

:func:`smooth_level` smooths the output of a coarser level in the same way, in that
level's representation (``smooth_levels="every"`` of the ``synth`` stage).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from mocapflow.stages.metrics.quality import acceleration_per_frame, jerk_p99, seams_from_source
from mocapflow.stages.motion.contacts import contact_thresholds, foot_contacts, toe_indices
from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.motion.kinematics import motion_positions
from mocapflow.stages.motion.rotations import (
    heading_split,
    quat_angle,
    quat_multiply,
    quat_rotate,
    yaw_quaternion,
)
from mocapflow.stages.texture.pyramid import Pyramid, PyramidLevel, level_positions
from mocapflow.stages.texture.root import (
    PACE_TOLERANCE,
    PathCurve,
    apply_foot_ik,
    chain_kinematics,
    follow_path,
    foot_corrections,
    integrate_root,
    leg_chains,
    plant_feet,
    rotate_xz,
    toe_displacements,
)
from mocapflow.stages.texture.smoothing import SMOOTHING_RATE, adaptive_smoothing, rate_scale
from mocapflow.stages.texture.smoothing import (  # (the stage param has the name)
    transition_blend as blend_transitions,
)

__all__ = ["ACCEL_FLOOR", "PATH_IK", "assemble_motion", "smooth_level"]

#: Seam accelerations below this fraction of the input's median acceleration pass the test.
ACCEL_FLOOR = 0.25

#: ``foot_corrections`` weights on a path: a root turned onto the path and paced to it
#: needs leg corrections that grow through a whole stance (the stride change), which
#: the default decay (0.01) pulls back; on the figure-8 walk looped on a figure-8 path
#: the toe-skate ratio is 1.57-1.83 with the defaults, 0.73-0.82 with these.
PATH_IK = {"stiffness": 0.1, "decay": 0.001}


def _input_features(pyramid: Pyramid) -> tuple[np.ndarray, np.ndarray]:
    """Level 0 rotations ``(F, J, 4)`` and root features ``(F, D)`` (yaw rate, velocity,
    height, translations)."""
    lev = pyramid.levels[0]
    parts = [lev.yaw_rate[:, None], lev.velocity, lev.height[:, None]]
    if lev.translations is not None:
        parts.append(lev.translations.reshape(lev.n_nodes, -1))
    return lev.rotations, np.concatenate(parts, axis=1)


def _smooth_seams(
    skeleton,
    rate: float,
    rot: np.ndarray,
    feat: np.ndarray,
    seams: np.ndarray,
    constrained: list[int],
    loop: bool,
    *,
    gaussian_width: int,
    accel_tolerance: float,
    max_widening: int,
    jerk_tolerance: float | None,
    warn,
    world_in: np.ndarray,
    jerk_reach: int = 1,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Adaptive smoothing of the seams with the input's acceleration floor and jerk limit
    (``world_in``: the input's joint positions at ``rate``, :func:`motion_positions`;
    ``jerk_reach``: frames at 30 fps each side of a seam whose jerk is tested).

    Returns
    -------
    rotations : (L, J, 4) float ndarray
    features : (L, D) float ndarray
    report : dict
        ``widening``, ``passed``, ``seam_acc``, ``ref_acc`` per seam.
    """
    n_in = world_in.shape[0]
    acc_in = acceleration_per_frame(world_in, rate)
    floor = ACCEL_FLOOR * float(np.nanmedian(acc_in)) if n_in > 2 else 0.0
    jerk_limit = None
    if jerk_tolerance is not None and n_in > 8:
        jerk_limit = jerk_tolerance * jerk_p99(world_in, rate)
    sm = adaptive_smoothing(
        skeleton,
        rot,
        feat,
        seams,
        rate,
        constrained=constrained,
        cyclic=loop,
        gaussian_width=gaussian_width,
        accel_tolerance=accel_tolerance,
        accel_floor=floor,
        max_widening=max_widening,
        jerk_limit=jerk_limit,
        jerk_reach=jerk_reach,
    )
    failed = seams[~sm.passed]
    if failed.size:
        warn(
            f"{failed.size} of {seams.size} seams still fail the acceleration test after "
            f"widening to k={max_widening} (output frames {failed[:10].tolist()})"
        )
    report = dict(
        widening=sm.widening.tolist(),
        passed=sm.passed.tolist(),
        seam_acc=sm.seam_acc.tolist(),
        ref_acc=sm.ref_acc.tolist(),
    )
    return sm.rotations, sm.features, report


def smooth_level(
    pyramid: Pyramid,
    skeleton,
    level: int,
    source: np.ndarray,
    *,
    constrained: list[int] = (),
    loop: bool = False,
    gaussian_width: int = 5,
    accel_tolerance: float = 1.0,
    max_widening: int = 12,
    jerk_tolerance: float | None = 1.0,
) -> PyramidLevel:
    """The output of one coarser level with its seams smoothed (Moradoff §3.8, after
    every level).

    The level's representation is smoothed: its nodes are frames at ``rate / 2**level``
    (joint rotations, root as per-node yaw and heading-frame velocity, height), tested
    and smoothed as the finest level is (:func:`_smooth_seams`, frame counts in nodes, as
    the thesis filters every level), against the acceleration floor and jerk of the
    input's own level.

    Parameters
    ----------
    pyramid : Pyramid
    skeleton : Skeleton
        The input's.
    level : int
        Pyramid level of ``source``.
    source : (n,) int ndarray
        Input node copied at each output node of the level.
    constrained : sequence of int
        Output nodes pinned (the constraints' anchors ``j >> level``).
    loop : bool
    gaussian_width, accel_tolerance, max_widening, jerk_tolerance :
        As :func:`assemble_motion`.

    Returns
    -------
    PyramidLevel
        ``n`` output nodes: smoothed rotations, root features and the 3-D pose
        representation (:func:`~mocapflow.stages.texture.pyramid.level_positions`).
    """
    lev = pyramid.levels[level]
    f = 2.0**level
    rate = pyramid.rate / f
    src = np.asarray(source, dtype=np.int64)
    trans = lev.translations
    parts = [f * lev.yaw_rate[:, None], f * lev.velocity, lev.height[:, None]]
    if trans is not None:
        parts.append(trans.reshape(lev.n_nodes, -1))
    feat_in = np.concatenate(parts, axis=1)  # root per node of the level
    rot, feat = lev.rotations[src].copy(), feat_in[src].copy()
    seams = seams_from_source(src, cyclic=loop)
    if seams.size:
        heading, ground = integrate_root(feat_in[:, 0], feat_in[:, 1:3])
        world_in = quat_rotate(yaw_quaternion(heading)[:, None], lev.positions)
        world_in[..., 0] += ground[:, None, 0]
        world_in[..., 2] += ground[:, None, 1]
        rot, feat, _ = _smooth_seams(
            skeleton, rate, rot, feat, seams, list(constrained), loop,
            gaussian_width=gaussian_width, accel_tolerance=accel_tolerance,
            max_widening=max_widening, jerk_tolerance=jerk_tolerance,
            warn=lambda msg: None, world_in=world_in,
        )
    J = skeleton.n_joints
    tr = feat[:, 4:].reshape(-1, J, 3) if feat.shape[1] > 4 else None
    return PyramidLevel(rot, feat[:, 0] / f, feat[:, 1:3] / f, feat[:, 3],
                        level_positions(skeleton, rot, feat[:, 3], tr), tr)


def _input_contacts(motion: Motion, world: np.ndarray):
    """Toe joints and their input contacts ``(F, T)`` (input thresholds), or ``None``
    when the skeleton has no usable toes (``world``: the input's joint positions)."""
    try:
        toes = toe_indices(motion.skeleton)
    except ValueError:
        return None
    h, s = contact_thresholds(world, toes, motion.rate)
    return toes, foot_contacts(world, toes, motion.rate, height_threshold=h, speed_threshold=s)


def _planted_velocity(pyramid, motion, rot, feat, lines, weight, loop, contacts) -> np.ndarray:
    """Root velocities keeping the input's stance toes planted (see ``plant_feet``;
    ``contacts``: :func:`_input_contacts`; ``lines``, ``weight``: the input frames mixed
    at each output frame, :func:`~mocapflow.stages.texture.smoothing.transition_blend`:
    a cross-faded frame's toes move by the same mix of the two lines' displacements and
    are in contact where both lines are)."""
    if contacts is None:
        return feat[:, 1:3]
    toes, contact = contacts
    L = lines.shape[0]
    lev = pyramid.levels[0]
    disp_in = toe_displacements(lev.yaw_rate, lev.velocity, lev.positions[:, toes][..., [0, 2]])
    w = weight[:, None, None]
    disp = (1.0 - w) * disp_in[lines[:, 0]] + w * disp_in[lines[:, 1]]
    J = motion.skeleton.n_joints
    trans = feat[:, 4:].reshape(L, J, 3) if feat.shape[1] > 4 else None
    root = np.zeros((L, 3))  # heading-free, as level_positions
    root[:, 1] = feat[:, 3]
    local = chain_kinematics(motion.skeleton, rot, root, toes, translations=trans)[0][..., [0, 2]]
    # the planted root offset is smoothed over 2 frames at 30 fps, the same time at any rate
    return plant_feet(feat[:, 0], feat[:, 1:3], local, disp,
                      contact[lines[:, 0]] & contact[lines[:, 1]], cyclic=loop,
                      smooth=2.0 * rate_scale(motion.rate))


def _place_root(
    motion: Motion,
    feat: np.ndarray,
    src: np.ndarray,
    constraints: list[tuple[int, int]],
    curve: PathCurve | None,
    rate: float,
    warn,
    loop: bool = False,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """World heading and ground position of every output frame.

    Along ``curve`` when given (a loop on a closed path paced to whole laps; a
    warning when the stride must change by more than ``PACE_TOLERANCE`` or the
    path of a loop is open); else the integrated root velocities, turned and
    moved so that the first constrained output frame (else frame 0) has its
    source frame's heading and ground position in the input.

    Returns
    -------
    heading : (L,) float ndarray
    ground : (L, 2) float ndarray
        ``(x, z)``.
    path_info : dict
        :func:`~mocapflow.stages.texture.root.follow_path`'s info (empty without a path).
    """
    if curve is not None:
        heading, ground, path_info = follow_path(feat[:, 0], feat[:, 1:3], curve, rate,
                                                 cyclic=loop)
        pace = path_info["pace"]
        if loop and not curve.closed:
            warn(
                f"loop on an open path ({path_info['path_length']:.2f} m): the last frame "
                "does not lead back to the first; close the path (last point = first point)"
            )
        elif loop and abs(pace - 1.0) > PACE_TOLERANCE:
            n = path_info["laps"]
            warn(
                f"loop on a closed path: the motion travels {path_info['distance']:.2f} m in "
                f"{feat.shape[0]} frames, {n} lap(s) of the {path_info['path_length']:.2f} m "
                f"path need its stride scaled by {pace:.2f} (beyond ±{PACE_TOLERANCE:.0%}): "
                f"scale the path by {1 / pace:.2f} or the length to "
                f"{round(feat.shape[0] * pace)} frames"
            )
        if path_info["beyond_end"]:
            warn(
                f"the motion travels {path_info['distance']:.2f} m but the path is only "
                f"{path_info['path_length']:.2f} m long: the last {path_info['beyond_end']} "
                "frames continue along the final tangent"
            )
        return heading, ground, path_info
    heading_in, _ = heading_split(motion.rotations[:, 0])
    ref = constraints[0][1] if constraints else 0
    h0, g0 = integrate_root(feat[:, 0], feat[:, 1:3])
    dh = heading_in[src[ref]] - h0[ref]
    c, s = np.cos(dh), np.sin(dh)
    rel = g0 - g0[ref]
    ground = np.stack([rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c], 1)
    ground += motion.root_position[src[ref], [0, 2]]
    return h0 + dh, ground, {}


def _output_motion(
    motion: Motion, rot: np.ndarray, feat: np.ndarray, heading: np.ndarray, ground: np.ndarray
) -> Motion:
    """The motion on the input skeleton: heading put back on the root, root at ``ground``."""
    L = feat.shape[0]
    root = np.stack([ground[:, 0], feat[:, 3], ground[:, 1]], axis=1)
    rotations = rot.copy()
    rotations[:, 0] = quat_multiply(yaw_quaternion(heading), rot[:, 0])
    J = motion.skeleton.n_joints
    trans = feat[:, 4:].reshape(L, J, 3) if feat.shape[1] > 4 else None
    attrs = dict(motion.attrs)
    attrs["synthesized_from"] = motion.attrs.get("source", motion.attrs.get("path"))
    return Motion(motion.skeleton, root, rotations, motion.rate, trans, attrs)


def _foot_ik(motion: Motion, out: Motion, lines: np.ndarray, weight: np.ndarray, constrained,
             blended, retargeted: bool = False, loop: bool = False, *, world: np.ndarray,
             contacts):
    """Leg IK keeping every stance toe moving as in the input (see ``foot_corrections``).

    ``lines``, ``weight``: the input frames mixed at each output frame and the weight of
    the second (:func:`~mocapflow.stages.texture.smoothing.transition_blend`): a
    cross-faded frame's toes move by the same mix of the two lines' steps, and are in
    contact where both lines are.  ``blended``: frames a Gaussian pass changed (their
    stance toes are kept still).

    ``retargeted``: the root follows a path (turned, stride paced), so the legs use
    the :data:`PATH_IK` weights; ``loop``: the corrections are periodic (the toes'
    ground positions wrap: a loop on a closed path).

    ``world``: the input's joint positions; ``contacts``: :func:`_input_contacts`.

    Returns the new local rotations and the largest correction (metres), or
    ``None`` when the skeleton has no usable toes or legs.
    """
    if contacts is None:
        return None
    toes, contact_in = contacts
    try:
        chains = leg_chains(motion.skeleton, toes)
    except ValueError:
        return None
    heading_in, _ = heading_split(motion.rotations[:, 0])
    ground = world[:, toes][..., [0, 2]]
    step = np.concatenate([np.diff(ground, axis=0), np.zeros((1,) + ground.shape[1:])], axis=0)
    if step.shape[0] > 1:
        step[-1] = step[-2]
    step_h = rotate_xz(step, -heading_in[:, None])
    heading_out, _ = heading_split(out.rotations[:, 0])
    L = lines.shape[0]
    w = weight[:, None, None]
    toe_step = rotate_xz((1.0 - w) * step_h[lines[:, 0]] + w * step_h[lines[:, 1]],
                         heading_out[:, None])
    toe_step[blended] = 0.0  # a blend of two stances keeps the stance foot still
    toes_out = chain_kinematics(out.skeleton, out.rotations, out.root_position, toes,
                                translations=out.translations)[0][..., [0, 2]]
    fixed = np.zeros(L, dtype=bool)
    fixed[[int(j) for j in constrained]] = True
    weights = PATH_IK if retargeted else {}
    contact = contact_in[lines[:, 0]] & contact_in[lines[:, 1]]
    corr = foot_corrections(toes_out, toe_step, contact, fixed=fixed,
                            cyclic=loop, **weights)
    rot = apply_foot_ik(
        out.skeleton, out.rotations, out.root_position, chains, corr,
        translations=out.translations,
    )
    return rot, float(np.linalg.norm(corr, axis=-1).max()) if L else 0.0


def _constraint_errors(motion_in: Motion, rot_out, feat_out, rot_in, feat_in, constraints):
    """Worst geodesic angle (deg) and root-relative FK distance (m) at constrained frames."""
    if not constraints:
        return 0.0, 0.0
    i = np.array([c[0] for c in constraints])
    j = np.array([c[1] for c in constraints])
    ang = float(np.degrees(quat_angle(rot_out[j], rot_in[i]).max()))
    J = rot_in.shape[1]
    tr_o = feat_out[j, 4:].reshape(len(j), J, 3) if feat_out.shape[1] > 4 else None
    tr_i = feat_in[i, 4:].reshape(len(i), J, 3) if feat_in.shape[1] > 4 else None
    po = level_positions(motion_in.skeleton, rot_out[j], feat_out[j, 3], tr_o)
    pi = level_positions(motion_in.skeleton, rot_in[i], feat_in[i, 3], tr_i)
    return ang, float(np.linalg.norm(po - pi, axis=-1).max())


def assemble_motion(
    pyramid: Pyramid,
    motion: Motion,
    source_index: np.ndarray,
    *,
    constraints: list[tuple[int, int]] = (),
    loop: bool = False,
    curve: PathCurve | None = None,
    smoothing: bool = True,
    transition_blend: float = 0.0,
    gaussian_width: int = 5,
    accel_tolerance: float = 1.0,
    max_widening: int = 12,
    jerk_tolerance: float | None = 1.0,
    plant: bool = True,
    foot_ik: bool = True,
    warn=None,
) -> tuple[Motion, dict[str, Any]]:
    """Turn a source track into a motion: copy, smooth the seams, integrate the root.

    Parameters
    ----------
    pyramid : Pyramid
        Tree of ``motion`` (level 0 supplies the copied frames).
    motion : Motion
        Input motion (skeleton, world heading and position of the first frame).
    source_index : (L,) int ndarray
        Input frame per output frame.
    constraints : list of (int, int)
        ``(input_frame, output_frame)``, pinned through smoothing; the first one
        (else output frame 0) is placed at its input frame's world position and heading.
    loop : bool
        Cyclic output.
    curve : PathCurve, optional
        Path to follow.
    smoothing : bool
    transition_blend : float
        Seconds of the cross-fade of each seam between its two input lines before the
        adaptive smoothing (:func:`~mocapflow.stages.texture.smoothing.transition_blend`;
        0: none, the thesis).
    gaussian_width, accel_tolerance, max_widening :
        See :func:`~mocapflow.stages.texture.smoothing.adaptive_smoothing`.
    jerk_tolerance : float or None
        A seam also fails the smoothing test while its jerk exceeds this
        multiple of the input's p99 jerk (None: acceleration test only).
    plant : bool
        Keep stance toes moving as in the input (root velocity correction).
    foot_ik : bool
        Then pin the residual toe slide of every contact span with two-bone
        leg IK (feet keep their world orientation; constrained frames untouched).
    warn : callable, optional

    Returns
    -------
    motion : Motion
    report : dict
        ``seams``, ``smoothing``, constraint errors, ``path``.
    """
    warn = warn or (lambda msg: None)
    src = np.asarray(source_index, dtype=np.int64)
    L = src.size
    cons = list(constraints)
    rot_in, feat_in = _input_features(pyramid)
    seams = seams_from_source(src, cyclic=loop)
    # the seams cross-faded between their input lines (frame t mixes lines[t] by weight[t])
    rot, feat, lines, weight = blend_transitions(
        rot_in, feat_in, src, seams, motion.rate,
        duration=transition_blend if smoothing else 0.0, constrained=[j for _, j in cons],
        cyclic=loop)
    rot_faded = rot.copy()
    # the input's joint positions and toe contacts, once for the steps that need them
    world_in = motion_positions(motion) if (smoothing and seams.size) or plant or foot_ik \
        else None
    contacts = _input_contacts(motion, world_in) if plant or (foot_ik and L > 2) else None
    sm_report: dict[str, Any] = {"enabled": smoothing}
    if smoothing and seams.size:
        rot, feat, widened = _smooth_seams(
            motion.skeleton,
            motion.rate,
            rot,
            feat,
            seams,
            [j for _, j in cons],
            loop,
            gaussian_width=gaussian_width,
            accel_tolerance=accel_tolerance,
            max_widening=max_widening,
            jerk_tolerance=jerk_tolerance,
            warn=warn,
            world_in=world_in,
            jerk_reach=1 + math.ceil(0.5 * transition_blend * SMOOTHING_RATE),
        )
        sm_report.update(widened)

    if plant:
        feat[:, 1:3] = _planted_velocity(pyramid, motion, rot, feat, lines, weight, loop,
                                         contacts)
    heading, ground, path_info = _place_root(motion, feat, src, cons, curve, pyramid.rate,
                                             warn, loop)
    out = _output_motion(motion, rot, feat, heading, ground)
    ik_max = 0.0
    if foot_ik and L > 2:
        blended = np.abs(rot - rot_faded).max(axis=(1, 2)) > 1e-9  # by the Gaussian
        # periodic corrections only where the ground positions wrap too (a loop on a
        # closed path); a loop in place of a path ends a lap away from its start
        res = _foot_ik(motion, out, lines, weight, [j for _, j in cons], blended,
                       curve is not None,
                       loop and curve is not None and curve.closed, world=world_in,
                       contacts=contacts)
        if res is not None:
            rotations, ik_max = res
            rot[:, 1:] = rotations[:, 1:]
            out = out.replace(rotations=rotations)
    ang, fk = _constraint_errors(motion, rot, feat, rot_in, feat_in, cons)
    report = {
        "seams": seams.tolist(),
        "n_seams": int(seams.size),
        "smoothing": sm_report,
        "constraint_max_angle_deg": ang,
        "constraint_max_fk_m": fk,
        "path": path_info,
        "foot_ik_max_m": ik_max,
    }
    return out, report
