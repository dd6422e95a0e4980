"""Binding a detailed mesh to the segmented marker surface (Park & Hodgins 2006, §5.3).

Every vertex takes its part weights ``β`` from the nearest marker-surface triangle
(:func:`closest_points_on_triangles`): barycentric interpolation of the markers'
``α``, sharpened by default (``β ∝ β_bary^γ``, a departure measured in
:mod:`mocapflow.stages.skin.deform`; :func:`bind_mesh`).  Also home of
:class:`DeformError`, the error of the deformation stages (``deform``, ``fit_mesh``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from mocapflow.stages.skin.segmentation import Segmentation

__all__ = [
    "DeformError",
    "MeshBinding",
    "bind_mesh",
    "blend_smoothing_operator",
    "closest_points_on_triangles",
    "mesh_edges",
]


class DeformError(ValueError):
    """Inputs of the skin deformation are inconsistent (names the part / mesh problem)."""


def closest_points_on_triangles(
    points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, *, k: int = 12
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point of a triangle mesh to each query point (Ericson's region test).

    Candidates are the ``k`` triangles with the nearest centroids.

    Parameters
    ----------
    points : (N, 3) float ndarray
    vertices : (V, 3) float ndarray
    faces : (T, 3) int ndarray
    k : int

    Returns
    -------
    triangle : (N,) int ndarray
    barycentric : (N, 3) float ndarray
        Weights of the triangle's corners (non-negative, sum 1).
    distance : (N,) float ndarray
    """
    P = np.asarray(points, dtype=np.float64)
    tri = vertices[faces]  # (T, 3, 3)
    k = int(min(k, len(faces)))
    _, cand = cKDTree(tri.mean(1)).query(P, k=k)
    cand = np.asarray(cand).reshape(len(P), k)
    triangle = np.empty(len(P), np.int64)
    barycentric = np.empty((len(P), 3))
    distance = np.empty(len(P))
    # the points in chunks, whose (n, k) temporaries stay in cache (each point's result is
    # its own: the same bits as all at once, in about 2/3 of the time for 13,000 points)
    for a in range(0, len(P), _POINTS_PER_CHUNK):
        p, c = P[a : a + _POINTS_PER_CHUNK], cand[a : a + _POINTS_PER_CHUNK]
        A, B, C = tri[c, 0], tri[c, 1], tri[c, 2]  # (n, k, 3)
        bary = _closest_barycentric(p[:, None, :], A, B, C)
        Q = bary[..., :1] * A + bary[..., 1:2] * B + bary[..., 2:] * C
        d2 = np.sum((Q - p[:, None, :]) ** 2, axis=-1)
        j = np.argmin(d2, axis=1)
        n = np.arange(len(p))
        triangle[a : a + len(p)], barycentric[a : a + len(p)] = c[n, j], bary[n, j]
        distance[a : a + len(p)] = np.sqrt(d2[n, j])
    return triangle, barycentric, distance


#: Query points per chunk of :func:`closest_points_on_triangles` (a few hundred kB of
#: temporaries with its 12 candidates).
_POINTS_PER_CHUNK = 1024


def _closest_barycentric(p, a, b, c):
    """Barycentric coordinates of the closest point on triangles ``abc`` (broadcast)."""
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.sum(ab * ap, -1)
    d2 = np.sum(ac * ap, -1)
    bp = p - b
    d3 = np.sum(ab * bp, -1)
    d4 = np.sum(ac * bp, -1)
    cp = p - c
    d5 = np.sum(ab * cp, -1)
    d6 = np.sum(ac * cp, -1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_in = vb / denom
        w_in = vc / denom
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    shape = np.broadcast_shapes(d1.shape, va.shape)
    u = np.ones(shape)
    v = np.zeros(shape)
    w = np.zeros(shape)
    # regions, in reverse priority so the first matching test wins (assign last)
    inside = np.ones(shape, bool)
    regions = [
        (inside, 1 - v_in - w_in, v_in, w_in),
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), 0 * t_bc, 1 - t_bc, t_bc),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - t_ac, 0 * t_ac, t_ac),
        ((d6 >= 0) & (d5 <= d6), 0.0, 0.0, 1.0),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - t_ab, t_ab, 0 * t_ab),
        ((d3 >= 0) & (d4 <= d3), 0.0, 1.0, 0.0),
        ((d1 <= 0) & (d2 <= 0), 1.0, 0.0, 0.0),
    ]
    for mask, uu, vv, ww in regions:
        u = np.where(mask, uu, u)
        v = np.where(mask, vv, v)
        w = np.where(mask, ww, w)
    bary = np.stack([u, v, w], -1)
    bary = np.where(np.isfinite(bary), bary, np.array([1.0, 0.0, 0.0]))
    return bary


