"""Gait metrics of generated motion streams and variants (issue 17's "Must show").

Imports only :mod:`mocapflow.stages.motion` and :mod:`.quality`; registers nothing.
Angles are radians, rates frames per second.

hip flexion DOF
    Per side (``left`` / ``right``), the rotation DOF of a hip joint (a joint
    whose name contains ``upleg``, ``thigh``, ``femur`` or ``hip``, with a
    ``Left`` / ``Right`` prefix, or ``L`` / ``R`` before a capital or ``_``, or
    ``l_`` / ``r_``; the root never has a side) with
    the largest range over the reference (input) trajectories
    → :func:`hip_flexion_columns`.
cadence and cycles made
    The hip flexion signal minus its own linear trend; a cycle is counted at
    every upward crossing of ``+h`` that follows a visit below ``−h``
    (zero crossings with hysteresis ``h``, so a hip jittering about its mean
    makes no cycle).  The cadence (cycles per second) is ``(n − 1)`` cycles
    over the time between the first and the last of ``n ≥ 2`` crossings, else
    ``n`` over the whole duration → :func:`gait_cycles`, :func:`cadence`.
    ``h`` defaults to a fraction (0.2) of the inputs' median per-clip range
    (:func:`swing_hysteresis`).  The inputs' cadence of cut gait cycles is the
    rate over their mean length → :func:`clip_cadence`.
frozen windows
    Consecutive non-overlapping windows of ``width`` frames (half a second)
    where a hip flexion DOF's range (max − min) is below ``fraction`` (½) of
    the smallest range of any window of the same width (sliding, within one
    input clip) of the inputs → :func:`window_ranges`, :func:`frozen_threshold`,
    :func:`frozen_windows`.
range excess
    BVH rotation channels (every non-root joint's Euler angles in its BVH
    channel order, continuous over time, from
    :func:`~mocapflow.stages.variation.dofs.motion_to_dofs`); an output
    channel is first moved by the multiple of 2π that brings its mean nearest
    to the inputs' mean of that channel (unwrapping may start on another
    branch); the excess is how far it goes beyond the inputs' ``[min, max]``
    → :func:`~mocapflow.stages.variation.dofs.rotation_channels` (there: metrics import
    no paper package), :func:`channel_range`, :func:`range_excess`.
join jerk
    The p99 of the per-frame mean joint jerk (:func:`~.quality.jerk_per_frame`)
    on the frames within ``radius`` frames of each join of clips played one
    after the other → :func:`join_mask`, :func:`join_jerk_p99`.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.signal import detrend

from mocapflow.stages.metrics.quality import jerk_p99, seam_mask

__all__ = [
    "cadence",
    "channel_range",
    "clip_cadence",
    "frozen_threshold",
    "frozen_windows",
    "gait_cycles",
    "hip_flexion_columns",
    "join_jerk_p99",
    "join_mask",
    "range_excess",
    "swing_hysteresis",
    "window_ranges",
]

_HIP = ("upleg", "thigh", "femur", "hip")


def _side(joint: str) -> str | None:
    """``"left"`` / ``"right"`` from a joint name's prefix (``Left…``, ``L…``), else None."""
    low = joint.lower()
    if low.startswith("left") or re.match(r"^L[A-Z_]", joint) or re.match(r"^l_", joint):
        return "left"
    if low.startswith("right") or re.match(r"^R[A-Z_]", joint) or re.match(r"^r_", joint):
        return "right"
    return None


def hip_flexion_columns(
    names: Sequence[str], trajectories: Sequence[np.ndarray]
) -> dict[str, int]:
    """Columns of the left and right hip flexion DOFs.

    Parameters
    ----------
    names : sequence of str
        ``D`` DOF names ``"<joint>:<channel>"`` (as :func:`motion_to_dofs`).
    trajectories : sequence of (T_c, D) float ndarray
        Reference clips (the inputs); the range is taken over all of them.

    Returns
    -------
    dict
        ``{"left": column, "right": column}`` for the sides that have a hip
        joint with a rotation DOF; the rotation DOF of a hip joint of that side
        with the largest range (max − min).  ``ValueError`` when neither side has one.
    """
    x = np.concatenate([np.asarray(t, dtype=np.float64) for t in trajectories], axis=0)
    rng = np.ptp(x, axis=0)
    best: dict[str, int] = {}
    for i, n in enumerate(names):
        joint, _, channel = n.partition(":")
        side = _side(joint)
        if side is None or not channel.endswith("rotation"):
            continue
        if not any(h in joint.lower() for h in _HIP):
            continue
        if side not in best or rng[i] > rng[best[side]]:
            best[side] = i
    if not best:
        raise ValueError(f"no left or right hip joint rotation among the DOFs {list(names)}")
    return best


