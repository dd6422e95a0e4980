"""Near-rigid segmentation of a marker surface (Park & Hodgins 2006, §5.2): the ``segment`` stage.

The marker surface (a triangle mesh whose vertices are the markers) is cut into
near-rigid parts from a range-of-motion trial:

1. every triangle gets its rotation sequence (reference pose -> each frame,
   :func:`triangle_rotations`),
2. triangles with similar rotation sequences (:func:`rotation_features`) are
   grouped by mean-shift clustering (James & Twigg 2005; :func:`mean_shift`),
3. the clusters become marker parts and are cleaned up automatically
   (:func:`marker_labels_from_triangles`, :func:`clean_up_parts`): each
   marker takes the cluster of most of its triangles, disconnected pieces are
   split, adjacent parts are merged (most rigid union first) while their union
   stays rigid within ``merge_rms`` (the narrow kernel over-segments on
   purpose), parts smaller than ``min_part_markers`` are merged into the
   adjacent part that stays most rigid, and (optionally) adjacent parts are
   merged greedily until ``n_parts`` remain (the paper adjusted its 17 parts
   by hand; a manual override is accepted, :func:`_apply_override`),
4. boundary markers get soft weights ``alpha`` from a Gaussian likelihood of
   their rigid-fit error against every neighbouring part (:func:`soft_weights`);
   weights below the threshold (0.2) are dropped, so a marker may belong to
   several parts,
5. each part gets a local frame (:func:`part_frames`): origin at the weighted
   mean of its reference positions, axes the eigenvectors of their covariance.

The result is a :class:`~mocapflow.stages.skin.segmentation.Segmentation`, stored
with its own codec (:mod:`mocapflow.stages.skin.segmentation`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from mocapflow.pipeline import Context, FilePath, stage
from mocapflow.stages.motion.absolute_orientation import absolute_orientation_batch
from mocapflow.stages.motion.datatypes import Markers, Mesh
from mocapflow.stages.skin.density import (
    density_warning,
    marker_density,
    object_markers,
)
from mocapflow.stages.skin.segmentation import Segmentation, SegmentationError

__all__ = [
    "clean_up_parts",
    "marker_adjacency",
    "marker_labels_from_triangles",
    "mean_shift",
    "part_frames",
    "rigid_fit_errors",
    "rotation_features",
    "segment",
    "soft_weights",
    "triangle_rotations",
]


# --------------------------------------------------------------------------- surface helpers


def marker_adjacency(faces: np.ndarray, n_markers: int) -> sp.csr_matrix:
    """Symmetric marker adjacency (one-ring) of a marker surface.

    Parameters
    ----------
    faces : (T, 3) int ndarray
    n_markers : int

    Returns
    -------
    (M, M) bool sparse matrix
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    i = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    j = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    A = sp.coo_matrix((np.ones(i.size, bool), (i, j)), shape=(n_markers, n_markers)).tocsr()
    A = (A + A.T).astype(bool)
    A.setdiag(False)
    A.eliminate_zeros()
    return A


def triangle_rotations(
    positions: np.ndarray, reference: np.ndarray, faces: np.ndarray
) -> np.ndarray:
    """Rotation of every marker-surface triangle from the reference pose to each frame.

    Each triangle's orthonormal frame is (first edge, in-plane normal to it,
    triangle normal); the rotation is ``B_f B_ref^T``.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        Marker positions, NaN where missing.
    reference : (M, 3) float ndarray
    faces : (T, 3) int ndarray

    Returns
    -------
    (F, T, 3, 3) float ndarray
        NaN where a corner of the triangle is missing.
    """

    def frames(p: np.ndarray) -> np.ndarray:
        a, b, c = p[..., faces[:, 0], :], p[..., faces[:, 1], :], p[..., faces[:, 2], :]
        e1 = b - a
        n = np.cross(e1, c - a)
        e1 = e1 / np.linalg.norm(e1, axis=-1, keepdims=True)
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
        e2 = np.cross(n, e1)
        return np.stack([e1, e2, n], axis=-1)  # columns

    with np.errstate(invalid="ignore", divide="ignore"):
        B0 = frames(np.asarray(reference, dtype=np.float64))
        Bf = frames(np.asarray(positions, dtype=np.float64))
    return np.einsum("ftij,tkj->ftik", Bf, B0)


