"""Fitting a detailed mesh to the marker surface (Park & Hodgins 2006 §5.3; Allen et al. 2003).

The deformation (:mod:`mocapflow.stages.skin.deform`) moves the vertices of a detailed
mesh bound to the marker surface; this module makes that mesh fit the subject:
a template (the procedural body or a user mesh, stage ``template_mesh``) is
brought onto the marker surface of the reference pose (stage ``fit_mesh``,
:func:`fit_detailed_mesh`): an initial guess from landmarks or bounding boxes
(:func:`_initial_alignment`), iterated closest-point similarity / affine
alignment (:func:`_icp_alignment`), then a non-rigid, Laplacian-regularised fit
to the markers (:func:`_nonrigid_fit`).
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from mocapflow.pipeline import Context, FilePath, stage
from mocapflow.stages.motion.absolute_orientation import absolute_orientation
from mocapflow.stages.motion.axes import frame_basis
from mocapflow.stages.motion.datatypes import Mesh, Motion
from mocapflow.stages.motion.geometry import mesh_laplacian, vertex_normals
from mocapflow.stages.motion.rotations import quat_from_axis_angle, quat_identity
from mocapflow.stages.motion.simulate.body import Body, skin, skinning_transforms
from mocapflow.stages.motion.simulate.capsules import procedural_body
from mocapflow.stages.motion.simulate.makehuman import load_makehuman_body
from mocapflow.stages.motion.simulate.markers import find_joint
from mocapflow.stages.motion.simulate.skeleton import procedural_skeleton
from mocapflow.stages.skin import limb_pose
from mocapflow.stages.skin.binding import DeformError, closest_points_on_triangles
from mocapflow.stages.skin.marker_regions import body_facing, marker_region, region_vertices
from mocapflow.stages.skin.registration import DEFAULT_SCHEDULE, affine_registration
from mocapflow.stages.skin.segmentation import Segmentation

__all__ = [
    "fit_detailed_mesh",
    "fit_mesh",
    "mesh_laplacian",
    "similarity_transform",
    "template_mesh",
    "upright_fit",
]


# --------------------------------------------------------------------------- detailed mesh fitting

#: ``fit_mesh`` refuses an alignment whose axis scales (singular values of the affine
#: map) are more than this many times apart: a template squashed onto markers that
#: are not on a body like it (a flat sheet of markers: 0 along its normal), which
#: the distance test alone can pass (the sheet's p90 114.7 mm under its 116 mm
#: spacing with the evened-out 1,500-vertex template).
MAX_AXIS_SCALE_RATIO = 3.0


def similarity_transform(
    source: np.ndarray, target: np.ndarray, *, weights: np.ndarray | None = None
) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``target ≈ s R source + t`` (Umeyama 1991).

    Parameters
    ----------
    source, target : (N, 3) float ndarray
    weights : (N,) float ndarray, optional

    Returns
    -------
    s : float
    R : (3, 3) float ndarray
        Proper rotation.
    t : (3,) float ndarray
    """
    w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    ms, mt = w @ source, w @ target
    S, T = source - ms, target - mt
    C = (w[:, None] * T).T @ S
    U, sv, Vt = np.linalg.svd(C)
    E = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ E @ Vt
    var = float(w @ np.sum(S**2, 1))
    s = float(np.sum(sv * np.diag(E)) / var) if var > 0 else 1.0
    return s, R, mt - s * R @ ms


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of a triangle mesh (> 0 when the faces wind outward)."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _marker_correspondences(Y: np.ndarray, X: np.ndarray, faces: np.ndarray, offset: float):
    """Closest skin point of each marker, pushed ``offset`` along the skin normal.

    Returns ``(triangle, barycentric, point, distance)`` with ``point`` where the
    marker should be and ``distance = |Y - point|``.
    """
    tri, bary, _ = closest_points_on_triangles(Y, X, faces)
    pt = np.einsum("mc,mci->mi", bary, X[faces[tri]])
    if offset:
        n = np.einsum("mc,mci->mi", bary, vertex_normals(X, faces)[faces[tri]])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        pt = pt + offset * n
    return tri, bary, pt, np.linalg.norm(Y - pt, axis=1)


_Group = tuple[str, np.ndarray, np.ndarray, np.ndarray]


def _region_groups(marker_regions: list[str | None] | None,
                   region_masks: dict[str, np.ndarray] | None,
                   faces: np.ndarray) -> list[_Group]:  # fmt: skip
    """``[(region, markers (k,), faces (n,), vertices (v,))]`` per region of
    ``region_masks`` that ``marker_regions`` names: the named markers, the faces with a
    corner in the region and the region's vertices (indices)."""
    if not marker_regions or not region_masks:
        return []
    names = np.array([r or "" for r in marker_regions], dtype=object)
    out = []
    for region, mask in region_masks.items():
        mi = np.flatnonzero(names == region)
        fi = np.flatnonzero(mask[faces].any(1))
        if len(mi) and len(fi):
            out.append((region, mi, fi, np.flatnonzero(mask)))
    return out


def _region_correspondences(Y: np.ndarray, X: np.ndarray, faces: np.ndarray, offset: float,
                            groups: list[_Group]):
    """:func:`_marker_correspondences`, each marker of ``groups`` (:func:`_region_groups`)
    on its region's faces only, the others on the whole mesh."""
    if not groups:
        return _marker_correspondences(Y, X, faces, offset)
    tri, dist = np.zeros(len(Y), np.int64), np.zeros(len(Y))
    bary, pt = np.zeros((len(Y), 3)), np.zeros((len(Y), 3))
    named = np.concatenate([mi for _, mi, _, _ in groups])
    rest = np.setdiff1d(np.arange(len(Y)), named)
    for mi, fi in [(rest, None), *((mi, fi) for _, mi, fi, _ in groups)]:
        if len(mi):
            t, b, p, d = _marker_correspondences(Y[mi], X, faces if fi is None else faces[fi],
                                                 offset)  # fmt: skip
            tri[mi], bary[mi], pt[mi], dist[mi] = t if fi is None else fi[t], b, p, d
    return tri, bary, pt, dist


