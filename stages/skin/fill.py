"""Hole filling in the local frame (Park & Hodgins 2006, §4.3, and a wider regression).

Two models, chosen by ``fill_holes(model=...)``:

* ``"pca"`` — the paper's: per marker a PCA of the marker and its one-ring in
  its local frame, coefficients solved from the visible members, the estimates
  of the marker's and its neighbours' models averaged (:func:`train_local_pca`,
  :func:`model_estimates`);
* ``"regression"`` (default) — per gap, ridge regression of the marker's
  local coordinates on those of its :data:`REGRESSION_PREDICTORS` most rigid
  nearby markers visible through the gap (:func:`regression_estimates`),
  trained on the frames nearest the gap where the marker and those predictors
  are measured (no complete frame of the capture needed).  What it cannot
  reach (fewer than :data:`REGRESSION_MIN_PREDICTORS` predictors, or too few
  training frames) goes to the paper's passes.

Measured on the simulated 350-marker dynamic capture (120 Hz, 0.3 mm noise,
real occlusion, no complete frame for most neighbourhoods), the same gap masks
for every method, mean error after the clean stage's smoothing (independent /
clustered placement, 2 repetitions): 0.5 s gaps in 10 % of the markers 0.33 /
0.36 mm (paper's PCA 1.38 / 6.47 mm, Gløersen & Federolf 2016 R2 1.02 / 0.40
mm), 2 s gaps 0.32 / 0.72 mm (PCA 0.98 / 21.2 mm, G&F 0.61 / 0.86 mm);
Table 2 (0.5 s gaps in 10 % of the markers, 10 masks, gaps in the motion
after the calibration pose, seeds 0/1/2): mean 0.0040 / 0.0043 / 0.0040 of
the mean neighbour distance; max over the paper's regions (abdomen, elbow,
thigh, knee) 0.020 / 0.046 / 0.020, over every region but the foot 0.048 /
0.046 / 0.025; the foot 0.050 / 0.072 / 0.128 (one marker per foot: no shank
marker shows the ankle angle).  With gaps anywhere the max is 0.26 / 0.20 /
0.10: markers measured only in the calibration pose and the first frames of
the run, extrapolated from 4–12 frames (16–17 mm), which only the rigid model
can fill.  More predictors (40–64), other ridges, more training frames or an
ensemble of 16/32/64 predictors move single worst cases but not the tail.
Sending gaps whose predictor leverage
``h = zᵀ(ZᵀZ + λI)⁻¹z`` exceeds 1.5× the training frames' largest to the PCA
passes measured much worse (mean 0.0077, max 0.37, 5× slower): high leverage
here does not mean the regression is wrong, and the PCA is worse.  Shifting
each gap by the model's residual at its measured ends (``offset_correction``)
measured worse (+10–15 %: it adds the end frames' noise to an estimate that is
already unbiased), so it is off.

See :mod:`mocapflow.stages.skin.clean` for the whole procedure and where it goes
beyond the paper.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context
from mocapflow.stages.motion.kinematics import absolute_orientation_batch
from mocapflow.stages.skin.predict import (
    MIN_NEIGHBOURS,
    RIGID_ANCHOR,
    _apply,
    _apply_inv,
    _chunks,
    _third_anchor,
    rigid_estimates,
)
from mocapflow.stages.skin.regress import (
    REGRESSION_MIN_PREDICTORS,
    REGRESSION_POOL,
    REGRESSION_PREDICTORS,
    REGRESSION_RIDGE,
    REGRESSION_TRAIN,
    _regress_chunk,
    predictor_ranking,
    regress_gap,
    regression_estimates,
)
from mocapflow.stages.skin.surface import MarkerSurface

__all__ = [
    "NEIGHBOUR_MODEL_WEIGHT",
    "PCA_FRAMES_PER_COORDINATE",
    "REGRESSION_MIN_PREDICTORS",
    "REGRESSION_PREDICTORS",
    "REGRESSION_RIDGE",
    "LocalPCA",
    "fill_holes",
    "model_estimates",
    "model_estimates_batch",
    "predictor_ranking",
    "regress_gap",
    "regression_estimates",
    "train_local_pca",
]

#: Default weight of the neighbours' model estimates relative to the marker's own
#: model in the §4.3 average (see :func:`fill_holes`).
NEIGHBOUR_MODEL_WEIGHT = 0.1

#: With ``model="regression"``, a local PCA of ``n`` members needs at least this
#: many complete frames per coordinate (``3 n``): the markers left to the PCA
#: passes are those measured too rarely for the regression, whose PCA from a
#: handful of frames (12 frames, 10 components for 21 coordinates) extrapolated
#: the start of a motion by 20–30 mm (see :func:`train_local_pca`).
PCA_FRAMES_PER_COORDINATE = 3

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
    frames_per_coordinate: int = 0,
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
    vis = np.isfinite(X[:, members]).all(-1)  # (F, n)
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

    The pose fits of every model and frame are one batched Horn solve over
    the members padded to the largest model (padding weighs 0); only the
    coefficient solves run per model.  A pass of the fill calls this once per
    chunk of models instead of once per model.

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
    vis_all = np.isfinite(X).all(-1)
    vis = vis_all[:, mem] & real[None]  # (F, m, n)
    tgt = targets[:, mem] & real[None] & ~vis
    if masks is not None:
        for i, mk in enumerate(masks):
            if mk is not None:
                tgt[~mk, i] = False
    support = _third_anchor(vis * mw[None])
    pick = tgt.any(-1) & (vis.sum(-1) >= MIN_NEIGHBOURS) & (support >= min_support)  # (F, m)
    # blocks of models that fit in cache, each one batched pose solve
    block = np.cumsum(pick.sum(0)) // BATCH_PAIRS
    out: list = []
    for b in np.unique(block):
        sel = np.flatnonzero(block == b)
        out += _estimate_block([models[i] for i in sel], X, vis[:, sel], tgt[:, sel],
                               pick[:, sel], mem[sel], mw[sel], mean[sel],
                               iterations=iterations, neighbour_weight=neighbour_weight)
    return out


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
    Xr = X[row[:, None], mem[model_of]]  # (P, n, 3)
    Xw = np.where(w[..., None] > 0, Xr, np.nan)
    shape = mean[model_of]
    R, t = absolute_orientation_batch(shape, Xw, weights=w)
    starts = np.searchsorted(model_of, np.arange(nm + 1))
    solvable = [i for i, md in enumerate(models)
                if md.basis.shape[1] and starts[i + 1] > starts[i]]
    if solvable:
        shape = shape.copy()
        Xr0 = np.nan_to_num(Xr)
        for it in range(iterations + 1):
            for i in solvable:
                md = models[i]
                sl = slice(starts[i], starts[i + 1])
                n = len(md.members)
                B = md.basis
                w3 = np.repeat(w[sl, :n], 3, axis=1)
                prior = np.diag(1.0 / np.maximum(md.eigenvalues, 1e-12))
                A = np.matmul(B.T[None] * w3[:, None, :], B) / md.noise + prior
                mu = md.mean.reshape(-1)
                z = _apply_inv(R[sl], t[sl], Xr0[sl, :n]).reshape(-1, 3 * n)
                rhs = (w3 * np.nan_to_num(z - mu)) @ B / md.noise
                a = np.linalg.solve(A, rhs[..., None])[..., 0]
                shape[sl, :n] = (mu + a @ B.T).reshape(-1, n, 3)
            if it < iterations:
                sel = np.concatenate([np.arange(starts[i], starts[i + 1]) for i in solvable])
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


def _train_item(X: np.ndarray, specs: list[tuple], reference: np.ndarray, frames: np.ndarray,
                variance: float, per_coordinate: int) -> tuple:
    """The work of one :func:`_train_chunk`, cut down to the columns its models read."""
    cols = np.unique(np.concatenate([np.concatenate([[m], nb]) for m, nb, _ in specs]))
    remap = np.full(X.shape[1], -1, dtype=np.int64)
    remap[cols] = np.arange(len(cols))
    local = [(int(remap[m]), remap[nb], w) for m, nb, w in specs]
    return (X[:, cols], local, reference[cols], frames[cols], variance, per_coordinate, cols)


def _train_chunk(item: tuple) -> list[LocalPCA]:
    X, specs, reference, frames, variance, per_coordinate, cols = item
    models = [
        train_local_pca(X, m, nb, reference, frames[m], weights=w, variance=variance,
                        frames_per_coordinate=per_coordinate)
        for m, nb, w in specs
    ]
    return [replace(md, marker=int(cols[md.marker]), members=cols[md.members]) for md in models]


def _estimate_item(X: np.ndarray, models: list[LocalPCA], targets: np.ndarray,
                   min_support: float, neighbour_weight: float,
                   dirty: list[np.ndarray | None] | None = None) -> tuple:
    """The work of one :func:`_estimate_chunk`, cut down to what its models read.

    Only the members' columns and the frames where a member is a target are
    sent (a worker process receives a copy): the models are re-indexed onto
    the columns, and the results carry the frame and marker maps back.
    ``dirty`` (per model, ``(F,)`` bool or None for all) limits each model to
    the frames whose estimates must be recomputed.
    """
    cols = np.unique(np.concatenate([md.members for md in models]))
    dirty = dirty or [None] * len(models)
    need = [targets[:, md.members].any(1) if d is None else targets[:, md.members].any(1) & d
            for md, d in zip(models, dirty)]
    rows = np.flatnonzero(np.logical_or.reduce(need))
    remap = np.full(X.shape[1], -1, dtype=np.int64)
    remap[cols] = np.arange(len(cols))
    local = [replace(md, marker=int(remap[md.marker]), members=remap[md.members])
             for md in models]
    masks = [None if d is None else n[rows] for d, n in zip(dirty, need)]
    return (X[rows][:, cols], local, targets[rows][:, cols], min_support, neighbour_weight,
            masks, rows, cols)


def _estimate_chunk(item: tuple) -> list[tuple[np.ndarray, ...]]:
    X, models, targets, min_support, neighbour_weight, masks, rows, cols = item
    out = model_estimates_batch(models, X, targets, masks=masks, min_support=min_support,
                                neighbour_weight=neighbour_weight)
    return [(rows[f], cols[m], e, w) for f, m, e, w in out]


def _changed_samples(X: np.ndarray, todo: np.ndarray, X0: np.ndarray,
                     todo0: np.ndarray) -> np.ndarray:
    """``(F, M)`` bool: samples whose value, presence or target flag differ."""
    a, b = np.isfinite(X).all(-1), np.isfinite(X0).all(-1)
    with np.errstate(invalid="ignore"):
        same = (X == X0).all(-1)
    return (a != b) | (a & ~same) | (todo != todo0)


#: Passes of :func:`fill_holes` whose per-model estimates a ``cache`` keeps
#: (they hold most of the work; later passes fill few samples).
CACHED_PASSES = 4


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
    model: Literal["regression", "pca"] = "regression",
    n_predictors: int = REGRESSION_PREDICTORS,
    ridge: float = REGRESSION_RIDGE,
    offset_correction: bool = False,
    cache: dict | None = None,
    rigid_fallback: bool = True,
    ctx: Context | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Hole filling in the local frame (Park & Hodgins §4.3, or a wider regression).

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
    model : {"regression", "pca"}
        ``"pca"``: the paper's local PCA passes only.  ``"regression"``: every
        hole run is first estimated by ridge regression on the marker's
        ``n_predictors`` most rigid nearby markers visible through it
        (:func:`regression_estimates`, measured data only); what it cannot
        reach goes to the PCA passes.
    n_predictors : int
        Predictors per regression (:data:`REGRESSION_PREDICTORS`).
    ridge : float
        Ridge penalty of the regression, m² per training frame
        (:data:`REGRESSION_RIDGE`).
    offset_correction : bool
        Shift each regressed gap by the model's residual at its measured ends,
        blended linearly across it (off: it adds the end frames' noise and
        measured slightly worse on simulated captures).
    cache : dict, optional
        Kept between calls with the same ``models`` on data that changed in
        few samples (the merge rounds): each of the first
        :data:`CACHED_PASSES` passes re-uses a model's estimates in the frames
        where none of its members changed value, presence or target flag
        since the previous call (an estimate depends on its frame only), and
        computes the rest.  The result is the same as without it.
    rigid_fallback : bool
        Finally estimate what the passes left by the rigid one-ring fit (off:
        those samples stay NaN).
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
        a model, -1 = interpolated in time; with ``model="regression"`` pass 1
        is the regression), ``interpolated`` (samples), ``regression``
        (samples filled by the regression).
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
    if model not in ("regression", "pca"):
        raise ValueError(f"fill_holes: model must be 'regression' or 'pca', got {model!r}")
    parts = max(1, ctx.workers) * 2 if ctx.mapper is not None else 1
    fill_pass = np.zeros((F, M), dtype=np.int8)
    info["pass"] = fill_pass
    if model == "regression":
        gapped = np.flatnonzero(holes.any(0))
        kw = {"n_predictors": n_predictors, "min_predictors": REGRESSION_MIN_PREDICTORS,
              "ridge": ridge, "max_train": REGRESSION_TRAIN,
              "offset_correction": offset_correction, "pool": REGRESSION_POOL}
        res = ctx.map(_regress_chunk, [(positions, gapped[c], holes, surface.reference, dict(kw))
                                       for c in _chunks(len(gapped), parts)])
        f = np.concatenate([r[0] for r in res]) if res else np.zeros(0, np.int64)
        m = np.concatenate([r[1] for r in res]) if res else np.zeros(0, np.int64)
        if len(f):
            X[f, m] = np.concatenate([r[2] for r in res])
            fill_pass[f, m] = 1
        info["filled_by_pass"].append(int(len(f)))
        info["regression"] = int(len(f))
    todo0 = holes & ~np.isfinite(X).all(-1)
    markers = np.flatnonzero(fillable)
    if models is None:
        if model == "regression":  # only the models with a member left to fill
            nbr = surface.neighbours[markers]
            t0 = todo0.any(0)
            markers = markers[t0[markers] | ((nbr >= 0) & t0[np.maximum(nbr, 0)]).any(1)]
        specs = [(int(m), surface.neighbours[m][surface.neighbours[m] >= 0],
                  surface.rigidity[m][surface.neighbours[m] >= 0]) for m in markers]
        per_coordinate = PCA_FRAMES_PER_COORDINATE if model == "regression" else 0
        items = [_train_item(positions, [specs[i] for i in c], surface.reference, surface.frames,
                             variance, per_coordinate) for c in _chunks(len(specs), parts)]
        model_chunks = ctx.map(_train_chunk, items) if len(specs) else []
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
    support = min_support
    info["pass_seconds"] = []
    ids = [list(range(a, a + len(ch)))
           for a, ch in zip(np.cumsum([0] + [len(ch) for ch in model_chunks]), model_chunks)]
    all_models = info["model_list"]
    if cache is not None and cache.get("models") != [id(md) for md in all_models]:
        cache.clear()  # other models: nothing to re-use
        cache["models"] = [id(md) for md in all_models]
    for p in range(max_passes):
        t_pass = time.perf_counter()
        todo = holes & ~np.isfinite(X).all(-1)
        if not todo.any():
            break
        need = todo.any(0)  # only models with a member still to fill
        active = [[i for i in ch if need[all_models[i].members].any()] for ch in ids]
        active = [ch for ch in active if ch]
        key = (p, support, neighbour_weight)
        prev = cache.get(key) if cache is not None and p < CACHED_PASSES else None
        dirty: list[list[np.ndarray | None]] = [[None] * len(ch) for ch in active]
        if prev is not None:
            changed = _changed_samples(X, todo, prev["X"], prev["todo"])
            dirty = [[changed[:, all_models[i].members].any(1) if i in prev["out"] else None
                      for i in ch] for ch in active]
        res = ctx.map(_estimate_chunk, [
            _estimate_item(X, [all_models[i] for i in ch], todo, support, neighbour_weight, d)
            for ch, d in zip(active, dirty)])
        if not res:
            break
        outs: dict[int, tuple[np.ndarray, ...]] = {}
        for ch, d, r in zip(active, dirty, res):
            for i, di, o in zip(ch, d, r):
                if di is not None:  # cached estimates in the unchanged frames
                    old = prev["out"][i]
                    keep = ~di[old[0]]
                    o = tuple(np.concatenate([a[keep], b]) for a, b in zip(old, o))
                    order = np.argsort(o[0], kind="stable")
                    o = tuple(a[order] for a in o)
                outs[i] = o
        if cache is not None and p < CACHED_PASSES:
            cache[key] = {"X": X.copy(), "todo": todo, "out": outs}
        f = np.concatenate([o[0] for o in outs.values()])
        m = np.concatenate([o[1] for o in outs.values()])
        e = np.concatenate([o[2] for o in outs.values()])
        wt = np.concatenate([o[3] for o in outs.values()])
        n_new = 0
        if len(f):
            flat = f * M + m  # weighted average of the estimates per sample
            c = np.bincount(flat, weights=wt, minlength=F * M).reshape(F, M)
            s = np.stack([np.bincount(flat, weights=e[:, k] * wt, minlength=F * M)
                          for k in range(3)], -1).reshape(F, M, 3)
            new = (c > 0) & todo
            X[new] = s[new] / c[new][:, None]
            n_new = int(new.sum())
            fill_pass[new] = len(info["filled_by_pass"]) + 1
        info["filled_by_pass"].append(n_new)
        info["pass_seconds"].append(round(time.perf_counter() - t_pass, 3))
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
    if not rigid_fallback:
        todo2[:] = False
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