def gait_cycles(x: np.ndarray, *, hysteresis: float) -> np.ndarray:
    """Frames where a detrended hip flexion signal completes a swing.

    Parameters
    ----------
    x : (F,) float ndarray
        One hip flexion DOF over time, radians.
    hysteresis : float
        ``h`` (radians, ≥ 0): a crossing counts when the detrended signal
        rises above ``+h`` after having been below ``−h``.

    Returns
    -------
    (n,) int ndarray
        The frames of the counted upward crossings (``n`` = cycles made).
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f"gait_cycles: expected one signal (F,), got shape {x.shape}")
    if x.size < 2:
        return np.zeros(0, dtype=np.int64)
    y = detrend(x)
    h = float(hysteresis)
    # state: +1 above +h, -1 below -h, 0 between (carry the last non-zero state forward)
    s = np.where(y > h, 1, np.where(y < -h, -1, 0))
    idx = np.flatnonzero(s)
    if idx.size == 0:
        return np.zeros(0, dtype=np.int64)
    held = s[idx]
    up = np.flatnonzero((held[1:] == 1) & (held[:-1] == -1)) + 1
    return idx[up].astype(np.int64)


def swing_hysteresis(inputs: Sequence[np.ndarray], *, fraction: float = 0.2) -> np.ndarray:
    """Hysteresis of :func:`gait_cycles`: a fraction of the inputs' median range.

    Parameters
    ----------
    inputs : sequence of (T_c,) or (T_c, C) float ndarray
        The inputs' hip flexion DOFs, one gait cycle (or more) per clip.
    fraction : float
        0.2: a swing counts when it spans more than 40 % of the inputs' range.

    Returns
    -------
    float or (C,) float ndarray
        Radians, per column.
    """
    if not len(inputs):
        raise ValueError("swing_hysteresis: no input clip")
    return fraction * np.median(
        np.stack([np.ptp(np.asarray(x, dtype=np.float64), axis=0) for x in inputs]), axis=0)


def cadence(x: np.ndarray, rate: float, *, hysteresis: float) -> tuple[float, int]:
    """Gait cycles per second of one hip flexion signal.

    Parameters
    ----------
    x : (F,) float ndarray
        Hip flexion DOF, radians.
    rate : float
        Frames per second.
    hysteresis : float
        See :func:`gait_cycles`.

    Returns
    -------
    cadence : float
        Cycles per second: ``(n − 1) · rate / (last − first)`` crossing frames
        for ``n ≥ 2`` crossings, else ``n · rate / F``.
    cycles : int
        ``n``, the cycles made.
    """
    c = gait_cycles(x, hysteresis=hysteresis)
    n = int(c.size)
    if n >= 2:
        return float((n - 1) * rate / (c[-1] - c[0])), n
    return float(n * rate / max(len(x), 1)), n


def clip_cadence(lengths: Sequence[int], rate: float) -> float:
    """Cadence of clips that are one gait cycle each: the rate over their mean length.

    Parameters
    ----------
    lengths : sequence of int
        Frames per cycle.
    rate : float

    Returns
    -------
    float
        Cycles per second.
    """
    lengths = np.asarray(lengths, dtype=np.float64)
    if lengths.size == 0 or np.any(lengths <= 0):
        raise ValueError(f"clip_cadence: needs positive cycle lengths, got {lengths.tolist()}")
    return float(rate / lengths.mean())


def window_ranges(x: np.ndarray, width: int, *, step: int | None = None) -> np.ndarray:
    """Range (max − min) of every window of ``width`` frames.

    Parameters
    ----------
    x : (F,) or (F, C) float ndarray
    width : int
        Frames per window (≥ 1).
    step : int, optional
        Frames between window starts; default ``width`` (consecutive,
        non-overlapping; a last partial window is left out); 1 gives sliding windows.

    Returns
    -------
    (W,) or (W, C) float ndarray
        ``W = (F − width) // step + 1`` windows (0 when ``F < width``).
    """
    x = np.asarray(x, dtype=np.float64)
    width = int(width)
    if width < 1:
        raise ValueError(f"window width must be >= 1 frame, got {width}")
    step = width if step is None else int(step)
    if x.shape[0] < width:
        return np.zeros((0,) + x.shape[1:])
    w = sliding_window_view(x, width, axis=0)[::step]  # (W, [C,] width)
    return np.ptp(w, axis=-1)


def frozen_threshold(
    inputs: Sequence[np.ndarray], width: int, *, fraction: float = 0.5
) -> np.ndarray:
    """``fraction`` × the smallest range of any input window of ``width`` frames.

    Parameters
    ----------
    inputs : sequence of (T_c,) or (T_c, C) float ndarray
        The inputs' hip flexion DOFs (clips shorter than ``width`` are skipped).
    width : int
        Frames per window.
    fraction : float
        ½ in the issue.

    Returns
    -------
    float or (C,) float ndarray
        Per column threshold, radians.
    """
    r = [window_ranges(x, width, step=1) for x in inputs]
    r = [v for v in r if v.shape[0]]
    if not r:
        raise ValueError(f"frozen_threshold: no input clip has {width} frames")
    return fraction * np.concatenate(r, axis=0).min(axis=0)


def frozen_windows(x: np.ndarray, threshold: np.ndarray | float, width: int) -> np.ndarray:
    """Consecutive windows where a hip flexion DOF barely moves.

    Parameters
    ----------
    x : (F,) or (F, C) float ndarray
        Hip flexion DOFs of one motion.
    threshold : float or (C,) float ndarray
        From :func:`frozen_threshold`.
    width : int
        Frames per window (half a second: ``round(0.5 · rate)``).

    Returns
    -------
    (W,) bool ndarray
        Window ``w`` (frames ``w · width … (w + 1) · width − 1``) is frozen when
        the range of some column is below its threshold.
    """
    r = window_ranges(x, width)
    frozen = r < np.asarray(threshold, dtype=np.float64)
    return frozen if frozen.ndim == 1 else frozen.any(axis=1)


def channel_range(inputs: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-channel min, max and mean over the input motions.

    Parameters
    ----------
    inputs : sequence of (T_c, C) float ndarray
        E.g. :func:`~mocapflow.stages.variation.dofs.rotation_channels` of each input.

    Returns
    -------
    low, high, mean : (C,) float ndarray
    """
    x = np.concatenate([np.asarray(t, dtype=np.float64) for t in inputs], axis=0)
    return x.min(axis=0), x.max(axis=0), x.mean(axis=0)


