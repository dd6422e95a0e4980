"""The merge rounds' speed-ups decide exactly as the plain forms (issue 15 throughput).

:func:`~mocapflow.stages.skin.merge._entry_screen` takes the entry test of all the
fragments of a round at once and decides those no candidate enters; the others go to
:func:`~mocapflow.stages.skin.merge._judge_fragment` with their entry distances.
:func:`~mocapflow.stages.skin.merge._rival_fragment` sums distances over the rivals seen
in enough frames only; :func:`~mocapflow.stages.skin.merge.continue_breaks` repeats a
pass only near the merges of the pass before; a
:class:`~mocapflow.stages.skin.merge.PredictionIndex` of the same data shares the other's
counts.  Each is checked against the plain form (verdicts equal as dicts: the same
reasons and reported numbers) and on known answers.
"""

from __future__ import annotations

import numpy as np
import pytest

import mocapflow.stages.skin.merge as cm
from tests.stages.skin.test_clean_merge import judge_setup
from tests.stages.skin.test_merge_equivalence import rival_case, unmerged_counts
from tests.stages.skin.test_merge_keeps_samples import GRID, grid_neighbours, moving_grid


def random_fragments(rng, E_all, n):
    """``(F, n, 3)`` contiguous fragments near random markers' predictions (some drifting
    out of the tube, some far off) and their frames."""
    F, M, _ = E_all.shape
    fragments = np.full((F, n, 3), np.nan)
    for u in range(n):
        a = int(rng.integers(0, F - 1))
        T = np.arange(a, min(F, a + int(rng.integers(1, 30))))
        m = int(rng.choice([int(rng.integers(0, M)), 10, 11, 20, 21]))
        noise = rng.choice([0.0005, 0.005, 0.015, 0.2])
        frag = np.nan_to_num(E_all[T, m], nan=0.5) + rng.normal(size=(len(T), 3)) * noise
        frag[:, 1] += rng.choice([0.0, 0.002]) * np.arange(len(T))
        fragments[T, u] = frag
    return fragments, [np.flatnonzero(np.isfinite(fragments[:, u]).all(-1)) for u in range(n)]


@pytest.mark.parametrize("seed", range(4))
def test_entry_screen_then_judge_equals_the_plain_judge(seed):
    rng, E, E_all, avail, eps1, eps2, labels, index = judge_setup(seed)
    F, M, _ = E.shape
    usable = np.isfinite(eps1)
    fragments, frames_of = random_fragments(rng, E_all, 300)
    us = list(range(300))
    free, entries, screened = cm._entry_screen(fragments, frames_of, us, index, E, eps1,
                                               usable, labels)
    assert set(entries).isdisjoint(screened) and set(entries) | set(screened) == set(us)
    kinds = set()
    for u in us:
        T = frames_of[u]
        want_free = ~avail[T].any(0) & usable
        np.testing.assert_array_equal(free[u], want_free)
        plain = cm._judge_fragment(fragments[T, u], T, want_free, E, E_all, eps1, eps2,
                                   labels, index)
        if u in screened:
            assert screened[u] == plain
            kinds.add("screened " + plain["reason"].split(" ")[0])
        else:
            got = cm._judge_fragment(fragments[T, u], T, want_free, E, E_all, eps1, eps2,
                                     labels, index, entry=entries[u])
            assert got == plain
            kinds.add("judged " + ("marker" if "marker" in plain else
                                   plain["reason"].split(" ")[0].rstrip(":")))
    assert {"screened entry", "screened no", "judged marker", "judged ambiguous",
            "judged leaves"} <= kinds, kinds


