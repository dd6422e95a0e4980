"""Cleaning dense marker captures (Park & Hodgins 2006, §4): the ``clean`` stage.

The stage (:func:`clean`) runs these steps, each in the paper's words, each in
one place:

0. **reference pose** (:func:`mocapflow.stages.skin.predict.reference_pose`) —
   the frame with the most visible markers (or the ``reference_frame`` param).
   Markers missing there get their reference position from the nearest frame in
   which they are visible, carried over by a rigid fit of their spatial
   neighbours (a warning names them); markers never visible have none and are
   left NaN.
1. **marker surface and local frames** (§4.1) — :mod:`mocapflow.stages.skin.surface`
   (:func:`~mocapflow.stages.skin.surface.build_marker_surface`): built
   automatically (or read from the ``surface`` override file), one-ring
   neighbours, a local frame ``(t, b, n)`` per marker.
2. **merging** (§4.2) — :func:`mocapflow.stages.skin.merge.merge_fragments`,
   predictions by :func:`mocapflow.stages.skin.predict.predict_missing`: every
   missing sample of a marker is predicted from at least 3 available neighbours
   by a rigid fit (Horn) into its local reference frame.  In every frame the
   missing markers are processed greedily by their number of available
   neighbours, and estimates are re-used as neighbours for the next ones.  An
   unlabelled fragment is merged into a marker that is missing over the whole
   fragment when its first predicted sample lies within ``ε₁ = α₁·d̄`` of the
   prediction and every sample stays within ``ε₂ = α₂·d̄`` (``d̄`` the marker's
   mean neighbour distance).  Ties between markers or fragments are conflicts
   (reported, nothing merged unless one is clearly closest); predictions are
   recomputed after every round of merges.
3. **hole filling** (§4.3) — :func:`mocapflow.stages.skin.fill.fill_holes`: per
   marker a PCA model (``variance`` = 99 %) of the marker and its one-ring in the
   local frame; each training frame (all members present) is brought to the
   reference pose by the rotation that best aligns the members (P&H Eq. 5).  A
   missing sample is estimated from every model that contains the marker (its
   own and its neighbours') with at least 3 visible members: coefficients from
   the visible members, then the estimates are averaged.  Only local
   neighbourhoods need complete frames, never the whole body; a neighbourhood
   without enough complete frames drops its least co-visible neighbours, then
   falls back to the rigid prediction.  Holes whose models see too few members
   are filled in later passes from earlier estimates (as the merge step does).
   This is ``fill_model="pca"``; the default ``"regression"`` estimates every
   hole first by a wider local model (below, :mod:`mocapflow.stages.skin.regress`)
   and leaves to these passes only what it cannot reach.
4. **smoothing** (§4.4) — :func:`smooth_local`: each trajectory is expressed in
   its local frame over time, smoothed by ``x ← x − λ Δ⁴x``
   (``smooth_iterations`` times), and moved back to global coordinates (its
   measured samples: the filled ones are left as filled, see below).

Nothing is invented: a marker never visible, or with fewer than 3 surface
neighbours, keeps its NaNs (warning naming it, listed in the report), except on
sparse captures a marker with 1 or 2 neighbours (the third marker of a cluster),
which the whole-body blend fills with its models that need no neighbourhood
(:func:`~mocapflow.stages.skin.fill._thinly_connected_holes`); on sparse captures a
gap every estimate of which leaves the marker's rigid partners or outruns its
fastest measured step by more than
:data:`~mocapflow.stages.skin.fill_checks.PLAUSIBILITY_LIMIT` stays a hole too
(warning naming the markers, samples per marker in the report's
``fill.implausible``).

Where this implementation goes beyond the paper (each measured on simulated
captures with ground truth, see ``benchmarks/clean.py``):

* the surface is automatic, so one-rings may straddle a joint or the armpit:
  every neighbour carries a *rigidity* weight (how constant its distance to the
  marker stays over the capture) used in all rigid fits, and a marker with
  fewer than 3 rigid neighbours borrows rigid ones from its two-ring
  (:mod:`mocapflow.stages.skin.rigidity`);
* merge predictions carry the marker's own local coordinates measured at the
  ends of its gap (interpolated across it) instead of the reference pose's
  (:func:`mocapflow.stages.skin.predict.local_targets`);
  predictions derived from estimates are trusted only one step at a time
  (``depths``), a fragment must also stay within ``ε₁`` on average, any other
  missing marker predicted within
  :data:`~mocapflow.stages.skin.merge.AMBIGUITY_RATIO` times the distance
  makes it ambiguous, ``d̄`` is capped by the distance to the nearest marker,
  and fragments still unmerged are judged again against the PCA hole filling
  of the merged data (``pca_merge_rounds``; :data:`MERGE_FILL_PASSES` passes,
  estimates re-used between rounds where no member changed; :func:`_pca_merge_rounds`);
* fragments still unmerged after that (the paper merged them by hand) are judged
  against the final hole filling with the same ``ε₁`` / ``ε₂`` tests, in rounds
  until nothing merges (``fill_merge_rounds``; :func:`_fill_merge_rounds`,
  :func:`mocapflow.stages.skin.assign.assign_fragments`): a fragment that fills a
  marker's gap exactly and continues its trajectory at the gap ends merges; the
  others are resolved jointly, one assignment problem per frame window of
  overlapping fragments (``scipy.optimize.linear_sum_assignment``, ``ε₁`` the
  cost cap), refused only when a labelling within
  :data:`~mocapflow.stages.skin.assign.ASSIGNMENT_RATIO` remains.  On the
  simulated 900-frame dynamic capture (seed 0) the merged share of the real
  fragments' samples goes from 76 % to 99.9 %, no wrong merge;
* fragments left after that get a marker proposed by the markers' layout and are
  judged again (``template_merge_rounds``; :func:`_template_merge_rounds`,
  :func:`mocapflow.stages.skin.labelling.template_proposals`): where a limb lost
  all its labels at once, every prediction of its markers comes from the trunk,
  10-20 cm off, and none of its fragments passes the entry test; the layout of the
  missing markers' estimates is matched to the fragments seen in a frame (ICP, a
  thin-plate warp and a one-to-one assignment), the proposals are put in place, and
  the fragments are judged with the usual tests against rigid predictions from
  their neighbours, proposals included;
* in the §4.3 average a neighbour's model weighs
  :data:`~mocapflow.stages.skin.fill.NEIGHBOUR_MODEL_WEIGHT` of the marker's own
  model (the paper: equal weights);
* ``fill_model="regression"`` (default): per gap, the marker's local
  coordinates are regressed (ridge,
  :data:`~mocapflow.stages.skin.regress.REGRESSION_RIDGE`) on those of its
  ``fill_predictors`` (32) most rigid nearby markers visible through the gap,
  in the predictors' local frame, trained on the 250 frames nearest the gap
  where the marker and those predictors are measured (no complete frame
  needed; :func:`mocapflow.stages.skin.regress.regression_estimates`).  On
  the simulated 350-marker capture (Table 2: 0.5 s gaps in 10 % of the
  markers, in the motion) it gives mean 0.004 of the mean neighbour distance
  and max 0.036 over the paper's regions (abdomen, elbow, thigh, knee);
  ``fill_model="pca"`` is the paper's model;
* the smoother smooths runs of measured samples only and moves a measurement by
  at most :data:`MAX_CORRECTION_SIGMA` noise deviations; filled samples keep the
  fill's estimate.  A filled run smoothed in its local frame takes up the frame's
  own jitter (on a sparse capture the one-ring spans joints and objects), with no
  noise to remove: on the real ``ktk_kinematics_racing_full.c3d`` a 0.18 s gap of
  ``NAR`` came out 1.3 mm from the truth after the fill and 8.1 mm (max 36 mm)
  after smoothing it, a 0.5 s gap of ``WheelchairRearL`` 0.4 -> 1.7 mm
  (``tests/stages/skin/test_fill_blend.py::test_filled_runs_keep_the_fill``).
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context, FilePath, stage
from mocapflow.stages.motion.absolute_orientation import absolute_orientation_batch
from mocapflow.stages.motion.contacts import true_runs
from mocapflow.stages.motion.datatypes import Markers
from mocapflow.stages.skin.assign import assign_fragments
from mocapflow.stages.skin.fill import fill_holes
from mocapflow.stages.skin.fill_blend import WHOLE_BODY_MAX_MARKERS
from mocapflow.stages.skin.fill_checks import PLAUSIBILITY_LIMIT
from mocapflow.stages.skin.labelling import (
    LabellingError,
    fragment_frames,
    fragment_subjects,
    label_markers,
    subject_groups,
    template_proposals,
)
from mocapflow.stages.skin.merge import (
    ASSIGN_MIN_FRAMES,
    BREAK_JUMP,
    merge_fragments,
)
from mocapflow.stages.skin.predict import (
    MIN_NEIGHBOURS,
    _apply,
    _apply_inv,
    _chunks,
    _names,
    choose_reference_frame,
    finite_rows,
    reference_pose,
    rigid_estimates,
)
from mocapflow.stages.skin.regress import REGRESSION_MIN_PREDICTORS, REGRESSION_PREDICTORS
from mocapflow.stages.skin.surface import (
    MarkerSurface,
    build_marker_surface,
    marker_surface_from_faces,
    read_surface_file,
)

__all__ = [
    "MAX_CORRECTION_SIGMA",
    "MERGE_FILL_PASSES",
    "SMOOTH_FRAME_MIN_MEASURED",
    "STATUS",
    "TEMPLATE_MIN_DURATION",
    "CleanError",
    "clean",
    "frame_weights",
    "smooth_local",
]

#: The smoother moves a measured sample by at most this many noise standard
#: deviations per axis (noise estimated robustly from the 4th differences of
#: the marker's measured local trajectory).  A jump of the local frame — a
#: neighbour switching between measured and filled, skin folding — is not noise.
MAX_CORRECTION_SIGMA = 2.0

#: Fill passes of each PCA merge round.  The fragments are judged against the
#: first pass only (estimates from measured members); later passes serve the
#: ambiguity test.  Passes beyond the 4th and the rigid fallback changed no
#: merge on 7 simulated captures (3 motions x 2 seeds and the 1000-frame
#: throughput capture) and cost ~10 % of the clean; 3 passes lost 17 of 1545.
MERGE_FILL_PASSES = 4

#: A neighbour measured in fewer than this share of the frames does not define
#: the smoothing frame of a marker (while 3 others do): its estimates elsewhere
#: may be centimetres off, and its rigidity, judged from the few frames it
#: shares with the marker, looks high.  (Found when filled runs were smoothed too:
#: a marker seen only in the calibration pose made a shoulder marker's filled gap
#: 4.7 mm worse; now such a frame bends measured samples, by at most
#: :data:`MAX_CORRECTION_SIGMA` noise deviations.)
SMOOTH_FRAME_MIN_MEASURED = 0.5

#: Codes of the ``status`` array in the clean report.
STATUS = {"missing": -1, "observed": 0, "merged": 1, "filled": 2}
#: Fragments shorter than this (seconds; at least ``ASSIGN_MIN_FRAMES`` frames) are not
#: judged by :func:`_template_merge_rounds`: its one wrong merge on the simulated
#: captures (range of motion, labels stripped, seed 2) was a 4-frame fragment at
#: 0.47 ε₁ from its prediction.
TEMPLATE_MIN_DURATION = 0.1


# --------------------------------------------------------------------------- smoothing (§4.4)


def _smooth_run(y: np.ndarray, lam: float, iterations: int) -> np.ndarray:
    """``y ← y − λ Δ⁴ y`` along axis 0, ends extended by odd reflection."""
    return _smooth_runs(y, np.array([0]), np.array([len(y)]), lam, iterations)


def _smooth_runs(y: np.ndarray, starts: np.ndarray, stops: np.ndarray, lam: float,
                 iterations: int) -> np.ndarray:
    """:func:`_smooth_run` of every run ``y[a:b]`` at once (runs of 5 or more samples;
    the rest of ``y``, shorter runs included, is returned as it is).

    Parameters
    ----------
    y : (N, 3) float ndarray
    starts, stops : (R,) int ndarray
        Disjoint half-open runs ``[a, b)`` along axis 0.
    lam : float
    iterations : int

    Returns
    -------
    (N, 3) float ndarray
    """
    long = (stops - starts) >= 5
    starts, stops = starts[long], stops[long]
    if not len(starts) or iterations <= 0 or lam == 0:
        return y
    L = stops - starts
    # each run padded by 2 samples a side: index into y, and for the pads the run
    # end they reflect about (odd reflection: 2 y[end] - y[mirror])
    seg = np.repeat(np.arange(len(L)), L + 4)
    pos = np.arange(len(seg)) - np.repeat(np.cumsum(L + 4) - (L + 4), L + 4) - 2  # -2 .. L+1
    a, last = starts[seg], stops[seg] - 1
    src = np.where(pos < 0, a - pos, np.where(pos >= L[seg], 2 * last - (a + pos), a + pos))
    pad = (pos < 0) | (pos >= L[seg])
    anchor = np.where(pos < 0, a, last)[pad]
    body = np.flatnonzero(~pad)  # the run samples, in order, in the padded array
    idx = src[body]
    out = y.copy()
    mirror, at = src[pad], body - 2
    for _ in range(iterations):  # np.take: the same rows as fancy indexing, faster
        ext = np.take(out, src, axis=0)
        ext[pad] = 2 * np.take(out, anchor, axis=0) - np.take(out, mirror, axis=0)
        d4 = ext[:-4] - 4 * ext[1:-3] + 6 * ext[2:-2] - 4 * ext[3:-1] + ext[4:]
        upd = np.take(out, idx, axis=0)
        upd -= lam * np.take(d4, at, axis=0)
        out[idx] = upd
    return out


def _smooth_chunk(item: tuple) -> tuple[np.ndarray, np.ndarray]:
    X, markers, neighbours, rigidity, reference, lam, iterations, measured = item
    F = X.shape[0]
    out = X[:, markers].copy()
    fits, ys_all, runs = [], [], []
    for c, m in enumerate(markers):
        sel = neighbours[c] >= 0
        nb = neighbours[c][sel]
        src = np.broadcast_to(reference[nb], (F, len(nb), 3))
        w = np.broadcast_to(rigidity[c][sel], (F, len(nb)))
        R, t = absolute_orientation_batch(src, X[:, nb], weights=w)
        y = _apply_inv(R, t, X[:, m])
        ok = np.isfinite(y).all(1)
        # runs of measured samples are smoothed; filled samples keep the fill's
        # estimate (the frame's jitter is all smoothing would add to them)
        meas = np.ones(F, dtype=bool) if measured is None else measured[:, m]
        kind = ok & meas
        cut = np.flatnonzero(np.diff(kind.view(np.int8)) != 0) + 1
        a, b = np.r_[0, cut], np.r_[cut, F]
        fits.append((R, t, kind, a, b))
        ys_all.append(y)
        runs.append((a[kind[a]] + c * F, b[kind[a]] + c * F))
    # every marker's runs in one vectorised smoothing
    Y = np.concatenate(ys_all) if ys_all else np.zeros((0, 3))
    YS = _smooth_runs(Y, np.concatenate([r[0] for r in runs]).astype(np.int64),
                      np.concatenate([r[1] for r in runs]).astype(np.int64), lam, iterations)
    for c, (R, t, kind, a_, b_) in enumerate(fits):
        y, ys = Y[c * F:(c + 1) * F], YS[c * F:(c + 1) * F]
        d4 = [np.diff(y[a:b], n=4, axis=0) for a, b in zip(a_, b_) if kind[a] and b - a >= 5]
        if d4:  # measurements move by at most MAX_CORRECTION_SIGMA noise deviations
            k = MAX_CORRECTION_SIGMA
            dd = np.concatenate(d4)
            sigma = 1.4826 * np.median(np.abs(dd - np.median(dd, 0)), 0) / np.sqrt(70.0)
            ys = y + np.clip(ys - y, -k * sigma, k * sigma)
            xs = _apply(R, t, ys)
            out[kind, c] = xs[kind]
    return markers, out


def frame_weights(neighbours: np.ndarray, rigidity: np.ndarray, measured_share: np.ndarray,
                  *, threshold: float = SMOOTH_FRAME_MIN_MEASURED) -> np.ndarray:
    """Neighbour weights of the smoothing frames.

    A neighbour measured in less than ``threshold`` of the frames weighs 0,
    as long as at least 3 others keep a weight (else the marker keeps all).

    Parameters
    ----------
    neighbours : (M, K) int ndarray
        One-rings, ``-1`` padded.
    rigidity : (M, K) float ndarray
    measured_share : (M,) float ndarray
        Share of the frames in which each marker was measured.
    threshold : float

    Returns
    -------
    (M, K) float ndarray
    """
    nb = np.maximum(neighbours, 0)
    rare = (measured_share[nb] < threshold) & (neighbours >= 0)
    w = np.where(rare, 0.0, rigidity)
    keep = ((w > 0) & (neighbours >= 0)).sum(1) >= MIN_NEIGHBOURS
    return np.where(keep[:, None], w, rigidity)


def smooth_local(
    positions: np.ndarray,
    surface: MarkerSurface,
    *,
    smooth_lambda: float = 0.1,
    smooth_iterations: int = 10,
    measured: np.ndarray | None = None,
    ctx: Context | None = None,
) -> np.ndarray:
    """Smooth trajectories in their local frames (Park & Hodgins §4.4).

    Each marker's trajectory is expressed in its local frame (rigid fit of its
    one-ring's reference positions per frame, neighbours weighted by rigidity;
    neighbours measured in few frames left out, :func:`frame_weights`),
    smoothed with ``x ← x − λ Δ⁴x`` iterated, and moved back to global
    coordinates.  Only runs of measured samples are smoothed (estimates never
    drag measurements, and a filled sample keeps the fill's estimate: smoothing it
    in the local frame would only add the frame's jitter), and a measured sample
    moves by at most :data:`MAX_CORRECTION_SIGMA` noise deviations.  Frames whose
    local frame cannot be fitted keep their sample unsmoothed; runs shorter than 5
    frames are left as they are.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
    surface : MarkerSurface
    smooth_lambda : float
        ``λ``; the iteration is stable for ``λ < 1/8``.
    smooth_iterations : int
    measured : (F, M) bool ndarray, optional
        Samples that were measured (observed or merged), as opposed to filled:
        only their runs are smoothed, and their corrections are bounded.  Default:
        every available sample counts as measured.
    ctx : Context, optional

    Returns
    -------
    (F, M, 3) float ndarray
    """
    ctx = ctx or Context()
    X = positions.copy()
    ok = np.isfinite(surface.reference).all(1) & (surface.n_neighbours >= MIN_NEIGHBOURS)
    markers = np.flatnonzero(ok)
    if smooth_iterations <= 0 or smooth_lambda == 0 or len(markers) == 0:
        return X
    parts = max(1, ctx.workers) * 2 if ctx.mapper is not None else 1
    weights = surface.rigidity
    if measured is not None:
        weights = frame_weights(surface.neighbours, surface.rigidity, measured.mean(0))
    items = []
    for c in _chunks(len(markers), parts):
        ms = markers[c]
        items.append((positions, ms, surface.neighbours[ms], weights[ms],
                      surface.reference, smooth_lambda, smooth_iterations, measured))
    for ms, out in ctx.map(_smooth_chunk, items):
        X[:, ms] = out
    return X


# --------------------------------------------------------------------------- the stage


class CleanError(ValueError):
    """The capture cannot be cleaned (no markers, bad reference frame, ...)."""


def _trajectory_count(positions: np.ndarray) -> int:
    return int(finite_rows(positions).any(0).sum())


def _check_params(positions: np.ndarray, *, alpha1: float, alpha2: float, variance: float,
                  fill_model: str, fill_predictors: int, max_break: float = BREAK_JUMP) -> None:
    """Raise :class:`CleanError` for an empty capture or params out of range."""
    F, M, _ = positions.shape
    if M == 0 or F == 0:
        raise CleanError("clean: the capture has no labelled markers or no frames")
    if not (0 < alpha1 and 0 < alpha2):
        raise CleanError(f"clean: alpha1 and alpha2 must be positive (got {alpha1}, {alpha2})")
    if not 0 < variance <= 1:
        raise CleanError(f"clean: variance must be in (0, 1], got {variance}")
    if fill_model not in ("regression", "pca"):
        raise CleanError(f"clean: fill_model must be 'regression' or 'pca', got {fill_model!r}")
    if fill_predictors < REGRESSION_MIN_PREDICTORS:
        raise CleanError(f"clean: fill_predictors must be >= {REGRESSION_MIN_PREDICTORS}, "
                         f"got {fill_predictors}")
    if not max_break >= 0:
        raise CleanError(f"clean: max_break must be >= 0 (0: off), got {max_break}")


def _reference(
    positions: np.ndarray, labels: list[str], reference_frame: int | None, ctx: Context
) -> tuple[int, np.ndarray, dict[int, int], np.ndarray]:
    """Step 0: the reference frame and pose, markers missing there carried over (warned).

    Returns ``(frame, reference (M, 3), carried {marker: source frame},
    unrecoverable (K,) markers never visible)``.
    """
    F = positions.shape[0]
    if reference_frame is None:
        ref_frame = choose_reference_frame(positions)
    else:
        if not -F <= reference_frame < F:
            raise CleanError(
                f"clean: reference_frame {reference_frame} out of range (capture has {F} frames)"
            )
        ref_frame = int(reference_frame) % F
    reference, carried, unrecoverable = reference_pose(positions, ref_frame)
    if carried:
        ctx.warn(
            f"clean: {len(carried)} marker(s) missing in reference frame {ref_frame}; reference "
            f"position carried over from the nearest frame where visible: "
            + ", ".join(f"{labels[m]} (frame {g})" for m, g in list(carried.items())[:20])
        )
    if len(unrecoverable):
        ctx.warn(f"clean: marker(s) never visible, left NaN: {_names(labels, unrecoverable)}")
    return ref_frame, reference, carried, unrecoverable


def _marker_surface(
    reference: np.ndarray, positions: np.ndarray, labels: list[str], surface: str | None,
    ref_frame: int, ctx: Context,
) -> tuple[MarkerSurface, np.ndarray]:
    """Step 1 (§4.1): the marker surface, from the ``surface`` file or automatic.

    Returns the surface and the markers with fewer than 3 neighbours (warned: not
    merged, filled only by the whole-body blend, and only with 1-2 neighbours).
    """
    if surface is not None:
        faces = read_surface_file(surface, labels)
        surf = marker_surface_from_faces(reference, faces, labels=labels, positions=positions,
                                         source=str(surface).rsplit("/", 1)[-1])
    else:
        surf = build_marker_surface(reference, positions=positions, labels=labels)
    surf.reference_frame = ref_frame  # carried into the exported surface mesh's attrs
    few = np.flatnonzero(np.isfinite(reference).all(1) & (surf.n_neighbours < MIN_NEIGHBOURS))
    if len(few):
        ctx.warn(
            f"clean: marker(s) with fewer than {MIN_NEIGHBOURS} surface neighbours are not "
            f"merged, and filled only by the models that need no neighbourhood (with 1-2 "
            f"neighbours, the regression fill, at most {WHOLE_BODY_MAX_MARKERS} markers; "
            f"else their holes stay NaN): {_names(labels, few)}",
            hint="give clean.surface a marker-surface file that connects them to their "
                 "neighbours; harmless if they are never occluded",
        )
    return surf, few


def _record_round(mrep: dict[str, Any], rep: dict[str, Any], assigned: np.ndarray,
                  left: np.ndarray, a2: np.ndarray, depth: str, *,
                  reason: str | None = None) -> None:
    """A round over the fragments ``left`` into the merge report (in place): their
    markers ``a2`` (-1: none) into ``assigned``, the round's merges and conflicts added,
    its merge count under ``depth``.  The rejections become the round's; with
    ``reason``, a fragment's earlier verdict stays its reason (it says more: entry
    distance, nearest marker) and the round's comes with it under that key."""
    assigned[left[a2 >= 0]] = a2[a2 >= 0]
    mrep["merges"] += rep["merges"]
    mrep["conflicts"] += rep["conflicts"]
    if reason is None:
        mrep["rejections"] = rep["rejections"]
    else:
        before = {r["fragment"]: r for r in mrep["rejections"]}
        mrep["rejections"] = [{**r, **before.get(r["fragment"], {}), reason: r["reason"]}
                              for r in rep["rejections"]]
    mrep["merged_by_depth"][depth] = len(rep["merges"])


