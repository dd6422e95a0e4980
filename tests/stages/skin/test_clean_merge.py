"""Fast paths of the merge step against straightforward reference implementations.

* ``absolute_orientation_batch`` (closed-form eigenvector, cheap degeneracy test)
  against a per-set textbook Horn (``np.linalg.eigh`` of the 4×4 matrix, exact
  eigenvalues for the collinearity test), on random sets with NaN rows,
  collinear, coincident, planar, mirrored and half-turn sets;
* the fragment judge with its per-round index against the dense judge (every
  candidate's distances over the whole fragment);
* ``merge_fragments`` with and without the index on a small simulated capture;
* judging against hole-filled estimates (``predictions``) on a 6×6 grid with
  ε₁ = 20 mm: a fragment 4 mm from a wrong marker's estimate while the true,
  adjacent marker's estimate is 18–25 mm off is not merged (the plain ratio-3
  ambiguity test merges it), 50 mm off it is merged; a mean distance of
  14 mm (0.7 ε₁) is rejected (> 0.6 ε₁);
* a missing marker with no prediction 40 mm from the chosen one (same grid): a
  fragment more than a quarter of that from the chosen marker's prediction is
  ambiguous (the rule before merged it), closer or with the other marker's
  prediction 40 mm off it merges.
"""

from __future__ import annotations

import numpy as np
import pytest

import mocapflow.stages.skin.merge as cm
from mocapflow.stages.motion import absolute_orientation as kin
from mocapflow.stages.motion.absolute_orientation import (
    DegenerateFitError,
    absolute_orientation,
    absolute_orientation_batch,
)
from mocapflow.stages.motion.rotations import quat_from_rotvec, quat_to_matrix
from mocapflow.stages.skin.surface import build_marker_surface
from tests.stages.conftest import simulated_capture

REL_TOL = 1e-7


# --------------------------------------------------------------------------- Horn


def horn_reference(source, target, weights, rel_tol=REL_TOL):
    """Textbook Horn, one set at a time: eigh of the 4×4 matrix, exact spread test."""
    B = len(source)
    R = np.full((B, 3, 3), np.nan)
    t = np.full((B, 3), np.nan)
    for b in range(B):
        ok = (np.isfinite(source[b]).all(1) & np.isfinite(target[b]).all(1)
              & np.isfinite(weights[b]) & (weights[b] > 0))
        if ok.sum() < 3:
            continue
        w = weights[b, ok] / weights[b, ok].sum()
        s, x = source[b, ok], target[b, ok]
        cs, cx = w @ s, w @ x
        s0, x0 = s - cs, x - cx
        ls = np.linalg.eigvalsh((w[:, None] * s0).T @ s0)
        lx = np.linalg.eigvalsh((w[:, None] * x0).T @ x0)
        if not (ls[1] > rel_tol**2 * ls[2] and lx[1] > rel_tol**2 * lx[2] and ls[2] > 0):
            continue
        S = (w[:, None] * s0).T @ x0
        (Sxx, Sxy, Sxz), (Syx, Syy, Syz), (Szx, Szy, Szz) = S
        N = np.array([
            [Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx],
            [Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz],
            [Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy],
            [Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz],
        ])
        q = np.linalg.eigh(N)[1][:, -1]
        R[b] = quat_to_matrix(q)
        t[b] = cx - R[b] @ cs
    return R, t


