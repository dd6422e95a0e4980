"""Transition and prior scores: the re-anchored horizon against the paper's unbounded form,
and the batched scores of the structure search against the same scores written plainly."""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.registry import ParamError
from mocapflow.stages.variation.clips import make_clips
from mocapflow.stages.variation.kernel import (
    KERNEL_GRID,
    bandwidth_rows,
    gauss_log_density,
    k_nearest,
    kernel_regression,
)
from mocapflow.stages.variation.learn import LearnError, learn
from mocapflow.stages.variation.scores import (
    prior_node_fit,
    prior_node_fits,
    transition_node_fit,
    transition_node_fits,
)
from mocapflow.stages.variation.training import prior_data, standardization, transition_data


def _ramp_clips(n=4, T=60, seed=0):
    """x: two sine cycles; ramp: normalised time t/T_c (clip lengths 60, 66, 72, 78).

    The ramp's delta std is 0.5 % of its position std, like a phase DOF: a
    re-synthesised ramp that leaves the data runs away in delta units.
    """
    rng = np.random.default_rng(seed)
    out = []
    for c in range(n):
        u = np.arange(T + 6 * c) / (T + 6 * c)
        out.append(np.stack([np.sin(2 * np.pi * 2 * u + rng.uniform(0, 6)), u], axis=1))
    return make_clips(out, ["x", "ramp"], rate=60.0)


@pytest.fixture(scope="module")
def ramp_data():
    c = _ramp_clips()
    st = standardization(c.trajectories)
    return transition_data(c.trajectories, st, cyclic=False, k=8, kernel_width=None,
                           min_std=0.01)


def _frames(td, i, horizon):
    N = td.F.shape[0]
    lp, _ = transition_node_fits(td, i, np.zeros((1, N, N)), horizon=horizon, per_frame=True)
    return lp[0][np.concatenate(td.rows)]


def test_runaway_frames_dominate_the_paper_score_not_the_reanchored_one(ramp_data):
    td = ramp_data
    assert td.ratio[1] < 0.01  # the ramp's deltas are tiny against its positions
    paper = _frames(td, 1, None)
    capped = _frames(td, 1, 5)
    assert len(paper) == len(capped) == 4 * 60 + 36 - 4 * 2
    # measured: paper worst frame -1.9e7, total -1.5e9; re-anchored every 5 frames
    # worst -5.1, median -2.2, total -697
    assert paper.min() < -1e6
    assert paper.min() < 1e3 * capped.sum()  # one paper frame outweighs the whole capped score
    assert capped.min() > -20 and np.median(capped) > -5
    assert capped.min() / capped.sum() < 0.02  # no frame carries more than 2 % of the score
    # the sums are the per-frame densities' sums; the default stays the paper's form
    N = td.F.shape[0]
    s, _ = transition_node_fits(td, 1, np.zeros((1, N, N)), horizon=5)
    assert s[0] == pytest.approx(capped.sum(), rel=1e-12)
    assert transition_node_fit(td, 1, [])[0] == pytest.approx(paper.sum(), rel=1e-12)


def test_reanchored_score_still_prefers_the_true_parent():
    rng = np.random.default_rng(0)
    out = []
    from scipy.ndimage import gaussian_filter1d

    for _ in range(4):
        a = gaussian_filter1d(rng.standard_normal(81), 1) * 2
        b = gaussian_filter1d(rng.standard_normal(80), 1) * 2
        out.append(np.stack([a[1:], a[:-1], b], axis=1))  # x1[t] = x0[t-1]
    c = make_clips(out, ["x0", "x1", "x2"], rate=30.0)
    td = transition_data(c.trajectories, standardization(c.trajectories), cyclic=False, k=10,
                         kernel_width=None, min_std=0.01)
    D = 3
    true = transition_node_fit(td, 1, [D + 0], horizon=10)[0]
    none = transition_node_fit(td, 1, [], horizon=10)[0]
    wrong = transition_node_fit(td, 1, [D + 2], horizon=10)[0]
    assert true > none + 50 and true > wrong + 50


