"""Novelty of generated variants against their inputs (METRICS.md §2).

Poses are compared in DOF space standardised by the inputs' per-DOF standard
deviation.  Metrics:

longest copied run
    The longest run of consecutive output frames that match consecutive
    *moving* frames of one input (each pose within ``tol`` of the input pose;
    cyclic inputs wrap).  ``tol`` defaults to a tenth of the median
    frame-to-frame step of the inputs; input frames that move less than half
    the median step (a pen or body at rest, where every example looks alike)
    never count as copied.  The same measure among the inputs (each against
    the others) is reported for reference.
nearest pose distance
    The smallest distance from any output pose to any input pose; an output
    pose *equals* an input pose when it is within ``equal_tol`` (1e-6).
DTW-aligned distance
    Dynamic time warping with Euclidean frame cost; the aligned distance is the
    total cost divided by the path length (mean distance of aligned poses).
    Each output's distance to its nearest input is compared with the
    distances among the inputs (pairwise).
warp-slope std
    The DTW path as input frame versus output frame, averaged per output
    frame, smoothed, differentiated, 10 % trimmed at each end: its standard
    deviation (relative to the mean slope) measures temporal variation.
    Compared with the same among the inputs.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

__all__ = [
    "aligned_distance",
    "dtw",
    "longest_copied_run",
    "nearest_pose_distance",
    "novelty_report",
    "warp_slope_std",
]


def dtw(a: np.ndarray, b: np.ndarray, *, window: int | None = None) -> tuple[float, np.ndarray]:
    """Dynamic time warping of two sequences (Euclidean frame cost).

    Parameters
    ----------
    a : (n, D) float ndarray
    b : (m, D) float ndarray
    window : int, optional
        Sakoe–Chiba band half-width (frames, widened to ``|n − m|``).

    Returns
    -------
    cost : float
        Sum of frame distances along the optimal path.
    path : (L, 2) int ndarray
        Aligned index pairs ``(i, j)`` from ``(0, 0)`` to ``(n−1, m−1)``.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim == 1:
        a = a[:, None]
    if b.ndim == 1:
        b = b[:, None]
    n, m = len(a), len(b)
    if n == 0 or m == 0:
        raise ValueError("dtw: empty sequence")
    C = cdist(a, b)
    if window is not None:
        w = max(int(window), abs(n - m))
        ii, jj = np.indices((n, m))
        C = np.where(np.abs(ii * (m / n) - jj) <= w, C, np.inf)
    Dp = np.full((n + 1, m + 1), np.inf)
    Dp[0, 0] = 0.0
    for s in range(n + m - 1):
        i = np.arange(max(0, s - m + 1), min(n - 1, s) + 1)
        j = s - i
        best = np.minimum(np.minimum(Dp[i, j], Dp[i, j + 1]), Dp[i + 1, j])
        Dp[i + 1, j + 1] = C[i, j] + best
    # backtrack
    i, j = n, m
    path = [(n - 1, m - 1)]
    while (i, j) != (1, 1):
        cands = (
            (Dp[i - 1, j - 1], i - 1, j - 1), (Dp[i - 1, j], i - 1, j), (Dp[i, j - 1], i, j - 1)
        )
        _, i, j = min(cands, key=lambda c: c[0])
        path.append((i - 1, j - 1))
    return float(Dp[n, m]), np.array(path[::-1], dtype=np.int64)


def aligned_distance(a: np.ndarray, b: np.ndarray, *, window: int | None = None) -> float:
    """Mean distance of DTW-aligned poses (total cost / path length).

    Parameters
    ----------
    a : (n, D) float ndarray
    b : (m, D) float ndarray
    window : int, optional

    Returns
    -------
    float
    """
    return _aligned(a, b, window)[0]


def _aligned(a: np.ndarray, b: np.ndarray, window: int | None) -> tuple[float, np.ndarray]:
    """:func:`aligned_distance` and the DTW path it comes from."""
    cost, path = dtw(a, b, window=window)
    return cost / len(path), path


