"""Per-vertex affine registration of a template to markers (Allen, Curless & Popović 2003).

Park & Hodgins (2006) §5.1/§5.3 fit their detailed mesh to the subject with the
optimisation of Allen et al. (2003): every template vertex ``i`` gets its own
affine transform ``T_i`` (3 × 4), and the transforms minimise

    E = α E_d + β E_s + γ E_m

* :func:`data_term` ``E_d`` — each marker ``m`` lies ``h`` (the marker height,
  ``marker_offset``) outside the deformed template along its normal: the closest
  point of the deformed template to the marker, ``Σ_c b_mc T_c ṽ_c``, should be
  at ``y_m - h n_m``;
* :func:`smoothness_term` ``E_s`` — ``Σ_(i,j) ∈ edges ‖T_i - T_j‖²_F``: neighbouring
  transforms agree, so the template's own detail (everything between the markers)
  is carried along instead of being flattened onto the markers;
* :func:`landmark_term` ``E_m`` — markers of known anatomical placement
  (landmarks, ``{marker: template vertex}``) go to their vertex:
  ``T_v ṽ_v = y_m - h n_v``; :func:`anatomical_landmarks` finds them for bodies
  with a skeleton (the simulator's, the MakeHuman mesh's joint-cube rig).

:func:`affine_registration` solves it coarse to fine: a schedule of
``(γ, β, α)`` from a high landmark and smoothness weight to low ones (Allen et
al.'s schedule), each stage a few iterations of closest points (cKDTree over the
triangles) and one sparse linear least-squares solve (the normal equations, one
sparse LU for the three coordinates).  The unknowns are ``X (4V, 3)``, vertex
``i``'s block ``X[4i:4i+4] = T_iᵀ``, so a deformed vertex is ``ṽ_iᵀ X_i`` with
``ṽ_i = (v_i - c, 1)`` (``c`` the template's centroid).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from mocapflow.stages.motion.geometry import vertex_normals
from mocapflow.stages.skin.binding import DeformError, closest_points_on_triangles

__all__ = [
    "DEFAULT_SCHEDULE",
    "affine_registration",
    "anatomical_landmarks",
    "data_term",
    "deformed_vertices",
    "landmark_term",
    "smoothness_term",
    "vertex_operator",
]

#: Allen et al.'s coarse-to-fine schedule as ``(landmark γ, smoothness β, data α,
#: iterations)``: landmarks alone with a stiff field first, then the markers
#: joined, then the landmarks and the smoothness relaxed so the markers decide.
DEFAULT_SCHEDULE: tuple[tuple[float, float, float, int], ...] = (
    (10.0, 1.0, 0.0, 1),
    (1.0, 1.0, 1.0, 3),
    (0.0, 0.3, 1.0, 3),
    (0.0, 0.1, 1.0, 3),
    (0.0, 0.03, 1.0, 4),
    (0.0, 0.01, 1.0, 3),
)


# --------------------------------------------------------------------------- terms


def vertex_operator(vertices_h: np.ndarray) -> sp.csr_matrix:
    """The map ``X (4V, 3) -> deformed vertices (V, 3)``: row ``i`` holds ``ṽ_iᵀ``.

    Parameters
    ----------
    vertices_h : (V, 4) float ndarray
        Homogeneous template vertices ``(v_i - c, 1)``.

    Returns
    -------
    (V, 4V) scipy.sparse.csr_matrix
    """
    V = len(vertices_h)
    rows = np.repeat(np.arange(V), 4)
    cols = (4 * np.arange(V)[:, None] + np.arange(4)).ravel()
    return sp.csr_matrix((vertices_h.ravel(), (rows, cols)), shape=(V, 4 * V))


def deformed_vertices(X: np.ndarray, vertices_h: np.ndarray) -> np.ndarray:
    """Deformed vertices ``T_i ṽ_i`` ``(V, 3)`` of the affine field ``X (4V, 3)``."""
    return np.einsum("vk,vkc->vc", vertices_h, X.reshape(-1, 4, 3))


def smoothness_term(n_vertices: int, faces: np.ndarray) -> sp.csr_matrix:
    """``E_s = ‖S X‖²``: the differences ``T_i - T_j`` of the affines over the mesh edges.

    Parameters
    ----------
    n_vertices : int
    faces : (T, 3) int ndarray

    Returns
    -------
    (4E, 4V) scipy.sparse.csr_matrix
        Edge-vertex incidence (``+1`` at ``i``, ``-1`` at ``j``) times ``I_4``.
    """
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    E = len(e)
    D = sp.csr_matrix((np.r_[np.ones(E), -np.ones(E)], (np.r_[np.arange(E), np.arange(E)],
                                                         np.r_[e[:, 0], e[:, 1]])),
                      shape=(E, n_vertices))  # fmt: skip
    return sp.kron(D, sp.identity(4), format="csr")


def data_term(vertices_h: np.ndarray, faces: np.ndarray, triangle: np.ndarray,
              barycentric: np.ndarray) -> sp.csr_matrix:
    """``E_d = ‖D X - (y - h n)‖²``: the markers' closest points on the deformed template.

    Parameters
    ----------
    vertices_h : (V, 4) float ndarray
    faces : (T, 3) int ndarray
    triangle : (M,) int ndarray
        Template triangle closest to each marker (on the current deformation).
    barycentric : (M, 3) float ndarray
        The closest point's weights of the triangle's corners.

    Returns
    -------
    (M, 4V) scipy.sparse.csr_matrix
    """
    M, V = len(triangle), len(vertices_h)
    rows = np.repeat(np.arange(M), 3)
    B = sp.csr_matrix((barycentric.ravel(), (rows, faces[triangle].ravel())), shape=(M, V))
    return (B @ vertex_operator(vertices_h)).tocsr()


def landmark_term(vertices_h: np.ndarray, landmark_vertices: np.ndarray) -> sp.csr_matrix:
    """``E_m = ‖L X - (y_l - h n_l)‖²``: landmark vertices ``T_v ṽ_v`` onto their markers.

    Parameters
    ----------
    vertices_h : (V, 4) float ndarray
    landmark_vertices : (L,) int ndarray

    Returns
    -------
    (L, 4V) scipy.sparse.csr_matrix
    """
    return vertex_operator(vertices_h)[np.asarray(landmark_vertices, dtype=np.int64)]


# --------------------------------------------------------------------------- solver


def _unit_normals_at(P: np.ndarray, faces: np.ndarray, triangle: np.ndarray,
                     barycentric: np.ndarray) -> np.ndarray:
    n = np.einsum("mc,mci->mi", barycentric, vertex_normals(P, faces)[faces[triangle]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def affine_registration(
    vertices: np.ndarray,
    faces: np.ndarray,
    targets: np.ndarray,
    *,
    landmarks: dict[int, int] | None = None,
    marker_offset: float = 0.0,
    schedule: tuple[tuple[float, float, float, int], ...] = DEFAULT_SCHEDULE,
    trim: float = 3.0,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Fit a template to markers with a smooth per-vertex affine field (Allen et al. 2003).

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        Template, already roughly aligned with the markers (same pose, unit and
        placement; e.g. by a global affine ICP).
    faces : (T, 3) int ndarray
        Triangles, wound outward.
    targets : (M, 3) float ndarray
        Marker positions (metres).
    landmarks : dict, optional
        ``{marker index: template vertex index}``.
    marker_offset : float
        Marker height ``h``: markers sit this far (m) outside the skin.
    schedule : tuple of (float, float, float, int)
        Stages ``(γ landmark, β smoothness, α data, iterations)``, coarse to fine.
        Weights are per landmark / edge / marker.
    trim : float
        Markers whose closest template point is farther than ``trim`` × the median
        distance (and more than 5 cm) are left out of that iteration's data term
        (outliers, or a marker over a part the template lacks).

    Returns
    -------
    vertices : (V, 3) float ndarray
        Fitted template.
    info : dict
        ``iterations``, per stage the marker-to-surface RMS (mm, marker height
        removed), ``landmark_rms_mm``.

    Raises
    ------
    DeformError
        Empty input, landmarks out of range, or a schedule whose first stage has
        neither landmarks nor data to pull on.
    """
    V0 = np.asarray(vertices, dtype=np.float64)
    Y = np.asarray(targets, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if len(V0) == 0 or len(faces) == 0 or len(Y) == 0:
        raise DeformError("registration: empty template or no markers")
    lm = dict(landmarks or {})
    lm_m = np.array(sorted(lm), dtype=np.int64)
    lm_v = np.array([lm[k] for k in lm_m], dtype=np.int64)
    if lm_m.size and (lm_v.min() < 0 or lm_v.max() >= len(V0) or lm_m.min() < 0
                      or lm_m.max() >= len(Y)):  # fmt: skip
        raise DeformError("registration: landmark indices out of range of the markers or template")
    if not lm_m.size:  # without landmarks the stages that rely on them only keep the field
        schedule = tuple(s for s in schedule if s[2] > 0)
        if not schedule:
            raise DeformError("registration: no landmarks and no data term in the schedule")
    nV = len(V0)
    c = V0.mean(0)
    vh = np.concatenate([V0 - c, np.ones((nV, 1))], axis=1)
    X = np.tile(np.vstack([np.eye(3), np.zeros((1, 3))]), (nV, 1))  # identity affines
    S = smoothness_term(nV, faces)
    StS = (S.T @ S).tocsr()
    Lop = landmark_term(vh, lm_v) if lm_m.size else None
    LtL = (Lop.T @ Lop).tocsr() if Lop is not None else None
    eps = 1e-9 * sp.identity(4 * nV, format="csr")
    history = []
    for gamma, beta, alpha, n_iter in schedule:
        for _ in range(n_iter):
            P = deformed_vertices(X, vh) + c
            N = beta * StS + eps
            rhs = eps @ X
            if alpha > 0:
                tri, bary, dist = closest_points_on_triangles(Y, P, faces)
                n = _unit_normals_at(P, faces, tri, bary)
                tgt = Y - marker_offset * n
                d = np.linalg.norm(tgt - np.einsum("mc,mci->mi", bary, P[faces[tri]]), axis=1)
                w = (d <= max(trim * float(np.median(d)), 0.05)).astype(float)
                Dop = data_term(vh, faces, tri, bary)
                Dw = sp.diags(alpha * w) @ Dop
                N = N + Dop.T @ Dw
                rhs = rhs + Dw.T @ (tgt - c)
            if Lop is not None and gamma > 0:
                nl = vertex_normals(P, faces)[lm_v]
                nl /= np.maximum(np.linalg.norm(nl, axis=1, keepdims=True), 1e-12)
                N = N + gamma * LtL
                rhs = rhs + gamma * (Lop.T @ (Y[lm_m] - marker_offset * nl - c))
            X = splu(N.tocsc()).solve(np.asarray(rhs))
        P = deformed_vertices(X, vh) + c
        history.append(_marker_rms_mm(Y, P, faces, marker_offset))
    P = deformed_vertices(X, vh) + c
    info: dict[str, Any] = {"stage_marker_rms_mm": history,
                            "marker_rms_mm": history[-1] if history else float("nan")}
    if lm_m.size:
        nl = vertex_normals(P, faces)[lm_v]
        nl /= np.maximum(np.linalg.norm(nl, axis=1, keepdims=True), 1e-12)
        res = np.linalg.norm(P[lm_v] + marker_offset * nl - Y[lm_m], axis=1)
        info["landmark_rms_mm"] = float(np.sqrt(np.mean(res**2)) * 1000)
    return P, info


def _marker_rms_mm(Y: np.ndarray, P: np.ndarray, faces: np.ndarray, offset: float) -> float:
    tri, bary, _ = closest_points_on_triangles(Y, P, faces)
    n = _unit_normals_at(P, faces, tri, bary)
    pt = np.einsum("mc,mci->mi", bary, P[faces[tri]]) + offset * n
    return float(np.sqrt(np.mean(np.sum((Y - pt) ** 2, 1))) * 1000)


# --------------------------------------------------------------------------- landmarks


def anatomical_landmarks(
    markers: np.ndarray,
    marker_joint: list[str],
    marker_skeleton: dict[str, tuple[np.ndarray, np.ndarray]],
    vertices: np.ndarray,
    vertex_joint: list[str],
    template_skeleton: dict[str, tuple[np.ndarray, np.ndarray]],
    *,
    forward: tuple[float, float, float] = (0.0, 0.0, 1.0),
    max_landmarks: int | None = 60,
) -> dict[int, int]:
    """Landmarks from anatomical placement: the same place on the same bone of both bodies.

    A marker on bone ``j`` (from joint ``a`` to joint ``b``) is placed by its
    fraction ``u`` along the bone and its direction ``θ`` around it (measured from
    ``forward`` projected off the bone); its landmark vertex is the template
    vertex on the same bone with the nearest ``(u, θ)`` (distance
    ``|Δu| L + r |Δθ|`` with ``L`` the template bone's length, ``r`` the vertex's
    distance to it).

    Parameters
    ----------
    markers : (M, 3) float ndarray
        Marker positions in the reference pose.
    marker_joint : list of str
        ``M`` bone (joint) names, each marker's dominant joint (the simulator's
        ``truth["part"]`` named by ``part_names``).
    marker_skeleton, template_skeleton : dict
        ``{joint name: (start (3,), end (3,))}`` bone axes of the markers' body
        and of the template in the same pose (joints without a bone are skipped).
    vertices : (V, 3) float ndarray
        Template vertices.
    vertex_joint : list of str
        ``V`` dominant joint names of the template vertices.
    forward : tuple of 3 float
        Facing direction of both bodies.
    max_landmarks : int, optional
        Keep at most this many, spread over the bones (most central of each bone first).

    Returns
    -------
    dict
        ``{marker index: vertex index}``.
    """
    Y = np.asarray(markers, dtype=np.float64)
    Vt = np.asarray(vertices, dtype=np.float64)
    mj = np.asarray(marker_joint, dtype=object)
    vj = np.asarray(vertex_joint, dtype=object)
    out: dict[int, int] = {}
    per_bone: list[list[tuple[float, int, int]]] = []
    for name in sorted(set(marker_skeleton) & set(template_skeleton)):
        mi = np.flatnonzero(mj == name)
        vi = np.flatnonzero(vj == name)
        if not mi.size or not vi.size:
            continue
        fwd = np.asarray(forward, dtype=np.float64)
        um, tm, _ = _bone_coordinates(Y[mi], *marker_skeleton[name], fwd)
        uv, tv, rv = _bone_coordinates(Vt[vi], *template_skeleton[name], fwd)
        L = float(np.linalg.norm(np.subtract(*template_skeleton[name][::-1])))
        dth = np.abs(np.angle(np.exp(1j * (tm[:, None] - tv[None, :]))))
        cost = np.abs(um[:, None] - uv[None, :]) * L + rv[None, :] * dth
        best = np.argmin(cost, axis=1)
        inside = (um > 0.1) & (um < 0.9)  # away from the joints, where parts blend
        per_bone.append(sorted((abs(float(um[k]) - 0.5), int(mi[k]), int(vi[best[k]]))
                               for k in np.flatnonzero(inside)))  # fmt: skip
    rank = 0
    while per_bone and (max_landmarks is None or len(out) < max_landmarks):
        progressed = False
        for lst in per_bone:
            if rank < len(lst) and (max_landmarks is None or len(out) < max_landmarks):
                out[lst[rank][1]] = lst[rank][2]
                progressed = True
        if not progressed:
            break
        rank += 1
    return out


def _bone_coordinates(P: np.ndarray, a: np.ndarray, b: np.ndarray,
                      forward: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(u, θ, r)`` of points about the bone ``a -> b``: fraction along it, angle around
    it from ``forward``, distance from its axis."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ax = b - a
    L = max(float(np.linalg.norm(ax)), 1e-9)
    ax = ax / L
    ref = np.asarray(forward, float) - ax * float(np.dot(forward, ax))
    if np.linalg.norm(ref) < 1e-6:  # bone along forward (feet): use up instead
        ref = np.array([0.0, 1.0, 0.0]) - ax * ax[1]
    ref /= np.linalg.norm(ref)
    side = np.cross(ax, ref)
    d = P - a
    u = d @ ax / L
    radial = d - np.outer(d @ ax, ax)
    return u, np.arctan2(radial @ side, radial @ ref), np.linalg.norm(radial, axis=1)
