"""Cutting a long cyclic take into cycles, the clips of the variation graph (Lau et al. 2009, §4).

The paper learns from a few similar clips; a single long take of a cyclic motion
(a walk) gives them once it is cut into cycles (:func:`cut_cycles`).

``feet``
    Gait cycles start at the heel strikes of the left foot
    (:func:`heel_strikes`: contact onsets, foot height in the lowest quarter of
    its range *and* horizontal speed below 30 % of its 90th percentile).
``period``
    The period of the summed autocorrelation of the standardised DOFs
    (:func:`autocorrelation_period`), with cuts placed at the frames most like a
    reference pose one period apart (:func:`period_cuts`).

Cycles of outlying duration or shape (start / stop of a take) are dropped.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from mocapflow.stages.motion.contacts import foot_joint, true_runs
from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.motion.kinematics import motion_positions
from mocapflow.stages.variation.clips import ClipError
from mocapflow.stages.variation.dofs import motion_to_dofs

__all__ = ["autocorrelation_period", "cut_cycles", "heel_strikes", "period_cuts"]


def heel_strikes(
    positions: np.ndarray,
    foot: int,
    rate: float,
    *,
    up: str = "y",
    height_fraction: float = 0.25,
    speed_fraction: float = 0.3,
    min_gap: float = 0.05,
) -> np.ndarray:
    """Frames where a foot comes into contact with the floor.

    Contact: the foot's height is in the lowest ``height_fraction`` of its
    5–95 % range and its horizontal speed is below ``speed_fraction`` of its
    90th percentile.  Contact runs separated by less than ``min_gap`` seconds
    are merged, runs shorter than ``min_gap`` dropped, and an onset counts
    only if the foot rose above the middle of its height range since the
    previous onset (a swing).

    Parameters
    ----------
    positions : (F, J, 3) float ndarray
        Joint world positions, metres.
    foot : int
        Joint index of the foot (ankle).
    rate : float
    up : {"y", "z"}
    height_fraction, speed_fraction, min_gap : float

    Returns
    -------
    (K,) int ndarray
        Contact onsets (frames), increasing; a contact already under way at
        frame 0 is not an onset.
    """
    u = "xyz".index(up.lower())
    p = np.asarray(positions, dtype=np.float64)[:, foot]
    F = len(p)
    if F < 3:
        return np.zeros(0, dtype=np.int64)
    h = p[:, u]
    lo, hi = np.percentile(h, [5, 95])
    low = h < lo + height_fraction * (hi - lo)
    hz = [a for a in range(3) if a != u]
    sp = np.linalg.norm(np.gradient(p[:, hz], axis=0), axis=1) * rate
    slow = sp < speed_fraction * np.percentile(sp, 90)
    contact = low & slow
    gap = max(1, int(round(min_gap * rate)))
    # close short gaps, then drop short runs
    for a, b in true_runs(~contact):
        if a > 0 and b < F and b - a < gap:
            contact[a:b] = True
    for a, b in true_runs(contact):
        if b - a < gap:
            contact[a:b] = False
    # an onset needs a real swing (foot above mid-range) since the previous one
    onsets: list[int] = []
    mid = lo + 0.5 * (hi - lo)
    for a, _ in true_runs(contact):
        if a == 0:
            continue
        if onsets and h[onsets[-1] : a].max() < mid:
            continue
        onsets.append(int(a))
    return np.array(onsets, dtype=np.int64)


def autocorrelation_period(dofs: np.ndarray, *, min_lag: int = 3) -> int:
    """Period (frames) of a multichannel signal from its summed autocorrelation.

    Parameters
    ----------
    dofs : (F, D) float ndarray
    min_lag : int
        Smallest period considered.

    Returns
    -------
    int
        The first autocorrelation peak (after the first drop below zero, in
        ``[min_lag, F // 2]``) that reaches 90 % of the highest; 0 when there
        is none.
    """
    x = np.asarray(dofs, dtype=np.float64)
    F = x.shape[0]
    s = x.std(axis=0)
    x = (x[:, s > 0] - x[:, s > 0].mean(axis=0)) / s[s > 0]
    if x.shape[1] == 0 or F < 2 * min_lag + 2:
        return 0
    n = 1 << int(np.ceil(np.log2(2 * F)))
    spec = np.fft.rfft(x, n=n, axis=0)
    r = np.fft.irfft((spec * spec.conj()).real, n=n, axis=0)[:F].sum(axis=1)
    r = r / (F - np.arange(F)) / (r[0] / F)
    half = F // 2
    below = np.flatnonzero(r[min_lag:half] < 0)
    if below.size == 0:
        return 0
    start = min_lag + below[0]
    if start >= half:
        return 0
    seg = r[start:half]
    # the first local maximum reaching 90 % of the highest one (not a multiple of it)
    peaks = [i for i in range(1, len(seg) - 1) if seg[i] >= seg[i - 1] and seg[i] >= seg[i + 1]]
    peaks = peaks or [int(np.argmax(seg))]
    top = max(seg[i] for i in peaks)
    if top <= 0:
        return 0
    return int(start + next(i for i in peaks if seg[i] >= 0.9 * top))


def period_cuts(dofs: np.ndarray, period: int, *, reference: int | None = None) -> np.ndarray:
    """Cut frames one period apart, each at the pose closest to a reference pose.

    Parameters
    ----------
    dofs : (F, D) float ndarray
    period : int
        Frames per cycle.
    reference : int, optional
        Reference frame (default the middle of the take).

    Returns
    -------
    (K,) int ndarray
        Increasing cut frames covering the take.
    """
    x = np.asarray(dofs, dtype=np.float64)
    F = x.shape[0]
    s = x.std(axis=0)
    s[s == 0] = 1.0
    z = (x - x.mean(axis=0)) / s
    r = F // 2 if reference is None else int(reference)
    dist = np.linalg.norm(z - z[r], axis=1)
    lo, hi = max(1, int(round(0.75 * period))), max(2, int(round(1.25 * period)))
    cuts = [r]
    c = r
    while c + lo < F:
        w = np.arange(c + lo, min(F, c + hi + 1))
        c = int(w[np.argmin(dist[w])])
        cuts.append(c)
    c = r
    while c - lo > 0:
        w = np.arange(max(0, c - hi), c - lo + 1)
        c = int(w[np.argmin(dist[w])])
        cuts.insert(0, c)
    return np.array(cuts, dtype=np.int64)


def _shape_outliers(dofs: np.ndarray, cuts: np.ndarray, factor: float) -> np.ndarray:
    """Keep-mask of cycles whose shape and duration are not outliers."""
    n = len(cuts) - 1
    if n < 3:
        return np.ones(n, dtype=bool)
    dur = np.diff(cuts).astype(float)
    med = np.median(dur)
    keep = (dur >= med / 1.5) & (dur <= med * 1.5)
    s = dofs.std(axis=0)
    s[s == 0] = 1.0
    grid = np.linspace(0.0, 1.0, 32)
    shapes = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        seg = (dofs[a:b] - dofs.mean(axis=0)) / s
        tt = np.linspace(0.0, 1.0, len(seg))
        shapes.append(np.stack([np.interp(grid, tt, seg[:, d]) for d in range(seg.shape[1])], 1))
    shapes = np.stack(shapes)
    ref = np.median(shapes[keep] if keep.sum() >= 2 else shapes, axis=0)
    dist = np.sqrt(((shapes - ref) ** 2).mean(axis=(1, 2)))
    mdist = np.median(dist[keep]) if keep.any() else np.median(dist)
    keep &= dist <= factor * max(mdist, 1e-12)
    return keep


def cut_cycles(
    motion: Motion | None = None,
    *,
    dofs: np.ndarray | None = None,
    rate: float | None = None,
    method: Literal["auto", "feet", "period"] = "auto",
    up: str = "y",
    outlier: float = 2.5,
) -> tuple[list[tuple[int, int]], dict[str, Any]]:
    """Cut a cyclic take into cycles.

    Parameters
    ----------
    motion : Motion, optional
        A take with feet (``feet`` method) — or pass ``dofs``.
    dofs : (F, D) float ndarray, optional
        Generic cyclic signal (``period`` method); computed from ``motion``
        when not given.
    rate : float, optional
        Frames per second (default ``motion.rate``).
    method : {"auto", "feet", "period"}
        ``auto``: heel strikes when the skeleton has a left foot and at least
        two cycles are found, else the autocorrelation period.
    up : {"y", "z"}
    outlier : float
        Cycles whose shape distance to the median cycle exceeds ``outlier``
        times the median distance (or whose duration is off by more than
        1.5×) are dropped.

    Returns
    -------
    cycles : list of (int, int)
        ``[start, stop)`` frame ranges of the kept cycles, in order.
    report : dict
        ``method``, ``cuts``, ``period`` (frames), ``dropped`` ranges.
    """
    if dofs is None:
        if motion is None:
            raise ClipError("cut_cycles needs a motion or a DOF matrix")
        dofs = motion_to_dofs(motion, up=up)[0]
    dofs = np.asarray(dofs, dtype=np.float64)
    rate = float(rate if rate is not None else (motion.rate if motion is not None else 1.0))
    used = None
    cuts = np.zeros(0, dtype=np.int64)
    if method in ("auto", "feet") and motion is not None:
        foot = foot_joint(motion.skeleton, "left")
        if foot >= 0:
            cuts = heel_strikes(motion_positions(motion), foot, rate, up=up)
            used = "feet"
        elif method == "feet":
            raise ClipError("cut_cycles: the skeleton has no left foot/ankle joint")
    if method == "period" or (method == "auto" and len(cuts) < 3):
        period = autocorrelation_period(dofs, min_lag=max(3, int(0.2 * rate)))
        if period > 0:
            cuts = period_cuts(dofs, period)
            used = "period"
    if len(cuts) < 2:
        return [], {"method": used, "cuts": cuts.tolist(), "period": 0, "dropped": []}
    keep = _shape_outliers(dofs, cuts, outlier)
    cycles = [(int(a), int(b)) for (a, b), k in zip(zip(cuts[:-1], cuts[1:]), keep) if k]
    dropped = [(int(a), int(b)) for (a, b), k in zip(zip(cuts[:-1], cuts[1:]), keep) if not k]
    period = float(np.median([b - a for a, b in cycles])) if cycles else 0.0
    return cycles, {"method": used, "cuts": cuts.tolist(), "period": period, "dropped": dropped}

