"""Temporal variation as sampled time warps (Lau, Bar-Joseph & Kuffner 2009, §4, §6).

The paper aligns its input clips in time and samples the time warp along with
the poses.  Here the transition network is learned on the unaligned cycles, so
the timing of a variant is what its second-order dynamics give: on the shared
walks 0.3-0.5 x the inputs' (DTW warp-slope std, METRICS.md §2), because every
DOF follows the cycle phase, which runs at a nearly constant speed.  The missing
part is added back as a time warp per variant:

learned (:func:`time_warps`)
    Each input cycle is aligned by dynamic time warping to the reference cycle
    (the one of median length; standardised DOFs, the cycles' common start and
    end events as the path's ends).  The warp's local speed, smoothed over
    :data:`WARP_SMOOTH`, is kept as a log per reference frame whose mean is the log
    of the cycle's length over the reference's, minus the cycles' mean: a ``(C, G)``
    table.
sampled (:func:`sample_time_warp`)
    A Gaussian with the table's covariance across cycles, ``ℓ = σ · gᵀ L / √(C − 1)``
    with ``g`` standard normal (``σ = 0``: no warp), resampled to the variant's
    length.  A whole-cycle variant is played at it, so its length changes as
    the input cycles' lengths differ (the network's own cycle lengths vary ~4x
    less: the per-frame noise averages out over a cycle, while an input cycle
    keeps its pace).  A variant of a given length (``keep_length``) keeps it
    and its speed at both ends: the log speed is eased to zero over
    :data:`TAPER` of each end and its mean taken out.
applied (:func:`apply_time_warp`)
    Every DOF is interpolated at the warped times, per-frame rates (the root's
    heading rate and heading-frame velocity) as values too: a cycle played
    slower keeps its per-frame speed and so takes a longer stride, as the
    demo's procedural walk does (scaled by the warp's speed, the forward
    velocity left the inputs' narrow range by 2-3 times that range).

Departure from the paper (stated): the warp is a Gaussian over the inputs'
warps (rank ``C − 1``) drawn once per variant, not a DOF of the network, and it
applies to the ``sample`` stage's variants, not to loops (their cycles are one
stream, whose timing is the network's: warped, the eased ends added jerk at the
joins, 1.53 -> 1.63 x the inputs' p99 after IK) nor to :class:`~.sample.Sampler`
streams (crowds).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq

from mocapflow.stages.metrics.novelty import dtw

__all__ = ["TAPER", "WARP_SMOOTH", "apply_time_warp", "sample_time_warp", "time_warps"]

WARP_SMOOTH = 1.0 / 12.0
"""Seconds: half-width of the moving average of the inputs' warps (5 frames at 60 fps, the
novelty metric's smoothing of the warp slope)."""

TAPER = 0.1
"""Fraction of a variant at each end over which the sampled warp's log speed eases to 0."""

_MIN_SPEED = 0.2  # a warp's local speed is kept >= this fraction of its mean