@dataclass
class MeshBinding:
    """Attachment of a detailed mesh to a segmented marker surface.

    Attributes
    ----------
    beta : (V, P) float ndarray
        Vertex weights per part (rows sum to 1).
    triangle : (V,) int ndarray
        Nearest marker-surface triangle of each vertex.
    barycentric : (V, 3) float ndarray
    distance : (V,) float ndarray
        Distance (m) from each vertex to the marker surface in the reference pose.
    """

    beta: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    distance: np.ndarray


def bind_mesh(
    vertices: np.ndarray,
    segmentation: Segmentation,
    *,
    max_distance: float | None = None,
    min_overlap: float = 0.9,
    sharpness: float = 4.0,
    min_weight: float = 1e-3,
    name: str = "mesh",
    allowed: np.ndarray | None = None,
) -> MeshBinding:
    """Vertex weights ``β`` by barycentric interpolation from the nearest marker triangle.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        Detailed mesh in the reference pose, fitted to the marker surface.
    segmentation : Segmentation
    max_distance : float, optional
        A vertex farther than this from the marker surface counts as not
        overlapping it; default 2 × the median marker-surface edge length.
    min_overlap : float
        Fraction of vertices that must overlap the marker surface.
    sharpness : float
        Exponent ``γ`` applied to the interpolated weights before they are
        renormalised, ``β ∝ β_bary^γ``; 1 is the paper's plain barycentric
        interpolation, larger values narrow the blend zones between parts.
    min_weight : float
        Weights below this (after sharpening) are dropped and the rest
        renormalised, so a vertex is not evaluated by parts it barely follows.
    name : str
        Name of the mesh in error messages.
    allowed : (V, P) bool ndarray, optional
        Parts each vertex may follow (a limb's skin its limb's and the body's parts:
        :func:`~mocapflow.stages.skin.limb_pose.limb_binding`): weights on other parts are
        dropped; a vertex left with none follows the parts of the nearest marker whose
        own part it may follow.

    Returns
    -------
    MeshBinding

    Raises
    ------
    DeformError
        When the mesh does not overlap the marker surface (wrong units, pose or
        placement), with the distances, extents and a unit hint in the message.
    """
    if not (np.isfinite(sharpness) and sharpness > 0):
        raise DeformError(f"{name}: beta sharpness must be a positive number, got {sharpness}")
    if not 0 <= min_weight < 0.5:
        raise DeformError(f"{name}: min_weight must be in [0, 0.5), got {min_weight}")
    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3 or not np.isfinite(V).all():
        raise DeformError(f"{name}: expected finite (V, 3) rest vertices, got {V.shape}")
    ref, faces = segmentation.reference, segmentation.faces
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    spacing = float(np.median(np.linalg.norm(ref[edges[:, 0]] - ref[edges[:, 1]], axis=1)))
    limit = 2.0 * spacing if max_distance is None else float(max_distance)
    tri, bary, dist = closest_points_on_triangles(V, ref, faces)
    overlap = float(np.mean(dist <= limit))
    if overlap < min_overlap:
        ext_m = np.ptp(ref, axis=0).max()
        ext_v = np.ptp(V, axis=0).max()
        ratio = ext_v / ext_m if ext_m > 0 else np.inf
        hint = ""
        for unit, scale in (("decimetres", 10.0), ("centimetres", 100.0), ("millimetres", 1000.0)):
            if 0.7 * scale < ratio < 1.4 * scale:
                hint = f"; the mesh looks {scale:g}x too large: is it in {unit}?"
        if not hint and 1.4 <= ratio < 7.0:
            hint = ("; the markers cover only part of the body (an upper-body or partial "
                    "marker set?): a whole-body mesh cannot follow them - give a mesh of the "
                    "part they cover")
        raise DeformError(
            f"{name} does not overlap the marker surface: only {overlap:.0%} of its "
            f"{len(V)} vertices lie within {limit * 1000:.0f} mm of it (median distance "
            f"{np.median(dist) * 1000:.0f} mm; mesh extent {ext_v:.3g} m, marker extent "
            f"{ext_m:.3g} m){hint}" + ("" if hint.startswith("; the markers") else
                                        "; fit the mesh to the markers first (stage fit_mesh)")
        )
    alpha = segmentation.weights
    beta = np.einsum("vc,vcp->vp", bary, alpha[faces[tri]])
    if sharpness != 1.0:
        beta = beta**sharpness
    beta /= beta.sum(1, keepdims=True)
    if allowed is not None:
        beta = _allowed_weights(beta, np.asarray(allowed, dtype=bool), V, ref, alpha)
    if min_weight > 0:
        beta[beta < min_weight] = 0.0
        beta /= beta.sum(1, keepdims=True)
    return MeshBinding(beta=beta, triangle=tri, barycentric=bary, distance=dist)


