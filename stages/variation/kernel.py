"""Kernel regression of one DBN node and its bandwidth (Lau, Bar-Joseph & Kuffner 2009, Eq. 5–6).

Each node's conditional density is non-parametric: for a parent value ``u`` the
``k`` nearest training instances in (standardised) parent space are weighted by
a Gaussian kernel ``w_j = exp(−d_j² / 2h²)`` and the node is Gaussian with the
weighted mean and weighted variance (plus ``min_std²``) of their values
(:func:`kernel_regression`, Lau Eq. 5–6).  The bandwidth is ``h = kernel_width · m``
with ``m`` the median distance to the k-th neighbour; with ``kernel_width=None``
the factor is chosen from :data:`KERNEL_GRID` by held-out likelihood
(:func:`bandwidth2`, an addition to the paper).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "KERNEL_GRID",
    "bandwidth2",
    "bandwidth2_of_nearest",
    "bandwidth_rows",
    "gauss_log_density",
    "k_nearest",
    "kernel_regression",
    "kernel_weights",
    "nearest_kernel_regression",
    "weighted_mean_var",
]

_LOG2PI = math.log(2.0 * math.pi)


def kernel_weights(d2: np.ndarray, h2: float | np.ndarray) -> np.ndarray:
    """Normalised Gaussian kernel weights ``w_j ∝ exp(−d_j² / 2h²)`` (Lau Eq. 5).

    Parameters
    ----------
    d2 : (..., k) float ndarray
        Squared distances to the ``k`` nearest training instances.
    h2 : float or (...) float ndarray
        Squared kernel bandwidth.

    Returns
    -------
    (..., k) float ndarray
        Weights summing to 1 along the last axis (shifted by the nearest
        distance, so they never underflow to NaN).
    """
    d2 = np.maximum(d2, 0.0)
    h2 = np.asarray(h2, dtype=np.float64)
    if h2.ndim:
        h2 = h2[..., None]
    w = np.exp(-0.5 * (d2 - d2.min(axis=-1, keepdims=True)) / np.maximum(h2, 1e-300))
    w /= w.sum(axis=-1, keepdims=True)
    return w


def weighted_mean_var(w: np.ndarray, y: np.ndarray, min_std: float):
    """Kernel-weighted mean and variance + ``min_std²`` of ``y (..., k)`` (Lau Eq. 6)."""
    mean = (w * y).sum(axis=-1)
    var = (w * (y - mean[..., None]) ** 2).sum(axis=-1) + min_std * min_std
    return mean, var


def kernel_regression(
    d2: np.ndarray, y: np.ndarray, *, h2: float | np.ndarray, min_std: float
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian kernel regression on the ``k`` nearest instances (Lau Eq. 5–6).

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
    return weighted_mean_var(kernel_weights(d2, h2), y, min_std)


#: Bandwidths tried per node, as multiples of the median k-th-neighbour distance.
KERNEL_GRID: tuple[float, ...] = (0.25, 0.5, 1.0, 2.0)


def bandwidth_rows(n: int, rows: int = 64) -> np.ndarray:
    """About ``rows`` evenly spaced row indices of ``n`` (enough to choose a bandwidth)."""
    return np.arange(0, n, max(1, n // rows))


def bandwidth2(
    d2: np.ndarray,
    k: int,
    kernel_width: float | None,
    *,
    y_query: np.ndarray | None = None,
    y_train: np.ndarray | None = None,
    min_std: float = 0.01,
) -> float | np.ndarray:
    """Squared kernel bandwidth of a node, or of ``M`` parent sets at once.

    ``h = kernel_width · m`` with ``m`` the median distance of the held-out
    instances to their k-th neighbour; with ``kernel_width=None`` the factor
    is chosen from :data:`KERNEL_GRID` by the held-out log-likelihood of
    ``y_query`` (so the predictive variance is calibrated per node).

    Parameters
    ----------
    d2 : (R, N) or (M, R, N) float ndarray
        Squared distances of held-out instances to the training instances
        (``inf`` where not allowed; a subset of rows is enough), or the same
        over each of ``M`` parent sets (one nearest-neighbour pass for all).
    k : int
    kernel_width : float or None
    y_query : (R,) float ndarray, optional
        Held-out targets (needed when ``kernel_width`` is None).
    y_train : (N,) float ndarray, optional
        Training targets (idem).
    min_std : float

    Returns
    -------
    float, or (M,) float ndarray for ``(M, R, N)`` distances
    """
    idx = k_nearest(d2, k)
    d2k = np.take_along_axis(d2, idx, axis=-1)
    kw = {"y_query": y_query, "y_train": y_train, "min_std": min_std}
    if d2.ndim == 2:
        return bandwidth2_of_nearest(d2k, idx, kernel_width, **kw)
    return np.array([bandwidth2_of_nearest(d2k[m], idx[m], kernel_width, **kw)
                     for m in range(d2.shape[0])])


def bandwidth2_of_nearest(
    d2k: np.ndarray,
    idx: np.ndarray,
    kernel_width: float | None,
    *,
    y_query: np.ndarray | None = None,
    y_train: np.ndarray | None = None,
    min_std: float = 0.01,
) -> float:
    """:func:`bandwidth2` from the held-out instances' ``k`` nearest (already found).

    Parameters
    ----------
    d2k : (R, k) float ndarray
        Squared distances to the ``k`` nearest training instances.
    idx : (R, k) int ndarray
        Their indices.
    kernel_width, y_query, y_train, min_std
        As in :func:`bandwidth2`.

    Returns
    -------
    float
    """
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
        ll = float(gauss_log_density(y_query[ok], mu, var).sum())
        if best is None or ll > best[0]:
            best = (ll, g)
    return max(best[1] ** 2 * med, 1e-12)


def gauss_log_density(y: np.ndarray, mean: np.ndarray, var: np.ndarray) -> np.ndarray:
    """Elementwise log density of ``y`` under ``N(mean, var)`` (shapes broadcast)."""
    return -0.5 * (_LOG2PI + np.log(var) + (y - mean) ** 2 / var)


def k_nearest(d2: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` smallest entries along the last axis (ascending index order).

    The selection runs in float32 (a SIMD partition, several times faster than
    a float64 ``argpartition``): rounding is monotone, so the entries at or
    below the float32 k-th smallest include the k smallest; a row where
    rounding ties make them more than ``k`` is selected again in float64.
    """
    n = d2.shape[-1]
    if k >= n:
        return np.broadcast_to(np.arange(n), d2.shape).copy()
    flat = d2.reshape(-1, n)
    with np.errstate(over="ignore"):
        q = flat.astype(np.float32)
    mask = q <= np.partition(q, k - 1, axis=-1)[:, k - 1 : k]
    ok = np.count_nonzero(mask, axis=-1) == k
    if ok.all():
        idx = (np.flatnonzero(mask) % n).reshape(-1, k)
    else:
        idx = np.empty((flat.shape[0], k), dtype=np.intp)
        idx[ok] = (np.flatnonzero(mask[ok]) % n).reshape(-1, k)
        idx[~ok] = np.argpartition(flat[~ok], k - 1, axis=-1)[:, :k]
    return idx.reshape(d2.shape[:-1] + (k,))


def nearest_kernel_regression(d2: np.ndarray, y: np.ndarray, k: int, h2: float, ms: float):
    """:func:`kernel_regression` on the ``k`` nearest of all instances.

    Parameters
    ----------
    d2 : (R, N) float ndarray
        Squared distances of ``R`` queries to ``N`` instances (``inf``: not allowed).
    y : (N,) float ndarray
        Instance targets.
    k : int
    h2 : float
        Squared bandwidth.
    ms : float
        ``min_std``.

    Returns
    -------
    mean, var : (R,) float ndarray
    """
    idx = k_nearest(d2, k)
    return kernel_regression(np.take_along_axis(d2, idx, axis=-1), y[idx], h2=h2, min_std=ms)
