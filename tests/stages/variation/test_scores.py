"""Propagated transition score: re-anchored horizon against the paper's unbounded form."""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.registry import ParamError
from mocapflow.stages.variation.clips import make_clips
from mocapflow.stages.variation.learn import LearnError, learn
from mocapflow.stages.variation.scores import transition_node_fit, transition_node_fits
from mocapflow.stages.variation.training import standardization, transition_data


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
