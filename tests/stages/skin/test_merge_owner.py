"""Who owns a fragment when the chosen marker's neighbourhood bends: the swap test of
:func:`mocapflow.stages.skin.merge._swap_rival` (issue 15, Table 1b, range of motion,
seed 4: the fragment of L155 merged into L298, L298 itself an unmerged fragment).

A 6×6 grid of markers 40 mm apart (``ε₁ = 20 mm``) moving as one; markers 14 and 15
(15 is 40 mm from 14 along +x) are missing in frames 5..12, where the fragments are.
One round of given predictions judged by the rigid rounds' rules, no continuity.
"""

from __future__ import annotations

import numpy as np
import pytest

import mocapflow.stages.skin.merge as cm
from mocapflow.stages.skin.surface import build_marker_surface

F = 20
T = np.arange(5, 13)


def grid(missing=(14, 15)):
    """``(X (F, 36, 3), surface)``: the grid translated over the frames, ``missing``
    NaN in ``T``."""
    gx, gy = np.meshgrid(np.arange(6) * 0.04, np.arange(6) * 0.04)
    ref = np.stack([gx.ravel(), gy.ravel(), 0.01 * np.sin(gx.ravel() * 20)], 1)
    X = np.repeat(ref[None], F, 0) + np.linspace(0, 0.1, F)[:, None, None]
    surf = build_marker_surface(ref, positions=X)
    truth = X.copy()
    for m in missing:
        X[T, m] = np.nan
    return X, truth, surf


def swap_case(delta=0.012, partner_shift=0.0):
    """Fragment 0 is marker 15, fragment 1 marker 14 (``partner_shift`` along y off it).
    Marker 14's prediction lies ``delta`` from fragment 0 towards 14 (off by
    ``0.04 - delta``, as where the neighbourhood bends); marker 15's is 50 mm off (z):
    no rival to the ambiguity test (more than 3 δ), and fragment 1 is more than ε₁
    from 14's prediction (no rival fragment)."""
    X, truth, surf = grid()
    frags = np.full((F, 2, 3), np.nan)
    frags[T, 0] = truth[T, 15]
    frags[T, 1] = truth[T, 14] + [0, partner_shift, 0]
    pred = np.full_like(X, np.nan)
    pred[T, 14] = truth[T, 15] - [delta, 0, 0]
    pred[T, 15] = truth[T, 15] + [0, 0, 0.05]
    return cm.merge_fragments(X, frags, surf, predictions=pred, max_break=0,
                              mean_tolerance=1.0, near_ratio=cm.AMBIGUITY_RATIO)


def test_grid_geometry():
    X, _, surf = grid()
    dbar = np.fmin(surf.mean_distance, cm.nearest_marker_distance(surf.reference))
    assert dbar[14] == pytest.approx(0.04, rel=0.05)  # ε₁ = 20 mm
    assert np.linalg.norm(surf.reference[15] - surf.reference[14]) == pytest.approx(0.0401,
                                                                                     abs=1e-4)


@pytest.mark.parametrize("delta", [0.0105, 0.012, 0.016])
def test_fragment_of_a_near_marker_with_the_chosen_one_seen_swapped_is_ambiguous(
        delta, monkeypatch):
    """Fragment 0 (marker 15) is ``delta`` from 14's prediction, 40.1 mm < 4 δ from 14;
    fragment 1 lies where 14 would be were fragment 0 marker 15 (the grid moves
    rigidly; the rotation of 14's neighbours is a little off, 15's prediction 50 mm
    off among them: within ε₁), and no free marker other than 14 and 15 could be it."""
    _, assigned, rep = swap_case(delta)
    assert assigned.tolist() == [-1, -1]
    why = next(r["reason"] for r in rep["rejections"] if r["fragment"] == "*1")
    assert why.startswith(f"ambiguous: M014 at {delta * 1000:.1f} mm, or M015 with M014 the "
                          "fragment *2 ("), why
    conflict = rep["conflicts"][0]
    assert conflict["labels"] == ["M014", "M015"] and conflict["fragments"] == ["*2"]
    assert conflict["mean_mm"] == [pytest.approx(delta * 1000, abs=1e-6)]
    assert 0 < conflict["swap_mm"] < 20.0
    # judged without the swap test (before it): the wrong merge
    monkeypatch.setattr(cm, "_swap_rival", lambda *a, **k: a[4])
    assert swap_case(delta)[1].tolist() == [14, -1]


@pytest.mark.parametrize("delta, partner_shift, merged_mm", [
    (0.0095, 0.0, 9.5),    # 40.1 mm >= 4 δ: had it been 15, 14's prediction is off >= 3 δ
    (0.012, 0.04, 12.0),   # fragment 1 is 40 mm (> ε₁) off where the swap puts 14
])
def test_merge_clear_of_a_swap_still_merges(delta, partner_shift, merged_mm):
    _, assigned, rep = swap_case(delta, partner_shift)
    assert assigned.tolist() == [14, -1]
    assert rep["merges"][0]["mean_mm"] == pytest.approx(merged_mm, abs=1e-6)


def test_partner_placed_by_the_chosen_labelling_is_no_swap():
    """A regular layout: fragment 0 is marker 14, 12 mm from its prediction (off towards
    15); fragment 1 is marker 13, 40 mm on the other side, where the swap with 15 would
    put 14 — but 13 is missing too, and the chosen labelling puts 13 there as well
    (at 0 mm, not 3 times farther): no ambiguity, 14 merges."""
    X, truth, surf = grid(missing=(13, 14, 15))
    frags = np.full((F, 2, 3), np.nan)
    frags[T, 0] = truth[T, 14]
    frags[T, 1] = truth[T, 13]
    pred = np.full_like(X, np.nan)
    pred[T, 14] = truth[T, 14] + [0.012, 0, 0]
    pred[T, 15] = truth[T, 15] + [0, 0, 0.05]
    pred[T, 13] = truth[T, 13] + [0, 0, 0.05]
    _, assigned, rep = cm.merge_fragments(X, frags, surf, predictions=pred, max_break=0,
                                          mean_tolerance=1.0, near_ratio=cm.AMBIGUITY_RATIO)
    assert assigned[0] == 14
    assert rep["merges"][0]["mean_mm"] == pytest.approx(12.0, abs=1e-6)
    # marker 13 seen there: fragment 1 can only be 14, the swap refuses the merge
    X[T, 13] = truth[T, 13]
    _, assigned, rep = cm.merge_fragments(X, frags, surf, predictions=pred, max_break=0,
                                          mean_tolerance=1.0, near_ratio=cm.AMBIGUITY_RATIO)
    assert assigned[0] == -1
    assert rep["rejections"][0]["reason"].startswith("ambiguous: M014 at 12.0 mm, or M015")