def random_sets(B, N, seed):
    """Rings of N points (5 cm) 1 m from the origin, rotated, noisy, with special cases."""
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(B, N, 3)) * 0.05 + rng.normal(size=(B, 1, 3))
    R0 = quat_to_matrix(quat_from_rotvec(rng.normal(size=(B, 3)) * 1.5))
    tgt = (np.einsum("bij,bnj->bni", R0, src) + rng.normal(size=(B, 1, 3))
           + rng.normal(size=(B, N, 3)) * 0.002)
    w = rng.uniform(0.05, 1.0, (B, N))
    w[rng.uniform(size=(B, N)) < 0.2] = np.nan
    w[rng.uniform(size=(B, N)) < 0.05] = 0.0
    tgt[rng.uniform(size=(B, N)) < 0.1] = np.nan
    src[rng.uniform(size=(B, N)) < 0.02, 1] = np.nan
    k = B // 10
    line = src[:k, :1] + rng.normal(size=(k, 1, 3)) * rng.normal(size=(k, N, 1)) * 0.05
    src[:k] = line  # collinear
    src[k:k + 5] = src[k:k + 5, :1]  # coincident
    src[2 * k:3 * k, :, 2] = 0.3  # planar
    tgt[3 * k:4 * k] *= np.array([1.0, 1.0, -1.0])  # mirrored: best rotation is poor
    tgt[4 * k:5 * k] = src[4 * k:5 * k] * np.array([-1.0, -1.0, 1.0])  # half turn
    tgt[5 * k:6 * k] = src[5 * k:6 * k] + 1e-12 * rng.normal(size=(k, N, 3))  # identity
    # off a line by 1e-10 (degenerate) and 1e-2 (not): clear of the 1e-7 threshold,
    # where rounding decides, and of ill-conditioned rotations about the line
    near = src[6 * k:7 * k, :1] + rng.normal(size=(k, 1, 3)) * rng.normal(size=(k, N, 1))
    off = np.where(np.arange(k) % 2 == 0, 1e-10, 1e-2)[:, None, None]
    src[6 * k:7 * k] = near + rng.normal(size=(k, N, 3)) * off
    w[7 * k:7 * k + 5, 3:] = np.nan  # exactly 3 points
    w[7 * k + 5:7 * k + 10, 2:] = np.nan  # 2 points
    return src, tgt, w


@pytest.mark.parametrize("B,seed", [(40, 0), (3000, 1), (3000, 2)])
def test_batch_horn_matches_the_textbook_method(B, seed):
    """Closed form (LAPACK for nearly repeated eigenvalues) against the per-set reference."""
    src, tgt, w = random_sets(B, 8, seed)
    R, t = absolute_orientation_batch(src, tgt, weights=w)
    Rr, tr = horn_reference(src, tgt, w)
    # the same sets are degenerate (NaN), exactly
    np.testing.assert_array_equal(np.isnan(R), np.isnan(Rr))
    np.testing.assert_array_equal(np.isnan(t), np.isnan(tr))
    good = np.isfinite(Rr).all((1, 2))
    assert good.sum() > 0.3 * B and (~good).sum() > 0.1 * B  # both kinds present
    np.testing.assert_allclose(R[good], Rr[good], atol=1e-9)
    np.testing.assert_allclose(t[good], tr[good], atol=1e-9)
    # proper rotations, never reflections
    np.testing.assert_allclose(np.linalg.det(R[good]), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("bji,bjk->bik", R[good], R[good]),
                               np.broadcast_to(np.eye(3), R[good].shape), atol=1e-12)
    # each set's result does not depend on the batch it is solved in (parallel chunks)
    part = slice(B // 3, B // 3 + 7)
    Rp, tp = absolute_orientation_batch(src[part], tgt[part], weights=w[part])
    np.testing.assert_array_equal(Rp, R[part])
    np.testing.assert_array_equal(tp, t[part])


def test_batch_horn_exact_on_noise_free_rotations():
    rng = np.random.default_rng(3)
    B = 500
    src = rng.normal(size=(B, 6, 3)) * 0.05
    R0 = quat_to_matrix(quat_from_rotvec(rng.normal(size=(B, 3)) * 2.0))
    t0 = rng.normal(size=(B, 3))
    R, t = absolute_orientation_batch(src, np.einsum("bij,bnj->bni", R0, src) + t0[:, None])
    np.testing.assert_allclose(R, R0, atol=1e-12)
    np.testing.assert_allclose(t, t0, atol=1e-12)


def test_spread_test_matches_exact_eigenvalues():
    """The cheap sufficient test never decides differently from the eigenvalues."""
    rng = np.random.default_rng(4)
    B = 4000
    A = rng.normal(size=(B, 3, 3))
    # spreads from isotropic to exactly collinear, around the threshold too
    A[:, :, 1] *= 10.0 ** rng.uniform(-12, 0, B)[:, None]
    A[:, :, 2] *= 10.0 ** rng.uniform(-12, 0, B)[:, None]
    A[:50, :, 1:] = 0.0
    C = np.einsum("bij,bkj->bik", A, A)
    for tol2 in (REL_TOL**2, 1e-6, 0.5):
        lam = np.linalg.eigvalsh(C)
        exact = (lam[:, 1] > tol2 * lam[:, 2]) & (lam[:, 2] > 0)
        np.testing.assert_array_equal(kin._spread_ok(C, tol2), exact)
        assert 0 < exact.sum() < B


def test_top_eigenvector_matches_eigh_and_falls_back_when_repeated():
    rng = np.random.default_rng(5)
    B = 2000
    M = rng.normal(size=(B, 3, 3))
    M[:200] = np.eye(3) * np.array([1.0, -1.0, -1.0])  # top eigenvalue of N repeated
    M[200:400] = np.diag([1.0, 1e-7, -1e-7])  # nearly repeated
    N = kin._horn_matrix(M)
    bound = 0.5 * np.einsum("bij,bij->b", M, M) + 3.0  # any upper bound of λmax
    bound = np.maximum(bound, np.linalg.svd(M, compute_uv=False).sum(1))
    q = kin._top_eigenvector(N, bound)
    lam, V = np.linalg.eigh(N)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-14)
    # an eigenvector of the largest eigenvalue (any, when repeated)
    np.testing.assert_allclose(np.einsum("bi,bij,bj->b", q, N, q), lam[:, -1], atol=1e-12)
    simple = lam[:, -1] - lam[:, -2] > 1e-3
    dots = np.abs(np.einsum("bi,bi->b", q[simple], V[simple, :, -1]))
    np.testing.assert_allclose(dots, 1.0, atol=1e-12)