def rotation_features(
    rotations: np.ndarray, *, max_frames: int = 300, max_dims: int = 64
) -> np.ndarray:
    """Feature vectors of triangle rotation sequences for clustering.

    The distance between two feature vectors equals (up to the PCA truncation)
    the RMS over frames of ``||R_i(f) - R_j(f)||_F``.  Missing rotations are
    imputed with the mean over triangles of that frame (documented choice: a
    missing sample then pulls the triangle neither way).

    Parameters
    ----------
    rotations : (F, T, 3, 3) float ndarray
    max_frames : int
        Frames are subsampled evenly to at most this many.
    max_dims : int
        PCA truncation of the features.

    Returns
    -------
    (T, D) float ndarray
    """
    F, T = rotations.shape[:2]
    idx = np.unique(np.linspace(0, F - 1, min(F, max_frames)).round().astype(int))
    X = rotations[idx].reshape(len(idx), T, 9).transpose(1, 0, 2).reshape(T, -1)
    X = X / np.sqrt(len(idx))
    bad = ~np.isfinite(X)
    if bad.any():
        # np.nanmean's sum and count, without its warning for columns with no value (frames
        # where no triangle is measured: ezc3d's BTS.c3d before the subject walks in), 0 there
        count = (~bad).sum(0)
        col_mean = np.where(count > 0, np.where(bad, 0.0, X).sum(0) / np.maximum(count, 1), 0.0)
        X = np.where(bad, col_mean[None, :], X)
    Xc = X - X.mean(0)
    if Xc.shape[1] <= max_dims:
        return Xc
    if Xc.shape[0] <= Xc.shape[1]:  # principal coordinates from the (T, T) Gram matrix
        lam, U = np.linalg.eigh(Xc @ Xc.T)
        lam, U = lam[::-1], U[:, ::-1]
        k = min(max_dims, len(lam))
        return U[:, :k] * np.sqrt(np.maximum(lam[:k], 0.0))
    U, s, _ = np.linalg.svd(Xc, full_matrices=False)
    k = min(max_dims, len(s))
    return U[:, :k] * s[:k]


def mean_shift(
    points: np.ndarray, bandwidth: float, *, max_iter: int = 300, tol: float = 1e-5
) -> tuple[np.ndarray, np.ndarray]:
    """Mean-shift clustering with a Gaussian kernel.

    Every point climbs the kernel density estimate to its mode; modes closer
    than ``bandwidth / 2`` are merged into one cluster.

    Parameters
    ----------
    points : (N, D) float ndarray
    bandwidth : float
        Gaussian kernel standard deviation (same unit as the points).
    max_iter : int
    tol : float
        Convergence threshold on the largest shift, relative to ``bandwidth``.

    Returns
    -------
    labels : (N,) int ndarray
        Cluster of each point, clusters numbered by decreasing size.
    modes : (K, D) float ndarray
        Mode of each cluster.
    """
    X = np.asarray(points, dtype=np.float64)
    if bandwidth <= 0:
        raise ValueError(f"mean_shift: bandwidth must be positive, got {bandwidth}")
    Y = X.copy()
    xx = np.sum(X * X, axis=1)
    active = np.arange(len(X))
    for _ in range(max_iter):  # converged points stop moving (and stop costing)
        Ya = Y[active]
        d2 = np.sum(Ya * Ya, axis=1)[:, None] + xx[None, :] - 2.0 * Ya @ X.T
        W = np.exp(-np.maximum(d2, 0.0) / (2.0 * bandwidth**2))
        Y_new = (W @ X) / W.sum(axis=1, keepdims=True)
        shift = np.linalg.norm(Y_new - Ya, axis=1)
        Y[active] = Y_new
        active = active[shift >= tol * bandwidth]
        if active.size == 0:
            break
    pairs = cKDTree(Y).query_pairs(bandwidth / 2.0, output_type="ndarray")
    G = sp.coo_matrix(
        (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(Y), len(Y))
    )
    _, comp = connected_components(G, directed=False)
    labels = _renumber_by_size(comp)
    modes = np.stack([Y[labels == k].mean(0) for k in range(labels.max() + 1)])
    return labels, modes