def warp_slope_std(path: np.ndarray, *, smooth: int = 5, trim: float = 0.1) -> float:
    """Standard deviation of the local slope of a DTW path.

    Parameters
    ----------
    path : (L, 2) int ndarray
        From :func:`dtw` (output frame, input frame).
    smooth : int
        Half-width (frames) of the moving average applied before differencing.
    trim : float
        Fraction of output frames left out at each end: DTW absorbs a
        difference in start or end phase with a flat or steep stretch there,
        which is not a change of speed.

    Returns
    -------
    float
        Std of ``d(input frame) / d(output frame)``, the input frame averaged
        per output frame; the slope is normalised by its mean (1 = uniform).
    """
    i, j = path[:, 0], path[:, 1]
    n = int(i.max()) + 1
    jbar = np.bincount(i, weights=j, minlength=n) / np.maximum(np.bincount(i, minlength=n), 1)
    if smooth > 0 and n > 2 * smooth + 1:
        k = np.ones(2 * smooth + 1) / (2 * smooth + 1)
        jbar = np.convolve(np.pad(jbar, smooth, mode="reflect", reflect_type="odd"), k, "valid")
    slope = np.gradient(jbar)
    cut = int(trim * len(slope))
    if len(slope) - 2 * cut >= 3:
        slope = slope[cut : len(slope) - cut]
    mean = slope.mean()
    return float(slope.std() / mean) if mean > 0 else float("nan")


def longest_copied_run(
    output: np.ndarray,
    inputs: list[np.ndarray],
    tol: float,
    *,
    cyclic: bool = False,
    eligible: list[np.ndarray] | None = None,
) -> int:
    """Longest run of consecutive output frames equal to consecutive input frames.

    Parameters
    ----------
    output : (T, D) float ndarray
    inputs : list of (T_c, D) float ndarray
    tol : float
        Poses within ``tol`` (Euclidean) are equal.
    cyclic : bool
        Input frame ``T_c − 1`` is followed by frame 0.
    eligible : list of (T_c,) bool ndarray, optional
        Input frames that may count as copied (default all).

    Returns
    -------
    int
    """
    best = 0
    o = np.asarray(output, dtype=np.float64)
    for c, x in enumerate(inputs):
        x = np.asarray(x, dtype=np.float64)
        E = cdist(o, x) <= tol
        if eligible is not None:
            E &= np.asarray(eligible[c], dtype=bool)[None, :]
        if not E.any():
            continue
        run = np.zeros(len(x), dtype=np.int64)
        for t in range(len(o)):
            prev = np.roll(run, 1)
            if not cyclic:
                prev[0] = 0
            run = np.where(E[t], prev + 1, 0)
            best = max(best, int(run.max()))
    return best


def nearest_pose_distance(output: np.ndarray, inputs: list[np.ndarray]) -> float:
    """Smallest Euclidean distance from any output pose to any input pose.

    Parameters
    ----------
    output : (T, D) float ndarray
    inputs : list of (T_c, D) float ndarray

    Returns
    -------
    float
    """
    return float(np.min(_input_distances(output, inputs)))


def _input_distances(output: np.ndarray, inputs: list[np.ndarray]) -> np.ndarray:
    """``(T,)`` distance from each output pose to its nearest input pose (a k-d tree)."""
    d, _ = cKDTree(np.concatenate(inputs, axis=0)).query(np.asarray(output, dtype=np.float64))
    return d