def _barycentric_matrix(tri: np.ndarray, bary: np.ndarray, faces: np.ndarray, V: int):
    rows = np.repeat(np.arange(len(tri)), 3)
    return sp.csr_matrix((bary.ravel(), (rows, faces[tri].ravel())), shape=(len(tri), V))


def fit_detailed_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    targets: np.ndarray,
    *,
    landmarks: dict[int, int] | None = None,
    stiffness: tuple[float, ...] = (30.0, 10.0, 3.0, 1.0),
    rigid_iterations: int = 20,
    marker_offset: float = 0.0,
    allow_scale: bool = True,
    trim: float = 0.1,
    method: Literal["allen", "icp"] = "allen",
    schedule: tuple[tuple[float, float, float, int], ...] = DEFAULT_SCHEDULE,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Fit a template mesh to marker positions: affine ICP, then a non-rigid fit.

    ``method="allen"`` (default): after the alignment, the per-vertex affine field
    of Allen et al. (2003), :func:`~mocapflow.stages.skin.registration.affine_registration`
    (data, smoothness and landmark terms, coarse to fine by ``schedule``).
    ``method="icp"`` (the earlier fit, kept as a baseline): the Laplacian
    displacement below.

    An Allen et al. (2003)-style optimisation reduced to displacements: the
    template is first aligned by an iterated affine transform (bounding-box
    initialisation; markers to their closest template points pushed out by
    ``marker_offset``, the worst ``trim`` fraction ignored; rigid when
    ``allow_scale`` is false), then a
    displacement field ``U`` of its vertices minimises
    ``sum_m |B_m (V0 + U) - y_m|^2 + λ |L U|^2`` (``B_m`` the barycentric
    coordinates of marker ``m``'s closest point, ``L`` the mesh Laplacian, so
    ``|L U|^2`` is a bending energy of the displacement that keeps the template's
    detail), with decreasing stiffness ``λ`` and correspondences recomputed
    between steps.  Landmarks (marker -> vertex) replace the closest point of
    their markers in both stages.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        Template in any placement of similar pose (same up axis and facing).
    faces : (T, 3) int ndarray
    targets : (M, 3) float ndarray
        Marker reference positions (metres).
    landmarks : dict, optional
        ``{marker index: template vertex index}``.
    stiffness : tuple of float
        Schedule of ``λ`` (relative to the number of markers per vertex).
    rigid_iterations : int
    marker_offset : float
        Markers sit this far (m) outside the skin along its normal.
    allow_scale : bool
        Let the alignment scale the template (unit mismatch, body size and
        proportions: an affine map).
    trim : float
        Fraction of worst correspondences ignored in the alignment.
    method : {"allen", "icp"}
        Non-rigid fit: per-vertex affine field, or Laplacian displacement.
    schedule : tuple of (float, float, float, int)
        ``method="allen"``: stages ``(landmark, smoothness, data weight, iterations)``.

    Returns
    -------
    vertices : (V, 3) float ndarray
        Fitted template.
    info : dict
        ``scale`` (geometric mean of ``axis_scales``), ``rotation_deg``,
        marker-to-surface RMS/median distances (mm, offset removed) after
        alignment and after fitting.
    """
    V0 = np.asarray(vertices, dtype=np.float64)
    Y = np.asarray(targets, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    nV, M = len(V0), len(Y)
    lm_m, lm_v = _landmark_indices(landmarks, nV, M)
    A_tot, t_tot = _initial_alignment(V0, Y, lm_m, lm_v, allow_scale=allow_scale)
    X = V0 @ A_tot.T + t_tot
    outward = 1.0 if _signed_volume(V0, faces) >= 0 else -1.0
    phases = ["similarity", "affine"] if allow_scale and M >= 12 else ["rigid"]
    X, A_tot, t_tot = _icp_alignment(X, Y, faces, A_tot, t_tot, lm_m, lm_v, phases=phases,
                                     iterations=rigid_iterations, trim=trim,
                                     offset=marker_offset * outward)
    U_, sv, Vt_ = np.linalg.svd(A_tot)
    R_tot = U_ @ Vt_
    S_tot = float(np.prod(sv) ** (1 / 3))
    dist = _marker_correspondences(Y, X, faces, marker_offset * outward)[3]
    aligned = {"rms_mm": float(np.sqrt(np.mean(dist**2)) * 1000),
               "median_mm": float(np.median(dist) * 1000),
               "p90_mm": float(np.percentile(dist, 90) * 1000)}  # fmt: skip
    if method == "allen":
        wound = faces if outward > 0 else faces[:, [0, 2, 1]]  # normals outward for the offset
        out, _ = affine_registration(X, wound, Y, landmarks=dict(zip(lm_m.tolist(),
                                     lm_v.tolist())), marker_offset=marker_offset,
                                     schedule=schedule)  # fmt: skip
    elif method == "icp":
        out = _nonrigid_fit(X, Y, faces, lm_m, lm_v, stiffness=stiffness,
                            marker_offset=marker_offset, outward=outward)
    else:
        raise DeformError(f"fit_mesh: unknown method {method!r} (allen, icp)")
    dist = _marker_correspondences(Y, out, faces, marker_offset * outward)[3]
    info = {
        "scale": S_tot,
        "axis_scales": [float(v) for v in sv],
        "rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(R_tot) - 1) / 2, -1, 1)))),
        "translation_m": [float(v) for v in t_tot],
        "aligned": aligned,
        "fitted": {"rms_mm": float(np.sqrt(np.mean(dist**2)) * 1000),
                   "median_mm": float(np.median(dist) * 1000),
                   "max_mm": float(dist.max() * 1000)},
    }  # fmt: skip
    return out, info


def _landmark_indices(landmarks: dict[int, int] | None, n_vertices: int,
                      n_markers: int) -> tuple[np.ndarray, np.ndarray]:
    """``(markers, vertices)`` of the landmarks, ``(L,)`` each, sorted by marker."""
    lm = dict(landmarks or {})
    lm_m = np.array(sorted(lm), dtype=np.int64)
    lm_v = np.array([lm[k] for k in lm_m], dtype=np.int64)
    if lm_m.size and (lm_v.min() < 0 or lm_v.max() >= n_vertices or lm_m.max() >= n_markers):
        raise DeformError("fit_mesh: landmark indices out of range of the markers or template")
    return lm_m, lm_v


def _initial_alignment(V0: np.ndarray, Y: np.ndarray, lm_m: np.ndarray, lm_v: np.ndarray, *,
                       allow_scale: bool) -> tuple[np.ndarray, np.ndarray]:
    """Initial guess ``(A (3, 3), t (3,))`` of ``Y ≈ A V0 + t``: the similarity of 3+
    landmarks, else bounding boxes (scale), else centroids."""
    if lm_m.size >= 3:
        s, R, t = similarity_transform(V0[lm_v], Y[lm_m])
        return (s if allow_scale else 1.0) * R, t
    if allow_scale:  # bounding boxes: the markers span the body even where they are sparse
        lo_v, hi_v, lo_y, hi_y = V0.min(0), V0.max(0), Y.min(0), Y.max(0)
        ratios = (hi_y - lo_y) / np.maximum(hi_v - lo_v, 1e-12)
        A_tot = np.eye(3) * float(np.median(ratios))  # robust to markerless fingers / soles
        return A_tot, (lo_y + hi_y) / 2 - A_tot @ (lo_v + hi_v) / 2
    return np.eye(3), Y.mean(0) - V0.mean(0)


def _icp_alignment(
    X: np.ndarray, Y: np.ndarray, faces: np.ndarray, A_tot: np.ndarray, t_tot: np.ndarray,
    lm_m: np.ndarray, lm_v: np.ndarray, *, phases: list[str], iterations: int, trim: float,
    offset: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Iterated closest-point alignment, phase by phase (similarity first, robust; then
    affine, proportions; or rigid), the worst ``trim`` of the correspondences ignored.

    A phase is kept only if it fits better than the ones before; returns the
    aligned vertices ``(V, 3)`` and the accumulated ``A (3, 3)``, ``t (3,)``.
    """
    M = len(Y)
    best: tuple[float, np.ndarray, np.ndarray, np.ndarray] | None = None
    for phase in phases:  # ICP: similarity first (robust), then affine (proportions)
        for _ in range(iterations):
            tri, bary, src, dist = _marker_correspondences(Y, X, faces, offset)
            w = (dist <= np.quantile(dist, 1 - trim)).astype(float)
            if lm_m.size:
                src[lm_m] = X[lm_v]
                w[lm_m] = 1.0
            if phase == "affine":
                H = np.concatenate([src, np.ones((M, 1))], axis=1) * np.sqrt(w)[:, None]
                T, *_ = np.linalg.lstsq(H, Y * np.sqrt(w)[:, None], rcond=None)  # (4, 3)
                A, t = T[:3].T, T[3]
            elif phase == "similarity":
                sc, A, t = similarity_transform(src, Y, weights=w)
                A = sc * A
            else:
                A, t = absolute_orientation(src, Y, weights=w)
            X_new = X @ A.T + t
            step = float(np.abs(X_new - X).max())
            X = X_new
            A_tot, t_tot = A @ A_tot, A @ t_tot + t
            if step < 1e-7:
                break
        d_phase = _marker_correspondences(Y, X, faces, offset)[3]
        score = float(np.mean(np.sort(d_phase)[: max(1, int(len(d_phase) * (1 - trim)))] ** 2))
        if best is None or score < best[0]:  # keep a phase only if it fits better
            best = (score, X.copy(), A_tot.copy(), t_tot.copy())
    _, X, A_tot, t_tot = best
    return X, A_tot, t_tot


