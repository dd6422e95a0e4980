"""Greedy structure search of the prior and transition networks (Lau et al. 2009, §5).

Prior network (:func:`search_prior`)
    Greedy hill climbing with edge addition, deletion and reversal under
    acyclicity, at most ``max_parents`` parents, from the empty graph and from
    ``restarts`` random DAGs; the best-scoring result is kept.  The no-parent
    and single-parent scores of every node are computed in parallel through
    ``ctx.map``, and so are the starts (independent searches: the result is
    the serial one).
Transition network (:func:`search_transition`)
    Parents come only from earlier frames, so each node's search
    (addition/deletion) is independent and runs in parallel through ``ctx.map``;
    each greedy step scores all neighbouring parent sets of the node in one
    vectorised batch (an added parent's squared distances are added to the
    current set's, computed once per step, instead of summed anew).

Parallel work goes to ``ctx.map`` in ``4 × workers`` round-robin batches of
nodes (one task per node is too small to amortise the round trip).  Scores
(:mod:`~mocapflow.stages.variation.scores`) are cached per (node, parent set),
so an edge change re-scores only the one or two nodes it touches.  Candidate
parents are restricted to the ``candidates`` most correlated nodes (the sparse
candidate algorithm of Friedman et al. 1999, an addition; ``None`` searches all).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context
from mocapflow.stages.variation.scores import prior_node_fits, transition_node_fits
from mocapflow.stages.variation.training import PriorData, TransitionData

__all__ = ["DAG", "NetworkSearch", "search_prior", "search_transition"]


@dataclass
class NetworkSearch:
    """Structure found for one network.

    Attributes
    ----------
    parents : list of list of int
        Parent nodes of each node (``2D`` prior nodes, or ``D`` transition
        nodes with the self parents implicit).
    scores : (n,) float ndarray
        Cross-validated log-likelihood of each node.
    bandwidth : (n,) float ndarray
        Kernel bandwidth of each node (standardised units).
    evaluations : int
        Parent sets scored.
    """

    parents: list[list[int]]
    scores: np.ndarray
    bandwidth: np.ndarray
    evaluations: int


def search_transition(
    data: TransitionData,
    *,
    candidates: int | None,
    max_parents: int,
    score: Literal["propagated", "one_step"],
    ctx: Context,
    required: tuple[int, ...] = (),
    horizon: int | None = None,
) -> NetworkSearch:
    """Parents of every transition node, searched independently per node (in parallel).

    Parameters
    ----------
    data : TransitionData
        ``D`` DOFs.
    candidates : int or None
        Candidate parents per node (most correlated with the node's delta and
        next value); ``None``: all ``2D − 2`` non-self nodes.
    max_parents : int
    score : {"propagated", "one_step"}
    ctx : Context
        ``ctx.map`` runs the per-node searches.
    required : tuple of int
        Parents every node has (besides its self parents; the cycle phase
        DOFs of cyclic models): the search starts from them, never deletes
        them, and ``max_parents`` counts the others.
    horizon : int or None
        Frames between re-anchorings of the propagated score
        (:func:`~mocapflow.stages.variation.scores.transition_node_fits`;
        ``None``: never, the paper's form).

    Returns
    -------
    NetworkSearch
        ``D`` parent lists over ``0..2D-1`` (``X[t]`` then ``X[t+1]``).
    """
    D = data.n_dofs
    pool = list(range(2 * D))
    items = []
    for i in range(D):
        req = [r for r in required if r not in (i, D + i)]
        idx = [p for p in pool if p not in (i, D + i) and p not in req]
        target = np.stack([data.Y[:, i], data.Z2[:, i]], axis=1)
        items.append((i, _top_candidates(target, data.F, idx, candidates), req))
    fn = functools.partial(
        _search_transition_node, data=data, max_parents=max_parents, score=score,
        horizon=horizon,
    )
    results = _map_batched(ctx, fn, items, label="transition nodes")
    return NetworkSearch(
        parents=[r["parents"] for r in results],
        scores=np.array([r["score"] for r in results]),
        bandwidth=np.array([r["bandwidth"] for r in results]),
        evaluations=int(sum(r["evaluations"] for r in results)),
    )


def search_prior(
    data: PriorData,
    *,
    candidates: int | None,
    max_parents: int,
    restarts: int,
    seed: int,
    ctx: Context,
) -> NetworkSearch:
    """Prior-network DAG by greedy add / delete / reverse, best of ``restarts + 1`` starts.

    Parameters
    ----------
    data : PriorData
        ``2D`` nodes.
    candidates : int or None
        Candidate parents per node; ``None``: all other nodes.
    max_parents : int
    restarts : int
        Random initial DAGs tried after the empty one.
    seed : int
        Seed of the random initial DAGs.
    ctx : Context
        ``ctx.map`` computes the single-parent scores and runs the starts.

    Returns
    -------
    NetworkSearch
        ``evaluations`` counts the cached (node, parent set) scores.
    """
    n2 = data.Z.shape[1]
    cands = [
        _top_candidates(data.Z[:, v], data.Z, [u for u in range(n2) if u != v], candidates)
        for v in range(n2)
    ]
    singles = _map_batched(
        ctx, functools.partial(_prior_single_scores, data=data), list(enumerate(cands)),
        label="prior nodes",
    )
    cache: dict = {}
    for v, sc in enumerate(singles):
        for P, s in sc.items():
            cache[(v, P)] = s
    rng = np.random.default_rng([int(seed), 7919])
    inits = [None] + [_random_dag(cands, rng, max_parents) for _ in range(restarts)]
    # the starts are independent (scores are deterministic, the cache only saves
    # work): they run in parallel, each from the single-parent cache
    runs = _map_batched(
        ctx, functools.partial(_prior_restart, data=data, cands=cands, cache=cache,
                               max_parents=max_parents), inits, per_worker=1,
        label="prior restarts",
    )
    best = None
    for parents, sc, h, new in runs:
        cache.update(new)
        if best is None or sc.sum() > best[1].sum():
            best = (parents, sc, h)
    parents, scores, bandwidth = best
    return NetworkSearch(parents, scores, bandwidth, len(cache))


def _top_candidates(target: np.ndarray, pool: np.ndarray, idx: list[int], m: int | None):
    """The ``m`` columns of ``pool`` (indices ``idx``) most correlated with ``target``."""
    if m is None or m >= len(idx):
        return list(idx)
    t = (target - target.mean(axis=0)) / (target.std(axis=0) + 1e-12)
    p = pool[:, idx]
    p = (p - p.mean(axis=0)) / (p.std(axis=0) + 1e-12)
    corr = np.abs(t.T @ p / len(t))  # (n_targets, n_idx)
    corr = corr.max(axis=0) if corr.ndim == 2 else corr
    order = np.argsort(-corr, kind="stable")[:m]
    return sorted(int(idx[o]) for o in order)


def _search_transition_node(
    item: tuple[int, list[int]],
    *,
    data: TransitionData,
    max_parents: int,
    score: str,
    horizon: int | None = None,
    batch_bytes: int = 48 << 20,
) -> dict[str, Any]:
    """Greedy add/delete search of one transition node's parents (module level for ``ctx.map``).

    Each step scores every uncached neighbouring parent set at once
    (:func:`transition_node_fits`; in chunks of at most ``batch_bytes`` of
    distance matrices) and moves to the best while it improves.
    """
    i, cands, req = item
    cache: dict[frozenset, tuple[float, float]] = {}
    F = data.F
    feats = {c: (F[:, c][:, None] - F[:, c][None, :]) ** 2 for c in [*cands, *req]}

    def d2_of(P: frozenset, out: np.ndarray) -> np.ndarray:
        out[...] = 0.0
        for c in P:
            out += feats[c]
        return out

    N = F.shape[0]
    # a step has at most len(cands) moves (adds and deletes of candidates);
    # one buffer for the node, so its pages are touched once
    batch = max(1, min(batch_bytes // (8 * N * N), len(cands)))
    buf = np.empty((batch, N, N))

    def evaluate(sets: list[frozenset], base: frozenset | None = None) -> None:
        # an addition P | {c} is the current set's distances plus column c's
        # (computed once per step), the rest are summed from scratch
        todo = [Q for Q in dict.fromkeys(sets) if Q not in cache]
        d2_base = d2_of(base, np.empty((N, N))) if base is not None and len(todo) else None
        for a in range(0, len(todo), batch):
            chunk = todo[a : a + batch]
            out = buf[: len(chunk)]
            for j, Q in enumerate(chunk):
                extra = Q - base if d2_base is not None and base <= Q else None
                if extra is not None and len(extra) == 1:
                    np.add(d2_base, feats[next(iter(extra))], out=out[j])
                else:
                    d2_of(Q, out[j])
            sc, h2 = transition_node_fits(data, i, out, score=score, horizon=horizon)
            for Q, v, h in zip(chunk, sc, h2):
                cache[Q] = (float(v), float(h))

    P: frozenset = frozenset(req)
    evaluate([P])
    cur = cache[P][0]
    while True:
        moves = [P - {c} for c in P if c not in req]
        if len(P) < max_parents + len(req):
            moves += [P | {c} for c in cands if c not in P]
        if not moves:
            break
        evaluate(moves, base=P)
        best = max(moves, key=lambda Q: cache[Q][0])
        if cache[best][0] <= cur + 1e-9:
            break
        P, cur = best, cache[best][0]
    return {
        "parents": sorted(int(p) for p in P),
        "score": float(cur),
        "bandwidth": math.sqrt(cache[P][1]),
        "evaluations": len(cache),
    }


def _run_batch(items: list, *, fn) -> list:
    """``[fn(x) for x in items]`` (module level for ``ctx.map``)."""
    return [fn(x) for x in items]


def _map_batched(ctx: Context, fn, items: list, *, per_worker: int = 4,
                 label: str | None = None) -> list:
    """``ctx.map(fn, items)`` over ``per_worker × workers`` round-robin batches of the items.

    One task per node is too small to amortise a round trip to a worker (and
    the pickled training data travels with every task); interleaving keeps
    the batches balanced when the per-node cost grows along the list.
    ``label``: progress of the items (``ctx.progress``; per item when the map
    is sequential, else per map).
    """
    n = min(len(items), max(1, per_worker * int(getattr(ctx, "workers", 1) or 1)))
    if n <= 1 or ctx.mapper is None:
        return ctx.map(fn, items, progress=label)
    batches = [items[b::n] for b in range(n)]
    done = ctx.map(functools.partial(_run_batch, fn=fn), batches, progress=label)
    out: list = [None] * len(items)
    for b, res in enumerate(done):
        out[b::n] = res
    return out


def _prior_single_scores(v_cands: tuple[int, list[int]], *, data: PriorData) -> dict:
    """Scores of node ``v`` with no parent and with each single candidate parent."""
    v, cands = v_cands
    keys = [(), *[(u,) for u in cands]]
    sc, h2 = prior_node_fits(data, v, keys)
    return {P: (float(a), float(b)) for P, a, b in zip(keys, sc, h2)}


class DAG:
    """Parent sets with acyclicity checks."""

    def __init__(self, n: int):
        self.parents: list[set[int]] = [set() for _ in range(n)]
        self.children: list[set[int]] = [set() for _ in range(n)]

    def reaches(self, src: int, dst: int, skip: tuple[int, int] | None = None) -> bool:
        """Whether a directed path ``src ⇝ dst`` exists (ignoring edge ``skip``)."""
        stack, seen = [src], {src}
        while stack:
            a = stack.pop()
            if a == dst:
                return True
            for b in self.children[a]:
                if skip is not None and (a, b) == skip:
                    continue
                if b not in seen:
                    seen.add(b)
                    stack.append(b)
        return False

    def descendants(self, src: int) -> set[int]:
        """The nodes reachable from ``src`` (``src`` included)."""
        stack, seen = [src], {src}
        while stack:
            for b in self.children[stack.pop()]:
                if b not in seen:
                    seen.add(b)
                    stack.append(b)
        return seen

    def add(self, u: int, v: int) -> None:
        self.parents[v].add(u)
        self.children[u].add(v)

    def remove(self, u: int, v: int) -> None:
        self.parents[v].discard(u)
        self.children[u].discard(v)

    def order(self) -> list[int]:
        """A topological order."""
        indeg = [len(p) for p in self.parents]
        ready = [v for v, d in enumerate(indeg) if d == 0]
        out = []
        while ready:
            a = ready.pop(0)
            out.append(a)
            for b in sorted(self.children[a]):
                indeg[b] -= 1
                if indeg[b] == 0:
                    ready.append(b)
        return out


def _prior_restart(init, *, data: PriorData, cands: list[list[int]], cache: dict,
                   max_parents: int):
    """One greedy prior search from ``init`` (module level for ``ctx.map``): its result
    and the cache entries it added."""
    own = dict(cache)
    parents, sc, h = _prior_greedy(data, cands, own, max_parents=max_parents, init=init)
    return parents, sc, h, {key: val for key, val in own.items() if key not in cache}


def _prior_greedy(
    data: PriorData,
    cands: list[list[int]],
    cache: dict,
    *,
    max_parents: int,
    init: list[list[int]] | None,
) -> tuple[list[list[int]], np.ndarray, np.ndarray]:
    """Greedy add / delete / reverse hill climbing of the prior DAG from ``init``.

    Each step applies the best-improving legal move (acyclic, at most
    ``max_parents`` parents); ``cache`` maps ``(node, sorted parents)`` to
    :func:`~mocapflow.stages.variation.scores.prior_node_fit` results and is
    filled as the search goes (the sets a step needs, a node's at once:
    :func:`~mocapflow.stages.variation.scores.prior_node_fits`).

    Returns
    -------
    parents : list of list of int
    scores : (n,) float ndarray
    bandwidth : (n,) float ndarray
    """
    n = len(cands)
    dag = DAG(n)
    if init:
        for v, ps in enumerate(init):
            for u in ps:
                dag.add(u, v)

    pair_d2: dict = {}  # each node's pairwise squared distances, shared by the fits

    def fetch(keys) -> None:
        """Score the uncached ``(node, sorted parents)`` keys, all sets of a node at once."""
        by_node: dict[int, list[tuple]] = {}
        for key in dict.fromkeys(keys):
            if key not in cache:
                by_node.setdefault(key[0], []).append(key[1])
        for v, sets in by_node.items():
            sc, h2 = prior_node_fits(data, v, sets, pair_d2=pair_d2)
            for P, a, b in zip(sets, sc, h2):
                cache[(v, P)] = (float(a), float(b))

    def S(v: int, P) -> float:
        key = (v, tuple(sorted(P)))
        if key not in cache:
            fetch([key])
        return cache[key][0]

    fetch([(v, tuple(sorted(dag.parents[v]))) for v in range(n)])
    cur = np.array([S(v, dag.parents[v]) for v in range(n)])
    node_moves: dict[int, list[tuple[float, str, int]]] = {}

    def refresh(v: int) -> None:
        P = dag.parents[v]
        keys = [(v, tuple(sorted(P - {u}))) for u in P]
        if len(P) < max_parents:
            keys += [(v, tuple(sorted(P | {u}))) for u in cands[v] if u not in P]
        fetch(keys)
        moves = []
        if len(P) < max_parents:
            for u in cands[v]:
                if u not in P:
                    moves.append((S(v, P | {u}) - cur[v], "add", u))
        for u in P:
            moves.append((S(v, P - {u}) - cur[v], "del", u))
        node_moves[v] = moves

    for v in range(n):
        refresh(v)
    for _ in range(100 * n):
        ops = [(d, kind, u, v) for v in range(n) for d, kind, u in node_moves[v] if d > 1e-9]
        # reversals u→v  ⇒  v→u
        fetch([(u, tuple(sorted(dag.parents[u] | {v}))) for v in range(n)
               for u in dag.parents[v] if len(dag.parents[u]) < max_parents])
        for v in range(n):
            for u in dag.parents[v]:
                if len(dag.parents[u]) >= max_parents:
                    continue
                d = (S(v, dag.parents[v] - {u}) - cur[v]) + (S(u, dag.parents[u] | {v}) - cur[u])
                if d > 1e-9:
                    ops.append((d, "rev", u, v))
        if not ops:
            break
        ops.sort(key=lambda o: -o[0])
        applied = False
        desc: dict[int, set[int]] = {}  # the DAG is unchanged until a move applies
        for _, kind, u, v in ops:
            if kind == "add":
                if v not in desc:
                    desc[v] = dag.descendants(v)
                if u in desc[v]:
                    continue
                dag.add(u, v)
                touched = [v]
            elif kind == "del":
                dag.remove(u, v)
                touched = [v]
            else:
                if dag.reaches(u, v, skip=(u, v)):
                    continue
                dag.remove(u, v)
                dag.add(v, u)
                touched = [u, v]
            for t in touched:
                cur[t] = S(t, dag.parents[t])
            for t in touched:
                refresh(t)
            applied = True
            break
        if not applied:
            break
    parents = [sorted(p) for p in dag.parents]
    h = np.array([math.sqrt(cache[(v, tuple(parents[v]))][1]) for v in range(n)])
    return parents, cur, h


def _random_dag(cands: list[list[int]], rng: np.random.Generator, max_parents: int):
    """A random initial DAG: a random node order, 0–2 earlier candidate parents per node."""
    n = len(cands)
    rank = np.empty(n, dtype=int)
    rank[rng.permutation(n)] = np.arange(n)
    init = []
    for v in range(n):
        ok = [u for u in cands[v] if rank[u] < rank[v]]
        m = min(len(ok), int(rng.integers(0, 3)), max_parents)
        init.append([int(u) for u in rng.choice(ok, size=m, replace=False)] if m else [])
    return init
