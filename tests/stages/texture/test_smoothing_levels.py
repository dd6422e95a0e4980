"""Smoothing after every level (Moradoff §3.8; ``smooth_levels="every"``, issue 16 item 3).

The thesis smooths each level's output before the next finer level is synthesized
from it.  Here a level's output is the input nodes its source track copies; with
``smooth_levels="every"`` each coarser level is copied into its own representation
(joint rotations, root per node at ``rate / 2**l``), its seams smoothed
(:func:`~mocapflow.stages.texture.assemble.smooth_level`), and the finer level's
ancestor windows read that smoothed output.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from mocapflow.pipeline.registry import ParamError
from mocapflow.stages.metrics import quality as M
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.texture.assemble import smooth_level
from mocapflow.stages.texture.neighbourhood import level_view
from mocapflow.stages.texture.pyramid import build_pyramid
from mocapflow.stages.texture.refine import LevelRefinement
from mocapflow.stages.texture.search import LevelResult, SearchParams
from mocapflow.stages.texture.synth import _SmoothedParentRefinement, synthesize_source

RATE = 30.0


@pytest.fixture(scope="module")
def walk():
    return procedural_walk(300, rate=RATE, seed=3, variation=0.08)


@pytest.fixture(scope="module")
def pyr(walk):
    return build_pyramid(walk, levels=3)


def _seam_acc(positions: np.ndarray, seams: np.ndarray) -> np.ndarray:
    """Mean joint acceleration (per node²) of the two nodes either side of each seam."""
    a = np.linalg.norm(positions[2:] - 2 * positions[1:-1] + positions[:-2], axis=-1).mean(-1)
    return np.maximum(a[seams - 2], a[seams - 1])  # nodes t - 1 and t (a[k]: node k + 1)


def test_a_level_without_seams_is_the_input_level(pyr, walk):
    lev = pyr.levels[1]
    src = np.arange(20, 120)
    out = smooth_level(pyr, walk.skeleton, 1, src)
    np.testing.assert_array_equal(out.rotations, lev.rotations[src])
    np.testing.assert_allclose(out.positions, lev.positions[src], atol=1e-9)
    np.testing.assert_allclose(out.velocity, lev.velocity[src], atol=1e-12)
    np.testing.assert_allclose(out.yaw_rate, lev.yaw_rate[src], atol=1e-12)
    np.testing.assert_array_equal(out.height, lev.height[src])


def test_coarse_seams_are_smoothed_in_the_levels_representation(pyr, walk):
    """Random 15-node chunks of level 1 (every transition a jump of pose): the smoothed
    level's seam accelerations drop to under half the copy's at 80 % of the seams (the
    copy's are 3x its own median); a pinned node keeps the input's rotations."""
    lev = pyr.levels[1]
    starts = np.random.default_rng(0).integers(0, lev.n_nodes - 15, size=8)
    src = (starts[:, None] + np.arange(15)).ravel()
    seams = M.seams_from_source(src)
    assert seams.size >= 6
    pinned = int(seams[2])  # a constrained node right at a seam
    copy = smooth_level(pyr, walk.skeleton, 1, src, max_widening=0)
    smooth = smooth_level(pyr, walk.skeleton, 1, src, constrained=[pinned])
    a_copy = _seam_acc(copy.positions, seams)
    a_smooth = _seam_acc(smooth.positions, seams)
    acc_all = np.linalg.norm(np.diff(copy.positions, 2, axis=0), axis=-1).mean(-1)
    assert np.median(a_copy) > 3 * np.median(acc_all)  # the copy's seams are real jumps
    assert np.mean(a_smooth < 0.5 * a_copy) >= 0.8, (a_smooth / a_copy).round(2)
    np.testing.assert_array_equal(smooth.rotations[pinned], lev.rotations[src[pinned]])
    np.testing.assert_array_equal(copy.rotations, lev.rotations[src])


def test_ancestor_costs_of_an_unsmoothed_parent_are_the_inputs(pyr, walk):
    """Every output position and every candidate (the input's end included, where the
    candidate's parent window runs past the input): the costs of the plain search."""
    views = [level_view(pyr.levels[k], 2.0**k) for k in range(3)]
    n_out = [200, 100, 50]
    starts = np.random.default_rng(1).integers(0, pyr.levels[1].n_nodes - 20, size=5)
    src = (starts[:, None] + np.arange(20)).ravel()
    upper = LevelResult(src, np.stack([src, src, src], axis=1))
    copy = smooth_level(pyr, walk.skeleton, 1, src, max_widening=0)
    smooth = smooth_level(pyr, walk.skeleton, 1, src)
    args = (views, 0, n_out, False, upper, SearchParams(), np.random.default_rng(0))
    plain = LevelRefinement(*args)
    same = _SmoothedParentRefinement(*args, parent=copy)
    smoothed = _SmoothedParentRefinement(*args, parent=smooth)
    cands = np.arange(views[0].n)
    t = np.repeat(np.arange(n_out[0]), cands.size)  # one position per row
    c = np.tile(cands, n_out[0])
    for a, b in zip(plain._ancestor_cost(t, c), same._ancestor_cost(t, c)):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12)
    for t0 in (0, 57, n_out[0] - 1):  # one position for all rows
        for a, b in zip(plain._ancestor_cost(t0, cands), same._ancestor_cost(t0, cands)):
            np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12)
    num, den = smoothed._ancestor_cost(t, c)
    num0, den0 = plain._ancestor_cost(t, c)
    np.testing.assert_array_equal(den, den0)  # the same slots compared
    seams = M.seams_from_source(src)
    near = np.isin(t // 2, np.concatenate([seams - 1, seams]))
    assert (num != num0)[near].mean() > 0.9  # the parent windows at seams are smoothed


def test_the_ancestor_windows_read_the_smoothed_parent(pyr, walk):
    """An unsmoothed parent (no widening) gives the plain refinement's tracks exactly
    (the smoothed parent enters only through the ancestor windows, compared as the
    input's own nodes are); the smoothed one changes the tracks."""
    kw = dict(levels=3, cyclic=False, method="meeting_point", params=SearchParams())
    cons = [(10, 5), (150, 200)]
    differ = 0
    for seed in range(3):
        plain, _ = synthesize_source(pyr, 400, cons, rng=np.random.default_rng(seed), **kw)
        copy, _ = synthesize_source(
            pyr, 400, cons, rng=np.random.default_rng(seed),
            level_smoothing=functools.partial(smooth_level, pyr, walk.skeleton, max_widening=0),
            **kw)
        every, _ = synthesize_source(
            pyr, 400, cons, rng=np.random.default_rng(seed),
            level_smoothing=functools.partial(smooth_level, pyr, walk.skeleton), **kw)
        np.testing.assert_array_equal(copy, plain)
        assert all(every[j] == i for i, j in cons)
        differ += not np.array_equal(every, plain)
    assert differ >= 2


def test_smooth_levels_every_in_the_stage(run_synth, pyr, walk):
    cons = [[10, 5], [150, 200], [290, 397]]
    every = run_synth(pyr, walk, length=400, constraints=cons, smooth_levels="every")
    finest = run_synth(pyr, walk, length=400, constraints=cons)
    src = every["source_index"]
    assert all(src[j] == i for i, j in cons)
    assert every["report"]["constraint_max_angle_deg"] <= 1.0
    assert np.mean(every["report"]["smoothing"]["passed"]) >= 0.9
    assert not np.array_equal(src, finest["source_index"])
    # without smoothing there is no level to smooth: the setting changes nothing
    a = run_synth(pyr, walk, length=300, smoothing=False, smooth_levels="every")
    b = run_synth(pyr, walk, length=300, smoothing=False)
    np.testing.assert_array_equal(a["source_index"], b["source_index"])
    with pytest.raises(ParamError, match="smooth_levels: 'all' is not one of"):
        run_synth(pyr, walk, length=300, smooth_levels="all")
