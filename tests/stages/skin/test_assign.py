"""The joint assignment of the fragments left against the filled trajectories
(:mod:`mocapflow.stages.skin.assign`), on cases with known answers.

* :func:`~mocapflow.stages.skin.assign._exact_gap_jumps`: a marker moving 10 mm a frame,
  its gap exactly the fragment's frames, the fragment's ends 3 mm and 4 mm off the
  trajectory extrapolated over one frame: jump 4 mm; a gap not exactly the
  fragment's frames: NaN; a gap reaching the capture's start: its one end counts;
* :func:`~mocapflow.stages.skin.assign._decide` on two overlapping fragments: the
  other labelling costing 3.3x the chosen one merges, 2.5x is ambiguous, a marker
  taken by a closer fragment leaves the fragment unmerged;
* :func:`~mocapflow.stages.skin.assign.assign_fragments` on the 6x6 grid of
  ``test_clean_merge`` (ε₁ about 20 mm): the fragment that fills marker 15's gap
  exactly merges into it by continuity ("exact gap") when 15's estimate is within
  ε₁, into the wrong marker 14 ("alone") when 15's estimate is 30 mm off, and not
  at all when it is 22 mm off with 14's 8 mm off (2.75x, within the ratio 3);
* the merge rounds do not import the assignment (one-way imports).
"""

from __future__ import annotations

import ast
import importlib

import numpy as np
import pytest

from mocapflow.stages.skin import assign as ca
from tests.stages.skin.test_clean_merge import grid_case


def test_exact_gap_jumps_extrapolate_over_one_frame():
    F = 10
    X = np.zeros((F, 2, 3))
    X[:, :, 0] = 0.01 * np.arange(F)[:, None]  # 10 mm a frame along x
    avail = np.ones((F, 2), dtype=bool)
    T = np.arange(4, 7)
    avail[T, 0] = False
    avail[3:7, 1] = False  # marker 1's gap is longer than the fragment
    frag = X[T, 0].copy()
    frag[0, 1] += 0.003
    frag[-1, 2] += 0.004
    jumps = ca._exact_gap_jumps(X, avail, frag, T, np.array([0, 1]))
    assert jumps[0] == pytest.approx(0.004, abs=1e-12)
    assert np.isnan(jumps[1])
    # a gap from the capture's start: the end after it alone
    avail0 = np.ones((F, 1), dtype=bool)
    avail0[:3, 0] = False
    head = X[:3, 0].copy()
    head[-1, 1] += 0.005
    jumps = ca._exact_gap_jumps(X[:, :1], avail0, head, np.arange(3), np.array([0]))
    assert jumps[0] == pytest.approx(0.005, abs=1e-12)


def candidates(markers, costs, ok=None):
    cost = np.asarray(costs, dtype=float)
    ok = np.ones(len(cost), dtype=bool) if ok is None else np.asarray(ok)
    return ca._Candidates(np.asarray(markers), cost, ok, cost, cost, cost)


@pytest.mark.parametrize(("cost_u1", "expected"), [(0.25, (0, -1)), (0.4, (0, 1))])
def test_decide_refuses_a_labelling_within_the_ratio(cost_u1, expected):
    """Fragment 0: marker 0 at cost 0.2, marker 1 at 0.5; fragment 1: marker 1.  The
    other labelling (0 on marker 1, 1 unmerged at cost 1) costs 1.5 against
    0.2 + cost_u1: 3.3x with 0.25 (merges), 2.5x with 0.4 (ambiguous, rival marker 1)."""
    cand = {0: candidates([0, 1], [0.2, 0.5]), 1: candidates([1], [cost_u1])}
    assert ca._decide([0, 1], cand, ca.ASSIGNMENT_RATIO) == expected


def test_decide_leaves_a_fragment_whose_marker_a_closer_one_takes():
    cand = {0: candidates([0], [0.5]), 1: candidates([0], [0.1])}
    assert ca._decide([0, 1], cand, ca.ASSIGNMENT_RATIO) is None


@pytest.mark.parametrize(("offset_true", "offset_wrong", "marker", "how"), [
    (0.018, 0.004, 15, "exact gap"),
    (0.030, 0.004, 14, "alone"),
    (0.022, 0.008, -1, None),
])
def test_assign_fragments_on_the_grid(offset_true, offset_wrong, marker, how):
    X, frags, surf, _, estimates = grid_case(offset_true, offset_wrong)
    out, assigned, rep = ca.assign_fragments(X, frags, surf, estimates)
    assert assigned[0] == marker
    if marker >= 0:
        assert rep["merges"][0]["depth"] == how
        T = np.arange(5, 13)
        np.testing.assert_array_equal(out[T, marker], frags[T, 0])
    else:
        assert rep["rejections"][0]["reason"].startswith("ambiguous assignment: M")
        assert len(rep["conflicts"]) == 1


def test_merge_rounds_do_not_import_the_assignment():
    def skin_imports(name):
        path = importlib.import_module(f"mocapflow.stages.skin.{name}").__file__
        tree = ast.parse(open(path, encoding="utf-8").read())
        return {n.module.rsplit(".", 1)[1] for n in ast.walk(tree)
                if isinstance(n, ast.ImportFrom)
                and (n.module or "").startswith("mocapflow.stages.skin.")}

    assert "merge" in skin_imports("assign")
    assert "assign" not in skin_imports("merge")
    assert "assign" in skin_imports("clean")