def test_parallel_learn_with_a_horizon_equals_serial():
    c = _ramp_clips()
    seq = learn(c, k=8, restarts=1, horizon=0.1)["model"]
    with ThreadPoolExecutor(2) as pool:
        ctx = Context(mapper=lambda fn, items: list(pool.map(fn, items)), workers=2)
        par = learn(c, k=8, restarts=1, horizon=0.1, ctx=ctx)["model"]
    assert par.transition_parents == seq.transition_parents
    np.testing.assert_array_equal(par.transition_scores, seq.transition_scores)
    assert seq.params["horizon"] == 0.1
    paper = learn(c, k=8, restarts=1)["model"]
    assert paper.params["horizon"] is None
    assert paper.transition_scores.sum() < 1e3 * seq.transition_scores.sum()


@pytest.mark.parametrize("bad", [0, -0.5, float("nan"), float("inf"), True, "1"])
def test_bad_horizon_is_refused(bad, ramp_data):
    # refused by the stage's param check (type, finiteness) or by learn (range)
    with pytest.raises((LearnError, ParamError), match="horizon"):
        learn(_ramp_clips(), k=8, horizon=bad)
    td = ramp_data
    N = td.F.shape[0]
    if not isinstance(bad, str):
        with pytest.raises(ValueError, match="horizon"):
            transition_node_fits(td, 0, np.zeros((1, N, N)), horizon=bad)
    with pytest.raises(ValueError, match="score"):
        transition_node_fits(td, 0, np.zeros((1, N, N)), score="propagated_paper")


# ----------------------------------------------------------------------------- the batched scores
# against the scores written plainly: one parent set at a time, every frame's whole
# distance row, float64 argpartition, one kernel regression per quantity


def _plain_d2(X, cols):
    d2 = np.zeros((len(X), len(X)))
    for c in cols:
        d2 += (X[:, c][:, None] - X[:, c][None, :]) ** 2
    return d2


def _plain_nearest(d2, k):
    idx = np.argpartition(d2, k - 1, axis=-1)[..., :k]
    return np.take_along_axis(d2, idx, axis=-1), idx


def _plain_bandwidth2(d2, y_query, y, k, kw, min_std):
    d2k, idx = _plain_nearest(d2, k)
    dk = d2k.max(axis=-1)
    med = max(float(np.median(dk[np.isfinite(dk)])), 1e-12)
    if kw is not None:
        return kw * kw * med
    ok = np.isfinite(d2k).all(axis=-1)
    ll = [gauss_log_density(y_query[ok], *kernel_regression(
        d2k[ok], y[idx][ok], h2=g * g * med, min_std=min_std)).sum() for g in KERNEL_GRID]
    return KERNEL_GRID[int(np.argmax(ll))] ** 2 * med


def _plain_transition_fit(td, i, parents, score, horizon):
    """Lau §5's LOO score of one transition node, frame by frame of each held-out clip."""
    D, k, r = td.n_dofs, td.k, td.ratio[i]
    pen = np.where(td.valid, 0.0, np.inf)
    a, b = td.F[:, D + i], td.V[:, i]
    other = _plain_d2(td.F, parents) + pen
    sub = bandwidth_rows(len(a))
    self_d2 = (a[:, None] - a) ** 2 + (b[:, None] - b) ** 2
    y = td.Y[:, i]
    h2 = _plain_bandwidth2((other + self_d2)[sub], y[sub], y, k, td.kernel_width, td.min_std)

    def predict(d2_row, z):
        d2k, idx = _plain_nearest(d2_row, k)
        mu, var = kernel_regression(d2k, y[idx], h2=h2, min_std=td.min_std)
        zbar, _ = kernel_regression(d2k, a[idx], h2=h2, min_std=0.0)
        return mu + (td.retention - 1.0) * (z - zbar) / r, var

    if score == "one_step":
        mu, var = predict(other + self_d2, a)
        return gauss_log_density(y, mu, var).sum(), h2
    total = 0.0
    floor = (td.min_std / r) ** 2
    for rows in td.rows:
        zp, zc, vacc = td.F[rows[0], i], a[rows[0]], 0.0
        for t, n in enumerate(rows):
            if horizon is not None and t > 0 and t % horizon == 0:
                zp, zc, vacc = td.F[n, i], a[n], 0.0
            bq = (zc - zp) * td.velocity_weight / r
            mu, var = predict(other[n] + (zc - a) ** 2 + (bq - b) ** 2, zc)
            if horizon is not None:
                vacc = var = var + vacc
                var = var + floor
            total += gauss_log_density((td.Z2[n, i] - zc) / r, mu, var)
            zp, zc = zc, zc + mu * r
    return total, h2


