"""Variation cycle cutting: heel strikes against ground truth, the period cutter."""

import numpy as np
import pytest

from mocapflow.stages.variation.cycles import (
    autocorrelation_period,
    cut_cycles,
    heel_strikes,
    period_cuts,
)
from tests.stages.variation.conftest import positions


def test_heel_strikes_and_cycles_match_ground_truth(walk):
    events = np.array(walk.attrs["gait_events"]["left"]["heel_strike"])
    pos = positions(walk)
    hs = heel_strikes(pos, walk.skeleton.index("LeftFoot"), walk.rate) / walk.rate
    inside = events[(events > 0.1) & (events < 7.9)]
    # every true heel strike found within 3 frames (0.05 s), nothing spurious
    assert len(hs) == len(inside)
    assert np.abs(hs - inside).max() < 0.05
    cycles, rep = cut_cycles(walk)
    assert rep["method"] == "feet" and len(cycles) >= 5
    periods = np.array(walk.attrs["cycle_periods"])
    assert np.median([b - a for a, b in cycles]) / 60.0 == pytest.approx(
        np.median(periods), rel=0.1
    )


def test_period_cutter_on_generic_signal():
    t = np.arange(400)
    x = np.stack([np.sin(2 * np.pi * t / 40), np.cos(2 * np.pi * t / 40) ** 3], axis=1)
    assert autocorrelation_period(x) == 40
    cuts = period_cuts(x, 40)
    assert np.all(np.abs(np.diff(cuts) - 40) <= 1) and len(cuts) >= 9
    cycles, rep = cut_cycles(dofs=x, rate=40.0, method="period")
    assert rep["method"] == "period" and len(cycles) >= 8
    assert autocorrelation_period(np.random.default_rng(0).standard_normal((5, 2))) == 0
