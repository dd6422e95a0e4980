"""Graph-path gap filler at the coarsest level (Moradoff §3.7.2).

Instead of growing a gap from both sides and joining the fronts at a meeting
point, the coarsest level of a gap can be filled by a path in a *transition
graph* over the coarsest input nodes: an edge ``a → a+1`` for every natural
successor (cost 0) and an edge ``a → b`` for every jump whose transition cost
is below a threshold (the ``graph_threshold`` quantile of all jump costs).  A
path of exactly the gap's length from the left anchor to the right anchor is
found by depth-first search under a cost bound (``(1 + graph_slack)`` × the
cheapest such path); candidates are visited in random (seeded) order, so
every seed gives another path.  The exact remaining-cost table makes the DFS
prune every branch that cannot meet the bound.  It carries the length of the
verbatim run each node ends, so the path keeps ``max_run`` (no run of natural
successors longer than the synthesis' limit, counting the run that enters the
gap); where the graph cannot keep it (nodes with no jump edge along a stretch
longer than the limit, e.g. the first 10 of the 39 coarsest nodes of
``cmu_131_02`` at 30 fps), each node without a jump edge gets its cheapest jump
as one (``escapes``), and only a gap that still cannot keeps the shortest limit it can.  The
walk draws like the neighbourhood search (:mod:`~mocapflow.stages.texture.search`):
among the ``k_best`` allowed successors whose *key* — edge cost plus
``usage_weight`` windows per time the input nodes they would play next are
already in the output — lies within the ``variety`` window of the cheapest
(:func:`jump_window`), and only once the last jump has ``slots`` verbatim nodes
behind it, so the path neither circles through one well-connected block nor
jumps at every node; the cost bound grows by one such window per jump the run
limit forces (else only the cheapest jumps fit and the path circles), and a jump
of fewer than ``slots`` nodes is no edge (``min_jump``: refinement could turn it
back into the natural successor, merging two runs past the limit).  The ``slots`` edges
beside each constraint are natural successors (a constrained node is copied
with its neighbourhood), and the input's last nodes never jump into its first
(:func:`mocapflow.stages.texture.synth._graph_level`: the finer levels could not
join the two lines).  Finer levels then select the
sons of the path nodes (children ``±candidate_range``) with the usual
refinement (:mod:`~mocapflow.stages.texture.refine`).  The path is driven by
:func:`mocapflow.stages.texture.synth._graph_level`, which also reports the
costliest jump of each two-sided gap as its meeting point (its middle without jumps).

A gap no path can fill raises :class:`UnreachableGapError` naming it.
"""

from __future__ import annotations

import numpy as np

from mocapflow.stages.texture.neighbourhood import LevelView, slot_pair_weights, window_cost
from mocapflow.stages.texture.search import SynthesisError, ahead_usage

__all__ = [
    "UnreachableGapError",
    "graph_path",
    "jump_window",
    "transition_costs",
    "transition_graph",
]


class UnreachableGapError(SynthesisError):
    """No path of the gap's length joins its two anchors in the transition graph."""


