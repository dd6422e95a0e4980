"""Constrained multi-resolution synthesis of textural motion (Moradoff 2002, chapter 3).

Given the Gaussian pyramid of an input motion (:mod:`mocapflow.stages.texture.pyramid`),
the synthesis builds the output's tree level by level, coarsest first.  Each
output node copies one input node of the same level (the *source track*);
constraints ``(input frame i → output frame j)`` are anchors on every level
(``i >> l`` at ``j >> l``) and exact at the finest.  Gaps between anchors are
filled by the neighbourhood search of :mod:`~mocapflow.stages.texture.search`
(meeting points) or, at the coarsest level, by a path in the transition graph
(:mod:`~mocapflow.stages.texture.graph`).  The finest source track is stored as
``source_index`` so seams can be inspected; seams are smoothed adaptively
(:mod:`~mocapflow.stages.texture.smoothing`) and the root is integrated or
steered along a path (:mod:`~mocapflow.stages.texture.root`); stance toes are
then pinned by two-bone leg IK (``foot_ik``).

Variety: at the coarsest level the natural successor of a run always matches
perfectly, so drawing only among matches "close to the best" reproduces the
input almost verbatim.  ``variety`` sets the draw window as a quantile of the
input's own transition costs, ``max_run`` bounds the longest verbatim run, and
``usage_weight`` spreads the output over the input (coverage); see
:mod:`~mocapflow.stages.texture.search`.

Limitations of the thesis removed here: any output length (not a multiple of
the input's), any number of meeting points per output (one per gap), loops.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context, stage
from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.motion.kinematics import heading_split, yaw_quaternion
from mocapflow.stages.texture.graph import (
    UnreachableGapError,
    graph_path,
    transition_costs,
    transition_graph,
)
from mocapflow.stages.texture.pyramid import Pyramid
from mocapflow.stages.texture.search import (
    LevelResult,
    LevelSearch,
    SearchParams,
    SynthesisError,
    gaps_of,
    level_view,
    refine_level,
)

__all__ = [
    "ConstraintError",
    "SynthResult",
    "assemble_motion",
    "SynthesisError",
    "UnreachableGapError",
    "synth",
    "synthesize",
    "synthesize_source",
]


#: Seam accelerations below this fraction of the input's median acceleration pass the test.
ACCEL_FLOOR = 0.25


class ConstraintError(SynthesisError):
    """Constraints that cannot be met (outside the input/output, too close, …)."""


@dataclass
class SynthResult:
    """Output of :func:`synthesize`.

    Attributes
    ----------
    motion : Motion
        On the input skeleton.
    source_index : (L,) int ndarray
        Input frame copied into each output frame (before smoothing).
    report : dict
        Seams, meeting points, smoothing, constraint errors, timings.
    """

    motion: Motion
    source_index: np.ndarray
    report: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------- constraints


def _check_constraints(
    constraints, n_in: int, length: int, levels: int, cyclic: bool
) -> list[tuple[int, int]]:
    """Validate ``[[input_frame, output_frame], …]``; sorted by output frame."""
    out: list[tuple[int, int]] = []
    for k, c in enumerate(constraints or []):
        if len(c) != 2:
            raise ConstraintError(f"constraint {k}: expected [input_frame, output_frame], got {c}")
        i, j = int(c[0]), int(c[1])
        if not 0 <= i < n_in:
            raise ConstraintError(
                f"constraint {k} [{i}, {j}]: input frame {i} is outside the input "
                f"(frames 0-{n_in - 1})"
            )
        if j < 0:
            raise ConstraintError(f"constraint {k} [{i}, {j}]: output frame {j} is negative")
        if j >= length:
            raise ConstraintError(
                f"constraint {k} [{i}, {j}]: the output ({length} frames) is shorter than the "
                f"constraints (output frame {j} needs length >= {j + 1})"
            )
        out.append((i, j))
    out.sort(key=lambda c: c[1])
    span = 2 ** (levels - 1)
    for (_, j1), (_, j2) in zip(out[:-1], out[1:]):
        if j1 == j2:
            raise ConstraintError(f"two constraints on output frame {j1}")
        if j1 // span == j2 // span:
            raise ConstraintError(
                f"constraints on output frames {j1} and {j2} are closer than the coarsest level "
                f"can separate (they fall in one node of {span} frames at level {levels - 1}); "
                f"use fewer levels or move them apart"
            )
    if cyclic and len(out) > 1:
        n_top = -(-length // span)
        if (out[0][1] // span + n_top) - out[-1][1] // span < 1:
            raise ConstraintError(
                f"loop: constraints on output frames {out[-1][1]} and {out[0][1]} fall in one "
                f"coarsest node; use fewer levels"
            )
    return out


# --------------------------------------------------------------------------- source track


def _anchors(constraints, level: int) -> tuple[list[int], list[int], list]:
    pos = [j >> level for _, j in constraints]
    node = [i >> level for i, _ in constraints]
    keys = list(range(len(constraints)))
    return pos, node, keys


def _free_start(search: LevelSearch, src, ranked) -> None:
    """Choose output node 0 of a loop without anchors (random at the coarsest level)."""
    search.fill(src, ranked, 0, "the first output node")


def _graph_level(
    search: LevelSearch, src, ranked, gaps, params: SearchParams, threshold, slack, rng
) -> dict:
    """Fill the coarsest level's gaps with transition-graph paths."""
    view = search.view
    E = transition_graph(transition_costs(view, slots=params.slots), threshold=threshold)
    n = search.n
    meetings = {}
    for g in gaps:
        steps = g.hi - g.lo - (0 if (g.left and g.right) else 1)
        if not g.left:
            steps = g.hi
        if steps <= 0:
            continue
        start = int(src[g.lo % n]) if g.left else None
        end = int(src[g.hi % n]) if g.right else None
        where = _gap_name(g, search)
        path = graph_path(
            E, steps, rng, start=start, end=end, slack=slack, unit=view.unit, where=where
        )
        if g.left and g.right:
            nodes, pos = path[1:-1], np.arange(g.lo + 1, g.hi)
        elif g.left:
            nodes, pos = path[1:], np.arange(g.lo + 1, g.hi)
        else:
            nodes, pos = path[:-1], np.arange(0, g.hi)
        pw = np.mod(pos, n) if search.cyclic else pos
        src[pw] = nodes
        ranked[pw] = -1
        ranked[pw, 0] = nodes
        if g.left and g.right and pos.size:
            jumps = np.flatnonzero(path[1:] != path[:-1] + 1)
            if jumps.size:
                cost = E[path[jumps], path[jumps + 1]]
                m = g.lo + 1 + int(jumps[np.argmax(cost)])
                meetings[g.key] = int(min(max(m, g.lo + 1), g.hi - 1))
            else:
                meetings[g.key] = (g.lo + g.hi) // 2
    return meetings