def test_single_fit_still_raises_on_degenerate_sets():
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(DegenerateFitError, match="collinear"):
        absolute_orientation(line, line + 1.0)
    with pytest.raises(DegenerateFitError, match="got 2 usable"):
        absolute_orientation(np.eye(3), np.eye(3), weights=np.array([1.0, 1.0, np.nan]))


# --------------------------------------------------------------------------- judging fragments


def judge_case(seed, F=60, M=40):
    """Predictions (with holes) of markers 2-6 cm apart, two pairs of them close."""
    rng = np.random.default_rng(seed)
    base = np.stack([np.arange(M) * 0.04, np.zeros(M), np.zeros(M)], 1)
    base[11] = base[10] + [0.0, 0.004, 0.0]  # within the ambiguity ratio of 10
    base[21] = base[20] + [0.0, 0.03, 0.0]
    E = base[None] + rng.normal(size=(F, M, 3)) * 0.001
    E[rng.uniform(size=(F, M)) < 0.25] = np.nan
    E[:, :3] = np.nan  # never predicted
    E[48:56] = np.nan  # no predictions at all
    avail = rng.uniform(size=(F, M)) < 0.15
    avail[:, [10, 11, 20, 21]] &= rng.uniform(size=(F, 4)) < 0.1
    eps1 = np.full(M, 0.02)
    eps1[5] = np.nan
    eps2 = 1.2 * eps1
    return rng, E, avail, eps1, eps2


def judge_setup(seed):
    """:func:`judge_case` with what judging needs beside it: ``E_all`` (every prediction,
    random where ``E`` has none), marker labels and the :class:`PredictionIndex`."""
    rng, E, avail, eps1, eps2 = judge_case(seed)
    E_all = np.where(np.isfinite(E), E, rng.normal(size=E.shape))
    labels = [f"M{m}" for m in range(E.shape[1])]
    index = cm.PredictionIndex(avail, np.isfinite(E).all(-1))
    return rng, E, E_all, avail, eps1, eps2, labels, index


@pytest.mark.parametrize("seed", range(4))
def test_indexed_judge_equals_dense_judge(seed):
    rng, E, E_all, avail, eps1, eps2, labels, index = judge_setup(seed)
    F, M, _ = E.shape
    kinds = set()
    for _ in range(300):
        a = int(rng.integers(0, F - 1))
        T = np.arange(a, min(F, a + int(rng.integers(1, 30))))
        m = int(rng.choice([int(rng.integers(0, M)), 10, 11, 20, 21]))
        noise = rng.choice([0.0005, 0.005, 0.015, 0.2])
        frag = np.nan_to_num(E_all[T, m], nan=0.5) + rng.normal(size=(len(T), 3)) * noise
        frag[:, 1] += rng.choice([0.0, 0.002]) * np.arange(len(T))  # drifts out of the tube
        free = ~avail[T].any(0) & np.isfinite(eps1)
        np.testing.assert_array_equal(index.free(T[0], T[-1]) & np.isfinite(eps1), free)
        dense = cm._judge_fragment(frag, T, free, E, E_all, eps1, eps2, labels)
        fast = cm._judge_fragment(frag, T, free, E, E_all, eps1, eps2, labels, index)
        assert fast == dense
        kinds.add("marker" if "marker" in dense else dense["reason"].split(" ")[0].rstrip(":"))
    # merges, entry / tube / mean rejections, ambiguities, "no prediction" all seen
    assert {"marker", "entry", "ambiguous", "leaves", "no"} <= kinds, kinds