def _renumber_by_size(labels: np.ndarray) -> np.ndarray:
    uniq, inv, counts = np.unique(labels, return_inverse=True, return_counts=True)
    order = np.lexsort((uniq, -counts))  # largest first, ties by label
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[inv]


def marker_labels_from_triangles(
    triangle_labels: np.ndarray, faces: np.ndarray, n_markers: int
) -> np.ndarray:
    """Cluster of each marker: the most frequent cluster among its triangles.

    Parameters
    ----------
    triangle_labels : (T,) int ndarray
    faces : (T, 3) int ndarray
    n_markers : int

    Returns
    -------
    (M,) int ndarray
        -1 for a marker on no triangle.
    """
    K = int(triangle_labels.max()) + 1
    m = faces.ravel()
    k = np.repeat(triangle_labels, 3)
    votes = sp.coo_matrix((np.ones(m.size), (m, k)), shape=(n_markers, K)).toarray()
    lab = np.argmax(votes, axis=1)
    lab[votes.sum(1) == 0] = -1
    return lab


# --------------------------------------------------------------------------- rigid fits


def rigid_fit_errors(
    reference: np.ndarray, positions: np.ndarray, fit_members: np.ndarray
) -> np.ndarray:
    """Squared errors of all markers against the rigid motion of a marker set.

    Parameters
    ----------
    reference : (M, 3) float ndarray
    positions : (F, M, 3) float ndarray
        NaN where missing.
    fit_members : (K,) int ndarray
        Markers whose per-frame Horn fit defines the rigid motion (K >= 3).

    Returns
    -------
    (F, M) float ndarray
        ``|R_f ref_i + t_f - x_i(f)|^2``; NaN where the marker is missing or
        the frame's fit is degenerate.
    """
    F = positions.shape[0]
    src = np.broadcast_to(reference[fit_members], (F, len(fit_members), 3))
    R, t = absolute_orientation_batch(src, positions[:, fit_members])
    pred = np.einsum("fij,mj->fmi", R, reference) + t[:, None, :]
    return np.sum((pred - positions) ** 2, axis=-1)


def _rms(reference: np.ndarray, positions: np.ndarray, members: np.ndarray) -> float:
    e = rigid_fit_errors(reference[members], positions[:, members], np.arange(len(members)))
    return float(np.sqrt(np.nanmean(e))) if np.isfinite(e).any() else np.inf


def _part_adjacency(labels: np.ndarray, adjacency: sp.csr_matrix) -> set[tuple[int, int]]:
    A = adjacency.tocoo()
    a, b = labels[A.row], labels[A.col]
    keep = (a != b) & (a >= 0) & (b >= 0)
    return {(int(min(x, y)), int(max(x, y))) for x, y in zip(a[keep], b[keep])}


def _split_connected(labels: np.ndarray, adjacency: sp.csr_matrix) -> np.ndarray:
    A = adjacency.tocoo()
    same = labels[A.row] == labels[A.col]
    G = sp.coo_matrix((np.ones(same.sum()), (A.row[same], A.col[same])), shape=adjacency.shape)
    _, comp = connected_components(G, directed=False)
    return comp


