"""Learning the dynamic Bayesian network of motion variation (Lau, Bar-Joseph & Kuffner 2009, §5).

The model of ``D`` DOFs has two parts.

Prior network
    A Bayesian network over the ``2D`` nodes ``X[0]`` (nodes ``0..D-1``) and
    ``X[1]`` (nodes ``D..2D-1``).  Its training instances are the pairs
    ``(x[t], x[t+1])`` of the first ``w`` frames of every clip (``w`` grows
    when the clips are few: ``prior_window``).
Transition network
    ``X[t], X[t+1] → X[t+2]``, second-order Markov.  Node ``i`` of ``X[t+2]``
    always has the self parents ``X_i[t]`` and ``X_i[t+1]``; further parents
    are searched among the ``2D`` nodes of frames ``t`` and ``t+1``.  The
    regression target is the delta ``X_i[t+2] − X_i[t+1]``; the self parents
    enter the distance as position ``X_i[t+1]`` and velocity
    ``X_i[t+1] − X_i[t]`` (scaled by ``velocity_weight``).

Conditional densities (Eq. 5–6)
    Non-parametric: for a parent value ``u`` the ``k`` nearest training
    instances in (standardised) parent space are weighted by a Gaussian kernel
    ``w_j = exp(−d_j² / 2h²)``; the node is Gaussian with the weighted mean
    and weighted variance (plus ``min_std²``) of the neighbours' values.  The
    bandwidth of each node is ``h = kernel_width · m`` with ``m`` the median
    distance of its training instances to their k-th neighbour; with
    ``kernel_width=None`` (default) the factor is chosen per node and parent
    set from :data:`KERNEL_GRID` by the held-out likelihood, which keeps the
    predictive variance calibrated (a fixed width makes the scores reward
    irrelevant parents that merely widen the kernel).
Score
    Cross-validated log-likelihood.  Prior: each instance predicted from the
    instances of the other clips (leave one sequence out).  Transition
    (``score="propagated"``, default): each held-out clip is re-synthesised
    from its first two frames and the log-likelihood of each true frame given
    the re-synthesised state is summed; to keep the score decomposable (one
    node's parent change re-scores one node) the node's *own* value is
    propagated and the other parents are read from the held-out clip.
    ``score="one_step"`` uses the true previous frames (faster).  With a
    single clip, instances within ``exclusion`` frames of the held-out one are
    left out instead of the whole sequence.
Search
    Greedy hill climbing.  Prior: edge addition, deletion and reversal under
    acyclicity, at most ``max_parents`` parents, from the empty graph and from
    ``restarts`` random DAGs; the single-parent scores of every node are
    computed in parallel through ``ctx.map``.  Transition: parents come only
    from earlier frames, so each node's search (addition/deletion) is
    independent and runs in parallel through ``ctx.map``; each greedy step
    scores all neighbouring parent sets of the node in one vectorised batch.
    Parallel work goes to ``ctx.map`` in ``4 × workers`` round-robin batches of
    nodes (one task per node is too small to amortise the round trip).
    Scores are cached per (node, parent set), so an edge change re-scores only
    the one or two nodes it touches.  Candidate parents are restricted to the
    ``candidates`` most correlated nodes (the sparse candidate algorithm of
    Friedman et al. 1999; ``None`` searches all).

Additions to the paper (each can be switched off)
    ``half_life`` (default 0.5 s): the transition mean keeps only a fraction
    ``λ`` per frame of the state's offset from its neighbours
    (:func:`retention_of`); pure delta regression (``None``) lets a state
    that has left the data run away under sampling noise.  ``phase``
    (default for non-cyclic clips): a normalised-time DOF (:func:`with_phase`)
    that disambiguates look-alike states and ends variants.
    ``kernel_width=None``: per-node bandwidth by held-out likelihood.
    ``candidates``: sparse candidate parents.

Similar-input selection (§9) uses :func:`heldout_log_likelihood`.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context, stage
from mocapflow.pipeline.codecs import Encoded, codec, decode, encode
from mocapflow.stages.variation.clips import ClipError, Clips, flatten_clips

__all__ = [
    "LearnError",
    "PriorData",
    "TransitionData",
    "VariationModel",
    "heldout_log_likelihood",
    "kernel_regression",
    "learn",
    "with_phase",
    "learn_structure",
    "prior_data",
    "prior_node_score",
    "standardization",
    "transition_data",
    "transition_node_score",
]

_LOG2PI = math.log(2.0 * math.pi)


class LearnError(ValueError):
    """Training data that cannot support the network (too few frames or clips)."""


# --------------------------------------------------------------------------- kernel regression


def kernel_regression(
    d2: np.ndarray, y: np.ndarray, *, h2: float | np.ndarray, min_std: float
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian kernel regression on the ``k`` nearest instances (Eq. 5–6).

    Parameters
    ----------
    d2 : (..., k) float ndarray
        Squared distances to the ``k`` nearest training instances.
    y : (..., k) float ndarray
        Their target values.
    h2 : float or (...) float ndarray
        Squared kernel bandwidth: ``w_j = exp(-d_j² / 2 h²)``.
    min_std : float
        Floor added to the standard deviation (as variance ``min_std²``).

    Returns
    -------
    mean : (...) float ndarray
        Kernel-weighted mean of ``y``.
    var : (...) float ndarray
        Kernel-weighted variance of ``y`` + ``min_std²``.
    """
    d2 = np.maximum(d2, 0.0)
    h2 = np.asarray(h2, dtype=np.float64)
    if h2.ndim:
        h2 = h2[..., None]
    w = np.exp(-0.5 * (d2 - d2.min(axis=-1, keepdims=True)) / np.maximum(h2, 1e-300))
    w /= w.sum(axis=-1, keepdims=True)
    mean = (w * y).sum(axis=-1)
    var = (w * (y - mean[..., None]) ** 2).sum(axis=-1) + min_std * min_std
    return mean, var