def test_judge_with_gapped_frames_uses_the_dense_path():
    rng, E, avail, eps1, eps2 = judge_case(7)
    T = np.array([3, 4, 9, 10])  # not a run: the index cannot be used
    index = cm.PredictionIndex(avail, np.isfinite(E).all(-1))
    labels = [f"M{m}" for m in range(E.shape[1])]
    free = ~avail[T].any(0) & np.isfinite(eps1)
    m = int(np.flatnonzero(free & np.isfinite(E[T]).all(-1).all(0))[0])
    frag = E[T, m] + 1e-4
    v = cm._judge_fragment(frag, T, free, E, E, eps1, eps2, labels, index)
    assert v == cm._judge_fragment(frag, T, free, E, E, eps1, eps2, labels)
    assert v["marker"] == m or "ambiguous" in v.get("reason", "")


def test_prediction_index_counts_and_next_prediction():
    rng = np.random.default_rng(8)
    pred = rng.uniform(size=(30, 5)) < 0.3
    idx = cm.PredictionIndex(np.zeros_like(pred), pred)
    for a in range(30):
        for m in range(5):
            later = np.flatnonzero(pred[a:, m])
            assert idx.next_predicted[a, m] == (a + later[0] if len(later) else 30)
            assert idx.n_predicted[30, m] - idx.n_predicted[a, m] == pred[a:, m].sum()


# --------------------------------------------------------------------------- whole merge


def test_merge_with_index_equals_dense_merge(monkeypatch):
    sim = simulated_capture(n_markers=80, n_frames=120, motion="walk", rng=1,
                                 body_vertices=1000)
    m = sim.markers
    ref = np.nanmedian(m.positions, axis=0)
    surf = build_marker_surface(ref, positions=m.positions, labels=m.labels)
    fast = cm.merge_fragments(m.positions, m.fragments, surf, depths=(1,))
    monkeypatch.setattr(cm, "_is_run", lambda T: False)
    dense = cm.merge_fragments(m.positions, m.fragments, surf, depths=(1,))
    np.testing.assert_array_equal(fast[0], dense[0])
    np.testing.assert_array_equal(fast[1], dense[1])
    assert fast[2] == dense[2]
    assert (fast[1] >= 0).sum() >= 10  # merges happened
    truth = sim.truth["fragment_marker"]
    merged = fast[1] >= 0
    np.testing.assert_array_equal(fast[1][merged], truth[merged])  # no wrong merge


# --------------------------------------------------------------------------- hole-filled estimates


def grid_case(offset_true, offset_wrong=0.004):
    """A 6×6 marker grid (40 mm); markers 14 and 15 missing in frames 5..12.

    The fragment is marker 15's true trajectory there (it continues marker 15 across
    the gap: the tests of the prediction rules turn continuity off, ``max_break=0``).
    Hole-filled estimates:
    marker 14's lies ``offset_wrong`` from the fragment; marker 15's (trusted
    only as a competitor) ``offset_true`` from it.
    """
    F, n = 20, 6
    gx, gy = np.meshgrid(np.arange(n) * 0.04, np.arange(n) * 0.04)
    ref = np.stack([gx.ravel(), gy.ravel(), 0.01 * np.sin(gx.ravel() * 20)], 1)
    X = np.repeat(ref[None], F, 0) + np.linspace(0, 0.1, F)[:, None, None]
    surf = build_marker_surface(ref, positions=X)
    T = np.arange(5, 13)
    frags = np.full((F, 1, 3), np.nan)
    frags[T, 0] = X[T, 15]
    X[T, 14] = X[T, 15] = np.nan
    direct = np.full_like(X, np.nan)
    direct[T, 14] = frags[T, 0] + [offset_wrong, 0, 0]
    competitors = direct.copy()
    competitors[T, 15] = frags[T, 0] + [0, offset_true, 0]
    return X, frags, surf, direct, competitors


