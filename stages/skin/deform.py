"""Skin deformation of a detailed mesh from dense markers (Park & Hodgins 2006, §5.3).

Per frame and per near-rigid part ``p`` (see :mod:`mocapflow.stages.skin.segment`):

1. **rigid**: Horn's absolute orientation of the part's reference marker positions
   ``p̄_i`` (in the part's local frame) onto the observed ``x_i``: ``x ≈ R p̄ + d``;
2. **quadratic** (Eq. 6): the markers brought back into the local frame,
   ``p̂_i = R^T (x_i - d)``, are fitted by a 3×9 quadratic transform
   ``p̂ ≈ A q(p̄)``, ``q = [x y z x² y² z² xy yz zx]``, by the pseudo-inverse;
3. **residual** (Eq. 7): what is left, ``p̂_i - A q(p̄_i)``, is interpolated by
   radial basis functions with a compactly supported cubic B-spline kernel
   whose dilation is twice the part's largest nearest-neighbour marker
   distance (a sparse system solved once per visibility pattern; a thin-plate
   spline is an option, see below);
4. **vertices** (Eq. 8–9): every vertex ``v̄`` of the detailed mesh is moved by the
   same model of every part it belongs to and the results are blended with
   its weights ``β`` (barycentric interpolation of the markers' ``α`` from the
   nearest marker-surface triangle, sharpened by default, see below).

Modes: ``rigid`` (1 + blend: linear blend skinning with the part transforms),
``quadratic`` (1–2), ``rigid_residual`` (1 + 3), ``quadratic_residual`` (1–3).

Departures from the paper, chosen by measurement (``benchmarks/deform.py``:
markers held out of the whole pipeline and predicted as mesh vertices on a
dynamic trial, and the simulator's true mesh).  The paper's exact method is
``beta_sharpness=1, quadratic_damping=0, residual_kernel="cubic_bspline"``:

* **sharpened weights** ``β ∝ β_bary^4`` (``beta_sharpness``; weights < 10⁻³
  dropped).  What dominated the held-out error was the blend, not the
  per-part models: markers binding to two or more parts had 9.9 mm mean
  error against 4.5 mm for markers inside one part (paper settings), and the
  best single part predicted them better than the blend (6.2 mm).  The segmentation's
  ``α`` are mostly 0/1, and barycentric interpolation over the coarse marker
  triangles (4–7 cm, larger around holes) spreads each part boundary over a
  whole triangle, blending two parts' extrapolations there.  Sharpening
  narrows that zone (a vertex midway between two hard parts stays 50/50):
  held-out error 7.3 → 5.9 mm with everything else at the paper's settings,
  6.5 → 5.1 mm with the thin-plate residual.  4 was chosen over 8 (better on
  seed 0, worse on seeds 1–5 and on the true mesh).  It costs the ``rigid``
  mode (plain skinning wants wide blends: ~1 mm more on the true mesh) and a
  little on a limb whose ``α`` are genuinely soft, so it is a parameter;
* an optional **thin-plate residual** (``residual_kernel="thin_plate"``; the
  default stays the paper's B-spline): ``φ(r) = r² log r``
  (``r`` in units of the part's RMS radius) with a linear polynomial, per part,
  dense.  The compact B-spline interpolates with dips between centres and made
  markers inside a part *worse* than no residual at all (held-out markers sit
  between centres); the thin plate lowered held-out error by a further 9–15 %
  on 6 simulated seeds and the true-mesh error by ~10 %.  Its polynomial is
  folded into ``A`` and ``d`` (so ``rigid_residual`` becomes affine + thin
  plate, which is why it is within a few hundredths of a millimetre of
  ``quadratic_residual`` with this kernel); the polynomial spans only the
  directions the markers extend in, so a flat part or a 3-marker frame does
  not extrapolate off its plane.  Held-out markers, 900-frame run (seed 0):
  quadratic + residual 5.56 mm mean with the B-spline, 5.13 with the thin
  plate; but with the thin plate ``rigid_residual`` ties it (5.14), i.e. the
  quadratic term no longer matters, while with the B-spline it is 0.10 mm
  better than ``rigid_residual`` (5.66) and both beat the global thin-plate
  RBF (6.06).  The default keeps the paper's kernel and its sparse solve;
* ``quadratic_damping`` (default 0.3; 0 = the paper's pseudo-inverse) adds a
  ridge toward the rigid transform on the 9 quadratic coefficients: parts
  with 10–15 markers otherwise extrapolate their quadratic by centimetres
  (held-out error 5.5 → 5.1 mm, true-mesh error 5.2 → 3.4 mm on 300 frames);
  0.03–1 measure the same within 0.1 mm.

Implementation notes (none changes the method):

* the quadratic monomials are centred on their weighted mean over the part's
  markers and scaled by the part's RMS radius; this is a change of basis of the
  paper's 3×9 ``A`` that makes Horn's translation absorb the constant, so a known
  quadratic deformation is recovered exactly;
* ``A`` is solved as a deviation from the identity (``p̂ - p̄ ≈ ΔA q``) so that
  directions the markers do not constrain (a flat part's normal) stay rigid
  instead of collapsing to the minimum-norm zero of a plain pseudo-inverse;
* the B-spline kernel is ``φ(r) = 1.5·B₃(2r/σ)``: it vanishes for ``r ≥ σ``, the
  dilation.  (With support ``2σ`` the kernel matrices of body-like marker
  layouts are indefinite; with support ``σ`` they are positive definite with
  condition numbers ~20–50.)  When one isolated marker makes the paper's
  ``σ = 2 × max nearest-neighbour distance`` so wide that the system is
  indefinite or ill-conditioned (condition > 100), ``σ`` is reduced in 15 %
  steps until it is not, with a warning naming the part: otherwise the
  residual oscillates by centimetres between markers (B-spline kernel only);
* all parts and frames are evaluated as one linear map
  ``vertices(f) = H · C(f)`` (``H``: β-weighted local coordinates, monomials
  and kernel values of the vertices; ``C``: per-frame part coefficients), done
  as one dense BLAS product per part and frame chunk.

Fallbacks, each with a warning naming the part: a part with fewer than
``min_quadratic_markers`` markers (quadratic under-determined) uses the rigid
transform (+ residual in residual modes); a frame in which a part has fewer than
3 visible markers (or a degenerate set) gets the part's model interpolated in
time from the nearest frames where it could be fitted (held at the ends); a
frame with 3 to ``min_quadratic_markers - 1`` visible markers keeps its own
rigid fit and residual but interpolates the quadratic terms.  A part never
fitted in any frame, and a mesh that does not overlap the marker surface, are
errors naming the problem.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from typing import Any, Literal

import numpy as np
import scipy.sparse as sp
from scipy.linalg import cho_factor, cho_solve, lu_factor, lu_solve
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from mocapflow.pipeline import Context, stage
from mocapflow.stages.motion.datatypes import Markers, Mesh
from mocapflow.stages.motion.kinematics import (
    absolute_orientation_batch,
    quat_continuity,
    quat_from_matrix,
    quat_normalize,
    quat_to_matrix,
)
from mocapflow.stages.skin.segment import Segmentation

__all__ = [
    "DeformError",
    "MODES",
    "RESIDUAL_KERNELS",
    "MeshBinding",
    "PartFit",
    "PartModel",
    "align_markers",
    "bind_mesh",
    "closest_points_on_triangles",
    "cubic_bspline",
    "deform",
    "deform_positions",
    "dilation",
    "evaluate_part",
    "fit_part",
    "frame_coefficients",
    "prepare_part",
    "quadratic_basis",
    "rbf_matrix",
    "thin_plate",
    "thin_plate_matrix",
    "VertexOperator",
    "operator_matrix",
    "vertex_operator",
]

Mode = Literal["rigid", "quadratic", "rigid_residual", "quadratic_residual"]
MODES: tuple[str, ...] = ("rigid", "quadratic", "rigid_residual", "quadratic_residual")
ResidualKernel = Literal["cubic_bspline", "thin_plate"]
RESIDUAL_KERNELS: tuple[str, ...] = ("cubic_bspline", "thin_plate")


class DeformError(ValueError):
    """Inputs of the skin deformation are inconsistent (names the part / mesh problem)."""


# --------------------------------------------------------------------------- bases and kernels


def quadratic_basis(p: np.ndarray) -> np.ndarray:
    """The paper's quadratic monomials ``q = [x y z x² y² z² xy yz zx]``.

    Parameters
    ----------
    p : (..., 3) float ndarray

    Returns
    -------
    (..., 9) float ndarray
    """
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    return np.stack([x, y, z, x * x, y * y, z * z, x * y, y * z, z * x], axis=-1)


def cubic_bspline(r: np.ndarray) -> np.ndarray:
    """Compactly supported cubic B-spline radial kernel, ``φ(0) = 1``, ``φ(r ≥ 1) = 0``.

    ``φ(r) = 1.5 · B₃(2r)`` with the uniform cubic B-spline ``B₃`` (support
    ``[-2, 2]``); ``r`` is the distance divided by the dilation.

    Parameters
    ----------
    r : ndarray
        Non-negative scaled distances.

    Returns
    -------
    ndarray
        Same shape; C² continuous, exactly 0 for ``r >= 1``.
    """
    u = 2.0 * np.abs(np.asarray(r, dtype=np.float64))
    out = np.zeros_like(u)
    a = u < 1.0
    b = (u >= 1.0) & (u < 2.0)
    out[a] = (4.0 - 6.0 * u[a] ** 2 + 3.0 * u[a] ** 3) / 6.0
    out[b] = (2.0 - u[b]) ** 3 / 6.0
    return 1.5 * out


def thin_plate(r: np.ndarray) -> np.ndarray:
    """Thin-plate spline kernel ``φ(r) = r² log r`` (``φ(0) = 0``), as scipy's ``RBFInterpolator``.

    Parameters
    ----------
    r : ndarray
        Non-negative distances (in units of the part's RMS radius).

    Returns
    -------
    ndarray
    """
    r = np.abs(np.asarray(r, dtype=np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(r > 0, r * r * np.log(np.where(r > 0, r, 1.0)), 0.0)


def dilation(points: np.ndarray, *, factor: float = 2.0) -> float:
    """Kernel dilation: ``factor`` × the largest nearest-neighbour distance of ``points``.

    Parameters
    ----------
    points : (n, 3) float ndarray
    factor : float

    Returns
    -------
    float
    """
    if len(points) < 2:
        return 1.0
    d, _ = cKDTree(points).query(points, k=2)
    return float(factor * d[:, 1].max())


def rbf_matrix(points: np.ndarray, centres: np.ndarray, sigma) -> sp.csr_matrix:
    """Sparse kernel matrix ``Φ[a, j] = φ(|points_a - centres_j| / σ_j)``.

    Parameters
    ----------
    points : (N, 3) float ndarray
    centres : (n, 3) float ndarray
    sigma : float or (n,) float ndarray
        Dilation (support radius), one for all centres or one per centre.

    Returns
    -------
    (N, n) scipy.sparse.csr_matrix
    """
    sig = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (len(centres),))
    D = cKDTree(points).sparse_distance_matrix(
        cKDTree(centres), float(sig.max()), output_type="coo_matrix"
    )
    # sparse_distance_matrix drops exact zeros (coincident points): add them back
    same_d, same_j = cKDTree(centres).query(points, k=1)
    coincident = np.flatnonzero(same_d == 0.0)
    rows = np.concatenate([D.row, coincident])
    cols = np.concatenate([D.col, same_j[coincident]])
    vals = np.concatenate([cubic_bspline(D.data / sig[D.col]), np.ones(coincident.size)])
    M = sp.coo_matrix((vals, (rows, cols)), shape=(len(points), len(centres))).tocsr()
    M.sum_duplicates()
    M.data = np.where(M.data > 1.0, 1.0, M.data)  # a coincident pair listed twice
    M.eliminate_zeros()
    return M


def thin_plate_matrix(points: np.ndarray, centres: np.ndarray, scale: float) -> sp.csr_matrix:
    """Dense thin-plate kernel ``Φ[a, j] = φ(|points_a - centres_j| / scale)`` as CSR.

    Parameters
    ----------
    points : (N, 3) float ndarray
    centres : (n, 3) float ndarray
    scale : float
        Length unit of the kernel (the part's RMS radius).

    Returns
    -------
    (N, n) scipy.sparse.csr_matrix
    """
    r = np.linalg.norm(points[:, None, :] - centres[None, :, :], axis=-1) / scale
    return sp.csr_matrix(thin_plate(r))


# --------------------------------------------------------------------------- geometry


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
    A, B, C = tri[cand, 0], tri[cand, 1], tri[cand, 2]  # (N, k, 3)
    bary = _closest_barycentric(P[:, None, :], A, B, C)
    Q = bary[..., :1] * A + bary[..., 1:2] * B + bary[..., 2:] * C
    d2 = np.sum((Q - P[:, None, :]) ** 2, axis=-1)
    j = np.argmin(d2, axis=1)
    n = np.arange(len(P))
    return cand[n, j], bary[n, j], np.sqrt(d2[n, j])


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
        raise DeformError(
            f"{name} does not overlap the marker surface: only {overlap:.0%} of its "
            f"{len(V)} vertices lie within {limit * 1000:.0f} mm of it (median distance "
            f"{np.median(dist) * 1000:.0f} mm; mesh extent {ext_v:.3g} m, marker extent "
            f"{ext_m:.3g} m){hint}; fit the mesh to the markers first (stage fit_mesh)"
        )
    alpha = segmentation.weights
    beta = np.einsum("vc,vcp->vp", bary, alpha[faces[tri]])
    if sharpness != 1.0:
        beta = beta**sharpness
    beta /= beta.sum(1, keepdims=True)
    if min_weight > 0:
        beta[beta < min_weight] = 0.0
        beta /= beta.sum(1, keepdims=True)
    return MeshBinding(beta=beta, triangle=tri, barycentric=bary, distance=dist)


# --------------------------------------------------------------------------- per-part model


@dataclass
class PartModel:
    """Everything about one part that does not depend on the frame.

    Attributes
    ----------
    name : str
    members : (n,) int ndarray
        Marker indices of the part (``α > 0``).
    alpha : (n,) float ndarray
        Their weights, used in the fits.
    local : (n, 3) float ndarray
        Reference marker positions in the part's local frame (``p̄``).
    origin : (3,) float ndarray
    axes : (3, 3) float ndarray
    scale : float
        RMS radius of ``local`` (basis normalisation).
    q_mean : (9,) float ndarray
        Weighted mean of the scaled monomials (basis centring).
    sigma : float
        RBF dilation.
    kernel : (n, n) scipy.sparse.csc_matrix
        ``Φ`` among the markers.
    quadratic : bool
        Whether the part has enough markers for the quadratic transform.
    vertices : (Vp, ) int ndarray
        Mesh vertices with ``β > 0`` for this part.
    beta : (Vp,) float ndarray
    vertex_basis : (Vp, 9) float ndarray
        Centred scaled monomials of the vertices.
    vertex_local : (Vp, 3) float ndarray
    vertex_kernel : (Vp, n) scipy.sparse.csr_matrix
    messages : list of str
        Adjustments made (e.g. a reduced dilation).
    residual_kernel : {"cubic_bspline", "thin_plate"}
        Radial kernel of the residual (Eq. 7 uses the cubic B-spline).
    """

    name: str
    members: np.ndarray
    alpha: np.ndarray
    local: np.ndarray
    origin: np.ndarray
    axes: np.ndarray
    scale: float
    q_mean: np.ndarray
    sigma: float
    kernel: sp.csc_matrix
    quadratic: bool
    vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    beta: np.ndarray = field(default_factory=lambda: np.zeros(0))
    vertex_basis: np.ndarray = field(default_factory=lambda: np.zeros((0, 9)))
    vertex_local: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    vertex_kernel: sp.csr_matrix | None = None
    messages: list[str] = field(default_factory=list)
    residual_kernel: str = "cubic_bspline"

    def basis(self, local: np.ndarray) -> np.ndarray:
        """Centred scaled monomials of local points ``(..., 3) -> (..., 9)``."""
        return quadratic_basis(local / self.scale) - self.q_mean

    def kernel_rows(self, local: np.ndarray) -> sp.csr_matrix:
        """Residual kernel values ``(N, n)`` of local points ``(N, 3)`` at the part's markers."""
        if self.residual_kernel == "thin_plate":
            return thin_plate_matrix(local, self.local, self.scale)
        return rbf_matrix(local, self.local, self.sigma)


def _well_conditioned_kernel(
    local: np.ndarray, sigma: float, name: str, *, max_condition: float = 100.0
) -> tuple[sp.csc_matrix, float, str]:
    """The marker kernel matrix, with the dilation shrunk until it is well conditioned.

    The cubic B-spline is not positive definite in 3-D for every layout: a part
    with an isolated marker gets a huge ``2 × max nearest-neighbour`` dilation,
    an indefinite, near-singular system and wildly oscillating residuals.  The
    dilation is then reduced by 15 % steps until the matrix is positive definite
    with condition number <= ``max_condition`` (uniform layouts: ~20–50).
    """
    s0 = sigma
    for _ in range(40):
        K = rbf_matrix(local, local, sigma).tocsc()
        lam = np.linalg.eigvalsh(K.toarray()) if K.shape[0] <= 2000 else None
        if lam is None or (lam[0] > 0 and lam[-1] / lam[0] <= max_condition):
            break
        sigma *= 0.85
    note = ""
    if sigma < s0:
        note = (f"part {name!r}: RBF dilation reduced from {s0 * 1000:.0f} to "
                f"{sigma * 1000:.0f} mm to keep the residual system well conditioned "
                "(an isolated marker made 2 x the largest nearest-neighbour distance too wide)")
    return K, sigma, note


def prepare_part(
    segmentation: Segmentation,
    p: int,
    *,
    vertices: np.ndarray | None = None,
    beta: np.ndarray | None = None,
    min_quadratic_markers: int = 10,
    dilation_factor: float = 2.0,
    residual_kernel: str = "cubic_bspline",
) -> PartModel:
    """Frame-independent model of part ``p`` (local coordinates, bases, kernels).

    Parameters
    ----------
    segmentation : Segmentation
    p : int
        Part index.
    vertices : (V, 3) float ndarray, optional
        Rest vertices of the detailed mesh (omit to fit markers only).
    beta : (V, P) float ndarray, optional
        Vertex weights from :func:`bind_mesh`.
    min_quadratic_markers : int
    dilation_factor : float
        B-spline support = this × the part's largest nearest-neighbour distance.
    residual_kernel : {"cubic_bspline", "thin_plate"}
        ``"cubic_bspline"``: the paper's compactly supported kernel (sparse);
        ``"thin_plate"``: ``r² log r`` with a linear polynomial (dense, per part).

    Returns
    -------
    PartModel
    """
    if residual_kernel not in RESIDUAL_KERNELS:
        raise DeformError(
            f"unknown residual kernel {residual_kernel!r}; choose one of {list(RESIDUAL_KERNELS)}"
        )
    members = segmentation.members(p)
    alpha = segmentation.weights[members, p]
    origin, axes = segmentation.origins[p], segmentation.axes[p]
    local = (segmentation.reference[members] - origin) @ axes
    w = alpha / alpha.sum()
    scale = float(np.sqrt(np.sum(w * np.sum(local**2, 1)))) or 1.0
    q_mean = w @ quadratic_basis(local / scale)
    sigma = dilation(local, factor=dilation_factor)
    note = ""
    if residual_kernel == "thin_plate":
        kernel = thin_plate_matrix(local, local, scale).tocsc()
    else:
        kernel, sigma, note = _well_conditioned_kernel(local, sigma, segmentation.part_names[p])
    model = PartModel(
        name=segmentation.part_names[p],
        members=members,
        alpha=alpha,
        local=local,
        origin=origin,
        axes=axes,
        scale=scale,
        q_mean=q_mean,
        sigma=sigma,
        kernel=kernel,
        quadratic=len(members) >= min_quadratic_markers,
        residual_kernel=residual_kernel,
    )
    if note:
        model.messages.append(note)
    if vertices is not None and beta is not None:
        vidx = np.flatnonzero(beta[:, p] > 0)
        vl = (vertices[vidx] - origin) @ axes
        model.vertices = vidx
        model.beta = beta[vidx, p]
        model.vertex_local = vl
        model.vertex_basis = model.basis(vl)
        model.vertex_kernel = model.kernel_rows(vl)
    return model


@dataclass
class PartFit:
    """Per-frame parameters of one part.

    Attributes
    ----------
    R : (F, 3, 3) float ndarray
    d : (F, 3) float ndarray
        Rigid transform ``x ≈ R p̄ + d`` (translation after the quadratic offset).
    A : (F, 3, 9) float ndarray
        Quadratic transform in the centred scaled basis, as a deviation from
        the identity (``p̂ = p̄ + A q``); zero in rigid modes.
    W : (F, n, 3) float ndarray
        RBF coefficients of the residual; zero in modes without residual.
    rigid_frames : (F,) bool ndarray
        Frames whose rigid transform was fitted (others interpolated).
    quadratic_frames : (F,) bool ndarray
        Frames whose quadratic was fitted (others interpolated or rigid).
    messages : list of str
        Fallbacks taken (the stage turns them into warnings).
    """

    R: np.ndarray
    d: np.ndarray
    A: np.ndarray
    W: np.ndarray
    rigid_frames: np.ndarray
    quadratic_frames: np.ndarray
    messages: list[str] = field(default_factory=list)


def _fill_in_time(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Linear interpolation along axis 0 from ``valid`` frames (held at the ends)."""
    if valid.all():
        return values
    F = len(values)
    good = np.flatnonzero(valid)
    flat = values.reshape(F, -1)
    out = np.empty_like(flat)
    t = np.arange(F)
    for k in range(flat.shape[1]):
        out[:, k] = np.interp(t, good, flat[good, k])
    return out.reshape(values.shape)


def _fill_rotations(R: np.ndarray, valid: np.ndarray) -> np.ndarray:
    if valid.all():
        return R
    q = quat_from_matrix(np.where(valid[:, None, None], R, np.eye(3)))
    q[valid] = quat_continuity(q[valid], axis=0)
    q = quat_normalize(_fill_in_time(q, valid))
    return quat_to_matrix(q)


def _frame_ranges(mask: np.ndarray) -> str:
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return ""
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts = np.r_[idx[0], idx[breaks + 1]]
    ends = np.r_[idx[breaks], idx[-1]]
    parts = [f"{a}" if a == b else f"{a}-{b}" for a, b in zip(starts, ends)]
    return ", ".join(parts[:5]) + (", ..." if len(parts) > 5 else "")


def fit_part(
    model: PartModel,
    x: np.ndarray,
    *,
    mode: str,
    min_quadratic_markers: int = 10,
    damping: float = 0.0,
) -> PartFit:
    """Fit one part's rigid, quadratic and residual model in every frame.

    Parameters
    ----------
    model : PartModel
    x : (F, n, 3) float ndarray
        Observed positions of the part's markers, NaN where missing.
    mode : {"rigid", "quadratic", "rigid_residual", "quadratic_residual"}
    min_quadratic_markers : int
        Fewer visible markers than this in a frame: the quadratic is not fitted
        there (interpolated from neighbouring frames).
    damping : float
        Ridge on the 9 quadratic coefficients (toward the rigid transform),
        relative to the summed marker weights; 0 is the paper's plain
        pseudo-inverse (Eq. 6).

    Returns
    -------
    PartFit

    Raises
    ------
    DeformError
        The part has < 3 visible non-collinear markers in every frame.
    """
    if mode not in MODES:
        raise DeformError(f"unknown deformation mode {mode!r}; choose one of {list(MODES)}")
    F, n = x.shape[:2]
    messages: list[str] = []
    vis = np.isfinite(x).all(-1)
    w = np.where(vis, model.alpha[None, :], 0.0)
    src = np.broadcast_to(model.local, (F, n, 3))
    R, d = absolute_orientation_batch(src, x, weights=w)
    rigid_ok = np.isfinite(R).all((1, 2))
    if not rigid_ok.any():
        raise DeformError(
            f"part {model.name!r} has fewer than 3 visible non-collinear markers in every "
            f"frame ({n} markers): it cannot be placed"
        )
    if not rigid_ok.all():
        messages.append(
            f"part {model.name!r}: fewer than 3 usable markers in {int((~rigid_ok).sum())} of "
            f"{F} frames ({_frame_ranges(~rigid_ok)}); its model there is interpolated from "
            "the nearest fitted frames"
        )
    use_quadratic = mode.startswith("quadratic")
    if use_quadratic and not model.quadratic:
        messages.append(
            f"part {model.name!r} has {n} markers (< {min_quadratic_markers}): the quadratic "
            f"transform is under-determined, using rigid"
            f"{' + residual' if mode.endswith('residual') else ''} for this part"
        )
        use_quadratic = False
    with np.errstate(invalid="ignore"):
        local_obs = (x - d[:, None, :]) @ R  # p̂ = R^T (x - d), NaN where missing
    dev = local_obs - model.local[None]  # p̂ - p̄
    A = np.zeros((F, 3, 9))
    c = np.zeros((F, 3))
    quad_ok = np.zeros(F, bool)
    if use_quadratic:
        quad_ok = rigid_ok & (vis.sum(1) >= min_quadratic_markers)
        if not quad_ok.any():
            messages.append(
                f"part {model.name!r}: never {min_quadratic_markers} visible markers in one "
                "frame, using rigid for this part"
            )
        else:
            D = np.concatenate([model.basis(model.local), np.ones((n, 1))], axis=1)  # (n, 10)
            for pattern, frames in _patterns(vis, quad_ok):
                sw = np.sqrt(model.alpha * pattern)
                G = _damped_pinv(sw[:, None] * D, damping * float(np.sum(model.alpha * pattern)))
                rhs = np.where(pattern[None, :, None], dev[frames], 0.0) * sw[None, :, None]
                coef = (G @ rhs).transpose(0, 2, 1)  # (f, 3, 10)
                A[frames] = coef[..., :9]
                c[frames] = coef[..., 9]
            if not quad_ok[rigid_ok].all():
                messages.append(
                    f"part {model.name!r}: fewer than {min_quadratic_markers} visible markers in "
                    f"{int((rigid_ok & ~quad_ok).sum())} frames "
                    f"({_frame_ranges(rigid_ok & ~quad_ok)}); quadratic terms interpolated there"
                )
            A = _fill_in_time(A, quad_ok)
            c = np.where(quad_ok[:, None], c, 0.0)
    # fold the offset into the translation: x = R (p̄ + A q + c) + d = R (p̄ + A q) + d'
    d = d + (R @ c[:, :, None])[..., 0]
    W = np.zeros((F, n, 3))
    if mode.endswith("residual"):
        with np.errstate(invalid="ignore"):
            model_pos = model.local[None] + model.basis(model.local) @ A.transpose(0, 2, 1)
            resid = (x - d[:, None, :]) @ R - model_pos
        poly = np.zeros((F, 4, 3))  # thin plate: [1, p̄/scale] coefficients per frame
        for pattern, frames in _patterns(vis, rigid_ok):
            idx = np.flatnonzero(pattern)
            rhs = resid[frames][:, idx, :].transpose(1, 0, 2).reshape(len(idx), -1)
            K = model.kernel[idx][:, idx]
            if model.residual_kernel == "thin_plate":
                sol, pc = _solve_thin_plate(K, model.local[idx] / model.scale, rhs)
                poly[frames] = pc.reshape(4, len(frames), 3).transpose(1, 0, 2)
            else:
                sol = _solve_kernel(K, rhs)
            W[np.ix_(frames, idx)] = sol.reshape(len(idx), len(frames), 3).transpose(1, 0, 2)
        W = _fill_in_time(W, rigid_ok)
        if model.residual_kernel == "thin_plate":
            poly = _fill_in_time(poly, rigid_ok)
    R = _fill_rotations(R, rigid_ok)
    d = _fill_in_time(d, rigid_ok)
    if mode.endswith("residual") and model.residual_kernel == "thin_plate":
        # fold the residual's linear polynomial a0 + a1 p̄/scale into A and d:
        # p̄_k/scale = q_k + q_mean_k for the first three (linear) monomials
        lin = poly[:, 1:].transpose(0, 2, 1)  # (F, 3, 3): [i, k]
        A = A.copy()
        A[:, :, :3] += lin
        const = poly[:, 0] + lin @ model.q_mean[:3]
        d = d + (R @ const[:, :, None])[..., 0]
    return PartFit(R, d, A, W, rigid_ok, quad_ok, messages)


def _damped_pinv(D: np.ndarray, lam: float) -> np.ndarray:
    """``(10, n)`` solution operator of ``min |D a - y|^2 + lam |a[:9]|^2`` (Eq. 6 when 0)."""
    if lam <= 0:
        return np.linalg.pinv(D, rcond=1e-8)
    reg = np.zeros((9, D.shape[1]))
    reg[:, :9] = np.sqrt(lam) * np.eye(9)
    return np.linalg.pinv(np.concatenate([D, reg]), rcond=1e-8)[:, : D.shape[0]]


def _solve_kernel(K: sp.spmatrix, rhs: np.ndarray) -> np.ndarray:
    """Solve the sparse RBF system ``K w = rhs`` for many right-hand sides.

    Small systems (a part's markers, n <= 400) go through a dense Cholesky of
    the sparse matrix (faster than SuperLU with thousands of right-hand sides;
    the kernel is positive definite), larger ones through SuperLU.
    """
    n = K.shape[0]
    if n <= 400:
        Kd = K.toarray()
        try:
            return cho_solve(cho_factor(Kd), rhs)
        except np.linalg.LinAlgError:  # not positive definite: general LU
            return lu_solve(lu_factor(Kd), rhs)
    return splu(sp.csc_matrix(K)).solve(rhs)


def _solve_thin_plate(
    K: sp.spmatrix, points: np.ndarray, rhs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Thin-plate interpolation with a linear polynomial: ``[K P; Pᵀ 0][w; a] = [rhs; 0]``.

    The polynomial spans only the directions the points extend in (a flat or
    collinear set, or one with fewer than 4 points, would make the system
    singular and extrapolate wildly off its plane).

    Parameters
    ----------
    K : (n, n) sparse matrix
        Thin-plate kernel among the points.
    points : (n, 3) float ndarray
    rhs : (n, k) float ndarray

    Returns
    -------
    w : (n, k) float ndarray
        Kernel weights.
    a : (4, k) float ndarray
        Polynomial coefficients on ``[1, x, y, z]``.
    """
    n = K.shape[0]
    _, sv, Vt = np.linalg.svd(points - points.mean(0), full_matrices=False)
    keep = sv > 0.05 * sv[0] if n > 1 and sv[0] > 0 else np.zeros(len(sv), bool)
    dirs = Vt[keep].T  # (3, r)
    P = np.concatenate([np.ones((n, 1)), points @ dirs], axis=1)
    m = P.shape[1]
    M = np.block([[K.toarray(), P], [P.T, np.zeros((m, m))]])
    b = np.concatenate([rhs, np.zeros((m, rhs.shape[1]))])
    try:
        sol = lu_solve(lu_factor(M, check_finite=False), b)
        if not np.isfinite(sol).all():
            raise np.linalg.LinAlgError
    except (np.linalg.LinAlgError, ValueError):
        sol = np.linalg.lstsq(M, b, rcond=None)[0]
    coef = np.zeros((4, rhs.shape[1]))
    coef[0] = sol[n]
    coef[1:] = dirs @ sol[n + 1 :]
    return sol[:n], coef


def _patterns(vis: np.ndarray, frames_ok: np.ndarray):
    """Yield ``(pattern (n,) bool, frame indices)`` for each visibility pattern."""
    ok = np.flatnonzero(frames_ok)
    if ok.size == 0:
        return
    if vis[ok].all():  # the common case after cleaning: one pattern, no sort
        yield np.ones(vis.shape[1], bool), ok
        return
    pats, inv = np.unique(vis[ok], axis=0, return_inverse=True)
    inv = np.asarray(inv).ravel()
    for k, pat in enumerate(pats):
        yield pat, ok[inv == k]


def evaluate_part(model: PartModel, fit: PartFit, local: np.ndarray | None = None,
                  basis: np.ndarray | None = None,
                  kernel: sp.csr_matrix | None = None) -> np.ndarray:
    """Global positions of points moved by one part's model (Eq. 8).

    Parameters
    ----------
    model : PartModel
    fit : PartFit
        Parameters of ``F`` frames.
    local, basis, kernel : optional
        Local coordinates ``(N, 3)``, centred monomials ``(N, 9)`` and kernel rows
        ``(N, n)`` of the points; default: the model's mesh vertices.

    Returns
    -------
    (F, N, 3) float ndarray
    """
    local = model.vertex_local if local is None else local
    basis = model.vertex_basis if basis is None else basis
    kernel = model.vertex_kernel if kernel is None else kernel
    F = fit.R.shape[0]
    N = len(local)
    y = basis @ fit.A.transpose(0, 2, 1) + local[None]
    if np.any(fit.W):
        n = fit.W.shape[1]
        r = kernel @ fit.W.transpose(1, 0, 2).reshape(n, F * 3)  # (N, F*3)
        y += r.reshape(N, F, 3).transpose(1, 0, 2)
    return y @ fit.R.transpose(0, 2, 1) + fit.d[:, None, :]


@dataclass
class VertexOperator:
    """Per-part dense blocks with ``vertices(f) = Σ_p scatter_p(H_p @ C_p(f))`` (Eq. 8–9).

    Attributes
    ----------
    vertices : list of (Vp,) int ndarray
        Mesh vertices of each part (``β > 0``).
    blocks : list of (Vp, Kp) float ndarray
        ``β_vp [v̄, q(v̄), 1, φ(v̄)]`` per part (local position, centred scaled
        monomials, constant, residual kernel values at the part's markers).
    offsets : (P + 1,) int ndarray
        Rows of each part's block in :func:`frame_coefficients`.
    n_vertices : int
    """

    vertices: list[np.ndarray]
    blocks: list[np.ndarray]
    offsets: np.ndarray
    n_vertices: int


def vertex_operator(models: list[PartModel], n_vertices: int, *, residual: bool) -> VertexOperator:
    """Operator with ``vertices(f) = H @ C(f)`` for every frame (Eq. 8–9).

    For part ``p`` and vertex ``v`` the row block is ``β_vp [v̄, q(v̄), 1, φ(v̄)]``
    (local position, centred scaled monomials, constant, kernel values at the
    part's markers); :func:`frame_coefficients` gives the matching ``C``.  The
    blocks are dense: one BLAS product per part and frame chunk is ~2.5× faster
    than one sparse product over all parts, even for the compact B-spline.

    Parameters
    ----------
    models : list of PartModel
    n_vertices : int
    residual : bool
        Include the RBF kernel columns.

    Returns
    -------
    VertexOperator
    """
    verts, blocks, sizes = [], [], []
    for m in models:
        n = len(m.members) if residual else 0
        cols = [m.vertex_local, m.vertex_basis, np.ones((len(m.vertices), 1))]
        if n:
            cols.append(m.vertex_kernel.toarray())
        verts.append(m.vertices)
        blocks.append(np.concatenate(cols, axis=1) * m.beta[:, None])
        sizes.append(13 + n)
    return VertexOperator(verts, blocks, np.cumsum([0, *sizes]), n_vertices)


def operator_matrix(operator: VertexOperator) -> sp.csr_matrix:
    """The operator as one sparse ``(V, K)`` matrix ``H`` (``vertices(f) = H @ C(f)``)."""
    rows, cols, vals = [], [], []
    for v, blk, o in zip(operator.vertices, operator.blocks, operator.offsets):
        r, c = np.nonzero(blk)
        rows.append(v[r])
        cols.append(c + o)
        vals.append(blk[r, c])
    cat = (lambda x: np.concatenate(x)) if rows else (lambda x: np.zeros(0))
    return sp.csr_matrix((cat(vals), (cat(rows), cat(cols))),
                         shape=(operator.n_vertices, int(operator.offsets[-1])))  # fmt: skip


def frame_coefficients(
    models: list[PartModel], fits: list[PartFit], *, residual: bool
) -> np.ndarray:
    """Per-frame coefficients ``C (K, F, 3)`` matching :func:`vertex_operator`.

    Block of part ``p``: ``[R^T; (R A)^T; d; W R^T]`` so that
    ``[v̄, q, 1, φ] @ block = R (v̄ + A q + W^T φ) + d``.
    """
    if len(models) != len(fits):
        raise ValueError("frame_coefficients: one fit per model is needed")
    out = []
    for f in fits:
        out.append(f.R.transpose(2, 0, 1))  # (3, F, 3): row k = R[:, :, k]
        out.append((f.R @ f.A).transpose(2, 0, 1))  # (9, F, 3): row k = (R A)[:, :, k]
        out.append(f.d[None])  # (1, F, 3)
        if residual:
            out.append((f.W @ f.R.transpose(0, 2, 1)).transpose(1, 0, 2))  # (n, F, 3)
    return np.concatenate(out, axis=0)


def deform_positions(
    models: list[PartModel], fits: list[PartFit], n_vertices: int,
    operator: VertexOperator | None = None, *, residual: bool | None = None,
) -> np.ndarray:  # fmt: skip
    """Blend every part's moved vertices with their weights ``β`` (Eq. 9).

    Parameters
    ----------
    models : list of PartModel
    fits : list of PartFit
        One per model, same frames.
    n_vertices : int
    operator : VertexOperator, optional
        :func:`vertex_operator` of the models (built when omitted).
    residual : bool, optional
        Whether the fits carry a residual (default: any non-zero ``W``); must
        match ``operator``.

    Returns
    -------
    (F, V, 3) float ndarray
    """
    if residual is None:
        residual = any(np.any(f.W) for f in fits)
    if operator is None:
        operator = vertex_operator(models, n_vertices, residual=residual)
    C = frame_coefficients(models, fits, residual=residual)
    K, F, _ = C.shape
    if K != operator.offsets[-1]:
        raise ValueError("deform_positions: operator and fits disagree (residual?)")
    out = np.empty((F, n_vertices, 3))
    step = 16  # frames per product: keeps the (V, step, 3) -> (step, V, 3) copy in cache
    o = operator.offsets
    for a in range(0, F, step):
        b = min(F, a + step)
        X = np.zeros((n_vertices, (b - a) * 3))
        for p, (v, blk) in enumerate(zip(operator.vertices, operator.blocks)):
            if len(v):
                X[v] += blk @ C[o[p] : o[p + 1], a:b].reshape(o[p + 1] - o[p], (b - a) * 3)
        out[a:b] = X.reshape(n_vertices, b - a, 3).transpose(1, 0, 2)
    return out


def _slice_fit(fit: PartFit, sl: slice) -> PartFit:
    return PartFit(
        fit.R[sl], fit.d[sl], fit.A[sl], fit.W[sl], fit.rigid_frames[sl],
        fit.quadratic_frames[sl],
    )  # fmt: skip


def _deform_chunk(item: tuple) -> np.ndarray:
    models, fits, n_vertices, operator, residual = item
    return deform_positions(models, fits, n_vertices, operator, residual=residual)


def _without_vertices(m: PartModel) -> PartModel:
    """A copy of the model without its per-vertex arrays (cheap to ship to workers)."""
    return PartModel(
        name=m.name, members=m.members, alpha=m.alpha, local=m.local, origin=m.origin,
        axes=m.axes, scale=m.scale, q_mean=m.q_mean, sigma=m.sigma, kernel=m.kernel,
        quadratic=m.quadratic, residual_kernel=m.residual_kernel,
    )  # fmt: skip


def _fit_part_item(item: tuple[PartModel, np.ndarray], *, mode: str, min_quadratic_markers: int,
                   damping: float):  # fmt: skip
    model, x = item
    return fit_part(model, x, mode=mode, min_quadratic_markers=min_quadratic_markers,
                    damping=damping)  # fmt: skip


def align_markers(markers: Markers, segmentation: Segmentation) -> np.ndarray:
    """Positions ``(F, M, 3)`` of ``markers`` in the segmentation's marker order.

    Raises
    ------
    DeformError
        Naming the markers of the segmentation missing from the capture.
    """
    index = {m: i for i, m in enumerate(markers.labels)}
    missing = [m for m in segmentation.labels if m not in index]
    if missing:
        raise DeformError(
            f"capture lacks {len(missing)} markers of the segmentation: {missing[:10]}"
        )
    return markers.positions[:, [index[m] for m in segmentation.labels]]


@stage("deform", outputs=("mesh", "report"))
def deform(
    markers: Markers,
    segmentation: Segmentation,
    mesh: Mesh,
    *,
    mode: Mode = "quadratic_residual",
    min_quadratic_markers: int = 10,
    quadratic_damping: float = 0.3,
    dilation_factor: float = 2.0,
    beta_sharpness: float = 4.0,
    residual_kernel: ResidualKernel = "cubic_bspline",
    chunk_frames: int = 1024,
    ctx: Context,
) -> dict[str, Any]:
    """Animate a detailed mesh from markers: rigid + quadratic + RBF residual per part.

    Parameters
    ----------
    markers : Markers
        Cleaned capture ``(F, M, 3)``; must contain every segmented marker.
    segmentation : Segmentation
        Near-rigid parts with soft weights (stage ``segment``).
    mesh : Mesh
        Detailed mesh in the reference pose, overlapping the marker surface
        (stage ``fit_mesh``); ``vertices (V, 3)``.
    mode : {"rigid", "quadratic", "rigid_residual", "quadratic_residual"}
        Model per part (Figure 7 of the paper compares the four).
    min_quadratic_markers : int
        Parts (or frames) with fewer markers use the rigid transform (paper: 10).
    quadratic_damping : float
        Ridge toward rigid on the quadratic coefficients (0 = paper's Eq. 6);
        helps parts with few markers, whose quadratic extrapolates wildly.
    dilation_factor : float
        B-spline support = this × the part's largest nearest-neighbour distance.
    beta_sharpness : float
        ``β ∝ β_bary^γ`` (1 = the paper's barycentric weights); narrows the
        blend between parts, see the module docstring.
    residual_kernel : {"cubic_bspline", "thin_plate"}
        Kernel of the residual (``"cubic_bspline"`` = the paper's Eq. 7, the
        default; ``"thin_plate"``: see the module docstring).
    chunk_frames : int
        Frames per parallel evaluation task (``ctx.map``); a capture of at most
        this many frames is evaluated in one in-process pass.  Shipping the
        vertices back from worker processes costs more than the evaluation
        on a 2-core machine (see ``benchmarks/deform.py``), so the default only
        splits long captures.  The per-part fits always go through ``ctx.map``.

    Returns
    -------
    dict
        ``mesh``: animated :class:`Mesh` ``(F, V, 3)`` at the capture's rate;
        ``report``: per-part markers, mode used, fallback frames, and the RMS
        distance (mm) between the observed markers and the model's prediction.
    """
    if mesh.animated:
        raise DeformError("deform: the detailed mesh must be a single rest pose (V, 3)")
    x = align_markers(markers, segmentation)
    binding = bind_mesh(mesh.vertices, segmentation, sharpness=beta_sharpness,
                        name="detailed mesh")
    # frame-independent set-up in-process (cheap; per-vertex arrays stay here), the
    # per-part fits over all frames on the executor (small inputs and outputs)
    models = [
        prepare_part(segmentation, p, vertices=mesh.vertices, beta=binding.beta,
                     min_quadratic_markers=min_quadratic_markers,
                     dilation_factor=dilation_factor, residual_kernel=residual_kernel)
        for p in range(segmentation.n_parts)
    ]  # fmt: skip
    fits = ctx.map(
        partial(_fit_part_item, mode=mode, min_quadratic_markers=min_quadratic_markers,
                damping=quadratic_damping),
        [(_without_vertices(m), x[:, m.members]) for m in models],
    )
    for m, f in zip(models, fits):
        for msg in m.messages + f.messages:
            ctx.warn(msg)
    F = x.shape[0]
    V = mesh.vertices.shape[0]
    residual = mode.endswith("residual")
    operator = vertex_operator(models, V, residual=residual)
    bounds = list(range(0, F, max(1, chunk_frames))) + [F]
    if ctx.mapper is None or len(bounds) <= 2:  # in-process: one pass, no copies
        verts = deform_positions(models, fits, V, operator, residual=residual)
    else:  # frame chunks on the executor's workers
        light = [_without_vertices(m) for m in models]
        chunks = [
            (light, [_slice_fit(f, slice(a, b)) for f in fits], V, operator, residual)
            for a, b in zip(bounds, bounds[1:])
        ]
        verts = np.empty((F, V, 3))
        for (a, b), part in zip(zip(bounds, bounds[1:]), ctx.map(_deform_chunk, chunks)):
            verts[a:b] = part
    # how well the model reproduces the observed markers (0 up to round-off with residual)
    marker_rms = {}
    for m, f in zip(models, fits):
        pred = evaluate_part(m, f, m.local, m.basis(m.local), m.kernel.tocsr())
        err = np.linalg.norm(pred - x[:, m.members], axis=-1)
        ok = np.isfinite(err)
        marker_rms[m.name] = float(np.sqrt(np.mean(err[ok] ** 2)) * 1000) if ok.any() else None
    report = {
        "mode": mode,
        "frames": F,
        "vertices": V,
        "parts": {
            m.name: {
                "markers": int(len(m.members)),
                "vertices": int(len(m.vertices)),
                "quadratic": bool(m.quadratic and mode.startswith("quadratic")),
                "interpolated_frames": int((~f.rigid_frames).sum()),
                "rigid_only_frames": int((f.rigid_frames & ~f.quadratic_frames).sum())
                if mode.startswith("quadratic") and m.quadratic
                else 0,
                "marker_rms_mm": marker_rms[m.name],
                "dilation_mm": m.sigma * 1000 if m.residual_kernel == "cubic_bspline" else None,
            }
            for m, f in zip(models, fits)
        },
        "max_vertex_distance_to_markers_mm": float(binding.distance.max() * 1000),
    }
    out = Mesh(
        vertices=verts,
        faces=mesh.faces,
        rate=markers.rate,
        attrs={"mode": mode, "source": "deform", **{k: v for k, v in mesh.attrs.items()
                                                    if isinstance(v, (str, int, float))}},
    )
    return {"mesh": out, "report": report}