def _pca_merge_rounds(
    X: np.ndarray, assigned: np.ndarray, mrep: dict[str, Any], markers: Markers,
    surf: MarkerSurface, *, alpha1: float, alpha2: float, variance: float, rounds: int,
    ctx: Context, max_break: float = BREAK_JUMP,
) -> np.ndarray:
    """Step 2, beyond the paper: fragments left unmerged judged against the §4.3 PCA fill.

    Up to ``rounds`` rounds, each filling the frames where fragments wait
    (:data:`MERGE_FILL_PASSES` passes, models and estimates re-used between
    rounds) and judging the fragments against its first pass; ``assigned`` and
    ``mrep`` are updated in place.  Returns the merged positions ``(F, M, 3)``.
    """
    frags = markers.fragments
    fvis = finite_rows(frags)  # (F, U), once: the fragments never change
    models = None
    fill_cache: dict = {}  # the rounds' data differ only where fragments were merged
    for k in range(rounds):
        ctx.progress(1 + k, 1 + rounds, "merge passes")
        left = np.flatnonzero(assigned < 0)
        if not len(left):
            break
        # judge the rest against the PCA hole filling of the merged data (§4.3)
        waiting = fvis[:, left].any(1)
        Xf, finfo0 = fill_holes(X, surf, variance=variance, models=models, frames=waiting,
                                model="pca", cache=fill_cache, ctx=ctx,
                                max_passes=MERGE_FILL_PASSES, rigid_fallback=False)
        models = finfo0.get("model_list") or models
        # trust the estimates of the first pass (from measured members) only
        direct = np.where((finfo0["pass"] == 1)[..., None], Xf, np.nan)
        X, a2, rep2 = merge_fragments(
            X, frags[:, left], surf, alpha1=alpha1, alpha2=alpha2,
            fragment_labels=[markers.fragment_labels[u] for u in left], predictions=direct,
            competitors=Xf, max_break=max_break, rate=markers.rate, ctx=ctx,
        )
        for mg in rep2["merges"]:
            mg["predictor"] = "pca"
            mg["round"] = f"pca{k + 1}"
        _record_round(mrep, rep2, assigned, left, a2, f"pca{k + 1}")
        if not rep2["merges"]:
            break
    return X