def _allowed_weights(beta: np.ndarray, allowed: np.ndarray, V: np.ndarray, ref: np.ndarray,
                     alpha: np.ndarray) -> np.ndarray:
    """``beta (V, P)`` held to the ``allowed`` parts, rows renormalised; a row with no
    allowed weight takes the nearest marker's ``alpha`` row among the markers whose largest
    part that vertex may follow (held to the allowed parts too); with no such marker it
    stays as it was."""
    given = beta
    beta = np.where(allowed, beta, 0.0)
    lost = beta.sum(1) <= 0
    if lost.any():
        own = alpha.argmax(1)  # each marker's part
        rows = np.flatnonzero(lost)
        patterns, which = np.unique(allowed[rows], axis=0, return_inverse=True)
        for k, pattern in enumerate(patterns):
            markers = np.flatnonzero(pattern[own] & np.isfinite(ref).all(1))
            if not markers.size:
                continue
            r = rows[which.ravel() == k]
            _, m = cKDTree(ref[markers]).query(V[r])
            nearest = markers[np.asarray(m)]
            w = alpha[nearest] * pattern
            w[np.arange(len(r)), own[nearest]] += w.sum(1) <= 0  # (its own part at least)
            beta[r] = w
    none = beta.sum(1) <= 0  # no marker of a part it may follow: as bound
    beta[none] = given[none]
    return beta / beta.sum(1, keepdims=True)


def mesh_edges(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unique edges of triangles ``faces (T, 3)``.

    Returns
    -------
    ends : (E, 2) int ndarray
        Each edge's two vertices, lower first.
    face_edge : (T, 3) int ndarray
        Edge ``k`` of each triangle (from its corner ``k`` to corner ``k + 1``).
    first : (E,) int ndarray
        The first ``3 t + k`` of each edge in ``face_edge``.
    """
    ahead = np.roll(faces, -1, axis=1)  # corner k + 1
    lo, hi = np.minimum(faces, ahead).ravel(), np.maximum(faces, ahead).ravel()
    _, first, inverse = np.unique(lo * n_vertices + hi, return_index=True, return_inverse=True)
    return np.stack([lo[first], hi[first]], 1), inverse.reshape(faces.shape), first


def blend_smoothing_operator(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """One step of weight diffusion over a triangle mesh: ``β ← S β`` (rows sum to 1).

    Each vertex keeps half its weight and takes the other half from its mesh
    neighbours in proportion to ``1 / edge length``, so the two ends of a short edge
    (a sliver's) are pulled together hardest and the blend widens over surface
    distance rather than over triangle counts.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        Rest positions.
    faces : (T, 3) int ndarray

    Returns
    -------
    (V, V) scipy.sparse.csr_matrix
    """
    V = len(vertices)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    e = mesh_edges(faces, V)[0]
    length = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    w = 1.0 / np.maximum(length, 1e-9 * max(float(length.max(initial=0.0)), 1e-12))
    W = sp.csr_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                      shape=(V, V))  # fmt: skip
    deg = np.asarray(W.sum(1)).ravel()
    alone = deg == 0  # a vertex on no edge keeps its weights
    deg[alone] = 1.0
    return (sp.diags(0.5 / deg) @ W + sp.diags(np.where(alone, 1.0, 0.5))).tocsr()