def range_excess(
    x: np.ndarray, low: np.ndarray, high: np.ndarray, mean: np.ndarray | None = None
) -> np.ndarray:
    """How far each channel of a motion goes beyond the inputs' range.

    Parameters
    ----------
    x : (F, C) float ndarray
        Channels of one output motion, radians.
    low, high : (C,) float ndarray
        The inputs' range (:func:`channel_range`).
    mean : (C,) float ndarray, optional
        The inputs' mean: each output channel (a whole unwrapped track, which a
        file may hold at any multiple of 2π) is first shifted by the multiple of
        2π that gives it the smallest excess, the one that brings its mean
        nearest to the inputs' among equals.  The mean-nearest shift alone fails
        when the inputs span more than 2π (a joint near gimbal lock, e.g.
        ``RThumb:Yrotation`` of ``cmu_131_02.bvh``: 9.6 rad).  ``None``: no shift.

    Returns
    -------
    (C,) float ndarray
        ``max(0, max_t x − high, low − min_t x)`` per channel, radians.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != np.shape(low)[0] or np.shape(low) != np.shape(high):
        raise ValueError(f"range_excess: channels {x.shape} do not match the range "
                         f"{np.shape(low)} / {np.shape(high)}")
    top, bottom = x.max(axis=0), x.min(axis=0)
    if mean is None:
        return np.maximum(np.maximum(top - high, low - bottom), 0.0)
    k0 = np.round((x.mean(axis=0) - mean) / (2 * np.pi))
    # candidate shifts, nearest the mean-nearest first (argmin keeps the first of equals)
    k = k0[None, :] + np.array([0, -1, 1, -2, 2, -3, 3])[:, None]
    over = np.maximum(np.maximum(top - 2 * np.pi * k - high, low - bottom + 2 * np.pi * k), 0.0)
    return over[np.argmin(over, axis=0), np.arange(x.shape[1])]


def join_mask(lengths: Sequence[int], *, radius: int = 3) -> np.ndarray:
    """Frames within ``radius`` of each join of clips played one after the other.

    Parameters
    ----------
    lengths : sequence of int
        Frames of each clip, in playing order.
    radius : int
        Frames each side of a join (the join lies between the last frame of a
        clip and the first of the next).

    Returns
    -------
    (sum(lengths),) bool ndarray
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    joins = np.cumsum(lengths)[:-1]
    return seam_mask(int(lengths.sum()), joins, radius=radius)


def join_jerk_p99(
    positions: np.ndarray, lengths: Sequence[int], rate: float, *, radius: int = 3
) -> float:
    """p99 of the per-frame mean joint jerk at the joins of chained clips.

    Parameters
    ----------
    positions : (F, J, 3) float ndarray
        Global joint positions of the chained clips (``F = sum(lengths)``), metres.
    lengths : sequence of int
        Frames of each clip (at least two clips).
    rate : float
    radius : int
        See :func:`join_mask`.

    Returns
    -------
    float
        m/s³.
    """
    positions = np.asarray(positions, dtype=np.float64)
    if len(lengths) < 2:
        raise ValueError("join_jerk_p99: needs at least two chained clips")
    if positions.shape[0] != int(np.sum(lengths)):
        raise ValueError(f"join_jerk_p99: {positions.shape[0]} frames, but the clips have "
                         f"{int(np.sum(lengths))}")
    return jerk_p99(positions, rate, mask=join_mask(lengths, radius=radius), trim=0)