def _nonrigid_fit(X: np.ndarray, Y: np.ndarray, faces: np.ndarray, lm_m: np.ndarray,
                  lm_v: np.ndarray, *, stiffness: tuple[float, ...], marker_offset: float,
                  outward: float) -> np.ndarray:
    """The displacement field ``U`` minimising ``Σ_m |B_m (X + U) - y_m|² + λ |L U|²`` for
    each stiffness ``λ`` in turn, correspondences recomputed between steps; returns
    ``X + U``."""
    nV, M = len(X), len(Y)
    L = mesh_laplacian(nV, faces)
    LtL = (L.T @ L).tocsr()
    ratio = nV / max(M, 1)
    U = np.zeros_like(X)
    for lam in stiffness:
        tri, bary, _, _ = _marker_correspondences(Y, X + U, faces, 0.0)
        B = _barycentric_matrix(tri, bary, faces, nV)
        tgt = Y.copy()
        if marker_offset:
            n = np.einsum("mc,mci->mi", bary, vertex_normals(X + U, faces)[faces[tri]])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            tgt = tgt - marker_offset * outward * n
        if lm_m.size:
            B = B.tolil()
            for m, v in zip(lm_m, lm_v):
                B.rows[m], B.data[m] = [int(v)], [1.0]
            B = B.tocsr()
        Amat = (lam * ratio * LtL + B.T @ B + 1e-8 * sp.identity(nV)).tocsc()
        rhs = B.T @ (tgt - B @ X)
        U = splu(Amat).solve(np.asarray(rhs))
    return X + U