def test_grid_case_geometry():
    X, frags, surf, direct, comp = grid_case(0.018)
    dbar = np.fmin(surf.mean_distance, cm.nearest_marker_distance(surf.reference))
    assert dbar[14] == pytest.approx(0.04, rel=0.05)  # ε₁ = 20 mm
    assert cm.NEAR_RADIUS * surf.mean_distance[14] > 0.04  # 15 is near 14


@pytest.mark.parametrize("offset_true", [0.018, 0.022, 0.025])
def test_pca_merge_with_a_close_marker_far_off_its_estimate_is_ambiguous(offset_true):
    """The true marker's estimate (a competitor only) is 4.5–6.25× farther than the
    wrong one's: the plain ambiguity ratio (3) merges into the wrong marker, the
    rule for hole-filled estimates (ratio 6.5 for markers within one d̄) does not."""
    X, frags, surf, direct, comp = grid_case(offset_true)
    plain = cm.merge_fragments(X, frags, surf, predictions=direct, competitors=comp,
                               max_break=0, mean_tolerance=1.0,
                               near_ratio=cm.AMBIGUITY_RATIO)
    assert plain[1][0] == 14  # the wrong merge the rule prevents
    _, assigned, rep = cm.merge_fragments(X, frags, surf, predictions=direct,
                                          competitors=comp, max_break=0)
    assert assigned[0] == -1
    assert rep["rejections"][0]["reason"].startswith("ambiguous: M")
    assert rep["conflicts"][0]["labels"] == [surf.labels[14], surf.labels[15]]


def test_pca_merge_without_close_rival_still_merges():
    X, frags, surf, direct, comp = grid_case(0.05)  # 12.5× farther: not a rival
    _, assigned, rep = cm.merge_fragments(X, frags, surf, predictions=direct,
                                          competitors=comp, max_break=0)
    assert assigned[0] == 14
    assert rep["merges"][0]["mean_mm"] == pytest.approx(4.0, abs=1e-6)


def test_pca_merge_needs_a_tighter_mean_distance():
    X, frags, surf, direct, comp = grid_case(0.2, offset_wrong=0.014)  # 0.7 ε₁
    rigid_rule = cm.merge_fragments(X, frags, surf, predictions=direct, competitors=comp,
                                    max_break=0, mean_tolerance=1.0)
    assert rigid_rule[1][0] == 14
    _, assigned, rep = cm.merge_fragments(X, frags, surf, predictions=direct,
                                          competitors=comp, max_break=0)
    assert assigned[0] == -1
    assert rep["rejections"][0]["reason"].startswith("mean distance 14.0 mm")


# --------------------------------------------------------------------------- rival fragments


def fold_case(offset_rival, rival_frames=8):
    """The 6×6 grid of :func:`grid_case`, markers 14 and 15 missing in frames 5..12,
    where they come within 15 mm of each other (a skin fold, x axis).

    Fragment 0 is marker 15 there, fragment 1 another trajectory ``offset_rival``
    (x) from marker 14's prediction in the first ``rival_frames`` of them; marker
    14's prediction lies 6 mm from
    fragment 0 (off towards marker 15), marker 15's 30 mm from it (one round of
    given predictions judged by the rigid rounds' rules: ``mean_tolerance=1``,
    plain ambiguity ratio, no continuity).
    """
    X, _, surf, _, _ = grid_case(0.05)
    T = np.arange(5, 13)
    p14 = np.repeat(surf.reference[14][None], len(T), 0) + np.linspace(0, 0.1, 20)[T, None]
    frags = np.full((20, 2, 3), np.nan)
    frags[T, 0] = p14 + [0.015, 0, 0]
    pred = np.full_like(X, np.nan)
    pred[T, 14] = p14 + [0.009, 0, 0]
    pred[T, 15] = frags[T, 0] + [0, 0.03, 0]
    R = T[:rival_frames]
    frags[R, 1] = pred[R, 14] + [-offset_rival, 0, 0]
    return cm.merge_fragments(X, frags, surf, predictions=pred, max_break=0,
                              mean_tolerance=1.0, near_ratio=cm.AMBIGUITY_RATIO)


