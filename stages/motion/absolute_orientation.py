"""Absolute orientation: the rigid motion best mapping one point set onto another.

Horn's closed form (Horn 1987, unit quaternions): the rotation is the top
eigenvector of a symmetric 4x4 matrix of the weighted cross-covariance, so it
is never a reflection.  :func:`absolute_orientation_batch` solves ``B`` sets at
once; the eigenvector comes from Theobald's QCP closed form (Newton on the
characteristic quartic, then a column of the adjugate), with ``np.linalg.eigh``
where that is ill-conditioned.  :func:`absolute_orientation` is one set, raising
:class:`DegenerateFitError` when fewer than 3 non-collinear points remain.
"""

from __future__ import annotations

import numpy as np

from mocapflow.stages.motion.rotations import quat_to_matrix

__all__ = ["DegenerateFitError", "absolute_orientation", "absolute_orientation_batch"]


class DegenerateFitError(ValueError):
    """Absolute orientation is undetermined (fewer than 3 non-collinear points)."""


#: Fast-path margins of :func:`_horn_batch` (the exact solver decides otherwise).
_SPREAD_MARGIN = 30.0  # the cheap spread test must pass by this factor
_GAP_MIN = 1e-4  # smallest eigen-gap product (relative) trusted to the closed form
_GAP_REFINE = 1e-1  # below this eigen-gap product (relative) the eigenvector is refined
_NEWTON_ITERATIONS = 40


def _weighted_moments(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Usable rows, centroids and (cross-)covariances of weighted point sets.

    Returns ``ok (B, N)``, ``cs, cx (B, 3)``, ``M = Σ w s xᵀ``, ``Css``, ``Cxx``
    (each ``(B, 3, 3)``, centred, weights normalised to sum 1).
    """
    P = np.concatenate(np.broadcast_arrays(source, target), axis=-1)  # (B, N, 6)
    fin = np.isfinite(P)
    ok = fin[..., 0] & fin[..., 1] & fin[..., 2] & fin[..., 3] & fin[..., 4] & fin[..., 5]
    ok &= np.isfinite(weights) & (weights > 0)
    w = np.where(ok, weights, 0.0)
    wsum = w.sum(-1)
    wn = w / np.where(wsum > 0, wsum, 1.0)[..., None]
    every = bool(ok.all())  # the common case: no row to zero (the same values)
    if not every:
        P = np.where(ok[..., None], P, 0.0)
    c = np.matmul(wn[:, None], P)  # (B, 1, 6) centroids
    P -= c
    if not every:
        P[~ok] = 0.0
    G = np.matmul((wn[..., None] * P).transpose(0, 2, 1), P)  # (B, 6, 6)
    return ok, c[:, 0, :3], c[:, 0, 3:], G[:, :3, 3:], G[:, :3, :3], G[:, 3:, 3:]


def _spread_ok(C: np.ndarray, tol2: float) -> np.ndarray:
    """``(B,)`` bool: second eigenvalue of each PSD ``C (B,3,3)`` above ``tol2`` × the first.

    A cheap sufficient test (``λ₂/λ₃ ≥ e₂ / 3 tr²`` with ``e₂`` the sum of the
    principal 2×2 minors) decides most sets; the rest get the exact eigenvalues.
    """
    a, b, c = C[:, 0, 0], C[:, 1, 1], C[:, 2, 2]
    tr = a + b + c
    e2 = a * b - C[:, 0, 1] * C[:, 1, 0] + a * c - C[:, 0, 2] * C[:, 2, 0]
    e2 += b * c - C[:, 1, 2] * C[:, 2, 1]
    out = (tr > 0) & (e2 > _SPREAD_MARGIN * 3.0 * tol2 * tr * tr)
    unsure = np.flatnonzero(~out)
    if len(unsure):
        lam = np.linalg.eigvalsh(C[unsure])
        out[unsure] = (lam[:, 1] > tol2 * lam[:, 2]) & (lam[:, 2] > 0)
    return out


def _horn_matrix(M: np.ndarray) -> np.ndarray:
    """Horn's symmetric ``(B, 4, 4)`` matrix of cross-covariances ``M (B, 3, 3)``."""
    Sxx, Sxy, Sxz = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    Syx, Syy, Syz = M[:, 1, 0], M[:, 1, 1], M[:, 1, 2]
    Szx, Szy, Szz = M[:, 2, 0], M[:, 2, 1], M[:, 2, 2]
    return np.stack(
        [
            np.stack([Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx], -1),
            np.stack([Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz], -1),
            np.stack([Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy], -1),
            np.stack([Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz], -1),
        ],
        axis=-2,
    )


#: Upper-triangle entries of a symmetric 4×4 matrix and the rows / columns of their minors.
_TRIU = [(i, j) for i in range(4) for j in range(i, 4)]
_KEEP = [[k for k in range(4) if k != i] for i in range(4)]
_MINOR_ROWS = np.array([_KEEP[i] for i, _ in _TRIU])[:, :, None]  # (10, 3, 1)
_MINOR_COLS = np.array([_KEEP[j] for _, j in _TRIU])[:, None, :]  # (10, 1, 3)
_MINOR_SIGN = np.array([(-1.0) ** (i + j) for i, j in _TRIU])
_TRIU_I = np.array([i for i, _ in _TRIU])
_TRIU_J = np.array([j for _, j in _TRIU])
_TRIU_DIAG = np.flatnonzero(_TRIU_I == _TRIU_J)  # (0,0), (1,1), (2,2), (3,3)
#: ``_TRIU_OF[j]``: the :data:`_TRIU` entries of column ``j`` of a symmetric 4×4 matrix.
_TRIU_OF = np.array([[_TRIU.index((min(i, j), max(i, j))) for i in range(4)] for j in range(4)])


def _cofactors(A: np.ndarray) -> np.ndarray:
    """``(B, 10)`` cofactors of symmetric ``A (B, 4, 4)`` at the :data:`_TRIU` entries."""
    m = A[:, _MINOR_ROWS, _MINOR_COLS]  # (B, 10, 3, 3)
    det = (m[..., 0, 0] * (m[..., 1, 1] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 1])
           - m[..., 0, 1] * (m[..., 1, 0] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 0])
           + m[..., 0, 2] * (m[..., 1, 0] * m[..., 2, 1] - m[..., 1, 1] * m[..., 2, 0]))
    return det * _MINOR_SIGN


