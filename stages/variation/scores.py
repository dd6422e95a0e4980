"""Leave-one-out kernel-regression score of one DBN node (Lau, Bar-Joseph & Kuffner 2009, §5).

A node's score for a parent set is its cross-validated log-likelihood under the
kernel regression of :mod:`~mocapflow.stages.variation.kernel` (Lau Eq. 5–6).

Prior network (:func:`prior_node_fit`)
    Each instance is predicted from the instances of the other clips (leave one
    sequence out; with one clip, from instances outside an exclusion window).
Transition network (:func:`transition_node_fits`)
    ``score="propagated"`` (default): each held-out clip is re-synthesised from
    its first two frames and the log-likelihood of each true frame given the
    re-synthesised state is summed; to keep the score decomposable (one node's
    parent change re-scores one node) the node's *own* value is propagated and
    the other parents are read from the held-out clip.  ``horizon=H`` (an
    addition) re-anchors the propagated state to the held-out clip's true
    frames every ``H`` frames, and adds to each frame's predictive variance
    the variances accumulated along the run since the last anchor (the
    re-synthesised state's own uncertainty, in the node's delta units, so the
    floor scales with how far the state can have drifted) and a floor of
    ``min_std`` *position* standard deviations (``min_std / ratio`` delta
    standard deviations: scale-aware where the delta std is tiny against the
    position's, as for a phase DOF whose deltas are nearly constant), so a run that
    drifts away from the data costs at most ``H`` frames of error, each
    judged against the run's spread, instead of the rest of the clip (with the
    paper's unbounded propagation, ``horizon=None``, a few runaway frames can
    outweigh every other frame and decide the structure); ``horizon=1`` is the
    one-step score.  ``score="one_step"``
    uses the true previous frames (faster).  The transition mean includes the
    retention term of :func:`~mocapflow.stages.variation.training.retention_of`.
Speed (the structure search scores thousands of parent sets)
    A node's parent sets are scored together (:func:`transition_node_fits`,
    :func:`prior_node_fits`); the propagated score picks each step's k nearest
    on ``d² − |query|²`` (one product per step;
    :func:`~mocapflow.stages.variation.kernel.k_nearest` selects in float32 and
    falls back to float64 on rounding ties) and sums the k chosen distances
    exactly; the delta and the retention's ``z̄`` share one set of kernel
    weights.  The scores equal the plain per-set computation to rounding
    (``tests/stages/variation/test_scores.py``).
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np

from mocapflow.stages.variation.kernel import (
    bandwidth2,
    bandwidth2_of_nearest,
    bandwidth_rows,
    gauss_log_density,
    k_nearest,
    kernel_regression,
    kernel_weights,
    weighted_mean_var,
)
from mocapflow.stages.variation.training import PriorData, TransitionData

__all__ = [
    "prior_node_fit",
    "prior_node_fits",
    "prior_node_score",
    "transition_node_fit",
    "transition_node_fits",
    "transition_node_retention",
    "transition_node_score",
]


def _pair_d2(X: np.ndarray, cols) -> np.ndarray:
    """``(N, N)`` squared distances over columns ``cols`` of ``X``."""
    N = X.shape[0]
    d2 = np.zeros((N, N))
    for c in cols:
        x = X[:, c]
        d2 += (x[:, None] - x[None, :]) ** 2
    return d2


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
    sc, h2 = prior_node_fits(data, v, [parents])
    return float(sc[0]), float(h2[0])


def prior_node_fits(data: PriorData, v: int, parent_sets, *,
                    pair_d2: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`prior_node_fit` of ``M`` parent sets of node ``v`` at once.

    Parameters
    ----------
    data : PriorData
    v : int
    parent_sets : sequence of iterables of int
        ``M`` parent sets (the distances sum the parents in the order given).
    pair_d2 : dict, optional
        Cache of each node's ``(N, N)`` squared distances (and a scratch
        buffer), filled as needed (shared across calls by the search).

    Returns
    -------
    scores : (M,) float ndarray
    h2 : (M,) float ndarray
        0 for an empty set.
    """
    y = data.Z[:, v]
    sets = [list(P) for P in parent_sets]
    scores = np.empty(len(sets))
    h2 = np.zeros(len(sets))
    full = [m for m, P in enumerate(sets) if P]
    for m, P in enumerate(sets):
        if not P:
            W = data.valid.astype(np.float64)
            n = W.sum(axis=1)
            mu = W @ y / n
            var = np.maximum(W @ (y * y) / n - mu * mu, 0.0) + data.min_std**2
            scores[m] = gauss_log_density(y, mu, var).sum()
    if not full:
        return scores, h2
    cache = {} if pair_d2 is None else pair_d2
    N = len(y)
    buf = cache.get("scratch")  # reused: fresh (M, N, N) arrays cost page faults
    if buf is None or buf.shape[0] < len(full) or buf.shape[1] != N:
        buf = cache["scratch"] = np.empty((len(full), N, N))
    d2 = buf[: len(full)]
    d2[...] = 0.0
    for j, m in enumerate(full):
        for c in sets[m]:
            if c not in cache:
                cache[c] = _pair_d2(data.Z, [c])
            d2[j] += cache[c]
    d2[:, ~data.valid] = np.inf
    idx = k_nearest(d2, data.k)
    d2k = np.take_along_axis(d2, idx, axis=-1)
    sub = bandwidth_rows(N)  # the bandwidth's held-out rows (their k nearest found above)
    hs = np.array([
        bandwidth2_of_nearest(d2k[j, sub], idx[j, sub], data.kernel_width, y_query=y[sub],
                              y_train=y, min_std=data.min_std)
        for j in range(len(full))
    ])
    mu, var = kernel_regression(d2k, y[idx], h2=hs[:, None], min_std=data.min_std)
    scores[full] = gauss_log_density(y, mu, var).sum(axis=-1)
    h2[full] = hs
    return scores, h2


