"""Bases, radial kernels and their solves for the per-part deformation (Park & Hodgins 2006, §5.3).

* the quadratic monomials of P&H Eq. 6 (:func:`quadratic_basis`);
* the residual kernels of P&H Eq. 7: the compact cubic B-spline (:func:`cubic_bspline`,
  :func:`rbf_matrix`, dilation :func:`dilation`, shrunk until the marker system is
  well conditioned: :func:`_well_conditioned_kernel`) and the optional thin plate
  (:func:`thin_plate`, :func:`thin_plate_matrix`);
* the RBF solves: the B-spline system (:func:`_solve_kernel`) and the thin plate with
  its linear polynomial (:func:`_solve_thin_plate`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.linalg import cho_factor, cho_solve, lu_factor, lu_solve
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

__all__ = [
    "cubic_bspline",
    "dilation",
    "quadratic_basis",
    "rbf_matrix",
    "thin_plate",
    "thin_plate_matrix",
]


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


#: Most point-centre pairs for which :func:`rbf_matrix` measures every distance instead of
#: building k-d trees (a part's vertices against its markers: at most a few MB of work).
_MOST_DENSE_PAIRS = 1_000_000


def _dense_rbf_matrix(points: np.ndarray, centres: np.ndarray,
                      sig: np.ndarray) -> sp.csr_matrix | None:  # fmt: skip
    """:func:`rbf_matrix` from every distance: the pairs within ``sig.max()`` that the trees'
    ``sparse_distance_matrix`` lists, their distances summed as it sums them (``dx² + dy²
    + dz²``, the same bits), so the same matrix; None where a point coincides with a centre
    (the tree path's own rule for those)."""
    d = points[:, None, :] - centres[None, :, :]
    r = d[..., 0] * d[..., 0]
    r += d[..., 1] * d[..., 1]
    r += d[..., 2] * d[..., 2]
    np.sqrt(r, out=r)
    if not r.all():
        return None
    i, j = np.nonzero(r <= sig.max())  # row by row, columns ascending: CSR order as it is
    indptr = np.zeros(len(points) + 1, np.int64)
    np.cumsum(np.bincount(i, minlength=len(points)), out=indptr[1:])
    M = sp.csr_matrix((cubic_bspline(r[i, j] / sig[j]), j, indptr),
                      shape=(len(points), len(centres)))  # fmt: skip
    M.eliminate_zeros()
    return M


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
    if len(points) * len(centres) <= _MOST_DENSE_PAIRS:  # no trees: the same pairs and bits
        M = _dense_rbf_matrix(points, centres, sig)
        if M is not None:
            return M
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
