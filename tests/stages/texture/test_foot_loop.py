"""Foot corrections on a loop are periodic (the loop's wrap stays an ordinary step)."""

from __future__ import annotations

import numpy as np

from mocapflow.stages.texture.root import foot_corrections


def _sliding_loop(L=120):
    """One toe that slides 1 cm per frame during a stance spanning the wrap
    (frames 100..119 and 0..19) and should stand still there."""
    contact = np.zeros((L, 1), dtype=bool)
    contact[:20] = contact[100:] = True
    x = np.zeros((L, 1, 2))
    x[:, 0, 0] = np.cumsum(np.where(contact[:, 0], 0.01, 0.0))
    x[:, 0, 0] -= x[:, 0, 0].mean()
    x[0, 0, 0] = x[-1, 0, 0] + 0.01  # the wrap continues the slide
    x[:20, 0, 0] = x[0, 0, 0] + 0.01 * np.arange(20)
    return x, np.zeros_like(x), contact


def test_cyclic_corrections_stop_the_slide_across_the_wrap():
    x, step, contact = _sliding_loop()
    def steps(e):
        y = (x + e)[:, 0, 0]
        d = np.abs(np.diff(np.r_[y, y[0]]))  # d[-1]: the wrap, frame 119 -> 0
        return d[-1], max(d[100:119].max(), d[:19].max())

    wrap, inside = steps(foot_corrections(x, step, contact, cyclic=True))
    assert wrap <= 1.05 * inside and inside < 0.0095, (wrap, inside)  # input: 1 cm a frame
    # on an open interval the stance is cut at the wrap: the ends are corrected
    # apart and the wrap jumps (16 cm here)
    wrap_open, inside_open = steps(foot_corrections(x, step, contact))
    assert wrap_open > 5 * inside_open, (wrap_open, inside_open)


def test_cyclic_corrections_are_zero_without_slide_and_keep_fixed_frames():
    x, step, contact = _sliding_loop()
    still = np.zeros_like(x)
    assert np.abs(foot_corrections(still, step, contact, cyclic=True)).max() < 1e-12
    fixed = np.zeros(len(x), dtype=bool)
    fixed[5] = True
    e = foot_corrections(x, step, contact, cyclic=True, fixed=fixed)
    assert np.abs(e[5]).max() < 1e-4