def prior_node_score(data: PriorData, v: int, parents) -> float:
    """Cross-validated log-likelihood of prior node ``v`` (see :func:`prior_node_fit`)."""
    return prior_node_fit(data, v, parents)[0]


def _self_d2(data: TransitionData, i: int, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
    """Squared distances over node ``i``'s self parents (position and velocity): ``(R, N)``."""
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
    horizon: int | None = None,
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
        See the module docstring.
    other_d2 : (N, N) float ndarray, optional
        Precomputed squared distances over ``parents`` (speeds up the search).
    horizon : int or None
        Propagated score only: frames between re-anchorings to the true
        state (see the module docstring; ``None``: never, the paper's form).

    Returns
    -------
    score : float
    h2 : float
        Squared bandwidth (:func:`bandwidth2` of the one-step distances).
    """
    if other_d2 is None:
        other_d2 = _pair_d2(data.F, list(parents))
    sc, h2 = transition_node_fits(data, i, other_d2[None], score=score, horizon=horizon)
    return float(sc[0]), float(h2[0])


def transition_node_fits(
    data: TransitionData,
    i: int,
    other_d2: np.ndarray,
    *,
    score: Literal["propagated", "one_step"] = "propagated",
    horizon: int | None = None,
    per_frame: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`transition_node_fit` of ``M`` parent sets of node ``i`` at once.

    Parameters
    ----------
    data : TransitionData
    i : int
    other_d2 : (M, N, N) float ndarray
        Squared distances over each parent set (self parents excluded).
    score : {"propagated", "one_step"}
    horizon : int or None
        Frames between re-anchorings of the propagated state (``None``: never).
    per_frame : bool
        Return each instance's held-out log density, ``(M, N)``, instead of
        the sums (for diagnostics: which frames decide a score).

    Returns
    -------
    scores : (M,) float ndarray
    h2 : (M,) float ndarray
    """
    if score not in ("propagated", "one_step"):
        raise ValueError(f"score must be 'propagated' or 'one_step', got {score!r}")
    if horizon is not None and (
        isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer, float))
        or not np.isfinite(horizon) or int(horizon) != horizon or horizon < 1
    ):
        raise ValueError(f"horizon must be a whole number of frames >= 1 or None, got {horizon!r}")
    D = data.n_dofs
    M, N, _ = other_d2.shape
    k, kw = data.k, data.kernel_width
    penalty = np.where(data.valid, 0.0, np.inf)
    y = data.Y[:, i]
    sub = bandwidth_rows(N)
    if score == "one_step":
        d2 = other_d2 + (_self_d2(data, i) + penalty)
        h2 = bandwidth2(d2[:, sub], k, kw, y_query=y[sub], y_train=y, min_std=data.min_std)
        zc = np.broadcast_to(data.F[:, D + i], (M, N))
        mu, var = _transition_kr(data, i, d2, zc, h2[:, None])
        lp = gauss_log_density(y, mu, var)
        return (lp if per_frame else lp.sum(axis=-1)), h2
    base = _self_d2(data, i, sub) + penalty[sub]
    h2 = bandwidth2(other_d2[:, sub] + base, k, kw, y_query=y[sub], y_train=y,
                    min_std=data.min_std)
    # propagated: re-synthesise node i along every held-out clip at once,
    # all clips' frame t per step
    a_tr = data.F[:, D + i]
    b_tr = data.V[:, i]
    r_i = data.ratio[i]
    vw = data.velocity_weight
    rows = data.rows
    L = np.array([len(r) for r in rows])
    # the neighbours are chosen on d2 less the query's own squared norm
    # (constant per row): other + penalty + a² + b² − 2 (z a + b_q b), one
    # product per step; the k chosen distances are then summed exactly
    norm2 = a_tr * a_tr + b_tr * b_tr
    ab2 = np.stack([2.0 * a_tr, 2.0 * b_tr])  # (2, N)
    first = np.array([r[0] for r in rows])
    zprev = np.tile(data.F[first, i], (M, 1))  # (M, C)
    zcur = np.tile(data.F[first, D + i], (M, 1))
    lp = np.zeros((M, N))
    hh = h2[:, None]
    vacc = np.zeros_like(zprev)  # variance accumulated since the last anchor
    floor = (data.min_std / r_i) ** 2  # min_std of the position, in delta units
    y2 = data.Z2[:, i]
    for t in range(int(L.max())):
        act = np.flatnonzero(L > t)
        R = np.array([rows[c][t] for c in act])
        if horizon is not None and t > 0 and t % horizon == 0:
            zprev[:, act] = data.F[R, i]
            zcur[:, act] = data.F[R, D + i]
            vacc[:, act] = 0.0
        zp, zc = zprev[:, act], zcur[:, act]  # (M, A)
        bq = (zc - zp) * (vw / r_i)
        block = other_d2[:, R]  # (M, A, N)
        block += penalty[R]
        q = np.stack([zc, bq], axis=-1) @ ab2
        np.subtract(norm2, q, out=q)
        q += block
        idx = k_nearest(q, data.k)
        # the k nearest distances as (other + penalty) + (z − a)² + (b_q − b)²
        d2k = block.reshape(-1)[(np.arange(M * len(R)) * N).reshape(M, -1, 1) + idx]
        d2k += (zc[..., None] - a_tr[idx]) ** 2
        d2k += (bq[..., None] - b_tr[idx]) ** 2
        mu, var = _transition_kr_nearest(data, i, d2k, idx, zc, hh)
        y_true = (y2[R] - zc) / r_i
        if horizon is not None:  # the re-synthesised state's own uncertainty
            var = var + vacc[:, act]
            vacc[:, act] = var
            var = var + floor
        lp[:, R] = gauss_log_density(y_true, mu, var)
        zprev[:, act] = zc
        zcur[:, act] = zc + mu * r_i
    return (lp if per_frame else lp.sum(axis=-1)), h2


