"""Motion quality metrics used by the benchmarks (texture, variation).

Definitions follow ``shared/METRICS.md``:

Seams and feet
    Global joint positions from forward kinematics; per frame the mean over
    joints of ``‖acceleration‖`` and ``‖jerk‖`` (finite differences times the
    rate); the 99th percentile over frames (2 frames trimmed at each end),
    overall or within ±5 frames of each transition.  Foot skate is the mean
    horizontal toe speed on contact frames (toe near the floor *and* slow).
Patch nearest-neighbour metrics (GANimator's definitions)
    Features are the 6-D rotations of every joint (root translation excluded).
    Frame cost ``c[i, k] = ‖f_out[i] - f_in[k]‖₂``; window cost along the
    diagonal ``W(i, k, T) = Σ_{t<T} c[i+t, k+t]``, read from the diagonal
    cumulative sum ``C[t+1, k+1] = C[t, k] + c[t, k]`` in ``O(L · L_in)`` memory.

All functions are pure NumPy (and SciPy); nothing here imports the engine.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.distance import cdist

from mocapflow.stages.motion.contacts import foot_contacts, horizontal_speed
from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.motion.rotations import heading_split, quat_to_6d

__all__ = [
    "acceleration_per_frame",
    "acceleration_p99",
    "coverage",
    "diagonal_cumsum",
    "foot_skate",
    "global_diversity",
    "jerk_p99",
    "jerk_per_frame",
    "local_diversity",
    "longest_verbatim_run",
    "patch_metrics",
    "rotation_features",
    "seam_mask",
    "seams_from_source",
]


# --------------------------------------------------------------------------- FK helpers


def rotation_features(motion: Motion, *, heading_free: bool = False) -> np.ndarray:
    """GANimator features: the 6-D rotation of every joint, root translation excluded.

    Parameters
    ----------
    motion : Motion
        ``F`` frames of ``J`` joints.
    heading_free : bool
        Remove the root's heading (twist about ``y``) first, for methods that
        integrate the heading instead of copying it.

    Returns
    -------
    (F, 6 J) float ndarray
    """
    rot = motion.rotations
    if heading_free:
        rot = rot.copy()
        _, rot[:, 0] = heading_split(rot[:, 0])
    return quat_to_6d(rot).reshape(motion.n_frames, -1)


# --------------------------------------------------------------------------- seams


def _finite_difference(positions: np.ndarray, order: int) -> np.ndarray:
    """``order``-th forward difference along frames, ``(F - order, J, 3)``."""
    d = np.asarray(positions, dtype=np.float64)
    for _ in range(order):
        d = d[1:] - d[:-1]
    return d


def acceleration_per_frame(positions: np.ndarray, rate: float) -> np.ndarray:
    """Mean over joints of ``‖acceleration‖`` at every frame.

    Parameters
    ----------
    positions : (F, J, 3) float ndarray
        Global joint positions, metres.
    rate : float
        Frames per second.

    Returns
    -------
    (F,) float ndarray
        m/s²; frame ``t`` uses frames ``t-1, t, t+1`` (NaN at the two ends).
    """
    positions = np.asarray(positions, dtype=np.float64)
    out = np.full(positions.shape[0], np.nan)
    if positions.shape[0] >= 3:
        a = _finite_difference(positions, 2) * rate**2
        out[1:-1] = np.linalg.norm(a, axis=-1).mean(axis=-1)
    return out


def jerk_per_frame(positions: np.ndarray, rate: float) -> np.ndarray:
    """Mean over joints of ``‖jerk‖`` at every frame.

    Parameters
    ----------
    positions : (F, J, 3) float ndarray
        Global joint positions, metres.
    rate : float
        Frames per second.

    Returns
    -------
    (F,) float ndarray
        m/s³; frame ``t`` uses frames ``t-1 … t+2`` (NaN at frame 0 and the
        last two frames).
    """
    positions = np.asarray(positions, dtype=np.float64)
    out = np.full(positions.shape[0], np.nan)
    if positions.shape[0] >= 4:
        j = _finite_difference(positions, 3) * rate**3
        out[1:-2] = np.linalg.norm(j, axis=-1).mean(axis=-1)
    return out


def _p99(values: np.ndarray, mask: np.ndarray | None, trim: int, q: float) -> float:
    v = np.asarray(values, dtype=np.float64).copy()
    keep = np.ones(v.shape[0], dtype=bool)
    if trim > 0:
        keep[:trim] = False
        keep[v.shape[0] - trim :] = False
    if mask is not None:
        keep &= np.asarray(mask, dtype=bool)
    v = v[keep & np.isfinite(v)]
    if v.size == 0:
        return float("nan")
    return float(np.percentile(v, q))


def jerk_p99(
    positions: np.ndarray,
    rate: float,
    *,
    mask: np.ndarray | None = None,
    trim: int = 2,
    q: float = 99.0,
) -> float:
    """99th percentile over frames of the per-frame mean joint jerk.

    Parameters
    ----------
    positions : (F, J, 3) float ndarray
        Global joint positions, metres.
    rate : float
        Frames per second.
    mask : (F,) bool ndarray, optional
        Frames to include (e.g. :func:`seam_mask`); all when ``None``.
    trim : int
        Frames dropped at each end.
    q : float
        Percentile.

    Returns
    -------
    float
        m/s³ (NaN when no frame is left).
    """
    return _p99(jerk_per_frame(positions, rate), mask, trim, q)


def acceleration_p99(
    positions: np.ndarray,
    rate: float,
    *,
    mask: np.ndarray | None = None,
    trim: int = 2,
    q: float = 99.0,
) -> float:
    """99th percentile over frames of the per-frame mean joint acceleration.

    Parameters
    ----------
    positions : (F, J, 3) float ndarray
    rate : float
    mask : (F,) bool ndarray, optional
    trim : int
    q : float

    Returns
    -------
    float
        m/s².
    """
    return _p99(acceleration_per_frame(positions, rate), mask, trim, q)


def seams_from_source(source_index: np.ndarray, *, cyclic: bool = False) -> np.ndarray:
    """Transitions of a per-frame source-index track.

    Parameters
    ----------
    source_index : (L,) int ndarray
        Input frame copied into each output frame.
    cyclic : bool
        Also test the last → first wrap (loops).

    Returns
    -------
    (S,) int ndarray
        Output frames ``t`` where ``source_index[t] != source_index[t-1] + 1``
        (the transition lies between ``t - 1`` and ``t``); ``0`` stands for the
        wrap in cyclic mode.
    """
    s = np.asarray(source_index, dtype=np.int64)
    t = np.flatnonzero(s[1:] != s[:-1] + 1) + 1
    if cyclic and s.size > 1 and s[0] != s[-1] + 1:
        t = np.concatenate([[0], t])
    return t


def seam_mask(n_frames: int, seams: np.ndarray, *, radius: int = 5) -> np.ndarray:
    """Frames within ``±radius`` of a transition.

    Parameters
    ----------
    n_frames : int
    seams : (S,) int ndarray
        Transitions as from :func:`seams_from_source` (between ``t-1`` and ``t``).
    radius : int

    Returns
    -------
    (n_frames,) bool ndarray
    """
    mask = np.zeros(n_frames, dtype=bool)
    for t in np.asarray(seams, dtype=np.int64):
        mask[max(0, t - 1 - radius) : min(n_frames, t + radius + 1)] = True
    return mask


def longest_verbatim_run(source_index: np.ndarray) -> int:
    """Longest run of output frames copied consecutively from the input.

    Parameters
    ----------
    source_index : (L,) int ndarray

    Returns
    -------
    int
        Frames in the longest run with ``source_index[t] == source_index[t-1] + 1``.
    """
    s = np.asarray(source_index, dtype=np.int64)
    if s.size == 0:
        return 0
    breaks = np.concatenate([[0], seams_from_source(s), [s.size]])
    return int(np.max(np.diff(breaks)))


# --------------------------------------------------------------------------- feet


def foot_skate(
    positions: np.ndarray,
    toe_indices: list[int] | np.ndarray,
    rate: float,
    *,
    height_threshold: float | None = None,
    speed_threshold: float | None = None,
    up_axis: int = 1,
) -> float:
    """Mean horizontal toe speed on contact frames (foot skate).

    Compare two motions with the *same* thresholds (take them from the input
    with :func:`contact_thresholds` and pass them for both).

    Parameters
    ----------
    positions : (F, J, 3) float ndarray
        Global joint positions, metres.
    toe_indices : sequence of int
    rate : float
    height_threshold, speed_threshold : float, optional
        See :func:`foot_contacts`.
    up_axis : int

    Returns
    -------
    float
        m/s (NaN when no contact frame exists).
    """
    positions = np.asarray(positions, dtype=np.float64)
    contact = foot_contacts(
        positions,
        toe_indices,
        rate,
        height_threshold=height_threshold,
        speed_threshold=speed_threshold,
        up_axis=up_axis,
    )
    if not contact.any():
        return float("nan")
    speed = horizontal_speed(positions[:, list(toe_indices)], rate, up_axis)
    return float(speed[contact].mean())


# --------------------------------------------------------------------------- patch metrics


def diagonal_cumsum(cost: np.ndarray) -> np.ndarray:
    """Diagonal cumulative sum ``C[t+1, k+1] = C[t, k] + cost[t, k]``.

    Parameters
    ----------
    cost : (L, K) float ndarray

    Returns
    -------
    (L + 1, K + 1) float ndarray
        ``W(i, k, T) = C[i+T, k+T] - C[i, k]`` is the cost of the diagonal
        window of length ``T`` starting at ``(i, k)``.
    """
    cost = np.asarray(cost, dtype=np.float64)
    L, K = cost.shape
    C = np.zeros((L + 1, K + 1))
    for t in range(L):
        C[t + 1, 1:] = C[t, :-1] + cost[t]
    return C


def _window_costs(C: np.ndarray, T: int) -> np.ndarray:
    """``W[i, k] = C[i+T, k+T] - C[i, k]``, shape ``(L-T+1, K-T+1)``."""
    return C[T:, T:] - C[:-T, :-T]


def _check_len(name: str, n: int, T: int) -> None:
    if n < T:
        raise ValueError(f"{name}: needs at least {T} frames, got {n}")


def local_diversity(f_out: np.ndarray, f_in: np.ndarray, *, T: int = 15) -> float:
    """GANimator local diversity: mean nearest-window cost of output windows.

    Parameters
    ----------
    f_out : (L, D) float ndarray
        Output features (6-D rotations).
    f_in : (L_in, D) float ndarray
        Input features.
    T : int
        Window length (15).

    Returns
    -------
    float
        Mean over output windows ``i < L - T`` (the last window excluded, as in
        GANimator) of ``min_k W(i, k, T) / T``.
    """
    _check_len("local_diversity output", len(f_out), T + 1)
    _check_len("local_diversity input", len(f_in), T)
    C = diagonal_cumsum(cdist(f_out, f_in))
    W = _window_costs(C, T)[:-1]
    return float(np.mean(W.min(axis=1) / T))


def coverage(
    f_out: np.ndarray, f_in: np.ndarray, *, T: int = 30, threshold: float = 2.0
) -> float:
    """GANimator coverage: fraction of input windows found in the output.

    Parameters
    ----------
    f_out : (L, D) float ndarray
    f_in : (L_in, D) float ndarray
    T : int
        Window length (30).
    threshold : float
        Mean per-frame cost under which an input window counts as covered (2.0).

    Returns
    -------
    float
        Fraction of input windows ``j`` with ``min_i W(j, i, T) / T < threshold``.
    """
    _check_len("coverage output", len(f_out), T)
    _check_len("coverage input", len(f_in), T)
    C = diagonal_cumsum(cdist(f_in, f_out))
    W = _window_costs(C, T)
    return float(np.mean(W.min(axis=1) / T < threshold))


def global_diversity(f_out: np.ndarray, f_in: np.ndarray, *, T: int = 30) -> float:
    """GANimator global diversity: cost of the best piecewise copy of the output.

    The output is partitioned into contiguous segments of length ``≥ T``, each
    matched (diagonally, no time warping) to an input segment of equal length;
    the minimal total cost divided by the output length.  Segments longer than
    ``2T - 1`` never help (they split into two segments of ``≥ T`` that match at
    most as badly), so lengths ``T … 2T-1`` suffice.

    Parameters
    ----------
    f_out : (L, D) float ndarray
    f_in : (L_in, D) float ndarray
    T : int
        Minimal segment length (30).

    Returns
    -------
    float
    """
    L, L_in = len(f_out), len(f_in)
    _check_len("global_diversity output", L, T)
    _check_len("global_diversity input", L_in, T)
    C = diagonal_cumsum(cdist(f_out, f_in))
    best = np.full(L + 1, np.inf)
    best[0] = 0.0
    max_len = min(2 * T - 1, L_in)
    for e in range(T, L + 1):
        lengths = np.arange(T, min(max_len, e) + 1)
        s = e - lengths
        ok = np.isfinite(best[s])
        if not ok.any():
            continue
        lengths, s = lengths[ok], s[ok]
        # segment cost for start s, length n: min_k C[e, k+n] - C[s, k], k <= L_in - n
        seg = np.empty(lengths.size)
        for m, (n, s0) in enumerate(zip(lengths, s)):
            seg[m] = np.min(C[e, n:] - C[s0, : L_in + 1 - n])
        best[e] = np.min(best[s] + seg)
    return float(best[L] / L)


def patch_metrics(f_out: np.ndarray, f_in: np.ndarray) -> dict[str, float]:
    """Coverage, global and local diversity with GANimator's windows.

    Parameters
    ----------
    f_out : (L, D) float ndarray
    f_in : (L_in, D) float ndarray

    Returns
    -------
    dict
        ``coverage``, ``global_diversity``, ``local_diversity``.
    """
    return {
        "coverage": coverage(f_out, f_in),
        "global_diversity": global_diversity(f_out, f_in),
        "local_diversity": local_diversity(f_out, f_in),
    }
