"""Shortcuts of the synthesis that must give the values of the plain computation to the
last bit (issue 16, CPU time): the search's choices, and so ``source_index``, depend on
exact ties, so every table, subset or restricted range below is checked against the
straightforward definition, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.stages.motion.kinematics import forward_kinematics
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.texture.neighbourhood import (
    LevelView,
    pair_distance,
    pair_tables,
    window_cost,
)
from mocapflow.stages.texture.pyramid import build_pyramid, level_positions
from mocapflow.stages.texture.refine import verbatim_runs
from mocapflow.stages.texture.root import chain_kinematics
from mocapflow.stages.texture.smoothing import _window


@pytest.fixture(scope="module")
def view() -> LevelView:
    rng = np.random.default_rng(11)
    n, K, E = 26, 4, 2
    P = np.cumsum(rng.normal(scale=0.05, size=(n, K, 3)), axis=0)
    return LevelView(P, rng.normal(scale=0.1, size=(n, E, 3)), spacing=1.0)


def test_rate_feature_table_gives_the_computed_norms(view, monkeypatch):
    # known answer: rate features 3 and 4 apart on two axes are 5 apart
    R = np.zeros((4, 1, 3))
    R[2, 0] = [3.0, 0.0, 4.0]
    small = LevelView(np.zeros((4, 1, 3)), R, spacing=1.0)
    assert small.rate_norms()[2, 0, 0] == 5.0 and small.rate_norms()[0, 2, 0] == 5.0
    rng = np.random.default_rng(0)
    o0, o1, i0 = (rng.integers(0, view.n, 300) for _ in range(3))
    i0 = np.minimum(i0, view.n - 2)
    tabled = pair_distance(view, o0, o1, i0, i0 + 1)
    monkeypatch.setattr(LevelView, "RATE_TABLE_NODES", 0)  # the computed path
    plain = LevelView(view.P, view.R, view.spacing)
    assert plain.rate_norms() is None
    np.testing.assert_array_equal(tabled, pair_distance(plain, o0, o1, i0, i0 + 1))


def test_children_tables_hold_exactly_what_a_coarser_search_reads(view):
    n = view.n
    T = pair_tables(view, out_of=False, children=True)
    assert T.partial and T.out_of is None
    full = pair_tables(view)
    x, y = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    same = (x - y) % 2 == 0
    np.testing.assert_array_equal(T.verbatim[same], full.verbatim[same])
    assert np.isnan(T.verbatim[~same]).all()
    x, y = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    odd_even = (x % 2 == 1) & (y % 2 == 0)
    np.testing.assert_array_equal(T.into[odd_even], full.into[odd_even])
    assert np.isnan(T.into[~odd_even]).all()
    # windows of children (a coarser level's finer windows) and arbitrary ones: the
    # entries not tabulated are computed, the sums are those without tables
    rng = np.random.default_rng(3)
    W, m = 8, 400
    par = rng.integers(0, n // 2, (m, W // 2))
    par[:, 1:] = np.where(rng.random((m, W // 2 - 1)) < 0.5, par[:, :-1] + 1, par[:, 1:])
    ov = (2 * par[:, :, None] + np.arange(2)[None, None, :]).reshape(m, W)
    ov[rng.random((m, W)) < 0.1] = -1
    ov[ov >= n] = -1
    odd = rng.random(m) < 0.3  # some rows not made of children
    ov[odd] = rng.integers(-1, n, (int(odd.sum()), W))
    iv = 2 * rng.integers(-1, n // 2 + 1, m)[:, None] + np.arange(-3, 5)[None, :]
    block = (np.arange(-3, 5) == 0) | (np.arange(-3, 5) == 1)
    pw = np.exp(-0.5 * ((np.arange(W - 1) - 3.0) / 3) ** 2)
    for a, b in zip(window_cost(view, ov, iv, block, pw),
                    window_cost(view, ov, iv, block, pw, T)):
        np.testing.assert_array_equal(a, b)


def test_chain_kinematics_is_forward_kinematics_of_those_joints():
    walk = procedural_walk(40, rate=30.0, seed=1)
    sk = walk.skeleton
    rng = np.random.default_rng(2)
    tr = np.broadcast_to(sk.offsets, (walk.n_frames,) + sk.offsets.shape) + rng.normal(
        scale=0.01, size=(walk.n_frames,) + sk.offsets.shape)
    tr[:, ::3] = np.nan  # offsets where not finite
    for trans in (None, tr):
        pos, glob = forward_kinematics(sk, walk.rotations, walk.root_position,
                                       translations=trans)
        joints = [sk.n_joints - 1, 3, 0, 3]  # any order, repeats
        p, g = chain_kinematics(sk, walk.rotations, walk.root_position, joints,
                                translations=trans)
        np.testing.assert_array_equal(p, pos[:, joints])
        np.testing.assert_array_equal(g, glob[:, joints])


def test_smoothing_window_on_its_frames_and_zero_beyond_its_reach():
    L, r, taper = 90, 1.0, 5.0
    for cyclic, centre in ((False, 40.5), (True, 2.5), (True, 87.5)):
        full = _window(L, centre, 3.0 * r, cyclic, taper)
        f = np.arange(L)[::3]
        np.testing.assert_array_equal(_window(L, centre, 3.0 * r, cyclic, taper, frames=f),
                                      full[f])
        d = np.abs(np.arange(L) - centre)
        if cyclic:
            d = np.minimum(d, L - d)
        assert (full[d >= 3.0 * r + taper] == 0.0).all() and full[d <= 3.0 * r].min() == 1.0


def test_verbatim_runs_are_the_definition():
    def runs_by_loop(val, valid, cyclic):  # the definition, position by position
        n = val.size
        cont = np.zeros(n, dtype=bool)
        cont[1:] = valid[1:] & valid[:-1] & (val[1:] == val[:-1] + 1)
        if cyclic:
            cont[0] = valid[0] and valid[-1] and val[0] == val[-1] + 1
        starts = np.flatnonzero(valid & ~cont)
        if starts.size == 0:
            return 0, ([[0, n - 1]] if valid.all() else [])
        p0, runs = int(starts[0]), []
        for u in range(p0, p0 + n if cyclic else n):
            i = u % n
            if valid[i] and runs and cont[i] and runs[-1][1] == u - 1:
                runs[-1][1] = u
            elif valid[i]:
                runs.append([u, u])
        return p0, runs

    rng = np.random.default_rng(5)
    for _ in range(2000):
        n = int(rng.integers(1, 25))
        val = np.cumsum(rng.integers(0, 3, n)) if rng.random() < 0.5 else rng.integers(0, 4, n)
        valid = rng.random(n) < (0.7 if rng.random() < 0.5 else 1.0)
        for cyclic in (False, True):
            assert verbatim_runs(val, valid, cyclic) == runs_by_loop(val, valid, cyclic)
    # known answer: 5 6 | 2 3 4 | (invalid) | 9, and in a loop 9 → 10 wraps onto 10 11
    val, valid = np.array([10, 11, 2, 3, 4, 0, 9]), np.array([1, 1, 1, 1, 1, 0, 1], bool)
    assert verbatim_runs(val, valid, False) == (0, [[0, 1], [2, 4], [6, 6]])
    assert verbatim_runs(val, valid, True) == (2, [[2, 4], [6, 8]])


def test_pyramid_positions_are_each_levels_own_kinematics():
    walk = procedural_walk(96, rate=30.0, seed=4)
    pyr = build_pyramid(walk, levels=4)
    for lev in pyr.levels:
        np.testing.assert_array_equal(
            lev.positions, level_positions(walk.skeleton, lev.rotations, lev.height,
                                           lev.translations))


def test_short_row_sums_are_numpys_sums_and_norms():
    from mocapflow.stages.texture.smoothing import _row_sum

    rng = np.random.default_rng(8)
    for shape in ((1, 3), (7, 4), (300, 31, 4), (40, 12, 23, 3), (5000, 4)):
        x = rng.normal(size=shape) * rng.choice([1e-8, 1.0, 1e8], size=shape)
        np.testing.assert_array_equal(_row_sum(x), np.sum(x, axis=-1, keepdims=True))
        np.testing.assert_array_equal(np.sqrt(_row_sum(x * x)),
                                      np.linalg.norm(x, axis=-1, keepdims=True))
    assert _row_sum(np.array([[1.0, 2.0, 3.0, 4.0]]))[0, 0] == 10.0  # known answer