def _adjugate_column(N: np.ndarray, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column of ``adj(N − λI)`` with the largest diagonal entry, and that entry.

    Returns ``(B, 4)`` (not normalised) and ``(B,)`` ``|diagonal|``.
    """
    A = N - lam[:, None, None] * np.eye(4)
    cof = _cofactors(A)
    d = np.abs(cof[:, _TRIU_DIAG])
    col = np.argmax(d, axis=-1)
    rows = np.arange(len(A))
    return cof[rows[:, None], _TRIU_OF[col]], d[rows, col]


def _row_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(B,)`` dot products of the rows of ``a, b (B, n)``, each summed left to right.

    ``np.einsum`` and ``np.linalg.norm`` sum a row with SIMD accumulators whose split
    depends on where the row lies in memory, so a set's last bit depended on its place in
    the batch (one in four sets of a real gap's 251 frames, ``c0`` of the quartic, up to
    1.6e-14 in ``R``); column by column, each row's sum is the same wherever it is.
    """
    out = a[:, 0] * b[:, 0]
    for j in range(1, a.shape[1]):
        out += a[:, j] * b[:, j]
    return out


def _top_eigenvector(N: np.ndarray, bound: np.ndarray) -> np.ndarray:
    """Unit eigenvectors ``(B, 4)`` of the largest eigenvalue of traceless symmetric ``N``.

    Closed form (Theobald's QCP): Newton on the characteristic quartic from the
    upper bound ``bound (B,)``, then the best-conditioned column of the
    adjugate of ``N − λI``.  Sets whose top eigenvalue is (nearly) repeated, or
    where Newton did not converge, are solved by ``np.linalg.eigh``.  Every
    set's result depends on that set only (not on the batch it comes in).
    """
    if len(N) == 0:
        return np.empty((0, 4))
    with np.errstate(divide="ignore", invalid="ignore"):  # failures go to eigh below
        return _top_eigenvector_closed_form(N, bound)


def _top_eigenvector_closed_form(N: np.ndarray, bound: np.ndarray) -> np.ndarray:
    B = len(N)
    # characteristic polynomial λ⁴ + c2 λ² + c1 λ + c0 (tr N = 0): c2 = -tr(N²)/2,
    # c1 = -(sum of the principal 3×3 minors), c0 = det N (along the first row)
    cof = _cofactors(N)
    c0 = _row_dot(N[:, 0, :], cof[:, :4])
    c1 = -(cof[:, 0] + cof[:, 4] + cof[:, 7] + cof[:, 9])  # the diagonal's (_TRIU_DIAG)
    c2 = -0.5 * _row_dot(N.reshape(B, 16), N.reshape(B, 16))
    lam = bound.copy()
    tol = 1e-15 * np.maximum(bound, np.finfo(float).tiny)
    todo = np.arange(B)
    for _ in range(_NEWTON_ITERATIONS):
        l_ = lam[todo]
        a2, a1, a0 = c2[todo], c1[todo], c0[todo]
        p = ((l_ * l_ + a2) * l_ + a1) * l_ + a0
        dp = (4.0 * l_ * l_ + 2.0 * a2) * l_ + a1
        step = p / dp
        lam[todo] = l_ - step
        todo = todo[~(np.abs(step) <= tol[todo])]
        if not len(todo):
            break
    # adjugate of A = N - λI (rank one, ∝ q qᵀ): take its column with the largest
    # diagonal.  Where the top eigenvalues are close, once more at the Rayleigh
    # quotient of that q (far more accurate than the Newton root).
    scale = np.maximum(bound, np.finfo(float).tiny) ** 3
    q, gap = _adjugate_column(N, lam)
    redo = np.flatnonzero(gap < _GAP_REFINE * scale)
    if len(redo):
        qn = q[redo] / np.maximum(np.sqrt(_row_dot(q[redo], q[redo])),
                                  np.finfo(float).tiny)[:, None]  # fmt: skip
        Nr = N[redo]
        lr = _row_dot(qn, np.stack([_row_dot(Nr[:, i], qn) for i in range(4)], -1))
        q[redo], gap[redo] = _adjugate_column(N[redo], lr)
    norm = np.sqrt(_row_dot(q, q))
    bad = ~(gap > _GAP_MIN * scale) | ~(norm > 0)
    bad[todo] = True
    q /= np.where(bad, 1.0, norm)[:, None]
    badi = np.flatnonzero(bad)
    if len(badi):
        q[badi] = np.linalg.eigh(N[badi])[1][..., :, -1]
    return q


def _horn_batch(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray, rel_tol: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Core of Horn's method; returns R, t, degenerate mask, valid counts."""
    ok, cs, cx, M, Css, Cxx = _weighted_moments(source, target, weights)
    n_ok = ok.sum(-1)
    tol2 = rel_tol**2
    degenerate = n_ok < 3
    B = len(ok)
    if not degenerate.any():  # the common case, without copies: the same values
        degenerate = ~(_spread_ok(Css, tol2) & _spread_ok(Cxx, tol2))
        if not degenerate.any():
            bound = 0.5 * (np.trace(Css, axis1=1, axis2=2) + np.trace(Cxx, axis1=1, axis2=2))
            R = quat_to_matrix(_top_eigenvector(_horn_matrix(M), bound))
            return R, cx - np.matmul(R, cs[..., None])[..., 0], degenerate, n_ok
    live = np.flatnonzero(~degenerate)
    degenerate[live] = ~(_spread_ok(Css[live], tol2) & _spread_ok(Cxx[live], tol2))
    live = np.flatnonzero(~degenerate)
    R = np.full((B, 3, 3), np.nan)
    t = np.full((B, 3), np.nan)
    if len(live):
        bound = 0.5 * (np.trace(Css[live], axis1=1, axis2=2) + np.trace(Cxx[live], axis1=1,
                                                                          axis2=2))
        q = _top_eigenvector(_horn_matrix(M[live]), bound)
        Rl = quat_to_matrix(q)
        R[live] = Rl
        t[live] = cx[live] - np.matmul(Rl, cs[live][..., None])[..., 0]
    return R, t, degenerate, n_ok


def absolute_orientation_batch(
    source: np.ndarray,
    target: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    rel_tol: float = 1e-7,
) -> tuple[np.ndarray, np.ndarray]:
    """Horn's closed-form absolute orientation for ``B`` point sets at once.

    Finds the rotation ``R`` and translation ``t`` minimising
    ``sum_n w_n |target_n - (R source_n + t)|^2`` (Horn 1987, unit quaternions:
    the top eigenvector of a 4x4 symmetric matrix, so never a reflection).

    Parameters
    ----------
    source, target : (B, N, 3) float ndarray
        Corresponding points; rows with a NaN in either are ignored.
    weights : (B, N) float ndarray, optional
        Non-negative weights; NaN or 0 ignores the point.
    rel_tol : float
        A set is degenerate when its second principal spread is below
        ``rel_tol`` times its first (collinear) or it has < 3 usable points.

    Returns
    -------
    R : (B, 3, 3) float ndarray
        Rotations with ``target ~ source @ R.T + t``; NaN for degenerate sets.
    t : (B, 3) float ndarray
        NaN for degenerate sets.
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if source.ndim != 3 or source.shape[-1] != 3 or source.shape != target.shape:
        raise ValueError(
            f"absolute_orientation_batch: source and target must both be (B, N, 3), "
            f"got {source.shape} and {target.shape}"
        )
    if weights is None:
        weights = np.ones(source.shape[:2])
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape != source.shape[:2]:
        raise ValueError(f"weights must be {source.shape[:2]}, got {weights.shape}")
    R, t, _, _ = _horn_batch(source, target, weights, rel_tol)
    return R, t


def absolute_orientation(
    source: np.ndarray,
    target: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    rel_tol: float = 1e-7,
) -> tuple[np.ndarray, np.ndarray]:
    """Horn's closed-form absolute orientation of one point set.

    Parameters
    ----------
    source, target : (N, 3) float ndarray
        Corresponding points; rows with a NaN are ignored.
    weights : (N,) float ndarray, optional
        Non-negative weights.
    rel_tol : float
        Collinearity tolerance (see :func:`absolute_orientation_batch`).

    Returns
    -------
    R : (3, 3) float ndarray
        Proper rotation with ``target ~ source @ R.T + t``.
    t : (3,) float ndarray

    Raises
    ------
    DegenerateFitError
        Fewer than 3 usable non-collinear points.
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if source.ndim != 2 or source.shape[-1] != 3 or source.shape != target.shape:
        raise ValueError(
            f"absolute_orientation: source and target must both be (N, 3), "
            f"got {source.shape} and {target.shape}"
        )
    w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(source),):
        raise ValueError(f"weights must be ({len(source)},), got {w.shape}")
    R, t, degenerate, n_ok = _horn_batch(source[None], target[None], w[None], rel_tol)
    if degenerate[0]:
        raise DegenerateFitError(
            f"absolute_orientation needs at least 3 non-collinear points with positive "
            f"weight in both source and target; got {int(n_ok[0])} usable of {len(source)} "
            f"and they are collinear or coincident"
            if n_ok[0] >= 3
            else f"absolute_orientation needs at least 3 non-collinear points with positive "
            f"weight; got {int(n_ok[0])} usable of {len(source)}"
        )
    return R[0], t[0]