def _gap_name(g, search: LevelSearch) -> str:
    f = 2**search.l
    lo = "start" if not g.left else f"output frame ~{g.lo * f}"
    hp = g.hi % search.n if search.cyclic else g.hi
    hi = "end" if not g.right else f"output frame ~{hp * f}"
    return f"gap between {lo} and {hi} (constraints {g.key})"


def synthesize_source(
    pyramid: Pyramid,
    length: int,
    constraints: list[tuple[int, int]],
    *,
    levels: int,
    cyclic: bool,
    method: str,
    params: SearchParams,
    rng: np.random.Generator,
    graph_threshold: float = 0.1,
    graph_slack: float = 0.5,
) -> tuple[np.ndarray, dict]:
    """The finest source track of a constrained multi-resolution synthesis.

    Parameters
    ----------
    pyramid : Pyramid
    length : int
        Output frames ``L``.
    constraints : list of (int, int)
        Validated ``(input_frame, output_frame)``, sorted by output frame.
        Without any (and no loop) the output starts with the input's first frame.
    levels : int
        Pyramid levels used (finest ``levels``).
    cyclic : bool
        Loop mode.
    method : {"meeting_point", "graph_path"}
    params : SearchParams
    rng : numpy.random.Generator
    graph_threshold, graph_slack : float
        Transition-graph options (graph_path).

    Returns
    -------
    source_index : (L,) int ndarray
    info : dict
        ``meetings`` per level (output frames at that level's resolution).
    """
    if not constraints and not cyclic:
        constraints = [(0, 0)]  # unconstrained: the output starts where the input starts
    views = [level_view(pyramid.levels[l], 2.0**l) for l in range(levels)]
    n_out = [-(-length // 2**l) for l in range(levels)]
    upper: LevelResult | None = None
    meetings: dict = {}
    info: dict[str, Any] = {"meetings": {}}
    for l in range(levels - 1, -1, -1):
        search = LevelSearch(views, l, n_out, cyclic, upper, params, rng)
        n = n_out[l]
        src = np.full(n, -1, dtype=np.int64)
        ranked = np.full((n, 3), -1, dtype=np.int64)
        pos, node, keys = _anchors(constraints, l)
        for p, v in zip(pos, node):
            src[p] = v
            ranked[p] = [v, -1, -1]
        if l < levels - 1:
            upper = refine_level(search, dict(zip(pos, node)))
            continue
        if not pos:
            _free_start(search, src, ranked)
            pos, keys = [0], ["free"]
        gaps = gaps_of(pos, keys, n, cyclic)
        if method == "graph_path":
            meetings = _graph_level(
                search, src, ranked, gaps, params, graph_threshold, graph_slack, rng
            )
        else:
            for g in gaps:
                mp = search.fill_gap(src, ranked, g, None)
                if mp is not None:
                    meetings[g.key] = mp
        if (src < 0).any():  # pragma: no cover - every gap fills or raises
            raise SynthesisError(f"level {l}: nodes {np.flatnonzero(src < 0)} left empty")
        info["meetings"] = {str(k): int(v) * 2**l for k, v in meetings.items()}
        upper = LevelResult(src, ranked, meetings)
    return upper.src.copy(), info


# --------------------------------------------------------------------------- assembly


def _input_features(pyramid: Pyramid) -> tuple[np.ndarray, np.ndarray]:
    lev = pyramid.levels[0]
    parts = [lev.yaw_rate[:, None], lev.velocity, lev.height[:, None]]
    if lev.translations is not None:
        parts.append(lev.translations.reshape(lev.n_nodes, -1))
    return lev.rotations, np.concatenate(parts, axis=1)


def _constraint_errors(motion_in: Motion, rot_out, feat_out, rot_in, feat_in, constraints):
    """Worst geodesic angle (deg) and root-relative FK distance (m) at constrained frames."""
    from mocapflow.stages.motion.kinematics import quat_angle
    from mocapflow.stages.texture.pyramid import level_positions

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


def _planted_velocity(pyramid, motion, rot, feat, src, loop) -> np.ndarray:
    """Root velocities keeping the input's stance toes planted (see ``plant_feet``)."""
    from mocapflow.stages.motion.contacts import contact_thresholds, foot_contacts, toe_indices
    from mocapflow.stages.motion.kinematics import motion_positions
    from mocapflow.stages.texture.pyramid import level_positions
    from mocapflow.stages.texture.root import plant_feet, toe_displacements

    try:
        toes = toe_indices(motion.skeleton)
    except ValueError:
        return feat[:, 1:3]
    lev = pyramid.levels[0]
    world = motion_positions(motion)
    h, s = contact_thresholds(world, toes, motion.rate)
    contact = foot_contacts(world, toes, motion.rate, height_threshold=h, speed_threshold=s)
    disp_in = toe_displacements(lev.yaw_rate, lev.velocity, lev.positions[:, toes][..., [0, 2]])
    J = motion.skeleton.n_joints
    trans = feat[:, 4:].reshape(len(src), J, 3) if feat.shape[1] > 4 else None
    local = level_positions(motion.skeleton, rot, feat[:, 3], trans)[:, toes][..., [0, 2]]
    return plant_feet(feat[:, 0], feat[:, 1:3], local, src, disp_in, contact, cyclic=loop)


def _foot_ik(motion: Motion, out: Motion, src: np.ndarray, constrained, blended):
    """Leg IK keeping every stance toe moving as in the input (see ``foot_corrections``).

    Returns the new local rotations and the largest correction (metres), or
    ``None`` when the skeleton has no usable toes or legs.
    """
    from mocapflow.stages.motion.contacts import contact_thresholds, foot_contacts, toe_indices
    from mocapflow.stages.motion.kinematics import motion_positions
    from mocapflow.stages.texture.root import (
        _rotate_xz,
        apply_foot_ik,
        foot_corrections,
        leg_chains,
    )

    try:
        toes = toe_indices(motion.skeleton)
        chains = leg_chains(motion.skeleton, toes)
    except ValueError:
        return None
    world = motion_positions(motion)
    h, s = contact_thresholds(world, toes, motion.rate)
    contact_in = foot_contacts(world, toes, motion.rate, height_threshold=h, speed_threshold=s)
    heading_in, _ = heading_split(motion.rotations[:, 0])
    ground = world[:, toes][..., [0, 2]]
    step = np.concatenate([np.diff(ground, axis=0), np.zeros((1,) + ground.shape[1:])], axis=0)
    if step.shape[0] > 1:
        step[-1] = step[-2]
    step_h = _rotate_xz(step, -heading_in[:, None])
    heading_out, _ = heading_split(out.rotations[:, 0])
    L = src.size
    toe_step = _rotate_xz(step_h[src], heading_out[:, None])
    toe_step[blended] = 0.0  # a blend of two stances keeps the stance foot still
    pos_out = motion_positions(out)
    fixed = np.zeros(L, dtype=bool)
    fixed[[int(j) for j in constrained]] = True
    corr = foot_corrections(pos_out[:, toes][..., [0, 2]], toe_step, contact_in[src], fixed=fixed)
    rot = apply_foot_ik(
        out.skeleton, out.rotations, out.root_position, chains, corr,
        translations=out.translations,
    )
    return rot, float(np.linalg.norm(corr, axis=-1).max()) if L else 0.0


def assemble_motion(
    pyramid: Pyramid,
    motion: Motion,
    source_index: np.ndarray,
    *,
    constraints: list[tuple[int, int]] = (),
    loop: bool = False,
    curve=None,
    smoothing: bool = True,
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
    from mocapflow.stages.metrics.quality import seams_from_source
    from mocapflow.stages.motion.kinematics import quat_multiply
    from mocapflow.stages.texture.root import follow_path, integrate_root
    from mocapflow.stages.texture.smoothing import adaptive_smoothing

    t0 = time.perf_counter()
    warn = warn or (lambda msg: None)
    src = np.asarray(source_index, dtype=np.int64)
    L = src.size
    cons = list(constraints)
    rot_in, feat_in = _input_features(pyramid)
    rot, feat = rot_in[src].copy(), feat_in[src].copy()
    seams = seams_from_source(src, cyclic=loop)
    sm_report: dict[str, Any] = {"enabled": smoothing}
    if smoothing and seams.size:
        from mocapflow.stages.metrics.quality import acceleration_per_frame, jerk_p99
        from mocapflow.stages.motion.kinematics import motion_positions

        world_in = motion_positions(motion)
        acc_in = acceleration_per_frame(world_in, motion.rate)
        floor = ACCEL_FLOOR * float(np.nanmedian(acc_in)) if motion.n_frames > 2 else 0.0
        jerk_limit = None
        if jerk_tolerance is not None and motion.n_frames > 8:
            jerk_limit = jerk_tolerance * jerk_p99(world_in, motion.rate)
        sm = adaptive_smoothing(
            motion.skeleton,
            rot,
            feat,
            seams,
            pyramid.rate,
            constrained=[j for _, j in cons],
            cyclic=loop,
            gaussian_width=gaussian_width,
            accel_tolerance=accel_tolerance,
            accel_floor=floor,
            max_widening=max_widening,
            jerk_limit=jerk_limit,
        )
        rot, feat = sm.rotations, sm.features
        failed = seams[~sm.passed]
        if failed.size:
            warn(
                f"{failed.size} of {seams.size} seams still fail the acceleration test after "
                f"widening to k={max_widening} (output frames {failed[:10].tolist()})"
            )
        sm_report.update(
            widening=sm.widening.tolist(),
            passed=sm.passed.tolist(),
            seam_acc=sm.seam_acc.tolist(),
            ref_acc=sm.ref_acc.tolist(),
        )
    t_smooth = time.perf_counter() - t0

    if plant:
        feat[:, 1:3] = _planted_velocity(pyramid, motion, rot, feat, src, loop)
    heading_in, _ = heading_split(motion.rotations[:, 0])
    path_info: dict[str, Any] = {}
    if curve is not None:
        heading, ground, path_info = follow_path(feat[:, 0], feat[:, 1:3], curve, pyramid.rate)
        if path_info["beyond_end"]:
            warn(
                f"the motion travels {path_info['distance']:.2f} m but the path is only "
                f"{path_info['path_length']:.2f} m long: the last {path_info['beyond_end']} "
                "frames continue along the final tangent"
            )
    else:
        ref = cons[0][1] if cons else 0
        h0, g0 = integrate_root(feat[:, 0], feat[:, 1:3])
        dh = heading_in[src[ref]] - h0[ref]
        c, s = np.cos(dh), np.sin(dh)
        rel = g0 - g0[ref]
        ground = np.stack([rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c], 1)
        ground += motion.root_position[src[ref], [0, 2]]
        heading = h0 + dh
    root = np.stack([ground[:, 0], feat[:, 3], ground[:, 1]], axis=1)
    rotations = rot.copy()
    rotations[:, 0] = quat_multiply(yaw_quaternion(heading), rot[:, 0])
    J = motion.skeleton.n_joints
    trans = feat[:, 4:].reshape(L, J, 3) if feat.shape[1] > 4 else None
    attrs = dict(motion.attrs)
    attrs["synthesized_from"] = motion.attrs.get("source", motion.attrs.get("path"))
    out = Motion(motion.skeleton, root, rotations, motion.rate, trans, attrs)
    ik_max = 0.0
    if foot_ik and L > 2:
        blended = np.abs(rot - rot_in[src]).max(axis=(1, 2)) > 1e-9
        res = _foot_ik(motion, out, src, [j for _, j in cons], blended)
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
        "seconds_smoothing": t_smooth,
    }
    return out, report


def synthesize(
    pyramid: Pyramid,
    motion: Motion,
    *,
    length: int | None = None,
    constraints: list[list[int]] | None = None,
    path: list[list[float]] | None = None,
    path_mode: str = "polyline",
    loop: bool = False,
    levels: int | None = None,
    filter_size: int | None = None,
    method: str = "meeting_point",
    params: SearchParams | None = None,
    graph_threshold: float = 0.1,
    graph_slack: float = 0.5,
    smoothing: bool = True,
    gaussian_width: int = 5,
    accel_tolerance: float = 1.0,
    max_widening: int = 12,
    jerk_tolerance: float | None = 1.0,
    foot_ik: bool = True,
    rng: np.random.Generator | None = None,
    warn=None,
) -> SynthResult:
    """Synthesize a longer (or looping, constrained, path-following) version of a motion.

    Parameters
    ----------
    pyramid : Pyramid
        Gaussian tree of ``motion``.
    motion : Motion
        The input (``F`` frames), for its skeleton, world heading and position.
    length : int, optional
        Output frames ``L`` (default ``2 F``).
    constraints : list of [int, int], optional
        ``[input_frame, output_frame]`` pairs: output frame shows the input frame's pose.
    path : list of [x, z] or [x, y, z], optional
        Ground path to follow (root steered along it from its first point).
    path_mode : {"polyline", "spline"}
    loop : bool
        Cyclic output: the frame after the last is the first (seam smoothed).
    levels : int, optional
        Pyramid levels used (default all).
    filter_size : int, optional
        Must match the pyramid's when given.
    method : {"meeting_point", "graph_path"}
    params : SearchParams, optional
    graph_threshold, graph_slack : float
        Transition-graph quantile and DFS cost slack (graph_path).
    smoothing : bool
        Adaptive local smoothing of the seams.
    gaussian_width, accel_tolerance, max_widening :
        See :func:`~mocapflow.stages.texture.smoothing.adaptive_smoothing`.
    jerk_tolerance : float or None
        Seams also fail the smoothing test while their jerk exceeds this
        multiple of the input's p99 jerk.
    foot_ik : bool
        Pin the stance toes with leg IK after smoothing (:func:`assemble_motion`).
    rng : numpy.random.Generator, optional
    warn : callable, optional
        ``warn(message)`` for non-fatal problems.

    Returns
    -------
    SynthResult

    Raises
    ------
    ConstraintError
        Constraint outside the input or output, or closer than the coarsest level separates.
    UnreachableGapError
        graph_path: a gap no path of its length can fill.
    """
    from mocapflow.stages.texture.root import PathCurve

    t0 = time.perf_counter()
    rng = rng if rng is not None else np.random.default_rng(0)
    params = params or SearchParams()
    warn = warn or (lambda msg: None)
    F = motion.n_frames
    if pyramid.n_frames != F:
        raise SynthesisError(
            f"pyramid has {pyramid.n_frames} frames but the motion has {F}: "
            "build the pyramid from the same motion"
        )
    if filter_size is not None and filter_size != pyramid.filter_size:
        raise SynthesisError(
            f"filter_size {filter_size} differs from the pyramid's {pyramid.filter_size}"
        )
    levels = pyramid.n_levels if levels is None else int(levels)
    if not 1 <= levels <= pyramid.n_levels:
        raise SynthesisError(
            f"levels must be in 1-{pyramid.n_levels} (the pyramid's), got {levels}"
        )
    if method not in ("meeting_point", "graph_path"):
        raise SynthesisError(f"method must be 'meeting_point' or 'graph_path', got {method!r}")
    L = 2 * F if length is None else int(length)
    if L < 2:
        raise SynthesisError(f"length must be >= 2 frames, got {L}")
    cons = _check_constraints(constraints, F, L, levels, loop)
    curve = PathCurve.from_points(path, mode=path_mode) if path is not None else None

    src, info = synthesize_source(
        pyramid,
        L,
        cons,
        levels=levels,
        cyclic=loop,
        method=method,
        params=params,
        rng=rng,
        graph_threshold=graph_threshold,
        graph_slack=graph_slack,
    )
    t_search = time.perf_counter() - t0

    out, rep = assemble_motion(
        pyramid,
        motion,
        src,
        constraints=cons,
        loop=loop,
        curve=curve,
        smoothing=smoothing,
        gaussian_width=gaussian_width,
        accel_tolerance=accel_tolerance,
        max_widening=max_widening,
        jerk_tolerance=jerk_tolerance,
        foot_ik=foot_ik,
        warn=warn,
    )
    report = {
        "length": L,
        "input_frames": F,
        "levels": levels,
        "method": method,
        "loop": loop,
        "constraints": [list(c) for c in cons],
        "meetings": info["meetings"],
        **rep,
    }
    report["seconds"] = {
        "search": t_search,
        "smoothing": rep["seconds_smoothing"],
        "total": time.perf_counter() - t0,
    }
    del report["seconds_smoothing"]
    return SynthResult(out, src, report)


@stage("synth", outputs=("motion", "source_index", "report"))
def synth(
    pyramid: Pyramid,
    motion: Motion,
    *,
    length: int | None = None,
    constraints: list[list[int]] | None = None,
    path: list[list[float]] | None = None,
    path_mode: Literal["polyline", "spline"] = "polyline",
    loop: bool = False,
    seed: int = 0,
    levels: int | None = None,
    filter_size: int | None = None,
    method: Literal["meeting_point", "graph_path"] = "meeting_point",
    slots: int = 3,
    ancestor_weight: float = 1.0,
    current_weight: float = 1.0,
    finer_weight: float = 1.0,
    candidate_range: int = 4,
    k_best: int = 3,
    variety: float = 0.3,
    max_run: float = 0.3,
    usage_weight: float = 0.5,
    tolerance: float = 0.5,
    meeting_window: int = 4,
    graph_threshold: float = 0.1,
    graph_slack: float = 0.5,
    smoothing: bool = True,
    gaussian_width: int = 5,
    accel_tolerance: float = 1.0,
    jerk_tolerance: float = 1.0,
    max_widening: int = 12,
    foot_ik: bool = True,
    ctx: Context,
) -> dict[str, Any]:
    """Constrained multi-resolution texture synthesis (Moradoff 2002).

    Parameters
    ----------
    pyramid : Pyramid
        Gaussian tree of ``motion`` (stage ``pyramid``).
    motion : Motion
        Input motion (``F`` frames), for the skeleton and world placement.
    length : int, optional
        Output frames (default ``2 F``); any length.
    constraints : list of [input_frame, output_frame], optional
        Poses required at output frames (exact before smoothing).
    path : list of [x, z] (or [x, y, z]), optional
        Ground path to follow.
    path_mode : {"polyline", "spline"}
    loop : bool
        Cyclic output (last → first seam smoothed).
    seed : int
        Variant; randomness comes from ``ctx.rng``.
    levels : int, optional
        Pyramid levels used (default all of the pyramid's).
    filter_size : int, optional
        Checked against the pyramid's.
    method : {"meeting_point", "graph_path"}
        Gap filler at the coarsest level.
    slots : int
        Neighbourhood half width (±3).
    ancestor_weight, current_weight, finer_weight : float
        Relative weights of the three neighbourhood levels.
    candidate_range : int
        ± nodes around the children of the parent's 3 best matches (±4).
    k_best : int
        Random choice among the k best at all but the finest level (2–3).
    variety : float
        How new the arrangement is, 0–1 (default 0.3).  At the coarsest level
        jumps are drawn among the k best whose cost lies within the
        ``variety`` quantile of the input's own best-jump costs (about the
        share of moments a drawn jump may leave): 0 keeps only the jumps the
        input's end forces (near-verbatim copies), 1 draws among the k best at
        every node as in the thesis.  Raise for more novelty, lower for longer
        verbatim stretches.
    max_run : float
        Longest verbatim run as a fraction of the input (0.3): a run that long
        must jump, where the jump fits best among its last positions.  0 (or
        >= 1) disables.
    usage_weight : float
        Preference for input material not used yet (coverage of the input); 0
        disables.
    tolerance : float
        Cost units within which the k best joins are drawn below the coarsest level.
    meeting_window : int
        ± nodes searched around the previous level's meeting point.
    graph_threshold : float
        Quantile of jump costs kept as transition-graph edges.
    graph_slack : float
        DFS cost bound relative to the cheapest path.
    smoothing : bool
        Adaptive local smoothing (§3.8).
    gaussian_width : int
        Taps of the smoothing Gaussian (5).
    accel_tolerance : float
        Acceleration test threshold relative to the reference frames.
    jerk_tolerance : float
        A seam also fails the smoothing test while its jerk exceeds this
        multiple of the input's p99 jerk (0 disables).
    max_widening : int
        Largest smoothing half width ``k``.
    foot_ik : bool
        Pin the stance toes with two-bone leg IK after smoothing (no foot skate
        at the seams; constrained frames untouched).
    ctx : Context

    Returns
    -------
    dict
        ``motion`` (Motion on the input skeleton), ``source_index`` ((L,) int
        ndarray, input frame per output frame before smoothing), ``report`` (JSON).
    """
    params = SearchParams(
        slots=slots,
        level_weights=(ancestor_weight, current_weight, finer_weight),
        candidate_range=candidate_range,
        k_best=k_best,
        tolerance=tolerance,
        meeting_window=meeting_window,
        variety=variety,
        max_run=max_run,
        usage_weight=usage_weight,
    )
    res = synthesize(
        pyramid,
        motion,
        length=length,
        constraints=constraints,
        path=path,
        path_mode=path_mode,
        loop=loop,
        levels=levels,
        filter_size=filter_size,
        method=method,
        params=params,
        graph_threshold=graph_threshold,
        graph_slack=graph_slack,
        smoothing=smoothing,
        gaussian_width=gaussian_width,
        accel_tolerance=accel_tolerance,
        max_widening=max_widening,
        jerk_tolerance=jerk_tolerance if jerk_tolerance > 0 else None,
        foot_ik=foot_ik,
        rng=ctx.rng,
        warn=ctx.warn,
    )
    res.report["seed"] = seed
    return {"motion": res.motion, "source_index": res.source_index, "report": res.report}