def clean_up_parts(
    labels: np.ndarray,
    adjacency: sp.csr_matrix,
    reference: np.ndarray,
    positions: np.ndarray,
    *,
    merge_rms: float | None = 0.008,
    min_part_markers: int = 6,
    n_parts: int | None = None,
) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """Turn marker clusters into connected near-rigid parts.

    1. disconnected pieces of one cluster become separate parts;
    2. adjacent parts are merged greedily, the pair whose union has the lowest
       RMS rigid-fit error first, while that error stays below ``merge_rms``
       (mean shift with a narrow kernel over-segments; this undoes it wherever
       the union still moves rigidly);
    3. a part with fewer than ``min_part_markers`` markers is merged into the
       adjacent part whose union with it fits best;
    4. if ``n_parts`` is given, adjacent pairs are merged (best union first)
       until ``n_parts`` remain.

    Parameters
    ----------
    labels : (M,) int ndarray
        Cluster per marker.
    adjacency : (M, M) sparse bool matrix
    reference : (M, 3) float ndarray
    positions : (F, M, 3) float ndarray
    merge_rms : float, optional
        Rigidity tolerance of step 2 in metres (``None`` skips step 2).
    min_part_markers : int
    n_parts : int, optional

    Returns
    -------
    labels : (M,) int ndarray
        Part per marker, ``0 .. P-1`` numbered by first marker index.
    merges : list of dict
        One entry per merge: the two parts' marker counts, union RMS (m), reason.
    """
    lab = _split_connected(np.asarray(labels), adjacency)
    merges: list[dict[str, Any]] = []
    cache: dict[tuple[int, ...], float] = {}

    def union_rms(a: int, b: int) -> float:
        members = np.flatnonzero((lab == a) | (lab == b))
        key = tuple(members.tolist())
        if key not in cache:
            cache[key] = _rms(reference, positions, members)
        return cache[key]

    def merge(a: int, b: int, reason: str, cost: float) -> None:
        na, nb = int(np.sum(lab == a)), int(np.sum(lab == b))
        merges.append({"sizes": [na, nb], "union_rms": cost, "reason": reason})
        lab[lab == b] = a

    def best_pair() -> tuple[tuple[int, int] | None, float]:
        pairs = sorted(_part_adjacency(lab, adjacency))
        if not pairs:
            return None, np.inf
        costs = [union_rms(a, b) for a, b in pairs]
        j = int(np.argmin(costs))
        return pairs[j], costs[j]

    if merge_rms is not None:
        while len(np.unique(lab)) > 1:
            pair, cost = best_pair()
            if pair is None or cost > merge_rms:
                break
            merge(pair[0], pair[1], f"union rigid within merge_rms={merge_rms}", cost)
    isolated: set[int] = set()
    while True:
        sizes = np.bincount(lab, minlength=lab.max() + 1)
        alive = np.flatnonzero(sizes)
        small = [k for k in alive if sizes[k] < min_part_markers and k not in isolated]
        if not small or len(alive) == 1:
            break
        k = min(small, key=lambda x: (sizes[x], x))
        adj_pairs = _part_adjacency(lab, adjacency)
        nbrs = sorted({b if a == k else a for a, b in adj_pairs if k in (a, b)})
        if not nbrs:  # an island of the surface: nothing to merge with
            isolated.add(k)
            continue
        costs = [union_rms(min(k, n), max(k, n)) for n in nbrs]
        j = int(np.argmin(costs))
        merge(nbrs[j], k, f"fewer than {min_part_markers} markers", costs[j])
    if n_parts is not None:
        while len(np.unique(lab)) > n_parts:
            pair, cost = best_pair()
            if pair is None:
                break
            merge(pair[0], pair[1], f"reduce to n_parts={n_parts}", cost)
    # renumber by first marker index
    _, first = np.unique(lab, return_index=True)
    order = np.argsort(first)
    remap = np.empty(lab.max() + 1, dtype=np.int64)
    remap[np.unique(lab)[order]] = np.arange(len(order))
    return remap[lab], merges