def _upright_step(src: np.ndarray, Y: np.ndarray, w: np.ndarray, up: np.ndarray,
                  scale_range: tuple[float, float], *,
                  turn: tuple[float, float] = (-np.pi, np.pi),
                  ) -> tuple[np.ndarray, np.ndarray, float]:  # fmt: skip
    """Weighted ``Y ≈ s R src + t`` with ``R`` a turn about ``up`` by an angle clipped to
    ``turn`` (radians) and ``s`` clipped to ``scale_range``: returns ``A = s R (3, 3)``,
    ``t (3,)`` and the angle."""
    w = w / w.sum()
    ms, mt = w @ src, w @ Y
    S, T = src - ms, Y - mt
    Sh, Th = S - np.outer(S @ up, up), T - np.outer(T @ up, up)  # horizontal parts
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    a = np.sum(w * ((Sh @ e1) * (Th @ e1) + (Sh @ e2) * (Th @ e2)))
    b = np.sum(w * ((Sh @ e1) * (Th @ e2) - (Sh @ e2) * (Th @ e1)))
    theta = float(np.clip(np.arctan2(b, a), *turn))
    K = np.array([[0, -up[2], up[1]], [up[2], 0, -up[0]], [-up[1], up[0], 0]])
    R = np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K  # Rodrigues about up
    RS = S @ R.T
    var = float(np.sum(w * np.sum(S**2, 1)))
    s = float(np.sum(w * np.sum(RS * T, 1)) / var) if var > 0 else 1.0
    s = float(np.clip(s, *scale_range))
    return s * R, mt - s * R @ ms, theta


#: Most the upright fit turns the template away from the body's facing read from its
#: named front and back markers (:func:`~mocapflow.stages.skin.marker_regions.body_facing`).
FACING_TURN = float(np.radians(15.0))