def transition_costs(view: LevelView, *, slots: int = 3) -> np.ndarray:
    """Cost of following input node ``a`` by node ``b`` (instead of ``a + 1``).

    The output window ``a-slots+1 … a, b … b+slots`` is compared with the input
    windows around ``b`` and around ``a + 1`` (the neighbourhood distance of
    the synthesis); the cost is the mean of the two.

    Parameters
    ----------
    view : LevelView
        Coarsest level, ``n`` nodes.
    slots : int

    Returns
    -------
    (n, n) float ndarray
        ``T[a, b]``; 0 on the natural successor, ``inf`` where no slot compares.
    """
    n = view.n
    S = slots
    off = np.arange(-S, S + 1)
    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a, b = a.ravel(), b.ravel()
    # output: a-S+1..a at offsets -S..-1, b..b+S at offsets 0..S
    ov = np.where(off[None, :] < 0, a[:, None] + 1 + off[None, :], b[:, None] + off[None, :])
    ov = np.where((ov >= 0) & (ov < n), ov, -1)
    blk = off == 0
    pw = slot_pair_weights(off, 0.0, max(S, 1))
    out = np.empty(a.size)
    chunk = max(1, 200_000 // (2 * S + 1) // max(view.P.shape[1], 1))
    for s in range(0, a.size, chunk):
        sl = slice(s, s + chunk)
        n1, d1, _ = window_cost(view, ov[sl], b[sl, None] + off[None, :], blk, pw)
        n2, d2, _ = window_cost(view, ov[sl], a[sl, None] + 1 + off[None, :], blk, pw)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[sl] = 0.5 * (n1 / d1 + n2 / d2)
    T = out.reshape(n, n)
    T[~np.isfinite(T)] = np.inf
    nat = np.arange(n - 1)
    T[nat, nat + 1] = 0.0
    return T


def transition_graph(
    costs: np.ndarray, *, threshold: float = 0.1, min_jump: int = 2
) -> np.ndarray:
    """Thresholded transition graph.

    Parameters
    ----------
    costs : (n, n) float ndarray
        From :func:`transition_costs`.
    threshold : float
        Quantile (0–1) of the jump costs (``|b - (a+1)| >= min_jump``) kept as edges.
    min_jump : int
        Shortest jump (nodes skipped or replayed) that is an edge; a shorter one is
        the natural successor shifted in time, which refinement may turn back into
        it (merging the runs on either side past ``max_run``).

    Returns
    -------
    (n, n) float ndarray
        Edge costs, ``inf`` where there is no edge; natural successors always kept.
    """
    n = costs.shape[0]
    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    jump = np.abs(b - (a + 1)) >= max(int(min_jump), 2)
    vals = costs[jump & np.isfinite(costs)]
    cut = np.quantile(vals, threshold) if vals.size else -np.inf
    E = np.where(jump & (costs <= cut), costs, np.inf)
    nat = np.arange(n - 1)
    E[nat, nat + 1] = 0.0
    return E


def jump_window(costs: np.ndarray, variety: float) -> float:
    """Draw window of the graph walk: the ``variety`` quantile of the input's own
    best-jump costs.

    Parameters
    ----------
    costs : (n, n) float ndarray
        From :func:`transition_costs`.
    variety : float
        0–1 (clipped): roughly the share of the input's nodes whose best jump lies
        in the window; 0 gives a zero window (only the cheapest successor is drawn).

    Returns
    -------
    float
        ``min_b costs[a, b]`` over jumps (``|b - (a+1)| >= 2``) per node ``a``, its
        ``variety`` quantile over the nodes (0 when no node has a finite jump).
    """
    n = costs.shape[0]
    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    best = np.where(np.abs(b - (a + 1)) >= 2, costs, np.inf).min(axis=1)
    best = best[np.isfinite(best)]
    q = float(np.clip(variety, 0.0, 1.0))
    return float(np.quantile(best, q)) if best.size and q > 0 else 0.0


def _natural_and_jumps(E: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(n,)`` cost of each node's natural successor edge (inf for the last) and the
    ``(n, n)`` edge costs without those edges (jumps only)."""
    n = E.shape[0]
    nat = np.full(n, np.inf)
    nat[:-1] = np.diagonal(E, 1)
    J = E.copy()
    J[np.arange(n - 1), np.arange(1, n)] = np.inf
    return nat, J


def _min_cost_to_end(
    E: np.ndarray, end: np.ndarray, steps: int, max_run: int | None, end_run: int = 0
) -> np.ndarray:
    """``D[k, v, i]``: cheapest ``k``-edge path from ``v`` into ``end`` when ``v`` is the
    ``i + 1``-th node of a verbatim run, no run longer than ``max_run`` nodes (inf: none;
    ``max_run=None``: no limit, one run index); the run reaching ``end`` goes on for
    ``end_run`` more nodes.
    """
    n = E.shape[0]
    if max_run is None:
        D = np.full((steps + 1, n, 1), np.inf)
        D[0, end] = 0.0
        for k in range(1, steps + 1):
            D[k, :, 0] = np.min(E + D[k - 1, :, 0][None, :], axis=1)
        return D
    R = max_run
    nat, J = _natural_and_jumps(E)
    D = np.full((steps + 1, n, R), np.inf)
    D[0, end[:, None], np.arange(max(R - end_run, 1))[None, :]] = 0.0
    for k in range(1, steps + 1):
        jump = np.min(J + D[k - 1, :, 0][None, :], axis=1)  # a jump starts a new run
        cont = np.full((n, R), np.inf)
        cont[:-1, :-1] = nat[:-1, None] + D[k - 1, 1:, 1:]  # v → v+1, one node longer
        D[k] = np.minimum(jump[:, None], cont)
    return D


def graph_path(
    E: np.ndarray,
    steps: int,
    rng: np.random.Generator,
    *,
    start: int | None,
    end: int | None,
    slack: float = 0.5,
    unit: float = 1.0,
    max_run: int | None = None,
    run_before: int = 1,
    keep: int = 0,
    end_run: int = 0,
    window: float = np.inf,
    k_best: int | None = None,
    usage: np.ndarray | None = None,
    usage_weight: float = 0.0,
    settle: int = 0,
    escapes: np.ndarray | None = None,
    where: str = "gap",
) -> np.ndarray:
    """A random path of exactly ``steps`` edges under a cost bound (DFS).

    The exact remaining-cost table prunes every successor that cannot finish
    within the bound, so the search is a forward walk; at each node the next one
    is drawn (seeded) among the allowed successors ``v`` ranked by their *key*
    ``E[u, v] + usage_weight · max(window, unit) · U(v)``, where ``U(v)`` is the
    mean number of times the input nodes ``v … v + 2·settle`` (the material ``v``
    plays next) are already in the output (``usage`` plus the path so far): the
    draw is uniform among the ``k_best`` lowest keys within ``window`` of the
    lowest.  While the current verbatim run has fewer than ``settle`` nodes the
    natural successor is taken when allowed (a jump is not followed by another
    inside its neighbourhood).  The defaults draw uniformly among all allowed
    successors (the thesis' random DFS).

    Parameters
    ----------
    E : (n, n) float ndarray
        Edge costs (``inf``: no edge).
    steps : int
        Edges in the path.
    rng : numpy.random.Generator
    start, end : int or None
        Anchor nodes (``None``: free).
    slack : float
        Cost bound ``(1 + slack) × cheapest + slack × unit`` (plus, with a run limit
        and a finite ``window``, one ``window`` per jump the limit forces,
        ``steps // max_run``: those jumps are drawn too, not all the cheapest).
    unit : float
        Cost unit of the level.
    max_run : int, optional
        Most nodes a verbatim run (natural successors) may have.  Where no path
        keeps it (too few edges or steps), every node without a jump edge first gets
        its cheapest transition of ``escapes`` as one; where that is not enough, the
        smallest limit some path keeps is used instead.  ``None``: no limit.
    run_before : int
        Nodes of the verbatim run that ends at ``start`` (``start`` included).
    keep : int
        Natural edges the path keeps after ``start`` and before ``end`` (a
        constrained node is copied with its neighbourhood); dropped where the
        input or the gap is too short for them.
    end_run : int
        Nodes the verbatim run reaching ``end`` goes on for after it (counted
        against ``max_run``).
    window : float
        Draw window in edge-cost units (e.g. :func:`jump_window`); ``inf``: every
        allowed successor, 0: only the lowest key.
    k_best : int, optional
        Most successors drawn among (``None``: all within ``window``).
    usage : (n,) float ndarray, optional
        Times each input node is already in the output outside this path.
    usage_weight : float
        Windows (``max(window, unit)``) added to a key per use of the material it
        plays next; 0 disables.
    settle : int
        Verbatim nodes a run needs before the next drawn jump, and the half width
        of the material ``U`` measures (0: no rule, ``U`` of ``v`` alone).
    escapes : (n, n) float ndarray, optional
        Costs of the transitions outside the graph that may become edges so that
        ``max_run`` holds (``inf``: none; its natural successors are ignored), e.g.
        every jump of the graph's ``min_jump``: ``transition_graph(costs,
        threshold=1.0, min_jump=…)``.  ``None``: the graph only.
    where : str
        Gap description for error messages.

    Returns
    -------
    (steps + 1,) int ndarray
        Nodes of the path including both ends.

    Raises
    ------
    UnreachableGapError
        No path of that length joins the anchors.
    """
    draw = {"window": window, "k_best": k_best, "usage": usage,
            "usage_weight": usage_weight, "settle": settle}
    n = E.shape[0]
    head = keep if start is not None and start + keep < n else 0
    tail = keep if end is not None and end - keep >= 0 else 0
    if (head or tail) and steps - head - tail >= 1:
        try:
            inner = graph_path(
                E, steps - head - tail, rng,
                start=None if start is None else start + head,
                end=None if end is None else end - tail, slack=slack, unit=unit,
                max_run=max_run, run_before=run_before + head, keep=0,
                end_run=tail, escapes=escapes, where=where, **draw)
            none = np.zeros(0, np.int64)
            return np.concatenate([
                np.arange(start, start + head, dtype=np.int64) if head else none, inner,
                np.arange(end - tail + 1, end + 1, dtype=np.int64) if tail else none])
        except UnreachableGapError:
            pass  # the gap cannot keep the neighbourhoods: search without them
    end_set = np.arange(n) if end is None else np.array([end])
    starts = np.arange(n) if start is None else np.array([start])
    E, R, i0, D = _run_limit_kept(E, end_set, starts, steps, max_run, start, run_before,
                                  end_run, escapes)
    feasible = starts[np.isfinite(D[steps, starts, i0])]
    if feasible.size == 0:
        raise UnreachableGapError(
            f"{where}: unreachable — no path of {steps} transitions in the transition graph "
            f"joins input node {start} to input node {end} at the coarsest level; raise "
            "graph_threshold, move the constraints, or use method='meeting_point'"
        )
    best = float(np.min(D[steps, feasible, i0]))
    bound = best * (1.0 + slack) + slack * unit
    if R is not None and np.isfinite(window):
        bound += window * (steps // R)  # each jump the run limit forces: a drawn one
    nat, J = _natural_and_jumps(E)
    base = np.zeros(n) if usage is None else np.asarray(usage, dtype=np.float64)
    weigh = usage_weight > 0
    scale = usage_weight * max(window if np.isfinite(window) else 0.0, unit)
    plain = not weigh and not np.isfinite(window) and k_best is None and settle <= 0
    run0 = max(int(run_before), 1) if start is not None else 1
    # depth-first search with the exact remaining-cost table as pruning bound;
    # a stack entry: (path, cost so far, run index of its last node, nodes in its run)
    first = rng.permutation(feasible)
    first = first[D[steps, first, i0] <= bound]
    stack: list[tuple[list[int], float, int, int]] = [
        ([int(v)], 0.0, i0, run0) for v in first[::-1]]
    while stack:
        path, acc, i, run = stack.pop()
        k = steps - (len(path) - 1)
        if k == 0:
            return np.asarray(path, dtype=np.int64)
        u = path[-1]
        nxt = [(int(v), acc + float(J[u, v]), 0, 1) for v in np.flatnonzero(
            np.isfinite(J[u]) & (acc + J[u] + D[k - 1, :, 0] <= bound + 1e-12))]
        inext = 0 if R is None else i + 1  # (no limit: one run index)
        natural = (u + 1 < n and (R is None or inext < R)
                   and acc + nat[u] + D[k - 1, u + 1, inext] <= bound + 1e-12)
        if natural:
            nxt.append((u + 1, acc + float(nat[u]), inext, run + 1))
        if plain:
            order = rng.permutation(len(nxt))
        else:
            order = _drawn_order(nxt, acc, run, natural, settle, window, k_best,
                                 (base + np.bincount(path, minlength=n)) if weigh else None,
                                 scale, rng)
        for j in order[::-1]:
            stack.append((path + [nxt[j][0]], *nxt[j][1:]))
    raise UnreachableGapError(f"{where}: no path within the cost bound {bound:.3g}")


def _run_limit_kept(E, end_set, starts, steps, max_run, start, run_before, end_run,
                    escapes=None):
    """``(E, R, i0, D)``: the graph and the run limit a path can keep, the start's run
    index and the remaining-cost table (:func:`_min_cost_to_end`).

    The limit is ``max_run``; where no path keeps it, the graph with the nodes that have
    no jump edge given their cheapest ``escapes`` transition (:func:`_with_escapes`),
    and where still none does, the smallest larger limit some path keeps (``R`` ``None``
    without a limit).
    """
    n = E.shape[0]
    R = None if max_run is None else max(int(max_run), 1)
    tried_escapes = escapes is None
    while True:
        i0 = 0 if R is None or start is None else min(max(int(run_before), 1), R) - 1
        D = _min_cost_to_end(E, end_set, steps, R, end_run if R is not None else 0)
        if R is None or np.isfinite(D[steps, starts, i0]).any():
            return E, R, i0, D
        if not tried_escapes:  # first the limit kept through the cheapest extra jumps
            E, tried_escapes = _with_escapes(E, escapes), True
            continue
        R = None if R > n + steps else R + max(1, R // 4)  # relax the limit by a quarter


def _with_escapes(E: np.ndarray, escapes: np.ndarray) -> np.ndarray:
    """``E`` with an edge from every node that has no jump edge: its cheapest jump in
    ``escapes`` (nodes with none there keep none)."""
    _, J = _natural_and_jumps(E)
    _, X = _natural_and_jumps(np.asarray(escapes, dtype=np.float64))
    lone = np.flatnonzero(~np.isfinite(J).any(axis=1) & np.isfinite(X).any(axis=1))
    out = E.copy()
    b = np.argmin(X[lone], axis=1)
    out[lone, b] = X[lone, b]
    return out


def _drawn_order(nxt, acc, run, natural, settle, window, k_best, counts, scale, rng):
    """Order in which the DFS tries the successors ``nxt``: the drawn one first, then the
    rest of the drawable ones, then the others (see :func:`graph_path`)."""
    m = len(nxt)
    if m == 0:  # a dead end (only through rounding: the table is exact): backtrack
        return np.zeros(0, dtype=np.int64)
    if natural and run < settle:  # the last jump is not settled yet: play on
        return np.r_[m - 1, rng.permutation(m - 1)]
    v = np.array([e[0] for e in nxt], dtype=np.int64)
    key = np.array([e[1] for e in nxt]) - acc
    if counts is not None:
        key = key + scale * ahead_usage(counts, 2 * max(settle, 0) + 1, 1)[v]
    order = np.argsort(key, kind="stable")
    ok = key[order] <= key[order[0]] + window
    if k_best is not None:
        ok &= np.arange(m) < k_best
    chosen, rest = order[ok], order[~ok]
    return np.r_[rng.permutation(chosen), rng.permutation(rest)].astype(np.int64)
