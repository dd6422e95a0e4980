"""Training instances of the two networks of the DBN (Lau, Bar-Joseph & Kuffner 2009, §5).

Prior network
    Nodes ``X[0]`` (``0..D-1``) and ``X[1]`` (``D..2D-1``); its instances are the
    standardised pairs ``(x[t], x[t+1])`` of the first ``w`` frames of every clip
    (:func:`prior_data`; ``w`` grows when the clips are few: :func:`prior_window`).
Transition network
    ``X[t], X[t+1] → X[t+2]``, second order (:func:`transition_data`): candidate
    parent values are the standardised ``[x[t], x[t+1]]``, the regression target
    is the delta ``x[t+2] − x[t+1]`` in units of the DOF's delta std, the self
    velocity ``x[t+1] − x[t]`` enters the distance scaled by ``velocity_weight``.
    Cyclic clips wrap their end onto their start.
Held-out masks
    Leave one clip out; with a single clip, instances within ``exclusion`` frames
    of the held-out one are left out instead.

Additions to the paper: the offset retention ``λ`` of the transition mean
(:func:`retention_of`) and the phase DOFs (:func:`with_phase`): normalised time
``_phase`` for non-cyclic clips, the cycle phase ``(cos φ, sin φ)`` for cycles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mocapflow.stages.variation.clips import Clips

__all__ = [
    "PHASE",
    "CYCLE_PHASE",
    "INTERNAL_DOFS",
    "LearnError",
    "PriorData",
    "TransitionData",
    "phase_columns",
    "prior_data",
    "prior_window",
    "prior_window_of",
    "retention_of",
    "standardization",
    "transition_data",
    "with_phase",
]


class LearnError(ValueError):
    """Training data that cannot support the network (too few frames or clips)."""


def standardization(trajectories: list[np.ndarray]) -> dict[str, np.ndarray]:
    """Per-DOF mean and std of positions, and std of frame-to-frame deltas.

    Parameters
    ----------
    trajectories : list of (T_c, D) float ndarray

    Returns
    -------
    dict
        ``mean (D,)``, ``std (D,)``, ``delta_std (D,)`` (floored away from 0).
    """
    X = np.concatenate(trajectories, axis=0)
    mean = X.mean(axis=0)
    std = X.std(axis=0)
    std = np.where(std > 1e-12, std, 1.0)
    dl = [np.diff(t, axis=0) for t in trajectories if len(t) > 1]
    if dl:
        dstd = np.concatenate(dl, axis=0).std(axis=0)
    else:
        dstd = np.zeros_like(std)
    dstd = np.maximum(dstd, 1e-6 * std)
    return {"mean": mean, "std": std, "delta_std": dstd}


def _valid_mask(group: np.ndarray, tindex: np.ndarray, exclusion: int) -> np.ndarray:
    """``valid[r, s]``: instance ``s`` may predict held-out instance ``r``."""
    if len(np.unique(group)) > 1:
        return group[:, None] != group[None, :]
    return np.abs(tindex[:, None] - tindex[None, :]) > exclusion


@dataclass
class PriorData:
    """Training instances of the prior network.

    Attributes
    ----------
    Z : (N, 2D) float ndarray
        Standardised ``[x[t], x[t+1]]`` rows.
    group : (N,) int ndarray
        Clip of each row.
    tindex : (N,) int ndarray
        Frame ``t`` of each row.
    valid : (N, N) bool ndarray
        Leave-one-sequence-out (or exclusion window) mask.
    k : int
        Neighbours used (clamped to the available instances).
    kernel_width, min_std : float
    """

    Z: np.ndarray
    group: np.ndarray
    tindex: np.ndarray
    valid: np.ndarray
    k: int
    kernel_width: float | None
    min_std: float


def prior_window(lengths: np.ndarray, k: int, window: int | None) -> int:
    """Frames per clip used as prior instances (more when the clips are few)."""
    if window is not None:
        return max(1, int(window))
    C = len(lengths)
    return max(2, int(math.ceil(2.0 * (k + 1) / max(C - 1, 1))) if C > 1 else 2 * (k + 1))


def prior_data(
    trajectories: list[np.ndarray],
    stats: dict[str, np.ndarray],
    *,
    k: int,
    kernel_width: float | None,
    min_std: float,
    window: int | None = None,
    exclusion: int | None = None,
) -> PriorData:
    """Prior-network instances: ``(x[t], x[t+1])`` for the first frames of each clip.

    Parameters
    ----------
    trajectories : list of (T_c, D) float ndarray
    stats : dict
        From :func:`standardization`.
    k, kernel_width, min_std
        Kernel regression parameters.
    window : int, optional
        Frames per clip (default :func:`prior_window`).
    exclusion : int, optional
        With one clip, instances within this many frames are not neighbours
        (default a fifth of the window, at least 1).

    Returns
    -------
    PriorData
    """
    lengths = np.array([len(t) for t in trajectories])
    w = prior_window(lengths, k, window)
    rows, group, tindex = [], [], []
    m, s = stats["mean"], stats["std"]
    for c, t in enumerate(trajectories):
        n = min(w, len(t) - 1)
        if n < 1:
            continue
        z = (t - m) / s
        rows.append(np.concatenate([z[:n], z[1 : n + 1]], axis=1))
        group += [c] * n
        tindex += list(range(n))
    if not rows:
        raise LearnError("prior network: every clip has fewer than 2 frames")
    group_a = np.asarray(group)
    tindex_a = np.asarray(tindex)
    excl = max(1, w // 5) if exclusion is None else int(exclusion)
    valid = _valid_mask(group_a, tindex_a, excl)
    avail = int(valid.sum(axis=1).min())
    if avail < 2:
        raise LearnError(
            f"prior network: only {avail} instance(s) left for cross-validation; "
            "give more or longer clips"
        )
    return PriorData(
        Z=np.concatenate(rows, axis=0),
        group=group_a,
        tindex=tindex_a,
        valid=valid,
        k=min(int(k), avail),
        kernel_width=None if kernel_width is None else float(kernel_width),
        min_std=float(min_std),
    )


@dataclass
class TransitionData:
    """Training instances of the transition network.

    Attributes
    ----------
    F : (N, 2D) float ndarray
        Standardised ``[x[t], x[t+1]]`` (candidate parent values).
    V : (N, D) float ndarray
        Velocity feature ``(x[t+1] − x[t]) / delta_std · velocity_weight``.
    Y : (N, D) float ndarray
        Target ``(x[t+2] − x[t+1]) / delta_std``.
    Z2 : (N, D) float ndarray
        Standardised ``x[t+2]``.
    ratio : (D,) float ndarray
        ``delta_std / std`` (delta units → standardised position units).
    rows : list of (L_c,) int ndarray
        Instance rows of each clip in time order.
    group, tindex : (N,) int ndarray
    valid : (N, N) bool ndarray
    k : int
    kernel_width, min_std, velocity_weight : float
    """

    F: np.ndarray
    V: np.ndarray
    Y: np.ndarray
    Z2: np.ndarray
    ratio: np.ndarray
    rows: list[np.ndarray]
    group: np.ndarray
    tindex: np.ndarray
    valid: np.ndarray
    k: int
    kernel_width: float | None
    min_std: float
    velocity_weight: float
    retention: float = 1.0

    @property
    def n_dofs(self) -> int:
        """``D``."""
        return self.V.shape[1]


def _triples(t: np.ndarray, cyclic: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x[t], x[t+1], x[t+2])`` row blocks of a ``(T, D)`` clip (wrapped if ``cyclic``)."""
    if cyclic and len(t) >= 2:
        e = np.concatenate([t, t[:2]], axis=0)
        n = len(t)
    else:
        e = t
        n = len(t) - 2
    return e[:n], e[1 : n + 1], e[2 : n + 2]