def novelty_report(
    outputs: list[np.ndarray],
    inputs: list[np.ndarray],
    *,
    cyclic: bool = False,
    copy_tolerance: float = 0.1,
    equal_tol: float = 1e-6,
    window: int | None = None,
    smooth: int = 5,
) -> dict[str, Any]:
    """Novelty of outputs against inputs (see module docstring).

    Parameters
    ----------
    outputs : list of (T_o, D) float ndarray
        Generated variants (same DOF columns as the inputs).
    inputs : list of (T_c, D) float ndarray
        At least one input clip (two for the among-input statistics).
    cyclic : bool
        Inputs are cycles (copied runs may wrap).
    copy_tolerance : float
        Copied-run pose tolerance as a fraction of the median input frame step.
    equal_tol : float
        Distance (standardised units) below which two poses are equal.
    window : int, optional
        DTW band half-width.
    smooth : int
        Warp-slope smoothing half-width, frames.

    Returns
    -------
    dict
        ``tol`` (copied runs), ``equal_tol``, ``equal_poses`` (output poses
        equal to an input pose, total), ``input_copied_run`` (longest copied
        run of an input against the others); per output ``nearest_pose``
        (min distance), ``copied_run``
        (frames), ``aligned_distance`` (to the nearest input), ``warp_slope_std``
        (against that input); among inputs ``input_distances`` (pairwise
        aligned distances), ``input_distance_p95`` and
        ``input_warp_slope_std`` (mean over pairs); all in standardised DOF units.
    """
    if not inputs:
        raise ValueError("novelty_report: no input clip")
    zin, zout = _standardised(inputs, outputs)
    tol, moving = _copy_tolerance(zin, copy_tolerance)
    rep: dict[str, Any] = {"tol": tol, "equal_tol": equal_tol}
    near, runs, adist, wstd = [], [], [], []
    for z in zout:
        near.append(nearest_pose_distance(z, zin))
        runs.append(longest_copied_run(z, zin, tol, cyclic=cyclic, eligible=moving))
        d, path = _nearest_aligned(z, zin, window)
        adist.append(d)
        wstd.append(warp_slope_std(path, smooth=smooth))
    pair_d, pair_w = _among_inputs(zin, window, smooth)
    rep.update(
        {
            "equal_poses": int(sum((_input_distances(z, zin) <= equal_tol).sum() for z in zout)),
            "nearest_pose": near,
            "copied_run": runs,
            "aligned_distance": adist,
            "warp_slope_std": wstd,
            "input_copied_run": _input_copied_run(zin, tol, cyclic=cyclic, moving=moving),
            "input_distances": pair_d,
            "input_distance_p95": float(np.percentile(pair_d, 95)) if pair_d else float("nan"),
            "input_warp_slope_std": float(np.mean(pair_w)) if pair_w else float("nan"),
        }
    )
    return rep


def _standardised(
    inputs: list[np.ndarray], outputs: list[np.ndarray]
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Inputs and outputs in DOF units standardised by the inputs' per-DOF mean and std
    (a DOF that never moves keeps its unit)."""
    allin = np.concatenate(inputs, axis=0)
    mean = allin.mean(axis=0)
    std = allin.std(axis=0)
    std = np.where(std > 0, std, 1.0)
    return [(x - mean) / std for x in inputs], [(y - mean) / std for y in outputs]


def _copy_tolerance(
    zin: list[np.ndarray], copy_tolerance: float
) -> tuple[float, list[np.ndarray]]:
    """Copied-run tolerance and the input frames that may count as copied.

    The tolerance is ``copy_tolerance`` × the median frame-to-frame step of the
    inputs; a frame moving less than half that median step (at rest) is never
    counted as copied.  Returns the tolerance and one ``(T_c,)`` bool per input.
    """
    steps = [np.linalg.norm(np.diff(z, axis=0), axis=1) for z in zin]
    allsteps = np.concatenate(steps)
    med = float(np.median(allsteps)) if allsteps.size else 0.0
    tol = copy_tolerance * med
    moving = [np.append(s, s[-1:]) >= 0.5 * med if s.size else np.zeros(1, bool) for s in steps]
    return tol, moving


def _nearest_aligned(
    z: np.ndarray, zin: list[np.ndarray], window: int | None
) -> tuple[float, np.ndarray]:
    """The smallest DTW-aligned distance of ``z`` to an input, and that alignment's path
    (the first input wins a tie)."""
    best = None
    for x in zin:
        d, path = _aligned(z, x, window)
        if best is None or d < best[0]:
            best = (d, path)
    return best


def _among_inputs(
    zin: list[np.ndarray], window: int | None, smooth: int
) -> tuple[list[float], list[float]]:
    """Aligned distance of every input pair, and the warp-slope std of both directions."""
    pair_d, pair_w = [], []
    for a in range(len(zin)):
        for b in range(a + 1, len(zin)):
            d, path = _aligned(zin[a], zin[b], window)
            pair_d.append(d)
            pair_w.append(warp_slope_std(path, smooth=smooth))
            _, path = _aligned(zin[b], zin[a], window)
            pair_w.append(warp_slope_std(path, smooth=smooth))
    return pair_d, pair_w


def _input_copied_run(
    zin: list[np.ndarray], tol: float, *, cyclic: bool, moving: list[np.ndarray]
) -> int:
    """Longest copied run of an input against the other inputs (0 with one input)."""
    return max(
        (longest_copied_run(zin[a], [x for b, x in enumerate(zin) if b != a], tol,
                            cyclic=cyclic, eligible=[m for b, m in enumerate(moving) if b != a])
         for a in range(len(zin)) if len(zin) > 1),
        default=0,
    )
