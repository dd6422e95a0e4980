"""The vectorised merge helpers equal plain loops over the same rules (issue 15 throughput).

:func:`mocapflow.stages.skin.merge.continue_breaks` screens only the (fragment end,
marker) pairs with a sample within the bridge, and its rival test looks only at the
fragments seen in that frame; :func:`~mocapflow.stages.skin.merge._rival_fragment`
computes distances only for the fragments seen in enough frames;
:func:`~mocapflow.stages.skin.merge._blind_rival` counts predictions from a
:class:`~mocapflow.stages.skin.merge.PredictionIndex`; ``_nan_mean`` / ``_nan_stats``
replace ``np.nanmean`` / ``np.nanmax`` bit for bit.  Each is checked here against a
straightforward loop (or numpy's own function) on random data.
"""

from __future__ import annotations

import numpy as np
import pytest

import mocapflow.stages.skin.merge as cm
from tests.stages.skin.test_merge_keeps_samples import GRID, grid_neighbours, moving_grid


@pytest.mark.parametrize("shape", [(1, 1), (7, 1), (9, 1), (40, 1), (300, 1), (9, 2),
                                   (50, 5), (300, 17)])
def test_nan_stats_are_numpys_bit_for_bit(shape):
    rng = np.random.default_rng(shape[0] * 31 + shape[1])
    d = rng.random(shape) * 0.05
    d[rng.random(shape) < 0.3] = np.nan
    d[:, -1] = np.nan  # an all-NaN column
    with np.errstate(all="ignore"), pytest.warns(RuntimeWarning):
        want_max, want_mean = np.nanmax(d, axis=0), np.nanmean(d, axis=0)
    got_max, got_mean = cm._nan_stats(d)
    np.testing.assert_array_equal(got_max, want_max)
    np.testing.assert_array_equal(got_mean, want_mean)  # NaN where NaN, else same bits
    np.testing.assert_array_equal(cm._nan_mean(d), want_mean)


def test_spread_is_sixteen_frames_at_most_and_read_only():
    assert cm._spread(1).tolist() == [0]
    assert cm._spread(5).tolist() == [0, 1, 2, 3, 4]
    s = cm._spread(100)
    assert len(s) == 16 and s[0] == 0 and s[-1] == 99
    assert s.tolist() == np.unique(np.linspace(0, 99, 16).round().astype(int)).tolist()
    with pytest.raises(ValueError):
        s[0] = 1


def blind_case(seed, F=80, M=30):
    rng = np.random.default_rng(seed)
    E_all = rng.normal(size=(F, M, 3))
    E_all[rng.random((F, M)) < 0.4] = np.nan
    ref = rng.normal(scale=0.05, size=(M, 3))
    return rng, E_all, ref


@pytest.mark.parametrize("seed", range(6))
def test_blind_rival_with_index_equals_the_dense_count(seed):
    rng, E_all, ref = blind_case(seed)
    F, M = E_all.shape[:2]
    index_all = cm.PredictionIndex(np.zeros((F, M), bool), np.isfinite(E_all).all(-1))
    labels = [f"m{j}" for j in range(M)]
    outcomes = set()
    for _ in range(40):
        a = int(rng.integers(0, F - 2))
        T = np.arange(a, int(rng.integers(a + 1, F + 1)))
        free = rng.random(M) < 0.5
        m = int(rng.choice(np.flatnonzero(free))) if free.any() else 0
        free[m] = True
        v = {"marker": m, "entry": 0.01, "max": 0.02, "mean": float(rng.uniform(0.001, 0.03))}
        dense = cm._blind_rival(rng.normal(size=(len(T), 3)), T, v, free, E_all, ref, labels)
        fast = cm._blind_rival(rng.normal(size=(len(T), 3)), T, v, free, E_all, ref, labels,
                               index_all)
        assert fast == dense
        outcomes.add("marker" in fast)
    assert outcomes == {True, False}  # both verdicts were exercised


