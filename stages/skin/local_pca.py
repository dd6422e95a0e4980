"""The local PCA model of Park & Hodgins (2006, §4.3): a marker and its one-ring.

:func:`train_local_pca` fits the model of one marker from the frames where the
marker and its neighbours are all present, each brought onto the reference
pose by the members' rigid fit and expressed in the marker's local frame
(P&H Eq. 5); :func:`model_estimates_batch` estimates the missing members of many
models at once (one batched pose solve, a prior-regularised coefficient solve
per model).  The passes that use them are :func:`mocapflow.stages.skin.fill.fill_by_local_pca`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocapflow.stages.motion.absolute_orientation import absolute_orientation_batch
from mocapflow.stages.skin.predict import (
    MIN_NEIGHBOURS,
    _apply,
    _apply_inv,
    _third_anchor,
    finite_rows,
    gather_samples,
)

__all__ = [
    "BATCH_PAIRS",
    "PCA_FRAMES_PER_COORDINATE",
    "LocalPCA",
    "model_estimates",
    "model_estimates_batch",
    "train_local_pca",
]

#: With ``model="regression"``, a local PCA of ``n`` members needs at least this
#: many complete frames per coordinate (``3 n``): the markers left to the PCA
#: passes are those measured too rarely for the regression, whose PCA from a
#: handful of frames (12 frames, 10 components for 21 coordinates) extrapolated
#: the start of a motion by 20–30 mm (see :func:`train_local_pca`).
PCA_FRAMES_PER_COORDINATE = 3


@dataclass
class LocalPCA:
    """PCA model of a marker and its neighbours in the marker's local frame.

    Attributes
    ----------
    marker : int
        The marker the model belongs to.
    members : (n,) int ndarray
        Marker indices, the marker first.
    weights : (n,) float ndarray
        Member weights (1 for the marker, the neighbours' rigidity otherwise):
        they weight the pose fits, the coefficient solve and, for a neighbour's
        estimate, its share in the average.
    mean : (n, 3) float ndarray
        Mean local shape (local frame of the marker, metres).
    basis : (3n, k) float ndarray
        Principal directions kept (``k`` may be 0: rigid model).
    eigenvalues : (k,) float ndarray
        Their variances.
    noise : float
        Variance per coordinate of what the kept components do not explain.
    kind : str
        ``"pca"``, ``"reduced"`` (neighbours dropped for lack of complete
        frames) or ``"rigid"`` (too few training frames: reference shape only).
    n_train : int
        Training frames used.
    """

    marker: int
    members: np.ndarray
    weights: np.ndarray
    mean: np.ndarray
    basis: np.ndarray
    eigenvalues: np.ndarray
    noise: float
    kind: str
    n_train: int


def _complete_rows(X: np.ndarray, frames: np.ndarray, members: np.ndarray) -> np.ndarray:
    """``X[frames][:, members]``: the same values in the same memory layout, gathered
    without copying every marker of ``frames`` first.

    The layout is that of a C-ordered ``(n, L, 3)`` array seen as ``(L, n, 3)``
    (strides ``(24, 24 L, 8)``), whatever the layout of ``X``; the rigid fit and
    the local coordinates computed from it round by that layout, so it is kept.

    Parameters
    ----------
    X : (F, M, 3) float ndarray
    frames : (L,) int ndarray
    members : (n,) int ndarray

    Returns
    -------
    (L, n, 3) float ndarray
    """
    if X.flags.c_contiguous:
        Y = gather_samples(X, frames[None, :], members[:, None])  # (n, L, 3)
    else:  # X[:, cols] (a column selection) is C-contiguous seen as (M, F, 3)
        Y = gather_samples(X.transpose(1, 0, 2), members[:, None], frames[None, :])
    return Y.transpose(1, 0, 2)


def train_local_pca(
    X: np.ndarray,
    marker: int,
    neighbours: np.ndarray,
    reference: np.ndarray,
    frame: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    variance: float = 0.99,
    min_frames: int = 10,
    max_frames: int = 300,
    noise_floor: float = (2e-4) ** 2,
    frames_per_coordinate: int = 0,
) -> LocalPCA:
    """Train the local PCA model of one marker (Park & Hodgins §4.3).

    Training frames are those where the marker and all its neighbours are
    present; each is rotated and translated onto the reference pose by the
    rigid fit of the members (P&H Eq. 5) and expressed in the marker's local frame.

    Parameters
    ----------
    X : (F, M, 3) float ndarray
        Observed (merged) positions, NaN where missing.
    marker : int
    neighbours : (k,) int ndarray
        The marker's one-ring.
    reference : (M, 3) float ndarray
    frame : (3, 3) float ndarray
        The marker's local frame (rows t, b, n).
    weights : (k,) float ndarray, optional
        Neighbour rigidity weights (default 1).
    variance : float
        Fraction of variance kept.
    min_frames : int
        Fewest complete frames for a PCA; with fewer, the least co-visible
        neighbours are dropped (down to 3), then the model is rigid.
    max_frames : int
        Complete frames are subsampled evenly to at most this many.
    noise_floor : float
        Lower bound of the residual variance (m²).
    frames_per_coordinate : int
        A PCA of ``n`` members also needs ``frames_per_coordinate × 3n``
        complete frames (0: only ``min_frames``, the paper's setting); from
        fewer its components fit the few frames' noise and their start of a
        motion, and extrapolate them (:data:`PCA_FRAMES_PER_COORDINATE`).

    Returns
    -------
    LocalPCA
        Without enough complete frames even for a reduced ring, a rigid model
        of the whole one-ring (it needs no complete frame; the neighbours the
        reduction keeps are chosen for co-visibility, not rigidity, and three
        of them may straddle a joint).
    """
    members = np.concatenate([[marker], neighbours]).astype(np.int64)
    mw = np.concatenate([[1.0], np.ones(len(neighbours)) if weights is None else weights])
    ring, ring_w = members, mw
    vis = finite_rows(X[:, members])  # (F, n)
    kind = "pca"
    complete = vis.all(1)
    while (complete.sum() < max(min_frames, frames_per_coordinate * 3 * len(members))
           and len(members) > 1 + MIN_NEIGHBOURS):
        # drop the neighbour whose removal gains the most complete frames
        gains = [(vis[:, np.r_[0:j, j + 1:len(members)]].all(1).sum(), j)
                 for j in range(1, len(members))]
        _, j = max(gains)
        members, mw = np.delete(members, j), np.delete(mw, j)
        vis = np.delete(vis, j, axis=1)
        complete = vis.all(1)
        kind = "reduced"
    origin = reference[marker]
    idx = np.flatnonzero(complete)
    if len(idx) < max(min_frames, frames_per_coordinate * 3 * len(members)):
        # no PCA: the rigid model keeps the whole one-ring
        n = len(ring)
        ref_local = (reference[ring] - origin) @ frame.T
        return LocalPCA(marker, ring, ring_w, ref_local, np.zeros((3 * n, 0)), np.zeros(0),
                        noise_floor, "rigid", int(len(idx)))
    n = len(members)
    ref_local = (reference[members] - origin) @ frame.T
    if len(idx) > max_frames:
        idx = idx[np.linspace(0, len(idx) - 1, max_frames).round().astype(int)]
    Xt = _complete_rows(X, idx, members)
    R, t = absolute_orientation_batch(np.broadcast_to(ref_local, Xt.shape), Xt,
                                      weights=np.broadcast_to(mw, Xt.shape[:2]))
    Z = _apply_inv(R, t, Xt).reshape(len(idx), 3 * n)  # P&H Eq. 5, in the local frame
    mean = Z.mean(0)
    _, sv, vt = np.linalg.svd(Z - mean, full_matrices=False)
    lam = sv**2 / max(len(idx) - 1, 1)
    total = lam.sum()
    k = 0
    if total > 0:
        k = min(int(np.searchsorted(np.cumsum(lam) / total, variance - 1e-12) + 1), len(lam))
    rest = lam[k:]
    noise = max(float(rest.sum() / (3 * n)) if len(rest) else 0.0, noise_floor)
    return LocalPCA(marker, members, mw, mean.reshape(n, 3), vt[:k].T.copy(), lam[:k].copy(),
                    noise, kind, int(len(idx)))


def model_estimates(
    model: LocalPCA,
    X: np.ndarray,
    targets: np.ndarray,
    *,
    iterations: int = 1,
    min_support: float = 0.0,
    neighbour_weight: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Estimate the missing members of one local PCA model.

    Per frame with at least 3 visible members: rigid fit of the mean local
    shape onto the visible members, coefficients from their local coordinates
    (least squares with the PCA prior ``a_j ~ N(0, λ_j)``, members weighted),
    then ``iterations`` refits of the pose onto the reconstructed shape.

    Parameters
    ----------
    model : LocalPCA
    X : (F, M, 3) float ndarray
        Available positions (NaN where missing).
    targets : (F, M) bool ndarray
        Samples to estimate.
    iterations : int
        Pose refits.
    min_support : float
        Frames whose third most rigid visible member weighs less are skipped
        (left to a later pass, when more members are available).
    neighbour_weight : float
        Weight of the estimates of the model's neighbours (times their
        rigidity) relative to the estimate of its own marker (1).

    Returns
    -------
    frames, markers : (N,) int ndarray
    estimates : (N, 3) float ndarray
    weights : (N,) float ndarray
        Share of each estimate in the average: 1 for the model's own marker,
        ``neighbour_weight`` times the rigidity for its neighbours.
    """
    return model_estimates_batch([model], X, targets, iterations=iterations,
                                 min_support=min_support, neighbour_weight=neighbour_weight)[0]


#: Model-frame pairs per batched pose solve of :func:`model_estimates_batch`
#: (larger batches stop fitting in cache and run slower).
BATCH_PAIRS = 8000


def model_estimates_batch(
    models: list[LocalPCA],
    X: np.ndarray,
    targets: np.ndarray,
    *,
    masks: list[np.ndarray | None] | None = None,
    iterations: int = 1,
    min_support: float = 0.0,
    neighbour_weight: float = 1.0,
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`model_estimates` of several models at once.

    The pose fits of the models of one member count, over every frame, are one
    batched Horn solve (no padding, so a model's result does not depend on the
    other models of the call); the coefficient solves are batched over the models
    of one component count, the system of a model inverted once per pattern of
    visible members (:func:`_coefficient_group`), not once per frame and pose
    refit.  A pass of the fill calls this once per chunk of models instead of
    once per model.

    Parameters
    ----------
    models : list of LocalPCA
    X : (F, M, 3) float ndarray
    targets : (F, M) bool ndarray
    masks : list of ((F,) bool ndarray or None), optional
        Per model, the only frames it estimates (None: all).
    iterations, min_support, neighbour_weight
        As for :func:`model_estimates`.

    Returns
    -------
    list of (frames, markers, estimates, weights)
        Per model, what :func:`model_estimates` returns.
    """
    if not models:
        return []
    n_max = max(len(md.members) for md in models)
    nm = len(models)
    mem = np.zeros((nm, n_max), dtype=np.int64)
    real = np.zeros((nm, n_max), dtype=bool)
    mw = np.zeros((nm, n_max))
    mean = np.zeros((nm, n_max, 3))
    for i, md in enumerate(models):
        n = len(md.members)
        mem[i, :n], real[i, :n], mw[i, :n], mean[i, :n] = md.members, True, md.weights, md.mean
    vis_all = finite_rows(X)
    vis = vis_all[:, mem] & real[None]  # (F, m, n)
    tgt = targets[:, mem] & real[None] & ~vis
    if masks is not None:
        for i, mk in enumerate(masks):
            if mk is not None:
                tgt[~mk, i] = False
    support = _third_anchor(vis * mw[None])
    pick = tgt.any(-1) & (vis.sum(-1) >= MIN_NEIGHBOURS) & (support >= min_support)  # (F, m)
    # models of one size at a time, unpadded: a model's sums then never depend on
    # which other models share its call (the fill's chunks follow the worker count);
    # blocks of models that fit in cache, each one batched pose solve
    sizes = np.array([len(md.members) for md in models])
    out: list = [None] * nm
    for n in np.unique(sizes):
        group = np.flatnonzero(sizes == n)
        block = np.cumsum(pick[:, group].sum(0)) // BATCH_PAIRS
        for b in np.unique(block):
            sel = group[block == b]
            res = _estimate_block([models[i] for i in sel], X, vis[:, sel, :n], tgt[:, sel, :n],
                                  pick[:, sel], mem[sel, :n], mw[sel, :n], mean[sel, :n],
                                  iterations=iterations, neighbour_weight=neighbour_weight)
            for i, r in zip(sel, res):
                out[i] = r
    return out


def _coefficient_group(models: list[LocalPCA], model_of: np.ndarray, q: np.ndarray,
                       vis: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, ...]:
    """The coefficient solve's per-pair arrays of pairs ``q`` (models of one component
    count): ``(q, mu (P, 3n), B (P, 3n, k), A⁻¹ (P, k, k), w3 (P, 3n), noise (P, 1))``.

    ``A = Bᵀ W B / noise + diag(1/λ)`` depends on the model and which members are
    visible only, so it is inverted once per model and visibility pattern (the
    same for every frame and every pose refit), each pair's result independent
    of the other pairs and models of the call.
    """
    mi = model_of[q]
    n = vis.shape[1]
    key = mi * (1 << n) + vis[q] @ (1 << np.arange(n))
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    ui = mi[first]  # model of each pattern
    Bm = {i: models[i].basis for i in np.unique(mi)}
    Bu = np.stack([Bm[i] for i in ui])  # (U, 3n, k)
    w3u = np.repeat(w[q[first]], 3, axis=1)
    noise_u = np.array([models[i].noise for i in ui])[:, None, None]
    prior = np.stack([np.diag(1.0 / np.maximum(models[i].eigenvalues, 1e-12)) for i in ui])
    A = np.matmul(np.swapaxes(Bu, 1, 2) * w3u[:, None, :], Bu) / noise_u + prior
    Ainv = np.linalg.inv(A)[inverse]
    mu = np.stack([models[i].mean.reshape(-1) for i in ui])[inverse]
    return (q, mu, Bu[inverse], Ainv, np.repeat(w[q], 3, axis=1),
            noise_u[inverse, 0])


def _estimate_block(models: list[LocalPCA], X: np.ndarray, vis: np.ndarray, tgt: np.ndarray,
                    pick: np.ndarray, mem: np.ndarray, mw: np.ndarray, mean: np.ndarray, *,
                    iterations: int, neighbour_weight: float) -> list[tuple[np.ndarray, ...]]:
    """One block of :func:`model_estimates_batch`: ``vis, tgt (F, m, n)``, ``pick
    (F, m)`` frames to estimate, padded ``mem, mw (m, n)`` and ``mean (m, n, 3)``."""
    nm = len(models)
    model_of, row = np.nonzero(pick.T)  # model-major, frames ascending (as per model)
    if not len(row):
        empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0))
        return [empty] * nm
    w = vis[row, model_of] * mw[model_of]  # (P, n)
    Xr = gather_samples(X, row[:, None], mem[model_of])  # (P, n, 3)
    Xw = np.where(w[..., None] > 0, Xr, np.nan)
    shape = mean[model_of]
    R, t = absolute_orientation_batch(shape, Xw, weights=w)
    k_of = np.array([md.basis.shape[1] for md in models])
    solvable = k_of[model_of] > 0  # (P,) pairs of models with components
    if solvable.any():
        shape = shape.copy()
        Xr0 = np.nan_to_num(Xr)
        vis_p = vis[row, model_of]  # (P, n)
        groups = [_coefficient_group(models, model_of,
                                     np.flatnonzero(solvable & (k_of[model_of] == k)), vis_p, w)
                  for k in np.unique(k_of[model_of][solvable])]
        sel = np.flatnonzero(solvable)
        for it in range(iterations + 1):
            for q, mu, B, Ainv, w3, noise in groups:
                z = _apply_inv(R[q], t[q], Xr0[q]).reshape(len(q), -1)
                rhs = np.matmul((w3 * np.nan_to_num(z - mu))[:, None, :], B)[:, 0] / noise
                a = np.matmul(Ainv, rhs[..., None])[..., 0]
                shape[q] = (mu + np.matmul(a[:, None, :], np.swapaxes(B, 1, 2))[:, 0]
                            ).reshape(len(q), -1, 3)
            if it < iterations:
                R2, t2 = absolute_orientation_batch(shape[sel], Xw[sel], weights=w[sel])
                good = np.isfinite(R2).all((1, 2))
                R[sel[good]], t[sel[good]] = R2[good], t2[good]
    est = _apply(R, t, shape)  # (P, n, 3)
    p, j = np.nonzero(tgt[row, model_of])  # pair-major, members in order
    e = est[p, j]
    ok = np.isfinite(e).all(1)
    p, j, e = p[ok], j[ok], e[ok]
    mi = model_of[p]
    wgt = np.where(j == 0, 1.0, neighbour_weight * mw[mi, j])
    cut = np.searchsorted(mi, np.arange(nm + 1))
    f_all, m_all = row[p], mem[mi, j]
    return [(f_all[a:b], m_all[a:b], e[a:b], wgt[a:b]) for a, b in zip(cut[:-1], cut[1:])]