def test_entry_screen_known_answers():
    # markers 0 and 1 predicted at x = -5 cm and +5 cm in every frame, marker 2 never
    F, M = 10, 3
    E = np.zeros((F, M, 3))
    E[:, 0, 0], E[:, 1, 0], E[:, 2] = -0.05, 0.05, np.nan
    avail = np.zeros((F, M), bool)
    avail[8:, :2] = True  # frames 8-9: only marker 2 missing
    avail[6, :] = True  # frame 6: every marker seen
    index = cm.PredictionIndex(avail, np.isfinite(E).all(-1))
    eps1 = np.full(M, 0.02)
    fragments = np.full((F, 5, 3), np.nan)
    fragments[0:4, 0] = [-0.02, 0.0, 0.0]  # 30 mm from marker 0, 70 mm from marker 1
    fragments[0:4, 1] = [0.0, 0.0, 0.0]  # 50 mm from both: the first one is the nearest
    fragments[8:10, 2] = [0.0, 0.0, 0.0]  # only marker 2 free, never predicted
    fragments[5:7, 3] = [0.0, 0.0, 0.0]  # overlaps every marker at frame 6
    fragments[0:3, 4] = [-0.049, 0.0, 0.0]  # enters marker 0
    frames_of = [np.flatnonzero(np.isfinite(fragments[:, u]).all(-1)) for u in range(5)]
    free, entries, v = cm._entry_screen(fragments, frames_of, list(range(5)), index, E,
                                        eps1, np.ones(M, bool), ["A", "B", "C"])
    assert v[0] == {"reason": "entry 30.0 mm from the prediction of nearest marker A > eps1 "
                              "20.0 mm", "nearest": "A", "entry_mm": 30.0}
    assert v[1]["nearest"] == "A" and v[1]["entry_mm"] == 50.0
    assert v[2]["reason"].startswith("no prediction")
    assert v[3]["reason"].startswith("overlaps every marker")
    assert free[2].tolist() == [False, False, True] and not free[3].any()
    markers, dist = entries[4]
    assert markers.tolist() == [0, 1]
    np.testing.assert_allclose(dist, [0.001, 0.099], rtol=1e-12)
    assert set(v) == {0, 1, 2, 3}


