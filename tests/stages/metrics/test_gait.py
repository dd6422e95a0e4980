"""Gait metrics against synthetic ground truth (sine hips, frozen windows, known jumps)."""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.stages.metrics.gait import (
    cadence,
    channel_range,
    clip_cadence,
    frozen_threshold,
    frozen_windows,
    gait_cycles,
    hip_flexion_columns,
    join_jerk_p99,
    join_mask,
    range_excess,
    swing_hysteresis,
    window_ranges,
)
from mocapflow.stages.metrics.quality import jerk_per_frame
from mocapflow.stages.motion.kinematics import motion_positions
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.variation.dofs import rotation_channels

RATE = 60.0


def _sine(freq, seconds=10.0, amp=0.4, phase=0.3, trend=0.0):
    t = np.arange(int(seconds * RATE)) / RATE
    return amp * np.sin(2 * np.pi * freq * t + phase) + trend * t


@pytest.mark.parametrize("freq", [0.7, 1.0, 1.37])
def test_cadence_of_a_sine_hip(freq):
    c, n = cadence(_sine(freq, trend=0.05), RATE, hysteresis=0.1)
    assert c == pytest.approx(freq, rel=0.01)
    assert abs(n - 10 * freq) <= 1


def test_hysteresis_ignores_jitter_and_a_frozen_hip():
    rng = np.random.default_rng(0)
    jitter = 0.02 * rng.standard_normal(600)  # crosses zero ~ every other frame
    assert gait_cycles(jitter, hysteresis=0.1).size == 0
    assert gait_cycles(jitter, hysteresis=0.0).size > 100  # the hysteresis is what stops it
    x = _sine(1.0)
    x[120:480] = x[120]  # frozen for 6 s: cycles only in the first 2 and last 2 s
    c = gait_cycles(x, hysteresis=0.1)  # (the start, above +h, is no crossing)
    assert c.size == 3 and c[0] < 120 and np.all(c[1:] > 480)
    assert np.all(np.abs(c - 60 * np.round(c / 60)) <= 3)  # one per period of 60 frames
    assert cadence(np.zeros(600), RATE, hysteresis=0.1) == (0.0, 0)


def test_gait_cycles_rejects_several_columns():
    with pytest.raises(ValueError, match="one signal"):
        gait_cycles(np.zeros((10, 2)), hysteresis=0.1)


def test_swing_hysteresis_is_a_fraction_of_the_median_range():
    clips = [np.stack([a * np.sin(np.linspace(0, 2 * np.pi, 61)), 2 * a * np.ones(61)], axis=1)
             for a in (0.3, 0.5, 0.4)]
    clips[0][5, 1] += 1.0  # a range of 1.0 in one clip only: the median ignores it
    np.testing.assert_allclose(swing_hysteresis(clips), [0.2 * 0.8, 0.0], atol=1e-9)
    with pytest.raises(ValueError):
        swing_hysteresis([])


def test_clip_cadence():
    assert clip_cadence([60, 60, 66, 54], RATE) == pytest.approx(1.0)
    with pytest.raises(ValueError):
        clip_cadence([], RATE)


def test_hip_flexion_columns_pick_the_largest_range_per_side():
    names = ["Hips:swing_X", "LHipJoint:Zrotation", "LeftHip:Zrotation", "LeftHip:Xrotation",
             "RightUpLeg:Xrotation", "RightUpLeg:Yrotation", "LeftKnee:Xrotation"]
    x = np.zeros((100, len(names)))
    amp = [5.0, 0.01, 0.2, 0.9, 0.7, 0.1, 2.0]  # the root and the knee move most: not hips
    x[:] = np.sin(np.linspace(0, 6, 100))[:, None] * amp
    assert hip_flexion_columns(names, [x[:50], x[50:]]) == {"left": 3, "right": 4}
    with pytest.raises(ValueError, match="no left or right hip"):
        hip_flexion_columns(["Hips:swing_X", "LeftKnee:Xrotation"], [x[:, :2]])


def test_frozen_windows_find_a_known_freeze():
    inputs = [_sine(1.0, seconds=1.0, amp=0.4, phase=p) for p in (0.0, 1.0, 2.0)]
    w = 30
    thr = frozen_threshold(inputs, w)
    # the narrowest window of 30 frames (29 steps of 2π/60) of a 1 Hz sine of amplitude
    # 0.4 is centred on a peak: it spans 0.4 · (1 − cos(29π/60)); half of it
    assert thr == pytest.approx(0.5 * 0.4 * (1 - np.cos(29 * np.pi / 60)), rel=0.01)
    x = _sine(1.0, amp=0.4)
    x[150:330] = 0.1 + 0.01 * np.sin(np.arange(180))  # frozen from 2.5 s to 5.5 s
    f = frozen_windows(x, thr, w)
    assert f.shape == (20,)
    assert np.flatnonzero(f).tolist() == list(range(5, 11))
    # two columns: a window is frozen when either hip is
    two = np.stack([_sine(1.0), x], axis=1)
    assert frozen_windows(two, np.array([thr, thr]), w).sum() == 6
    assert not frozen_windows(_sine(1.0), thr, w).any()


