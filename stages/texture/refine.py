"""Son selection and refinement of the transitions at the finer levels (Moradoff §3.5–3.7).

Below the coarsest level the output of a level is derived from the level above
(:class:`LevelRefinement`, a :class:`~mocapflow.stages.texture.search.LevelSearch`):

* **son selection** — every output node takes the child (same parity) of its
  parent's source (:meth:`LevelRefinement.son_track`); runs holding a
  constraint are shifted to pass through it
  (:meth:`LevelRefinement._align_to_anchors`).  The track is then a sequence of
  *verbatim runs* (:func:`verbatim_runs`).
* **refinement of every transition** — each transition between two runs (a
  seam, meeting point or random jump of the parent level) is searched again
  around twice its parent position (:meth:`LevelRefinement._rejoin`): the left
  run is extended forwards, the right run backwards, and the join position
  ``m`` and the right run's line are chosen by the three-level neighbourhood
  cost at the join (:meth:`LevelRefinement.join_costs`).
* **the join schedule** — where and among which lines a join is searched, in
  order until one fits (:meth:`LevelRefinement._join_windows`,
  :meth:`LevelRefinement._candidate_lines`,
  :meth:`LevelRefinement._join_attempts`): the ``±meeting_window`` nodes around
  the transition, narrowed so that joins keep ``MIN_RUN_FRAMES`` between each
  other; first the line the coarser level drew (the children of the parent's
  source), then the other lines through the children of the parent's 3 best
  matches ``±candidate_range`` nodes (candidate acceleration), lines that merely
  continue the left run only when nothing else fits; a new line must stay in
  the input for ``2 slots + 1`` nodes.  So the coarse plan's transitions — and
  its randomisation — survive refinement; as a last resort a join may replay a
  few nodes (a stall), rather than fail.  Joins are drawn within
  ``tolerance`` cost units (:meth:`LevelRefinement._draw_join`).
* **pose term** (an addition: ``SearchParams.pose_weight``) — at
  the finest level a join also costs how far apart in pose (6-D joint rotations)
  the two lines stay
  within ``±SearchParams.pose_span`` frames (:meth:`LevelRefinement.line_costs`), and
  the ``pose_lines`` nearest lines are tried beside the drawn one
  (:meth:`LevelRefinement._pose_lines`; none that would leave the input before
  the run ends or run into the next run).
* **gap growing** — ends the runs leave outside the input (open outputs) are
  grown node by node with the ordinary search
  (:meth:`LevelRefinement._grow_free_ends`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from mocapflow.stages.texture.neighbourhood import pose_distance
from mocapflow.stages.texture.search import LevelResult, LevelSearch, SynthesisError

__all__ = ["MIN_RUN_FRAMES", "POSE_SPAN_FRAMES", "LevelRefinement", "verbatim_runs"]

#: Shortest run (fine frames) refinement leaves between two transitions when it can.
MIN_RUN_FRAMES = 12

#: Half span (finest frames at 30 fps) over which :meth:`LevelRefinement.line_costs`
#: compares the two lines of a join: the half window of the local patch metric (15
#: frames); ``SearchParams.pose_span`` is this scaled with the synthesis rate.
POSE_SPAN_FRAMES = 7


def verbatim_runs(
    val: np.ndarray, valid: np.ndarray, cyclic: bool
) -> tuple[int, list[list[int]]]:
    """Verbatim runs of a source track: stretches that play the input forwards.

    A run is a maximal stretch of output positions whose input nodes follow
    each other (``val[u + 1] == val[u] + 1``); invalid positions belong to no
    run.  In loop mode a run may wrap past the last position.

    Parameters
    ----------
    val : (n,) int ndarray
        Input node at each output position.
    valid : (n,) bool ndarray
        Positions holding an input node.
    cyclic : bool

    Returns
    -------
    p0 : int
        First run start: the runs are listed from there.
    runs : list of [int, int]
        ``[start, end]`` (unwrapped, inclusive), in output order.
    """
    n = val.size
    cont = np.zeros(n, dtype=bool)  # position continues the previous one
    cont[1:] = valid[1:] & valid[:-1] & (val[1:] == val[:-1] + 1)
    if cyclic:
        cont[0] = valid[0] and valid[-1] and val[0] == val[-1] + 1
    starts = np.flatnonzero(valid & ~cont)
    if starts.size == 0:
        return 0, ([[0, n - 1]] if valid.all() else [])
    p0 = int(starts[0])
    # positions from p0 on (wrapping in loop mode): a run starts at every valid position
    # that does not continue its predecessor and ends before the next position that does
    # not continue the run (a start or an invalid position)
    u = np.arange(p0, p0 + n) if cyclic else np.arange(p0, n)
    i = u % n if cyclic else u
    on = valid[i] & cont[i]
    on[0] = False  # p0 starts the first run
    first = np.flatnonzero(valid[i] & ~on)
    stop = np.flatnonzero(~on)
    last = np.append(stop, u.size)[np.searchsorted(stop, first, side="right")] - 1
    return p0, np.stack([u[first], u[last]], axis=1).tolist()


@dataclass
class _Transition:
    """The transition from run ``[a1, b1]`` to run ``[a2, b2]`` (unwrapped positions).

    Attributes
    ----------
    a1, b1, a2, b2 : int
    left_end : int
        Input node the left run plays at ``b1`` (its line: ``left_end + (u - b1)``).
    right_start : int
        Input node the right run plays at ``a2``.
    left_anchors, right_anchors : list of int
        Constrained positions in each run.
    """

    a1: int
    b1: int
    a2: int
    b2: int
    left_end: int
    right_start: int
    left_anchors: list[int]
    right_anchors: list[int]


class LevelRefinement(LevelSearch):
    """Son selection with refinement of every transition (a finer level).

    Every output node first takes the child (same parity) of its parent's
    source; runs holding a constraint are shifted to pass through it.  Each
    transition between two runs — a seam or meeting point of the parent level
    — is then searched again around twice its parent position: the left run is
    extended forwards, the right run backwards, and the join position ``m``
    (``±meeting_window`` nodes) and the right run's line (the children of the
    parent's 3 best matches ``±candidate_range`` nodes) are chosen by the
    three-level neighbourhood cost at the join.  Lines that merely continue
    the left run are only taken when nothing else fits, and the drawn line
    (the children of the parent's source) is preferred to the other parent
    matches, so the coarse plan's transitions — and its randomisation —
    survive refinement.  Joins keep ``MIN_RUN_FRAMES`` between each other when
    the window allows, and a new line must stay in the input for ``2 slots + 1``
    nodes.

    Constructed like :class:`~mocapflow.stages.texture.search.LevelSearch`
    (``upper``: the synthesised parent level); :meth:`refine` does the work.
    """

    def refine(self, anchors: dict[int, int]) -> LevelResult:
        """The source track of this level.

        Parameters
        ----------
        anchors : dict
            Output position -> input node at this level (constraints).

        Returns
        -------
        LevelResult
        """
        n_in = self.view.n
        val = self.son_track()
        self._align_to_anchors(val, anchors)
        valid = (val >= 0) & (val < n_in)
        _, runs = verbatim_runs(val, valid, self.cyclic)
        ranked = np.full((self.n, 3), -1, dtype=np.int64)
        if len(runs) <= 1 and valid.all():
            ranked[:, 0] = val
            return LevelResult(val, ranked, {})
        if self.cyclic and runs:
            # the wrap joins the last run to the first
            runs.append([runs[0][0] + self.n, runs[0][1] + self.n])
        prev_join = None
        for k in range(len(runs) - 1):
            prev_join = self._rejoin(val, ranked, runs, k, anchors, prev_join)
        ranked[:, 0] = val
        val = self._grow_free_ends(val, ranked)
        if not ((val >= 0) & (val < n_in)).all():
            bad = np.flatnonzero((val < 0) | (val >= n_in))
            raise SynthesisError(f"level {self.l}: output nodes {bad[:5].tolist()} left unfilled")
        return LevelResult(val.astype(np.int64), ranked, {})

    # ----------------------------------------------------------- son selection
    def son_track(self) -> np.ndarray:
        """Every output node takes the child (same parity) of its parent's source.

        Returns
        -------
        (n_out,) int ndarray
        """
        up = self.upper
        t = np.arange(self.n)
        T = np.minimum(t // 2, up.src.size - 1)
        return 2 * up.src[T] + (t - 2 * T)

    def _align_to_anchors(self, val: np.ndarray, anchors: dict[int, int]) -> None:
        """Shift every run holding anchors onto them (in place), then write the anchors.

        Each position of such a run takes the shift of its nearest anchor.
        """
        n, cyclic = self.n, self.cyclic
        valid = (val >= 0) & (val < self.view.n)
        _, runs = verbatim_runs(val, valid, cyclic)
        for a, b in runs:
            pos = np.arange(a, b + 1)
            wp = np.mod(pos, n) if cyclic else pos
            inside = [(u, anchors[int(i)]) for u, i in zip(pos, wp) if int(i) in anchors]
            if not inside:
                continue
            au = np.array([u for u, _ in inside])
            nearest = np.abs(pos[:, None] - au[None, :]).argmin(axis=1)
            off = np.array([v - val[np.mod(u, n) if cyclic else u] for u, v in inside])
            val[wp] = val[wp] + off[nearest]
        for p, v in anchors.items():
            val[p] = v

    # ----------------------------------------------------------- one transition
    def _at(self, u):
        """Array position(s) of unwrapped output position(s) ``u``."""
        return np.mod(u, self.n) if self.cyclic else u

    def _anchored(self, anchors: dict[int, int], a: int, b: int) -> list[int]:
        """Constrained positions (unwrapped) in ``[a, b]``."""
        if not anchors:
            return []
        n, cyclic = self.n, self.cyclic
        return [u for u in range(int(a), int(b) + 1) if (u % n if cyclic else u) in anchors]

    def _transition(self, val, runs, k: int, anchors: dict[int, int]) -> _Transition:
        """Transition from run ``k`` to ``k + 1`` (an open output's last run ends at n - 1)."""
        (a1, b1), (a2, b2) = runs[k], runs[k + 1]
        if not self.cyclic and k == len(runs) - 2 and b2 >= self.n:
            b2 = self.n - 1
        return _Transition(
            a1,
            b1,
            a2,
            b2,
            left_end=int(val[self._at(b1)]),
            right_start=int(val[self._at(a2)]),
            left_anchors=self._anchored(anchors, a1, b1),
            right_anchors=self._anchored(anchors, a2, b2),
        )

    def _rejoin(self, val, ranked, runs, k: int, anchors, prev_join: int | None) -> int | None:
        """Search transition ``k`` again and rewrite both runs (in place).

        Returns
        -------
        int or None
            The join position; ``prev_join`` when the two runs have become one.

        Raises
        ------
        SynthesisError
            No line joins the two runs anywhere.
        """
        tr = self._transition(val, runs, k, anchors)
        at_join = tr.left_end + (tr.a2 - tr.b1)  # the left line at a2
        if tr.right_start == at_join and tr.a2 == tr.b1 + 1 and not tr.right_anchors:
            runs[k + 1] = [tr.a1, tr.b2]  # a previous join made the two runs one
            return prev_join
        last_run = k + 1 == len(runs) - 1 and not self.cyclic
        start = self._verbatim_start(val, tr.b1)
        window, fallback = self._join_windows(tr, prev_join, last_run=last_run,
                                              run_start=start)
        cap = self._run_cap()
        merged_too_long = False
        if cap is not None:  # the run a join that keeps the left line would make
            end, lim = tr.b2, tr.b2 + (self.n if self.cyclic else self.n - 1 - tr.b2)
            while end < lim and val[self._at(end + 1)] == at_join + (end + 1 - tr.a2):
                end += 1  # (through the next run when it plays the same line)
            merged_too_long = end + 1 - start > cap
        starts = self._candidate_lines(tr)
        near = self._pose_lines(tr)
        if near.size and k + 2 < len(runs):  # a pose line must not run into the next run
            a3 = runs[k + 2][0]
            nxt = int(val[self._at(a3)]) - (a3 - tr.a2)  # that run's line at a2
            # (clear of it by the span a new run plays: a line closer leaves the next join
            # only a replay or a join beside a constraint)
            near = near[np.abs(near - nxt) >= 2 * self.p.slots + 1]
        if near.size:  # (starts: np.unique's, already sorted and distinct)
            starts = np.union1d(starts, near)
        for lines, (m_lo, m_hi), strict, min_run, stall in self._join_attempts(
            tr, starts, window, fallback, near
        ):
            rows, keys, ms = self.join_costs(val, tr, lines, m_lo, m_hi, strict, min_run,
                                             allow_stall=stall)
            if rows and merged_too_long:  # the left line continued: one run past max_run
                keep = [i for i, (_, s_) in enumerate(ms) if s_ != at_join]
                if keep:
                    rows, keys, ms = ([x[i] for i in keep] for x in (rows, keys, ms))
            if rows:
                break
        if not rows:
            raise SynthesisError(
                f"level {self.l}: no join between output nodes {tr.b1} and {tr.a2} "
                f"(input runs ending at {tr.left_end} and starting at {tr.right_start})"
            )
        pick, order = self._draw_join(rows, keys)
        m, s_ = ms[pick]
        # the lines of the joins at m, best first (the ranked alternatives written there)
        m_all, s_all = np.asarray(ms).T
        self._write_join(val, ranked, runs, k, tr, m, s_, s_all[order[m_all[order] == m]])
        return m

    # ----------------------------------------------------------- join schedule
    def _join_windows(
        self, tr: _Transition, prev_join: int | None, *, last_run: bool,
        run_start: int | None = None,
    ) -> tuple[tuple[int, int], tuple[int, int]]:
        """Inclusive ranges of join positions: the scheduled one and the fallback.

        The scheduled window is ``±meeting_window`` nodes around the transition,
        after the previous join and ``slots`` nodes after the left run's
        constraints, up to ``slots`` nodes before the right run's first
        constraint (a constraint is copied with its neighbourhood) and while
        the left line stays in the input;
        when it can be, it is narrowed so that the runs on both sides keep
        ``MIN_RUN_FRAMES`` (and more than ``slots`` nodes) — long enough to
        smooth, no bridge of a few frames — and so that the left run (verbatim since
        ``run_start``, default its first position) and the right run stay within
        ``max_run`` (:meth:`_run_cap`; a left run already longer — the right line had
        to fill a gap the left line could not — joins before the cap, outside the
        schedule).  The fallback window reaches from the left run's constraints to the
        right run's end (or first constraint).
        """
        S, w = self.p.slots, self.p.meeting_window
        a1, b1, a2, b2 = tr.a1, tr.b1, tr.a2, tr.b2
        lo = max(a1 + 1, b1 + 1 - w, (prev_join + 1) if prev_join is not None else a1 + 1)
        # a constraint is copied with its neighbourhood: no join within `slots` of it
        if tr.left_anchors:
            lo = max(lo, max(tr.left_anchors) + 1 + S)
        hi = min(b2, a2 + w)
        if tr.right_anchors:
            hi = min(hi, min(tr.right_anchors) - S)
        lo = max(lo, a1 + 1)
        hi_left = b1 + (self.view.n - 1 - tr.left_end) + 1  # m - 1 must keep L in range
        hi = min(hi, hi_left)
        # keep the runs on both sides long enough to smooth: no bridge of a few frames
        gap = max(S + 1, -(-MIN_RUN_FRAMES // 2**self.l))
        start = prev_join if prev_join is not None else a1  # where the left run begins
        lo_s = max(lo, start + gap)
        hi_s = hi if last_run else min(hi, b2 + 1 - gap)
        if lo_s <= hi_s:
            lo, hi = lo_s, hi_s
        lo_f = max([a1 + 1] + [x + 1 for x in tr.left_anchors])
        hi_f = min([b2, hi_left] + tr.right_anchors)
        # and no longer than max_run (the coarsest level kept it; a join moved later at
        # every finer level would lengthen the run by up to meeting_window nodes each)
        cap = self._run_cap()
        if cap is not None:
            first = start if run_start is None else min(start, run_start)
            end_left = first + cap  # the left run (verbatim since `first`) ends by here
            if lo <= min(hi, end_left):
                hi = min(hi, end_left)
            elif lo_f <= end_left < lo:  # already too long: join earlier than scheduled
                lo, hi = max(lo_f, end_left - w), end_left
            if max(lo, b2 + 1 - cap) <= hi:  # the right run (up to its end as it stands)
                lo = max(lo, b2 + 1 - cap)
        return (lo, hi), (lo_f, hi_f)

    def _verbatim_start(self, val: np.ndarray, b: int) -> int:
        """First position of the verbatim run (each node its predecessor's successor in
        the input) that ends at position ``b`` — before the previous join when that join
        kept the left line."""
        lim = b - (self.n - 1 if self.cyclic else b)
        u = b
        while u > lim and val[self._at(u - 1)] >= 0 and \
                val[self._at(u)] == val[self._at(u - 1)] + 1:
            u -= 1
        return u

    def _run_cap(self) -> int | None:
        """Longest run (nodes of this level) a join may leave: ``max_run`` of the input's
        nodes here (at least ``2 slots``), None without a limit."""
        if not 0 < self.p.max_run < 1:
            return None
        return max(2 * self.p.slots, int(self.p.max_run * self.view.n))

    def _candidate_lines(self, tr: _Transition) -> np.ndarray:
        """Input nodes the right run may play at ``a2`` (its line: ``s + (u - a2)``).

        Only its own when it holds a constraint; else the children of the
        parent's source and best matches ``±candidate_range`` and its own.
        """
        if tr.right_anchors:
            return np.array([tr.right_start])
        up, r = self.upper, self.p.candidate_range
        q = int(self._at(tr.a2))
        Tq = min(q // 2, up.src.size - 1)
        par = up.ranked[Tq]
        par = par[par >= 0][: self.p.n_parent_matches].tolist() + [int(up.src[Tq])]
        lines = 2 * np.array(sorted(set(par)), dtype=np.int64) + (q - 2 * Tq)
        starts = (lines[:, None] + np.arange(-r, r + 1)[None, :]).ravel()
        return np.unique(np.concatenate([starts, [tr.right_start]]))

    def _pose_term(self, tr: _Transition) -> bool:
        """Whether the joins of ``tr`` are scored and widened by pose (finest level,
        ``pose_weight > 0``, the right run unconstrained)."""
        return self.l == 0 and self.p.pose_weight > 0 and not tr.right_anchors

    def line_costs(self, tr: _Transition, m: np.ndarray, s: np.ndarray) -> np.ndarray:
        """How far apart the left line and right line ``s`` stay around a join at ``m``.

        The mean :func:`~mocapflow.stages.texture.neighbourhood.pose_distance`
        (RMS over joints of the 6-D rotations) between the left line's node
        ``L(u) = left_end + (u - b1)`` and the right line's ``R_s(u) = s + (u - a2)``
        over the output positions ``u`` within ``±SearchParams.pose_span`` of ``m``
        where both are inside the input: the frames a 15-frame patch around the join
        mixes from the two lines (0 when they are one line).

        Parameters
        ----------
        tr : _Transition
        m, s : (r,) int ndarrays
            Join positions and right lines.

        Returns
        -------
        (r,) float ndarray
            ``inf`` where fewer than ``pose_span + 1`` positions compare.
        """
        view, h = self.view, self.p.pose_span
        n = view.n
        m, s = np.asarray(m, dtype=np.int64), np.asarray(s, dtype=np.int64)
        if m.size == 0:
            return np.zeros(0)
        x = tr.left_end + (m - tr.b1)  # the left line at m
        y = s + (m - tr.a2)  # the right line at m
        j = np.arange(-h, h + 1)
        x0 = max(int(x.min()) - h, 0)
        x1 = min(int(x.max()) + h, n - 1)
        if x1 < x0:
            return np.full(m.size, np.inf)
        rows = np.arange(x0, x1 + 1)
        pd = pose_distance(view, rows, np.arange(n))  # (rows, n)
        xj, yj = x[:, None] + j[None, :], y[:, None] + j[None, :]
        ok = (xj >= 0) & (xj < n) & (yj >= 0) & (yj < n)
        vals = np.where(ok, pd[np.clip(xj - x0, 0, rows.size - 1), np.clip(yj, 0, n - 1)], 0.0)
        cnt = ok.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(cnt > h, vals.sum(axis=1) / cnt, np.inf)

    def _pose_lines(self, tr: _Transition) -> np.ndarray:
        """Right lines whose poses stay nearest the left line's around the join.

        With the pose term (:meth:`_pose_term`): the ``pose_lines`` input lines with
        the lowest :meth:`line_costs` at ``a2``, the left line's own continuation
        (closer than ``slots``) and lines that would leave the input before the
        right run's end excluded — the transitions that leave the input's
        patch space least, so smoothing has little to bridge.  They are tried
        beside the drawn line (:meth:`_join_attempts`).

        Returns
        -------
        (k,) int ndarray
            Empty without the pose term.
        """
        k = self.p.pose_lines
        if k <= 0 or not self._pose_term(tr):
            return np.zeros(0, dtype=np.int64)
        n = self.view.n
        s = np.arange(n)
        cost = self.line_costs(tr, np.full(n, tr.a2), s)
        cost[np.abs(s - (tr.left_end + (tr.a2 - tr.b1))) < self.p.slots] = np.inf
        cost[s + (tr.b2 - tr.a2) >= n] = np.inf  # the whole right run stays in the input
        order = np.argsort(cost, kind="stable")[:k]
        return order[np.isfinite(cost[order])].astype(np.int64)

    def _join_attempts(self, tr: _Transition, starts: np.ndarray, window, fallback,
                       near: np.ndarray | None = None) -> Iterator[tuple]:
        """``(lines, window, strict, min_run, allow_stall)`` to try in order until a join
        fits (a generator: the later attempts are built only when reached).

        Right lines ``R_s(u) = s + (u - a2)``; where one runs past the input's
        end the run is cut short and the next join covers the rest.  The last
        resort lets the right line replay a few nodes the left one just played
        (a stall): when a constrained right run's line is at most ``slots``
        nodes behind the left line — e.g. a loop's wrap into a constraint near
        the output's start — nothing else joins them, and a short replay is
        better than no motion (finer levels search the join again).  ``near``
        (:meth:`_pose_lines`) join the drawn line in the first attempt.
        """
        S = self.p.slots
        novel = starts[np.abs(starts - (tr.left_end + (tr.a2 - tr.b1))) >= S]
        own = np.abs(novel - tr.right_start) <= self.p.candidate_range  # the drawn line
        if near is not None and near.size:
            own |= np.isin(novel, near)
        own = novel[own]
        span = 2 * S + 1  # a new run plays at least this long before the input ends
        yield own, window, True, span, False
        yield novel, window, True, span, False
        yield starts, window, True, span, False
        yield starts, fallback, True, 1, False
        yield starts, fallback, False, 1, False
        # the last resorts (built only when reached)
        any_line = np.arange(-self.p.meeting_window - (tr.a2 - tr.b1), self.view.n)
        if tr.right_anchors:  # a constrained run keeps its line
            any_line = starts
        yield any_line, fallback, False, 1, False
        yield any_line, fallback, False, 1, True

    # ----------------------------------------------------------- join cost, draw, write
    def join_costs(
        self,
        val: np.ndarray,
        tr: _Transition,
        starts: np.ndarray,
        lo: int,
        hi: int,
        strict: bool = True,
        min_run: int = 1,
        *,
        allow_stall: bool = False,
    ) -> tuple[list[float], list[int], list[tuple[int, int]]]:
        """Costs of joining the left line to right lines ``starts`` at ``m`` in ``[lo, hi]``.

        A right line must stay inside the input for ``min_run`` nodes from ``m``
        (or up to ``b2``): no bridge of a few nodes into the input's end.
        ``strict`` and ``allow_stall`` as in :meth:`cost_rows`.

        Returns
        -------
        rows : list of float
            Neighbourhood cost at the join (:meth:`cost_rows`, no coherence bonus).
        keys : list of int
            Identity of each join for the draw.
        ms : list of (int, int)
            ``(m, s)`` of each join.
        """
        n_in = self.view.n
        a1, b1, a2, b2, L_end = tr.a1, tr.b1, tr.a2, tr.b2, tr.left_end
        # every (m, s) at once, m ascending then s as in `starts`
        M = np.arange(lo, hi + 1)
        last = np.minimum(b2, M + min_run - 1) - a2
        fits = (starts[None, :] + (M - a2)[:, None] >= 0) & (
            starts[None, :] + last[:, None] < n_in)
        mi, si = np.nonzero(fits)
        if mi.size == 0:
            return [], [], []
        m, ss = M[mi], starts[si]
        u = m[:, None] + self.off[None, :]
        ov = self._out_values(val, u)
        left = (u < m[:, None]) & (u >= a1)
        right = (u >= m[:, None]) & (u <= b2)
        ov = np.where(left, L_end + (u - b1), ov)
        ov = np.where(right, ss[:, None] + (u - a2), ov)
        ov[(ov < 0) | (ov >= n_in)] = -1
        c = self.cost_rows(ov, m, coherence=False, strict=strict, allow_stall=allow_stall)
        c = np.where(np.isnan(c), 0.0, c)
        if self._pose_term(tr):
            # a join whose lines compare over too few frames (near the input's ends) is
            # not ruled out by the pose term: it costs the largest pose term of the rest
            pc = self.line_costs(tr, m, ss)
            fin = np.isfinite(pc)
            pc = np.where(fin, pc, pc[fin].max() if fin.any() else 0.0)
            c = c + self.p.pose_weight * pc
        ok = np.isfinite(c)
        m, ss = m[ok].tolist(), ss[ok].tolist()
        keys = [s_ * 1_000_000 + mm for mm, s_ in zip(m, ss)]
        return c[ok].tolist(), keys, list(zip(m, ss))

    def _draw_join(self, rows: list[float], keys: list[int]) -> tuple[int, np.ndarray]:
        """Index of the chosen join and the joins' order (cheapest first, ties random)."""
        cost = np.array(rows)
        perm = self.rng.permutation(cost.size)
        order = perm[np.argsort(cost[perm], kind="stable")]
        pick = order[0]
        if self.randomize and self.p.k_best > 1:
            pick = order[self._draw(np.array(keys)[order], cost[order])]
        return pick, order

    def _write_join(self, val, ranked, runs, k: int, tr: _Transition, m: int, s_: int,
                    lines_here: np.ndarray) -> None:
        """Write both lines around the join at ``m`` (in place); ``lines_here``: the right
        lines ``s`` of the joins at ``m``, best first."""
        n_in = self.view.n
        span_l = np.arange(tr.a1, m)
        span_r = np.arange(m, tr.b2 + 1)
        val[self._at(span_l)] = tr.left_end + (span_l - tr.b1)
        val[self._at(span_r)] = s_ + (span_r - tr.a2)
        runs[k + 1] = [m, min(tr.b2, m + (n_in - 1 - (s_ + m - tr.a2)))]
        top = list(dict.fromkeys((lines_here + (m - tr.a2)).tolist()))[:3]
        ranked[self._at(m), : len(top)] = top

    # ----------------------------------------------------------- gap growing
    def _grow_free_ends(self, val: np.ndarray, ranked: np.ndarray) -> np.ndarray:
        """Grow the ends the runs leave outside the input node by node (open outputs).

        Returns
        -------
        (n_out,) int ndarray
            ``val``, or the track with the grown ends (``ranked`` updated in place).
        """
        bad = (val < 0) | (val >= self.view.n)
        if not (bad.any() and not self.cyclic and not bad.all()):
            return val
        src = np.where(bad, -1, val)
        first = int(np.argmin(bad))
        for u in range(first - 1, -1, -1):
            self.fill(src, ranked, u, f"output node {u}")
        for u in np.flatnonzero(src < 0):
            self.fill(src, ranked, int(u), f"output node {u}")
        return src
