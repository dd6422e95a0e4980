"""Fragments the merge rounds left, against the filled trajectories, jointly.

Beyond Park & Hodgins 2006, §4.2.

:func:`assign_fragments` judges each fragment left unmerged by
:func:`mocapflow.stages.skin.merge.merge_fragments` against the hole filling of the
merged data with the paper's tolerances (:func:`_fill_candidates`: the entry sample
within ε₁, the mean within ε₁, every sample within ε₂), then, in rounds until nothing
changes, merges a fragment that is exactly a marker's gap and continues its
trajectory at the gap's end(s) (:func:`_exact_gap_jumps`, :data:`EXACT_GAP_JUMP`),
and solves the others in frame windows of fragments that overlap in time and share
a candidate marker (:func:`_windows`) as assignment problems (:func:`_decide`,
``scipy.optimize.linear_sum_assignment``; ambiguous merges refused within
:data:`ASSIGNMENT_RATIO`).  Fragments shorter than
:data:`~mocapflow.stages.skin.merge.ASSIGN_MIN_FRAMES` frames (defined with the merge
rounds, which hold such fragments to a tighter mean) merge only by continuing an exact
gap.  The rounds that alternate it with the hole filling:
:func:`mocapflow.stages.skin.clean._fill_merge_rounds`.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linear_sum_assignment

from mocapflow.stages.skin.merge import (
    ASSIGN_MIN_FRAMES,
    OVERLAPS_EVERY_MARKER,
    _is_run,
    _nan_stats,
    _spread,
    _tolerances,
)
from mocapflow.stages.skin.predict import finite_rows
from mocapflow.stages.skin.surface import MarkerSurface

#: Joint assignment (:func:`assign_fragments`): a merge is refused as ambiguous
#: when the best other labelling of the fragments it involves costs less than
#: this many times the chosen one (costs: mean distances in units of ε₁), or
#: a marker not taken by an overlapping fragment comes within this ratio.
ASSIGNMENT_RATIO = 3.0
#: A fragment whose frames are exactly a marker's gap continues that marker when
#: it starts (ends) within this share of ε₁ of the marker's trajectory
#: extrapolated linearly across the gap end(s) (:func:`_exact_gap_jumps`).
EXACT_GAP_JUMP = 0.25
#: Cost of an impossible pair in the assignment matrices.
_FORBIDDEN = 1e6


@dataclass
class _Candidates:
    """One fragment against the estimates of the markers missing in all its frames.

    ``markers`` with estimates in at least half of the fragment's frames (and a
    screened mean distance below :data:`ASSIGNMENT_RATIO` ε₁), ``cost`` their
    mean distance / ε₁, ``ok`` whether they pass the entry (``ε₁``), mean
    (``ε₁``) and tube (``ε₂``) tests, ``entry`` / ``mean`` / ``max`` in metres,
    ``short``: fewer than :data:`~mocapflow.stages.skin.merge.ASSIGN_MIN_FRAMES` frames.
    """

    markers: np.ndarray
    cost: np.ndarray
    ok: np.ndarray
    entry: np.ndarray
    mean: np.ndarray
    max: np.ndarray
    short: bool = False


def _fill_candidates(frag: np.ndarray, T: np.ndarray, free: np.ndarray, E: np.ndarray,
                     eps1: np.ndarray, eps2: np.ndarray, screen: float) -> _Candidates:
    """:class:`_Candidates` of one fragment (frames ``T``) against the estimates ``E``."""
    cands = np.flatnonzero(free)
    if len(cands):  # screen on a few frames: only near markers can be chosen or rivals
        sub = _spread(len(T))
        ds = np.linalg.norm(frag[sub][:, None] - E[T[sub]][:, cands], axis=-1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            cands = cands[np.nanmean(ds, 0) < screen * eps1[cands]]
    d = np.linalg.norm(frag[:, None] - E[T][:, cands], axis=-1)
    have = np.isfinite(d)
    cov = have.sum(0) >= max(1, int(np.ceil(0.5 * len(T))))
    cands, d, have = cands[cov], d[:, cov], have[:, cov]
    entry = d[np.argmax(have, 0), np.arange(len(cands))]
    d_max, d_mean = _nan_stats(np.where(have, d, np.nan)) if len(cands) else (d[0], d[0])
    e1, e2 = eps1[cands], eps2[cands]
    ok = (entry < e1) & (d_mean < e1) & (d_max < e2)
    short = len(T) < ASSIGN_MIN_FRAMES  # a rival in the windows, never chosen there
    return _Candidates(cands, d_mean / e1, ok, entry, d_mean, d_max, short)


def _exact_gap_jumps(X: np.ndarray, avail: np.ndarray, frag: np.ndarray, T: np.ndarray,
                     markers: np.ndarray) -> np.ndarray:
    """``(len(markers),)`` the larger jump at the ends of a marker's gap that is exactly
    the fragment's frames ``T`` (NaN where the gap is not exactly ``T``).

    A jump is the distance from the fragment's end sample to the marker's trajectory
    extrapolated linearly over one frame from its two samples beyond the gap end
    (one sample: held).  A gap reaching the start or end of the capture has one end.
    """
    F = len(X)
    out = np.full(len(markers), np.nan)
    if not _is_run(T) or not len(markers):
        return out
    a, b = int(T[0]), int(T[-1])
    jumps = []
    for end, step, sample in ((a - 1, -1, frag[0]), (b + 1, 1, frag[-1])):
        if not 0 <= end < F:
            jumps.append(np.zeros(len(markers)))
            continue
        inside = avail[end, markers]
        p = X[end, markers]
        far = end + step
        if 0 <= far < F:
            two = inside & avail[far, markers]
            p = np.where(two[:, None], 2 * p - X[far, markers], p)
        jumps.append(np.where(inside, np.linalg.norm(sample - p, axis=-1), np.nan))
    if a == 0 and b == F - 1:
        return out
    return np.maximum(jumps[0], jumps[1])  # NaN where either end is not measured


def _windows(rest: list[int], cand: dict[int, _Candidates], lo: np.ndarray, hi: np.ndarray,
             ratio: float) -> dict[int, list[int]]:
    """The frame window of each fragment ``u`` of ``rest``: ``u`` first, then the others
    that share a frame with it and a candidate marker within ``ratio``."""
    if not rest:
        return {}
    r = np.asarray(rest)
    ii = np.concatenate([np.full(int((cand[u].cost < ratio).sum()), i)
                         for i, u in enumerate(rest)])
    jj = np.concatenate([cand[u].markers[cand[u].cost < ratio] for u in rest])
    A = sp.csr_matrix((np.ones(len(ii)), (ii, jj)),
                      shape=(len(rest), int(jj.max(initial=0)) + 1))
    share = (A @ A.T).toarray() > 0
    link = share & (lo[r][:, None] <= hi[r][None]) & (lo[r][None] <= hi[r][:, None])
    np.fill_diagonal(link, False)
    return {u: [u] + [rest[j] for j in np.flatnonzero(link[i])] for i, u in enumerate(rest)}


def _solve(cost: np.ndarray) -> np.ndarray:
    """Column of each row (``(n,)``) minimising the total cost."""
    r, c = linear_sum_assignment(cost)
    col = np.empty(cost.shape[0], dtype=np.int64)
    col[r] = c
    return col


def _decide(rows: list[int], cand: dict[int, _Candidates],
            ratio: float) -> tuple[int, int] | None:
    """The joint assignment of the window ``rows`` (fragments overlapping ``rows[0]``),
    decided for ``rows[0]``.

    Rows are the fragments, columns their candidate markers and one "unmerged"
    column per fragment at cost 1 (the tolerance caps the cost: a pair failing
    the entry, mean or tube test is forbidden), costs the mean distances in
    units of ε₁; ``scipy.optimize.linear_sum_assignment`` minimises the total.
    When ``rows[0]`` gets a marker ``m``, the choice must be clear: every other
    candidate of it within ``ratio`` times its cost must be taken by another
    fragment of the window (which overlaps it), and the best labelling with
    ``rows[0]`` on another marker (any candidate, within the tolerance or not)
    must cost at least ``ratio`` times the chosen one over the fragments it
    changes.

    Returns ``(m, -1)`` to merge, ``(m, rival)`` if ambiguous, ``None`` if
    ``rows[0]`` is better left unmerged (its markers taken by closer fragments).
    """
    cols = np.unique(np.concatenate([cand[u].markers for u in rows]))
    n, k = len(rows), len(cols)
    full = np.full((n, k + n), _FORBIDDEN)
    feas = np.full((n, k + n), _FORBIDDEN)
    for i, u in enumerate(rows):
        c = cand[u]
        j = np.searchsorted(cols, c.markers)
        full[i, j] = c.cost
        feas[i, j[c.ok]] = c.cost[c.ok]
        feas[i, k + i] = full[i, k + i] = 1.0
    best = _solve(feas)
    j = int(best[0])
    if j >= k:
        return None
    bcost = feas[np.arange(n), best]
    taken = set(int(x) for x in best[1:] if x < k)
    loose = [r for r in np.flatnonzero(full[0, :k] < ratio * bcost[0])
             if r != j and int(r) not in taken]
    if loose:
        return int(cols[j]), int(cols[loose[0]])
    alt_cost = feas.copy()
    alt_cost[0] = full[0]
    alt_cost[0, j] = alt_cost[0, k] = _FORBIDDEN
    alt = _solve(alt_cost)
    acost = alt_cost[np.arange(n), alt]
    if (acost >= _FORBIDDEN).any():
        return int(cols[j]), -1  # no other labelling
    ch = alt != best
    if acost[ch].sum() < ratio * bcost[ch].sum():
        return int(cols[j]), int(cols[alt[0]])
    return int(cols[j]), -1


def assign_fragments(
    positions: np.ndarray,
    fragments: np.ndarray,
    surface: MarkerSurface,
    estimates: np.ndarray,
    *,
    alpha1: float = 0.5,
    alpha2: float = 0.6,
    ratio: float = ASSIGNMENT_RATIO,
    fragment_labels: list[str] | None = None,
    max_rounds: int = 20,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Merge fragments against filled trajectories, jointly (beyond the paper, §4.2).

    The fragments the §4.2 rounds left are judged against ``estimates`` (the
    hole filling of the merged data) with the paper's tolerances: the entry
    sample within ``ε₁``, the mean distance within ``ε₁``, every sample within
    ``ε₂`` (:func:`_fill_candidates`).  Then, in rounds until nothing changes:

    1. a fragment whose frames are exactly a marker's gap and that continues the
       marker's trajectory at the gap's end(s) within :data:`EXACT_GAP_JUMP` ε₁
       (:func:`_exact_gap_jumps`) is merged when it passes the tests and is the
       only such fragment of the only such marker (two markers cannot both
       continue into the same samples);
    2. the other fragments are grouped into windows of fragments that overlap
       in time and share a candidate marker (:func:`_windows`), and each window
       is solved as an assignment problem (``scipy.optimize.linear_sum_assignment``)
       on the mean distances in units of ε₁, the tolerance as the cost cap;
       ambiguous pairs are refused (:func:`_decide`).

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        Labelled (merged) trajectories, NaN where missing.
    fragments : (F, U, 3) float ndarray
        Unlabelled fragments, NaN outside each.
    surface : MarkerSurface
    estimates : (F, M, 3) float ndarray
        Filled trajectories (used where ``positions`` is missing).
    alpha1, alpha2 : float
        ``ε₁ = α₁ d̄``, ``ε₂ = α₂ d̄`` as in
        :func:`~mocapflow.stages.skin.merge.merge_fragments`.
    ratio : float
        :data:`ASSIGNMENT_RATIO`.
    fragment_labels : list of str, optional
    max_rounds : int

    Returns
    -------
    positions : (F, M, 3) float ndarray
        With the merged fragments written in.
    assigned : (U,) int ndarray
        Marker of each fragment, ``-1`` if none.
    report : dict
        ``merges``, ``rejections``, ``conflicts`` as
        :func:`~mocapflow.stages.skin.merge.merge_fragments`.
    """
    F, U = fragments.shape[:2]
    X = positions.copy()
    fvis = finite_rows(fragments)
    frames_of = [np.flatnonzero(fvis[:, u]) for u in range(U)]
    flabels = list(fragment_labels or [f"*{u + 1}" for u in range(U)])
    labels = surface.labels
    dbar, eps1, eps2 = _tolerances(surface, alpha1, alpha2)
    usable = np.isfinite(dbar)
    E = np.where(np.isfinite(positions), np.nan, estimates)
    assigned = np.full(U, -1, dtype=np.int64)
    lo = np.array([T[0] if len(T) else F for T in frames_of], dtype=np.int64)
    hi = np.array([T[-1] if len(T) else -1 for T in frames_of], dtype=np.int64)
    verdict: dict[int, dict[str, Any]] = {u: {"reason": "empty fragment"}
                                          for u in range(U) if not len(frames_of[u])}
    merges: list[dict[str, Any]] = []
    conflicts: list[dict[str, Any]] = []
    mm = 1000.0

    def merge(u: int, m: int, c: _Candidates, how: str, rnd: int) -> None:
        T = frames_of[u]
        X[T, m] = fragments[T, u]
        assigned[u] = m
        verdict.pop(u, None)
        i = int(np.flatnonzero(c.markers == m)[0])
        merges.append({
            "fragment": flabels[u], "label": labels[m], "first_frame": int(T[0]),
            "last_frame": int(T[-1]), "n_frames": len(T),
            "entry_mm": round(float(c.entry[i]) * mm, 2),
            "mean_mm": round(float(c.mean[i]) * mm, 2),
            "max_mm": round(float(c.max[i]) * mm, 2), "eps1_mm": round(float(eps1[m] * mm), 2),
            "eps2_mm": round(float(eps2[m] * mm), 2), "round": rnd, "predictor": "fill",
            "depth": how,
        })

    # the estimates are fixed: candidates are judged once, and only lose the markers
    # merges fill in their frames
    avail = finite_rows(X)
    judged: dict[int, _Candidates] = {}
    for u in range(U):
        T = frames_of[u]
        if len(T):
            judged[u] = _fill_candidates(fragments[T, u], T, ~avail[T].any(0) & usable, E,
                                         eps1, eps2, ratio)
    for rnd in range(max_rounds):
        todo = [u for u in range(U) if assigned[u] < 0 and len(frames_of[u])]
        if not todo:
            break
        avail = finite_rows(X)
        cand: dict[int, _Candidates] = {}
        for u in todo:
            c = judged[u]
            keep = ~avail[frames_of[u]][:, c.markers].any(0)
            cand[u] = _Candidates(*(getattr(c, f)[keep] for f in
                                    ("markers", "cost", "ok", "entry", "mean", "max")),
                                  short=c.short)
        n_before = int((assigned >= 0).sum())
        # 1. exact gaps continued at their ends
        exact: dict[int, list[int]] = {}
        for u in todo:
            c = cand[u]
            jump = _exact_gap_jumps(X, avail, fragments[frames_of[u], u], frames_of[u],
                                    c.markers[c.ok])
            cont = c.markers[c.ok][jump < EXACT_GAP_JUMP * eps1[c.markers[c.ok]]]
            if len(cont) == 1:
                exact.setdefault(int(cont[0]), []).append(u)
            elif len(cont) > 1:
                verdict[u] = {"reason": "continues several markers' gaps: "
                              + ", ".join(labels[int(m)] for m in cont[:3])}
        for m, us in exact.items():
            if len(us) == 1:
                merge(us[0], m, cand[us[0]], "exact gap", rnd)
            else:
                for u in us:
                    verdict[u] = {"reason": f"several fragments continue the gap of {labels[m]}"}
        if int((assigned >= 0).sum()) > n_before:
            continue  # availability changed: judge the rest again
        # 2. per fragment, its frame window solved jointly; merges closest first
        rest = [u for u in todo if assigned[u] < 0 and len(cand[u].markers)]
        for u in todo:
            if assigned[u] < 0 and not len(cand[u].markers):
                verdict[u] = {"reason": f"no filled marker within {ratio:g} eps1 (of the "
                                        "markers missing in all its frames)"
                              if (~avail[frames_of[u]].any(0) & usable).any() else
                              OVERLAPS_EVERY_MARKER}
        decided = []
        window = _windows(rest, cand, lo, hi, ratio)
        for u in rest:
            if not cand[u].ok.any():
                verdict[u] = {"reason": "no filled marker within eps1 / eps2"}
                continue
            if cand[u].short:
                verdict[u] = {"reason": f"shorter than {ASSIGN_MIN_FRAMES} frames and no "
                                        "exact gap continued"}
                continue
            d = _decide(window[u], cand, ratio)
            if d is None:
                verdict[u] = {"reason": "no filled marker within eps1 / eps2 left "
                                        "(overlapping fragments closer)"}
            elif d[1] >= 0:
                m, r = d
                why = (f"ambiguous assignment: {labels[m]} or {labels[r]} "
                       f"(within ratio {ratio:g})")
                if verdict.get(u, {}).get("reason") != why:
                    conflicts.append({"fragment": flabels[u], "labels": [labels[m], labels[r]],
                                      "resolution": "ambiguous assignment: not merged"})
                verdict[u] = {"reason": why}
            else:
                i = int(np.flatnonzero(cand[u].markers == d[0])[0])
                decided.append((float(cand[u].cost[i]), u, d[0], len(window[u]) > 1))
        for _, u, m, joint in sorted(decided):
            if np.isfinite(X[frames_of[u], m]).any():
                continue  # an overlapping fragment took it first: judged again next round
            merge(u, m, cand[u], "assignment" if joint else "alone", rnd)
        if int((assigned >= 0).sum()) == n_before:
            break
    n_rounds = rnd + 1 if U else 0
    rejections = [{"fragment": flabels[u], "n_frames": len(frames_of[u]),
                   "first_frame": int(frames_of[u][0]) if len(frames_of[u]) else None,
                   **verdict.get(u, {"reason": "not examined"})}
                  for u in range(U) if assigned[u] < 0]
    return X, assigned, {"merges": merges, "rejections": rejections, "conflicts": conflicts,
                         "rounds": n_rounds}
