"""The GenMM baseline's two computations (``benchmarks/genmm_baseline.py``).

``computation="released"`` follows GenMM's released code step for step (one-hot
``unfoldNd``/``foldNd``, two blocked distance passes); ``"lean"`` is the same algorithm
computed once per step on strided views.  Checked here: the released-code operations
against their direct definitions, and both computations giving the same matches and
blended frames (float32 tolerance) on small random cases and on a tiny motion.
"""

from __future__ import annotations

import numpy as np
import pytest
from genmm_baseline import (  # (benchmarks/ on sys.path: conftest.py)
    GenMMParams,
    _blend,
    _normalised_nn,
    _patches,
    _released_step,
    combine_patches,
    efficient_cdist,
    extract_patches,
    fold,
    genmm_synthesize,
    nearest_released,
    unfold,
)

from tests.benchmarks.test_genmm_outputs import tiny_motion

P = 5


@pytest.fixture(scope="module")
def rng():
    return np.random.default_rng(3)


def test_unfold_is_the_patch_definition(rng):
    """unfoldNd: row ``c·p + k``, column ``t`` holds ``x[c, t + k]``."""
    x = rng.standard_normal((3, 17)).astype(np.float32)
    u = unfold(x, P)
    assert u.shape == (3 * P, 17 - P + 1) and u.dtype == np.float32
    direct = np.array([[x[c, t + k] for t in range(13)] for c in range(3) for k in range(P)])
    np.testing.assert_array_equal(u, direct)
    # extract_patches: one row per patch, channel-major (c, k) inside the row
    np.testing.assert_array_equal(extract_patches(x, P)[4].reshape(3, P), x[:, 4:4 + P])


def test_fold_is_the_transpose_of_unfold(rng):
    """foldNd scatter-adds ``cols[c·p + k, t]`` at frame ``t + k``; <unfold x, y> = <x, fold y>."""
    cols = rng.standard_normal((2 * P, 9)).astype(np.float32)
    direct = np.zeros((2, 9 + P - 1), dtype=np.float32)
    for c in range(2):
        for k in range(P):
            for t in range(9):
                direct[c, t + k] += cols[c * P + k, t]
    np.testing.assert_array_equal(fold(cols, 13, P), direct)
    x = rng.standard_normal((2, 13))
    assert np.sum(unfold(x, P) * cols) == pytest.approx(np.sum(x * fold(cols, 13, P)))


def test_divisor_counts_the_patches_over_each_frame():
    """fold(unfold(ones)): 1, 2, …, p, …, p, …, 2, 1 patches over the frames."""
    L = 12
    count = fold(unfold(np.ones((1, L), dtype=np.float32), P), L, P)[0]
    t = np.arange(L)
    np.testing.assert_array_equal(count, np.minimum.reduce([t + 1, L - t, np.full(L, P),
                                                            np.full(L, L - P + 1)]))
    # combining a sequence's own patches gives the sequence back
    x = np.random.default_rng(0).standard_normal((4, L)).astype(np.float32)
    np.testing.assert_allclose(combine_patches(extract_patches(x, P), L, P), x, rtol=1e-6,
                               atol=1e-6)


def test_efficient_cdist_is_the_mean_squared_difference(rng):
    X = rng.standard_normal((6, 10)).astype(np.float32)
    Y = rng.standard_normal((4, 10)).astype(np.float32)
    brute = ((X[:, None, :] - Y[None, :, :]) ** 2).mean(-1)
    np.testing.assert_allclose(efficient_cdist(X, Y), brute, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("block", [1024, 7])
def test_released_matches_equal_lean_matches(rng, block):
    """Two blocked passes (several blocks when ``block`` = 7) = one distance matrix."""
    C, Lx, Ly = 4, 40, 30
    syn = rng.standard_normal((C, Lx)).astype(np.float32)
    target = rng.standard_normal((C, Ly)).astype(np.float32)
    nnf_r, dists = nearest_released(extract_patches(syn, P), extract_patches(target, P),
                                    0.01, block)
    Y = _patches(target.T, P)
    nnf_l = _normalised_nn(_patches(syn.T, P), Y, (Y * Y).sum(1), 0.01, block)
    np.testing.assert_array_equal(nnf_r, nnf_l)
    # the normalised distance of the match, from its definition
    X = extract_patches(syn, P)
    Yc = extract_patches(target, P)
    D = ((X[:, None] - Yc[None]) ** 2).mean(-1)
    D /= 0.01 + D.min(0)
    np.testing.assert_allclose(dists, D.min(1), rtol=1e-4)
    assert np.array_equal(D.argmin(1), nnf_r)


def test_released_step_equals_lean_step(rng):
    """One match-and-blend step: fold / divisor = the lean per-frame average."""
    C = 3
    syn = rng.standard_normal((C, 36)).astype(np.float32)
    target = rng.standard_normal((C, 25)).astype(np.float32)
    blended, nnf, loss = _released_step(syn, extract_patches(target, P), P, 0.01, 1024)
    lean = _blend(target.T, nnf, 36, P)
    np.testing.assert_allclose(blended, lean.T, rtol=1e-6, atol=1e-6)
    assert blended.shape == syn.shape and blended.dtype == np.float32 and loss > 0


def test_whole_synthesis_released_equals_lean():
    """Same seed: the two computations give the same output motion (float32 rounding)."""
    motion = tiny_motion(90)
    a = genmm_synthesize(motion, 140, seed=2)
    b = genmm_synthesize(motion, 140, seed=2, params=GenMMParams(computation="lean"))
    np.testing.assert_array_equal(a["source_index"], b["source_index"])
    np.testing.assert_allclose(a["motion"].rotations, b["motion"].rotations, atol=1e-4)
    np.testing.assert_allclose(a["motion"].root_position, b["motion"].root_position, atol=1e-4)
    assert len(a["losses"]) == 3 * len(a["input_lengths"]) and not b["losses"]


def test_computation_is_checked():
    assert GenMMParams().computation == "released"
    with pytest.raises(ValueError, match="computation"):
        GenMMParams(computation="fast")