@pytest.fixture(scope="module")
def lagged_data():
    """x1[t] = x0[t-1], x2 independent; 4 clips of 30-45 frames, retention 0.8 (k 10)."""
    from scipy.ndimage import gaussian_filter1d

    rng = np.random.default_rng(4)
    out = []
    for c in range(4):
        a = gaussian_filter1d(rng.standard_normal(31 + 5 * c), 1) * 2
        b = gaussian_filter1d(rng.standard_normal(30 + 5 * c), 1) * 2
        out.append(np.stack([a[1:], a[:-1], b], axis=1))
    c = make_clips(out, ["x0", "x1", "x2"], rate=30.0)
    st = standardization(c.trajectories)
    return {kw: transition_data(c.trajectories, st, cyclic=False, k=10, kernel_width=kw,
                                min_std=0.01, retention=0.8) for kw in (None, 2.0)}, c, st


@pytest.mark.parametrize("score,horizon,kw", [
    ("propagated", None, None), ("propagated", None, 2.0), ("propagated", 4, None),
    ("one_step", None, 2.0)])
def test_batched_transition_scores_equal_the_plain_ones(lagged_data, score, horizon, kw):
    td = lagged_data[0][kw]
    assert td.retention == 0.8
    D = td.n_dofs
    sets = [[], [D + 0], [D + 0, 2], [D + 2], [0, 2, D + 0]]
    for i in (1, 2):
        sc, h2 = transition_node_fits(td, i, np.stack([_plain_d2(td.F, P) for P in sets]),
                                      score=score, horizon=horizon)
        want = [_plain_transition_fit(td, i, P, score, horizon) for P in sets]
        np.testing.assert_allclose(sc, [w[0] for w in want], rtol=1e-9)
        np.testing.assert_allclose(h2, [w[1] for w in want], rtol=1e-12)
        # and the scores tell the parent sets apart (the check could fail)
        assert np.ptp(sc) > 1.0


def test_batched_prior_scores_equal_the_plain_ones(lagged_data):
    _, c, st = lagged_data
    D = 3
    for kw in (None, 2.0):
        pd = prior_data(c.trajectories, st, k=10, kernel_width=kw, min_std=0.01)
        sets = [(), (0,), (2,), (0, 2), (1, 2, 4)]
        cache: dict = {}
        sc, h2 = prior_node_fits(pd, D + 1, sets, pair_d2=cache)
        for P, s, h in zip(sets, sc, h2):
            y = pd.Z[:, D + 1]
            if not P:
                assert h == 0.0 and s == pytest.approx(prior_node_fit(pd, D + 1, ())[0])
                continue
            d2 = np.where(pd.valid, _plain_d2(pd.Z, P), np.inf)
            hh = _plain_bandwidth2(d2[bandwidth_rows(len(y))], y, y, pd.k, kw, 0.01)
            d2k, idx = _plain_nearest(d2, pd.k)
            want = gauss_log_density(y, *kernel_regression(d2k, y[idx], h2=hh,
                                                            min_std=0.01)).sum()
            assert s == pytest.approx(want, rel=1e-9) and h == pytest.approx(hh, rel=1e-12)
        assert sc[1] > sc[2] and np.ptp(sc) > 1.0  # X_1[1] = X_0[0]: the true parent wins
        # the shared cache holds each node's distances and is reused on the next call
        assert set(cache) >= {0, 1, 2, 4}
        again, _ = prior_node_fits(pd, D + 1, sets[::-1], pair_d2=cache)
        np.testing.assert_array_equal(again, sc[::-1])


def test_k_nearest_is_exact_where_float32_rounding_ties():
    rng = np.random.default_rng(0)
    d2 = rng.random((50, 200))
    d2[:, :30] = np.inf  # left-out instances
    got = np.sort(k_nearest(d2, 15), axis=-1)
    want = np.sort(np.argpartition(d2, 14, axis=-1)[:, :15], axis=-1)
    np.testing.assert_array_equal(got, want)
    # 1 and 1 + 1e-12 are one float32: the float64 selection decides (index 3, not 2)
    tie = np.array([[0.1, 0.2, 1.0 + 1e-12, 1.0, 5.0], [np.inf, np.inf, 0.5, np.inf, 7.0]])
    got = np.sort(k_nearest(tie, 3), axis=-1)
    np.testing.assert_array_equal(got[0], [0, 1, 3])
    assert {2, 4} <= set(got[1].tolist())  # the finite ones, then any infinite one
    assert k_nearest(tie, 5).shape == (2, 5)  # k = N: all