def _fill_merge_rounds(
    X: np.ndarray, assigned: np.ndarray, mrep: dict[str, Any], markers: Markers,
    surf: MarkerSurface, *, alpha1: float, alpha2: float, variance: float, fill_model: str,
    fill_predictors: int, rounds: int, ctx: Context,
) -> np.ndarray:
    """Step 2, beyond the paper: fragments still left judged against the final hole filling.

    Up to ``rounds`` rounds, each filling the merged data as step 3 does
    (``fill_model``, in the frames where fragments wait) and merging the
    fragments against it jointly
    (:func:`~mocapflow.stages.skin.assign.assign_fragments`: the ε₁ / ε₂ tests,
    exact gaps, one assignment problem per frame window), until a round merges
    nothing.  ``assigned`` and ``mrep`` are updated in place.  Returns the
    merged positions ``(F, M, 3)``.
    """
    frags = markers.fragments
    for k in range(rounds):
        left = np.flatnonzero(assigned < 0)
        if not len(left):
            break
        waiting = finite_rows(frags[:, left]).any(1)
        Xf, _ = fill_holes(X, surf, variance=variance, model=fill_model,
                           n_predictors=fill_predictors, frames=waiting, ctx=ctx)
        X, a2, rep = assign_fragments(
            X, frags[:, left], surf, Xf, alpha1=alpha1, alpha2=alpha2,
            fragment_labels=[markers.fragment_labels[u] for u in left])
        for mg in rep["merges"]:
            mg["round"] = f"fill{k + 1}.{mg['round']}"
        _record_round(mrep, rep, assigned, left, a2, f"fill{k + 1}", reason="fill_reason")
        if not rep["merges"]:
            break
    return X


