"""Cleaning dense marker captures (Park & Hodgins 2006, §4).

Steps, each in the paper's words:

0. **reference pose** — the frame with the most visible markers (or the
   ``reference_frame`` param).  Markers missing there get their reference
   position from the nearest frame in which they are visible, carried over by a
   rigid fit of their spatial neighbours (a warning names them); markers never
   visible have none and are left NaN.
1. **marker surface and local frames** (§4.1) — :mod:`mocapflow.stages.surface`:
   built automatically (or read from the ``surface`` override file), one-ring
   neighbours, a local frame ``(t, b, n)`` per marker.
2. **merging** (§4.2) — every missing sample of a marker is predicted from at
   least 3 available neighbours by a rigid fit (Horn) into its local reference
   frame.  In every frame the missing markers are processed greedily by their
   number of available neighbours, and estimates are re-used as neighbours for
   the next ones.  An unlabelled fragment is merged into a marker that is
   missing over the whole fragment when its first predicted sample lies within
   ``ε₁ = α₁·d̄`` of the prediction and every sample stays within
   ``ε₂ = α₂·d̄`` (``d̄`` the marker's mean neighbour distance).  Ties between
   markers or fragments are conflicts (reported, nothing merged unless one is
   clearly closest); predictions are recomputed after every round of merges.
3. **hole filling** (§4.3) — per marker a PCA model (``variance`` = 99 %) of the
   marker and its one-ring in the local frame; each training frame (all members
   present) is brought to the reference pose by the rotation that best aligns
   the members (Eq. 5).  A missing sample is estimated from every model that
   contains the marker (its own and its neighbours') with at least 3 visible
   members: coefficients from the visible members, then the estimates are
   averaged.  Only local neighbourhoods need complete frames, never the whole
   body; a neighbourhood without enough complete frames drops its least
   co-visible neighbours, then falls back to the rigid prediction.  Holes whose
   models see too few members are filled in later passes from earlier
   estimates (as the merge step does).
4. **smoothing** (§4.4) — each trajectory is expressed in its local frame over
   time, smoothed by ``x ← x − λ Δ⁴x`` (``smooth_iterations`` times), and moved
   back to global coordinates.

Nothing is invented: a marker never visible, or with fewer than 3 surface
neighbours, keeps its NaNs (warning naming it, listed in the report).

Where this implementation goes beyond the paper (each measured on simulated
captures with ground truth, see ``benchmarks/clean.py``):

* the surface is automatic, so one-rings may straddle a joint or the armpit:
  every neighbour carries a *rigidity* weight (how constant its distance to the
  marker stays over the capture) used in all rigid fits, and a marker with
  fewer than 3 rigid neighbours borrows rigid ones from its two-ring;
* merge predictions carry the marker's own local coordinates measured at the
  ends of its gap (interpolated across it) instead of the reference pose's;
  predictions derived from estimates are trusted only one step at a time
  (``depths``), a fragment must also stay within ``ε₁`` on average, any other
  missing marker predicted within :data:`AMBIGUITY_RATIO` times the distance
  makes it ambiguous, ``d̄`` is capped by the distance to the nearest marker,
  and fragments still unmerged are judged again against the PCA hole filling
  of the merged data (``pca_merge_rounds``);
* in the §4.3 average a neighbour's model weighs :data:`NEIGHBOUR_MODEL_WEIGHT`
  of the marker's own model (the paper: equal weights);
* the smoother treats runs of measured and of filled samples separately and
  moves a measurement by at most :data:`MAX_CORRECTION_SIGMA` noise deviations.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from mocapflow.pipeline import Context, FilePath, stage
from mocapflow.stages.data import Markers
from mocapflow.stages.kinematics import absolute_orientation_batch
from mocapflow.stages.surface import (
    MarkerSurface,
    build_marker_surface,
    marker_surface_from_faces,
    read_surface_file,
)

__all__ = [
    "CleanError",
    "AMBIGUITY_RATIO",
    "MAX_CORRECTION_SIGMA",
    "MIN_NEIGHBOURS",
    "NEIGHBOUR_MODEL_WEIGHT",
    "RIGID_ANCHOR",
        "STATUS",
    "LocalPCA",
    "choose_reference_frame",
    "clean",
    "clean_markers",
    "fill_holes",
    "fragment_runs",
    "local_targets",
    "merge_fragments",
    "nearest_marker_distance",
    "predict_missing",
    "rigid_estimates",
    "reference_pose",
    "smooth_local",
    "train_local_pca",
]

#: Fewest neighbours for a rigid fit (Horn needs 3 non-collinear points).
MIN_NEIGHBOURS = 3

#: A fragment is merged only if every other missing marker's prediction is at
#: least this many times farther from it (on average over its frames).
AMBIGUITY_RATIO = 3.0

#: The smoother moves a measured sample by at most this many noise standard
#: deviations per axis (noise estimated robustly from the 4th differences of
#: the marker's measured local trajectory).  A jump of the local frame — a
#: neighbour switching between measured and filled, skin folding — is not noise.
MAX_CORRECTION_SIGMA = 2.0

#: Default weight of the neighbours' model estimates relative to the marker's own
#: model in the §4.3 average (see :func:`fill_holes`).
NEIGHBOUR_MODEL_WEIGHT = 0.1

#: A rigid fit is trusted when its third most rigid point has at least this
#: rigidity weight (three points that move with the marker).
RIGID_ANCHOR = 0.2

#: Codes of the ``status`` array in the clean report.
STATUS = {"missing": -1, "observed": 0, "merged": 1, "filled": 2}


class CleanError(ValueError):
    """The capture cannot be cleaned (no markers, bad reference frame, ...)."""


# --------------------------------------------------------------------------- helpers


def _chunks(n: int, parts: int) -> list[np.ndarray]:
    parts = max(1, min(parts, n))
    return [c for c in np.array_split(np.arange(n), parts) if len(c)]


def _apply(R: np.ndarray, t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``R x + t`` for batches: R (B,3,3), t (B,3), x (B,N,3) or (B,3)."""
    if x.ndim == 2:
        return np.einsum("bij,bj->bi", R, x) + t
    return np.einsum("bij,bnj->bni", R, x) + t[:, None]


