"""The clean stage's third speed pass gives the same bits as the plain computation.

:func:`~mocapflow.stages.skin.predict.finite_rows` replaces
``np.isfinite(X).all(-1)``; :func:`~mocapflow.stages.skin.local_pca._complete_rows`
replaces ``X[frames][:, members]`` (same values and memory layout: the rigid fit
rounds by layout); :func:`~mocapflow.stages.skin.rigidity._pair_distances` replaces
the norm of the gathered differences in
:func:`~mocapflow.stages.skin.rigidity.edge_stretch`.  Every new function is missing
from the old code (commit 4bec42d): collection fails there.
"""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.stages.skin.local_pca import _complete_rows
from mocapflow.stages.skin.predict import finite_rows
from mocapflow.stages.skin.rigidity import _pair_distances, edge_stretch


def _layouts(X):
    """The same values as ``X (F, M, 3)`` in the layouts the clean stage meets."""
    cols = np.arange(X.shape[1])
    return {"C": X, "columns": X[:, cols],  # as fill._train_item cuts it
            "F": np.asfortranarray(X), "strided": np.repeat(X, 2, axis=1)[:, ::2]}


@pytest.mark.parametrize("layout", ["C", "columns", "F", "strided"])
def test_finite_rows_is_isfinite_all(layout):
    rng = np.random.default_rng(11)
    X = rng.normal(size=(50, 7, 3))
    X[rng.random(X.shape) < 0.1] = np.nan
    X[rng.random(X.shape) < 0.02] = np.inf
    X[rng.random(X.shape) < 0.02] = -np.inf
    Y = _layouts(X)[layout]
    got, want = finite_rows(Y), np.isfinite(Y).all(-1)
    assert got.dtype == bool and got.strides == want.strides
    np.testing.assert_array_equal(got, want)
    # known answers: one NaN or inf coordinate hides the sample
    Z = np.zeros((2, 2, 3))
    Z[0, 1, 2], Z[1, 0, 0] = np.nan, np.inf
    assert finite_rows(Z).tolist() == [[True, False], [False, True]]
    # other trailing lengths fall back to the reduction
    assert finite_rows(np.array([[1.0, np.nan], [1.0, 2.0]])).tolist() == [False, True]


@pytest.mark.parametrize("layout", ["C", "columns", "F", "strided"])
def test_complete_rows_is_two_step_indexing(layout):
    rng = np.random.default_rng(12)
    X = _layouts(rng.normal(size=(80, 20, 3)))[layout]
    frames = np.sort(rng.choice(80, 33, replace=False))
    members = np.array([7, 0, 19, 3, 3, 12])
    got, want = _complete_rows(X, frames, members), X[frames][:, members]
    assert got.shape == want.shape == (33, 6, 3)
    assert got.strides == want.strides == (24, 33 * 24, 8)  # the rounding follows the layout
    np.testing.assert_array_equal(got, want)
    assert got[4, 2].tolist() == X[frames[4], 19].tolist()


@pytest.mark.parametrize("layout", ["C", "columns", "F", "strided"])
def test_pair_distances_are_the_norm(layout):
    rng = np.random.default_rng(14)
    X = rng.normal(size=(60, 15, 3)) * 10.0 ** rng.integers(-3, 3, size=(60, 15, 1))
    X[rng.random((60, 15)) < 0.1] = np.nan
    Y = _layouts(X)[layout][::2]
    pairs = rng.integers(0, 15, size=(40, 2))
    want = np.linalg.norm(Y[:, pairs[:, 0]] - Y[:, pairs[:, 1]], axis=-1)
    np.testing.assert_array_equal(_pair_distances(Y, pairs), want)  # NaN where NaN
    # a known answer: a 3-4-12 box diagonal is 13
    Z = np.zeros((1, 2, 3))
    Z[0, 1] = [3.0, -4.0, 12.0]
    assert _pair_distances(Z, np.array([[0, 1], [1, 1]])).tolist() == [[13.0, 0.0]]
    # and edge_stretch on it: sd / median of a distance that alternates 1, 3 is 1 / 2
    W = np.zeros((20, 2, 3))
    W[:, 1, 0] = np.tile([1.0, 3.0], 10)
    assert edge_stretch(W, np.array([[0, 1]])).tolist() == [0.5]