def _template_merge_rounds(
    X: np.ndarray, assigned: np.ndarray, mrep: dict[str, Any], markers: Markers,
    surf: MarkerSurface, *, alpha1: float, alpha2: float, variance: float, fill_model: str,
    fill_predictors: int, rounds: int, max_break: float, ctx: Context,
) -> np.ndarray:
    """Step 2, beyond the paper: fragments left, proposed by the markers' layout and judged again.

    Each round, on the fragments left that last at least :data:`TEMPLATE_MIN_DURATION`:
    frames that together see them
    (:func:`~mocapflow.stages.skin.labelling.fragment_frames`), the missing markers
    estimated there by the hole filling (``fill_model``, those frames only), a
    marker proposed for each fragment by matching the estimates' layout to the
    fragments (:func:`~mocapflow.stages.skin.labelling.template_proposals`), the
    proposals put in place (a sample two proposals claim stays out), and every
    fragment left judged by the usual tests (:func:`merge_fragments` with given
    predictions: ε₁ / ε₂, the mean, the ambiguity and rival tests) against the rigid
    predictions (:func:`~mocapflow.stages.skin.predict.rigid_estimates`) of the
    missing samples from their neighbours, the proposals among them; until a round
    merges nothing.  A proposal is never merged on its own: a wrong one moves its
    neighbours' predictions off, not onto, the fragments.  ``assigned`` and ``mrep``
    are updated in place.  Returns the merged positions ``(F, M, 3)``.
    """
    frags = markers.fragments
    rate = markers.rate or 0.0
    shortest = max(ASSIGN_MIN_FRAMES, int(np.ceil(TEMPLATE_MIN_DURATION * rate)))
    n_frames = finite_rows(frags).sum(0)
    for k in range(rounds):
        left = np.flatnonzero((assigned < 0) & (n_frames >= shortest))
        if not len(left):
            break
        fl = frags[:, left]
        fvis = finite_rows(fl)
        frames = fragment_frames(fvis, min_frames=shortest)
        if not len(frames):
            break
        at = np.zeros(len(X), dtype=bool)
        at[frames] = True
        Xf, _ = fill_holes(X, surf, variance=variance, model=fill_model,
                           n_predictors=fill_predictors, frames=at, ctx=ctx)
        proposal = template_proposals(X, fl, Xf, frames, min_frames=shortest)
        if not (proposal >= 0).any():
            break
        Xt = X.copy()
        claims = np.zeros(X.shape[:2], dtype=np.int64)
        for u in np.flatnonzero(proposal >= 0):
            claims[fvis[:, u], proposal[u]] += 1
        for u in np.flatnonzero(proposal >= 0):
            v = fvis[:, u] & (claims[:, proposal[u]] == 1)
            Xt[v, proposal[u]] = fl[v, u]
        f, m = np.nonzero(fvis.any(1)[:, None] & ~finite_rows(X))
        E = np.full_like(X, np.nan)
        E[f, m] = rigid_estimates(Xt, surf.reference, surf.neighbours, f, m,
                                  rigidity=surf.rigidity)
        X, a2, rep = merge_fragments(
            X, fl, surf, alpha1=alpha1, alpha2=alpha2,
            fragment_labels=[markers.fragment_labels[u] for u in left], predictions=E,
            competitors=E, max_break=max_break, rate=markers.rate, ctx=ctx)
        for mg in rep["merges"]:
            mg["predictor"] = "template"
            mg["round"] = f"template{k + 1}"
        _record_round(mrep, rep, assigned, left, a2, f"template{k + 1}",
                      reason="template_reason")
        if not rep["merges"]:
            break
    return X


