"""Neighbourhood search, gap growing and meeting points (Moradoff §3.5–3.7).

The output of every pyramid level is a *source track*: for each output node the
index of the input node (same level) it copies.  A node is chosen by comparing
its neighbourhood in the output with the neighbourhood of each candidate in the
input, on three levels of the tree (:meth:`LevelSearch.cost_rows`):

* the **ancestor** level (``l + 1``, already synthesised) around the parent,
* the **current** level (``l``) around the node, only the slots filled so far,
* the **finer** level (``l - 1``) around the node's children, where every
  filled node provisionally brings the children of its source.

Every level contributes ``±slots`` slots, weighted by ``level_weights``; the
distance of two windows of one level is
:func:`~mocapflow.stages.texture.neighbourhood.window_cost` (velocities,
``‖d‖∞ + ‖d‖₀.₅`` per slot pair).  Empty slots (not yet synthesised, or outside
the input) have weight 0 and the weights are renormalised; a candidate without
input where the output next to it is already filled is rejected, and so is one
that would freeze or rewind the motion (``≤ slots`` nodes back from a filled
neighbour).

Coarsest level (:class:`LevelSearch`): gaps between anchors (constraints) are
grown from both sides (:meth:`LevelSearch.fill_gap`), alternating one node of
the left front and one of the right front in ONE output, so that the last nodes
of each front are searched with the other front's nodes in their neighbourhood
(``alternate=False``: the left half first, then the right half), each node
searched exhaustively over the input (:meth:`LevelSearch.fill`).  Where the
fronts meet, the *meeting point* (:meth:`LevelSearch._meet`) is moved within
``meeting_window`` nodes (the front that gives up positions is replaced there by
the other one played on verbatim), the node at the join searched over the input,
and the arrangement with the lowest *summed sequence cost* wins
(:meth:`LevelSearch.sequence_costs`: the neighbourhood costs of the gap's nodes
in the finished track; only nodes within ``slots`` of a changed one differ, so
only those are summed), not the meeting node's own cost; a join that would
lengthen a verbatim run past ``max_run`` is refused.  Gaps with one anchor
grow from it.

Finer levels (:class:`~mocapflow.stages.texture.refine.LevelRefinement`, a
``LevelSearch``): son selection, then every transition of the parent level is
searched again around twice its position (see :mod:`~mocapflow.stages.texture.refine`).

Randomisation (:meth:`LevelSearch._draw`): at every level but the finest, the
node (or join) is drawn at random (seeded) among the ``k_best`` best *distinct*
candidates (closer than ``slots`` nodes counts as the same match).  At the
coarsest level the natural successor of a run always matches perfectly (cost
0), so a window of a fixed number of cost units around the best admitted only
the rare near-perfect jumps of a periodic input: the outputs were near-verbatim
copies (a 512-frame salsa played through in one 510-frame run).  The window is
therefore measured on the input's own transitions: the ``variety`` quantile of
the best jump cost away from every input node (:meth:`LevelSearch.jump_threshold`)
— ``variety`` is roughly the share of moments a drawn jump may leave.
Candidates are ranked by cost plus ``usage_weight`` windows per time the input
they would play next is already in the output (coverage), a new draw happens
once the previous transition has ``slots`` verbatim nodes behind it
(:meth:`LevelSearch._settled`), and a run reaching ``max_run`` of the input
must end: its jump is searched at the last ``relocate`` positions of the run,
exhaustively over the input (:meth:`LevelSearch._jump_earlier`).  Finer levels
keep the coarse plan and draw joins within ``tolerance`` cost units (the unit:
the input's median frame-to-frame velocity change).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mocapflow.stages.texture.neighbourhood import (
    pair_tables,
    slot_pair_weights,
    window_cost,
)

__all__ = [
    "Gap",
    "LevelResult",
    "LevelSearch",
    "SearchParams",
    "SynthesisError",
    "ahead_usage",
    "gaps_of",
]


class SynthesisError(ValueError):
    """The synthesis cannot satisfy its inputs (message names the gap / constraint)."""


@dataclass
class SearchParams:
    """Parameters of the neighbourhood search (Moradoff's names).

    Attributes
    ----------
    slots : int
        Half width of a neighbourhood on each level (±3).
    level_weights : tuple of float
        Relative weights of the (ancestor, current, finer) levels.
    candidate_range : int
        ± nodes around the children of the parent's best matches (±4).
    n_parent_matches : int
        Parent matches whose children are candidates (3).
    k_best : int
        Random choice among the ``k_best`` best (2–3) at all but the finest level.
    tolerance : float
        Below the coarsest level, joins within ``tolerance`` cost units of the
        best are drawn (the unit: the input's median frame-to-frame velocity
        change).
    meeting_window : int
        ± nodes around the previous level's transitions searched at finer levels.
    coherence : float
        Cost units subtracted, below the coarsest level, for a candidate that
        continues a neighbour's source in node-by-node growth (0 disables).
    variety : float
        The knob of novelty, 0–1: at the coarsest level alternatives are drawn
        within the ``variety`` quantile of the input's own best-jump costs
        (0: only the forced jumps; 0.45 default; 1: the thesis' plain draw
        among the ``k_best``).
    max_run : float
        Longest verbatim run, as a fraction of the input (0.25): kept at the
        coarsest level (one node of margin) and by the finer levels' joins
        (:meth:`~mocapflow.stages.texture.refine.LevelRefinement._join_windows`,
        ``_rejoin``); ``0`` or ``>= 1`` disables.
    usage_weight : float
        Windows (``variety`` window, at least one cost unit) added to a
        candidate's rank per time the input it would play next is already in
        the output (0.5; 0 disables).
    relocate : int
        Positions, back into the run, where a forced jump (end of the input,
        ``max_run``) is searched.
    alternate : bool
        Grow the two fronts of a gap alternately, one node each (the thesis);
        False: the left front fills its half first, then the right front.
    pose_weight : float
        At the finest level a join also costs ``pose_weight`` × how far apart in pose
        (:func:`~mocapflow.stages.texture.neighbourhood.pose_distance`: RMS over the
        joints of their 6-D rotations) the two lines it joins stay within
        ``±pose_span`` frames (``LevelRefinement.line_costs`` in
        :mod:`~mocapflow.stages.texture.refine`), so a transition joins lines whose
        poses AND velocities match around it and smoothing has little to bridge.  Rotations,
        not positions: a leaf joint's turn moves no joint position, yet it is a pose
        (the walk ``cmu_131_02``'s right thumb jitters, and gave 52 % of its seams'
        6-D discontinuity while the position-based search could not see it).  0: the
        thesis' velocity neighbourhood only.

        The defaults (0.03, with ``pose_lines`` 2, ``variety`` 0.45, ``max_run`` 0.25,
        ``usage_weight`` 0.5 and the synth stage's ``transition_blend`` 0.33 s) were
        the best of the last of several random searches (60 settings with ``max_run``
        0.25; about 430 before it, on intermediate versions of this code, pointed
        there), 3 inputs × seeds 0-2, 1,024 frames at 30 fps
        (``benchmarks/texture_defaults.py`` scores any setting so): the lowest local
        diversity among the settings whose global diversity is at least the GenMM
        baseline's on all three inputs.  A stronger pose term
        lowers local diversity and global diversity with it: ``texture_defaults.py
        --setting '{"pose_weight": 0.2, "pose_lines": 4, "variety": 0.3, "max_run":
        0.3, "usage_weight": 0.5}'`` gives local 0.090 / 0.115 / 0.110 on salsa /
        walk / figure-8 walk (the baseline's 0.109 / 0.129 / 0.168) but global 0.085 /
        0.105 / 0.102 (its 0.117 / 0.157 / 0.204); no setting had both local ≤ 1.2 ×
        and global ≥ the baseline's on all three.  Part of why: with a strong pose
        term the finest joins take lines a few frames from the left line's own
        continuation (salsa, ``pose_weight`` 1, ``pose_lines`` 8: median jump 3
        frames), seams in name only.  Tried and dropped: finest joins kept ≥ 0.3-1 s
        from that continuation; pose lines tried only when their poses 8-30 frames
        from the join differ from the left line's at least 0.7 × as much as the drawn
        line's do; the coarsest level's jumps also costed by the finest-level pose
        distance of the lines they join (divided by its median, times 3 cost units).
        The best of these (``pose_weight`` 1, ``pose_lines`` 8, 0.3 s, 0.7, 3), seeds 0-4:
        local 0.135 / 0.151 / 0.156 (baseline 0.104 / 0.133 / 0.169), global 0.148 /
        0.188 / 0.190 (0.108 / 0.162 / 0.210), salsa coverage 0.85; with those joins
        also costing 0.5 cost units per use of the input they would play, salsa's
        coverage is back (0.99) but local 0.135 / 0.153 / 0.158, global 0.147 / 0.199 /
        0.187: the figure-8's global and salsa's local still fail.
        Also tried (seeds 0-4, local ÷ 1.2 × the baseline's / global ÷ the baseline's,
        salsa, walk, figure-8 walk): the coarsest level's jumps drawn within a window of
        absolute cost units instead of the ``variety`` quantile (1.2 units: the 0.53, 0.85
        and 0.83 quantile of the three inputs' best-jump costs), with ``pose_weight`` 0.2,
        ``pose_lines`` 4, ``usage_weight`` 1: 1.02 / 1.12, 1.02 / 1.20, 0.66 / 0.72 (coverage
        ≥ 0.98, jerk and skate ratios 0.94-1.03).  On the figure-8 walk the pose lines are
        a stride from the left line's own continuation (median jump 29 frames; 88 at the
        defaults), seams that replay the input a stride away; pose lines kept within 10
        frames of the drawn line lose the local gain (1.64 / 1.99, 1.83 / 2.05, 0.92 / 0.97).
        Shorter runs with a stronger pose term (same seeds and ratios; ``max_run`` 0.1-0.25,
        ``slots`` 2-3, ``pose_weight`` 0.15-0.7, ``pose_lines`` 4-8): each input meets both
        somewhere, never all three at once.  ``slots`` 2, ``max_run`` 0.15, ``pose_weight``
        0.4, ``pose_lines`` 8, ``variety`` 0.2: salsa 0.90 / 1.11, figure-8 walk 0.88 /
        1.14, walk 1.13 / 1.48 (its verbatim runs: median 16.5 frames at ``variety`` 0.45).
        The walk meets them at ``slots`` 3 and ``variety`` 0.45 (``pose_weight`` 0.4,
        ``pose_lines`` 8, ``max_run`` 0.12, ``transition_blend`` 0.6: 0.97 / 1.05;
        ``max_run`` 0.15, ``pose_weight`` 0.25, ``pose_lines`` 6: 0.98 / 1.03), where the
        figure-8's global falls to 0.72-0.81 (its runs replay its 29-frame stride) unless
        ``max_run`` is 0.1 (27 frames; 0.75 / 1.01 at ``pose_weight`` 0.25, ``pose_lines``
        6), where salsa's local is 1.58: its best jumps cost 1.6-2.4 × the walks' in pose,
        and at ``slots`` 3 it needs ``max_run`` ≥ 0.2.  Pose lines required to leave the
        left line's continuation (their poses 8-28 frames on at least 1.5 or 2.5 × as far
        from it as at the join) met no more inputs.
        ``benchmarks/texture.py --seeds 5`` (1,024 frames from the first 512 input
        frames), the previous default values (0, 4, 0.3, 0.3, 0.5, no cross-fade; on
        this code) -> these: global 0.164 -> 0.144, 0.185 -> 0.182, 0.167 -> 0.210
        (baseline 0.108, 0.162, 0.210); local 0.158 -> 0.157, 0.217 -> 0.193, 0.180 ->
        0.183 (baseline 0.104, 0.133, 0.169); jerk and skate ratios 0.94-1.02; coverage ≥ 0.98.
    pose_span : int
        Half span (finest frames) of the pose term's comparison of two lines
        (:meth:`~mocapflow.stages.texture.refine.LevelRefinement.line_costs`): the half
        window of the local patch metric, 7 frames at 30 fps; the ``synth`` stage scales
        it with the synthesis rate (the same ¼ s at any rate).
    pose_lines : int
        With ``pose_weight``, each finest-level join also tries the ``pose_lines``
        input lines nearest the left line in that sense (2)
        (:meth:`~mocapflow.stages.texture.refine.LevelRefinement._pose_lines`),
        beside the line the coarser levels drew (0: only that line).
    """

    slots: int = 3
    level_weights: tuple[float, float, float] = (1.0, 1.0, 1.0)
    candidate_range: int = 4
    n_parent_matches: int = 3
    k_best: int = 3
    tolerance: float = 0.5
    meeting_window: int = 4
    coherence: float = 0.25
    variety: float = 0.45
    max_run: float = 0.25
    usage_weight: float = 0.5
    relocate: int = 6
    alternate: bool = True
    pose_weight: float = 0.03
    pose_span: int = 7
    pose_lines: int = 2


def ahead_usage(counts: np.ndarray, span: int, side: int) -> np.ndarray:
    """Mean use of the ``span`` input nodes a candidate would play next.

    Parameters
    ----------
    counts : (n,) float ndarray
        Times each input node is already in the output.
    span : int
    side : {1, -1}
        1: the output grows forwards (nodes ``b … b+span-1``); -1: backwards.

    Returns
    -------
    (n,) float ndarray
    """
    n = counts.size
    c = np.concatenate([[0.0], np.cumsum(counts)])
    b = np.arange(n)
    lo = b if side > 0 else np.maximum(b - span + 1, 0)
    hi = np.minimum(b + span, n) if side > 0 else b + 1
    return (c[hi] - c[lo]) / (hi - lo)


def _longest_runs(vals: np.ndarray) -> np.ndarray:
    """Longest verbatim run (nodes playing the input forwards) of each row.

    Parameters
    ----------
    vals : (r, w) int ndarray
        Input node per position (-1: empty).

    Returns
    -------
    (r,) int ndarray
    """
    cont = (vals[:, 1:] == vals[:, :-1] + 1) & (vals[:, :-1] >= 0)
    out = np.zeros(vals.shape[0], dtype=np.int64)
    for k, row in enumerate(cont):
        edges = np.flatnonzero(np.diff(np.r_[0, row.astype(np.int8), 0]))
        out[k] = 1 + (int((edges[1::2] - edges[::2]).max()) if edges.size else 0)
    return out


# --------------------------------------------------------------------------- gaps


@dataclass
class Gap:
    """A run of output nodes between two anchors (positions unwrapped).

    Attributes
    ----------
    lo, hi : int
        Anchor positions (``lo = -1``: no left anchor; ``hi = n``: no right anchor).
    key : tuple
        Identity of the bounding anchors, stable across levels.
    """

    lo: int
    hi: int
    key: tuple
    left: bool = True
    right: bool = True

    @property
    def interior(self) -> range:
        """Positions to fill."""
        return range(self.lo + 1, self.hi)


def gaps_of(anchor_pos: list[int], anchor_keys: list, n: int, cyclic: bool) -> list[Gap]:
    """Gaps between sorted anchors.

    Parameters
    ----------
    anchor_pos : list of int
        Sorted anchor positions in ``[0, n)`` (at least one).
    anchor_keys : list
        Identity of each anchor.
    n : int
        Output nodes.
    cyclic : bool
        Loop mode: the last gap wraps to the first anchor (positions ``>= n``).

    Returns
    -------
    list of Gap
    """
    gaps = []
    for a, b, ka, kb in zip(anchor_pos[:-1], anchor_pos[1:], anchor_keys[:-1], anchor_keys[1:]):
        gaps.append(Gap(a, b, (ka, kb)))
    if cyclic:
        gaps.append(Gap(anchor_pos[-1], anchor_pos[0] + n, (anchor_keys[-1], anchor_keys[0])))
    else:
        if anchor_pos[0] > 0:
            gaps.append(Gap(-1, anchor_pos[0], ("start", anchor_keys[0]), left=False))
        if anchor_pos[-1] < n - 1:
            gaps.append(Gap(anchor_pos[-1], n, (anchor_keys[-1], "end"), right=False))
    return gaps


# --------------------------------------------------------------------------- one level


@dataclass
class LevelResult:
    """Source track of one output level.

    Attributes
    ----------
    src : (n_out,) int ndarray
        Input node copied at each output node.
    ranked : (n_out, 3) int ndarray
        Best candidates of each node (-1 padded), best first.
    meetings : dict
        Gap key -> meeting position (unwrapped).
    """

    src: np.ndarray
    ranked: np.ndarray
    meetings: dict = field(default_factory=dict)


class LevelSearch:
    """Neighbourhood search on one output level.

    The three-level neighbourhood cost of a candidate (:meth:`cost`,
    :meth:`cost_rows`), the candidates of a node (:meth:`candidates`), the
    seeded draw (:meth:`choose`, :meth:`_draw`, :meth:`jump_threshold`),
    node-by-node growth (:meth:`fill`, with the forced jumps of
    :meth:`_jump_earlier` at the coarsest level) and the gaps and meeting
    points of the coarsest level (:meth:`fill_gap`, :meth:`_meet`,
    :meth:`sequence_costs`).  Finer
    levels are refined by the subclass
    :class:`~mocapflow.stages.texture.refine.LevelRefinement`.

    Parameters
    ----------
    views : list of LevelView
        Input pyramid, finest first.
    level : int
    n_out : list of int
        Output nodes per level.
    cyclic : bool
    upper : LevelResult or None
        The synthesised coarser level (``None`` at the coarsest).
    params : SearchParams
    rng : numpy.random.Generator
    """

    def __init__(self, views, level, n_out, cyclic, upper, params, rng):
        self.views = views
        self.l = level
        self.n_out = n_out
        self.n = n_out[level]
        self.cyclic = cyclic
        self.upper = upper
        self.p = params
        self.rng = rng
        self.view = views[level]
        self._usage: np.ndarray | None = None
        self._tau: float | None = None
        self._tables: tuple | None = None
        self._after_run: np.ndarray | None = None
        #: cost unit of every level: natural frame-to-frame velocity change of the input
        self.unit = views[0].unit
        self.coarsest = level == len(views) - 1
        self.randomize = level > 0
        #: longest verbatim run (coarsest nodes) before a jump is forced
        self.max_run_nodes: int | None = None
        if self.coarsest and 0 < params.max_run < 1:
            # one node of margin: refinement may lengthen a run by a few frames
            self.max_run_nodes = max(2 * params.slots, int(params.max_run * self.view.n) - 1)
        S = params.slots
        self.off = np.arange(-S, S + 1)
        self.pw = slot_pair_weights(self.off, 0.0, max(S, 1))
        self.blk = self.off == 0
        self.off_f = np.arange(-S, S + 2)
        self.pw_f = slot_pair_weights(self.off_f, 0.5, max(S, 1))
        self.blk_f = (self.off_f == 0) | (self.off_f == 1)

    # ----------------------------------------------------------- positions
    def _wrap(self, pos: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Map positions to ``[0, n)``; second value marks positions that exist."""
        if self.cyclic:
            return np.mod(pos, n), np.ones(pos.shape, dtype=bool)
        return np.minimum(np.maximum(pos, 0), n - 1), (pos >= 0) & (pos < n)

    def _out_values(self, src: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Input node at output positions ``pos`` (unwrapped; -1 where none)."""
        n = src.shape[0]
        if self.cyclic:
            return src[np.mod(pos, n)]
        ok = (pos >= 0) & (pos < n)
        return np.where(ok, src[np.where(ok, pos, 0)], -1)

    def _out_value(self, src: np.ndarray, t: int) -> int:
        """:meth:`_out_values` of one position (a Python int, no arrays)."""
        n = src.shape[0]
        if self.cyclic:
            return int(src[t % n])
        return int(src[t]) if 0 <= t < n else -1

    # ----------------------------------------------------------- costs
    def cost(self, src: np.ndarray, t: int, cands: np.ndarray) -> np.ndarray:
        """Total neighbourhood cost of placing each candidate at output node ``t``.

        Parameters
        ----------
        src : (n_out,) int ndarray
            Current source track of the level (-1: empty).
        t : int
            Output position (unwrapped in loop mode).
        cands : (m,) int ndarray

        Returns
        -------
        (m,) float ndarray
            ``inf`` for rejected candidates; ``nan`` when no slot could be compared.
        """
        m = cands.shape[0]
        ov = np.broadcast_to(self._out_values(src, t + self.off), (m, self.off.size)).copy()
        ov[:, self.blk] = cands[:, None]
        return self.cost_rows(ov, t, tables=self._coarse_tables())

    def _coarse_tables(self) -> tuple | None:
        """Pair distances of this level and the finer one, tabulated at the coarsest
        level only (small levels searched over every input node; built once)."""
        if not self.coarsest:
            return None
        if self._tables is None:
            # jumps out of the input pair are rare here (computed); of the finer level only
            # the entries between children are read (the others computed if ever needed)
            self._tables = (pair_tables(self.view, out_of=False),
                            pair_tables(self.views[self.l - 1], out_of=False, children=True)
                            if self.l > 0 else None)
        return self._tables

    def cost_rows(
        self, ov: np.ndarray, t, *, coherence: bool = True, strict: bool = True,
        tables: tuple | None = None, allow_stall: bool = False,
    ) -> np.ndarray:
        """Neighbourhood cost of output windows around node ``t``, one context per row.

        Parameters
        ----------
        ov : (m, 2 slots + 1) int ndarray
            Input node at output positions ``t - slots … t + slots`` (-1: empty);
            the centre column is the candidate.
        t : int or (m,) int ndarray
            Output position (unwrapped in loop mode), one for all rows or one per row.
        coherence : bool
            Apply the coherence bonus.
        strict : bool
            Reject candidates whose input lacks a slot next to them that the
            output has (False: just leave that slot out).
        tables : (PairTables, PairTables or None), optional
            :func:`~mocapflow.stages.texture.neighbourhood.pair_tables` of this
            level and the finer one (same costs, faster).
        allow_stall : bool
            Keep candidates that replay one of the ``slots`` input nodes just
            played beside them (a stall; rejected by default).

        Returns
        -------
        (m,) float ndarray
        """
        la, lc, lf = self.p.level_weights
        S = self.p.slots
        cands = ov[:, S]
        iv = cands[:, None] + self.off[None, :]
        tab, tab_f = tables if tables is not None else (None, None)
        num, den, reject = window_cost(self.view, ov, iv, self.blk, self.pw, tab)
        # (a weight of 1 multiplies nothing: x * 1.0 is x, so it is skipped)
        if lc != 1.0:
            num, den = lc * num, lc * den
        if self.upper is not None and la > 0:
            a_num, a_den = self._ancestor_cost(t, cands)
            if la != 1.0:
                a_num, a_den = la * a_num, la * a_den
            num, den = num + a_num, den + a_den
        if self.l > 0 and lf > 0:
            f_num, f_den = self._finer_cost(ov, t, tab_f)
            if lf != 1.0:
                f_num, f_den = lf * f_num, lf * f_den
            num, den = num + f_num, den + f_den
        with np.errstate(invalid="ignore", divide="ignore"):
            total = num / den
        a, b = ov[:, S - 1], ov[:, S + 1]
        stall = ((a >= 0) & (cands <= a) & (cands >= a - S)) | (
            (b >= 0) & (cands >= b) & (cands <= b + S)
        )
        total[(reject & strict) | (stall & (not allow_stall))] = np.inf
        if coherence and self.p.coherence > 0 and not self.coarsest:
            coherent = ((cands == a + 1) & (a >= 0)) | ((cands == b - 1) & (b >= 0))
            total = np.where(coherent, total - self.p.coherence * self.unit, total)
        return total

    def _ancestor_cost(self, t, cands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ancestor level: the parent window around ``t // 2`` with the candidate's parent
        at its centre (``t``: one position, or one per candidate)."""
        view = self.views[self.l + 1]
        up = self.upper.src
        T = t // 2 if not self.cyclic else (t % self.n) // 2
        if np.ndim(T):  # one parent window per row: each distinct (T, parent) once
            T, P = np.asarray(T), cands // 2
            t0, p0 = int(T.min()), int(P.min())
            width = int(P.max()) - p0 + 1
            key, inv = np.unique((T - t0) * width + (P - p0), return_inverse=True)
            inv = inv.ravel()
            ov = self._out_values(up, (key // width + t0)[:, None] + self.off[None, :])
            C = key % width + p0
        else:
            C, inv = np.unique(cands // 2, return_inverse=True)
            ov = np.broadcast_to(self._out_values(up, T + self.off), (C.size, self.off.size))
            ov = ov.copy()
        ov[:, self.blk] = C[:, None]
        iv = C[:, None] + self.off[None, :]
        num, den, _ = window_cost(view, ov, iv, self.blk, self.pw)
        return num[inv], den[inv]

    def _finer_cost(self, ov: np.ndarray, t, tables=None) -> tuple[np.ndarray, np.ndarray]:
        """Finer level: every filled node brings the children of its source."""
        view = self.views[self.l - 1]
        nf = self.n_out[self.l - 1]
        S = self.p.slots
        rel = self.off_f // 2
        parity = self.off_f - 2 * rel
        pv = ov[:, S + rel]
        prov = np.where(pv >= 0, 2 * pv + parity[None, :], -1)
        if not self.cyclic:
            u = 2 * np.reshape(t, (-1, 1)) + self.off_f[None, :]
            prov[np.broadcast_to((u < 0) | (u >= nf), prov.shape)] = -1
        prov[prov >= view.n] = -1
        iv = 2 * ov[:, S : S + 1] + self.off_f[None, :]
        num, den, _ = window_cost(view, prov, iv, self.blk_f, self.pw_f, tables)
        return num, den

    # ----------------------------------------------------------- candidates
    def candidates(self, src: np.ndarray, t: int) -> np.ndarray:
        """Candidate input nodes for output node ``t``.

        All input nodes at the coarsest level; otherwise the children (same
        parity) of the parent's best matches ``±candidate_range`` and the natural
        continuations of filled neighbours.
        """
        n_in = self.view.n
        if self.coarsest:
            return np.arange(n_in)
        tt = t % self.n if self.cyclic else t
        T = tt // 2
        T = min(T, self.upper.src.shape[0] - 1)
        par = self.upper.ranked[T]
        par = par[par >= 0][: self.p.n_parent_matches]
        r = self.p.candidate_range
        kids = (2 * par[:, None] + (tt - 2 * T) + np.arange(-r, r + 1)[None, :]).ravel()
        nb = self._out_values(src, np.array([t - 1, t + 1]))
        cont = [nb[0] + 1] if nb[0] >= 0 else []
        if nb[1] >= 0:
            cont.append(nb[1] - 1)
        c = np.unique(np.concatenate([kids, np.asarray(cont, dtype=np.int64)]))
        return c[(c >= 0) & (c < n_in)]

    # ----------------------------------------------------------- choice
    def choose(
        self, cands: np.ndarray, cost: np.ndarray, where: str, *, draw: bool = True
    ) -> tuple[int, np.ndarray]:
        """Pick a node: the best at the finest level, else random among the k best.

        Parameters
        ----------
        cands, cost : (m,) ndarray
        where : str
            Node description for error messages.
        draw : bool
            Allow the random draw (False: take the best).

        Returns
        -------
        node : int
        ranked : (3,) int ndarray
            The best three distinct candidates (-1 padded).
        """
        cost = np.where(np.isnan(cost), 0.0, cost)
        perm = self.rng.permutation(cands.size)  # random tie-breaking
        cands, cost = cands[perm], cost[perm]
        order = np.argsort(cost, kind="stable")
        order = order[np.isfinite(cost[order])]
        if order.size == 0:
            raise SynthesisError(f"no input node fits {where} (every candidate was rejected)")
        ranked = cands[order]
        node = int(ranked[0])
        if draw and self.randomize and self.p.k_best > 1:
            pick = self._draw(ranked, cost[order], ranked)
            node = int(ranked[pick])
        top = np.full(3, -1, dtype=np.int64)
        top[: min(3, ranked.size)] = ranked[:3]
        return node, top

    def jump_costs(self) -> np.ndarray:
        """Cost of the best jump away from every input node (this level's search).

        For each input node ``a`` the output holds ``a-slots+1 … a`` (verbatim)
        and every input node ``b`` at least ``slots`` nodes from the natural
        successor ``a + 1`` is scored as the next node with :meth:`cost_rows`.

        Returns
        -------
        (n,) float ndarray
            ``min_b cost`` per ``a`` (``inf`` where no jump is possible).
        """
        n, S = self.view.n, self.p.slots
        b = np.arange(n)
        table = self.after_run_costs()
        if table is not None:
            far = np.abs(b[None, :] - (b[:, None] + 1)) >= S
            return np.where(far & np.isfinite(table), table, np.inf).min(axis=1)
        best = np.full(n, np.inf)
        for a, c in self._after_run_rows():
            far = np.abs(b[None, :] - (a[:, None] + 1)) >= S
            best[a] = np.where(far & np.isfinite(c), c, np.inf).min(axis=1)
        return best

    #: Largest input (nodes) whose :meth:`after_run_costs` table is kept (n² floats).
    AFTER_RUN_TABLE_NODES = 2048

    def _after_run_rows(self):
        """``(a, costs)`` blocks: the :meth:`cost_rows` of every input node ``b`` placed
        after the verbatim run ``a-slots+1 … a`` (nothing after it), for every ``a``."""
        n, S = self.view.n, self.p.slots
        t = S
        base = np.full(2 * S + 1, -1, dtype=np.int64)
        b = np.arange(n)
        chunk = max(1, 60_000 // max(n, 1))
        # slot pair distances looked up (same costs)
        tables = self._coarse_tables() or (
            pair_tables(self.view, out_of=False),
            pair_tables(self.views[self.l - 1], out_of=False, children=True)
            if self.l > 0 else None)
        for a0 in range(0, n, chunk):
            a = np.arange(a0, min(n, a0 + chunk))
            ov = np.tile(base, (a.size * n, 1))
            aa = np.repeat(a, n)
            bb = np.tile(b, a.size)
            ov[:, :S] = aa[:, None] + np.arange(-S + 1, 1)[None, :]
            ov[:, :S][ov[:, :S] < 0] = -1
            ov[:, S] = bb
            yield a, self.cost_rows(ov, t, coherence=False, tables=tables).reshape(a.size, n)

    def after_run_costs(self) -> np.ndarray | None:
        """``(n, n)`` cost of input node ``b`` right after the verbatim run ending at
        ``a`` with nothing filled after it (row ``a``; :meth:`cost_rows`, no coherence
        bonus), at the coarsest level; built once (``None`` elsewhere, or above
        :attr:`AFTER_RUN_TABLE_NODES` input nodes).

        This is the whole neighbourhood of a front growing forwards from a settled run:
        :meth:`fill` and :meth:`_jump_earlier` read it there instead of scoring every
        input node again (same values: the rows are the ones they would compute), and
        :meth:`jump_costs` takes its row minima.
        """
        if not self.coarsest or self.view.n > self.AFTER_RUN_TABLE_NODES:
            return None
        if self._after_run is None:
            self._after_run = np.concatenate([c for _, c in self._after_run_rows()])
        return self._after_run

    def _cost_after_run(self, src: np.ndarray, t: int) -> np.ndarray | None:
        """:meth:`cost` of every input node at ``t`` read from :meth:`after_run_costs`,
        when the window around ``t`` is a settled run before it and nothing after it;
        ``None`` otherwise (then the cost is computed)."""
        S = self.p.slots
        if not self.coarsest or self.view.n > self.AFTER_RUN_TABLE_NODES:
            return None
        if not self.cyclic:
            # the finer level's slots of the window must all exist, as in the table's
            nf = self.n_out[self.l - 1] if self.l > 0 else 2 * self.n
            if t < S or 2 * t + S + 1 >= nf or 3 * S + 1 >= nf:
                return None
        ov = [self._out_value(src, t + o) for o in range(-S, S + 1)]  # Python ints
        a = ov[S - 1]
        if a < S - 1 or any(x >= 0 for x in ov[S + 1:]):
            return None
        if ov[:S] != list(range(a - S + 1, a + 1)):
            return None
        return self.after_run_costs()[a].copy()

    def jump_threshold(self) -> float:
        """Cost window (cost units × unit) within which alternatives are drawn.

        At the coarsest level the window is the ``variety`` quantile of
        :meth:`jump_costs`: the natural successor always matches perfectly, so
        a window relative to it would only admit the rare near-perfect jumps of
        a periodic input and never one of a dance; measured on the input's own
        transitions, ``variety`` is the share of the input's moments that can
        be left by a drawn jump.  Finer levels use ``tolerance``.
        """
        if not self.coarsest:
            return self.p.tolerance * self.unit
        if self._tau is None:
            q = float(np.clip(self.p.variety, 0.0, 1.0))
            jc = self.jump_costs()
            jc = jc[np.isfinite(jc)]
            self._tau = float(np.quantile(jc, q)) if (jc.size and q > 0) else 0.0
        return self._tau

    def _draw(
        self, ranked: np.ndarray, sorted_cost: np.ndarray, nodes: np.ndarray | None = None
    ) -> int:
        """Index (into ``ranked``) drawn among the ``k_best`` distinct best matches.

        Only matches within :meth:`jump_threshold` of the best are drawn.
        Matches closer than ``slots`` nodes to a better one are the same match
        shifted in time, not another one; they are skipped.  At the coarsest
        level matches are ranked by cost plus ``usage_weight`` windows per
        time the input nodes they would play next are already in the output,
        so the draw spreads over the input (coverage) instead of circling
        through its best-connected moments.

        Parameters
        ----------
        ranked : (m,) int ndarray
            Candidate identities (input nodes, or join keys), best first.
        sorted_cost : (m,) float ndarray
            Their costs, ascending.
        nodes : (m,) int ndarray, optional
            Input node each candidate plays next (for the usage ranking).
        """
        if self.coarsest and self.p.variety <= 0:
            return 0
        tau = self.jump_threshold()
        key = np.array(sorted_cost, dtype=np.float64)
        if self._usage is not None and nodes is not None and self.p.usage_weight > 0:
            u = self._usage[np.clip(nodes, 0, self._usage.size - 1)]
            key = key + self.p.usage_weight * max(tau, self.unit) * u
        order = np.argsort(key, kind="stable")
        order = order[key[order] <= key[order[0]] + tau]
        chosen: list[int] = []
        picked: list[int] = []  # their identities (Python ints: a short loop, no arrays)
        for i, r in zip(order.tolist(), ranked[order].tolist()):
            if len(chosen) >= self.p.k_best:
                break
            if all(abs(r - c) >= self.p.slots for c in picked):
                chosen.append(i)
                picked.append(r)
        # Generator.choice of a list draws integers(0, len) (the same stream; measured on
        # NumPy 2.4 against choice), without turning the list into an array
        return chosen[int(self.rng.integers(0, len(chosen)))]

    def _settled(self, src: np.ndarray, t: int) -> bool:
        """Whether the ``slots`` filled nodes on one side of ``t`` form one verbatim run.

        A new random transition is only drawn once the last one has a full
        neighbourhood of verbatim nodes behind it; otherwise a second jump would
        land inside the first one's neighbourhood (and often jump straight back).
        """
        S = self.p.slots
        for side in (-1, 1):  # Python ints: a handful of positions
            v = [self._out_value(src, t + side * k) for k in range(1, S + 1)]
            if v[0] < 0:
                continue
            return all(x >= 0 for x in v) and all(b - a == side for a, b in zip(v, v[1:]))
        return True

    def fill(self, src, ranked, t: int, where: str) -> None:
        """Choose and write the node at position ``t`` (in place)."""
        if self.coarsest:
            used = src[src >= 0]
            counts = np.bincount(used, minlength=self.view.n).astype(np.float64)
            a, b = self._out_value(src, t - 1), self._out_value(src, t + 1)
            self._usage = ahead_usage(counts, 2 * self.p.slots + 1, -1 if b >= 0 > a else 1)
        cands = self.candidates(src, t)
        cost = self._cost_after_run(src, t)  # every input node, as candidates() gives
        if cost is None:
            cost = self.cost(src, t, cands)
        if not np.isfinite(cost).any():  # accelerated set exhausted: search everything
            cands = np.arange(self.view.n)
            cost = self.cost(src, t, cands)
        forced = False
        if self.coarsest and self.max_run_nodes is not None:
            _, nxt, run = self._run_behind(src, t)
            if run >= self.max_run_nodes:  # the run must end: no continuation
                keep = np.abs(cands - nxt) >= self.p.slots
                if np.isfinite(cost[keep]).any():
                    cands, cost, forced = cands[keep], cost[keep], True
        node, top = self.choose(cands, cost, where, draw=forced or self._settled(src, t))
        p = t % self.n if self.cyclic else t
        src[p] = node
        ranked[p] = top
        if self.coarsest:
            self._jump_earlier(src, ranked, t, where, forced=forced)

    def _run_behind(self, src: np.ndarray, t: int) -> tuple[int, int, int]:
        """Growth side, natural next node and length of the verbatim run behind ``t``.

        Returns
        -------
        growth : int
            1 when the output grows forwards (filled neighbour at ``t-1``), -1
            backwards, 0 when neither neighbour is filled.
        nxt : int
            The node continuing that run (``-1`` when none).
        run : int
            Nodes in the run.
        """
        a, b = self._out_value(src, t - 1), self._out_value(src, t + 1)
        if a >= 0 and b < 0:
            growth = 1
        elif b >= 0 and a < 0:
            growth = -1
        else:
            return 0, -1, 0
        # walk back while the nodes play the input on (at most n positions)
        first = prev = a if growth == 1 else b
        run = 1
        for k in range(2, self.n + 1):
            v = self._out_value(src, t - growth * k)
            if v < 0 or prev - v != growth:
                break
            run, prev = run + 1, v
        return growth, first + growth, run

    def _jump_earlier(self, src, ranked, t: int, where: str, *, forced: bool = False) -> None:
        """A run that had to end jumps where the jump fits best.

        When the node just placed at ``t`` had to jump — its neighbour is the
        input's last (first, for a right front) node, or the run reached
        ``max_run`` (``forced``) — the jump is searched again at ``t`` and the
        ``slots`` positions before it (inside the same verbatim run),
        exhaustively over the input (no continuation of the run), and drawn
        like any other; the run then continues verbatim from the new jump.
        """
        n_in, S = self.view.n, self.p.slots
        a, b = self._out_value(src, t - 1), self._out_value(src, t + 1)
        here = self._out_value(src, t)
        if a >= 0 and b < 0 and here != a + 1 and (forced or a == n_in - 1):
            side = -1  # left front: move back into the run behind
        elif b >= 0 and a < 0 and here != b - 1 and (forced or b == 0):
            side = 1  # right front
        else:
            return
        every = np.arange(n_in)
        rows, ts, at, bads, read = [], [], [], [], {}
        for d in range(0, self.p.relocate + 1):
            m = t + side * d  # candidate jump position; m+side .. t-side must stay verbatim
            if d:
                run = self._out_values(src, np.array([m, m + side]))
                if run[1] < 0 or run[0] != run[1] - side:
                    break
            trial = src.copy()
            trial[self._positions(min(m, t), max(m, t))] = -1
            prev = self._out_values(trial, np.array([m + side]))[0]
            bad = np.abs(every - (prev - side)) < S  # continuing the run is what ends here
            bad |= (every - side * d < 0) | (every - side * d >= n_in)  # run must fit to t
            row = self._cost_after_run(trial, m)  # a left front: the tabulated costs
            if row is not None:
                read[len(bads)] = row
            else:
                ov = np.broadcast_to(self._out_values(trial, m + self.off),
                                     (n_in, self.off.size)).copy()
                ov[:, self.blk] = every[:, None]
                rows.append(ov)
                ts.append(np.full(n_in, m))
                at.append(len(bads))
            bads.append(bad)
        # every other position d at once (one cost evaluation)
        c = np.empty((len(bads), n_in))
        if rows:
            c[at] = self.cost_rows(np.concatenate(rows), np.concatenate(ts),
                                   tables=self._coarse_tables()).reshape(len(rows), n_in)
        for i, row in read.items():
            c[i] = row
        c = np.where(np.stack(bads) | np.isnan(c), np.inf, c).ravel()
        # the finite (d, node) pairs in (d, node) order, then by cost (stable: ties keep it)
        flat = np.flatnonzero(np.isfinite(c))
        if flat.size == 0:
            return
        flat = flat[np.argsort(c[flat], kind="stable")]
        costs, (ds, nodes) = c[flat], np.divmod(flat, n_in)
        ms = t + side * ds
        pick = 0
        if self.randomize and self.p.k_best > 1:
            pick = self._draw(ms * 1_000_000 + nodes, costs, nodes)
        m, node = int(ms[pick]), int(nodes[pick])
        span = np.arange(min(m, t), max(m, t) + 1)
        vals = node + (span - m)  # the output plays forwards on both sides of the jump
        pos = self._positions(span[0], span[-1])
        src[pos] = vals
        ranked[pos] = -1
        ranked[pos, 0] = vals

    # ----------------------------------------------------------- gaps
    def fill_gap(self, src, ranked, gap: Gap, window: tuple[int, int] | None) -> int | None:
        """Fill a gap in place; returns the meeting position (two-sided gaps).

        Parameters
        ----------
        src, ranked : ndarray
            Level state, anchors already written.
        gap : Gap
        window : (int, int) or None
            Inclusive range searched for the meeting point (whole gap when None).
        """
        lo, hi = gap.lo, gap.hi
        if hi - lo <= 1:
            return None
        name = f"gap {gap.key}"
        if not gap.right:
            for t in range(lo + 1, hi):
                self.fill(src, ranked, t, f"{name}, node {t}")
            return None
        if not gap.left:
            for t in range(hi - 1, lo, -1):
                self.fill(src, ranked, t, f"{name}, node {t}")
            return None
        ws, we = window if window is not None else (lo + 1, hi - 1)
        ws, we = max(ws, lo + 1), min(we, hi - 1)
        if ws > we:
            ws, we = lo + 1, hi - 1
        # both fronts grow in this one output, so each sees the other once they are near
        nl, nr, last = lo + 1, hi - 1, lo + 1
        while nl <= nr:
            if self.p.alternate or nl <= (lo + hi) // 2:
                self.fill(src, ranked, nl, f"{name}, node {nl} (left front)")
                last, nl = nl, nl + 1
                if not self.p.alternate:
                    continue
            if nl <= nr:
                self.fill(src, ranked, nr, f"{name}, node {nr} (right front)")
                last, nr = nr, nr - 1
        return self._meet(src, ranked, gap, last, ws, we)

    def _positions(self, a: int, b: int) -> np.ndarray:
        """Wrapped array positions of unwrapped ``a … b`` (inclusive)."""
        pos = np.arange(a, b + 1)
        return np.mod(pos, self.n) if self.cyclic else pos

    def sequence_costs(self, tracks: np.ndarray, band: np.ndarray) -> np.ndarray:
        """Summed neighbourhood cost of the nodes at ``band`` in each candidate track.

        The cost of a node is :meth:`cost_rows` of its window in the finished track
        (every neighbour filled; no coherence bonus, missing input slots left out).

        Parameters
        ----------
        tracks : (r, n_out) int ndarray
            Candidate source tracks of this level.
        band : (b,) int ndarray
            Output positions (unwrapped) summed over.

        Returns
        -------
        (r,) float ndarray
            ``inf`` for a track with a rejected node in ``band``.
        """
        r = tracks.shape[0]
        u = band[:, None] + self.off[None, :]  # (b, W)
        p, ok = self._wrap(u, self.n)
        ov = np.where(ok[None], tracks[:, p], -1).reshape(-1, self.off.size)
        t = np.tile(band, r)
        c = self.cost_rows(ov, t, coherence=False, strict=False,
                           tables=self._coarse_tables())
        return np.where(np.isnan(c), 0.0, c).reshape(r, band.size).sum(axis=1)

    def _meet(self, src, ranked, gap: Gap, m0: int, ws: int, we: int) -> int:
        """The meeting point of a gap whose two fronts met at ``m0`` (in place).

        The join is moved to every position ``m`` of ``[ws, we]`` within
        ``meeting_window`` nodes of ``m0`` (the front that loses positions is
        replaced there by the other front played on verbatim), the node at ``m``
        is searched over the input (its ``k_best`` best), and each arrangement is
        scored by its *summed sequence cost*: the neighbourhood costs of every
        node of the gap in the finished track (:meth:`sequence_costs`; nodes
        farther than ``slots`` from the changed ones are the same in every
        arrangement, so only those are summed).  The cheapest wins (drawn among
        the ``k_best`` distinct at randomised levels); an arrangement whose
        verbatim run would exceed ``max_run`` is refused while another exists.

        Returns
        -------
        int
            The meeting position (unwrapped).
        """
        n_in, S, w = self.view.n, self.p.slots, self.p.meeting_window
        at = self._positions
        a, b = self._out_values(src, np.array([m0 - 1, m0 + 1]))
        tracks, keys, nodes, ms = [], [], [], []
        for m in range(max(ws, m0 - w), min(we, m0 + w) + 1):
            trial = src.copy()
            if m > m0:  # the left front plays on through m0 … m-1
                vals = a + np.arange(1, m - m0 + 1)
                if a < 0 or vals[-1] >= n_in:
                    continue
                trial[at(m0, m - 1)] = vals
            elif m < m0:  # the right front plays back through m+1 … m0
                vals = b - np.arange(m0 - m, 0, -1)
                if b < 0 or vals[0] < 0:
                    continue
                trial[at(m + 1, m0)] = vals
            trial[at(m, m)] = -1
            cands = np.arange(n_in)  # exhaustive (gaps are filled at the coarsest level)
            c = self.cost(trial, m, cands)
            c = np.where(np.isnan(c), 0.0, c)
            ok = np.flatnonzero(np.isfinite(c))
            for i in ok[np.argsort(c[ok], kind="stable")][: max(self.p.k_best, 1)]:
                t2 = trial.copy()
                t2[at(m, m)] = cands[i]
                tracks.append(t2)
                keys.append(m * 1_000_000 + int(cands[i]))
                nodes.append(int(cands[i]))
                ms.append(m)
        if not tracks:
            raise SynthesisError(
                f"gap {gap.key}: no input node joins the two sides anywhere in nodes "
                f"{max(ws, m0 - w)}-{min(we, m0 + w)}"
            )
        # the nodes whose neighbourhood differs between the arrangements (anchors included)
        lo_b = max(gap.lo, min(min(ms), m0) - S)
        hi_b = min(gap.hi, max(max(ms), m0) + S)
        tracks = np.array(tracks)
        total = self.sequence_costs(tracks, np.arange(lo_b, hi_b + 1))
        if self.max_run_nodes is not None:  # a join must not make a run longer than max_run
            R = self.max_run_nodes
            span = np.arange(lo_b - R, hi_b + R + 1)
            if not self.cyclic:
                span = span[(span >= 0) & (span < self.n)]
            elif span.size > self.n:
                span = np.arange(lo_b, lo_b + self.n)
            too_long = _longest_runs(tracks[:, at(span[0], span[-1])]) > R
            if not too_long.all():
                total = np.where(too_long, np.inf, total)
        if not np.isfinite(total).any():  # pragma: no cover - the fronts' own nodes fit
            raise SynthesisError(f"gap {gap.key}: every meeting point was rejected")
        perm = self.rng.permutation(total.size)
        order = perm[np.argsort(total[perm], kind="stable")]
        order = order[np.isfinite(total[order])]
        pick = order[0]
        if self.randomize and self.p.k_best > 1:
            pick = order[self._draw(np.array(keys)[order], total[order],
                                    np.array(nodes)[order])]
        m = ms[pick]
        changed = at(min(m, m0), max(m, m0))
        src[:] = tracks[pick]
        ranked[changed] = -1
        ranked[changed, 0] = src[changed]
        same_m = [nodes[i] for i in order if ms[i] == m]
        top = list(dict.fromkeys([nodes[pick]] + same_m))[:3]
        ranked[at(m, m), : len(top)] = top
        return m