def test_fragment_with_a_rival_fragment_at_the_prediction_is_ambiguous(monkeypatch):
    """Range-of-motion capture, labels stripped (seed 1): a 4-frame fragment of one
    marker merged 10.5 mm from its neighbour's prediction while the neighbour's own
    fragment lay 19.9 mm from it in the same frames (< ε₁, < 3×)."""
    _, assigned, rep = fold_case(0.009)  # fragment 1 is marker 14, 9 mm off (< 3 × 6)
    assert assigned.tolist() == [-1, -1]
    reasons = sorted(r["reason"] for r in rep["rejections"])
    assert reasons[0].startswith("ambiguous: fragment *1 in the same frames at 6.0 mm")
    assert reasons[1].startswith("ambiguous: fragment *2 in the same frames at 9.0 mm")
    assert rep["conflicts"][0]["fragments"] in (["*1"], ["*2"])
    # the rule judged one fragment at a time (before this check): the wrong merge
    monkeypatch.setattr(cm, "_rival_fragment", lambda *a, **k: a[4])
    assert fold_case(0.009)[1][0] == 14


@pytest.mark.parametrize("offset_rival", [0.019, 0.025])
def test_rival_fragment_clearly_farther_or_beyond_eps1_is_no_rival(offset_rival):
    """19 mm is > 3 × 6 mm (below ε₁ = 20 mm); 25 mm is beyond ε₁: fragment 0 merges."""
    _, assigned, rep = fold_case(offset_rival)
    assert assigned[0] == 14
    assert rep["merges"][0]["mean_mm"] == pytest.approx(6.0, abs=1e-6)


def test_rival_fragment_seen_in_under_half_the_frames_is_no_rival():
    """Seen in 3 of the 8 frames (a neighbour's short fragment crossing a long one)."""
    assert fold_case(0.009, rival_frames=3)[1][0] == 14
    assert fold_case(0.009, rival_frames=4)[1].tolist() == [-1, -1]


# ------------------------------------------------------------------ markers without a prediction


def blind_case(offset, rival_prediction=None):
    """The 6×6 grid of :func:`grid_case` (40 mm, ε₁ = 20 mm), markers 14 and 15 missing
    in frames 5..12; the fragment is marker 15 there.  Marker 14's prediction lies
    ``offset`` (y) from it; marker 15 has no prediction (``rival_prediction``: one
    that far (y) from the fragment instead).  One round of given predictions judged
    by the rigid rounds' rules, no continuity.
    """
    X, frags, surf, _, _ = grid_case(0.05)
    T = np.arange(5, 13)
    pred = np.full_like(X, np.nan)
    pred[T, 14] = frags[T, 0] + [0, offset, 0]
    if rival_prediction is not None:
        pred[T, 15] = frags[T, 0] + [0, rival_prediction, 0]
    return cm.merge_fragments(X, frags, surf, predictions=pred, max_break=0,
                              mean_tolerance=1.0, near_ratio=cm.AMBIGUITY_RATIO)


@pytest.mark.parametrize("offset", [0.0105, 0.012, 0.018])
def test_merge_beside_a_missing_marker_without_prediction_is_ambiguous(offset, monkeypatch):
    """Real PiG calibration, cut into pieces: RFHD's fragment went to RBHD 46 mm
    (0.75 ε₁) from its prediction while RFHD, 124 mm away, was missing with no
    prediction.  Here marker 15, 40.1 mm from 14, is the fragment; 14's prediction at
    10.5-18 mm: had the fragment been 14, 15 would sit 40.1 mm from it, so 14's
    prediction would be off by 29.6-22.1 mm, < 3x the offset."""
    _, assigned, rep = blind_case(offset)
    assert assigned[0] == -1
    why = rep["rejections"][0]["reason"]
    assert why.startswith(f"ambiguous: M014 at {offset * 1000:.1f} mm, M015 (40.1 mm from it"), why
    assert rep["conflicts"][0]["labels"] == ["M014", "M015"]
    # the rule judged the predicted markers only (before this check): the wrong merge
    monkeypatch.setattr(cm, "_blind_rival", lambda *a, **k: a[2])
    assert blind_case(offset)[1][0] == 14


@pytest.mark.parametrize("offset, rival_prediction", [(0.0095, None), (0.005, None),
                                                      (0.012, 0.04)])
def test_merge_clear_of_markers_without_prediction_still_merges(offset, rival_prediction):
    """Within D / 4 = 10.03 mm the marker without prediction cannot be it (0.5 ε₁, the
    bound for the nearest marker); with a prediction 40 mm off (> 3 x 12 mm) it is no
    rival either."""
    _, assigned, rep = blind_case(offset, rival_prediction)
    assert assigned[0] == 14
    assert rep["merges"][0]["mean_mm"] == pytest.approx(offset * 1000, abs=1e-6)
