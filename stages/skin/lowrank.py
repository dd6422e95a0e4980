"""Whole-body PCA estimates of a take's gaps (beyond Park & Hodgins 2006).

On sparse captures (tens of markers, one per bone landmark) a marker's few
neighbours say little about it, while the whole body's pose does: Gløersen &
Federolf 2016 (strategy R2) fill such captures by a distance-weighted PCA of
the whole marker set, but train it on complete frames only, so it fails on a
take with none.  :func:`whole_body_pca` trains the same reconstruction on
every frame where the marker is measured, the other markers' holes taken from
the local fill: no complete frame is needed.

A plain low-rank completion of the take (hard impute: fill, project on the
components keeping 99 % or 99.9 % of the summed singular values, put the
measurements back, repeat, started from the local fill) measured worse than
the local fill alone (``btkdata_c3dorg_Eb015pr.c3d``, the gap protocol's 24
configurations, mask seeds 0-1: mean 17 mm vs 7.1 mm): one unweighted model of
the whole body reconstructs a marker from distant ones as much as from near ones.
"""

from __future__ import annotations

import numpy as np

__all__ = ["WHOLE_BODY_MARKER_WEIGHT", "WHOLE_BODY_SIGMA", "WHOLE_BODY_VARIANCE",
           "whole_body_pca"]

#: Width of the Gaussian weight of the other markers by their mean distance to
#: the marker, m (Gløersen & Federolf's default, 200 mm).
WHOLE_BODY_SIGMA = 0.2

#: Weight of the marker's own coordinates in the PCA (their ``mm_weight``, 0.02).
WHOLE_BODY_MARKER_WEIGHT = 0.02

#: Share of the summed singular values kept (their 99 % criterion).
WHOLE_BODY_VARIANCE = 0.99


def _n_components(s: np.ndarray, variance: float) -> int:
    c = np.cumsum(s) / max(float(s.sum()), 1e-300)
    return int(min(len(s), np.searchsorted(c, variance - 1e-12) + 1))


def whole_body_pca(
    filled: np.ndarray,
    observed: np.ndarray,
    holes: np.ndarray,
    *,
    sigma: float = WHOLE_BODY_SIGMA,
    marker_weight: float = WHOLE_BODY_MARKER_WEIGHT,
    variance: float = WHOLE_BODY_VARIANCE,
    max_train: int = 250,
    min_measured: int = 8,
) -> np.ndarray:
    """Estimate each marker's holes from the whole body (Gløersen & Federolf R2, any frames).

    Per marker with holes: every frame relative to the centroid of all markers
    (the filled take), the markers measured throughout its holes (else those
    filled there) weighted by ``exp(-d²/2σ²)`` of their mean
    distance ``d`` to it (itself ``marker_weight``), standardised over the
    frames where the marker is measured; with ``V`` the leading principal
    directions of those frames and ``Vz`` those with the marker's columns
    zeroed, a hole frame ``z`` (the marker's columns zero) is reconstructed as
    ``z Vz (Vᵀ Vz)ᵀ V_gᵀ`` (Federolf 2013).  A marker that ``filled`` leaves NaN at
    every one of its holes (no local model: fewer than 3 surface neighbours) is
    estimated there all the same, from the others, each frame relative to the centroid
    of the other markers, so that its holes and its training frames have the same
    origin.

    Parameters
    ----------
    filled : (F, M, 3) float ndarray
        The take with its holes filled by another model (the local fill); NaN
        for samples nobody could fill (those markers' frames are left out).
    observed : (F, M) bool ndarray
        Measured samples (training frames of a marker: where it is measured).
    holes : (F, M) bool ndarray
        Samples to estimate.
    sigma : float
        Gaussian width of the distance weights, m.
    marker_weight : float
    variance : float
        Share of the summed singular values kept, in (0, 1].
    max_train : int
        Training frames are subsampled evenly to at most this many.
    min_measured : int
        As Gløersen & Federolf, only the markers measured throughout the
        marker's holes enter its model when there are at least this many
        (counting itself); else every marker the local fill completed there.

    Returns
    -------
    (F, M, 3) float ndarray
        The estimates at ``holes`` (NaN where the frame has an unfilled sample of
        another marker of the model, or the marker fewer than 10 measured frames), NaN
        elsewhere.
    """
    if not 0 < variance <= 1:
        raise ValueError(f"whole_body_pca: variance must be in (0, 1], got {variance}")
    if sigma <= 0 or marker_weight <= 0:
        raise ValueError("whole_body_pca: sigma and marker_weight must be positive")
    F, M, _ = filled.shape
    out = np.full(filled.shape, np.nan)
    fin = np.isfinite(filled).all(-1)  # (F, M)
    total = np.where(fin[..., None], filled, 0.0).sum(1)  # (F, 3) over the finite samples
    count = fin.sum(1)[:, None]  # (F, 1)
    with np.errstate(invalid="ignore", divide="ignore"):  # a frame with no marker: unused
        centroid = total / count
    for i in np.flatnonzero(holes.any(0)):
        h = holes[:, i] & fin[:, i]
        origin, itself = centroid, np.zeros(M, dtype=bool)
        if not h.any():  # nothing filled this marker (no local model): its holes as they are
            h = holes[:, i].copy()
            # the centroid of the other markers: the same origin at its holes and in its
            # training frames (where it is measured)
            with np.errstate(invalid="ignore", divide="ignore"):
                origin = ((total - np.where(fin[:, i, None], filled[:, i], 0.0))
                          / (count - fin[:, i, None]))  # fmt: skip
            itself[i] = True  # however few its measured frames (at least 10, below)
        # the markers filled wherever this one is to be estimated; frames where all are
        cols = np.flatnonzero(itself | (fin[h].all(0) & (fin.sum(0) >= 0.5 * F)))
        seen = observed[h].all(0)  # as G&F: markers measured through the holes, if enough
        seen[i] = True
        if seen[cols].sum() >= min_measured:
            cols = cols[seen[cols]]
        if i not in cols or len(cols) < 4:
            continue
        rows = fin[:, cols[cols != i]].all(1)
        h &= rows
        train = np.flatnonzero(observed[:, i] & rows & fin[:, i])
        if not h.any() or len(train) < 10:
            continue
        train = train[np.unique(np.linspace(0, len(train) - 1, min(len(train), max_train))
                                .round().astype(int))]
        ki = int(np.flatnonzero(cols == i)[0])
        Y = filled[:, cols] - origin[:, None]  # moving origin: the frame's centroid
        d = np.linalg.norm(Y[train] - Y[train, ki:ki + 1], axis=-1).mean(0)  # (K,)
        w = np.exp(-(d**2) / (2 * sigma**2))
        w[ki] = marker_weight
        Z = Y[train].reshape(len(train), -1)
        mean, sd = Z.mean(0), Z.std(0)
        sd[sd == 0] = 1.0
        scale = np.repeat(w, 3) / sd
        A = (Z - mean) * scale
        g = np.arange(3 * ki, 3 * ki + 3)
        Az = A.copy()
        Az[:, g] = 0.0
        _, s, vt = np.linalg.svd(A, full_matrices=False)
        _, sz, vtz = np.linalg.svd(Az, full_matrices=False)
        n = max(_n_components(s, variance), _n_components(sz, variance))
        V, Vz = vt[:n].T, vtz[:n].T
        q = (Y[h].reshape(int(h.sum()), -1) - mean) * scale
        q[:, g] = 0.0
        rec = (q @ Vz) @ (Vz.T @ V) @ V[g].T
        out[h, i] = origin[h] + mean[g] + rec / scale[g]
    return out