def _transition_kr(data: TransitionData, i: int, d2: np.ndarray, zc: np.ndarray, h2):
    """Mean and variance of node ``i``'s delta (delta-std units) given distances ``d2 (..., N)``.

    ``zc (...)`` is the node's current standardised value, ``h2`` broadcasts to
    ``zc``.  The mean includes the retention term ``(λ − 1)(z − z̄)`` of
    :func:`~mocapflow.stages.variation.training.retention_of` (``z̄`` with the
    same kernel weights as the delta).
    """
    idx = k_nearest(d2, data.k)
    return _transition_kr_nearest(data, i, np.take_along_axis(d2, idx, axis=-1), idx, zc, h2)


def _transition_kr_nearest(data: TransitionData, i: int, d2k: np.ndarray, idx: np.ndarray,
                           zc: np.ndarray, h2):
    """:func:`_transition_kr` from the k nearest distances ``d2k (..., k)`` and indices."""
    w = kernel_weights(d2k, h2)
    mu, var = weighted_mean_var(w, data.Y[:, i][idx], data.min_std)
    if data.retention < 1.0:
        zbar = (w * data.F[:, data.n_dofs + i][idx]).sum(axis=-1)
        mu = mu + (data.retention - 1.0) * (zc - zbar) / data.ratio[i]
    return mu, var


