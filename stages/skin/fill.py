"""Hole filling in the local frame (Park & Hodgins 2006, §4.3, and a wider regression).

:func:`fill_holes` dispatches to one function per fill model, chosen by
``fill_holes(model=...)``, and ends with a rigid fallback:

* ``"pca"`` — the paper's, :func:`fill_by_local_pca`: per marker a PCA of the
  marker and its one-ring in its local frame, each complete training frame
  brought onto the reference pose by the members' rigid fit (P&H Eq. 5,
  :func:`train_local_pca`), coefficients solved from the visible members
  (:func:`model_estimates_batch`), the estimates of the marker's and its
  neighbours' models averaged (:func:`_average_estimates`), in passes that
  re-use earlier estimates; when no pass progresses, interior holes are
  interpolated in time (:func:`~mocapflow.stages.skin.fill_blend._interpolate_interior`);
  Why it misses the paper's Table 2 on the simulated dynamic capture (0.5 s
  gaps in 10 % of the markers, 3 masks, seed 0, every error from the PCA's
  first pass): with the capture's real occlusion, elbow mean 0.054 / max 0.153
  and knee 0.020 / 0.141 of the mean neighbour distance; with the same masks on
  the same capture without occlusion, elbow 0.0058 / 0.019, knee 0.0077 /
  0.019, abdomen 0.0089 / 0.049, thigh 0.0074 / 0.035: within the paper's (mean 0.017–0.023, max
  0.045–0.062).
  The method is right; its training data is not there: 7 of the first 12 elbow
  markers' models were trained on 45–52 complete one-ring frames of 900 (the
  calibration pose at the start), so their PCA learns a standing pose and
  extrapolates the motion.  The paper merged its capture by hand before
  filling; in ours the occlusion leaves those rings incomplete through the
  motion (the knee's rings are complete in 476-718 frames; its tail is not
  yet explained);
* ``"regression"`` (default) — :func:`fill_by_regression` first: per gap, ridge
  regression of the marker's local coordinates on those of its
  :data:`~mocapflow.stages.skin.regress.REGRESSION_PREDICTORS` most rigid nearby
  markers visible through the gap
  (:func:`mocapflow.stages.skin.regress.regression_estimates`), trained on the
  frames nearest the gap where the marker and those predictors are measured (no
  complete frame of the capture needed).  What it cannot reach (fewer than
  :data:`~mocapflow.stages.skin.regress.REGRESSION_MIN_PREDICTORS` predictors,
  or too few training frames) goes to the paper's passes (:func:`fill_by_local_pca`);
* last, :func:`fill_by_rigid_fit`: the §4.2 rigid one-ring prediction
  where the passes left a hole and the one-ring sees 3 observed markers;
* on sparse captures (at most
  :data:`~mocapflow.stages.skin.fill_blend.WHOLE_BODY_MAX_MARKERS` markers, ``whole_body``),
  :func:`~mocapflow.stages.skin.fill_blend.fill_by_validated_blend`: the local fill blended
  with a whole-body PCA, a spline in time and two rigid-body fills, each weighted per run of
  holes by its error on copies of that run knocked out nearby
  (:mod:`mocapflow.stages.skin.fill_blend`, with its measurements on the real shared C3Ds).

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

from dataclasses import replace
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context
from mocapflow.stages.skin.fill_blend import (
    WHOLE_BODY_MAX_MARKERS,
    _interpolate_interior,
    fill_by_validated_blend,
)
from mocapflow.stages.skin.local_pca import (
    PCA_FRAMES_PER_COORDINATE,
    LocalPCA,
    model_estimates_batch,
    train_local_pca,
)
from mocapflow.stages.skin.predict import (
    MIN_NEIGHBOURS,
    RIGID_ANCHOR,
    _chunks,
    finite_rows,
    rigid_estimates,
)
from mocapflow.stages.skin.regress import (
    REGRESSION_MIN_PREDICTORS,
    REGRESSION_POOL,
    REGRESSION_PREDICTORS,
    REGRESSION_RIDGE,
    REGRESSION_TRAIN,
    _regress_chunk,
)
from mocapflow.stages.skin.surface import MarkerSurface

__all__ = [
    "CACHED_PASSES",
    "NEIGHBOUR_MODEL_WEIGHT",
    "fill_by_local_pca",
    "fill_by_regression",
    "fill_by_rigid_fit",
    "fill_holes",
]

#: Default weight of the neighbours' model estimates relative to the marker's own
#: model in the §4.3 average (see :func:`fill_holes`).
NEIGHBOUR_MODEL_WEIGHT = 0.1


# --------------------------------------------------------------------------- PCA fill (§4.3)


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
    a, b = finite_rows(X), finite_rows(X0)
    with np.errstate(invalid="ignore"):
        same = (X == X0).all(-1)
    return (a != b) | (a & ~same) | (todo != todo0)


#: Passes of :func:`fill_holes` whose per-model estimates a ``cache`` keeps
#: (they hold most of the work; later passes fill few samples).
CACHED_PASSES = 4


def _holes(observed: np.ndarray, surface: MarkerSurface,
           frames: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``fillable (M,)``: markers with a reference position and 3 neighbours;
    ``holes (F, M)``: their missing samples (in ``frames`` only, when given)."""
    nbc = surface.n_neighbours
    fillable = np.isfinite(surface.reference).all(1) & (nbc >= MIN_NEIGHBOURS)
    holes = ~observed & fillable[None, :]
    if frames is not None:
        holes &= np.asarray(frames, bool)[:, None]
    return fillable, holes