def rival_loop(fragments, unmerged, u, T, m, E_all, eps1):
    """``_rival_fragment``'s rule, one rival at a time: ``(rival, mean_u, mean_r)`` of the
    closest qualifying rival fragment, or None."""
    best = None
    for r in range(fragments.shape[1]):
        if r == u or not unmerged[T, r].any():
            continue
        du, dr = [], []
        for t in T:
            p = E_all[t, m]
            if unmerged[t, r] and np.isfinite(p).all():
                du.append(np.linalg.norm(fragments[t, u] - p))
                dr.append(np.linalg.norm(fragments[t, r] - p))
        if len(dr) < max(1, int(np.ceil(0.5 * len(T)))):
            continue
        mu, mr = float(np.mean(du)), float(np.mean(dr))
        if mr < eps1[m] and mr < cm.AMBIGUITY_RATIO * mu and (best is None or mr < best[2]):
            best = (r, mu, mr)
    return best


def rival_case(seed, F=60, U=25, M=6):
    """Random fragments, each a contiguous piece near marker ``r % M``'s prediction:
    ``fragments (F, U, 3)``, ``unmerged (F, U)``, ``E_all (F, M, 3)``, ``eps1 (M,)``,
    marker and fragment labels."""
    rng = np.random.default_rng(seed)
    E_all = rng.normal(scale=0.02, size=(F, M, 3))
    E_all[rng.random((F, M)) < 0.1] = np.nan
    fragments = np.full((F, U, 3), np.nan)
    for r in range(U):
        a = int(rng.integers(0, F - 5))
        b = int(rng.integers(a + 1, min(F, a + 40) + 1))
        fragments[a:b, r] = (np.nan_to_num(E_all[a:b, r % M])
                             + rng.normal(scale=rng.choice([0.002, 0.01]), size=(b - a, 3)))
    unmerged = np.isfinite(fragments).all(-1) & (rng.random(U) < 0.9)[None]
    return (fragments, unmerged, E_all, np.full(M, 0.012), [f"m{j}" for j in range(M)],
            [f"*{r}" for r in range(U)])


def unmerged_counts(unmerged):
    """``(F + 1, U)`` cumulative counts of ``unmerged (F, U)`` over frames (the
    ``n_unmerged`` of :func:`~mocapflow.stages.skin.merge._rival_fragment`)."""
    return np.concatenate([np.zeros((1, unmerged.shape[1]), np.int32), np.cumsum(unmerged, 0)])


@pytest.mark.parametrize("seed", range(8))
def test_rival_fragment_equals_a_loop_over_rivals(seed):
    fragments, unmerged, E_all, eps1, labels, flabels = rival_case(100 + seed)
    U, M = fragments.shape[1], E_all.shape[1]
    seen = 0
    for u in range(U):
        T = np.flatnonzero(np.isfinite(fragments[:, u]).all(-1))
        m = u % M
        v = {"marker": m, "entry": 0.0, "max": 0.0, "mean": 0.0}
        got = cm._rival_fragment(fragments, unmerged, u, T, v, E_all, eps1, labels, flabels)
        want = rival_loop(fragments, unmerged, u, T, m, E_all, eps1)
        if want is None:
            assert got is v
            continue
        seen += 1
        assert got["conflict"]["fragments"] == [flabels[want[0]]]
        np.testing.assert_allclose(got["conflict"]["mean_mm"],
                                   [round(want[1] * 1000, 2), round(want[2] * 1000, 2)],
                                   atol=0.011)
    assert seen >= 1  # some fragments had a rival


