"""Motion metrics: seams, feet, GANimator patch metrics (against brute force)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from mocapflow.stages.metrics import quality as M
from mocapflow.stages.motion.contacts import contact_thresholds, foot_contacts, toe_indices
from mocapflow.stages.motion.rotations import quat_multiply, yaw_quaternion
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.motion.simulate.skeleton import procedural_skeleton


def _cubic(n: int, a: float, rate: float) -> np.ndarray:
    t = np.arange(n) / rate
    p = np.zeros((n, 2, 3))
    p[:, 0, 0] = a * t**3
    p[:, 1, 1] = 0.5 * a * t**3
    return p


def test_jerk_and_acceleration_of_polynomials():
    rate = 30.0
    p = _cubic(40, 2.0, rate)
    j = M.jerk_per_frame(p, rate)
    assert np.isnan(j[0]) and np.isnan(j[-1]) and np.isnan(j[-2])
    np.testing.assert_allclose(j[1:-2], (12.0 + 6.0) / 2, rtol=1e-6)  # mean of |6a| and |3a|
    q = np.zeros((20, 1, 3))
    q[:, 0, 2] = 0.5 * 4.0 * (np.arange(20) / rate) ** 2  # constant acceleration 4 m/s²
    np.testing.assert_allclose(M.acceleration_per_frame(q, rate)[1:-1], 4.0, rtol=1e-9)
    assert M.acceleration_p99(q, rate) == pytest.approx(4.0)


def test_jerk_p99_mask_and_trim():
    rate = 30.0
    p = _cubic(60, 1.0, rate)
    p[30:, :, 0] += 0.05  # a step: one seam between frames 29 and 30
    overall = M.jerk_p99(p, rate)
    mask = M.seam_mask(60, np.array([30]), radius=5)
    assert mask[24:36].all() and not mask[:24].any() and not mask[36:].any()
    near = M.jerk_p99(p, rate, mask=mask)
    far = M.jerk_p99(p, rate, mask=~mask)
    assert near > 100 * far  # the step dominates near the seam only
    assert far == pytest.approx((6.0 + 3.0) / 2, rel=1e-6)
    assert overall >= far
    assert np.isfinite(M.jerk_p99(p[:5], rate))  # frame 2 survives the trim
    assert np.isnan(M.jerk_p99(p[:4], rate))  # nothing left after trimming


def test_seams_and_verbatim_runs():
    src = np.array([4, 5, 6, 20, 21, 22, 23, 5, 6, 3])
    np.testing.assert_array_equal(M.seams_from_source(src), [3, 7, 9])
    assert M.longest_verbatim_run(src) == 4
    loop = np.array([7, 8, 9, 5, 6, 10])
    np.testing.assert_array_equal(M.seams_from_source(loop, cyclic=True), [0, 3, 5])
    np.testing.assert_array_equal(M.seams_from_source(loop[:5], cyclic=True), [3])  # 6 -> 7
    np.testing.assert_array_equal(M.seams_from_source(np.array([0, 1, 2, 3]), cyclic=True), [0])
    assert M.seams_from_source(np.array([5, 6, 7, 4]), cyclic=True).tolist() == [3]
    assert M.longest_verbatim_run(np.arange(12)) == 12


def test_foot_skate_counts_only_slow_frames_near_the_floor():
    rate = 30.0
    n = 90
    pos = np.zeros((n, 3, 3))
    pos[:, 0, 1] = 1.0  # root
    # toe 1 slides at 0.2 m/s on the floor for 60 frames, then lifts and runs at 3 m/s
    pos[:60, 1, 0] = 0.2 * np.arange(60) / rate
    pos[60:, 1, 0] = pos[59, 1, 0] + 3.0 * np.arange(1, 31) / rate
    pos[60:, 1, 1] = 0.3
    # toe 2 planted
    pos[:, 2, 2] = 0.4
    contacts = foot_contacts(pos, [1, 2], rate, height_threshold=0.05, speed_threshold=0.5)
    assert contacts[:59, 0].all() and not contacts[61:, 0].any() and contacts[:, 1].all()
    skate = M.foot_skate(pos, [1, 2], rate, height_threshold=0.05, speed_threshold=0.5)
    expect = (0.2 * contacts[:, 0].sum() + 0.0 * n) / (contacts[:, 0].sum() + n)
    assert skate == pytest.approx(expect, rel=1e-3)
    assert M.foot_skate(pos, [1], rate, height_threshold=-1.0, speed_threshold=0.5) != (
        M.foot_skate(pos, [1], rate, height_threshold=-1.0, speed_threshold=0.5)
    )  # NaN: no contact at all
    h, s = contact_thresholds(pos, [2], rate)
    assert h == pytest.approx(0.05) and s == pytest.approx(0.5)


def test_toe_indices():
    sk = procedural_skeleton()
    names = [sk.names[i] for i in toe_indices(sk)]
    assert names and all("toe" in n.lower() for n in names)
    bare = sk.__class__(["root", "a"], [-1, 0], np.zeros((2, 3)), [[], []])
    with pytest.raises(ValueError, match="toe or foot"):
        toe_indices(bare)


# --------------------------------------------------------------------------- patch metrics


def _brute_window(c: np.ndarray, T: int) -> np.ndarray:
    """GANimator-style ``W[i, k] = sum_t c[i+t, k+t]`` by explicit loops."""
    L, K = c.shape
    W = np.zeros((L - T + 1, K - T + 1))
    for i in range(L - T + 1):
        for k in range(K - T + 1):
            W[i, k] = sum(c[i + t, k + t] for t in range(T))
    return W


def _brute_global(c: np.ndarray, T: int) -> float:
    L, K = c.shape
    best = np.full(L + 1, np.inf)
    best[0] = 0
    for e in range(T, L + 1):
        for s in range(0, e - T + 1):  # every length >= T (no 2T-1 shortcut)
            n = e - s
            if n > K or not np.isfinite(best[s]):
                continue
            seg = min(sum(c[s + t, k + t] for t in range(n)) for k in range(K - n + 1))
            best[e] = min(best[e], best[s] + seg)
    return best[L] / L


@pytest.fixture(scope="module")
def feats():
    rng = np.random.default_rng(4)
    f_in = rng.normal(size=(40, 6))
    f_out = np.vstack([f_in[5:25], rng.normal(size=(7, 6)), f_in[10:40] + 0.05])
    return f_out, f_in


def test_diagonal_cumsum_matches_brute_force(feats):
    f_out, f_in = feats
    c = cdist(f_out, f_in)
    C = M.diagonal_cumsum(c)
    for T in (1, 5, 15):
        np.testing.assert_allclose(C[T:, T:] - C[:-T, :-T], _brute_window(c, T), atol=1e-9)


def test_local_diversity_and_coverage_match_brute_force(feats):
    f_out, f_in = feats
    c = cdist(f_out, f_in)
    W = _brute_window(c, 15)[:-1]  # GANimator drops the last window
    assert M.local_diversity(f_out, f_in) == pytest.approx(np.mean(W.min(1) / 15))
    Wc = _brute_window(c.T, 30)
    assert M.coverage(f_out, f_in) == pytest.approx(np.mean(Wc.min(1) / 30 < 2.0))
    assert M.coverage(f_out, f_in, threshold=1e9) == 1.0


def test_global_diversity_matches_brute_force_with_any_segment_length():
    rng = np.random.default_rng(5)
    f_in = rng.normal(size=(26, 4))
    f_out = np.vstack([f_in[3:14], rng.normal(size=(4, 4)), f_in[2:20]]) + 0.01
    T = 8
    got = M.global_diversity(f_out, f_in, T=T)
    assert got == pytest.approx(_brute_global(cdist(f_out, f_in), T), rel=1e-9)


def test_copy_scores_zero_and_noise_scores_high():
    walk = procedural_walk(90, rate=30.0, seed=1)
    f = M.rotation_features(walk)
    assert f.shape == (90, 6 * walk.skeleton.n_joints)
    copy = np.vstack([f[40:], f[:40]])
    pm = M.patch_metrics(copy, f)
    assert pm["global_diversity"] == pytest.approx(0.0, abs=1e-12)
    assert pm["coverage"] == 1.0
    assert pm["local_diversity"] < 0.2
    noise = f + np.random.default_rng(0).normal(0, 0.5, f.shape)
    assert M.local_diversity(noise, f) > 10 * M.local_diversity(copy, f)
    with pytest.raises(ValueError, match="at least 30 frames"):
        M.coverage(f[:20], f)


def test_heading_free_features_ignore_the_facing():
    walk = procedural_walk(40, rate=30.0, seed=1)
    rot = walk.rotations.copy()
    rot[:, 0] = quat_multiply(yaw_quaternion(np.full(40, 2.0)), rot[:, 0])
    turned = walk.replace(rotations=rot)
    a = M.rotation_features(walk, heading_free=True)
    b = M.rotation_features(turned, heading_free=True)
    np.testing.assert_allclose(a, b, atol=1e-9)
    assert np.abs(M.rotation_features(walk) - M.rotation_features(turned)).max() > 0.5