def transition_data(
    trajectories: list[np.ndarray],
    stats: dict[str, np.ndarray],
    *,
    cyclic: bool,
    k: int,
    kernel_width: float | None,
    min_std: float,
    velocity_weight: float = 1.0,
    exclusion: int | None = None,
    retention: float = 1.0,
) -> TransitionData:
    """Transition-network instances ``(x[t], x[t+1]) → x[t+2]`` of every clip.

    Parameters
    ----------
    trajectories : list of (T_c, D) float ndarray
    stats : dict
        From :func:`standardization`.
    cyclic : bool
        Wrap each clip's end onto its start (clips are cycles).
    k, kernel_width, min_std, velocity_weight
        Kernel regression parameters.
    exclusion : int, optional
        With one clip: frames around the held-out instance left out (default
        a tenth of the clip, at least 2).
    retention : float
        Fraction of the offset from the neighbours kept per frame (see
        :func:`retention_of`).

    Returns
    -------
    TransitionData
    """
    m, s, ds = stats["mean"], stats["std"], stats["delta_std"]
    Fs, Vs, Ys, Z2s, rows, group, tindex = [], [], [], [], [], [], []
    n0 = 0
    for c, t in enumerate(trajectories):
        a, b, nxt = _triples(t, cyclic)
        n = len(a)
        if n < 1:
            continue
        Fs.append(np.concatenate([(a - m) / s, (b - m) / s], axis=1))
        Vs.append((b - a) / ds * velocity_weight)
        Ys.append((nxt - b) / ds)
        Z2s.append((nxt - m) / s)
        rows.append(np.arange(n0, n0 + n))
        group += [c] * n
        tindex += list(range(n))
        n0 += n
    if not rows:
        raise LearnError("transition network: every clip has fewer than 3 frames")
    group_a = np.asarray(group)
    tindex_a = np.asarray(tindex)
    if exclusion is None:
        exclusion = max(2, int(math.ceil(0.1 * max(len(r) for r in rows))))
    valid = _valid_mask(group_a, tindex_a, int(exclusion))
    avail = int(valid.sum(axis=1).min())
    if avail < 2:
        raise LearnError(
            f"transition network: only {avail} instance(s) left for cross-validation; "
            "give more or longer clips"
        )
    return TransitionData(
        F=np.concatenate(Fs),
        V=np.concatenate(Vs),
        Y=np.concatenate(Ys),
        Z2=np.concatenate(Z2s),
        ratio=ds / s,
        rows=rows,
        group=group_a,
        tindex=tindex_a,
        valid=valid,
        k=min(int(k), avail),
        kernel_width=None if kernel_width is None else float(kernel_width),
        min_std=float(min_std),
        velocity_weight=float(velocity_weight),
        retention=float(retention),
    )


