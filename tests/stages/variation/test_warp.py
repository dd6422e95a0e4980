"""Sampled time warps (issue 17: warp-slope std of the walks' variants 0.3-0.5 x the inputs').

Synthetic cycles with known warps: the learned table recovers them, the sampled warps
have their spread, fix the ends (a given length: also the speed there) or change the
length with the inputs' spread (whole cycles), and a warped trajectory is interpolated.
"""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.stages.variation.warp import apply_time_warp, sample_time_warp, time_warps

T0, D = 60, 4


def _cycles(n=8, amp=0.25, seed=0):
    """``n`` cycles of one shape played at known warps: speed ``1 + a_c sin(2πu + p_c)``."""
    rng = np.random.default_rng(seed)
    u = np.arange(T0) / T0
    ph = np.linspace(0, np.pi, D, endpoint=False)
    out, speeds = [], []
    for _ in range(n):
        a, p = rng.uniform(-amp, amp), rng.uniform(0, 2 * np.pi)
        s = u + a * (np.cos(p) - np.cos(2 * np.pi * u + p)) / (2 * np.pi)  # s' = 1 + a sin
        out.append(np.sin(2 * np.pi * s[:, None] + ph) + 0.3 * np.sin(4 * np.pi * s[:, None]))
        speeds.append(1 + a * np.sin(2 * np.pi * u + p))
    return out, np.array(speeds)


def test_time_warps_recover_the_known_warps():
    cycles, speeds = _cycles()
    W = time_warps(cycles, rate=60.0)
    assert W.shape == (8, T0)
    assert np.allclose(W.mean(axis=0), 0.0)
    # the reference (median-length: all 60, the 4th) plays at its own speed, so each row
    # is the log of the cycle's speed over the reference's, about the mean
    true = -np.log(speeds)  # the warp maps reference frames to cycle frames: 1 / speed
    true -= true.mean(axis=0)
    inner = slice(6, T0 - 6)  # DTW pins both ends
    r = np.corrcoef(W[:, inner].ravel(), true[:, inner].ravel())[0, 1]
    assert r > 0.9, r  # measured 0.95
    ratio = W[:, inner].std() / true[:, inner].std()
    assert 0.6 < ratio < 1.4, ratio  # measured 0.97
    # fewer than 2 cycles: no table
    assert time_warps(cycles[:1], rate=60.0) is None


def test_sampled_warps_have_the_inputs_spread_and_fixed_ends():
    cycles, _ = _cycles()
    W = time_warps(cycles, rate=60.0)
    rng = np.random.default_rng(1)
    taus = np.stack([sample_time_warp(W, rng, length=T0, keep_length=True)
                     for _ in range(400)])
    assert np.all(taus[:, 0] == 0.0) and np.allclose(taus[:, -1], T0 - 1)
    speed = np.diff(taus, axis=1)
    assert np.all(speed > 0)
    # the speed eases to 1 at both ends (a variant of a given length)
    assert np.abs(speed[:, [0, -1]] - 1).max() < 0.02  # measured 0.013
    # in the middle the log speed has the inputs' spread about their mean (Gaussian with
    # the table's covariance): ratio 1 within sampling error (measured 0.97)
    mid = slice(15, T0 - 15)
    got = np.log(speed[:, mid]).std(axis=0).mean()
    want = W[:, mid].std(axis=0, ddof=1).mean()
    assert got / want == pytest.approx(1.0, abs=0.15)
    # sigma scales it; sigma 0 is the identity
    t2 = sample_time_warp(W, np.random.default_rng(1), length=T0, sigma=2.0, keep_length=True)
    t1 = sample_time_warp(W, np.random.default_rng(1), length=T0, sigma=1.0, keep_length=True)
    assert np.abs(t2 - np.arange(T0)).max() > 1.5 * np.abs(t1 - np.arange(T0)).max()
    np.testing.assert_array_equal(sample_time_warp(W, rng, length=T0, sigma=0.0),
                                  np.arange(T0))


def test_whole_cycle_warps_give_the_inputs_spread_of_lengths():
    """Input cycles of different lengths (and so paces): a warp drawn for a whole-cycle
    variant changes its length with the inputs' spread (the network's own cycle lengths
    vary ~4x less than the inputs' on the walks)."""
    rng = np.random.default_rng(3)
    u = np.arange(T0) / T0
    base = np.stack([np.sin(2 * np.pi * u), np.cos(4 * np.pi * u)], axis=1)
    lengths = rng.integers(48, 73, 10)
    cycles = [np.stack([np.interp(np.arange(n) * T0 / n, np.arange(T0), b) for b in base.T],
                       axis=1) for n in lengths]
    W = time_warps(cycles, rate=60.0)
    got = [len(sample_time_warp(W, rng, length=T0)) for _ in range(400)]
    ratio = np.std(np.log(got)) / np.std(np.log(lengths), ddof=1)
    assert 0.8 < ratio < 1.25, ratio  # measured RATIO
    assert abs(np.median(got) - T0) <= 2
    tau = sample_time_warp(W, rng, length=T0)
    assert tau[0] == 0 and tau[-1] == pytest.approx(T0 - 1) and np.all(np.diff(tau) > 0)


def test_apply_time_warp_interpolates_every_dof():
    """Rates (the root's velocity) are interpolated as values, not scaled by the warp's
    speed: scaled, the demo walk's forward velocity left the inputs' narrow range by 2-3
    times that range."""
    t = np.arange(50.0)
    x = np.stack([np.sin(t / 5), 0.02 + 0.001 * np.cos(t / 3)], axis=1)  # a pose, a velocity
    tau = 49 * (t / 49) ** 1.3  # slow start, fast end
    y = apply_time_warp(x, tau)
    for d in range(2):
        np.testing.assert_allclose(y[:, d], np.interp(tau, t, x[:, d]))
    assert y[:, 1].min() >= x[:, 1].min() and y[:, 1].max() <= x[:, 1].max()
    np.testing.assert_array_equal(apply_time_warp(x, t), x)  # identity
    assert apply_time_warp(x, np.linspace(0, 49, 61)).shape == (61, 2)  # another length
