"""Shortcuts of the synthesis that must give the values of the plain computation to the
last bit (issue 16, CPU time): the search's choices, and so ``source_index``, depend on
exact ties, so every table, subset or restricted range below is checked against the
straightforward definition, bit for bit."""

from __future__ import annotations

import numpy as np

from mocapflow.stages.motion.kinematics import forward_kinematics
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.texture.pyramid import build_pyramid, level_positions
from mocapflow.stages.texture.refine import verbatim_runs
from mocapflow.stages.texture.root import chain_kinematics
from mocapflow.stages.texture.smoothing import _window


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

        def follows(u):  # position u plays the node after position u - 1's
            return bool((u > 0 or cyclic) and valid[u % n] and valid[(u - 1) % n]
                        and val[u % n] == val[(u - 1) % n] + 1)

        starts = [u for u in range(n) if valid[u] and not follows(u)]
        if not starts:
            return 0, ([[0, n - 1]] if valid.all() else [])
        runs = []
        for u in range(starts[0], starts[0] + n if cyclic else n):
            if valid[u % n] and runs and follows(u) and runs[-1][1] == u - 1:
                runs[-1][1] = u
            elif valid[u % n]:
                runs.append([u, u])
        return starts[0], runs

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