def _thinly_connected_holes(observed: np.ndarray, surface: MarkerSurface) -> np.ndarray:
    """``(F, M)``: the missing samples of the markers with a reference position and 1 or 2
    surface neighbours (fewer than :data:`MIN_NEIGHBOURS`): no local model can be built
    for them, but the blend's models that need no neighbourhood can fill them (the whole
    body, the spline, the rigid-body fills; ``whole_body`` of :func:`fill_holes`).  The
    third marker of a 3-marker cluster is often one: Eb015pr's ``RFT1`` (neighbours
    ``RFT2``, ``RFT3``), ktk racing's ``ScapulaR1`` and ``Head3``.  A marker with no
    neighbour (basket_sprint's ``Sync:Sync``, a sync light) is not part of the surface and
    keeps its holes."""
    n = surface.n_neighbours
    thin = np.isfinite(surface.reference).all(1) & (n >= 1) & (n < MIN_NEIGHBOURS)
    return ~observed & thin[None, :]


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
    whole_body: bool | None = None,
    rate: float | None = None,
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
        ``"pca"``: the paper's local PCA passes only (:func:`fill_by_local_pca`).
        ``"regression"``: every hole run is first estimated by ridge regression
        on the marker's ``n_predictors`` most rigid nearby markers visible
        through it (:func:`fill_by_regression`, measured data only); what it
        cannot reach goes to the PCA passes.
    n_predictors : int
        Predictors per regression
        (:data:`~mocapflow.stages.skin.regress.REGRESSION_PREDICTORS`).
    ridge : float
        Ridge penalty of the regression, m² per training frame
        (:data:`~mocapflow.stages.skin.regress.REGRESSION_RIDGE`).
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
    whole_body : bool, optional
        Blend the local fill with a whole-body PCA, a spline in time and two
        rigid-body fills, each weighted per run of holes by its error on copies
        of the run moved onto measured samples nearby
        (:func:`~mocapflow.stages.skin.fill_blend.fill_by_validated_blend`); it also
        fills the markers with 1 or 2 surface neighbours, for which no local model is
        built (:func:`_thinly_connected_holes`).  Default
        (None): on captures of at most
        :data:`~mocapflow.stages.skin.fill_blend.WHOLE_BODY_MAX_MARKERS` markers, with
        ``model="regression"``.
    rate : float, optional
        The take's frames per second, for the blend's runs shorter than
        :data:`~mocapflow.stages.skin.fill_blend.RIGID_DISAGREEMENT_DURATION` (None: the
        blend as at 0.5 s on every run).
    ctx : Context, optional
        Models are trained and evaluated per marker chunk through ``ctx.map``.

    Returns
    -------
    filled : (F, M, 3) float ndarray
    info : dict
        ``filled_by_pass`` (samples per pass), ``rigid_fallback`` (samples left
        to the rigid predictor: reduced models that saw < 3 members where the
        full one-ring saw 3), ``models`` (counts per kind, mean components),
        ``fillable`` (markers the local models may fill), ``thinly_connected``
        (markers with 1-2 surface neighbours and holes the blend fills, with
        ``whole_body``), ``model_list`` (the models),
        ``pass`` (``(F, M)`` int8: the pass that filled each sample, 0 = not by
        a model, -1 = interpolated in time; with ``model="regression"`` pass 1
        is the regression), ``interpolated`` (samples), ``regression``
        (samples filled by the regression), ``blend`` (with ``whole_body``: the
        mean weight of each model over the filled samples), ``implausible`` (with
        ``whole_body``: ``(M,)`` int, the samples per marker left unfilled because no
        estimate of them stays within the marker's rigid partners' distances or its
        fastest step, :data:`~mocapflow.stages.skin.fill_checks.PLAUSIBILITY_LIMIT`).
    """
    ctx = ctx or Context()
    X = positions.copy()
    F, M, _ = X.shape
    obs = finite_rows(X)
    if model not in ("regression", "pca"):
        raise ValueError(f"fill_holes: model must be 'regression' or 'pca', got {model!r}")
    fillable, holes = _holes(obs, surface, frames)
    if whole_body is None:
        whole_body = model == "regression" and M <= WHOLE_BODY_MAX_MARKERS and frames is None
    thin = _thinly_connected_holes(obs, surface) if whole_body else np.zeros_like(holes)
    info: dict[str, Any] = {"filled_by_pass": [], "fillable": int(fillable.sum()),
                            "thinly_connected": int(thin.any(0).sum())}
    if not holes.any() and not thin.any():
        info["models"] = {}
        info["pass"] = np.zeros((F, M), dtype=np.int8)
        return X, info
    parts = max(1, ctx.workers) * 2 if ctx.mapper is not None else 1
    fill_pass = np.zeros((F, M), dtype=np.int8)
    info["pass"] = fill_pass
    if model == "regression":
        fill_by_regression(X, positions, holes, surface, fill_pass, info,
                           n_predictors=n_predictors, ridge=ridge,
                           offset_correction=offset_correction, parts=parts, ctx=ctx)
    fill_by_local_pca(X, positions, holes, fillable, surface, fill_pass, info,
                      after_regression=model == "regression", variance=variance,
                      max_passes=max_passes, min_support=min_support, interpolate=interpolate,
                      models=models, neighbour_weight=neighbour_weight, cache=cache,
                      parts=parts, ctx=ctx)
    info["rigid_fallback"] = (fill_by_rigid_fit(X, positions, holes, obs, surface)
                              if rigid_fallback else 0)
    if whole_body:
        local = dict(variance=variance, max_passes=max_passes, min_support=min_support,
                     interpolate=interpolate, neighbour_weight=neighbour_weight, model=model,
                     n_predictors=n_predictors, ridge=ridge,
                     offset_correction=offset_correction, rigid_fallback=rigid_fallback)

        def local_fill(p: np.ndarray) -> np.ndarray:  # the validation copies' local fill
            return fill_holes(p, surface, **local, whole_body=False, ctx=ctx)[0]

        before = finite_rows(X)
        X, info["blend"] = fill_by_validated_blend(X, positions, holes | thin, surface,
                                                   interpolate=interpolate,
                                                   local_fill=local_fill, rate=rate)
        info["implausible"] = (before & ~finite_rows(X)).sum(0)  # (M,) samples
    return X, info




def fill_by_regression(
    X: np.ndarray,
    positions: np.ndarray,
    holes: np.ndarray,
    surface: MarkerSurface,
    fill_pass: np.ndarray,
    info: dict[str, Any],
    *,
    n_predictors: int,
    ridge: float,
    offset_correction: bool,
    parts: int,
    ctx: Context,
) -> None:
    """The ``"regression"`` model's first pass: every hole run regressed on nearby markers.

    Per gapped marker (chunks through ``ctx.map``),
    :func:`~mocapflow.stages.skin.regress.regression_estimates` from the measured
    data only.  Writes the estimates into ``X`` (in place), marks them pass 1 in
    ``fill_pass`` and records ``filled_by_pass`` / ``regression`` in ``info``.

    Parameters
    ----------
    X : (F, M, 3) float ndarray
        The positions being filled (written in place).
    positions : (F, M, 3) float ndarray
        The measured (merged) positions, NaN at holes.
    holes : (F, M) bool ndarray
        Samples to fill.
    surface : MarkerSurface
    fill_pass : (F, M) int8 ndarray
    info : dict
    n_predictors, ridge, offset_correction
        As for :func:`fill_holes`.
    parts : int
        Marker chunks for ``ctx.map``.
    ctx : Context
    """
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


def _pca_models(
    positions: np.ndarray,
    surface: MarkerSurface,
    fillable: np.ndarray,
    todo: np.ndarray,
    models: list[LocalPCA] | None,
    *,
    after_regression: bool,
    variance: float,
    parts: int,
    ctx: Context,
) -> list[list[LocalPCA]]:
    """The local PCA models in chunks: ``models`` re-used, or trained per marker chunk.

    After the regression only the models with a member left to fill (``todo``)
    are trained, and a PCA needs :data:`PCA_FRAMES_PER_COORDINATE` complete frames
    per coordinate.
    """
    if models is not None:
        return [[models[i] for i in c] for c in _chunks(len(models), parts)]
    markers = np.flatnonzero(fillable)
    if after_regression:  # only the models with a member left to fill
        nbr = surface.neighbours[markers]
        t0 = todo.any(0)
        markers = markers[t0[markers] | ((nbr >= 0) & t0[np.maximum(nbr, 0)]).any(1)]
    specs = [(int(m), surface.neighbours[m][surface.neighbours[m] >= 0],
              surface.rigidity[m][surface.neighbours[m] >= 0]) for m in markers]
    per_coordinate = PCA_FRAMES_PER_COORDINATE if after_regression else 0
    items = [_train_item(positions, [specs[i] for i in c], surface.reference, surface.frames,
                         variance, per_coordinate) for c in _chunks(len(specs), parts)]
    return ctx.map(_train_chunk, items) if len(specs) else []


def _model_summary(model_chunks: list[list[LocalPCA]]) -> dict[str, Any]:
    """``by_kind`` (models per kind) and ``mean_components`` of the models."""
    kinds: dict[str, int] = {}
    comps = []
    for ch in model_chunks:
        for md in ch:
            kinds[md.kind] = kinds.get(md.kind, 0) + 1
            comps.append(md.basis.shape[1])
    return {"by_kind": kinds, "mean_components": float(np.mean(comps)) if comps else 0}


def _pass_estimates(
    X: np.ndarray,
    todo: np.ndarray,
    all_models: list[LocalPCA],
    ids: list[list[int]],
    prev: dict[str, Any] | None,
    *,
    support: float,
    neighbour_weight: float,
    ctx: Context,
) -> dict[int, tuple[np.ndarray, ...]] | None:
    """One pass's estimates of every model with a member in ``todo``, by model index.

    The models (indices ``ids`` per chunk) are evaluated through ``ctx.map``; with
    ``prev`` (this pass of the previous call, from a ``cache``) a model re-uses
    its estimates in the frames where none of its members changed.  ``None``
    when no model has anything to estimate.
    """
    need = todo.any(0)  # only models with a member still to fill
    active = [[i for i in ch if need[all_models[i].members].any()] for ch in ids]
    active = [ch for ch in active if ch]
    dirty: list[list[np.ndarray | None]] = [[None] * len(ch) for ch in active]
    if prev is not None:
        changed = _changed_samples(X, todo, prev["X"], prev["todo"])
        dirty = [[changed[:, all_models[i].members].any(1) if i in prev["out"] else None
                  for i in ch] for ch in active]
    res = ctx.map(_estimate_chunk, [
        _estimate_item(X, [all_models[i] for i in ch], todo, support, neighbour_weight, d)
        for ch, d in zip(active, dirty)])
    if not res:
        return None
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
    return outs


def _average_estimates(X: np.ndarray, outs: dict[int, tuple[np.ndarray, ...]],
                       todo: np.ndarray) -> np.ndarray:
    """Write the weighted average of the estimates of each ``todo`` sample into ``X``
    (P&H §4.3: the models containing the marker averaged); returns the samples filled."""
    F, M, _ = X.shape
    f = np.concatenate([o[0] for o in outs.values()])
    m = np.concatenate([o[1] for o in outs.values()])
    e = np.concatenate([o[2] for o in outs.values()])
    wt = np.concatenate([o[3] for o in outs.values()])
    if not len(f):
        return np.zeros((F, M), dtype=bool)
    flat = f * M + m  # weighted average of the estimates per sample
    c = np.bincount(flat, weights=wt, minlength=F * M).reshape(F, M)
    s = np.stack([np.bincount(flat, weights=e[:, k] * wt, minlength=F * M)
                  for k in range(3)], -1).reshape(F, M, 3)
    new = (c > 0) & todo
    X[new] = s[new] / c[new][:, None]
    return new


def fill_by_local_pca(
    X: np.ndarray,
    positions: np.ndarray,
    holes: np.ndarray,
    fillable: np.ndarray,
    surface: MarkerSurface,
    fill_pass: np.ndarray,
    info: dict[str, Any],
    *,
    after_regression: bool,
    variance: float,
    max_passes: int,
    min_support: float,
    interpolate: int,
    models: list[LocalPCA] | None,
    neighbour_weight: float,
    cache: dict | None,
    parts: int,
    ctx: Context,
) -> None:
    """The ``"pca"`` model (Park & Hodgins §4.3): passes of local PCA estimates.

    Trains (or re-uses) the per-marker models (:func:`train_local_pca`), then
    each pass estimates the holes still empty from every model containing the
    marker (:func:`model_estimates_batch`) and averages them; later passes use
    earlier estimates.  When a pass fills nothing, interior holes are
    interpolated in time and the support requirement drops to any 3 visible
    members.  Writes into ``X`` and ``fill_pass`` (in place) and records
    ``trained``, ``model_list``, ``models``, ``filled_by_pass``
    and ``interpolated`` in ``info``.

    Parameters
    ----------
    X : (F, M, 3) float ndarray
        The positions being filled (written in place).
    positions : (F, M, 3) float ndarray
        The measured (merged) positions, NaN at holes.
    holes : (F, M) bool ndarray
    fillable : (M,) bool ndarray
        Markers with a reference position and at least 3 neighbours.
    surface : MarkerSurface
    fill_pass : (F, M) int8 ndarray
    info : dict
    after_regression : bool
        The regression has run first (``model="regression"``): only models with
        a member left are trained, with :data:`PCA_FRAMES_PER_COORDINATE`.
    variance, max_passes, min_support, interpolate, models, neighbour_weight, cache
        As for :func:`fill_holes`.
    parts : int
        Chunks for ``ctx.map``.
    ctx : Context
    """
    todo0 = holes & ~finite_rows(X)
    model_chunks = _pca_models(positions, surface, fillable, todo0, models,
                               after_regression=after_regression, variance=variance,
                               parts=parts, ctx=ctx)
    info["trained"] = models is None
    info["model_list"] = [md for ch in model_chunks for md in ch]
    info["models"] = _model_summary(model_chunks)
    support = min_support
    ids = [list(range(a, a + len(ch)))
           for a, ch in zip(np.cumsum([0] + [len(ch) for ch in model_chunks]), model_chunks)]
    all_models = info["model_list"]
    if cache is not None and cache.get("models") != [id(md) for md in all_models]:
        cache.clear()  # other models: nothing to re-use
        cache["models"] = [id(md) for md in all_models]
    for p in range(max_passes):
        todo = holes & ~finite_rows(X)
        if not todo.any():
            break
        key = (p, support, neighbour_weight)
        prev = cache.get(key) if cache is not None and p < CACHED_PASSES else None
        with ctx.timer("fill_passes"):
            outs = _pass_estimates(X, todo, all_models, ids, prev, support=support,
                                   neighbour_weight=neighbour_weight, ctx=ctx)
        if outs is None:
            break
        if cache is not None and p < CACHED_PASSES:
            cache[key] = {"X": X.copy(), "todo": todo, "out": outs}
        new = _average_estimates(X, outs, todo)
        n_new = int(new.sum())
        if n_new:
            fill_pass[new] = len(info["filled_by_pass"]) + 1
        info["filled_by_pass"].append(n_new)
        if n_new == 0:
            if support == 0:
                break
            # holes no rigid neighbourhood can reach: the marker's own trajectory
            n_int = _interpolate_interior(X, positions, holes, interpolate)
            info["interpolated"] = n_int
            fill_pass[(holes & finite_rows(X)) & (fill_pass == 0)] = -1
            support = 0.0  # last resort: any 3 visible members


def fill_by_rigid_fit(X: np.ndarray, positions: np.ndarray, holes: np.ndarray,
                      observed: np.ndarray, surface: MarkerSurface) -> int:
    """The last resort: the rigid one-ring fit (the §4.2 predictor) where the passes left holes.

    Only where the one-ring sees at least 3 observed markers (``observed``
    ``(F, M)``); writes into ``X`` (in place) and returns the samples filled.
    """
    todo2 = holes & ~finite_rows(X)
    nb = np.maximum(surface.neighbours, 0)
    seen = (observed[:, nb] & (surface.neighbours >= 0)[None]).sum(-1) >= MIN_NEIGHBOURS
    f2, m2 = np.nonzero(todo2 & seen)
    n_rigid = 0
    if len(f2):
        e2 = rigid_estimates(np.where(observed[..., None], positions, np.nan),
                             surface.reference, surface.neighbours, f2, m2,
                             rigidity=surface.rigidity)
        ok = np.isfinite(e2).all(1)
        X[f2[ok], m2[ok]] = e2[ok]
        n_rigid = int(ok.sum())
    return n_rigid
