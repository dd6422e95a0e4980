"""The clean stage's second speed pass gives the same values as before (issue 15 throughput).

:func:`~mocapflow.stages.skin.predict.gather_samples` replaces two-array indexing
``X[frames, markers]`` (merge, local PCA, regression, rigid fits);
:func:`~mocapflow.stages.skin.merge._rival_fragment` finds the fragments seen in
contiguous frames from cumulative counts (``n_unmerged``); the regression's
:func:`~mocapflow.stages.skin.regress.choose_predictors` runs on a column-major
visibility array.  Each is checked here, bit for bit, against the plain form.
(``X[idx][:, members]`` is not replaced by a contiguous gather: its result is not
C-contiguous, and the rigid fit's sums over it round differently from a contiguous
copy's; ``local_pca._complete_rows`` later gathers it in its own layout, see
``test_clean_speed_pass3.py``.)
"""

from __future__ import annotations

import numpy as np
import pytest

import mocapflow.stages.skin.merge as cm
from mocapflow.stages.skin.predict import gather_samples
from mocapflow.stages.skin.regress import choose_predictors
from tests.stages.skin.test_merge_equivalence import rival_case, rival_loop, unmerged_counts


@pytest.mark.parametrize("contiguous", [True, False])
def test_gather_samples_equals_two_array_indexing(contiguous):
    rng = np.random.default_rng(3)
    X = rng.normal(size=(40, 9, 3))
    X[rng.random((40, 9)) < 0.2] = np.nan
    if not contiguous:
        X = np.swapaxes(np.swapaxes(X, 0, 1).copy(), 0, 1)  # same values, not C order
    assert X.flags.c_contiguous == contiguous
    f = np.array([0, 3, 3, 39, 17])
    m = np.array([[8, 0, 2], [1, 1, 7], [0, 4, 4], [8, 8, 8], [5, 6, 3]])
    cases = [(f[:, None], m), (f[:, None], np.array([2, 7])[None]), (f, m[:, 0]),
             (np.array(6), np.array([1, 2]))]
    for rows, cols in cases:
        got, want = gather_samples(X, rows, cols), X[rows, cols]
        assert got.shape == want.shape
        # the same memory layout too (downstream sums round by layout)
        assert got.flags.c_contiguous and want.flags.c_contiguous
        np.testing.assert_array_equal(got, want)  # NaN where NaN, else the same bits
    # a known sample
    assert gather_samples(X, np.array([17]), np.array([5]))[0].tolist() == X[17, 5].tolist()


@pytest.mark.parametrize("seed", range(6))
def test_rival_fragment_with_cumulative_counts_equals_the_scan(seed):
    fragments, unmerged, E_all, eps1, labels, flabels = rival_case(200 + seed)
    U, M = fragments.shape[1], E_all.shape[1]
    n_unmerged = unmerged_counts(unmerged)
    refused = 0
    for u in range(U):
        T = np.flatnonzero(np.isfinite(fragments[:, u]).all(-1))
        v = {"marker": u % M, "entry": 0.0, "max": 0.0, "mean": 0.0}
        got = cm._rival_fragment(fragments, unmerged, u, T, v, E_all, eps1, labels, flabels,
                                 n_unmerged)
        assert got == cm._rival_fragment(fragments, unmerged, u, T, v, E_all, eps1, labels,
                                         flabels)
        want = rival_loop(fragments, unmerged, u, T, u % M, E_all, eps1)
        assert ("marker" in got) == (want is None)
        if want is not None:
            refused += 1
            assert got["conflict"]["fragments"] == [flabels[want[0]]]
            np.testing.assert_allclose(got["conflict"]["mean_mm"],
                                       [round(want[1] * 1e3, 2), round(want[2] * 1e3, 2)],
                                       atol=0.011)
    assert refused > 0


def test_choose_predictors_on_column_major_visibility():
    rng = np.random.default_rng(5)
    vis = rng.random((300, 40)) < 0.9
    cand = rng.permutation(np.arange(1, 40))
    got = choose_predictors(np.asfortranarray(vis), 0, cand, n_predictors=12, min_frames=40)
    assert got.tolist() == choose_predictors(vis, 0, cand, n_predictors=12,
                                             min_frames=40).tolist()
    # by hand: take a candidate if at least max(40, 4 k) frames keep everything visible
    cur, want = vis[:, 0].copy(), []
    for j in cand:
        if (cur & vis[:, j]).sum() >= max(40, 4 * (len(want) + 1)):
            want.append(int(j))
            cur &= vis[:, j]
            if len(want) == 12:
                break
    assert got.tolist() == want and len(want) == 12