def _merge(
    markers: Markers, surf: MarkerSurface, *, merge: bool, alpha1: float, alpha2: float,
    variance: float, pca_rounds: int, ctx: Context, fill_rounds: int = 0,
    template_rounds: int = 0,
    fill_model: str = "regression", fill_predictors: int = REGRESSION_PREDICTORS,
    max_break: float = BREAK_JUMP,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Step 2 (§4.2): fragments merged against rigid predictions, then the PCA rounds,
    the rounds against the final filling (:func:`_fill_merge_rounds`) and the rounds
    with the markers' layout (:func:`_template_merge_rounds`).

    Returns ``(positions (F, M, 3), assigned (U,) marker per fragment or -1,
    report)``.
    """
    P, frags = markers.positions, markers.fragments
    U = frags.shape[1]
    if not (merge and U):
        mrep = {"merges": [], "rejections": [], "conflicts": [], "merged_by_depth": {}}
        return P.copy(), np.full(U, -1, dtype=np.int64), mrep
    total = 1 + pca_rounds + fill_rounds + template_rounds
    ctx.progress(0, total, "merge passes")
    X, assigned, mrep = merge_fragments(
        P, frags, surf, alpha1=alpha1, alpha2=alpha2,
        fragment_labels=markers.fragment_labels, depths=(1,), max_break=max_break,
        rate=markers.rate, ctx=ctx,
    )
    X = _pca_merge_rounds(X, assigned, mrep, markers, surf, alpha1=alpha1, alpha2=alpha2,
                          variance=variance, rounds=pca_rounds, max_break=max_break, ctx=ctx)
    X = _fill_merge_rounds(X, assigned, mrep, markers, surf, alpha1=alpha1, alpha2=alpha2,
                           variance=variance, fill_model=fill_model,
                           fill_predictors=fill_predictors, rounds=fill_rounds, ctx=ctx)
    X = _template_merge_rounds(X, assigned, mrep, markers, surf, alpha1=alpha1, alpha2=alpha2,
                               variance=variance, fill_model=fill_model,
                               fill_predictors=fill_predictors, rounds=template_rounds,
                               max_break=max_break, ctx=ctx)
    ctx.progress(total, total, "merge passes")
    return X, assigned, mrep


def _fill(
    X: np.ndarray, surf: MarkerSurface, labels: list[str], *, fill: bool, variance: float,
    fill_model: str, fill_predictors: int, rate: float, ctx: Context,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Step 3 (§4.3): hole filling; the info without the models and the pass map, the
    samples left unfilled as implausible per marker label (warned)."""
    if not fill:
        return X, {"filled_by_pass": []}
    Xf, finfo = fill_holes(X, surf, variance=variance, model=fill_model,
                           n_predictors=fill_predictors, rate=rate, ctx=ctx)
    finfo.pop("model_list", None)
    finfo.pop("pass", None)
    left = np.asarray(finfo.pop("implausible", np.zeros(len(labels), dtype=int)))
    finfo["implausible"] = {labels[m]: int(left[m]) for m in np.flatnonzero(left)}
    if left.any():
        ctx.warn(f"clean: {int(left.sum())} samples of {int((left > 0).sum())} marker(s) left "
                 f"unfilled: every estimate of their gaps leaves the marker's rigid partners "
                 f"or outruns its fastest measured step by more than "
                 f"{PLAUSIBILITY_LIMIT * 1000:.0f} mm (next to those samples, or next to half "
                 f"of the gap's samples): "
                 f"{_names(labels, np.flatnonzero(left))}",
                 hint="little is measured near them there (their segment is hidden with "
                      "them); they stay holes rather than estimates far off "
                      "(report: fill.implausible)")
    return Xf, finfo


def _status(observed: np.ndarray, merged: np.ndarray, filled: np.ndarray) -> np.ndarray:
    """``(F, M)`` int8 :data:`STATUS` codes from the samples available after each step."""
    status = np.full(observed.shape, STATUS["missing"], dtype=np.int8)
    status[observed] = STATUS["observed"]
    status[merged & ~observed] = STATUS["merged"]
    status[filled & ~merged] = STATUS["filled"]
    return status


def _cleaned_markers(markers: Markers, positions: np.ndarray, status: np.ndarray,
                     filled: np.ndarray, assigned: np.ndarray, ref_frame: int) -> Markers:
    """The cleaned :class:`Markers`: residuals 0 where merged or filled (``filled``:
    ``(F, M)`` samples available after filling), ``status`` (:data:`STATUS` codes),
    unmerged fragments kept, analogs and the source's attrs passed through, a summary
    in ``attrs["clean"]``."""
    keep_frag = assigned < 0
    out = markers.replace(
        positions=positions,
        residuals=None if markers.residuals is None else np.where(
            status == STATUS["observed"], markers.residuals, np.where(filled, 0.0, np.nan)),
        fragments=markers.fragments[:, keep_frag],
        fragment_labels=[lb for lb, k in zip(markers.fragment_labels, keep_frag) if k],
        status=status,
    )
    out.attrs["clean"] = {
        "reference_frame": ref_frame, "merged_fragments": int((~keep_frag).sum()),
        "filled_samples": int((status == STATUS["filled"]).sum()),
        "missing_samples": int((~filled).sum()),
    }
    return out


def _surface_summary(surf: MarkerSurface, reference: np.ndarray) -> dict[str, Any]:
    return {
        "source": surf.source,
        "n_faces": int(len(surf.faces)),
        "mean_neighbours": float(np.mean(surf.n_neighbours[np.isfinite(reference).all(1)]))
        if np.isfinite(reference).any() else 0.0,
        "mean_neighbour_distance_mm": round(float(np.nanmean(surf.mean_distance)) * 1000, 2)
        if np.isfinite(surf.mean_distance).any() else None,
    }


def _table1(markers: Markers, assigned: np.ndarray, status: np.ndarray, merged: np.ndarray,
            filled: np.ndarray) -> dict[str, int]:
    """The paper's Table 1: fragments before / after, merged, holes, filled, left.

    ``merged`` / ``filled``: ``(F, M)`` samples available after merging / filling.
    """
    P, vis0 = markers.positions, markers.visible
    M = P.shape[1]
    U = markers.fragments.shape[1]
    runs_before = sum(len(true_runs(vis0[:, m])) for m in range(M))
    n_traj = _trajectory_count(P)
    keep_frag = assigned < 0
    return {
        "markers": M,
        "fragments_before": n_traj + U,
        "fragments_after": n_traj + int(keep_frag.sum()),
        "runs_before": runs_before + U,
        "merged": int((~keep_frag).sum()),
        "holes": int((~merged).sum()),
        "filled": int((status == STATUS["filled"]).sum()),
        "left_unfilled": int((~filled).sum()),
    }


def _report(
    markers: Markers, surf: MarkerSurface, reference: np.ndarray, status: np.ndarray,
    assigned: np.ndarray, merged: np.ndarray, filled: np.ndarray, *, ref_frame: int,
    carried: dict[int, int], unrecoverable: np.ndarray, few: np.ndarray,
    mrep: dict[str, Any], finfo: dict[str, Any], params: dict[str, Any],
) -> dict[str, Any]:
    """The clean report (see :func:`clean`); ``merged`` / ``filled``: ``(F, M)`` samples
    available after merging / filling."""
    labels = markers.labels
    left = ~filled
    left_markers = np.flatnonzero(left.any(0))
    unfillable = np.flatnonzero(left.any(0) & (surf.n_neighbours < MIN_NEIGHBOURS))
    never = np.flatnonzero(~markers.visible.any(0))
    report: dict[str, Any] = {
        "reference_frame": ref_frame,
        "reference_carried_over": {labels[m]: g for m, g in carried.items()},
        "surface": _surface_summary(surf, reference),
        "table1": _table1(markers, assigned, status, merged, filled),
        **mrep,
        "fill": finfo,
        "never_visible": [labels[i] for i in unrecoverable],
        "too_few_neighbours": [labels[i] for i in few],
        "markers_with_holes_left": [labels[i] for i in left_markers],
        "unfillable_markers": [labels[i] for i in unfillable],
        "params": params,
        "status": status,
        "_dims": {"status": ["frame", "marker"]},  # (mocapflow.pipeline.codecs.RECORD_DIMS)
    }
    if never.size and not len(unrecoverable):
        report["never_visible"] = [labels[i] for i in never]
    return report


@stage("clean", outputs=("markers", "report", "surface"))
def clean(
    markers: Markers,
    *,
    alpha1: float = 0.5,
    alpha2: float = 0.6,
    variance: float = 0.99,
    smooth_lambda: float = 0.1,
    smooth_iterations: int = 10,
    reference_frame: int | None = None,
    surface: FilePath | None = None,
    merge: bool = True,
    fill: bool = True,
    fill_model: Literal["regression", "pca"] = "regression",
    fill_predictors: int = REGRESSION_PREDICTORS,
    pca_merge_rounds: int = 3,
    fill_merge_rounds: int = 0,
    template_merge_rounds: int = 8,
    max_break: float = BREAK_JUMP,
    subjects: Literal["auto", "none"] = "auto",
    subject_gap: float = 0.3,
    label_template: FilePath | None = None,
    ctx: Context,
) -> dict[str, Any]:
    """Merge fragments, fill holes and smooth a dense marker capture (Park & Hodgins 2006 §4).

    Parameters
    ----------
    markers : Markers
        ``positions (F, M, 3)`` labelled trajectories with NaN holes and
        ``fragments (F, U, 3)`` unlabelled trajectories.
    alpha1 : float
        Entry tolerance of a fragment, ``ε₁ = α₁ · mean neighbour distance`` (0.5).
    alpha2 : float
        Tolerance over the whole fragment, ``ε₂ = α₂ · mean neighbour distance`` (0.6).
    variance : float
        Variance kept by each local PCA model (0.99).
    smooth_lambda : float
        ``λ`` of the local-frame smoother ``x ← x − λ Δ⁴x`` (stable below 1/8).
    smooth_iterations : int
        Smoother iterations (0 disables smoothing).
    reference_frame : int, optional
        Frame of the reference pose; default: the frame with the most visible markers.
    surface : FilePath, optional
        Manual marker-surface file (see :mod:`mocapflow.stages.skin.surface`); default:
        built automatically from the reference pose.
    merge, fill : bool
        Run the merge / hole-filling steps.
    fill_model : {"regression", "pca"}
        ``"pca"``: the paper's local PCA of marker + one-ring (§4.3).
        ``"regression"`` (default): each gap first regressed on the marker's
        ``fill_predictors`` most rigid nearby markers visible through it (the
        PCA passes fill the rest).  Merging always judges fragments against
        the PCA fill.
    fill_predictors : int
        Predictors per regression (32).
    pca_merge_rounds : int
        Rounds judging the fragments the rigid predictions left unmerged against
        the PCA hole filling of the merged data (3; 0: rigid predictions only;
        none without ``fill``).
    fill_merge_rounds : int
        Rounds judging the fragments still left against the final hole filling
        (``fill_model``), jointly: exact gaps, then one assignment problem per
        frame window (:func:`~mocapflow.stages.skin.assign.assign_fragments`);
        until a round merges nothing (0: off, the default; none without ``fill``).
        5 (``--set clean.fill_merge_rounds=5``): on simulated dynamic and walk
        captures it keeps 99-100 % of real samples with no wrong merge, but on a
        range-of-motion capture, whose fill is off by more than ε₁, it made 1-2
        wrong merges (seeds 2, 3), so it is off by default.
    template_merge_rounds : int
        Then, rounds in which each fragment still left gets a marker proposed by
        matching the layout of the missing markers' estimates to the fragments seen
        in a frame (:func:`~mocapflow.stages.skin.labelling.template_proposals`), and
        every fragment left is judged again against rigid predictions made with the
        proposals in place (:func:`_template_merge_rounds`); until a round merges
        nothing (8; 0: off; none without ``fill``).  For a limb that lost all its
        labels at once (no prediction reaches its fragments).
    max_break : float
        A fragment that picks up where a marker stopped, across a break or a gap of
        at most 8 frames, or 67 ms above 120 Hz
        (:func:`~mocapflow.stages.skin.merge.bridge_frames`), merges by continuity
        when its end lies within
        ``max_break · ε₁`` of the marker's gap-end sample carried by its
        neighbours' rigid motion and no rival comes close
        (:func:`~mocapflow.stages.skin.merge.continue_breaks`; 0.25; 0: off, the
        paper).
    subjects : {"auto", "none"}
        Several subjects in one take (:func:`~mocapflow.stages.skin.labelling.subject_groups`):
        ``"auto"`` finds them by the C3D's ``SUBJECTS:LABEL_PREFIXES``, ``Name:``
        label prefixes, or groups of markers more than ``subject_gap`` apart in the
        reference pose (each of >= 10 markers), and cleans each subject on its own
        (one reference frame), so no neighbourhood, surface triangle or fill
        predictor spans two subjects; fragments go to the nearest subject.
        ``"none"``: one subject.
    subject_gap : float
        Metres between subjects standing apart (0.3).
    label_template : FilePath, optional
        For a take with no labelled markers: a labelled C3D or a JSON layout
        (``labels``, ``positions``, ``unit``) of the same marker set from an earlier
        session; the take's reference-frame trajectories are matched to it (rigid +
        non-rigid ICP) and get its labels.  Without it an unlabelled take is
        labelled ``L001 …`` by its reference frame (§4.1).

    Returns
    -------
    dict
        ``markers``: the cleaned :class:`Markers` (unmerged fragments kept);
        ``report``: record with ``labelling`` (how an unlabelled take got its
        labels, when it had none), ``subjects`` (names and labels, with two or
        more), ``status (F, M)`` int8 (-1 missing, 0 observed,
        1 merged, 2 filled) and JSON: reference frame, surface, ``table1``
        (fragments before/after, merges, holes, filled, left), ``merges`` /
        ``rejections`` / ``conflicts`` (fragment, label, reason), fill passes and
        models, samples left unfilled as implausible per marker (``fill.implausible``),
        never-visible and too-few-neighbour markers (step timings go to
        ``ctx.timer``: the manifest, never the report);
        ``surface``: the marker surface as a
        :class:`~mocapflow.stages.motion.datatypes.Mesh` (vertices = reference pose
        of the markers, ``attrs["labels"]``; :meth:`MarkerSurface.from_mesh` gives
        the :class:`MarkerSurface` back).
    """
    opts = {"alpha1": alpha1, "alpha2": alpha2, "variance": variance,
            "smooth_lambda": smooth_lambda, "smooth_iterations": smooth_iterations,
            "surface": surface, "merge": merge, "fill": fill, "fill_model": fill_model,
            "fill_predictors": fill_predictors, "pca_merge_rounds": pca_merge_rounds,
            "fill_merge_rounds": fill_merge_rounds,
            "template_merge_rounds": template_merge_rounds, "max_break": max_break}
    with ctx.timer("labelling"):
        try:
            markers, labelling = label_markers(markers, template=label_template,
                                               reference_frame=reference_frame)
        except LabellingError as e:
            raise CleanError(str(e)) from None
        if labelling:
            reference_frame = labelling["reference_frame"]
            ctx.warn(f"clean: unlabelled take labelled by {labelling['method']}: "
                     f"{len(markers.labels)} markers, {markers.fragments.shape[1]} fragments "
                     "left to merge")
    P = markers.positions
    _check_params(P, alpha1=alpha1, alpha2=alpha2, variance=variance, fill_model=fill_model,
                  fill_predictors=fill_predictors, max_break=max_break)
    groups = [("all", np.arange(P.shape[1]))]
    if subjects != "none" and surface is None:
        frame = choose_reference_frame(P) if reference_frame is None else reference_frame
        groups = subject_groups(markers, _nearest_visible_pose(P, _check_frame(frame, len(P))),
                                mode=subjects, gap=subject_gap)
        reference_frame = frame if len(groups) > 1 else reference_frame
    if len(groups) == 1:
        res = _clean_subject(markers, reference_frame=reference_frame, opts=opts, ctx=ctx)
    else:
        res = _clean_subjects(markers, groups, reference_frame=reference_frame, opts=opts,
                              ctx=ctx)
    if labelling:
        res["report"]["labelling"] = labelling
    _key_figures(res["report"], res["report"]["status"], ctx)
    return res


def _nearest_visible_pose(positions: np.ndarray, frame: int) -> np.ndarray:
    """``(M, 3)``: each marker where it is seen nearest in time to ``frame`` (NaN if never)."""
    vis = finite_rows(positions)
    dist = np.where(vis, np.abs(np.arange(len(positions)) - frame)[:, None], np.iinfo(np.int64).max)
    g = np.argmin(dist, axis=0)
    return positions[g, np.arange(positions.shape[1])]


def _check_frame(frame: int, F: int) -> int:
    if not -F <= frame < F:
        raise CleanError(f"clean: reference_frame {frame} out of range (capture has {F} frames)")
    return int(frame) % F


def _clean_subject(markers: Markers, *, reference_frame: int | None, opts: dict[str, Any],
                   ctx: Context, parts: dict[str, Any] | None = None) -> dict[str, Any]:
    """Steps 0-4 on one subject (:func:`clean`'s outputs); ``parts``, when given, also
    receives the intermediate arrays the multi-subject assembly needs."""
    P = markers.positions
    labels = markers.labels
    o = opts
    with ctx.timer("reference"):
        ref_frame, reference, carried, unrecoverable = _reference(P, labels, reference_frame,
                                                                  ctx)
    with ctx.timer("surface"):
        surf, few = _marker_surface(reference, P, labels, o["surface"], ref_frame, ctx)
    fill = o["fill"]
    with ctx.timer("merge"):
        X, assigned, mrep = _merge(markers, surf, merge=o["merge"], alpha1=o["alpha1"],
                                   alpha2=o["alpha2"], variance=o["variance"],
                                   pca_rounds=o["pca_merge_rounds"] if fill else 0,
                                   fill_rounds=o["fill_merge_rounds"] if fill else 0,
                                   template_rounds=o["template_merge_rounds"] if fill else 0,
                                   fill_model=o["fill_model"],
                                   fill_predictors=o["fill_predictors"],
                                   max_break=o["max_break"], ctx=ctx)
    vis1 = finite_rows(X)
    with ctx.timer("fill"):
        Xf, finfo = _fill(X, surf, markers.labels, fill=fill, variance=o["variance"],
                          fill_model=o["fill_model"], fill_predictors=o["fill_predictors"],
                          rate=markers.rate, ctx=ctx)
    vis2 = finite_rows(Xf)
    status = _status(markers.visible, vis1, vis2)
    with ctx.timer("smooth"):
        Xs = smooth_local(Xf, surf, smooth_lambda=o["smooth_lambda"],
                          smooth_iterations=o["smooth_iterations"], measured=vis1, ctx=ctx)
    if parts is not None:
        parts.update(Xs=Xs, status=status, vis1=vis1, vis2=vis2, assigned=assigned,
                     surf=surf, reference=reference, carried=carried,
                     unrecoverable=unrecoverable, few=few, mrep=mrep, finfo=finfo,
                     ref_frame=ref_frame)
    report = _report(markers, surf, reference, status, assigned, vis1, vis2, ref_frame=ref_frame,
                     carried=carried, unrecoverable=unrecoverable, few=few, mrep=mrep,
                     finfo=finfo, params=_report_params(o))
    out = _cleaned_markers(markers, Xs, status, vis2, assigned, ref_frame)
    return {"markers": out, "report": report, "surface": surf.to_mesh()}


def _report_params(opts: dict[str, Any]) -> dict[str, Any]:
    keys = ("alpha1", "alpha2", "variance", "smooth_lambda", "smooth_iterations", "fill_model",
            "fill_predictors")
    return {k: opts[k] for k in keys}


def _union_surface(surfs: list[MarkerSurface], groups: list[tuple[str, np.ndarray]],
                   labels: list[str], ref_frame: int) -> MarkerSurface:
    """One :class:`MarkerSurface` over every subject's markers (no edge between subjects)."""
    M = len(labels)
    K = max(s.neighbours.shape[1] for s in surfs)
    reference = np.full((M, 3), np.nan)
    neighbours = np.full((M, K), -1, dtype=np.int64)
    rigidity = np.zeros((M, K))
    frames = np.full((M, 3, 3), np.nan)
    n_ring = np.zeros(M, dtype=np.int64)
    faces = []
    for s, (_, idx) in zip(surfs, groups):
        reference[idx] = s.reference
        nb = s.neighbours
        neighbours[idx, : nb.shape[1]] = np.where(nb >= 0, idx[np.maximum(nb, 0)], -1)
        rigidity[idx, : nb.shape[1]] = s.rigidity
        frames[idx] = s.frames
        n_ring[idx] = s.n_ring
        faces.append(idx[s.faces.reshape(-1, 3)])
    return MarkerSurface(reference, np.concatenate(faces).astype(np.int64), neighbours, frames,
                         list(labels), surfs[0].source, rigidity, n_ring, ref_frame)


def _combine_merge_reports(mreps: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for rep in mreps:
        for k, v in rep.items():
            if isinstance(v, list):
                out.setdefault(k, []).extend(v)
            elif isinstance(v, dict):
                d = out.setdefault(k, {})
                for kk, vv in v.items():
                    d[kk] = d.get(kk, 0) + vv if isinstance(vv, (int, float)) else vv
            else:
                out.setdefault(k, v)
    return out


def _clean_subjects(markers: Markers, groups: list[tuple[str, np.ndarray]], *,
                    reference_frame: int, opts: dict[str, Any], ctx: Context) -> dict[str, Any]:
    """:func:`_clean_subject` on each subject (its markers and nearest fragments), the
    results assembled in the take's marker order."""
    F, M, _ = markers.positions.shape
    U = markers.fragments.shape[1]
    owner = fragment_subjects(markers, groups)
    Xs = np.full((F, M, 3), np.nan)
    status = np.full((F, M), STATUS["missing"], dtype=np.int8)
    vis1 = np.zeros((F, M), dtype=bool)
    vis2 = np.zeros((F, M), dtype=bool)
    reference = np.full((M, 3), np.nan)
    assigned = np.full(U, -1, dtype=np.int64)
    carried: dict[int, int] = {}
    unrec, few, surfs, mreps, finfos = [], [], [], [], {}
    for g, (name, idx) in enumerate(groups):
        fr = np.flatnonzero(owner == g)
        sub = markers.replace(
            positions=markers.positions[:, idx], labels=[markers.labels[i] for i in idx],
            residuals=None if markers.residuals is None else markers.residuals[:, idx],
            fragments=markers.fragments[:, fr],
            fragment_labels=[markers.fragment_labels[u] for u in fr], status=None)
        parts: dict[str, Any] = {}
        _clean_subject(sub, reference_frame=reference_frame, opts=opts, ctx=ctx, parts=parts)
        Xs[:, idx], status[:, idx] = parts["Xs"], parts["status"]
        vis1[:, idx], vis2[:, idx] = parts["vis1"], parts["vis2"]
        reference[idx] = parts["reference"]
        a = parts["assigned"]
        assigned[fr[a >= 0]] = idx[a[a >= 0]]
        carried.update({int(idx[m]): v for m, v in parts["carried"].items()})
        unrec.append(idx[np.asarray(parts["unrecoverable"], dtype=np.int64)])
        few.append(idx[np.asarray(parts["few"], dtype=np.int64)])
        surfs.append(parts["surf"])
        mreps.append(parts["mrep"])
        finfos[name] = parts["finfo"]
    ref_frame = _check_frame(reference_frame, F)
    surf = _union_surface(surfs, groups, markers.labels, ref_frame)
    report = _report(markers, surf, reference, status, assigned, vis1, vis2, ref_frame=ref_frame,
                     carried=carried, unrecoverable=np.concatenate(unrec),
                     few=np.concatenate(few), mrep=_combine_merge_reports(mreps),
                     finfo={"subjects": finfos}, params=_report_params(opts))
    report["subjects"] = {name: [markers.labels[i] for i in idx] for name, idx in groups}
    ctx.warn(f"clean: {len(groups)} subjects cleaned apart: " + ", ".join(
        f"{name} ({len(idx)} markers, {int((owner == g).sum())} fragments)"
        for g, (name, idx) in enumerate(groups)))
    out = _cleaned_markers(markers, Xs, status, vis2, assigned, ref_frame)
    return {"markers": out, "report": report, "surface": surf.to_mesh()}


#: A merge whose mean distance to its prediction exceeds this share of ε₂ is counted
#: as a wrong-merge risk in the run summary (it passed, but with little margin).
RISKY_MERGE_SHARE = 0.8


def _key_figures(report: dict[str, Any], status: np.ndarray, ctx: Context) -> None:
    """The run summary's figures of a clean (``ctx.figure``; never in an output)."""
    t1 = report["table1"]
    ctx.figure("holes filled", t1["filled"])
    ctx.figure("samples filled %", round(100.0 * t1["filled"] / max(status.size, 1), 2))
    ctx.figure("merges", t1["merged"])
    ctx.figure("unmerged fragments", len(report.get("rejections") or []))
    ctx.figure("wrong-merge risk", sum(
        1 for m in report.get("merges") or []
        if m.get("eps2_mm") and m["mean_mm"] > RISKY_MERGE_SHARE * m["eps2_mm"]))