#: Bandwidths tried per node, as multiples of the median k-th-neighbour distance.
KERNEL_GRID: tuple[float, ...] = (0.25, 0.5, 1.0, 2.0)


def _subrows(n: int, rows: int = 64) -> np.ndarray:
    return np.arange(0, n, max(1, n // rows))


def bandwidth2(
    d2: np.ndarray,
    k: int,
    kernel_width: float | None,
    *,
    y_query: np.ndarray | None = None,
    y_train: np.ndarray | None = None,
    min_std: float = 0.01,
) -> float:
    """Squared kernel bandwidth of a node.

    ``h = kernel_width · m`` with ``m`` the median distance of the held-out
    instances to their k-th neighbour; with ``kernel_width=None`` the factor
    is chosen from :data:`KERNEL_GRID` by the held-out log-likelihood of
    ``y_query`` (so the predictive variance is calibrated per node).

    Parameters
    ----------
    d2 : (R, N) float ndarray
        Squared distances of held-out instances to the training instances
        (``inf`` where not allowed); a subset of rows is enough.
    k : int
    kernel_width : float or None
    y_query : (R,) float ndarray, optional
        Held-out targets (needed when ``kernel_width`` is None).
    y_train : (N,) float ndarray, optional
        Training targets (idem).
    min_std : float

    Returns
    -------
    float
    """
    idx = _knn(d2, k)
    d2k = np.take_along_axis(d2, idx, axis=-1)
    dk = d2k.max(axis=-1)
    dk = dk[np.isfinite(dk)]
    med = max(float(np.median(dk)) if dk.size else 0.0, 1e-12)
    if kernel_width is not None:
        return max(kernel_width * kernel_width * med, 1e-12)
    ok = np.isfinite(d2k).all(axis=-1)
    yk = y_train[idx][ok]
    best = None
    for g in KERNEL_GRID:
        mu, var = kernel_regression(d2k[ok], yk, h2=g * g * med, min_std=min_std)
        ll = float(_gauss_ll(y_query[ok], mu, var).sum())
        if best is None or ll > best[0]:
            best = (ll, g)
    return max(best[1] ** 2 * med, 1e-12)


def _gauss_ll(y: np.ndarray, mean: np.ndarray, var: np.ndarray) -> np.ndarray:
    return -0.5 * (_LOG2PI + np.log(var) + (y - mean) ** 2 / var)


def _knn(d2: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` smallest entries along the last axis (unordered)."""
    if k >= d2.shape[-1]:
        return np.broadcast_to(np.arange(d2.shape[-1]), d2.shape).copy()
    return np.argpartition(d2, k - 1, axis=-1)[..., :k]


# --------------------------------------------------------------------------- training data


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


# --------------------------------------------------------------------------- node scores


def _pair_d2(X: np.ndarray, cols) -> np.ndarray:
    """``(N, N)`` squared distances over columns ``cols`` of ``X``."""
    N = X.shape[0]
    d2 = np.zeros((N, N))
    for c in cols:
        x = X[:, c]
        d2 += (x[:, None] - x[None, :]) ** 2
    return d2


def _masked_kr(d2: np.ndarray, y: np.ndarray, k: int, h2: float, ms: float):
    idx = _knn(d2, k)
    return kernel_regression(np.take_along_axis(d2, idx, axis=-1), y[idx], h2=h2, min_std=ms)


def prior_node_fit(data: PriorData, v: int, parents) -> tuple[float, float]:
    """Cross-validated log-likelihood and squared bandwidth of prior node ``v``.

    Parameters
    ----------
    data : PriorData
    v : int
        Node in ``0..2D-1``.
    parents : iterable of int
        Parent nodes.

    Returns
    -------
    score : float
        Sum over instances of the held-out log density.
    h2 : float
        Squared kernel bandwidth (:func:`bandwidth2`; 0 without parents).
    """
    y = data.Z[:, v]
    parents = list(parents)
    if not parents:
        W = data.valid.astype(np.float64)
        n = W.sum(axis=1)
        mu = W @ y / n
        var = np.maximum(W @ (y * y) / n - mu * mu, 0.0) + data.min_std**2
        return float(_gauss_ll(y, mu, var).sum()), 0.0
    d2 = np.where(data.valid, _pair_d2(data.Z, parents), np.inf)
    sub = _subrows(len(y))
    h2 = bandwidth2(d2[sub], data.k, data.kernel_width, y_query=y[sub], y_train=y,
                    min_std=data.min_std)
    mu, var = _masked_kr(d2, y, data.k, h2, data.min_std)
    return float(_gauss_ll(y, mu, var).sum()), h2


def prior_node_score(data: PriorData, v: int, parents) -> float:
    """Cross-validated log-likelihood of prior node ``v`` (see :func:`prior_node_fit`)."""
    return prior_node_fit(data, v, parents)[0]


def _self_d2(data: TransitionData, i: int, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
    a = data.F[:, data.n_dofs + i]
    b = data.V[:, i]
    return (a[rows, None] - a[None, :]) ** 2 + (b[rows, None] - b[None, :]) ** 2


def transition_node_fit(
    data: TransitionData,
    i: int,
    parents,
    *,
    score: Literal["propagated", "one_step"] = "propagated",
    other_d2: np.ndarray | None = None,
) -> tuple[float, float]:
    """Cross-validated log-likelihood and squared bandwidth of transition node ``i``.

    Parameters
    ----------
    data : TransitionData
    i : int
        DOF index (node ``X_i[t+2]``).
    parents : iterable of int
        Extra parents: ``j`` is ``X_j[t]``, ``D + j`` is ``X_j[t+1]`` (the self
        parents are always included).
    score : {"propagated", "one_step"}
        See module docstring.
    other_d2 : (N, N) float ndarray, optional
        Precomputed squared distances over ``parents`` (speeds up the search).

    Returns
    -------
    score : float
    h2 : float
        Squared bandwidth (:func:`bandwidth2` of the one-step distances).
    """
    if other_d2 is None:
        other_d2 = _pair_d2(data.F, list(parents))
    sc, h2 = transition_node_fits(data, i, other_d2[None], score=score)
    return float(sc[0]), float(h2[0])


def transition_node_fits(
    data: TransitionData,
    i: int,
    other_d2: np.ndarray,
    *,
    score: Literal["propagated", "one_step"] = "propagated",
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`transition_node_fit` of ``M`` parent sets of node ``i`` at once.

    Parameters
    ----------
    data : TransitionData
    i : int
    other_d2 : (M, N, N) float ndarray
        Squared distances over each parent set (self parents excluded).
    score : {"propagated", "one_step"}

    Returns
    -------
    scores : (M,) float ndarray
    h2 : (M,) float ndarray
    """
    D = data.n_dofs
    M, N, _ = other_d2.shape
    k, kw = data.k, data.kernel_width
    penalty = np.where(data.valid, 0.0, np.inf)
    if score == "one_step":
        d2 = other_d2 + (_self_d2(data, i) + penalty)
        sub = _subrows(N)
        y = data.Y[:, i]
        h2 = np.array([
            bandwidth2(d2[m, sub], k, kw, y_query=y[sub], y_train=y, min_std=data.min_std)
            for m in range(M)
        ])
        zc = np.broadcast_to(data.F[:, D + i], (M, N))
        mu, var = _transition_kr(data, i, d2, zc, h2[:, None])
        return _gauss_ll(data.Y[:, i], mu, var).sum(axis=-1), h2
    sub = _subrows(N)
    base = _self_d2(data, i, sub) + penalty[sub]
    y = data.Y[:, i]
    h2 = np.array([
        bandwidth2(other_d2[m, sub] + base, k, kw, y_query=y[sub], y_train=y,
                   min_std=data.min_std)
        for m in range(M)
    ])
    # propagated: re-synthesise node i along every held-out clip at once
    a_tr = data.F[:, D + i]
    b_tr = data.V[:, i]
    r_i = data.ratio[i]
    vw = data.velocity_weight
    rows = data.rows
    L = np.array([len(r) for r in rows])
    first = np.array([r[0] for r in rows])
    zprev = np.tile(data.F[first, i], (M, 1))  # (M, C)
    zcur = np.tile(data.F[first, D + i], (M, 1))
    total = np.zeros(M)
    hh = h2[:, None]
    for t in range(int(L.max())):
        act = np.flatnonzero(L > t)
        R = np.array([rows[c][t] for c in act])
        zp, zc = zprev[:, act], zcur[:, act]  # (M, A)
        bq = (zc - zp) * (vw / r_i)
        d2 = other_d2[:, R] + penalty[R]  # (M, A, N)
        d2 += (zc[..., None] - a_tr) ** 2
        d2 += (bq[..., None] - b_tr) ** 2
        mu, var = _transition_kr(data, i, d2, zc, hh)
        y_true = (data.Z2[R, i] - zc) / r_i
        total += _gauss_ll(y_true, mu, var).sum(axis=-1)
        zprev[:, act] = zc
        zcur[:, act] = zc + mu * r_i
    return total, h2


def _transition_kr(data: TransitionData, i: int, d2: np.ndarray, zc: np.ndarray, h2):
    """Mean and variance of node ``i``'s delta (delta-std units) given distances ``d2 (..., N)``.

    ``zc (...)`` is the node's current standardised value, ``h2`` broadcasts to
    ``zc``.  The mean includes the retention term ``(λ − 1)(z − z̄)`` of
    :func:`retention_of`.
    """
    idx = _knn(d2, data.k)
    d2k = np.take_along_axis(d2, idx, axis=-1)
    mu, var = kernel_regression(d2k, data.Y[idx, i], h2=h2, min_std=data.min_std)
    if data.retention < 1.0:
        zbar, _ = kernel_regression(d2k, data.F[idx, data.n_dofs + i], h2=h2, min_std=0.0)
        mu = mu + (data.retention - 1.0) * (zc - zbar) / data.ratio[i]
    return mu, var


def transition_node_score(data: TransitionData, i: int, parents, **kw: Any) -> float:
    """Cross-validated log-likelihood of transition node ``i`` (see :func:`transition_node_fit`)."""
    return transition_node_fit(data, i, parents, **kw)[0]


# --------------------------------------------------------------------------- searches


def _top_candidates(target: np.ndarray, pool: np.ndarray, idx: list[int], m: int | None):
    """The ``m`` columns of ``pool`` (indices ``idx``) most correlated with ``target``."""
    if m is None or m >= len(idx):
        return list(idx)
    t = (target - target.mean(axis=0)) / (target.std(axis=0) + 1e-12)
    p = pool[:, idx]
    p = (p - p.mean(axis=0)) / (p.std(axis=0) + 1e-12)
    corr = np.abs(t.T @ p / len(t))  # (n_targets, n_idx)
    corr = corr.max(axis=0) if corr.ndim == 2 else corr
    order = np.argsort(-corr, kind="stable")[:m]
    return sorted(int(idx[o]) for o in order)


def _search_transition_node(
    item: tuple[int, list[int]],
    *,
    data: TransitionData,
    max_parents: int,
    score: str,
    batch: int = 16,
) -> dict[str, Any]:
    """Greedy add/delete search of one transition node's parents (module level for ``ctx.map``).

    Each step scores every uncached neighbouring parent set in batches of
    ``batch`` (:func:`transition_node_fits`) and moves to the best while it improves.
    """
    i, cands = item
    cache: dict[frozenset, tuple[float, float]] = {}
    feats = {c: (data.F[:, c][:, None] - data.F[:, c][None, :]) ** 2 for c in cands}
    t0 = time.perf_counter()

    def d2_of(P: frozenset) -> np.ndarray:
        d2 = np.zeros((data.F.shape[0],) * 2)
        for c in P:
            d2 += feats[c]
        return d2

    def evaluate(sets: list[frozenset]) -> None:
        todo = [Q for Q in dict.fromkeys(sets) if Q not in cache]
        for a in range(0, len(todo), batch):
            chunk = todo[a : a + batch]
            sc, h2 = transition_node_fits(
                data, i, np.stack([d2_of(Q) for Q in chunk]), score=score
            )
            for Q, v, h in zip(chunk, sc, h2):
                cache[Q] = (float(v), float(h))

    P: frozenset = frozenset()
    evaluate([P])
    cur = cache[P][0]
    while True:
        moves = [P - {c} for c in P]
        if len(P) < max_parents:
            moves += [P | {c} for c in cands if c not in P]
        if not moves:
            break
        evaluate(moves)
        best = max(moves, key=lambda Q: cache[Q][0])
        if cache[best][0] <= cur + 1e-9:
            break
        P, cur = best, cache[best][0]
    return {
        "parents": sorted(int(p) for p in P),
        "score": float(cur),
        "bandwidth": math.sqrt(cache[P][1]),
        "evaluations": len(cache),
        "seconds": time.perf_counter() - t0,
    }


def _run_batch(items: list, *, fn) -> list:
    """``[fn(x) for x in items]`` (module level for ``ctx.map``)."""
    return [fn(x) for x in items]


def _map_batched(ctx: Context, fn, items: list, *, per_worker: int = 4) -> list:
    """``ctx.map(fn, items)`` over ``per_worker × workers`` round-robin batches of the items.

    One task per node is too small to amortise a round trip to a worker (and
    the pickled training data travels with every task); interleaving keeps
    the batches balanced when the per-node cost grows along the list.
    """
    n = min(len(items), max(1, per_worker * int(getattr(ctx, "workers", 1) or 1)))
    if n <= 1 or ctx.mapper is None:
        return ctx.map(fn, items)
    batches = [items[b::n] for b in range(n)]
    done = ctx.map(functools.partial(_run_batch, fn=fn), batches)
    out: list = [None] * len(items)
    for b, res in enumerate(done):
        out[b::n] = res
    return out


def _prior_single_scores(v_cands: tuple[int, list[int]], *, data: PriorData) -> dict:
    """Scores of node ``v`` with no parent and with each single candidate parent."""
    v, cands = v_cands
    out = {(): prior_node_fit(data, v, [])}
    for u in cands:
        out[(u,)] = prior_node_fit(data, v, [u])
    return out


class _DAG:
    """Parent sets with acyclicity checks."""

    def __init__(self, n: int):
        self.parents: list[set[int]] = [set() for _ in range(n)]
        self.children: list[set[int]] = [set() for _ in range(n)]

    def reaches(self, src: int, dst: int, skip: tuple[int, int] | None = None) -> bool:
        """Whether a directed path ``src ⇝ dst`` exists (ignoring edge ``skip``)."""
        stack, seen = [src], {src}
        while stack:
            a = stack.pop()
            if a == dst:
                return True
            for b in self.children[a]:
                if skip is not None and (a, b) == skip:
                    continue
                if b not in seen:
                    seen.add(b)
                    stack.append(b)
        return False

    def add(self, u: int, v: int) -> None:
        self.parents[v].add(u)
        self.children[u].add(v)

    def remove(self, u: int, v: int) -> None:
        self.parents[v].discard(u)
        self.children[u].discard(v)

    def order(self) -> list[int]:
        """A topological order."""
        indeg = [len(p) for p in self.parents]
        ready = [v for v, d in enumerate(indeg) if d == 0]
        out = []
        while ready:
            a = ready.pop(0)
            out.append(a)
            for b in sorted(self.children[a]):
                indeg[b] -= 1
                if indeg[b] == 0:
                    ready.append(b)
        return out


def _prior_greedy(
    data: PriorData,
    cands: list[list[int]],
    cache: dict,
    *,
    max_parents: int,
    init: list[list[int]] | None,
) -> tuple[list[list[int]], np.ndarray]:
    n = len(cands)
    dag = _DAG(n)
    if init:
        for v, ps in enumerate(init):
            for u in ps:
                dag.add(u, v)

    def S(v: int, P) -> float:
        key = (v, tuple(sorted(P)))
        if key not in cache:
            cache[key] = prior_node_fit(data, v, key[1])
        return cache[key][0]

    cur = np.array([S(v, dag.parents[v]) for v in range(n)])
    node_moves: dict[int, list[tuple[float, str, int]]] = {}

    def refresh(v: int) -> None:
        P = dag.parents[v]
        moves = []
        if len(P) < max_parents:
            for u in cands[v]:
                if u not in P:
                    moves.append((S(v, P | {u}) - cur[v], "add", u))
        for u in P:
            moves.append((S(v, P - {u}) - cur[v], "del", u))
        node_moves[v] = moves

    for v in range(n):
        refresh(v)
    for _ in range(100 * n):
        ops = [(d, kind, u, v) for v in range(n) for d, kind, u in node_moves[v] if d > 1e-9]
        # reversals u→v  ⇒  v→u
        for v in range(n):
            for u in dag.parents[v]:
                if len(dag.parents[u]) >= max_parents:
                    continue
                d = (S(v, dag.parents[v] - {u}) - cur[v]) + (S(u, dag.parents[u] | {v}) - cur[u])
                if d > 1e-9:
                    ops.append((d, "rev", u, v))
        if not ops:
            break
        ops.sort(key=lambda o: -o[0])
        applied = False
        for _, kind, u, v in ops:
            if kind == "add":
                if dag.reaches(v, u):
                    continue
                dag.add(u, v)
                touched = [v]
            elif kind == "del":
                dag.remove(u, v)
                touched = [v]
            else:
                if dag.reaches(u, v, skip=(u, v)):
                    continue
                dag.remove(u, v)
                dag.add(v, u)
                touched = [u, v]
            for t in touched:
                cur[t] = S(t, dag.parents[t])
            for t in touched:
                refresh(t)
            applied = True
            break
        if not applied:
            break
    parents = [sorted(p) for p in dag.parents]
    h = np.array([math.sqrt(cache[(v, tuple(parents[v]))][1]) for v in range(n)])
    return parents, cur, h


def _random_dag(cands: list[list[int]], rng: np.random.Generator, max_parents: int):
    n = len(cands)
    rank = np.empty(n, dtype=int)
    rank[rng.permutation(n)] = np.arange(n)
    init = []
    for v in range(n):
        ok = [u for u in cands[v] if rank[u] < rank[v]]
        m = min(len(ok), int(rng.integers(0, 3)), max_parents)
        init.append([int(u) for u in rng.choice(ok, size=m, replace=False)] if m else [])
    return init


def learn_structure(
    clips: Clips,
    *,
    k: int = 15,
    kernel_width: float | None = None,
    min_std: float = 0.01,
    velocity_weight: float = 1.0,
    max_parents: int = 8,
    candidates: int | None = 20,
    restarts: int = 2,
    prior_window: int | None = None,
    score: Literal["propagated", "one_step"] = "propagated",
    half_life: float | None = 0.5,
    phase: bool | None = None,
    cyclic: bool | None = None,
    seed: int = 0,
    ctx: Context | None = None,
) -> VariationModel:
    """Learn the prior and transition networks from clips (see module docstring).

    Parameters
    ----------
    clips : Clips
        ``C`` clips of ``D`` varying DOFs.
    k : int
        Nearest instances of the kernel regression (paper: 15–60).
    kernel_width : float or None
        Kernel bandwidth as a multiple of the median k-th neighbour distance;
        ``None``: chosen per node by held-out likelihood.
    min_std : float
        Standard-deviation floor (standardised units).
    velocity_weight : float
        Weight of the self velocity in the transition distance.
    max_parents : int
        At most this many parents per node (besides the transition self parents).
    candidates : int or None
        Candidate parents per node (most correlated); ``None``: all.
    restarts : int
        Random restarts of the prior-network search.
    prior_window : int, optional
        Prior instances per clip (default: enough for ``2(k+1)`` held-out
        neighbours).
    score : {"propagated", "one_step"}
        Transition score.
    half_life : float or None
        Seconds; offset retention of the transition mean (:func:`retention_of`);
        ``None``: pure delta regression.
    phase : bool, optional
        Add the DOF ``_phase`` = frame / last frame of each clip (default: for
        non-cyclic clips), a parent candidate like any DOF (see :func:`with_phase`).
    cyclic : bool, optional
        Default ``clips.cyclic``.
    seed : int
        Seed of the restarts.
    ctx : Context, optional
        Parallel map (per node) and warnings.

    Returns
    -------
    VariationModel
    """
    ctx = ctx or Context()
    t0 = time.perf_counter()
    D = clips.n_dofs
    if D == 0:
        raise LearnError(
            "no varying DOF: every DOF is constant over all clips "
            f"({len(clips.dof_names)} constant DOFs)"
        )
    if k < 2:
        raise LearnError(f"k must be at least 2, got {k}")
    if not 15 <= k <= 60:
        ctx.warn(f"k = {k} is outside the paper's range 15–60")
    if kernel_width is not None and not kernel_width > 0:
        raise LearnError(f"kernel_width must be > 0 or null, got {kernel_width}")
    cyclic = clips.cyclic if cyclic is None else bool(cyclic)
    if phase is None:
        phase = not cyclic
    if phase:
        clips = with_phase(clips)
        D = clips.n_dofs
    trajs = clips.trajectories
    if clips.n_clips == 1:
        ctx.warn(
            "only one input clip: held-out scores leave out nearby frames instead of whole "
            "clips, and variants stay close to the input"
        )
    stats = standardization(trajs)
    tdata = transition_data(
        trajs,
        stats,
        cyclic=cyclic,
        k=k,
        kernel_width=kernel_width,
        min_std=min_std,
        velocity_weight=velocity_weight,
        retention=retention_of(half_life, clips.rate),
    )
    pdata = prior_data(
        trajs, stats, k=k, kernel_width=kernel_width, min_std=min_std, window=prior_window
    )
    for name, dk in (("transition", tdata.k), ("prior", pdata.k)):
        if dk < k:
            ctx.warn(f"{name} network: k reduced from {k} to {dk} (too few held-out instances)")

    # transition network: independent per node
    t1 = time.perf_counter()
    pool = list(range(2 * D))
    items = []
    for i in range(D):
        idx = [p for p in pool if p not in (i, D + i)]
        target = np.stack([tdata.Y[:, i], tdata.Z2[:, i]], axis=1)
        items.append((i, _top_candidates(target, tdata.F, idx, candidates)))
    base_seed = int(seed)
    fn = functools.partial(
        _search_transition_node, data=tdata, max_parents=max_parents, score=score
    )
    results = _map_batched(ctx, fn, items)
    t_parents = [r["parents"] for r in results]
    t_scores = np.array([r["score"] for r in results])
    t_band = np.array([r["bandwidth"] for r in results])
    t_evals = int(sum(r["evaluations"] for r in results))
    t_trans = time.perf_counter() - t1

    # prior network: greedy DAG search with add / delete / reverse
    t2 = time.perf_counter()
    n2 = 2 * D
    p_cands = [
        _top_candidates(pdata.Z[:, v], pdata.Z, [u for u in range(n2) if u != v], candidates)
        for v in range(n2)
    ]
    singles = _map_batched(
        ctx, functools.partial(_prior_single_scores, data=pdata), list(enumerate(p_cands))
    )
    cache: dict = {}
    for v, sc in enumerate(singles):
        for P, s in sc.items():
            cache[(v, P)] = s
    best = None
    rng = np.random.default_rng([base_seed, 7919])
    for r in range(restarts + 1):
        init = None if r == 0 else _random_dag(p_cands, rng, max_parents)
        parents, sc, h = _prior_greedy(pdata, p_cands, cache, max_parents=max_parents, init=init)
        if best is None or sc.sum() > best[1].sum():
            best = (parents, sc, h)
    p_parents, p_scores, p_band = best
    t_prior = time.perf_counter() - t2
    return VariationModel(
        clips=clips.replace(cyclic=cyclic),
        prior_parents=p_parents,
        transition_parents=t_parents,
        params={
            "k": int(k),
            "k_prior": int(pdata.k),
            "k_transition": int(tdata.k),
            "kernel_width": None if kernel_width is None else float(kernel_width),
            "min_std": float(min_std),
            "velocity_weight": float(velocity_weight),
            "prior_window": int(prior_window_of(clips, k, prior_window)),
            "score": score,
            "cyclic": cyclic,
            "half_life": half_life,
            "retention": retention_of(half_life, clips.rate),
            "phase": bool(phase),
        },
        prior_scores=p_scores,
        transition_scores=t_scores,
        prior_bandwidth=p_band,
        transition_bandwidth=t_band,
        attrs={
            "seconds": {
                "total": time.perf_counter() - t0,
                "transition": t_trans,
                "prior": t_prior,
            },
            "evaluations": {"transition": t_evals, "prior": len(cache)},
        },
    )


PHASE = "_phase"


def with_phase(clips: Clips) -> Clips:
    """Clips with the extra DOF ``_phase`` = frame / (frames − 1) of each clip.

    A 2nd-order model of a non-cyclic motion cannot tell apart states that
    look alike at different times (the loop of an 'a' closing where it
    started); normalised time disambiguates them, varies in speed from clip
    to clip like any DOF, and tells the sampler where a variant ends.
    """
    if PHASE in clips.dof_names:
        return clips
    trajs = [
        np.concatenate([t, (np.arange(len(t)) / max(len(t) - 1, 1))[:, None]], axis=1)
        for t in clips.trajectories
    ]
    return clips.replace(
        trajectories=trajs,
        dof_names=[*clips.dof_names, PHASE],
        varying=np.append(clips.varying, True),
        constant_values=np.append(clips.constant_values, 0.0),
    )


def prior_window_of(clips: Clips, k: int, window: int | None) -> int:
    """The prior window :func:`learn_structure` uses for these clips."""
    return prior_window(clips.lengths, k, window)


# --------------------------------------------------------------------------- model type


@dataclass(eq=False)
class VariationModel:
    """A learned DBN of motion variation plus its training clips.

    Parameters
    ----------
    clips : Clips
        Training clips (kernel regression is non-parametric: the data is the model).
    prior_parents : list of list of int
        ``2D`` parent lists over nodes ``0..2D-1`` (``X[0]``, then ``X[1]``).
    transition_parents : list of list of int
        ``D`` parent lists over ``0..2D-1`` (``X[t]``, then ``X[t+1]``), self
        parents implicit.
    params : dict
        Kernel regression parameters used (``k``, ``kernel_width``,
        ``min_std``, ``velocity_weight``, ``prior_window``, ``cyclic``, ...).
    prior_scores : (2D,) float ndarray
    transition_scores : (D,) float ndarray
        Cross-validated log-likelihood of each node.
    prior_bandwidth : (2D,) float ndarray, optional
    transition_bandwidth : (D,) float ndarray, optional
        Kernel bandwidth of each node (standardised units); computed from the
        training data when not given.
    attrs : dict
        Timings, evaluation counts.
    """

    clips: Clips
    prior_parents: list[list[int]]
    transition_parents: list[list[int]]
    params: dict[str, Any]
    prior_scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    transition_scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    prior_bandwidth: np.ndarray | None = None
    transition_bandwidth: np.ndarray | None = None
    attrs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        D = self.clips.n_dofs
        self.prior_parents = [[int(u) for u in p] for p in self.prior_parents]
        self.transition_parents = [[int(u) for u in p] for p in self.transition_parents]
        if len(self.prior_parents) != 2 * D or len(self.transition_parents) != D:
            raise LearnError(
                f"model: {len(self.prior_parents)} prior / {len(self.transition_parents)} "
                f"transition parent lists for {D} DOFs"
            )
        self.prior_scores = np.asarray(self.prior_scores, dtype=np.float64)
        self.transition_scores = np.asarray(self.transition_scores, dtype=np.float64)
        if self.prior_bandwidth is None or self.transition_bandwidth is None:
            self.prior_bandwidth, self.transition_bandwidth = _bandwidths(self)
        self.prior_bandwidth = np.asarray(self.prior_bandwidth, dtype=np.float64).reshape(2 * D)
        self.transition_bandwidth = np.asarray(
            self.transition_bandwidth, dtype=np.float64
        ).reshape(D)

    @property
    def n_dofs(self) -> int:
        """``D``."""
        return self.clips.n_dofs

    def edges(self) -> dict[str, int]:
        """Edge counts (prior; transition extra parents, self edges excluded)."""
        return {
            "prior": sum(len(p) for p in self.prior_parents),
            "transition": sum(len(p) for p in self.transition_parents),
        }


def _bandwidths(m: VariationModel) -> tuple[np.ndarray, np.ndarray]:
    """Per-node bandwidths of a model's structure from its training data (one-step)."""
    p = m.params
    trajs = m.clips.trajectories
    stats = standardization(trajs)
    kw = dict(k=p["k"], kernel_width=p["kernel_width"], min_std=p["min_std"])
    td = transition_data(
        trajs, stats, cyclic=bool(p["cyclic"]), velocity_weight=p["velocity_weight"],
        retention=float(p.get("retention", 1.0)), **kw,
    )
    pd = prior_data(trajs, stats, window=p["prior_window"], **kw)
    hp = [math.sqrt(prior_node_fit(pd, v, ps)[1]) for v, ps in enumerate(m.prior_parents)]
    ht = [
        math.sqrt(transition_node_fit(td, i, ps, score="one_step")[1])
        for i, ps in enumerate(m.transition_parents)
    ]
    return np.array(hp), np.array(ht)


def _encode_model(m: VariationModel) -> Encoded:
    e = encode(m.clips)
    arrays = {f"clips_{k}": v for k, v in e.arrays.items()}
    arrays["prior_scores"] = (m.prior_scores, ("prior_node",))
    arrays["transition_scores"] = (m.transition_scores, ("dof",))
    arrays["prior_bandwidth"] = (m.prior_bandwidth, ("prior_node",))
    arrays["transition_bandwidth"] = (m.transition_bandwidth, ("dof",))
    return Encoded(
        "variation_model",
        arrays,
        {
            "clips": e.attrs,
            "prior_parents": m.prior_parents,
            "transition_parents": m.transition_parents,
            "params": m.params,
            "attrs": m.attrs,
        },
    )


def _decode_model(e: Encoded) -> VariationModel:
    arrs = {k[len("clips_") :]: v for k, v in e.arrays.items() if k.startswith("clips_")}
    clips = decode(Encoded("clips", arrs, e.attrs["clips"]))
    return VariationModel(
        clips=clips,
        prior_parents=e.attrs["prior_parents"],
        transition_parents=e.attrs["transition_parents"],
        params=e.attrs["params"],
        prior_scores=e.arrays["prior_scores"][0],
        transition_scores=e.arrays["transition_scores"][0],
        prior_bandwidth=e.arrays["prior_bandwidth"][0],
        transition_bandwidth=e.arrays["transition_bandwidth"][0],
        attrs=e.attrs.get("attrs", {}),
    )


codec("variation_model", encode=_encode_model, decode=_decode_model)(VariationModel)


# --------------------------------------------------------------------------- §9 helper


def heldout_log_likelihood(
    train: list[np.ndarray],
    test: list[np.ndarray],
    *,
    cyclic: bool = False,
    transition_parents: list[list[int]] | None = None,
    k: int = 15,
    kernel_width: float | None = None,
    min_std: float = 0.01,
    velocity_weight: float = 1.0,
    statistic: Literal["mean", "median"] = "median",
) -> np.ndarray:
    """Per-frame log-likelihood of test clips under a transition network.

    Parameters
    ----------
    train : list of (T_c, D) float ndarray
        Training clips (kernel regression data; standardisation).
    test : list of (T_c, D) float ndarray
        Clips to score.
    cyclic : bool
    transition_parents : list of list of int, optional
        Extra parents per DOF (default: self parents only).
    k, kernel_width, min_std, velocity_weight
        Kernel regression parameters.
    statistic : {"median", "mean"}
        Summary over frames of the per-frame log density (mean over DOFs);
        the median is robust to the few frames a small training set cannot
        predict.

    Returns
    -------
    (len(test),) float ndarray
        Per-frame one-step log density (standardised delta units).
    """
    stats = standardization(train)
    common = dict(kernel_width=kernel_width, min_std=min_std, velocity_weight=velocity_weight)
    tr = transition_data(train, stats, cyclic=cyclic, k=k, **common)
    D = tr.n_dofs
    parents = transition_parents or [[] for _ in range(D)]
    kk = min(k, tr.F.shape[0])
    h2s = [transition_node_fit(tr, i, parents[i], score="one_step")[1] for i in range(D)]
    out = []
    for t in test:
        te = transition_data([t], stats, cyclic=cyclic, k=2, exclusion=0, **common)
        ll = np.zeros(te.F.shape[0])
        for i in range(D):
            d2 = np.zeros((te.F.shape[0], tr.F.shape[0]))
            for c in [D + i, *parents[i]]:
                d2 += (te.F[:, c][:, None] - tr.F[:, c][None, :]) ** 2
            d2 += (te.V[:, i][:, None] - tr.V[:, i][None, :]) ** 2
            mu, var = _masked_kr(d2, tr.Y[:, i], kk, h2s[i], min_std)
            ll += _gauss_ll(te.Y[:, i], mu, var)
        per_frame = ll / D
        out.append(float(np.median(per_frame) if statistic == "median" else per_frame.mean()))
    return np.asarray(out)


# --------------------------------------------------------------------------- the stage


@stage("learn", outputs=("model", "report"))
def learn(
    clips: Any,
    *,
    k: int = 15,
    kernel_width: float | None = None,
    min_std: float = 0.01,
    velocity_weight: float = 1.0,
    max_parents: int = 8,
    candidates: int | None = 20,
    restarts: int = 2,
    prior_window: int | None = None,
    score: Literal["propagated", "one_step"] = "propagated",
    half_life: float | None = 0.5,
    phase: bool | None = None,
    cyclic: bool | None = None,
    seed: int = 0,
    ctx: Context,
) -> dict:
    """Learn the prior and transition networks of motion variation (Lau et al. 2009, §5).

    Parameters
    ----------
    clips : Clips or list of Clips
        Training clips (a gather input is a list; it is merged).
    k : int
        Nearest instances of the kernel regression (paper: 15–60).
    kernel_width : float or None
        Bandwidth as a multiple of the median k-th neighbour distance
        (``None``: chosen per node by held-out likelihood).
    min_std : float
        Standard-deviation floor, standardised units.
    velocity_weight : float
        Weight of the self velocity in the transition distance.
    max_parents : int
        Parents per node at most (paper: 2–15).
    candidates : int or None
        Candidate parents per node (sparse candidate search); ``None``: all.
    restarts : int
        Random restarts of the prior-network search.
    prior_window : int, optional
        Prior training frames per clip.
    score : {"propagated", "one_step"}
        Transition network score (see module docstring).
    half_life : float or None
        Seconds; offset retention of the transition mean (``None``: pure delta
        regression, which can run away from the data under noise).
    phase : bool, optional
        Add a normalised-time DOF ``_phase`` (default: for non-cyclic clips).
    cyclic : bool, optional
        Override ``clips.cyclic``.
    seed : int
        Seed of the random restarts.
    ctx : Context

    Returns
    -------
    dict
        ``model`` (:class:`VariationModel`) and ``report`` (JSON: sizes, k used,
        edge counts, parents per node, scores, seconds).
    """
    try:
        data = flatten_clips(clips)
    except ClipError as e:
        raise LearnError(str(e)) from None
    model = learn_structure(
        data,
        k=k,
        kernel_width=kernel_width,
        min_std=min_std,
        velocity_weight=velocity_weight,
        max_parents=max_parents,
        candidates=candidates,
        restarts=restarts,
        prior_window=prior_window,
        score=score,
        half_life=half_life,
        phase=phase,
        cyclic=cyclic,
        seed=seed,
        ctx=ctx,
    )
    tp = [len(p) for p in model.transition_parents]
    pp = [len(p) for p in model.prior_parents]
    report = {
        "n_clips": data.n_clips,
        "n_dofs": data.n_dofs,
        "frames": int(data.lengths.sum()),
        "k_prior": model.params["k_prior"],
        "k_transition": model.params["k_transition"],
        "edges": model.edges(),
        "transition_parents_mean": float(np.mean(tp) + 2),
        "prior_parents_max": int(max(pp)),
        "prior_score": float(model.prior_scores.sum()),
        "transition_score": float(model.transition_scores.sum()),
        "seconds": model.attrs["seconds"],
        "evaluations": model.attrs["evaluations"],
    }
    return {"model": model, "report": report}