def rival_plain(fragments, unmerged, u, T, v, E_all, eps1, labels, flabels):
    """``_rival_fragment`` with every rival's column in the distance table (the form
    before the speed-up): the reference the restricted table must equal."""
    m = int(v["marker"])
    seen = unmerged[T]
    rivals = np.flatnonzero(seen.any(0))
    rivals = rivals[rivals != u]
    if not len(rivals):
        return v
    p = E_all[T, m]
    d_u = np.linalg.norm(fragments[T, u] - p, axis=-1)
    both = seen[:, rivals] & np.isfinite(d_u)[:, None]
    n = both.sum(0)
    enough = n >= max(1, int(np.ceil(0.5 * len(T))))
    cols = np.flatnonzero(enough)
    t, r = np.nonzero(both[:, cols])
    d_r = np.zeros(both.shape)
    d_r[t, cols[r]] = np.linalg.norm(fragments[T[t], rivals[cols[r]]] - p[t], axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_r = d_r.sum(0) / n
        mean_u = np.where(both, d_u[:, None], 0.0).sum(0) / n
    close = enough & (mean_r < eps1[m]) & (mean_r < cm.AMBIGUITY_RATIO * mean_u)
    if not close.any():
        return v
    k = int(np.argmin(np.where(close, mean_r, np.inf)))
    return {"reason": f"ambiguous: fragment {flabels[int(rivals[k])]} in the same frames at "
                      f"{mean_r[k] * 1000.0:.1f} mm of the prediction of {labels[m]}, this one "
                      f"at {mean_u[k] * 1000.0:.1f} mm",
            "conflict": {"labels": [labels[m]], "fragments": [flabels[int(rivals[k])]],
                         "mean_mm": [round(float(mean_u[k] * 1000.0), 2),
                                     round(float(mean_r[k] * 1000.0), 2)]}}


@pytest.mark.parametrize("seed", range(8))
def test_rival_fragment_on_enough_rivals_only_equals_the_full_table(seed):
    fragments, unmerged, E_all, eps1, labels, flabels = rival_case(300 + seed)
    U, M = fragments.shape[1], E_all.shape[1]
    n_unmerged = unmerged_counts(unmerged)
    refused = 0
    for u in range(U):
        T = np.flatnonzero(np.isfinite(fragments[:, u]).all(-1))
        for T_ in (T, T[::2]):  # contiguous, and gapped frames
            v = {"marker": u % M, "entry": 0.0, "max": 0.0, "mean": 0.0}
            want = rival_plain(fragments, unmerged, u, T_, v, E_all, eps1, labels, flabels)
            for counts in (n_unmerged, None):
                assert cm._rival_fragment(fragments, unmerged, u, T_, v, E_all, eps1, labels,
                                          flabels, counts) == want
            refused += "conflict" in want
    assert refused > 0


def test_rival_fragment_with_one_rival_in_enough_frames_known_answer():
    # fragment 0 over frames 0-39, 4 mm from marker 0's prediction; fragment 1 seen in all
    # of them 2 mm from it (a rival), fragment 2 in 5 frames only (none)
    F = 40
    E_all = np.zeros((F, 1, 3))
    fragments = np.full((F, 3, 3), np.nan)
    fragments[:, 0] = [0.004, 0.0, 0.0]
    fragments[:, 1] = [0.0, 0.002, 0.0]
    fragments[:5, 2] = [0.0, 0.0, 0.001]
    unmerged = np.isfinite(fragments).all(-1)
    n_unmerged = unmerged_counts(unmerged)
    v = {"marker": 0, "entry": 0.004, "max": 0.004, "mean": 0.004}
    got = cm._rival_fragment(fragments, unmerged, 0, np.arange(F), v, E_all, np.full(1, 0.01),
                             ["A"], ["*1", "*2", "*3"], n_unmerged)
    assert got["conflict"] == {"labels": ["A"], "fragments": ["*2"], "mean_mm": [4.0, 2.0]}
    assert got["reason"] == ("ambiguous: fragment *2 in the same frames at 2.0 mm of the "
                             "prediction of A, this one at 4.0 mm")


def test_continue_breaks_chains_across_passes_known_answer():
    # breaks only (max_gap 1): each piece continues the marker once the one before it
    # is merged, one piece per pass; the later passes look only near the last merges
    F = 40
    true = moving_grid(F)
    X = true.copy()
    X[10:, 14] = np.nan
    X[30:, 20] = np.nan
    frags = np.full((F, 6, 3), np.nan)
    for u, (m, a, b) in enumerate([(14, 10, 15), (14, 15, 20), (14, 20, 25), (14, 25, 40),
                                   (20, 30, 35), (20, 35, 40)]):
        frags[a:b, u] = true[a:b, m]
    assigned = np.full(6, -1)
    done = cm.continue_breaks(X, frags, np.full(36, 0.5 * GRID), assigned,
                              grid_neighbours(true[0]), max_gap=1)
    assert [d[:2] for d in done] == [(0, 14), (4, 20), (1, 14), (5, 20), (2, 14), (3, 14)]
    assert assigned.tolist() == [14, 14, 14, 14, 20, 20]
    np.testing.assert_array_equal(X, true)


def test_prediction_index_like_shares_the_availability_counts():
    rng = np.random.default_rng(9)
    avail = rng.random((30, 5)) < 0.4
    pred_a, pred_b = rng.random((30, 5)) < 0.3, rng.random((30, 5)) < 0.6
    first = cm.PredictionIndex(avail, pred_a)
    second = cm.PredictionIndex(avail, pred_b, like=first)
    assert second.n_available is first.n_available
    np.testing.assert_array_equal(second.n_available[1:], np.cumsum(avail, 0))
    np.testing.assert_array_equal(second.n_predicted[1:], np.cumsum(pred_b, 0))
    assert second.free(3, 9).tolist() == (~avail[3:10].any(0)).tolist()
    for a in range(30):
        later = [np.flatnonzero(pred_b[a:, m]) for m in range(5)]
        assert second.next_predicted[a].tolist() == [a + x[0] if len(x) else 30 for x in later]
