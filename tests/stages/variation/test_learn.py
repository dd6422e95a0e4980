"""Variation DBN learning: kernel regression, scores, structure search, model entry, edge cases."""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d

from mocapflow.pipeline import Context
from mocapflow.pipeline.codecs import decode, digest_encoded, encode
from mocapflow.stages.variation.clips import make_clips
from mocapflow.stages.variation.kernel import kernel_regression
from mocapflow.stages.variation.learn import LearnError, learn
from mocapflow.stages.variation.model import VariationModel
from mocapflow.stages.variation.scores import prior_node_score, transition_node_fit
from mocapflow.stages.variation.search import DAG
from mocapflow.stages.variation.similar import heldout_log_likelihood
from mocapflow.stages.variation.training import prior_data, standardization, transition_data
from tests.stages.variation.conftest import variants


def _lagged(n_clips=4, T=80, seed=0):
    """x0: smooth noise; x1[t] = x0[t-1] (needs x0 as parent); x2: independent smooth noise."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_clips):
        a = gaussian_filter1d(rng.standard_normal(T + 1), 1) * 2
        b = gaussian_filter1d(rng.standard_normal(T), 1) * 2
        out.append(np.stack([a[1:], a[:-1], b], axis=1))
    return make_clips(out, ["x0", "x1", "x2"], rate=30.0)


def _cycles(n=4, T=48, D=3, seed=0):
    rng = np.random.default_rng(seed)
    ph = np.linspace(0, np.pi, D, endpoint=False)
    out = []
    for _ in range(n):
        Tc = T + int(rng.integers(-4, 5))
        u = np.arange(Tc) / Tc
        s = u + 0.1 * np.sin(2 * np.pi * u + rng.uniform(0, 6)) / (2 * np.pi)
        out.append((1 + 0.1 * rng.standard_normal(D)) * np.sin(2 * np.pi * s[:, None] + ph))
    return out


def test_kernel_regression_matches_hand_computation():
    d2 = np.array([[0.0, 1.0, 4.0]])
    y = np.array([[1.0, 2.0, 4.0]])
    mu, var = kernel_regression(d2, y, h2=1.0, min_std=0.1)
    w = np.exp(-0.5 * np.array([0.0, 1.0, 4.0]))
    w /= w.sum()
    m = (w * y[0]).sum()
    assert mu[0] == pytest.approx(m, rel=1e-12)
    assert var[0] == pytest.approx((w * (y[0] - m) ** 2).sum() + 0.01, rel=1e-12)
    # far from every instance the weights do not underflow to NaN
    mu2, _ = kernel_regression(d2 + 1e6, y, h2=1e-3, min_std=0.1)
    assert mu2[0] == pytest.approx(1.0)


def test_scores_prefer_the_true_parent():
    c = _lagged()
    st = standardization(c.trajectories)
    td = transition_data(c.trajectories, st, cyclic=False, k=10, kernel_width=None,
                         min_std=0.01)
    D = 3
    # measured: none -395, true -172, wrong (X_2) -400 (one-step); propagated -1545 / -249
    none = transition_node_fit(td, 1, [], score="one_step")[0]
    true = transition_node_fit(td, 1, [D + 0], score="one_step")[0]  # X_0[t+1]
    wrong = transition_node_fit(td, 1, [D + 2], score="one_step")[0]
    assert true > none + 100 and true > wrong + 100
    prop_true = transition_node_fit(td, 1, [D + 0])[0]
    prop_none = transition_node_fit(td, 1, [])[0]
    assert prop_true > prop_none + 500
    # an irrelevant parent does not pay (calibrated bandwidths)
    assert wrong < none + 5
    pd = prior_data(c.trajectories, st, k=10, kernel_width=None, min_std=0.01)
    # X_1[1] = X_0[0]: the prior network sees it too (-27.5 against -45.6 / -42.9)
    assert prior_node_score(pd, D + 1, [0]) > prior_node_score(pd, D + 1, [2]) + 5
    assert prior_node_score(pd, D + 1, [0]) > prior_node_score(pd, D + 1, []) + 5


def test_structure_search_recovers_the_lag_and_the_prior_pairs():
    c = _lagged()
    m = learn(c, k=10, restarts=1)["model"]
    D = m.n_dofs  # x0, x1, x2 and the _phase DOF added for non-cyclic clips
    assert D == 4 and m.clips.labels[-1] == "_phase"
    assert D + 0 in m.transition_parents[1]
    # X_i[0] and X_i[1] are linked in the prior (either direction), the graph is acyclic
    for i in range(3):
        assert (i in m.prior_parents[D + i]) or (D + i in m.prior_parents[i])
    dag = DAG(2 * D)
    for v, ps in enumerate(m.prior_parents):
        for u in ps:
            dag.add(u, v)
    assert len(dag.order()) == 2 * D
    assert max(len(p) for p in m.prior_parents + m.transition_parents) <= 8
    assert m.attrs["evaluations"]["transition"] > 0


def test_parallel_map_gives_the_same_model_and_codec_round_trip():
    c = make_clips(_cycles(), ["a", "b", "c"], rate=48.0, cyclic=True)
    seq = learn(c, k=10, seed=3)["model"]
    with ThreadPoolExecutor(2) as pool:
        ctx = Context(mapper=lambda fn, items: list(pool.map(fn, items)), workers=2)
        par = learn(c, k=10, seed=3, ctx=ctx)["model"]
    assert par.transition_parents == seq.transition_parents
    assert par.prior_parents == seq.prior_parents
    np.testing.assert_array_equal(par.transition_scores, seq.transition_scores)
    e = encode(seq)
    back = decode(e)
    assert isinstance(back, VariationModel) and back.params == seq.params
    np.testing.assert_array_equal(back.transition_bandwidth, seq.transition_bandwidth)
    assert digest_encoded(encode(back)) == digest_encoded(e)
    a = variants(seq, 5, count=2, length=30)
    b = variants(back, 5, count=2, length=30)
    np.testing.assert_array_equal(a.trajectories[1], b.trajectories[1])


def test_learn_stage_merges_gathered_clips_and_reports():
    trajs = _cycles(n=4)
    parts = [make_clips(trajs[:2], ["a", "b", "c"], rate=48.0, cyclic=True),
             make_clips(trajs[2:], ["a", "b", "c"], rate=48.0, cyclic=True)]
    out = learn([parts], k=10, score="one_step", ctx=Context())
    rep = out["report"]
    assert rep["n_clips"] == 4 and rep["n_dofs"] == 3 and rep["k_transition"] == 10
    assert out["model"].clips.cyclic


def test_edge_cases_one_clip_constant_dof_lengths_and_bad_params():
    base = _cycles(n=3, T=60)
    # one clip: learns with a warning, samples
    ctx = Context()
    one = learn(make_clips(base[:1], ["a", "b", "c"], rate=48.0, cyclic=True),
                k=8, score="one_step", ctx=ctx)["model"]
    assert any("only one input clip" in w for w in ctx.warnings)
    assert variants(one, 0, length=50).trajectories[0].shape == (
        50, 3)
    # a DOF constant in all clips is dropped and comes back exactly
    with_const = [np.concatenate([t, np.full((len(t), 1), 0.25)], axis=1) for t in base]
    c = make_clips(with_const, ["a", "b", "c", "k"], rate=48.0, cyclic=True)
    m = learn(c, k=8, score="one_step")["model"]
    assert m.n_dofs == 3 + 2 and c.attrs["constant_dofs"] == ["k"]  # + the cycle phase
    v = variants(m, 0, length=40)
    np.testing.assert_array_equal(v.full(0)[:, 3], 0.25)
    # clips of very different lengths: fine, k clamped where needed
    ctx = Context()
    uneven = [base[0][:12], base[1], np.concatenate([base[2]] * 4)]
    mu = learn(make_clips(uneven, ["a", "b", "c"], rate=48.0), k=15,
               score="one_step", ctx=ctx)["model"]
    assert mu.params["k_transition"] <= 15
    assert np.isfinite(variants(mu, 1).trajectories[0]).all()
    # errors
    flat = make_clips([np.ones((10, 2)), np.ones((12, 2))], ["a", "b"], rate=10.0)
    with pytest.raises(LearnError, match="no varying DOF"):
        learn(flat)
    with pytest.raises(LearnError, match="k must be"):
        learn(c, k=1)
    with pytest.raises(LearnError, match="half_life"):
        learn(c, k=8, half_life=-1.0)
    with pytest.raises(LearnError, match="fewer than 3 frames"):
        learn(make_clips([base[0][:2], base[1][:2]], ["a", "b", "c"], rate=48.0), k=2)


def test_heldout_likelihood_ranks_an_outlier_last():
    trajs = _cycles(n=6, seed=2)
    u = np.arange(48) / 48
    odd = np.sin(4 * np.pi * u[:, None] + np.linspace(0, np.pi, 3, endpoint=False))  # 2x faster
    ll = heldout_log_likelihood(trajs[:5], [trajs[5], odd], cyclic=True, k=8)
    assert ll[0] > ll[1] + 1.0


# the structure search on the shipped walk config (configs/variation.yaml, its first part):
# parents and scores of four transition nodes and the prior network's greedy search from
# the empty DAG, as the search found them before it batched its scores (commit 87e3b9e)
WALK_TRANSITION = {
    0: ([2, 5, 23, 38, 56, 68, 93, 96, 106, 107], -2676.974430056219),
    13: ([7, 57, 61, 101, 106, 107], -23852.748416736104),
    26: ([27, 36, 44, 57, 68, 79, 81, 90, 106, 107], -3448.456340869235),
    40: ([3, 5, 42, 93, 106, 107], -3792.010140116809),
}
WALK_PRIOR = {"score": -6081.014937253519, "edges": 185, "evaluations": 6220,
              "some": {4: [36, 67], 14: [24, 64, 78, 99], 51: [44, 53, 105, 106, 107], 73: []}}


def test_walk_config_structure_is_unchanged():
    from mocapflow.pipeline.config import load_config
    from mocapflow.stages.motion.ingest import ingest_bvh
    from mocapflow.stages.variation import learn as learn_mod
    from mocapflow.stages.variation.inputs import clips as clips_stage
    from mocapflow.stages.variation.search import (
        _search_transition_node,
        _top_candidates,
        search_prior,
    )
    from tests.stages.variation.conftest import CONFIGS, DATA

    path = DATA / "bvh" / "pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh"
    if not path.exists():
        pytest.skip("shared walk data absent")
    nodes = {n: dict(v.params) for n, v in load_config(CONFIGS / "variation.yaml").nodes.items()}
    motion = ingest_bvh(str(path), rate=nodes["ingest"]["rate"], ctx=Context())["motion"]
    clips = clips_stage(motion, **nodes["clips"], ctx=Context())["clips"]
    lp = nodes["learn"]
    train = learn_mod._training_clips(learn_mod.flatten_clips(clips), phase=True, ctx=Context())
    td, pd = learn_mod._training_data(
        train, cyclic=True, k=lp["k"], kernel_width=lp["kernel_width"], min_std=lp["min_std"],
        velocity_weight=lp["velocity_weight"], half_life=lp["half_life"], prior_window=None,
        ctx=Context())
    req = learn_mod._phase_parents(train, cyclic=True)
    D = td.n_dofs
    assert (clips.n_clips, D, td.F.shape[0], pd.Z.shape[0]) == (6, 54, 358, 78)
    for i, (parents, score) in WALK_TRANSITION.items():
        idx = [p for p in range(2 * D) if p not in (i, D + i, *req)]
        target = np.stack([td.Y[:, i], td.Z2[:, i]], axis=1)
        cands = _top_candidates(target, td.F, idx, lp["candidates"])
        r = _search_transition_node((i, cands, list(req)), data=td,
                                    max_parents=lp["max_parents"], score=lp["score"])
        assert r["parents"] == parents
        assert r["score"] == pytest.approx(score, rel=1e-9, abs=0)
    p = search_prior(pd, candidates=lp["candidates"], max_parents=lp["max_parents"],
                     restarts=0, seed=0, ctx=Context())
    assert p.scores.sum() == pytest.approx(WALK_PRIOR["score"], rel=1e-9, abs=0)
    assert sum(map(len, p.parents)) == WALK_PRIOR["edges"]
    assert p.evaluations == WALK_PRIOR["evaluations"]
    for v, ps in WALK_PRIOR["some"].items():
        assert p.parents[v] == ps