def continue_loop(X, fragments, eps1, assigned, nb, max_gap=cm.MAX_BRIDGE):
    """``continue_breaks``' rule, one fragment end and one marker at a time (the carry
    itself is ``_carry`` on single pairs)."""
    X = X.copy()
    assigned = assigned.copy()
    F, U = fragments.shape[:2]
    M = X.shape[1]
    rig = np.where(nb >= 0, 1.0, 0.0)
    done = []
    while True:
        avail = np.isfinite(X).all(-1)
        vis = np.isfinite(fragments).all(-1)
        picks = {}
        for u in range(U):
            T = np.flatnonzero(vis[:, u])
            if assigned[u] >= 0 or not len(T) or T[-1] - T[0] + 1 != len(T):
                continue
            a, b = int(T[0]), int(T[-1])
            ends = []
            for at, sign in ((a, -1), (b, 1)):
                cands = []
                for m in range(M):
                    if avail[a:b + 1, m].any() or not np.isfinite(eps1[m]):
                        continue
                    end = next((at + sign * k for k in range(1, max_gap + 1)
                                if 0 <= at + sign * k < F and avail[at + sign * k, m]), None)
                    if end is None or np.linalg.norm(X[end, m] - fragments[at, u]) >= \
                            cm.BRIDGE_SCREEN:
                        continue
                    p = cm._carry(X, avail, np.array([end]), np.array([at]), np.array([m]),
                                  nb, rig)[0]
                    d = float(np.linalg.norm(p - fragments[at, u]))
                    cands.append((d if np.isfinite(d) else np.inf, m, p))
                if not cands:
                    continue
                cands.sort(key=lambda c: (c[0], c[1]))
                d, m, p = cands[0]
                second = cands[1][0] if len(cands) > 1 else np.inf
                e1 = eps1[m]
                if not (d < cm.BREAK_JUMP * e1 and second >= max(e1, cm.AMBIGUITY_RATIO * d)):
                    continue
                rivals = [np.linalg.norm(X[at, j] - p) for j in range(M)
                          if j != m and avail[at, j]]
                rivals += [np.linalg.norm(fragments[at, w] - p) for w in range(U)
                           if w != u and assigned[w] < 0 and vis[at, w]]
                rival = min(rivals, default=np.inf)
                if rival >= e1 and rival >= cm.AMBIGUITY_RATIO * d:
                    ends.append((m, d))
            if ends and len({m for m, _ in ends}) == 1:
                picks[u] = (ends[0][0], max(d for _, d in ends))
        n_before = len(done)
        for u, (m, d) in picks.items():
            T = np.flatnonzero(vis[:, u])
            if np.isfinite(X[T, m]).any():
                continue
            X[T, m] = fragments[T, u]
            assigned[u] = m
            done.append((u, m, d))
        if len(done) == n_before:
            return done, X, assigned


@pytest.mark.parametrize("seed", range(4))
def test_continue_breaks_equals_a_loop_on_randomly_cut_grids(seed):
    """A rigidly moving grid, markers cut into pieces with gaps of 0-10 frames, some
    pieces moved off their marker (ghost-like), some left labelled."""
    rng = np.random.default_rng(seed)
    F = 50
    true = moving_grid(F)
    X = true.copy()
    pieces = []
    for j in rng.choice(36, 14, replace=False):
        cut = int(rng.integers(5, 20))
        X[cut:, j] = np.nan
        a = cut + int(rng.integers(0, 11))
        while a < F:
            b = min(F, a + int(rng.integers(3, 15)))
            piece = np.full((F, 3), np.nan)
            piece[a:b] = true[a:b, j] + (rng.normal(scale=0.004, size=3)
                                         if rng.random() < 0.2 else 0.0)
            pieces.append(piece)
            a = b + int(rng.integers(0, 11))
    frags = np.stack(pieces, 1)
    eps1 = np.full(36, 0.5 * GRID)
    eps1[rng.integers(0, 36)] = np.nan  # a marker without tolerance takes nothing
    nb = grid_neighbours(true[0])
    want, X_want, a_want = continue_loop(X, frags, eps1, np.full(frags.shape[1], -1), nb)
    for visible in (None, np.isfinite(frags).all(-1)):
        Xg, assigned = X.copy(), np.full(frags.shape[1], -1)
        got = cm.continue_breaks(Xg, frags, eps1, assigned, nb, visible=visible)
        assert sorted(g[:2] for g in got) == sorted(w[:2] for w in want)
        np.testing.assert_allclose(sorted(g[2] for g in got), sorted(w[2] for w in want),
                                   atol=1e-12)
        np.testing.assert_array_equal(assigned, a_want)
        np.testing.assert_array_equal(Xg, X_want)
    assert len(want) >= 3  # continuity merged pieces