def time_warps(
    trajectories: list[np.ndarray], *, rate: float, smooth: float = WARP_SMOOTH
) -> np.ndarray | None:
    """Log speed deviations of the input cycles' time warps onto a reference cycle.

    Parameters
    ----------
    trajectories : list of (T_c, D) float ndarray
        The input cycles (each starting at the same event), without phase DOFs.
    rate : float
        Frames per second.
    smooth : float
        Seconds; half-width of the moving average of each warp.

    Returns
    -------
    (C, G) float ndarray or None
        Per cycle, per frame of the reference cycle (``G`` frames), the log of
        the warp's local speed (cycle frames per reference frame), its mean set
        to the log of the cycle's length over the reference's, minus the mean
        over cycles;
        ``None`` for fewer than 2 cycles or a reference shorter than 4 frames.
    """
    lengths = np.array([len(t) for t in trajectories])
    if len(lengths) < 2:
        return None
    ref = int(np.argsort(lengths, kind="stable")[(len(lengths) - 1) // 2])
    G = int(lengths[ref])
    if G < 4 or lengths.min() < 2:
        return None
    allx = np.concatenate(trajectories, axis=0)
    mean, std = allx.mean(axis=0), allx.std(axis=0)
    std = np.where(std > 0, std, 1.0)
    zr = (trajectories[ref] - mean) / std
    half = max(1, int(round(smooth * rate)))
    box = np.ones(2 * half + 1) / (2 * half + 1)
    out = np.zeros((len(trajectories), G))
    for c, t in enumerate(trajectories):
        _, path = dtw(zr, (t - mean) / std)
        i, j = path[:, 0], path[:, 1]
        jbar = np.bincount(i, weights=j, minlength=G) / np.maximum(np.bincount(i, minlength=G), 1)
        if G > 2 * half + 1:
            jbar = np.convolve(np.pad(jbar, half, mode="reflect", reflect_type="odd"), box,
                               "valid")
        speed = np.gradient(jbar)
        speed = np.maximum(speed / speed.mean(), _MIN_SPEED)
        out[c] = np.log(speed) - np.log(speed).mean() + math.log(len(t) / G)
    return out - out.mean(axis=0)


def _taper(length: int, taper: float) -> np.ndarray:
    """``(length,)`` window: 0 at both ends, rising as ``sin²`` over ``taper`` of the length."""
    u = np.linspace(0.0, 1.0, length)
    r = np.clip(np.minimum(u, 1.0 - u) / max(taper, 1e-9), 0.0, 1.0)
    return np.sin(0.5 * np.pi * r) ** 2


def sample_time_warp(
    deviations: np.ndarray,
    rng: np.random.Generator,
    *,
    length: int,
    sigma: float = 1.0,
    keep_length: bool = False,
    taper: float = TAPER,
) -> np.ndarray:
    """A time warp drawn with the covariance of the inputs' warps.

    Parameters
    ----------
    deviations : (C, G) float ndarray
        From :func:`time_warps`.
    rng : numpy.random.Generator
        Draws ``C`` standard normals.
    length : int
        Frames of the variant (≥ 2).
    sigma : float
        Scale of the warp's log speed (0: the identity).
    keep_length : bool
        Keep the variant's length and its speed at both ends: the log speed
        eases to 0 over ``taper`` of each end and its mean is taken out.
        ``False``: the warp also changes the length by the drawn overall
        speed, as the input cycles' lengths differ.
    taper : float
        Fraction of the variant at each end where the log speed eases to 0
        (``keep_length``).

    Returns
    -------
    (L,) float ndarray
        Increasing source times ``τ`` (frames) with ``τ[0] = 0`` and
        ``τ[-1] = length − 1``; the warped variant's frame ``t`` is the
        variant at ``τ[t]``; ``L = length`` with ``keep_length``.
    """
    C, G = deviations.shape
    g = rng.standard_normal(C)
    ell = sigma * (g @ deviations) / math.sqrt(max(C - 1, 1))
    ell = np.interp(np.linspace(0.0, 1.0, length), np.linspace(0.0, 1.0, G), ell)
    ell = np.clip(ell, math.log(_MIN_SPEED), -math.log(_MIN_SPEED))
    src = np.arange(length, dtype=np.float64)
    if length < 3 or not np.any(ell):
        return src
    if keep_length:
        w = _taper(length, taper)

        def excess(shift: float) -> float:  # mean rate over the interior steps minus 1
            return float(np.mean(np.exp(w * (ell - shift))[1:]) - 1.0)

        lo, hi = float(ell.min()) - 1.0, float(ell.max()) + 1.0
        ell = w * (ell - brentq(excess, lo, hi, xtol=1e-12))
    # output frames per source frame along the variant, accumulated: output time of each
    # source frame, then inverted at whole output frames
    r = np.exp(ell)
    out_t = np.concatenate([[0.0], np.cumsum(0.5 * (r[1:] + r[:-1]))])
    # the length from the mean log rate (log-normal, as the inputs' cycle lengths), not the
    # mean rate, which large local warps would lengthen
    n_out = length if keep_length else max(2, int(round((length - 1) * math.exp(ell.mean()))) + 1)
    out_t *= (n_out - 1) / out_t[-1]
    return np.interp(np.arange(n_out, dtype=np.float64), out_t, src)


def apply_time_warp(x: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """A trajectory played at warped times (every DOF interpolated linearly).

    Parameters
    ----------
    x : (T, D) float ndarray
        DOF values per frame.
    tau : (L,) float ndarray
        Source times (frames, within ``[0, T − 1]``) from :func:`sample_time_warp`.

    Returns
    -------
    (L, D) float ndarray
    """
    T = len(x)
    i0 = np.clip(np.floor(tau).astype(np.int64), 0, max(T - 2, 0))
    f = (tau - i0)[:, None]
    i1 = np.minimum(i0 + 1, T - 1)
    return (1.0 - f) * x[i0] + f * x[i1]
