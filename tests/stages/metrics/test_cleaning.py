"""Marker-cleaning scores: merges against the true fragment map, region errors."""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.stages.metrics.cleaning import region_errors, score_merges


def test_scoring_helpers():
    merges = [{"fragment": "*1", "label": "A"}, {"fragment": "*2", "label": "A"},
              {"fragment": "*3", "label": "B"}]
    sc = score_merges(merges, ["*1", "*2", "*3", "*4"], np.array([0, 1, -1, 1]), ["A", "B"])
    assert sc["wrong"] == 2 and sc["ghosts_merged"] == 1 and sc["missed"] == 1
    truth = np.zeros((2, 2, 3))
    est = truth.copy()
    est[0, 0, 0] = 0.01
    est[1, 1] = np.nan
    mask = np.array([[True, False], [False, True]])
    out = region_errors(est, truth, mask, np.array([0, 0]), np.array([0.05, 0.05]))
    assert out["abdomen"]["max"] == pytest.approx(0.2) and out["abdomen"]["unfilled"] == 1
    assert out["all"]["mean_mm"] == pytest.approx(10.0)