def test_window_ranges_shapes_and_errors():
    x = np.arange(10.0)
    assert window_ranges(x, 4).tolist() == [3.0, 3.0]
    assert window_ranges(x, 4, step=1).shape == (7,)
    assert window_ranges(x, 20).shape == (0,)
    with pytest.raises(ValueError):
        window_ranges(x, 0)
    with pytest.raises(ValueError, match="no input clip"):
        frozen_threshold([x[:3]], 4)


def test_range_excess_known_overshoot_and_wrap():
    low, high = np.array([-0.5, 0.0, 3.0]), np.array([0.5, 1.0, 3.1])
    mean = np.array([0.0, 0.5, 3.05])
    x = np.zeros((50, 3))
    x[:, 1] = 0.5
    x[10, 0] = 0.8  # 0.3 beyond the top
    x[20, 1] = -0.2  # 0.2 below the bottom
    x[:, 2] = 3.05 - 2 * np.pi  # the same angle on another branch: no excess after the shift
    ex = range_excess(x, low, high, mean)
    np.testing.assert_allclose(ex, [0.3, 0.2, 0.0], atol=1e-12)
    assert range_excess(x, low, high)[2] > 6  # without the shift it is off by 2π
    with pytest.raises(ValueError, match="do not match"):
        range_excess(x[:, :2], low, high)


def test_range_excess_takes_the_best_turn_when_the_inputs_span_more_than_one():
    """Inputs spanning more than 2π (a near-gimbal joint): the shift nearest the mean
    leaves a track 1 rad out although the track shifted by a turn lies inside."""
    low, high, mean = np.array([-5.0]), np.array([4.6]), np.array([-0.2])
    x = np.linspace(-6.0, -2.0, 40)[:, None]  # mean -4: nearest turn is 0, 1 rad below
    assert range_excess(x, low, high, mean)[0] == 0.0  # +2π: [0.28, 4.28] lies inside
    assert range_excess(x, low, high)[0] == pytest.approx(1.0)
    y = np.linspace(-6.0, 3.0, 40)[:, None]  # 9 rad: no turn fits; the smaller excess
    assert range_excess(y, low, high, mean)[0] == pytest.approx(1.0)


def test_rotation_channels_of_a_walk_exclude_the_root_and_match_the_range():
    m = procedural_walk(120, rate=RATE, seed=1)
    ang, names = rotation_channels(m)
    root = m.skeleton.names[0]
    assert ang.shape == (120, len(names)) and len(names) > 0
    assert all(n.endswith("rotation") and not n.startswith(root + ":") for n in names)
    lo, hi, mu = channel_range([ang[:60], ang[60:]])
    assert np.all(range_excess(ang, lo, hi, mu) == 0)
    bent = ang.copy()
    bent[30, 5] = hi[5] + 0.25
    ex = range_excess(bent, lo, hi, mu)
    assert ex[5] == pytest.approx(0.25) and np.count_nonzero(ex) == 1


def test_join_jerk_sees_a_known_jump():
    m = procedural_walk(180, rate=RATE, seed=2)
    p = motion_positions(m)
    lengths = [60, 60, 60]
    mask = join_mask(lengths, radius=3)
    assert np.flatnonzero(mask).tolist() == list(range(56, 64)) + list(range(116, 124))
    smooth = join_jerk_p99(p, lengths, RATE)
    jumped = p.copy()
    jumped[120:] += np.array([0.0, 0.0, 0.05])  # every joint jumps 5 cm at the second join
    # the third difference of a 5 cm step s between frames 119 and 120: s, −2s, s at
    # frames 118, 119, 120 (times 60³ m/s³), on top of the walk's own jerk
    step = 0.05 * RATE**3
    j = jerk_per_frame(jumped, RATE)
    np.testing.assert_allclose(j[118:121], [step, 2 * step, step], rtol=0.05)
    assert join_jerk_p99(jumped, lengths, RATE) > step > 10 * smooth
    # a jump away from the joins does not count at them
    away = p.copy()
    away[90:] += np.array([0.0, 0.0, 0.05])
    assert join_jerk_p99(away, lengths, RATE) == pytest.approx(smooth)
    with pytest.raises(ValueError, match="two chained"):
        join_jerk_p99(p, [180], RATE)
    with pytest.raises(ValueError, match="frames"):
        join_jerk_p99(p, [60, 60], RATE)
