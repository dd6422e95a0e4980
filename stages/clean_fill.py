"""Hole filling by local PCA in the local frame (Park & Hodgins 2006, §4.3).

See :mod:`mocapflow.stages.clean` for the whole procedure and where it goes
beyond the paper.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mocapflow.pipeline import Context
from mocapflow.stages.clean_predict import (
    MIN_NEIGHBOURS,
    RIGID_ANCHOR,
    _apply,
    _apply_inv,
    _chunks,
    _third_anchor,
    rigid_estimates,
)
from mocapflow.stages.kinematics import absolute_orientation_batch
from mocapflow.stages.surface import (
    MarkerSurface,
)

#: Default weight of the neighbours' model estimates relative to the marker's own
#: model in the §4.3 average (see :func:`fill_holes`).
NEIGHBOUR_MODEL_WEIGHT = 0.1

# --------------------------------------------------------------------------- PCA fill (§4.3)


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
) -> LocalPCA:
    """Train the local PCA model of one marker (Park & Hodgins §4.3).

    Training frames are those where the marker and all its neighbours are
    present; each is rotated and translated onto the reference pose by the
    rigid fit of the members (Eq. 5) and expressed in the marker's local frame.

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

    Returns
    -------
    LocalPCA
    """
    members = np.concatenate([[marker], neighbours]).astype(np.int64)
    mw = np.concatenate([[1.0], np.ones(len(neighbours)) if weights is None else weights])
    vis = np.isfinite(X[:, members]).all(-1)  # (F, n)
    kind = "pca"
    complete = vis.all(1)
    while complete.sum() < min_frames and len(members) > 1 + MIN_NEIGHBOURS:
        # drop the neighbour whose removal gains the most complete frames
        gains = [(vis[:, np.r_[0:j, j + 1:len(members)]].all(1).sum(), j)
                 for j in range(1, len(members))]
        _, j = max(gains)
        members, mw = np.delete(members, j), np.delete(mw, j)
        vis = np.delete(vis, j, axis=1)
        complete = vis.all(1)
        kind = "reduced"
    origin = reference[marker]
    ref_local = (reference[members] - origin) @ frame.T
    idx = np.flatnonzero(complete)
    n = len(members)
    if len(idx) < min_frames:
        return LocalPCA(marker, members, mw, ref_local, np.zeros((3 * n, 0)), np.zeros(0),
                        noise_floor, "rigid", int(len(idx)))
    if len(idx) > max_frames:
        idx = idx[np.linspace(0, len(idx) - 1, max_frames).round().astype(int)]
    Xt = X[idx][:, members]
    R, t = absolute_orientation_batch(np.broadcast_to(ref_local, Xt.shape), Xt,
                                      weights=np.broadcast_to(mw, Xt.shape[:2]))
    Z = _apply_inv(R, t, Xt).reshape(len(idx), 3 * n)  # Eq. 5, in the local frame
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
    mem = model.members
    n = len(mem)
    Xm = X[:, mem]
    vis = np.isfinite(Xm).all(-1)
    tgt = targets[:, mem] & ~vis
    mw = model.weights
    support = _third_anchor(vis * mw)
    rows = np.flatnonzero(tgt.any(1) & (vis.sum(1) >= MIN_NEIGHBOURS) & (support >= min_support))
    if len(rows) == 0:
        return (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0))
    Xr, w = Xm[rows], vis[rows] * mw
    shape = np.broadcast_to(model.mean, (len(rows), n, 3))
    R, t = absolute_orientation_batch(shape, np.where(w[..., None] > 0, Xr, np.nan), weights=w)
    k = model.basis.shape[1]
    if k:
        B = model.basis
        w3 = np.repeat(w, 3, axis=1)  # (N, 3n)
        prior = np.diag(1.0 / np.maximum(model.eigenvalues, 1e-12))
        A = np.einsum("ri,nr,rj->nij", B, w3, B) / model.noise + prior
        mu = model.mean.reshape(-1)
        for it in range(iterations + 1):
            z = _apply_inv(R, t, np.nan_to_num(Xr)).reshape(len(rows), 3 * n)
            rhs = np.einsum("ri,nr->ni", B, w3 * np.nan_to_num(z - mu)) / model.noise
            a = np.linalg.solve(A, rhs[..., None])[..., 0]
            shape = (mu + a @ B.T).reshape(len(rows), n, 3)
            if it < iterations:
                R2, t2 = absolute_orientation_batch(
                    shape, np.where(w[..., None] > 0, Xr, np.nan), weights=w)
                good = np.isfinite(R2).all((1, 2))
                R[good], t[good] = R2[good], t2[good]
    est = _apply(R, t, shape)  # (N, n, 3)
    f, j = np.nonzero(tgt[rows])
    e = est[f, j]
    ok = np.isfinite(e).all(1)
    wgt = np.where(j[ok] == 0, 1.0, neighbour_weight * model.weights[j[ok]])
    return rows[f[ok]], mem[j[ok]], e[ok], wgt


def _interpolate_interior(X: np.ndarray, measured: np.ndarray, holes: np.ndarray,
                          support: int) -> int:
    """Cubic interpolation (in place) of interior holes still empty, from up to
    ``support`` measured samples on each side; returns the samples filled."""
    from scipy.interpolate import CubicSpline

    obs = np.isfinite(measured).all(-1)
    todo = holes & ~np.isfinite(X).all(-1)
    n = 0
    for m in np.flatnonzero(todo.any(0)):
        d = np.diff(np.concatenate([[0], todo[:, m].astype(np.int8), [0]]))
        for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)):
            left = np.flatnonzero(obs[:a, m])[-support:]
            right = b + np.flatnonzero(obs[b:, m])[:support]
            if len(left) < 2 or len(right) < 2:
                continue  # an edge hole: nothing to interpolate between
            idx = np.concatenate([left, right])
            X[a:b, m] = CubicSpline(idx, measured[idx, m], axis=0)(np.arange(a, b))
            n += b - a
    return n


def _train_chunk(item: tuple) -> list[LocalPCA]:
    X, specs, reference, frames, variance = item
    return [
        train_local_pca(X, m, nb, reference, frames[m], weights=w, variance=variance)
        for m, nb, w in specs
    ]


def _estimate_chunk(item: tuple) -> tuple[np.ndarray, ...]:
    X, models, targets, min_support, neighbour_weight = item
    out = [model_estimates(md, X, targets, min_support=min_support,
                           neighbour_weight=neighbour_weight) for md in models]
    if not out:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
    return tuple(np.concatenate(a) for a in zip(*out))


def fill_holes(
    positions: np.ndarray,
    surface: MarkerSurface,
    *,
    variance: float = 0.99,
    max_passes: int = 12,
    min_support: float = RIGID_ANCHOR,
    interpolate: int = 10,
    models: list[LocalPCA] | None = None,
    frames: np.ndarray | None = None,
    neighbour_weight: float = NEIGHBOUR_MODEL_WEIGHT,
    ctx: Context | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """PCA hole filling (Park & Hodgins §4.3).

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        Merged trajectories, NaN at holes.
    surface : MarkerSurface
    variance : float
        Fraction of variance kept by each local PCA (0.99).
    max_passes : int
        Passes; later passes fill the holes whose models saw too few members
        from the estimates of earlier passes.
    min_support : float
        A model estimates a frame only when at least 3 visible members have a
        rigidity weight of at least this (3 points that move with the marker).
        When no pass makes progress any more, interior holes are interpolated
        in time (cubic, ``interpolate`` samples on each side) and then any 3
        visible members will do (so every sample with 3 visible neighbours is
        filled).
    models : list of LocalPCA, optional
        Models trained before (``info["model_list"]`` of an earlier call) to
        re-use instead of training.
    frames : (F,) bool ndarray, optional
        Fill only these frames (e.g. where fragments wait to be judged).
    neighbour_weight : float
        Weight of a neighbour's model estimate (times the neighbour's rigidity)
        in the average, the marker's own model weighing 1.  The paper averages
        them equally (1.0); on simulated captures with ground truth the own
        model is the best single estimate and 0.1 cuts the error by ~25 %.
    ctx : Context, optional
        Models are trained and evaluated per marker chunk through ``ctx.map``.

    Returns
    -------
    filled : (F, M, 3) float ndarray
    info : dict
        ``filled_by_pass`` (samples per pass), ``rigid_fallback`` (samples left
        to the rigid predictor: reduced models that saw < 3 members where the
        full one-ring saw 3), ``models`` (counts per kind, mean components),
        ``fillable`` (markers that may be filled), ``model_list`` (the models),
        ``pass`` (``(F, M)`` int8: the pass that filled each sample, 0 = not by
        a model, -1 = interpolated in time), ``interpolated`` (samples).
    """
    ctx = ctx or Context()
    X = positions.copy()
    F, M, _ = X.shape
    nbc = surface.n_neighbours
    fillable = np.isfinite(surface.reference).all(1) & (nbc >= MIN_NEIGHBOURS)
    obs = np.isfinite(X).all(-1)
    holes = ~obs & fillable[None, :]
    if frames is not None:
        holes &= np.asarray(frames, bool)[:, None]
    info: dict[str, Any] = {"filled_by_pass": [], "fillable": int(fillable.sum())}
    if not holes.any():
        info["models"] = {}
        info["pass"] = np.zeros((F, M), dtype=np.int8)
        return X, info
    parts = max(1, ctx.workers) * 2 if ctx.mapper is not None else 1
    markers = np.flatnonzero(fillable)
    if models is None:
        specs = [(int(m), surface.neighbours[m][surface.neighbours[m] >= 0],
                  surface.rigidity[m][surface.neighbours[m] >= 0]) for m in markers]
        items = [(X, [specs[i] for i in c], surface.reference, surface.frames, variance)
                 for c in _chunks(len(specs), parts)]
        model_chunks = ctx.map(_train_chunk, items)
    else:
        model_chunks = [[models[i] for i in c] for c in _chunks(len(models), parts)]
    info["trained"] = models is None
    info["model_list"] = [md for ch in model_chunks for md in ch]
    kinds: dict[str, int] = {}
    comps = []
    for ch in model_chunks:
        for md in ch:
            kinds[md.kind] = kinds.get(md.kind, 0) + 1
            comps.append(md.basis.shape[1])
    info["models"] = {"by_kind": kinds, "mean_components": float(np.mean(comps)) if comps else 0}
    fill_pass = np.zeros((F, M), dtype=np.int8)
    info["pass"] = fill_pass
    support = min_support
    for _ in range(max_passes):
        todo = holes & ~np.isfinite(X).all(-1)
        if not todo.any():
            break
        need = todo.any(0)  # only models with a member still to fill
        active = [[md for md in ch if need[md.members].any()] for ch in model_chunks]
        res = ctx.map(_estimate_chunk, [(X, ch, todo, support, neighbour_weight)
                                        for ch in active if ch])
        if not res:
            break
        f = np.concatenate([r[0] for r in res])
        m = np.concatenate([r[1] for r in res])
        e = np.concatenate([r[2] for r in res])
        wt = np.concatenate([r[3] for r in res])
        n_new = 0
        if len(f):
            s = np.zeros((F, M, 3))
            c = np.zeros((F, M))
            np.add.at(s, (f, m), e * wt[:, None])
            np.add.at(c, (f, m), wt)
            new = (c > 0) & todo
            X[new] = s[new] / c[new][:, None]
            n_new = int(new.sum())
            fill_pass[new] = len(info["filled_by_pass"]) + 1
        info["filled_by_pass"].append(n_new)
        if n_new == 0:
            if support == 0:
                break
            # holes no rigid neighbourhood can reach: the marker's own trajectory
            n_int = _interpolate_interior(X, positions, holes, interpolate)
            info["interpolated"] = n_int
            fill_pass[(holes & np.isfinite(X).all(-1)) & (fill_pass == 0)] = -1
            support = 0.0  # last resort: any 3 visible members
    # rigid fallback (the §4.2 predictor) where the one-ring sees >= 3 observed markers
    todo2 = holes & ~np.isfinite(X).all(-1)
    nb = np.maximum(surface.neighbours, 0)
    seen = (obs[:, nb] & (surface.neighbours >= 0)[None]).sum(-1) >= MIN_NEIGHBOURS
    f2, m2 = np.nonzero(todo2 & seen)
    n_rigid = 0
    if len(f2):
        e2 = rigid_estimates(np.where(obs[..., None], positions, np.nan), surface.reference,
                             surface.neighbours, f2, m2, rigidity=surface.rigidity)
        ok = np.isfinite(e2).all(1)
        X[f2[ok], m2[ok]] = e2[ok]
        n_rigid = int(ok.sum())
    info["rigid_fallback"] = n_rigid
    return X, info