def transition_node_retention(
    data: TransitionData, i: int, parents, h2: float, *, cap: float = 1.0
) -> float:
    """Offset retention ``λ_i`` of transition node ``i`` calibrated on held-out clips.

    Under the sampler the offset ``o = x[t+1] − x̄[t+1]`` of a DOF from its
    kernel-weighted neighbours follows ``o' = λ o + e`` with ``e`` the sampling
    noise of variance ``s²`` (the node's predictive variance), so its spread
    settles at ``s² / (1 − λ²)``.  Matching that to the held-out clips' offsets
    (each instance's offset from its neighbours in the other clips, the
    leave-one-out masks of ``data``) gives ``λ² = 1 − mean s² / mean o²``
    (0 when the noise alone reaches the held-out spread: value regression,
    ``x̄[t+2]``), at most ``cap``.  Near-identical examples (offsets as small as
    the noise) get a strong pull back to the data; varied ones keep ``cap``.

    Parameters
    ----------
    data : TransitionData
    i : int
        DOF index.
    parents : iterable of int
        Extra parents of the node (as in :func:`transition_node_fit`).
    h2 : float
        The node's squared bandwidth.
    cap : float
        Upper bound (the ``half_life`` retention).

    Returns
    -------
    float
    """
    penalty = np.where(data.valid, 0.0, np.inf)
    d2 = _pair_d2(data.F, list(parents)) + _self_d2(data, i) + penalty
    idx = k_nearest(d2, data.k)
    d2k = np.take_along_axis(d2, idx, axis=-1)
    _, var = kernel_regression(d2k, data.Y[idx, i], h2=h2, min_std=data.min_std)
    zc = data.F[:, data.n_dofs + i]
    zbar, _ = kernel_regression(d2k, zc[idx], h2=h2, min_std=0.0)
    o2 = float(np.mean((zc - zbar) ** 2))
    s2 = float(np.mean(var)) * data.ratio[i] ** 2  # delta units -> standardised position
    lam2 = 1.0 - s2 / o2 if o2 > 0.0 else 0.0
    return float(min(math.sqrt(max(lam2, 0.0)), cap))


def transition_node_score(data: TransitionData, i: int, parents, **kw: Any) -> float:
    """Cross-validated log-likelihood of transition node ``i`` (see :func:`transition_node_fit`)."""
    return transition_node_fit(data, i, parents, **kw)[0]