def upright_fit(
    vertices: np.ndarray,
    faces: np.ndarray,
    targets: np.ndarray,
    up: np.ndarray,
    *,
    marker_offset: float = 0.0,
    trim: float = 0.25,
    iterations: int = 15,
    scale_range: tuple[float, float] | None = None,
    marker_regions: list[str | None] | None = None,
    region_masks: dict[str, np.ndarray] | None = None,
    facing: np.ndarray | None = None,
    forward: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Fit a body template to sparse markers keeping it upright: scale, turn, shift.

    Sparse or partial marker sets (a clinical set, one arm and the trunk) cannot
    constrain an affine map or a non-rigid fit (the template shears, tips over or
    swells to the markers' bounding box); a body stands along the capture's up
    axis, so only a uniform scale (within ``scale_range`` of the template's,
    which is in metres), a turn about ``up`` and a shift are fitted, by trimmed
    iterated closest points from 12 starts (4 headings x the markers' top, middle
    or bottom at the template's; a fourth height with ``marker_regions``, one heading
    with ``facing``), the best kept.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        Template in the capture's axes (its long axis along ``up``), metres.
    faces : (T, 3) int ndarray
    targets : (M, 3) float ndarray
        Marker reference positions (metres).
    up : (3,) float ndarray
        Unit up vector of the capture.
    marker_offset : float
        Markers sit this far (m) outside the skin.
    trim : float
        Fraction of the worst correspondences ignored (markers off the template's
        pose, e.g. arms down against a T-pose).
    iterations : int
        Closest-point iterations per start.
    scale_range : tuple of float, optional
        Allowed uniform scale; default from the markers' extent ``h`` along ``up``
        and the template's height ``H``: ``[max(0.8, h/H), max(1.05, 1.1 h/H)]``
        (the body holds the markers; a partial set -- trunk and arm -- keeps about
        the template's adult size: sparse markers inside a T-pose otherwise pull
        the scale up, measured 1.4 on the Qualisys capture).
    marker_regions : list of (str or None), optional
        ``M`` body regions the markers' labels name
        (:func:`~mocapflow.stages.skin.marker_regions.marker_region`), with
        ``region_masks`` (``{region: (V,) bool}``,
        :func:`~mocapflow.stages.skin.marker_regions.region_vertices`): a named marker is
        matched to the skin of its region only, and a 13th start per heading puts the
        named markers' mean height at their regions'.  Without them a partial set can
        settle on the wrong part of the body: pyomeca's seated trunk-and-arm capture
        had the standing template's legs laid through its trunk markers.
    facing, forward : (3,) float ndarray, optional
        The horizontal direction the body faces (from its named front and back
        markers, :func:`~mocapflow.stages.skin.marker_regions.body_facing`) and the
        template's own forward in ``vertices``' axes: with both, the template is
        turned to face it, then turned at most :data:`FACING_TURN` from it (one heading
        instead of four): the closest points alone turned it 121 degrees away on the
        Qualisys capture (its left ASIS marker on the template's right thigh).

    Returns
    -------
    vertices : (V, 3) float ndarray
        The fitted template.
    info : dict
        As :func:`fit_detailed_mesh`'s (``scale``, ``rotation_deg``, ``aligned``,
        ``fitted``), plus ``method="upright"`` and ``trimmed_rms_mm`` (the RMS distance
        of the best ``1 - trim`` of the markers, which the fit minimises).
    """
    V0 = np.asarray(vertices, dtype=np.float64)
    Y = np.asarray(targets, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    offset = marker_offset * (1.0 if _signed_volume(V0, faces) >= 0 else -1.0)
    hv, hy = V0 @ up, Y @ up
    if scale_range is None:
        r = float(np.ptp(hy) / max(np.ptp(hv), 1e-12))
        scale_range = (min(max(0.8, r), 1.3), min(max(1.05, 1.1 * r), 1.4))
    groups = _region_groups(marker_regions, region_masks, faces)
    heights = {"top": (hv.max(), hy.max()), "middle": ((hv.max() + hv.min()) / 2,
               (hy.max() + hy.min()) / 2), "bottom": (hv.min(), hy.min())}  # fmt: skip
    if groups:  # the named markers' mean height at their regions' mean height
        named = np.concatenate([mi for _, mi, _, _ in groups])
        region_height = np.concatenate([np.full(len(mi), hv[vi].mean())
                                        for _, mi, _, vi in groups])  # fmt: skip
        heights["named"] = (region_height.mean(), hy[named].mean())
    best = None
    K = np.array([[0, -up[2], up[1]], [up[2], 0, -up[0]], [-up[1], up[0], 0]])
    fixed = facing is not None and forward is not None
    if fixed:  # the turn about up taking the template's forward to the body's facing
        f0 = np.asarray(forward, dtype=np.float64) - (np.asarray(forward) @ up) * up
        f1 = np.asarray(facing, dtype=np.float64) - (np.asarray(facing) @ up) * up
        start = float(np.arctan2(np.cross(f0, f1) @ up, f0 @ f1))
    for heading in range(1 if fixed else 4):
        ang = start if fixed else heading * np.pi / 2
        R0 = np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K
        for c_v, c_y in heights.values():
            mv, my = V0.mean(0) - (V0.mean(0) @ up) * up, Y.mean(0) - (Y.mean(0) @ up) * up
            A, t = R0, my - R0 @ mv + (c_y - c_v) * up
            turned = 0.0  # from the start (with a facing, within FACING_TURN)
            for _ in range(iterations):
                X = V0 @ A.T + t
                _, _, src, dist = _region_correspondences(Y, X, faces, offset, groups)
                w = (dist <= np.quantile(dist, 1 - trim)).astype(float)
                bounds = ((-FACING_TURN - turned, FACING_TURN - turned) if fixed else
                          (-np.pi, np.pi))  # fmt: skip
                A_s, t_s, theta = _upright_step(src, Y, w, up, (0.5, 2.0), turn=bounds)
                turned += theta
                A_new, t_new = A_s @ A, A_s @ t + t_s
                s_new = float(np.cbrt(abs(np.linalg.det(A_new))))
                if not scale_range[0] <= s_new <= scale_range[1]:  # hold the scale in range
                    A_new = A_new * (np.clip(s_new, *scale_range) / s_new)
                step = float(np.abs((V0 @ A_new.T + t_new) - X).max())
                A, t = A_new, t_new
                if step < 1e-6:
                    break
            dist = _region_correspondences(Y, V0 @ A.T + t, faces, offset, groups)[3]
            score = float(np.mean(np.sort(dist)[: max(1, int(len(dist) * (1 - trim)))] ** 2))
            if best is None or score < best[0]:
                best = (score, A, t)
    score, A, t = best
    out = V0 @ A.T + t
    dist = _region_correspondences(Y, out, faces, offset, groups)[3]
    s = float(np.cbrt(abs(np.linalg.det(A))))
    R = A / s
    stats = {"rms_mm": float(np.sqrt(np.mean(dist**2)) * 1000),
             "median_mm": float(np.median(dist) * 1000),
             "p90_mm": float(np.percentile(dist, 90) * 1000),
             "max_mm": float(dist.max() * 1000)}  # fmt: skip
    info = {
        "method": "upright",
        "named_markers": {region: int(len(mi)) for region, mi, _, _ in groups},
        "facing": None if not fixed else [float(v) for v in facing],
        "scale": s,
        "axis_scales": [s, s, s],
        "rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))),
        "translation_m": [float(v) for v in t],
        "aligned": stats,
        "fitted": stats,
        "trimmed_rms_mm": float(np.sqrt(score) * 1000),
    }
    return out, info


#: Rounds of turning the limbs and fitting again at most, and the largest turn (degrees)
#: after which they stop.
POSE_PASSES = 4
POSE_SETTLED = 2.0


def _affine_between(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(A (3, 3), t (3,))`` with ``b = a @ A.T + t`` (least squares; exact for the
    upright fit's scale, turn and shift)."""
    X = np.hstack([a, np.ones((len(a), 1))])
    M = np.linalg.lstsq(X, b, rcond=None)[0]
    return M[:3].T, M[3]


def _posed_fit(V: np.ndarray, fitted: np.ndarray, info: dict[str, Any], template: Mesh,
               segmentation: Segmentation, R: np.ndarray, fit) -> tuple[np.ndarray, dict]:
    """The upright fit with the template's limbs turned to the named joint markers.

    With the limbs' joints named (:func:`~mocapflow.stages.skin.limb_pose.joint_targets`),
    in turn the template's limbs are turned to them
    (:func:`~mocapflow.stages.skin.limb_pose.pose_limbs`) and it is fitted again with the
    joints' markers on the skin around them
    (:func:`~mocapflow.stages.skin.limb_pose.joint_regions`), until no bone turns more than
    :data:`POSE_SETTLED` degrees (at most :data:`POSE_PASSES` times).  The T-pose's fit is
    too large and low (the Qualisys walker's at the scale range's top, 1.05, its feet 0.3 m
    under the floor, so the knee markers sat half a thigh from the hips, beyond
    :data:`~mocapflow.stages.skin.limb_pose.BONE_REACH`); each round's fit of the turned
    limbs brings it nearer (0.96 after the rounds).  ``fit``: the
    upright fit of a template in the capture's axes; ``R``: the template's axes into the
    capture's.  Without named joint markers: as fitted."""
    names = list(template.attrs["joint_names"])
    part = np.asarray(template.attrs["vertex_part"])
    # the rig's bones in vertex_part order (joints without a bone keep their index)
    order = {k: np.asarray(template.attrs["bones"].get(k, np.zeros((2, 3))),
                           dtype=np.float64) @ R.T for k in names}  # fmt: skip
    found: dict[str, int] = {}
    turned: dict[str, float] = {}
    beyond: dict[str, float] = {}
    start = V

    def placed():
        A, t = _affine_between(start, fitted)
        bones = {k: b @ A.T + t for k, b in order.items()}
        targets = limb_pose.joint_targets(segmentation.labels, segmentation.reference, bones,
                                          fitted)
        return A, t, bones, targets

    A, t, bones, targets = placed()
    for _ in range(POSE_PASSES if targets else 0):
        found = {f"{side} {joint}": len(i) for (side, joint), (_, i) in sorted(targets.items())}
        posed, posed_bones, rep = limb_pose.pose_limbs(fitted, template.faces, bones, part,
                                                       targets)
        for bone, deg in rep["turned_deg"].items():
            turned[bone] = round(turned.get(bone, 0.0) + deg, 2)
        beyond = rep["beyond_reach"]
        if not rep["turned_deg"]:
            break
        inverse = np.linalg.inv(A).T
        start = (posed - t) @ inverse  # the posed template, as fit() takes it
        order = {k: (b - t) @ inverse for k, b in posed_bones.items()}
        joints = limb_pose.joint_regions(posed, posed_bones, targets, len(segmentation.labels))
        fitted, info = fit(start, joints)
        if max(rep["turned_deg"].values()) <= POSE_SETTLED:
            break
        A, t, bones, targets = placed()
    info = {**info, "limbs": {"joints": found, "turned_deg": turned, "beyond_reach": beyond}}
    return fitted, info


def _closest_frame(vertices: np.ndarray, faces: np.ndarray, targets: np.ndarray) -> int:
    """Frame of an animated mesh ``(F, V, 3)`` whose surface is nearest the targets."""
    F = vertices.shape[0]
    step = max(1, F // 60)

    def cost(f: int) -> float:
        return float(np.median(closest_points_on_triangles(targets, vertices[f], faces)[2]))

    coarse = min(range(0, F, step), key=cost)
    return min(range(max(0, coarse - step), min(F, coarse + step + 1)), key=cost)


@stage("fit_mesh", outputs=("mesh", "report"))
def fit_mesh(
    template: Mesh,
    segmentation: Segmentation,
    *,
    landmarks: dict[str, int] | None = None,
    stiffness: list[float] | None = None,
    marker_offset: float = 0.0,
    allow_scale: bool = True,
    template_frame: int | None = None,
    method: Literal["allen", "icp"] = "allen",
    schedule: list[list[float]] | None = None,
    named_regions: bool = True,
    pose_limbs: bool = True,
    ctx: Context,
) -> dict[str, Any]:
    """Fit a detailed template mesh to the marker surface's reference pose.

    Parameters
    ----------
    template : Mesh
        Detailed mesh (its first frame if animated), roughly in the markers'
        pose, same up axis and facing; any unit (a scale is fitted).
    segmentation : Segmentation
        Provides the markers' reference positions and labels.
    landmarks : dict, optional
        ``{marker label: template vertex index}`` correspondences (Allen et al.).
    stiffness : list of float, optional
        Non-rigid stiffness schedule (default ``[30, 10, 3, 1]``).
    marker_offset : float
        Distance (m) of the marker centres from the skin.
    allow_scale : bool
        Fit scale and proportions (an affine alignment: template in another
        unit or of another body); rigid alignment when false.
    template_frame : int, optional
        Frame of an animated template to use (its pose must match the markers'
        reference pose); default: the frame closest to the markers' reference
        positions (e.g. the simulator's true mesh at the reference frame).
    method : {"allen", "icp"}
        ``allen``: per-vertex affine registration (Allen et al. 2003; P&H §5.1);
        ``icp``: the earlier Laplacian displacement fit (baseline).
    schedule : list of [landmark, smoothness, data, iterations], optional
        ``allen``'s coarse-to-fine weights (default
        :data:`~mocapflow.stages.skin.registration.DEFAULT_SCHEDULE`).
    named_regions : bool
        Below the density (the upright fit): match the markers whose labels name a
        place on the pelvis, trunk, head or shoulder girdle (``LASI``, ``C7``,
        ``STRN``, ``L_HDF``, ``Daphnee:ASISr``, ...;
        :func:`~mocapflow.stages.skin.marker_regions.marker_region`) to that region of
        the template only (its rig names the regions), and turn the template to face the
        way the named front and back markers do
        (:func:`~mocapflow.stages.skin.marker_regions.body_facing`, within
        :data:`FACING_TURN`); the report's ``named_markers`` counts them per region and
        ``facing`` gives the direction.  False: every marker to the whole template, four
        headings tried.
    pose_limbs : bool
        Below the density, after the upright fit: turn the template's upper arms,
        forearms, thighs and shanks (its T-pose) to the elbow, wrist, knee and ankle
        markers the labels name (``LELB``, ``L_HLE``, ``LWRA``, ``R_RSP``, ``LKNE``,
        ``L_FAL``, ...; :func:`~mocapflow.stages.skin.limb_pose.pose_limbs`), fit again
        and turn them again; the report's ``limbs`` gives the joints found, the turns
        (degrees per bone, summed over the rounds) and the bones beyond reach.
        False: the template's T-pose (the arms stand out where the markers hang down).

    Returns
    -------
    dict
        ``mesh``: fitted rest :class:`Mesh`; ``report``: scale, rotation and
        marker-to-surface distances in mm after alignment and after fitting.

    Raises
    ------
    DeformError
        Unknown landmark labels, or a template that stays far from the markers
        after alignment (90th percentile distance > one marker spacing).  A
        segmentation below Park & Hodgins' density (``attrs["density"]["suited"]`` false, see
        :mod:`~mocapflow.stages.skin.density`) gets :func:`upright_fit` instead
        (no non-rigid fit, no such error).
    """
    if template.animated and template_frame is None:
        template_frame = _closest_frame(template.vertices, template.faces, segmentation.reference)
    if template.animated and not 0 <= template_frame < template.vertices.shape[0]:
        raise DeformError(
            f"fit_mesh: template_frame {template_frame} outside the template's "
            f"{template.vertices.shape[0]} frames"
        )
    V = template.vertices if not template.animated else template.vertices[template_frame]
    # the template into the capture's axes (both default to Y up, facing +Z)
    axes = {k: segmentation.attrs.get(k, d) for k, d in (("up", "+y"), ("forward", "+z"))}
    R = frame_basis(axes["up"], axes["forward"]) @ frame_basis(
        template.attrs.get("up", "+y"), template.attrs.get("forward", "+z")).T
    V = V @ R.T
    index = {m: i for i, m in enumerate(segmentation.labels)}
    unknown = [k for k in (landmarks or {}) if k not in index]
    if unknown:
        raise DeformError(f"fit_mesh: landmarks name unknown markers {unknown[:10]}")
    lm = {index[k]: int(v) for k, v in (landmarks or {}).items()}
    if (segmentation.attrs.get("density") or {}).get("suited") is False:
        # below Park & Hodgins' density (segment warned once): the upright fit
        regions = masks = facing = None
        basis = frame_basis(axes["up"], axes["forward"])
        if named_regions and "joint_names" in template.attrs and "vertex_part" in template.attrs:
            regions = [marker_region(label) for label in segmentation.labels]
            masks = region_vertices(list(template.attrs["joint_names"]),
                                    np.asarray(template.attrs["vertex_part"]),
                                    V @ basis[:, 1])  # fmt: skip
            facing = body_facing(segmentation.labels, segmentation.reference, basis[:, 1])
        def fit(start: np.ndarray, joints: tuple[list, dict] | None = None,
                ) -> tuple[np.ndarray, dict[str, Any]]:
            """The upright fit of ``start``; ``joints``: the limb joints' marker regions
            and masks too (:func:`~mocapflow.stages.skin.limb_pose.joint_regions`)."""
            named, named_masks = regions, masks
            if joints is not None:
                named = [a or b for a, b in zip(regions or [None] * len(joints[0]),
                                                joints[0])]  # fmt: skip
                named_masks = {**(masks or {}), **joints[1]}
            return upright_fit(start, template.faces, segmentation.reference, basis[:, 1],
                               marker_offset=marker_offset, marker_regions=named,
                               region_masks=named_masks, facing=facing,
                               forward=basis[:, 2])  # fmt: skip

        fitted, info = fit(V)
        if pose_limbs and "bones" in template.attrs and "vertex_part" in template.attrs:
            fitted, info = _posed_fit(V, fitted, info, template, segmentation, R, fit)
        report = {**info, "vertices": int(len(V)), "template_frame": template_frame}
        ctx.figure("fit", f"upright x{info['scale']:.2f}")
        mesh = Mesh(vertices=fitted, faces=template.faces, attrs={**template.attrs, **axes})
        return {"mesh": mesh, "report": report}
    fitted, info = fit_detailed_mesh(
        V, template.faces, segmentation.reference, landmarks=lm,
        stiffness=tuple(stiffness) if stiffness else (30.0, 10.0, 3.0, 1.0),
        marker_offset=marker_offset, allow_scale=allow_scale, method=method,
        schedule=tuple((float(a), float(b), float(c), int(n)) for a, b, c, n in schedule)
        if schedule else DEFAULT_SCHEDULE,
    )  # fmt: skip
    ref, faces = segmentation.reference, segmentation.faces
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    spacing = float(np.median(np.linalg.norm(ref[edges[:, 0]] - ref[edges[:, 1]], axis=1)))
    if info["aligned"]["p90_mm"] / 1000 > spacing:
        raise DeformError(
            f"fit_mesh: template does not match the markers: after alignment 10 % of the "
            f"markers are farther than {info['aligned']['p90_mm']:.0f} mm from it, more than "
            f"the marker spacing {spacing * 1000:.0f} mm (different pose, facing or body?); "
            "give landmarks"
        )
    sv = info["axis_scales"]
    if min(sv) < max(sv) / MAX_AXIS_SCALE_RATIO:
        raise DeformError(
            "fit_mesh: template does not match the markers: the alignment squashed it "
            f"(axis scales {', '.join(f'{v:.3g}' for v in sv)}, more than "
            f"{MAX_AXIS_SCALE_RATIO:g}x apart: not a body like the template?); give landmarks"
        )
    if abs(np.log(info["scale"])) > np.log(1.25):
        ctx.warn(f"template scaled by {info['scale']:.3g} to fit the markers")
    report = {**info, "vertices": int(len(V)), "marker_spacing_mm": spacing * 1000,
              "template_frame": template_frame}  # fmt: skip
    mesh = Mesh(vertices=fitted, faces=template.faces, attrs={**template.attrs, **axes})
    return {"mesh": mesh, "report": report}


def skeleton_bones(body: Body, R: np.ndarray, p: np.ndarray) -> dict[str, list[list[float]]]:
    """Bone axes of a posed body: ``{joint name: [start (3,), end (3,)]}``.

    A joint's bone runs from it to the child farthest along the bone into it (the
    spine continues up into the neck, not sideways into a shoulder; the root's
    bone goes up), or to its end site.

    Parameters
    ----------
    body : Body
    R : (J, 3, 3) float ndarray
    p : (J, 3) float ndarray
        One frame of :func:`~mocapflow.stages.motion.simulate.body.skinning_transforms`.

    Returns
    -------
    dict
    """
    sk = body.skeleton
    bind = body.bind_positions()
    ends: dict[int, np.ndarray] = {}
    for j in range(sk.n_joints):
        par = sk.parents[j]
        into = bind[j] - bind[par] if par >= 0 else np.array([0.0, 1.0, 0.0])
        into = into / max(float(np.linalg.norm(into)), 1e-12)
        kids = [bind[c] for c in np.flatnonzero(sk.parents == j)]
        kids += [bind[j] + sk.end_offsets[e] for e in np.flatnonzero(sk.end_parents == j)]
        kids = [k for k in kids if np.linalg.norm(k - bind[j]) > 1e-6]
        if kids:
            ends[j] = max(kids, key=lambda k: float((k - bind[j]) @ into))
    return {sk.names[j]: [p[j].tolist(), (R[j] @ (end - bind[j]) + p[j]).tolist()]
            for j, end in sorted(ends.items())}


@stage("template_mesh", outputs=("mesh",))
def template_mesh(
    *,
    body_mesh: FilePath | None = None,
    n_vertices: int = 13000,
    relax: int = 5,
    pose: Literal["rest", "bind"] = "rest",
    leg_abduction: float = 12.0,
    ctx: Context,
) -> dict[str, Any]:
    """A detailed body mesh to fit to the markers (the paper's scan), in its T-pose.

    Parameters
    ----------
    body_mesh : FilePath, optional
        The MakeHuman ``makehuman_base.obj`` (CC0; rig and weights JSON beside it,
        see :func:`mocapflow.stages.motion.simulate.body.load_makehuman_body`); default:
        a procedural body around the procedural CMU skeleton.
    n_vertices : int
        Vertex count of the procedural body.
    relax : int
        Rounds of :func:`~mocapflow.stages.motion.simulate.capsules.relax_surface`
        evening out the procedural body's decimated triangles (0: as decimated).  A
        sliver is what a deformation stretches first: through the skin graph to
        ``deform`` on ``ezc3d-testFiles_Qualisys.c3d`` (13,000 vertices, rigid
        skinning) 6 triangles had an edge stretched beyond 3× (rest edges of 4–7 mm
        beside 12–98 mm ones) as decimated, 0 relaxed.  The fit is unchanged
        (``benchmarks/fit_mesh.py``'s ``allen`` rows, seeds 3–5: 1.89 mm mean either
        way).
    pose : {"rest", "bind"}
        ``rest``: posed by its rig into the rest pose of the procedural CMU
        skeleton (T-pose, arms out; with the default ``leg_abduction`` the
        simulator's calibration pose; the MakeHuman mesh is modelled in an A-pose); ``bind``:
        as modelled.
    leg_abduction : float
        ``rest``: hip abduction (degrees) of the pose, to match a calibration pose
        with the legs apart; default 12, the simulator's (``capture_motion``'s
        ``calibration_abduction``) and a usual star pose.  The registration bends
        less where the poses agree: through the skin graph (``benchmarks/deform.py
        --graph-path``) legs together (0) against the simulator's 12 left the fitted
        feet and shins 1-4 cm off (fitted rest mesh 6.0 mm mean from the true one,
        2.7 mm with 12; procedural template, seed 0).

    Returns
    -------
    dict
        ``mesh``: rest :class:`Mesh` in metres, y up, facing +z; ``attrs`` also
        carry the rig for :func:`~mocapflow.stages.skin.registration.anatomical_landmarks`:
        ``joint_names``, ``vertex_part`` (dominant joint per vertex), ``bones``
        (``{joint: [start, end]}`` in the mesh's pose).
    """
    if body_mesh is not None:
        body = load_makehuman_body(body_mesh)
    else:
        body = procedural_body(procedural_skeleton(), n_vertices=n_vertices, relax=relax)
    J = body.skeleton.n_joints
    if pose == "rest":
        sk = procedural_skeleton()
        rot = quat_identity((1, sk.n_joints))
        for side, sign in (("Left", 1.0), ("Right", -1.0)):
            j = find_joint(sk.names, f"{side}UpLeg")
            if j is not None and leg_abduction:
                rot[0, j] = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]),
                                                 np.radians(sign * leg_abduction))
        rest = Motion(sk, np.zeros((1, 3)), rot, rate=1.0)
        R, p = skinning_transforms(body, rest)
        R, p = R[0], p[0]
        V = skin(body, R[None], p[None])[0]
    else:
        R, p, V = np.broadcast_to(np.eye(3), (J, 3, 3)), body.bind_positions(), body.vertices
    attrs = {"source": body.attrs.get("source"), "up": "+y", "forward": "+z", "pose": pose,
             "joint_names": list(body.skeleton.names), "vertex_part": body.part.tolist(),
             "bones": skeleton_bones(body, R, p)}  # fmt: skip
    return {"mesh": Mesh(V, body.faces, attrs=attrs)}