def retention_of(half_life: float | None, rate: float) -> float:
    """Per-frame retention ``λ = 2^(−1 / (half_life · rate))`` of the offset from the neighbours.

    The transition mean is ``x̄[t+2] + λ (x[t+1] − x̄[t+1])`` with ``x̄`` the
    kernel-weighted neighbour values: ``λ = 1`` (``half_life=None``) is pure
    delta regression, ``x[t+1] + mean Δ``; ``λ < 1`` lets a state that left
    the data drift back with the given half-life instead of running away.
    """
    if half_life is None:
        return 1.0
    if not half_life > 0:
        raise LearnError(f"half_life must be > 0 seconds or null, got {half_life}")
    return float(2.0 ** (-1.0 / (half_life * rate)))


#: Name of the normalised-time DOF added by :func:`with_phase` (non-cyclic clips).
PHASE = "_phase"

#: Names of the cycle-phase DOFs added by :func:`with_phase` (cyclic clips): the cosine
#: and sine of ``2π · frame / frames`` of each cycle.
CYCLE_PHASE = ("_phase_cos", "_phase_sin")

#: Every DOF :func:`with_phase` may add; they are internal (variants drop them).
INTERNAL_DOFS = (PHASE, *CYCLE_PHASE)


def with_phase(clips: Clips, *, cyclic: bool | None = None) -> Clips:
    """Clips with phase DOFs: ``_phase`` (non-cyclic) or ``_phase_cos, _phase_sin`` (cycles).

    Non-cyclic clips get ``_phase`` = frame / (frames − 1): a 2nd-order model of
    a non-cyclic motion cannot tell apart states that look alike at different
    times (the loop of an 'a' closing where it started); normalised time
    disambiguates them, varies in speed from clip to clip like any DOF, and
    tells the sampler where a variant ends.

    Cyclic clips (gait cycles, each starting at the same event) get the cycle
    phase ``φ = 2π · frame / frames`` as the pair ``(cos φ, sin φ)``, which wraps
    with the cycle.  Without it the kernel-regression mean dynamics of a walk
    have a second attractor besides the gait cycle: a state near the middle of
    the cycle in state space has neighbours from opposite phases whose deltas
    cancel, so the motion comes to rest there (on the figure-8 walk 5 of 8
    streams from random prior draws stop within a cycle at sigma = 0).  Every
    training instance advances the phase, so the phase DOFs never stall and,
    as parents, hold the other DOFs' neighbourhoods at one phase; the phase
    also tells the sampler where a cycle begins (loopable variants).

    Parameters
    ----------
    clips : Clips
    cyclic : bool, optional
        Which kind of phase (default ``clips.cyclic``).

    Returns
    -------
    Clips
        The clips with the phase DOFs as the last varying columns (unchanged if
        they are there already).
    """
    cyclic = clips.cyclic if cyclic is None else bool(cyclic)
    names = CYCLE_PHASE if cyclic else (PHASE,)
    if any(n in clips.dof_names for n in INTERNAL_DOFS):
        return clips

    def columns(n: int) -> np.ndarray:
        if cyclic:
            a = 2.0 * np.pi * np.arange(n) / max(n, 1)
            return np.stack([np.cos(a), np.sin(a)], axis=1)
        return (np.arange(n) / max(n - 1, 1))[:, None]

    trajs = [np.concatenate([t, columns(len(t))], axis=1) for t in clips.trajectories]
    return clips.replace(
        trajectories=trajs,
        dof_names=[*clips.dof_names, *names],
        varying=np.append(clips.varying, [True] * len(names)),
        constant_values=np.append(clips.constant_values, [0.0] * len(names)),
    )


def phase_columns(names: list[str]) -> tuple[int, ...]:
    """Column indices of the phase DOFs among ``names`` (varying DOF names), in order."""
    return tuple(names.index(n) for n in INTERNAL_DOFS if n in names)


def prior_window_of(clips: Clips, k: int, window: int | None) -> int:
    """The prior window the ``learn`` stage uses for these clips (:func:`prior_window`)."""
    return prior_window(clips.lengths, k, window)
