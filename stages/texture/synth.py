"""Constrained multi-resolution synthesis of textural motion (Moradoff 2002, chapter 3).

Given the Gaussian pyramid of an input motion (:mod:`mocapflow.stages.texture.pyramid`),
the synthesis builds the output's tree level by level, coarsest first
(:func:`synthesize_source`).  Each output node copies one input node of the same
level (the *source track*); constraints ``(input frame i → output frame j)``
are anchors on every level (``i >> l`` at ``j >> l``) and exact at the finest.
At the coarsest level (:func:`_coarsest_level`) the gaps between anchors are
filled by the neighbourhood search of :mod:`~mocapflow.stages.texture.search`
(meeting points) or by a path in the transition graph
(:mod:`~mocapflow.stages.texture.graph`); every finer level is son selection
with its transitions searched again (:mod:`~mocapflow.stages.texture.refine`).
The finest source track is stored as ``source_index`` so seams can be
inspected; :func:`~mocapflow.stages.texture.assemble.assemble_motion` turns it
into the motion: seams smoothed adaptively
(:mod:`~mocapflow.stages.texture.smoothing`), the root integrated or steered
along a path (:mod:`~mocapflow.stages.texture.root`), stance toes then pinned
by two-bone leg IK (``foot_ik``).  The ``synth`` stage composes the three.
With ``smooth_levels="every"`` (the thesis' §3.8) every coarser level is smoothed
too, in its own representation, before the next finer level is refined from it
(:func:`~mocapflow.stages.texture.assemble.smooth_level`, read by the finer level's
ancestor windows: :class:`_SmoothedParentRefinement`).

Frame rate: the synthesis works at the rate of its input motion (the ingest
``rate``); the output motion is resampled back to the source's rate (the rate
the BVH was read at, ``attrs["resampled_from_rate"]``, so the export gets the
input's exact ``Frame Time`` text) or to ``output_rate``, by a C² rotation
spline (:func:`~mocapflow.stages.motion.kinematics.resample_motion`,
``method="spline"``); the report's ``jerk_p99`` is measured at that rate.
Constraint frames are given and reported in those numbers: input frames of the
source file, output frames at the output rate.

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

import functools
import math
from collections.abc import Callable
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context, stage
from mocapflow.stages.metrics.quality import jerk_p99, longest_verbatim_run, seams_from_source
from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.motion.kinematics import (
    motion_positions,
    reorient_motion,
    resample_motion,
)
from mocapflow.stages.texture.assemble import assemble_motion, smooth_level
from mocapflow.stages.texture.graph import (
    UnreachableGapError,
    graph_path,
    jump_window,
    transition_costs,
    transition_graph,
)
from mocapflow.stages.texture.neighbourhood import LevelView, level_view, window_cost
from mocapflow.stages.texture.pyramid import Pyramid, PyramidLevel
from mocapflow.stages.texture.refine import POSE_SPAN_FRAMES, LevelRefinement
from mocapflow.stages.texture.root import PathCurve
from mocapflow.stages.texture.search import (
    LevelResult,
    LevelSearch,
    SearchParams,
    SynthesisError,
    gaps_of,
)
from mocapflow.stages.texture.smoothing import rate_scale

__all__ = [
    "ConstraintError",
    "SynthesisError",
    "UnreachableGapError",
    "synth",
    "synthesize_source",
]


class ConstraintError(SynthesisError):
    """Constraints that cannot be met (outside the input/output, too close, …)."""


# --------------------------------------------------------------------------- inputs


def _levels_used(pyramid: Pyramid, n_frames: int, levels: int | None, filter_size) -> int:
    """Pyramid levels the synthesis uses; the pyramid must be the motion's."""
    if pyramid.n_frames != n_frames:
        raise SynthesisError(
            f"pyramid has {pyramid.n_frames} frames but the motion has {n_frames}: "
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
    return levels


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
    """Positions ``j >> l``, input nodes ``i >> l`` and keys of the constraints at ``level``."""
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
    """Fill the coarsest level's gaps with transition-graph paths (in place).

    Returns the meetings: the costliest jump of each two-sided gap (its middle
    when the path has none).
    """
    view = search.view
    T = transition_costs(view, slots=params.slots)
    E = transition_graph(T, threshold=threshold, min_jump=params.slots)
    # the walk draws as the search does: variety window, k best, usage, settled jumps
    draw = {"window": jump_window(T, params.variety) if params.variety > 0 else 0.0,
            "k_best": params.k_best, "usage_weight": params.usage_weight,
            "settle": params.slots}
    # no jump from the input's last nodes into its first: the finer levels could extend
    # neither line to join them (the left one ends the input, the right one starts it)
    S = params.slots
    E[-S:, :S] = np.inf
    # where the graph cannot keep max_run: every jump (same rules) may become an edge
    escapes = transition_graph(T, threshold=1.0, min_jump=S)
    escapes[-S:, :S] = np.inf
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
            E, steps, rng, start=start, end=end, slack=slack, unit=view.unit,
            max_run=_graph_run_limit(search, params),
            run_before=_run_into(src, g.lo, search.cyclic),
            keep=params.slots, escapes=escapes, where=where,
            usage=np.bincount(src[src >= 0], minlength=view.n).astype(np.float64), **draw,
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


def _graph_run_limit(search: LevelSearch, params: SearchParams) -> int | None:
    """``max_run`` of the graph walk (coarsest nodes): the search's limit less what
    refinement may add to a run — a join moves at most ``meeting_window`` nodes at each
    finer level, ``meeting_window · (1 - 2^-l)`` coarsest nodes in all (one end)."""
    if search.max_run_nodes is None:
        return None
    grow = math.ceil(params.meeting_window * (1.0 - 2.0 ** -search.l))
    return max(2 * params.slots, search.max_run_nodes - grow)


def _run_into(src: np.ndarray, t: int, cyclic: bool) -> int:
    """Nodes of the verbatim run of ``src`` that ends at position ``t`` (0: unfilled)."""
    n = src.size
    if not cyclic and not 0 <= t < n or src[t % n] < 0:
        return 0
    back = t - np.arange(n if cyclic else t + 1)  # t, t-1, … (wrapping in a loop)
    v = src[back % n]
    follows = (v[1:] >= 0) & (v[:-1] == v[1:] + 1)  # v[u] continues v[u + 1]
    return 1 + (int(np.argmin(follows)) if not follows.all() else follows.size)


def _gap_name(g, search: LevelSearch) -> str:
    f = 2**search.l
    lo = "start" if not g.left else f"output frame ~{g.lo * f}"
    hp = g.hi % search.n if search.cyclic else g.hi
    hi = "end" if not g.right else f"output frame ~{hp * f}"
    return f"gap between {lo} and {hi} (constraints {g.key})"


def _coarsest_level(
    search: LevelSearch,
    constraints: list[tuple[int, int]],
    *,
    method: str,
    params: SearchParams,
    graph_threshold: float,
    graph_slack: float,
    rng: np.random.Generator,
) -> LevelResult:
    """The coarsest source track: anchors written, every gap filled.

    ``meetings`` of the result: gap key -> meeting position (coarsest nodes).
    """
    n = search.n
    src = np.full(n, -1, dtype=np.int64)
    ranked = np.full((n, 3), -1, dtype=np.int64)
    pos, node, keys = _anchors(constraints, search.l)
    for p, v in zip(pos, node):
        src[p] = v
        ranked[p] = [v, -1, -1]
    if not pos:
        _free_start(search, src, ranked)
        pos, keys = [0], ["free"]
    gaps = gaps_of(pos, keys, n, search.cyclic)
    if method == "graph_path":
        meetings = _graph_level(
            search, src, ranked, gaps, params, graph_threshold, graph_slack, rng
        )
    else:
        meetings = {}
        for g in gaps:
            mp = search.fill_gap(src, ranked, g, None)
            if mp is not None:
                meetings[g.key] = mp
    if (src < 0).any():  # pragma: no cover - every gap fills or raises
        raise SynthesisError(f"level {search.l}: nodes {np.flatnonzero(src < 0)} left empty")
    return LevelResult(src, ranked, meetings)


class _SmoothedParentRefinement(LevelRefinement):
    """Refinement whose ancestor windows read the parent level's *smoothed* output
    (Moradoff §3.8: every level is smoothed before the next finer one is synthesized
    from it), not the input nodes its source track copies.

    ``parent``: :func:`~mocapflow.stages.texture.assemble.smooth_level` of the level
    above.  The input's parent level and that output are one view (input nodes
    ``0 … n - 1``, output node ``T`` at ``n + T``), so
    :func:`~mocapflow.stages.texture.neighbourhood.window_cost` compares them as it
    compares input nodes; the candidate's own parent stays the input's.
    """

    def __init__(self, views, level, n_out, cyclic, upper, params, rng, *, parent):
        super().__init__(views, level, n_out, cyclic, upper, params, rng)
        inp = views[level + 1]
        out = level_view(parent, inp.spacing)
        self._parent_view = LevelView(np.concatenate([inp.P, out.P]),
                                      np.concatenate([inp.R, out.R]), inp.spacing, inp.unit)
        self._parent_ids = inp.n + np.arange(parent.n_nodes)

    def _ancestor_cost(self, t, cands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The parent window around ``t // 2`` (smoothed output) with the candidate's
        parent (an input node) at its centre; ``t``: one position or one per candidate."""
        n_in = self.views[self.l + 1].n
        T = np.broadcast_to(t // 2 if not self.cyclic else (np.asarray(t) % self.n) // 2,
                            cands.shape)
        C = cands // 2
        key, inv = np.unique(np.stack([T, C]), axis=1, return_inverse=True)
        ov = self._out_values(self._parent_ids, key[0][:, None] + self.off[None, :])
        ov[:, self.blk] = key[1][:, None]
        iv = key[1][:, None] + self.off[None, :]
        iv[iv >= n_in] = -1  # past the input's end: empty, as in the input's own view
        num, den, _ = window_cost(self._parent_view, ov, iv, self.blk, self.pw)
        inv = np.ravel(inv)
        return num[inv], den[inv]


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
    level_smoothing: Callable[..., PyramidLevel] | None = None,
) -> tuple[np.ndarray, dict]:
    """The finest source track of a constrained multi-resolution synthesis.

    The coarsest level is searched (:func:`_coarsest_level`), every finer one
    refined from the level above
    (:class:`~mocapflow.stages.texture.refine.LevelRefinement`; with
    ``level_smoothing``, from the level above smoothed:
    :class:`_SmoothedParentRefinement`).

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
    level_smoothing : callable, optional
        ``level_smoothing(l, src, constrained=…)`` -> the smoothed output of level ``l``
        (a :class:`~mocapflow.stages.texture.pyramid.PyramidLevel`, e.g.
        :func:`~mocapflow.stages.texture.assemble.smooth_level` with the skeleton and
        smoothing options bound): every level above the finest is smoothed before the
        next finer one is refined from it (``smooth_levels="every"``).  ``None``: the
        source tracks only (the finest is smoothed by the assembly).

    Returns
    -------
    source_index : (L,) int ndarray
    info : dict
        ``meetings``: gap key -> meeting point: the seam of the finest track it became
        (synthesis frame ``t``, the jump between ``t - 1`` and ``t``;
        :func:`_follow_meetings`).
    """
    pinned = list(constraints)  # the frames smoothing keeps (the user's constraints)
    if not constraints and not cyclic:
        constraints = [(0, 0)]  # unconstrained: the output starts where the input starts
    views = [level_view(pyramid.levels[l], 2.0**l) for l in range(levels)]
    n_out = [-(-length // 2**l) for l in range(levels)]
    top = levels - 1
    upper = _coarsest_level(
        LevelSearch(views, top, n_out, cyclic, None, params, rng),
        constraints,
        method=method,
        params=params,
        graph_threshold=graph_threshold,
        graph_slack=graph_slack,
        rng=rng,
    )
    meetings = dict(upper.meetings)
    for l in range(top - 1, -1, -1):
        pos, node, _ = _anchors(constraints, l)
        if level_smoothing is None:
            refinement = LevelRefinement(views, l, n_out, cyclic, upper, params, rng)
        else:
            parent = level_smoothing(l + 1, upper.src,
                                     constrained=_anchors(pinned, l + 1)[0])
            refinement = _SmoothedParentRefinement(views, l, n_out, cyclic, upper, params,
                                                   rng, parent=parent)
        upper = refinement.refine(dict(zip(pos, node)))
        meetings = _follow_meetings(meetings, upper.src, pos, cyclic)
    info: dict[str, Any] = {"meetings": {str(k): int(v) for k, v in meetings.items()}}
    return upper.src.copy(), info


def _follow_meetings(meetings: dict, src: np.ndarray, anchor_pos: list[int],
                     cyclic: bool) -> dict:
    """Each meeting point carried to the refined level: the seam of the refined track
    nearest twice its parent position, between the gap's two anchors (refinement
    searches every join again around there, :meth:`LevelRefinement._rejoin`).

    Parameters
    ----------
    meetings : dict
        Gap key ``(i, j)`` (constraint indices, ``"free"``: the free start of a loop
        without constraints, node 0) -> meeting position at the parent level.
    src : (n,) int ndarray
        Source track of the refined level.
    anchor_pos : list of int
        Constraint positions at the refined level.
    cyclic : bool

    Returns
    -------
    dict
        Gap key -> seam position (``t``: the jump lies between ``t - 1`` and ``t``); a
        gap whose refined track has no seam left between its anchors is dropped.
    """
    seams = seams_from_source(src, cyclic=cyclic)
    n = src.size
    out = {}
    for key, p in meetings.items():
        # a loop without constraints has one free anchor at output node 0 ("free")
        lo, hi = (anchor_pos[a] if isinstance(a, int) else 0 for a in key)
        if cyclic and hi <= lo:
            hi += n
        cand = np.concatenate([seams, seams + n]) if cyclic else seams
        cand = cand[(cand > lo) & (cand <= hi)]
        if cand.size:
            target = 2 * p + (n if cyclic and 2 * p <= lo else 0)
            out[key] = int(cand[np.argmin(np.abs(cand - target))] % n)
    return out


# --------------------------------------------------------------------------- stage

#: Most output frames per synthesized frame ``output_rate`` may make (e.g. 30 -> 480 fps).
MAX_OUTPUT_UPSAMPLE = 16


def _rates(motion: Motion, output_rate: float | None) -> tuple[float, float]:
    """``(source_rate, output_rate)``: the rate the file was read at and the output's.

    The source rate is ``motion.attrs["resampled_from_rate"]`` (before the ingest
    resampled it), else ``motion.rate``; the output rate defaults to it.
    """
    source = float(motion.attrs.get("resampled_from_rate", motion.rate))
    if output_rate is None:
        return source, source
    if not isinstance(output_rate, (int, float)):
        raise SynthesisError(f"output_rate: must be a number or null, got {output_rate!r}")
    rate = float(output_rate)
    if not (math.isfinite(rate) and 0 < rate <= MAX_OUTPUT_UPSAMPLE * motion.rate):
        raise SynthesisError(
            f"output_rate: must be a number in (0, {MAX_OUTPUT_UPSAMPLE} x the synthesis "
            f"rate {motion.rate:g}], got {output_rate}"
        )
    return source, rate


def _synthesis_constraints(constraints, rate: float, source_rate: float, output_rate: float):
    """Constraints ``[source frame, output frame]`` as frames at the synthesis ``rate``.

    Input frames count at ``source_rate`` (the file's 0-based frame index), output
    frames at ``output_rate``; both are rounded to the nearest synthesis frame.
    """
    if not constraints or (source_rate == rate and output_rate == rate):
        return constraints
    out = []
    for c in constraints:
        if len(c) != 2:
            return constraints  # left to _check_constraints' message
        out.append([round(int(c[0]) * rate / source_rate), round(int(c[1]) * rate / output_rate)])
    return out


def _synth_report(
    length: int,
    n_frames: int,
    levels: int,
    method: str,
    loop: bool,
    constraints: list[tuple[int, int]],
    info: dict,
    assembly: dict[str, Any],
    *,
    seed: int,
) -> dict[str, Any]:
    """The stage's report: the request, meeting points, assembly report, seed (no timings)."""
    report = {
        "length": length,
        "input_frames": n_frames,
        "levels": levels,
        "method": method,
        "loop": loop,
        "constraints": [list(c) for c in constraints],
        "meetings": info["meetings"],
        **assembly,
    }
    report["seed"] = seed
    return report


@stage("synth", outputs=("motion", "source_index", "report"),
       output_dims={"source_index": ("synthesis_frame",)})
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
    variety: float = 0.45,
    max_run: float = 0.25,
    usage_weight: float = 0.5,
    pose_weight: float = 0.03,
    pose_lines: int = 2,
    tolerance: float = 0.5,
    meeting_window: int = 4,
    graph_threshold: float = 0.1,
    graph_slack: float = 0.5,
    smoothing: bool = True,
    transition_blend: float = 0.33,
    smooth_levels: Literal["finest", "every"] = "finest",
    gaussian_width: int = 5,
    accel_tolerance: float = 1.0,
    jerk_tolerance: float = 1.0,
    max_widening: int = 12,
    foot_ik: bool = True,
    output_rate: float | None = None,
    ctx: Context,
) -> dict[str, Any]:
    """Constrained multi-resolution texture synthesis (Moradoff 2002).

    Parameters
    ----------
    pyramid : Pyramid
        Gaussian tree of ``motion`` (stage ``pyramid``).
    motion : Motion
        Input motion (``F`` frames), for the skeleton and world placement.  The
        synthesis works Y up, facing +Z; a motion in other axes (``attrs["up"]``,
        ``["forward"]`` from ``ingest_bvh``) is turned to them and the output back
        (``path`` points are ground-plane ``(x, z)`` of that Y-up frame).
    length : int, optional
        Output frames at the synthesis rate (default ``2 F``); any length.
    constraints : list of [input_frame, output_frame], optional
        Poses required at output frames (exact before smoothing).  Input frames
        are the source file's (0-based, at its rate), output frames count at the
        output rate; both are rounded to the nearest synthesis frame (the report
        gives ``constraints_synthesis`` and ``constraint_output_frames``, where
        the constrained poses land).
    path : list of [x, z] (or [x, y, z]), optional
        Ground path to follow.
    path_mode : {"polyline", "spline"}
        How ``path`` points are joined: straight segments, or a cubic spline
        through them (periodic when the path is closed).
    loop : bool
        Cyclic output (last → first seam smoothed).  With a closed ``path`` the
        stride is paced so the loop covers whole laps and its wrap is an ordinary
        step (a warning when that needs more than ±25 %: resize the path or the length).
    seed : int
        Variant; randomness comes from ``ctx.rng``.
    levels : int, optional
        Pyramid levels used (default all of the pyramid's, which by default are
        chosen by the rate: 4 at 30 fps, one more per doubling, 6 at 120 fps,
        :func:`~mocapflow.stages.texture.pyramid.levels_for_rate`; so the coarse
        plan spans the same time at any rate and a 120 fps synthesis is as fast).
    filter_size : int, optional
        Checked against the pyramid's.
    method : {"meeting_point", "graph_path"}
        Gap filler at the coarsest level.
    slots : int
        Neighbourhood half width (±3).
    ancestor_weight, current_weight, finer_weight : float
        Relative weights of the three neighbourhood levels (only their ratios
        count).  Equal by default: the thesis' heavier coarser level (e.g. 2 / 1 /
        0.5) measured worse on local diversity (``benchmarks/texture.py
        --level-weights 2/1/0.5``).
    candidate_range : int
        ± nodes around the children of the parent's 3 best matches (±4).
    k_best : int
        Random choice among the k best at all but the finest level (2–3).
    variety : float
        How new the arrangement is, 0–1 (default 0.45).  At the coarsest level
        jumps are drawn among the k best whose cost lies within the
        ``variety`` quantile of the input's own best-jump costs (about the
        share of moments a drawn jump may leave): 0 keeps only the jumps the
        input's end forces (near-verbatim copies), 1 draws among the k best at
        every node as in the thesis.  Raise for more novelty, lower for longer
        verbatim stretches.  ``method="graph_path"`` draws each path step the same
        way (window: the quantile of the transition graph's own best-jump costs,
        :func:`~mocapflow.stages.texture.graph.jump_window`).
    max_run : float
        Longest verbatim run as a fraction of the input (0.25): a run that long
        must jump, where the jump fits best among its last positions, and the finer
        levels' joins keep it (``LevelRefinement._join_windows`` in
        :mod:`~mocapflow.stages.texture.refine`).  0 (or >= 1) disables.  graph_path
        keeps it in its search (less the few nodes refinement may add; where the graph
        has too few edges for it, nodes without a jump edge get their cheapest jump as
        one, and only where that is not enough the shortest limit it can keep applies:
        raise ``graph_threshold``).
    usage_weight : float
        Preference for input material not used yet (coverage of the input): a
        candidate's rank rises by ``usage_weight`` draw windows per time the input
        it would play next (``2 slots + 1`` nodes, mean) is already in the output;
        the same in graph_path's draw.  0 disables.
    pose_weight : float
        Finest-level joins also cost ``pose_weight`` × how far apart in pose the
        two joined input lines stay around the seam (RMS over the joints of their
        6-D rotations, leaves included; 0, the thesis: velocities only).  Raising it
        lowers local diversity and global diversity together (measured in
        :class:`~mocapflow.stages.texture.search.SearchParams`); the default 0.03
        with ``variety`` 0.45 and ``max_run`` 0.25 is the balance measured there.
    pose_lines : int
        With ``pose_weight``, nearest input lines (in that pose sense) tried at each
        finest-level join beside the one the coarser levels drew (2).
    tolerance : float
        Cost units within which the k best joins are drawn below the coarsest level.
    meeting_window : int
        ± nodes searched around each transition of the previous level (meeting
        points and jumps); at the coarsest level, ± nodes around where the two
        fronts of a gap met (the lowest summed sequence cost wins).
    graph_threshold : float
        Quantile of jump costs kept as transition-graph edges.
    graph_slack : float
        DFS cost bound relative to the cheapest path.
    smoothing : bool
        Adaptive local smoothing (Moradoff §3.8).
    transition_blend : float
        Seconds of a cross-fade of every seam between the two input lines it joins,
        before the adaptive smoothing (an addition to §3.8,
        :func:`~mocapflow.stages.texture.smoothing.transition_blend`): each blended
        frame mixes the frame that continues the left line with the frame that leads
        into the right line, so the seam keeps the input's detail where a Gaussian
        pass low-passes it, and only the seams that still fail the test are smoothed
        (their jerk tested over the fade).  0: the thesis' smoothing alone.  Ignored
        when ``smoothing`` is off.
    smooth_levels : {"finest", "every"}
        Levels smoothed: the finest only (the output motion), or, as the thesis,
        every level after its synthesis, in its own representation (joint rotations
        and root at ``rate / 2**l``), before the next finer level is refined from it
        (its ancestor windows then read the smoothed level).  The finest measured
        better (``benchmarks/texture.py --smooth-levels every``; the package
        docstring's departures give the numbers).  Ignored when ``smoothing`` is off.
    gaussian_width : int
        Taps of the smoothing Gaussian (5) at 30 fps; at a higher synthesis rate
        the Gaussian keeps its width in seconds
        (:data:`~mocapflow.stages.texture.smoothing.SMOOTHING_RATE`).
    accel_tolerance : float
        Acceleration test threshold relative to the reference frames.
    jerk_tolerance : float
        A seam also fails the smoothing test while its jerk exceeds this
        multiple of the input's p99 jerk (0 disables).
    max_widening : int
        Most smoothing passes per seam; pass ``k`` smooths ``±k`` frames at 30 fps
        (``±k · rate / 30`` frames at the synthesis rate).
    foot_ik : bool
        Pin the stance toes with two-bone leg IK after smoothing (no foot skate
        at the seams; constrained frames untouched).
    output_rate : float, optional
        Frames per second of the output motion; default the source's (the rate
        its file was read at), so the BVH export keeps the input's ``Frame Time``.
        Resampled from the synthesis rate by a C² rotation spline.
    ctx : Context

    Returns
    -------
    dict
        ``motion`` (Motion on the input skeleton and in its units, at the output
        rate), ``source_index`` ((L,) int ndarray, input frame per output frame
        before smoothing, at the synthesis rate), ``report`` (JSON: seams, meeting
        points, smoothing, constraint errors, ``rate`` (synthesis), ``source_rate``,
        ``output_rate``, ``output_frames``, ``constraints_synthesis``,
        ``constraint_output_frames``, ``jerk_p99`` (m/s³ at the output rate),
        ``seed``; the times of
        the steps ``search`` and ``assemble`` go to ``ctx.timer``, never the report).

    Raises
    ------
    ConstraintError
        Constraint outside the input or output, or closer than the coarsest level separates.
    UnreachableGapError
        graph_path: a gap no path of its length can fill.
    SynthesisError
        Pyramid and motion that do not match, bad ``levels`` or ``length``.
    PathError
        A path that cannot be followed.
    """
    axes = {"up": motion.attrs.get("up", "+y"), "forward": motion.attrs.get("forward", "+z")}
    motion = reorient_motion(motion)  # the synthesis works Y up, facing +Z (as pyramid)
    F = motion.n_frames
    source_rate, out_rate = _rates(motion, output_rate)
    levels = _levels_used(pyramid, F, levels, filter_size)
    L = 2 * F if length is None else int(length)
    if L < 2:
        raise SynthesisError(f"length must be >= 2 frames, got {L}")
    if pose_weight < 0 or pose_lines < 0:
        raise SynthesisError(f"pose_weight and pose_lines must be >= 0, got {pose_weight}, "
                             f"{pose_lines}")
    given = [list(c) for c in constraints or []]
    cons = _constraints_at_synthesis_rate(given, motion.rate, source_rate, out_rate, F, L,
                                          levels, loop)
    curve = PathCurve.from_points(path, mode=path_mode) if path is not None else None
    params = SearchParams(
        slots=slots, level_weights=(ancestor_weight, current_weight, finer_weight),
        candidate_range=candidate_range, k_best=k_best, tolerance=tolerance,
        meeting_window=meeting_window, variety=variety, max_run=max_run,
        usage_weight=usage_weight, pose_weight=pose_weight, pose_lines=pose_lines,
        pose_span=max(1, round(POSE_SPAN_FRAMES * rate_scale(motion.rate))),
    )
    smooth_opts = dict(gaussian_width=gaussian_width, accel_tolerance=accel_tolerance,
                       max_widening=max_widening,
                       jerk_tolerance=jerk_tolerance if jerk_tolerance > 0 else None)
    per_level = None
    if smoothing and smooth_levels == "every":
        per_level = functools.partial(smooth_level, pyramid, motion.skeleton, loop=loop,
                                      **smooth_opts)
    with ctx.timer("search"):
        src, info = synthesize_source(
            pyramid, L, cons, levels=levels, cyclic=loop, method=method, params=params,
            rng=ctx.rng, graph_threshold=graph_threshold, graph_slack=graph_slack,
            level_smoothing=per_level,
        )
    with ctx.timer("assemble"):
        out, assembly = assemble_motion(
            pyramid, motion, src, constraints=cons, loop=loop, curve=curve,
            smoothing=smoothing, transition_blend=transition_blend, foot_ik=foot_ik,
            warn=ctx.warn, **smooth_opts,
        )
    out, assembly = _at_output_rate(out, assembly, motion.rate, source_rate, out_rate, cons,
                                    loop)
    out = reorient_motion(out, **axes)  # back in the source's axes
    shown = sorted(([int(c[0]), int(c[1])] for c in given), key=lambda c: c[1])  # as given
    report = _synth_report(L, F, levels, method, loop, shown, info, assembly, seed=seed)
    _key_figures(report, src, ctx)
    return {"motion": out, "source_index": src, "report": report}


def _key_figures(report: dict[str, Any], src: np.ndarray, ctx: Context) -> None:
    """The run summary's figures of a synthesis (``ctx.figure``; never in an output)."""
    ctx.figure("seams", int(report["n_seams"]))
    ctx.figure("longest verbatim run", longest_verbatim_run(src))
    if report["constraints"]:
        ctx.figure("constraint error deg", round(float(report["constraint_max_angle_deg"]), 3))
    if report.get("jerk_p99") is not None:
        ctx.figure("jerk p99 m/s³", round(float(report["jerk_p99"]), 1))



def _constraints_at_synthesis_rate(given: list[list[int]], rate: float, source_rate: float,
                                   out_rate: float, F: int, L: int, levels: int, loop: bool
                                   ) -> list[tuple[int, int]]:
    """``(input frame, output frame)`` constraints in source / output frame numbers, as
    checked ``(input, output)`` frames at the synthesis ``rate`` (rounded to the nearest).

    Raises
    ------
    ConstraintError
        As :func:`_check_constraints`, saying which rates the frames count at.
    """
    try:
        return _check_constraints(
            _synthesis_constraints(given, rate, source_rate, out_rate), F, L, levels, loop)
    except ConstraintError as e:
        if source_rate == rate and out_rate == rate:
            raise
        raise ConstraintError(
            f"{e} (frames at the synthesis rate {rate:g} fps; the constraints "
            f"{given} count input frames at the source's {source_rate:g} fps and output "
            f"frames at {out_rate:g} fps)"
        ) from None


def _at_output_rate(out: Motion, assembly: dict, rate: float, source_rate: float,
                    out_rate: float, cons: list[tuple[int, int]], loop: bool = False
                    ) -> tuple[Motion, dict]:
    """The synthesized motion at ``out_rate`` (C² rotation spline; a loop resampled as one,
    its last → first step an ordinary step at ``out_rate`` too) and the report's rate
    fields: ``rate`` (synthesis), ``source_rate``, ``output_rate``, ``output_frames``,
    the constraints at both rates, ``jerk_p99`` (m/s³) at the output rate."""
    if abs(out_rate - out.rate) > 1e-9 * out.rate:
        out = resample_motion(out, out_rate, method="spline", cyclic=loop)
    jerk = jerk_p99(motion_positions(out), out.rate)
    return out, {
        **assembly,
        "rate": rate,
        "source_rate": source_rate,
        "output_rate": out.rate,
        "output_frames": out.n_frames,
        "constraints_synthesis": [list(c) for c in cons],
        "constraint_output_frames": [round(j * out_rate / rate) for _, j in cons],
        "jerk_p99": jerk if math.isfinite(jerk) else None,
    }