def _apply_inv(R: np.ndarray, t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``R^T (x - t)`` for batches."""
    if x.ndim == 2:
        return np.einsum("bji,bj->bi", R, x - t)
    return np.einsum("bji,bnj->bni", R, x - t[:, None])


def fragment_runs(visible: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous runs of ``True`` as ``(first, last)`` frame pairs.

    Parameters
    ----------
    visible : (F,) bool ndarray

    Returns
    -------
    list of (int, int)
    """
    v = np.concatenate([[False], np.asarray(visible, bool), [False]])
    d = np.diff(v.astype(np.int8))
    starts = np.flatnonzero(d == 1)
    ends = np.flatnonzero(d == -1) - 1
    return [(int(a), int(b)) for a, b in zip(starts, ends)]


def _names(labels: list[str], idx: np.ndarray | list[int], limit: int = 20) -> str:
    idx = [int(i) for i in idx]
    s = ", ".join(labels[i] for i in idx[:limit])
    return s + (f" … (+{len(idx) - limit} more)" if len(idx) > limit else "")


# --------------------------------------------------------------------------- reference pose


def choose_reference_frame(positions: np.ndarray) -> int:
    """The frame with the most visible markers (the earliest on ties).

    Parameters
    ----------
    positions : (F, M, 3) float ndarray

    Returns
    -------
    int
    """
    return int(np.argmax(np.isfinite(positions).all(-1).sum(1)))


def reference_pose(
    positions: np.ndarray, frame: int, *, k: int = 6, search: int = 200
) -> tuple[np.ndarray, dict[int, int], np.ndarray]:
    """Marker positions in the reference pose, completing markers missing there.

    A marker missing in ``frame`` but visible elsewhere is carried over from the
    nearest frame ``g`` in which it is visible: its ``k`` nearest markers visible
    in both frames give a rigid fit ``g → frame`` (Horn).

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
    frame : int
        Reference frame.
    k : int
        Neighbours used for the carry-over fit.
    search : int
        Candidate frames tried per marker, nearest first.

    Returns
    -------
    reference : (M, 3) float ndarray
        NaN for markers never visible (or not recoverable).
    carried : dict
        ``marker index -> source frame`` for markers completed by carry-over.
    unrecoverable : (K,) int ndarray
        Markers with no reference position.
    """
    vis = np.isfinite(positions).all(-1)
    ref = positions[frame].copy()
    carried: dict[int, int] = {}
    missing = np.flatnonzero(~vis[frame])
    for m in missing:
        frames = np.flatnonzero(vis[:, m])
        if len(frames) == 0:
            continue
        order = frames[np.argsort(np.abs(frames - frame), kind="stable")][:search]
        for g in order:
            common = np.flatnonzero(vis[g] & vis[frame])
            if len(common) < MIN_NEIGHBOURS:
                continue
            d = np.linalg.norm(positions[g, common] - positions[g, m], axis=1)
            nb = common[np.argsort(d)[:k]]
            R, t = absolute_orientation_batch(positions[g, nb][None], positions[frame, nb][None])
            if np.isfinite(R).all():
                ref[m] = R[0] @ positions[g, m] + t[0]
                carried[int(m)] = int(g)
                break
    unrecoverable = np.flatnonzero(~np.isfinite(ref).all(1))
    return ref, carried, unrecoverable


# --------------------------------------------------------------------------- prediction (§4.2)


def _neighbour_fit(
    positions: np.ndarray,
    reference: np.ndarray,
    neighbours: np.ndarray,
    rigidity: np.ndarray | None,
    frames: np.ndarray,
    markers: np.ndarray,
    available: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Rigid fits (Horn) of the one-rings of ``markers`` at ``frames``: reference -> current.

    Returns R (N, 3, 3), t (N, 3); NaN where fewer than 3 neighbours are available.
    """
    nbv = neighbours[markers] >= 0
    nb = np.maximum(neighbours[markers], 0)
    tgt = positions[frames[:, None], nb]
    ok = nbv & (np.isfinite(tgt).all(-1) if available is None else available[frames[:, None], nb])
    w = ok * (1.0 if rigidity is None else rigidity[markers])
    R, t = absolute_orientation_batch(reference[nb], np.where(ok[..., None], tgt, np.nan),
                                      weights=w)
    R[ok.sum(1) < MIN_NEIGHBOURS] = np.nan
    t[ok.sum(1) < MIN_NEIGHBOURS] = np.nan
    return R, t


def _adjacency(neighbours: np.ndarray):
    """Sparse ``(M, M)`` matrix with a 1 at ``[j, k]`` for each neighbour ``k`` of ``j``."""
    import scipy.sparse as sp

    M = len(neighbours)
    j, k = np.nonzero(neighbours >= 0)
    return sp.csr_matrix((np.ones(len(j)), (j, neighbours[j, k])), shape=(M, M))


def local_targets(
    positions: np.ndarray,
    reference: np.ndarray,
    neighbours: np.ndarray,
    *,
    rigidity: np.ndarray | None = None,
) -> np.ndarray:
    """Where each missing marker sits in its local reference frame, per missing sample.

    The marker's coordinates in the frame of its neighbours (reference-pose
    coordinates after the rigid fit of the one-ring) are measured at the
    observed samples bounding each gap and interpolated linearly in time across
    the gap (held constant at the ends of the capture); a gap with no usable
    boundary takes the reference pose.  Skin slides slowly under the markers,
    so the boundary coordinates are better than the reference pose alone.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        Observed positions (NaN where missing).
    reference : (M, 3) float ndarray
    neighbours : (M, K) int ndarray
    rigidity : (M, K) float ndarray, optional
        Neighbour weights of the rigid fits (default 1).

    Returns
    -------
    (F, M, 3) float ndarray
        Reference-pose coordinates of the marker at its missing samples; NaN at
        observed samples and for markers without reference position.
    """
    F, M, _ = positions.shape
    vis = np.isfinite(positions).all(-1)
    out = np.where(vis[..., None], np.nan, reference[None])
    if F < 2 or neighbours.shape[1] == 0:
        return out
    # boundary samples: observed with a missing neighbour in time
    prev_miss = np.zeros_like(vis)
    prev_miss[1:] = ~vis[:-1]
    next_miss = np.zeros_like(vis)
    next_miss[:-1] = ~vis[1:]
    bf, bm = np.nonzero(vis & (prev_miss | next_miss) & np.isfinite(reference).all(1)[None])
    if len(bf) == 0:
        return out
    y = _apply_inv(*_neighbour_fit(positions, reference, neighbours, rigidity, bf, bm),
                   positions[bf, bm])
    Y = np.full((F, M, 3), np.nan)
    Y[bf, bm] = y
    # per marker, for every frame: last / next boundary with a valid local coordinate
    frames = np.arange(F)
    have = np.isfinite(Y).all(-1)
    last = np.where(have, frames[:, None], -1)
    last = np.maximum.accumulate(last, axis=0)
    nxt = np.where(have, frames[:, None], F)
    nxt = np.minimum.accumulate(nxt[::-1], axis=0)[::-1]
    mf, mm = np.nonzero(~vis & np.isfinite(reference).all(1)[None])
    a, b = last[mf, mm], nxt[mf, mm]
    # a boundary only counts if no observed sample lies between it and the gap
    ya = np.where((a >= 0)[:, None], Y[np.maximum(a, 0), mm], np.nan)
    yb = np.where((b < F)[:, None], Y[np.minimum(b, F - 1), mm], np.nan)
    okA, okB = np.isfinite(ya).all(1), np.isfinite(yb).all(1)
    u = np.where(okA & okB, (mf - a) / np.maximum(b - a, 1), 0.0)[:, None]
    est = np.where((okA & okB)[:, None], (1 - u) * ya + u * yb,
                   np.where(okA[:, None], ya, np.where(okB[:, None], yb, reference[mm])))
    out[mf, mm] = est
    return out


def predict_missing(
    positions: np.ndarray,
    reference: np.ndarray,
    neighbours: np.ndarray,
    *,
    targets: np.ndarray | None = None,
    rigidity: np.ndarray | None = None,
    return_depth: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Greedy rigid-neighbour prediction of every missing sample (Park & Hodgins §4.2).

    In each frame, the missing markers with the most available neighbours are
    predicted first — a rigid fit (Horn) of the neighbours' reference positions
    onto their current positions carries the marker's local coordinates into
    the frame — and become available to the next ones.  Vectorised over frames:
    each round handles, in every frame, the markers tied for the most available
    neighbours.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        NaN where missing.
    reference : (M, 3) float ndarray
        Reference pose (NaN: marker cannot be predicted).
    neighbours : (M, K) int ndarray
        One-ring, ``-1`` padded.
    targets : (F, M, 3) float ndarray, optional
        The marker's reference-pose coordinates per missing sample (see
        :func:`local_targets`); default: the reference pose.
    rigidity : (M, K) float ndarray, optional
        Neighbour weights of the rigid fits (default 1).
    return_depth : bool
        Also return how far each prediction is from observed data and its support.

    Returns
    -------
    estimates : (F, M, 3) float ndarray
        Predictions at the missing samples, NaN elsewhere and where fewer than 3
        neighbours were available (or they were collinear).
    depth : (F, M) int ndarray, only with ``return_depth``
        0 for observed samples, ``1 + `` the largest depth among the neighbours
        used (1: predicted from observed neighbours only); -1 where not predicted.
    support : (F, M) float ndarray, only with ``return_depth``
        The third largest rigidity weight among the neighbours used (a rigid
        fit needs 3 points that move with the marker).
    """
    F, M, _ = positions.shape
    X = positions.copy()
    avail = np.isfinite(X).all(-1)
    est = np.full_like(X, np.nan)
    depth = np.where(avail, 0, -1)
    support = np.zeros(avail.shape)
    if neighbours.shape[1] == 0:
        return (est, depth, support) if return_depth else est
    nbv = neighbours >= 0
    nb = np.maximum(neighbours, 0)
    canpredict = np.isfinite(reference).all(1) & (nbv.sum(1) >= MIN_NEIGHBOURS)
    pending = ~avail & canpredict[None, :]
    adjacency = _adjacency(neighbours)  # (M, M): row j counts the neighbours of j
    active = np.flatnonzero(pending.any(1))
    cnt = np.zeros((F, M))
    while len(active):
        cnt[active] = (adjacency @ avail[active].T.astype(float)).T
        cand = pending[active] & (cnt[active] >= MIN_NEIGHBOURS)
        keep = cand.any(1)
        active, cand = active[keep], cand[keep]
        if not len(active):
            break
        ca = cnt[active]
        best = np.where(cand, ca, -1).max(axis=1, keepdims=True)
        fi, m = np.nonzero(cand & (ca == best))
        f = active[fi]
        R, t = _neighbour_fit(X, reference, neighbours, rigidity, f, m, avail)
        y = reference[m] if targets is None else targets[f, m]
        p = _apply(R, t, y)
        ok = np.isfinite(p).all(1)
        used = avail[f[:, None], nb[m]] & nbv[m]
        d = np.where(used, depth[f[:, None], nb[m]], 0).max(1) + 1
        sup = _third_anchor(used * (1.0 if rigidity is None else rigidity[m]))
        X[f[ok], m[ok]] = p[ok]
        est[f[ok], m[ok]] = p[ok]
        depth[f[ok], m[ok]] = d[ok]
        support[f[ok], m[ok]] = sup[ok]
        avail[f[ok], m[ok]] = True
        pending[f, m] = False  # degenerate sets are not retried
    return (est, depth, support) if return_depth else est


def rigid_estimates(
    positions: np.ndarray,
    reference: np.ndarray,
    neighbours: np.ndarray,
    frames: np.ndarray,
    markers: np.ndarray,
    *,
    rigidity: np.ndarray | None = None,
) -> np.ndarray:
    """Rigid-neighbour estimates of given samples from the available neighbours only.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
    reference : (M, 3) float ndarray
    neighbours : (M, K) int ndarray
    frames, markers : (N,) int ndarray
        The samples to estimate.
    rigidity : (M, K) float ndarray, optional
        Neighbour weights.

    Returns
    -------
    (N, 3) float ndarray
        NaN where fewer than 3 non-collinear neighbours are available.
    """
    R, t = _neighbour_fit(positions, reference, neighbours, rigidity, frames, markers)
    return _apply(R, t, reference[markers])


def _predict_chunk(item: tuple) -> np.ndarray:
    positions, reference, neighbours, targets, rigidity, max_depth, min_support = item
    est, depth, support = predict_missing(positions, reference, neighbours, targets=targets,
                                          rigidity=rigidity, return_depth=True)
    trusted = np.where(((depth > max_depth) | (support < min_support))[..., None], np.nan, est)
    return np.stack([trusted, est])


def _predict_parallel(
    positions: np.ndarray,
    surface: MarkerSurface,
    targets: np.ndarray,
    frames: np.ndarray,
    ctx: Context,
    max_depth: int,
    min_support: float,
) -> np.ndarray:
    """Predictions for the given frames, in frame chunks through ``ctx.map``.

    Returns ``(2, len(frames), M, 3)``: the trusted predictions and all of them.
    """
    parts = max(1, ctx.workers) * 2 if ctx.mapper is not None else 1
    chunks = [frames[c] for c in _chunks(len(frames), parts)]
    items = [(positions[c], surface.reference, surface.neighbours, targets[c], surface.rigidity,
              max_depth, min_support) for c in chunks]
    out = ctx.map(_predict_chunk, items)
    if not out:
        return np.zeros((2, 0) + positions.shape[1:])
    return np.concatenate(out, axis=1)


# --------------------------------------------------------------------------- merging (§4.2)

def nearest_marker_distance(reference: np.ndarray) -> np.ndarray:
    """``(M,)`` distance from each marker to the nearest other one in the reference pose.

    NaN for markers without reference position.
    """
    from scipy.spatial import cKDTree

    out = np.full(len(reference), np.nan)
    ok = np.flatnonzero(np.isfinite(reference).all(1))
    if len(ok) >= 2:
        d, _ = cKDTree(reference[ok]).query(reference[ok], k=2)
        out[ok] = d[:, 1]
    return out





def _judge_fragment(
    frag: np.ndarray,
    T: np.ndarray,
    free: np.ndarray,
    E: np.ndarray,
    E_all: np.ndarray,
    eps1: np.ndarray,
    eps2: np.ndarray,
    labels: list[str],
) -> dict[str, Any]:
    """Decide one fragment against the predictions of the markers missing in all its frames.

    Returns ``{"marker", "entry", "max", "mean"}`` for a merge, else
    ``{"reason", ...}`` (and ``"conflict"`` for ambiguities).
    """
    mm = 1000.0
    cands = np.flatnonzero(free)
    if len(cands) == 0:
        return {"reason": "overlaps every marker (no marker is missing in all its frames)"}
    d = np.linalg.norm(frag[:, None] - E[T[:, None], cands[None]], axis=-1)  # (|T|, C)
    have = np.isfinite(d)
    checkable = have.sum(0) >= max(1, int(np.ceil(0.5 * len(T))))
    if not checkable.any():
        return {"reason": f"no prediction: candidate markers have fewer than {MIN_NEIGHBOURS} "
                          "reliable neighbours in its frames"}
    cc = np.flatnonzero(checkable)
    dc, hc = d[:, cc], have[:, cc]
    first = np.argmax(hc, axis=0)
    d_entry = dc[first, np.arange(len(cc))]
    dn = np.where(hc, dc, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        d_max = np.nanmax(dn, axis=0)
        d_mean = np.nanmean(dn, axis=0)
    m_c = cands[cc]
    e1, e2 = eps1[m_c], eps2[m_c]
    ok = (d_entry < e1) & (d_max < e2) & (d_mean < e1)
    if not ok.any():
        c = int(np.argmin(d_entry / e1))
        m = int(m_c[c])
        if d_entry[c] >= e1[c]:
            why = (f"entry {d_entry[c] * mm:.1f} mm from the prediction of nearest marker "
                   f"{labels[m]} > eps1 {e1[c] * mm:.1f} mm")
        elif d_max[c] < e2[c]:
            why = (f"mean distance {d_mean[c] * mm:.1f} mm to the prediction of {labels[m]} "
                   f"> eps1 {e1[c] * mm:.1f} mm")
        else:
            bad = int(T[np.nanargmax(dn[:, c])])
            why = (f"leaves the eps2 tube of {labels[m]}: {d_max[c] * mm:.1f} mm > "
                   f"{e2[c] * mm:.1f} mm at frame {bad}")
        return {"reason": why, "nearest": labels[m], "entry_mm": round(float(d_entry[c] * mm), 2)}
    okc = np.flatnonzero(ok)
    okc = okc[np.argsort(d_mean[okc])]
    c0 = okc[0]
    m = int(m_c[c0])
    if len(okc) > 1 and not AMBIGUITY_RATIO * d_mean[c0] < d_mean[okc[1]]:
        return {"reason": "ambiguous between markers "
                + ", ".join(labels[int(m_c[c])] for c in okc[:3]),
                "conflict": {"labels": [labels[int(m_c[c])] for c in okc],
                             "mean_mm": [round(float(d_mean[c] * mm), 2) for c in okc]}}
    # any other missing marker, even one predicted only from estimates, that comes
    # as close to the fragment makes it ambiguous
    others = cands[cands != m]
    if len(others):
        sub = np.unique(np.linspace(0, len(T) - 1, min(len(T), 16)).round().astype(int))
        da = np.linalg.norm(frag[sub][:, None] - E_all[T[sub][:, None], others[None]], axis=-1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            da_mean = np.nanmean(da, axis=0)
        if np.isfinite(da_mean).any() and np.nanmin(da_mean) < AMBIGUITY_RATIO * d_mean[c0]:
            k = int(np.nanargmin(da_mean))
            rival = labels[int(others[k])]
            return {"reason": f"ambiguous: {labels[m]} at {d_mean[c0] * mm:.1f} mm, {rival} at "
                              f"{da_mean[k] * mm:.1f} mm",
                    "conflict": {"labels": [labels[m], rival],
                                 "mean_mm": [round(float(d_mean[c0] * mm), 2),
                                             round(float(da_mean[k] * mm), 2)]}}
    return {"marker": m, "entry": float(d_entry[c0]), "max": float(d_max[c0]),
            "mean": float(d_mean[c0])}


def merge_fragments(
    positions: np.ndarray,
    fragments: np.ndarray,
    surface: MarkerSurface,
    *,
    alpha1: float = 0.5,
    alpha2: float = 0.6,
    fragment_labels: list[str] | None = None,
    predictions: np.ndarray | None = None,
    competitors: np.ndarray | None = None,
    depths: tuple[int, ...] = (1, 2, 3),
    rounds_per_level: int = 4,
    min_support: float = RIGID_ANCHOR,
    ctx: Context | None = None,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Merge unlabelled fragments into labelled markers (Park & Hodgins §4.2).

    Rounds: predict the missing samples (:func:`predict_missing` with the
    markers' local targets), judge every unmerged fragment (the ε₁ entry test,
    the ε₂ tube over its length, ambiguity tests), merge, repeat with the merged
    data.  Fragments whose frames saw no change since they were last judged are
    not judged again.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        Labelled trajectories, NaN where missing.
    fragments : (F, U, 3) float ndarray
        Unlabelled trajectories, NaN outside each fragment.
    surface : MarkerSurface
    alpha1, alpha2 : float
        ``ε₁ = α₁ d̄``: entry tolerance; ``ε₂ = α₂ d̄``: tolerance over the whole
        fragment (``d̄``: the marker's mean neighbour distance, capped by its
        distance to the nearest marker so that a closer marker — across the
        armpit or the crotch — never falls inside the tolerance).
    fragment_labels : list of str, optional
        ``U`` names for the report.
    predictions : (F, M, 3) float ndarray, optional
        Judge against these predictions of the missing samples instead (e.g.
        the PCA hole filling of the merged data); one round.
    competitors : (F, M, 3) float ndarray, optional
        With ``predictions``: the predictions used in the ambiguity test
        (default the same).
    depths : tuple of int
        How far predictions may be from observed data (estimates of estimates)
        to judge a fragment, tried in turn: rounds first trust only predictions
        made from observed (or merged) neighbours (depth 1), and go one step
        further when a level stops merging.  Every prediction, trusted or not,
        takes part in the ambiguity test.
    rounds_per_level : int
        Rounds at most per depth level.
    min_support : float
        Predictions whose third most rigid neighbour weighs less are not
        trusted either.
    ctx : Context, optional
        For the parallel prediction (frame chunks through ``ctx.map``).

    Returns
    -------
    positions : (F, M, 3) float ndarray
        With the merged fragments written in.
    assigned : (U,) int ndarray
        Marker each fragment was merged into, ``-1`` if none.
    report : dict
        ``merges``, ``rejections``, ``conflicts`` (lists of dicts naming fragment,
        label and reason), ``merged_by_depth``.
    """
    ctx = ctx or Context()
    X = positions.copy()
    F, M, _ = X.shape
    U = fragments.shape[1]
    flabels = list(fragment_labels or [f"*{u + 1}" for u in range(U)])
    labels = surface.labels
    dbar = np.fmin(surface.mean_distance, nearest_marker_distance(surface.reference))
    eps1, eps2 = alpha1 * dbar, alpha2 * dbar
    fvis = np.isfinite(fragments).all(-1)
    frames_of = [np.flatnonzero(fvis[:, u]) for u in range(U)]
    assigned = np.full(U, -1, dtype=np.int64)
    verdict: dict[int, dict[str, Any]] = {u: {"reason": "empty fragment"} for u in range(U)
                                          if not len(frames_of[u])}
    merges: list[dict[str, Any]] = []
    conflicts: list[dict[str, Any]] = []
    order = sorted((u for u in range(U) if len(frames_of[u])), key=lambda u: -len(frames_of[u]))
    mm = 1000.0
    n_by_depth: dict[str, int] = {}
    E = np.full_like(X, np.nan)
    E_all = np.full_like(X, np.nan)
    Y = np.full_like(X, np.nan)
    levels: list[Any] = ["given"] if predictions is not None else list(depths)
    level, rounds_here = 0, 0
    dirty = np.ones(F, dtype=bool)  # frames whose predictions / data changed
    stale = np.arange(F)
    for rnd in range(len(levels) * rounds_per_level):
        todo = [u for u in order if assigned[u] < 0]
        if not todo:
            break
        key = levels[level]
        if predictions is not None:
            E = np.where(np.isfinite(X), np.nan, predictions)
            E_all = E if competitors is None else np.where(np.isfinite(X), np.nan, competitors)
        else:
            Y_new = local_targets(X, surface.reference, surface.neighbours,
                                  rigidity=surface.rigidity)
            changed = ~((Y_new == Y) | (np.isnan(Y_new) & np.isnan(Y))).all((1, 2))
            frames = np.union1d(stale, np.flatnonzero(changed))
            Y = Y_new
            if len(frames):
                e, ea = _predict_parallel(X, surface, Y, frames, ctx, key, min_support)
                diff = ~(((e == E[frames]) | (np.isnan(e) & np.isnan(E[frames])))
                         & ((ea == E_all[frames]) | (np.isnan(ea) & np.isnan(E_all[frames])))
                         ).all((1, 2))
                dirty[frames[diff]] = True
                E[frames], E_all[frames] = e, ea
        stale = np.zeros(0, dtype=np.int64)
        avail = np.isfinite(X).all(-1)
        claims: dict[int, list[tuple[float, int, dict]]] = {}
        for u in todo:
            T = frames_of[u]
            if u in verdict and not dirty[T].any():
                continue  # nothing it depends on changed
            v = _judge_fragment(fragments[T, u], T, ~avail[T].any(0) & np.isfinite(dbar),
                                E, E_all, eps1, eps2, labels)
            if "marker" in v:
                claims.setdefault(v["marker"], []).append((v["mean"], u, v))
                verdict.pop(u, None)
            else:
                if "conflict" in v and verdict.get(u, {}).get("reason") != v["reason"]:
                    conflicts.append({"fragment": flabels[u], **v["conflict"],
                                      "resolution": "ambiguous: not merged"})
                verdict[u] = {k: x for k, x in v.items() if k != "conflict"}
        dirty[:] = False
        # resolve claims per marker: overlapping fragments conflict, closest first
        n_new = 0
        for m, cl in claims.items():
            cl.sort(key=lambda c: c[0])
            taken = np.zeros(F, dtype=bool)
            winner: dict[int, str] = {}
            for _, u, v in cl:
                T = frames_of[u]
                if taken[T].any():
                    w = next(flabels[w_] for w_, _ in winner.items() if taken[frames_of[w_]].any())
                    conflicts.append({
                        "fragment": flabels[u], "labels": [labels[m]],
                        "resolution": f"overlaps fragment {w} merged into {labels[m]} (closer): "
                                      "not merged"})
                    verdict[u] = {"reason": f"conflict with {w} for {labels[m]}"}
                    continue
                taken[T] = True
                winner[u] = flabels[u]
                X[T, m] = fragments[T, u]
                dirty[T] = True
                stale = np.union1d(stale, T)
                assigned[u] = m
                n_new += 1
                merges.append({
                    "fragment": flabels[u], "label": labels[m],
                    "first_frame": int(T[0]), "last_frame": int(T[-1]), "n_frames": len(T),
                    "entry_mm": round(v["entry"] * mm, 2), "mean_mm": round(v["mean"] * mm, 2),
                    "max_mm": round(v["max"] * mm, 2),
                    "eps1_mm": round(float(eps1[m] * mm), 2),
                    "eps2_mm": round(float(eps2[m] * mm), 2), "round": rnd,
                    "predictor": "rigid" if predictions is None else "given",
                    "depth": key,
                })
        n_by_depth[str(key)] = n_by_depth.get(str(key), 0) + n_new
        rounds_here += 1
        if n_new == 0 or rounds_here >= rounds_per_level or predictions is not None:
            if level + 1 >= len(levels) or predictions is not None:
                break
            level, rounds_here = level + 1, 0
            stale = np.arange(F)  # trust changes: every frame is predicted again
            dirty[:] = True
    rejections = [
        {"fragment": flabels[u], "n_frames": len(frames_of[u]),
         "first_frame": int(frames_of[u][0]) if len(frames_of[u]) else None,
         **verdict.get(u, {"reason": "not examined"})}
        for u in range(U) if assigned[u] < 0
    ]
    return X, assigned, {"merges": merges, "rejections": rejections, "conflicts": conflicts,
                         "merged_by_depth": n_by_depth}


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


def _third_anchor(w: np.ndarray) -> np.ndarray:
    """Third largest weight along the last axis (0 with fewer than 3)."""
    if w.shape[-1] < 3:
        return np.zeros(w.shape[:-1])
    return -np.partition(-w, 2, axis=-1)[..., 2]


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


# --------------------------------------------------------------------------- smoothing (§4.4)


def _smooth_run(y: np.ndarray, lam: float, iterations: int) -> np.ndarray:
    """``y ← y − λ Δ⁴ y`` along axis 0, ends extended by odd reflection."""
    n = len(y)
    if n < 5 or iterations <= 0 or lam == 0:
        return y
    y = y.copy()
    for _ in range(iterations):
        pad = np.concatenate([2 * y[:1] - y[2:0:-1], y, 2 * y[-1:] - y[-2:-4:-1]])
        d4 = pad[:-4] - 4 * pad[1:-3] + 6 * pad[2:-2] - 4 * pad[3:-1] + pad[4:]
        y -= lam * d4
    return y


def _smooth_chunk(item: tuple) -> tuple[np.ndarray, np.ndarray]:
    X, markers, neighbours, rigidity, reference, lam, iterations, measured = item
    F = X.shape[0]
    out = X[:, markers].copy()
    for c, m in enumerate(markers):
        sel = neighbours[c] >= 0
        nb = neighbours[c][sel]
        x = X[:, m]
        src = np.broadcast_to(reference[nb], (F, len(nb), 3))
        w = np.broadcast_to(rigidity[c][sel], (F, len(nb)))
        R, t = absolute_orientation_batch(src, X[:, nb], weights=w)
        y = _apply_inv(R, t, x)
        ok = np.isfinite(y).all(1)
        ys = y.copy()
        # runs of measured samples and runs of filled ones are smoothed separately:
        # estimates never drag measurements
        meas = np.ones(F, dtype=bool) if measured is None else measured[:, m]
        kind = np.where(ok, 1 + meas, 0)
        cut = np.flatnonzero(np.diff(kind) != 0) + 1
        d4 = []
        for a, b in zip(np.r_[0, cut], np.r_[cut, F]):
            if kind[a]:
                ys[a:b] = _smooth_run(y[a:b], lam, iterations)
                if kind[a] == 2 and b - a >= 5:
                    d4.append(np.diff(y[a:b], n=4, axis=0))
        if d4:  # measurements move by at most MAX_CORRECTION_SIGMA noise deviations
            k = MAX_CORRECTION_SIGMA
            dd = np.concatenate(d4)
            sigma = 1.4826 * np.median(np.abs(dd - np.median(dd, 0)), 0) / np.sqrt(70.0)
            corr = ys - y
            ys = np.where(meas[:, None], y + np.clip(corr, -k * sigma, k * sigma), ys)
        xs = _apply(R, t, ys)
        out[ok, c] = xs[ok]
    return markers, out


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
    one-ring's reference positions per frame, neighbours weighted by rigidity),
    smoothed with ``x ← x − λ Δ⁴x`` iterated, and moved back to global
    coordinates.  Runs of measured samples and runs of filled samples are
    smoothed separately (estimates never drag measurements), and a measured
    sample moves by at most :data:`MAX_CORRECTION_SIGMA` noise deviations.
    Frames whose local frame cannot be fitted keep their sample unsmoothed;
    runs shorter than 5 frames are left as they are.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
    surface : MarkerSurface
    smooth_lambda : float
        ``λ``; the iteration is stable for ``λ < 1/8``.
    smooth_iterations : int
    measured : (F, M) bool ndarray, optional
        Samples that were measured (observed or merged), as opposed to filled:
        their runs are smoothed apart from the filled runs and their corrections
        are bounded.  Default: every available sample counts as measured.
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
    items = []
    for c in _chunks(len(markers), parts):
        ms = markers[c]
        items.append((positions, ms, surface.neighbours[ms], surface.rigidity[ms],
                      surface.reference, smooth_lambda, smooth_iterations, measured))
    for ms, out in ctx.map(_smooth_chunk, items):
        X[:, ms] = out
    return X


# --------------------------------------------------------------------------- the stage


def _trajectory_count(positions: np.ndarray) -> int:
    return int(np.isfinite(positions).all(-1).any(0).sum())


def clean_markers(
    markers: Markers,
    *,
    alpha1: float = 0.5,
    alpha2: float = 0.6,
    variance: float = 0.99,
    smooth_lambda: float = 0.1,
    smooth_iterations: int = 10,
    reference_frame: int | None = None,
    surface: str | None = None,
    merge: bool = True,
    fill: bool = True,
    pca_merge_rounds: int = 3,
    ctx: Context | None = None,
) -> tuple[Markers, dict[str, Any], MarkerSurface]:
    """Clean a capture: merge, fill, smooth; see :func:`clean` for the parameters.

    Returns
    -------
    markers : Markers
        Cleaned; unmerged fragments kept in ``fragments``.
    report : dict
        JSON report plus ``status (F, M)`` int8 array (:data:`STATUS` codes).
    surface : MarkerSurface
    """
    ctx = ctx or Context()
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    P = markers.positions
    F, M, _ = P.shape
    if M == 0 or F == 0:
        raise CleanError("clean: the capture has no labelled markers or no frames")
    if not (0 < alpha1 and 0 < alpha2):
        raise CleanError(f"clean: alpha1 and alpha2 must be positive (got {alpha1}, {alpha2})")
    if not 0 < variance <= 1:
        raise CleanError(f"clean: variance must be in (0, 1], got {variance}")
    labels = markers.labels
    vis0 = markers.visible
    never = np.flatnonzero(~vis0.any(0))
    if reference_frame is None:
        ref_frame = choose_reference_frame(P)
    else:
        if not -F <= reference_frame < F:
            raise CleanError(
                f"clean: reference_frame {reference_frame} out of range (capture has {F} frames)"
            )
        ref_frame = int(reference_frame) % F
    reference, carried, unrecoverable = reference_pose(P, ref_frame)
    if carried:
        ctx.warn(
            f"clean: {len(carried)} marker(s) missing in reference frame {ref_frame}; reference "
            f"position carried over from the nearest frame where visible: "
            + ", ".join(f"{labels[m]} (frame {g})" for m, g in list(carried.items())[:20])
        )
    if len(unrecoverable):
        ctx.warn(f"clean: marker(s) never visible, left NaN: {_names(labels, unrecoverable)}")
    timings["reference"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    if surface is not None:
        faces = read_surface_file(surface, labels)
        surf = marker_surface_from_faces(reference, faces, labels=labels, positions=P,
                                         source=str(surface).rsplit("/", 1)[-1])
    else:
        surf = build_marker_surface(reference, positions=P, labels=labels)
    few = np.flatnonzero(np.isfinite(reference).all(1) & (surf.n_neighbours < MIN_NEIGHBOURS))
    if len(few):
        ctx.warn(
            f"clean: marker(s) with fewer than {MIN_NEIGHBOURS} surface neighbours are neither "
            f"merged nor filled (holes stay NaN): {_names(labels, few)}"
        )
    timings["surface"] = time.perf_counter() - t1

    frags = markers.fragments
    U = frags.shape[1]
    runs_before = sum(len(fragment_runs(vis0[:, m])) for m in range(M))
    t2 = time.perf_counter()
    if merge and U:
        X, assigned, mrep = merge_fragments(
            P, frags, surf, alpha1=alpha1, alpha2=alpha2,
            fragment_labels=markers.fragment_labels, depths=(1,), ctx=ctx,
        )
        models = None
        for k in range(pca_merge_rounds if fill else 0):
            left = np.flatnonzero(assigned < 0)
            if not len(left):
                break
            # judge the rest against the PCA hole filling of the merged data (§4.3)
            waiting = np.isfinite(frags[:, left]).all(-1).any(1)
            Xf, finfo0 = fill_holes(X, surf, variance=variance, models=models, frames=waiting,
                                    ctx=ctx)
            models = finfo0.get("model_list") or models
            # trust the estimates of the first pass (from measured members) only
            direct = np.where((finfo0["pass"] == 1)[..., None], Xf, np.nan)
            X, a2, rep2 = merge_fragments(
                X, frags[:, left], surf, alpha1=alpha1, alpha2=alpha2,
                fragment_labels=[markers.fragment_labels[u] for u in left], predictions=direct,
                competitors=Xf, ctx=ctx,
            )
            assigned[left[a2 >= 0]] = a2[a2 >= 0]
            for mg in rep2["merges"]:
                mg["predictor"] = "pca"
                mg["round"] = f"pca{k + 1}"
            mrep["merges"] += rep2["merges"]
            mrep["conflicts"] += rep2["conflicts"]
            mrep["rejections"] = rep2["rejections"]
            mrep["merged_by_depth"][f"pca{k + 1}"] = len(rep2["merges"])
            if not rep2["merges"]:
                break
    else:
        X, assigned = P.copy(), np.full(U, -1, dtype=np.int64)
        mrep = {"merges": [], "rejections": [], "conflicts": [], "merged_by_depth": {}}
    timings["merge"] = time.perf_counter() - t2
    status = np.full((F, M), STATUS["missing"], dtype=np.int8)
    status[vis0] = STATUS["observed"]
    vis1 = np.isfinite(X).all(-1)
    status[vis1 & ~vis0] = STATUS["merged"]
    holes_after_merge = int((~vis1).sum())

    t3 = time.perf_counter()
    if fill:
        Xf, finfo = fill_holes(X, surf, variance=variance, ctx=ctx)
        finfo.pop("model_list", None)
        finfo.pop("pass", None)
    else:
        Xf, finfo = X, {"filled_by_pass": []}
    timings["fill"] = time.perf_counter() - t3
    vis2 = np.isfinite(Xf).all(-1)
    status[vis2 & ~vis1] = STATUS["filled"]

    t4 = time.perf_counter()
    Xs = smooth_local(Xf, surf, smooth_lambda=smooth_lambda,
                      smooth_iterations=smooth_iterations, measured=vis1, ctx=ctx)
    timings["smooth"] = time.perf_counter() - t4
    timings["total"] = time.perf_counter() - t0

    left = ~vis2
    left_markers = np.flatnonzero(left.any(0))
    unfillable = np.flatnonzero(left.any(0) & (surf.n_neighbours < MIN_NEIGHBOURS))
    keep_frag = assigned < 0
    out = markers.replace(
        positions=Xs,
        residuals=None if markers.residuals is None else np.where(
            status == STATUS["observed"], markers.residuals, np.where(vis2, 0.0, np.nan)),
        fragments=frags[:, keep_frag],
        fragment_labels=[lb for lb, k in zip(markers.fragment_labels, keep_frag) if k],
    )
    out.attrs["clean"] = {
        "reference_frame": ref_frame, "merged_fragments": int((~keep_frag).sum()),
        "filled_samples": int((status == STATUS["filled"]).sum()),
        "missing_samples": int(left.sum()),
    }
    n_traj = _trajectory_count(P)
    report: dict[str, Any] = {
        "reference_frame": ref_frame,
        "reference_carried_over": {labels[m]: g for m, g in carried.items()},
        "surface": {
            "source": surf.source,
            "n_faces": int(len(surf.faces)),
            "mean_neighbours": float(np.mean(surf.n_neighbours[np.isfinite(reference).all(1)]))
            if np.isfinite(reference).any() else 0.0,
            "mean_neighbour_distance_mm": round(float(np.nanmean(surf.mean_distance)) * 1000, 2)
            if np.isfinite(surf.mean_distance).any() else None,
        },
        "table1": {
            "markers": M,
            "fragments_before": n_traj + U,
            "fragments_after": n_traj + int(keep_frag.sum()),
            "runs_before": runs_before + U,
            "merged": int((~keep_frag).sum()),
            "holes": holes_after_merge,
            "filled": int((status == STATUS["filled"]).sum()),
            "left_unfilled": int(left.sum()),
        },
        **mrep,
        "fill": finfo,
        "never_visible": [labels[i] for i in unrecoverable],
        "too_few_neighbours": [labels[i] for i in few],
        "markers_with_holes_left": [labels[i] for i in left_markers],
        "unfillable_markers": [labels[i] for i in unfillable],
        "params": {"alpha1": alpha1, "alpha2": alpha2, "variance": variance,
                   "smooth_lambda": smooth_lambda, "smooth_iterations": smooth_iterations},
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "status": status,
    }
    if never.size and not len(unrecoverable):
        report["never_visible"] = [labels[i] for i in never]
    return out, report, surf


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
        Manual marker-surface file (see :mod:`mocapflow.stages.surface`); default:
        built automatically from the reference pose.
    merge, fill : bool
        Run the merge / hole-filling steps.

    Returns
    -------
    dict
        ``markers``: the cleaned :class:`Markers` (unmerged fragments kept);
        ``report``: record with ``status (F, M)`` int8 (-1 missing, 0 observed,
        1 merged, 2 filled) and JSON: reference frame, surface, ``table1``
        (fragments before/after, merges, holes, filled, left), ``merges`` /
        ``rejections`` / ``conflicts`` (fragment, label, reason), fill passes and
        models, never-visible and too-few-neighbour markers, timings;
        ``surface``: the marker surface as a :class:`Mesh` (vertices = reference
        pose of the markers, ``attrs["labels"]``).
    """
    out, report, surf = clean_markers(
        markers, alpha1=alpha1, alpha2=alpha2, variance=variance, smooth_lambda=smooth_lambda,
        smooth_iterations=smooth_iterations, reference_frame=reference_frame, surface=surface,
        merge=merge, fill=fill, ctx=ctx,
    )
    return {"markers": out, "report": report, "surface": surf.to_mesh()}