def soft_weights(
    labels: np.ndarray,
    adjacency: sp.csr_matrix,
    reference: np.ndarray,
    positions: np.ndarray,
    *,
    threshold: float = 0.2,
    sigma: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Soft part weights ``alpha`` of the markers (Gaussian likelihood of rigid-fit error).

    For marker ``i`` and every part ``p`` that contains ``i`` or one of its
    one-ring neighbours, ``E_ip`` is the mean squared distance between the
    marker and its position predicted by the rigid motion of part ``p``
    (Horn fit of ``p``'s markers per frame).  The likelihood is
    ``exp(-E_ip / (2 sigma_i^2))``; unless ``sigma`` is given, ``sigma_i^2`` is the
    larger of the marker's best-fit error ``min_p E_ip`` and the mean ``E`` of its
    own part's markers (the part's non-rigidity), so the likelihoods are relative
    to how well the marker follows any part at all: a marker that follows two
    parts about equally well gets weights near 1/2 each, one that follows one
    part far better than the others gets 1.  Likelihoods are normalised per
    marker, weights below ``threshold`` dropped and the rest renormalised.

    Parameters
    ----------
    labels : (M,) int ndarray
        Hard part per marker ``0 .. P-1``.
    adjacency : (M, M) sparse bool matrix
    reference : (M, 3) float ndarray
    positions : (F, M, 3) float ndarray
    threshold : float
    sigma : float, optional
        Fixed Gaussian width in metres.

    Returns
    -------
    alpha : (M, P) float ndarray
    fit_rms : (P,) float ndarray
        RMS rigid-fit error of each part's own markers (metres).
    """
    M = len(labels)
    P = int(labels.max()) + 1
    E = np.full((M, P), np.inf)
    fit_rms = np.full(P, np.nan)
    A = adjacency.tocsr()
    one_hot = sp.csr_matrix((np.ones(M), (np.arange(M), labels)), shape=(M, P))
    candidate = ((A @ one_hot) + one_hot).toarray() > 0  # (M, P): own or neighbouring part
    for p in range(P):
        members = np.flatnonzero(labels == p)
        cand = np.flatnonzero(candidate[:, p])
        if len(members) < 3:
            E[members, p] = 0.0  # a part too small to fit keeps its own markers
            continue
        err = rigid_fit_errors(reference[cand], positions[:, cand], _index_in(cand, members))
        if not np.isfinite(err).any():
            E[members, p] = 0.0
            continue
        with np.errstate(all="ignore"):
            mean_err = np.nanmean(err, axis=0)
        E[cand, p] = np.where(np.isfinite(mean_err), mean_err, np.inf)
        own = E[members, p]
        fit_rms[p] = float(np.sqrt(np.mean(own[np.isfinite(own)]))) if np.isfinite(own).any() else 0
    floor = 1e-4**2  # (0.1 mm)^2: noise-free synthetic data would give sigma = 0
    if sigma is not None:
        s2 = np.full(M, float(sigma) ** 2)
    else:
        own_rms = np.where(np.isfinite(fit_rms), fit_rms, 0.0)[labels]
        s2 = np.maximum(np.maximum(E.min(axis=1), own_rms**2), floor)
    L = np.exp(-(E - E.min(axis=1, keepdims=True)) / (2.0 * s2[:, None]))
    alpha = L / L.sum(1, keepdims=True)
    alpha[alpha < threshold] = 0.0
    empty = alpha.sum(1) == 0
    alpha[empty, labels[empty]] = 1.0
    alpha /= alpha.sum(1, keepdims=True)
    return alpha, fit_rms


def _index_in(cand: np.ndarray, members: np.ndarray) -> np.ndarray:
    """Positions of ``members`` inside ``cand`` (both sorted, members a subset)."""
    return np.searchsorted(cand, members)


def part_frames(reference: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local frame of every part from its weighted reference positions.

    Parameters
    ----------
    reference : (M, 3) float ndarray
    weights : (M, P) float ndarray

    Returns
    -------
    origins : (P, 3) float ndarray
        Weighted mean position of each part.
    axes : (P, 3, 3) float ndarray
        Columns: eigenvectors of the weighted covariance, decreasing eigenvalue,
        each oriented so its largest component is positive (the third is then
        flipped if needed to keep the frame right-handed).
    """
    P = weights.shape[1]
    origins = np.zeros((P, 3))
    axes = np.zeros((P, 3, 3))
    for p in range(P):
        w = weights[:, p]
        w = w / w.sum()
        o = w @ reference
        d = reference - o
        C = (w[:, None] * d).T @ d
        _, vecs = np.linalg.eigh(C)
        V = vecs[:, ::-1].copy()
        for k in range(2):
            if V[np.argmax(np.abs(V[:, k])), k] < 0:
                V[:, k] *= -1
        V[:, 2] = np.cross(V[:, 0], V[:, 1])
        origins[p] = o
        axes[p] = V
    return origins, axes


# --------------------------------------------------------------------------- override


def _read_override(
    override: dict[str, list[str]] | None, override_file: str | None
) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    if override_file is not None:
        path = Path(override_file)
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise SegmentationError(f"segmentation override file {path}: {e}") from e
        if not isinstance(data, dict) or not all(isinstance(v, list) for v in data.values()):
            raise SegmentationError(
                f"segmentation override file {path}: expected a JSON object "
                "{part name: [marker labels]}"
            )
        out.update({str(k): [str(x) for x in v] for k, v in data.items()})
    if override:
        out.update({str(k): [str(x) for x in v] for k, v in override.items()})
    return out


def _apply_override(
    labels: np.ndarray, names: list[str], marker_labels: list[str], override: dict[str, list[str]]
) -> tuple[np.ndarray, list[str]]:
    index = {m: i for i, m in enumerate(marker_labels)}
    unknown = sorted({m for ms in override.values() for m in ms if m not in index})
    if unknown:
        raise SegmentationError(
            f"segmentation override names markers that are not in the capture: {unknown[:10]}"
        )
    part_of: dict[int, str] = {i: names[k] for i, k in enumerate(labels)}
    for part, ms in override.items():
        for m in ms:
            part_of[index[m]] = part
    new_names: list[str] = []
    for i in range(len(marker_labels)):
        if part_of[i] not in new_names:
            new_names.append(part_of[i])
    new = np.array([new_names.index(part_of[i]) for i in range(len(marker_labels))])
    return new, new_names


# --------------------------------------------------------------------------- stage


def _reference_and_faces(
    markers: Markers, surface: Mesh
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference positions and faces of the surface markers, and their indices in ``markers``."""
    M = markers.n_markers
    faces = np.asarray(surface.faces, dtype=np.int64)
    if faces.size == 0:
        raise SegmentationError("marker surface has no triangles")
    ref = surface.vertices if surface.vertices.ndim == 2 else surface.vertices[0]
    surf_labels = surface.attrs.get("labels") or surface.attrs.get("marker_labels")
    if surf_labels is not None:
        surf_labels = [str(x) for x in surf_labels]
        if len(surf_labels) != ref.shape[0]:
            raise SegmentationError(
                f"marker surface has {ref.shape[0]} vertices but {len(surf_labels)} labels"
            )
        index = {m: i for i, m in enumerate(markers.labels)}
        missing = [m for m in surf_labels if m not in index]
        if missing:
            raise SegmentationError(
                f"marker surface names markers that are not in the capture: {missing[:10]}"
            )
        cols = np.array([index[m] for m in surf_labels], dtype=np.int64)
    elif ref.shape[0] == M:
        cols = np.arange(M)
    else:
        raise SegmentationError(
            f"marker surface has {ref.shape[0]} unlabelled vertices but the capture has {M} "
            "markers"
        )
    on_surface = np.isfinite(ref).all(1)
    on_surface[np.setdiff1d(np.arange(len(ref)), faces.ravel())] = False
    if not on_surface[faces].all():
        raise SegmentationError("marker surface has triangles on markers without a position")
    keep = np.flatnonzero(on_surface)
    remap = np.full(len(ref), -1)
    remap[keep] = np.arange(len(keep))
    return np.asarray(ref[keep], dtype=np.float64), remap[faces], cols[keep]


def _surface_markers(markers: Markers, surface: Mesh,
                     ctx: Context) -> tuple[Markers, np.ndarray, np.ndarray]:
    """The capture cut down to the markers on the surface (the others warned about).

    Returns the markers ``(F, M', 3)`` in surface order, their reference
    positions ``(M', 3)`` and the faces ``(T, 3)`` re-indexed onto them.
    """
    reference, faces, cols = _reference_and_faces(markers, surface)
    left_out = sorted(set(markers.labels) - {markers.labels[i] for i in cols})
    if left_out:
        ctx.warn(
            f"{len(left_out)} markers are not on the marker surface and are left "
            f"out of the segmentation: {left_out[:10]}"
        )
    markers = markers.replace(
        positions=markers.positions[:, cols], labels=[markers.labels[i] for i in cols],
        residuals=None,
    )  # fmt: skip
    return markers, reference, faces


def _body_markers(markers: Markers, reference: np.ndarray, faces: np.ndarray,
                  ctx: Context) -> tuple[Markers, np.ndarray, np.ndarray]:
    """The capture without the markers on objects (:func:`~mocapflow.stages.skin.density.
    object_markers`; one warning names them): markers ``(F, M', 3)``, their reference
    positions ``(M', 3)`` and the faces ``(T', 3)`` among them."""
    obj = object_markers(markers.labels, reference)
    if not obj.any():
        return markers, reference, faces
    if obj.all():
        raise SegmentationError(
            f"{_source(markers)}: every marker looks like an object marker (names or place): "
            f"{markers.labels[:10]}; nothing is left for the body"
        )
    keep = np.flatnonzero(~obj)
    remap = np.full(len(obj), -1)
    remap[keep] = np.arange(len(keep))
    faces = remap[faces[~obj[faces].any(1)]]
    names = [lb for lb, o in zip(markers.labels, obj) if o]
    ctx.warn(
        f"{_source(markers)}: {len(names)} markers on objects are kept apart from the body "
        f"(a second subject, not segmented, fitted or deformed): {names[:12]}"
    )
    markers = markers.replace(positions=markers.positions[:, keep],
                              labels=[markers.labels[i] for i in keep])  # fmt: skip
    return markers, reference[keep], faces


def _source(markers: Markers) -> str:
    """The capture's file name for messages."""
    return Path(str(markers.attrs.get("source") or "capture")).name


def _cluster_triangles(positions: np.ndarray, reference: np.ndarray, faces: np.ndarray,
                       n_markers: int, *, bandwidth: float,
                       max_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Steps 1–2 and the start of 3: triangle rotation sequences clustered by mean shift,
    each marker taking the cluster of most of its triangles (markers on none get
    clusters of their own).  Returns ``(triangle clusters (T,), marker clusters (M,))``."""
    rot = triangle_rotations(positions, reference, faces)
    feats = rotation_features(rot, max_frames=max_frames)
    tri_labels, _ = mean_shift(feats, bandwidth)
    cluster = marker_labels_from_triangles(tri_labels, faces, n_markers)
    cluster[cluster < 0] = cluster.max() + 1 + np.arange(np.sum(cluster < 0))
    return tri_labels, cluster


def _warn_small_parts(names: list[str], alpha: np.ndarray, ctx: Context) -> None:
    """Warn about parts with fewer than 10 markers (``deform`` keeps them rigid)."""
    for p, n in enumerate(names):
        k = int(np.sum(alpha[:, p] > 0))
        if k < 10:
            ctx.warn(
                f"part {n!r} has {k} markers (< 10): deform will use a rigid "
                "transform for it (the quadratic is under-determined)",
                hint="harmless where the part moves rigidly (head, pelvis); for a part "
                     "that bends, raise segment.min_part_markers to merge it into a "
                     "neighbour, or give it more markers with segment.override",
            )


def _segment_report(marker_labels: list[str], names: list[str], labels: np.ndarray,
                    alpha: np.ndarray, fit_rms: np.ndarray, merges: list[dict[str, Any]], *,
                    n_clusters: int, frames_used: int, override: bool) -> dict[str, Any]:
    """The segment report: parts with their markers and rigid-fit RMS (mm), merges,
    boundary markers (weights for more than one part)."""
    boundary = np.flatnonzero((alpha > 0).sum(1) > 1)
    return {
        "n_clusters": n_clusters,
        "n_parts": len(names),
        "frames_used": frames_used,
        "parts": {
            n: {
                "markers": [marker_labels[i] for i in np.flatnonzero(labels == p)],
                "n_members": int(np.sum(alpha[:, p] > 0)),
                "rigid_fit_rms_mm": float(fit_rms[p] * 1000) if np.isfinite(fit_rms[p]) else None,
            }
            for p, n in enumerate(names)
        },
        "merges": merges,
        "boundary_markers": [marker_labels[i] for i in boundary],
        "override": override,
    }


@stage("segment", outputs=("segmentation", "report"))
def segment(
    markers: Markers,
    surface: Mesh,
    *,
    bandwidth: float = 0.05,
    merge_rms: float | None = 0.008,
    n_parts: int | None = None,
    min_part_markers: int = 4,
    threshold: float = 0.2,
    sigma: float | None = None,
    max_frames: int = 300,
    override: dict[str, list[str]] | None = None,
    override_file: FilePath | None = None,
    ctx: Context,
) -> dict[str, Any]:
    """Near-rigid segmentation of the marker surface from a range-of-motion trial.

    Parameters
    ----------
    markers : Markers
        Range-of-motion trial, ``(F, M, 3)`` positions (cleaned; NaN allowed).
    surface : Mesh
        Marker surface (stage ``clean``): ``vertices (M', 3)`` reference positions,
        ``faces (T, 3)``, ``attrs["labels"]`` naming the vertices (without labels
        the vertices are the capture's markers in order).  Markers without a
        reference position or triangle are left out, with a warning.
    bandwidth : float
        Mean-shift kernel width on the RMS (over frames) Frobenius distance
        between rotation sequences; narrow on purpose (over-segments, then the
        clean-up merges what is still rigid).
    merge_rms : float, optional
        Adjacent parts are merged while their union's RMS rigid-fit error over
        the trial stays below this (metres); ``None`` keeps the raw clusters.
    n_parts : int, optional
        Merge adjacent parts greedily (lowest union rigid-fit error first) until
        this many remain (the paper used 17).
    min_part_markers : int
        Parts with fewer markers are merged into their most rigid neighbour
        (a rigid fit needs 3; ``deform`` falls back to rigid below 10).
    threshold : float
        Soft weights ``alpha`` below this are dropped (paper: 0.2).
    sigma : float, optional
        Fixed width (m) of the Gaussian likelihood; default: relative to each
        marker's best rigid-fit error (see :func:`soft_weights`).
    max_frames : int
        Frames subsampled for the clustering features.
    override : dict, optional
        Manual segmentation ``{part name: [marker labels]}``; listed markers go to
        the named parts, the others keep their automatic parts.
    override_file : path, optional
        JSON file with the same mapping (merged before ``override``).

    Returns
    -------
    dict
        ``segmentation`` (:class:`Segmentation`) and ``report`` (JSON: parts with
        their markers, rigid-fit RMS in mm, merges, boundary markers).
    """
    markers, reference, faces = _surface_markers(markers, surface, ctx)
    markers, reference, faces = _body_markers(markers, reference, faces, ctx)
    M = markers.n_markers
    pos = markers.positions
    F = pos.shape[0]
    if F < 2:
        raise SegmentationError("segmentation needs a range-of-motion trial (>= 2 frames)")
    fidx = np.unique(np.linspace(0, F - 1, min(F, max_frames)).round().astype(int))
    pos_s = pos[fidx]
    adjacency = marker_adjacency(faces, M)
    isolated = np.flatnonzero(np.asarray(adjacency.sum(1)).ravel() == 0)
    if isolated.size:
        ctx.warn(
            f"markers on no surface triangle form their own parts: "
            f"{[markers.labels[i] for i in isolated[:10]]}"
        )
    tri_labels, cluster = _cluster_triangles(pos_s, reference, faces, M, bandwidth=bandwidth,
                                             max_frames=max_frames)
    pos_c = pos_s[np.unique(np.linspace(0, len(pos_s) - 1, min(len(pos_s), 120)).astype(int))]
    labels, merges = clean_up_parts(
        cluster, adjacency, reference, pos_c, merge_rms=merge_rms,
        min_part_markers=min_part_markers, n_parts=n_parts,
    )  # fmt: skip
    names = [f"part{k:02d}" for k in range(labels.max() + 1)]
    manual = _read_override(override, override_file)
    if manual:
        labels, names = _apply_override(labels, names, markers.labels, manual)
    alpha, fit_rms = soft_weights(
        labels, adjacency, reference, pos_s, threshold=threshold, sigma=sigma
    )
    origins, axes = part_frames(reference, alpha)
    density = marker_density(reference, labels)
    if density["suited"]:
        _warn_small_parts(names, alpha, ctx)
    else:  # one warning for the capture instead of one per small part
        ctx.warn(density_warning(density, _source(markers)),
                 hint="a dense capture (~350 markers, e.g. the one `mocapflow demo` "
                      "simulates) is what the method is for")  # fmt: skip
    report = _segment_report(markers.labels, names, labels, alpha, fit_rms, merges,
                             n_clusters=int(tri_labels.max() + 1), frames_used=len(fidx),
                             override=bool(manual))
    report["density"] = density
    seg = Segmentation(
        labels=markers.labels,
        part_names=names,
        weights=alpha,
        reference=reference,
        faces=faces,
        origins=origins,
        axes=axes,
        triangle_clusters=tri_labels,
        attrs={
            "bandwidth": bandwidth,
            "merge_rms": merge_rms,
            "threshold": threshold,
            "sigma": sigma,
            "n_parts": n_parts,
            "min_part_markers": min_part_markers,
            # Park & Hodgins' density rule (density.marker_density): fit_mesh and deform
            # fall back to an upright fit and rigid skinning when it is not met
            "density": density,
            # the capture's axes (ingest), read by fit_mesh and the renderer
            **{k: markers.attrs[k] for k in ("up", "forward") if k in markers.attrs},
        },
    )
    return {"segmentation": seg, "report": report}
