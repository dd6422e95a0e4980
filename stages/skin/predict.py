"""Rigid prediction of missing markers from their neighbours (Park & Hodgins 2006, §4.2).

The foundation of the clean stage (:mod:`mocapflow.stages.skin.clean`): the reference
pose, and every missing sample of a marker predicted from at least 3 available
neighbours by a rigid fit (Horn) into its local reference frame, greedily by the
number of available neighbours, re-using estimates.  Used by merging
(:mod:`mocapflow.stages.skin.merge`) and as the fallback of hole filling
(:mod:`mocapflow.stages.skin.fill`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from mocapflow.pipeline import Context
from mocapflow.stages.motion.absolute_orientation import absolute_orientation_batch
from mocapflow.stages.skin.surface import MarkerSurface

#: Fewest neighbours for a rigid fit (Horn needs 3 non-collinear points).
MIN_NEIGHBOURS = 3

#: A rigid fit is trusted when its third most rigid point has at least this
#: rigidity weight (three points that move with the marker).
RIGID_ANCHOR = 0.2

# --------------------------------------------------------------------------- helpers


def _chunks(n: int, parts: int) -> list[np.ndarray]:
    parts = max(1, min(parts, n))
    return [c for c in np.array_split(np.arange(n), parts) if len(c)]


def _apply(R: np.ndarray, t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``R x + t`` for batches: R (B,3,3), t (B,3), x (B,N,3) or (B,3)."""
    if x.ndim == 2:
        return np.matmul(R, x[..., None])[..., 0] + t
    return np.matmul(x, np.swapaxes(R, 1, 2)) + t[:, None]


def _apply_inv(R: np.ndarray, t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``R^T (x - t)`` for batches."""
    if x.ndim == 2:
        return np.matmul((x - t)[:, None], R)[:, 0]
    return np.matmul(x - t[:, None], R)


def finite_rows(X: np.ndarray) -> np.ndarray:
    """``np.isfinite(X).all(-1)`` (the same booleans, in the same memory layout) of an
    ``(..., 3)`` array, several times faster: the three coordinates' tests and-ed
    instead of a reduction over a length-3 axis.

    Parameters
    ----------
    X : (..., 3) float ndarray

    Returns
    -------
    (...) bool ndarray
    """
    fin = np.isfinite(X)
    if fin.shape[-1] != 3:
        return fin.all(-1)
    return fin[..., 0] & fin[..., 1] & fin[..., 2]


def gather_samples(X: np.ndarray, frames: np.ndarray, markers: np.ndarray) -> np.ndarray:
    """``X[frames, markers]`` of an ``(F, M, 3)`` array for broadcastable integer index
    arrays (the same values).  A C-contiguous ``X`` is gathered as rows of
    ``(F * M, 3)``: one flat gather, several times faster than the two-array index.
    """
    if not X.flags.c_contiguous:
        return X[frames, markers]
    F, M, _ = X.shape
    return np.take(X.reshape(F * M, 3), np.asarray(frames) * M + markers, axis=0)


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
    return int(np.argmax(finite_rows(positions).sum(1)))


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
    vis = finite_rows(positions)
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
    tgt = gather_samples(positions, frames[:, None], nb)
    ok = nbv & (finite_rows(tgt) if available is None else available[frames[:, None], nb])
    w = ok * (1.0 if rigidity is None else rigidity[markers])
    R, t = absolute_orientation_batch(reference[nb], np.where(ok[..., None], tgt, np.nan),
                                      weights=w)
    R[ok.sum(1) < MIN_NEIGHBOURS] = np.nan
    t[ok.sum(1) < MIN_NEIGHBOURS] = np.nan
    return R, t


def _adjacency(neighbours: np.ndarray):
    """Sparse ``(M, M)`` matrix with a 1 at ``[j, k]`` for each neighbour ``k`` of ``j``."""
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
    vis = finite_rows(positions)
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
    have = finite_rows(Y)
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
    avail = finite_rows(X)
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
    users = adjacency.T.tocsr()  # row k: the markers j that have k as a neighbour
    active = np.flatnonzero(pending.any(1))
    cnt = np.zeros((F, M))  # available neighbours, kept up to date as samples are predicted
    cnt[active] = (adjacency @ avail[active].T.astype(float)).T
    while len(active):
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
        # the new samples count for the markers that have them as neighbours
        new = users[m[ok]].tocoo()
        np.add.at(cnt, (f[ok][new.row], new.col), new.data)
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


def _third_anchor(w: np.ndarray) -> np.ndarray:
    """Third largest weight along the last axis (0 with fewer than 3)."""
    if w.shape[-1] < 3:
        return np.zeros(w.shape[:-1])
    return -np.partition(-w, 2, axis=-1)[..., 2]
