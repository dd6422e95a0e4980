"""The numerical core of the IK clean-up (Lau, Bar-Joseph & Kuffner 2009, §7, Eq. 7).

Lau Eq. 7 asks of every frame's pose ``q`` (paper weights w₁ = 1, w₂ = 5)

    w₁ ‖q − q̄‖² + w₂ ‖q − 2 q₋₁ + q₋₂‖²   minimal, the constraints met,

with ``q̄`` the network's predicted mean.  Here the sum of it over all frames
of a clip is minimised at once, so a frame's smoothness term sees the frames
after it as well as those before (solved frame by frame, the term can only
follow the past, and corrections ring):

* :func:`eq7_track`: every DOF without constraints, within its joint limits
  (a banded linear solve; columns it takes beyond a limit again within the
  limits by :func:`projected_gauss_newton`);
* :func:`solve_limb`: one limb's DOFs over the whole clip with its effector
  targets as stiff penalties (:func:`projected_gauss_newton`, bounds = joint
  limits, a sparse Jacobian from :class:`ChainFK` by finite differences).

Here ``w₂`` weighs second differences of model frames: the ``ik`` stage
scales the paper's weight, given at 60 fps, to the model's rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.linalg import solveh_banded
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation

from mocapflow.stages.motion.datatypes import Skeleton
from mocapflow.stages.motion.rotations import quat_to_matrix
from mocapflow.stages.variation.dofs import padded_order

__all__ = ["ChainFK", "LimbSolve", "eq7_track", "projected_gauss_newton", "solve_limb"]

_FD_STEP = 1e-6  # radians, the finite-difference step of the effector Jacobian


def second_difference(n: int) -> sparse.csr_matrix:
    """The ``(n − 2, n)`` operator ``q_t − 2 q_{t+1} + q_{t+2}``."""
    return sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(max(n - 2, 0), n), format="csr")


def eq7_track(
    qbar: np.ndarray, low: np.ndarray, high: np.ndarray, *, w1: float, w2: float
) -> np.ndarray:
    """Lau Eq. 7 without constraints over a whole clip, every DOF within its limits.

    Per DOF column, ``q = argmin w₁ Σ_t (q_t − q̄_t)² + w₂ Σ_t (q_t − 2 q_{t−1} + q_{t−2})²``
    subject to ``low ≤ q ≤ high``.

    Parameters
    ----------
    qbar : (F, D) float ndarray
        The predicted means (or the sample).
    low, high : (D,) float ndarray
        Joint limits (``±inf``: none).
    w1, w2 : float
        Closeness and smoothness weights (``w1 > 0``).

    Returns
    -------
    (F, D) float ndarray
    """
    qbar = np.asarray(qbar, dtype=np.float64)
    F = qbar.shape[0]
    if F < 3 or w2 == 0:
        return np.clip(qbar, low, high)
    D2 = second_difference(F)
    M = (D2.T @ D2).tocsr()
    ab = np.zeros((3, F))  # upper banded form of w1 I + w2 D2ᵀD2
    ab[2] = w1 + w2 * M.diagonal(0)
    ab[1, 1:] = w2 * M.diagonal(1)
    ab[0, 2:] = w2 * M.diagonal(2)
    q = solveh_banded(ab, w1 * qbar, check_finite=False)
    out = (q < low - 1e-12) | (q > high + 1e-12)
    bad = np.flatnonzero(out.any(axis=0))
    if bad.size:  # the bounded columns: a linear least-squares problem within the limits
        A = sparse.vstack([np.sqrt(w1) * sparse.identity(F), np.sqrt(w2) * D2]).tocsr()
        zeros = np.zeros(F - 2)
        for d in bad:
            b = np.concatenate([np.sqrt(w1) * qbar[:, d], zeros])
            lo, hi = np.full(F, low[d]), np.full(F, high[d])
            q[:, d], _ = projected_gauss_newton(lambda x, b=b: A @ x - b, lambda x: A,
                                                np.clip(q[:, d], lo, hi), lo, hi, max_iter=50)
    return q


class ChainFK:
    """Forward kinematics of one limb at many frames, batched over candidate DOF vectors.

    Rotation matrices from :class:`scipy.spatial.transform.Rotation` (upper-case
    order = intrinsic, the convention of
    :func:`~mocapflow.stages.motion.kinematics.euler_to_quat`).

    Parameters
    ----------
    sk : Skeleton
    joints : list of int
        The chain, top first.
    dof_slots : list of (int, int)
        ``(chain position, Euler slot)`` of each varied DOF.
    effectors : list of int
        Effector joints (children of chain joints).
    angles : (F, J_c, 3) float ndarray
        Euler angles of the chain joints at every frame (padded channel order).
    gpar : (F, 4) float ndarray
        Global rotation (quaternion) of the chain top's parent at every frame.
    ppar : (F, 3) float ndarray
        Global position of the chain top's parent at every frame.
    """

    def __init__(self, sk: Skeleton, joints: list[int], dof_slots: list[tuple[int, int]],
                 effectors: list[int], angles: np.ndarray, gpar: np.ndarray,
                 ppar: np.ndarray):
        self.dof_slots = dof_slots
        self.angles = np.asarray(angles, dtype=np.float64)
        self.Gpar = quat_to_matrix(np.asarray(gpar, dtype=np.float64))
        self.ppar = np.asarray(ppar, dtype=np.float64)
        self.orders = [padded_order(sk.rotation_order(j)) for j in joints]
        self.offsets = sk.offsets[joints]
        self.eff_parent = [joints.index(int(sk.parents[e])) for e in effectors]
        self.eff_offset = sk.offsets[effectors]

    def __call__(self, q: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Effector positions ``(N, E, 3)`` of DOF vectors ``q (N, V)`` at ``frames (N,)``."""
        q = np.atleast_2d(q)
        ang = self.angles[frames].copy()
        for v, (pos, slot) in enumerate(self.dof_slots):
            ang[:, pos, slot] = q[:, v]
        G = self.Gpar[frames]
        p = self.ppar[frames]
        gl, pl = [], []
        for k in range(len(self.orders)):
            p = p + G @ self.offsets[k]
            G = G @ Rotation.from_euler(self.orders[k], ang[:, k]).as_matrix()
            gl.append(G)
            pl.append(p)
        return np.stack(
            [pl[k] + gl[k] @ off for k, off in zip(self.eff_parent, self.eff_offset)], axis=1
        )


@dataclass(frozen=True)
class LimbSolve:
    """Result of :func:`solve_limb`.

    Attributes
    ----------
    q : (F, V) float ndarray
        The limb's DOFs.
    error : (N,) float ndarray
        Distance of each constrained effector from its target, metres.
    """

    q: np.ndarray
    error: np.ndarray


def solve_limb(
    fk: ChainFK,
    x0: np.ndarray,
    qbar: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    frames: np.ndarray,
    effector: np.ndarray,
    target: np.ndarray,
    weight: np.ndarray,
    *,
    w1: float,
    w2: float,
    w_ease: float,
    stiffness: float,
    max_iter: int,
) -> LimbSolve:
    """Lau Eq. 7 for one limb over a whole clip, its targets as stiff penalties.

    Minimises ``Σ_t w₁ ‖q_t − q̄_t‖² + w₂ ‖Δ²q_t‖² + w_e ‖Δ²(q_t − x0_t)‖²
    + ρ Σ_n c_n ‖FK_{e_n}(q_{t_n}) − p_n‖²`` over ``low ≤ q ≤ high``, where
    ``Δ²q_t = q_t − 2 q_{t−1} + q_{t−2}``.  With ``x0`` the unconstrained
    solve (:func:`eq7_track`) the third term smooths only the correction the
    targets make: it eases in and out over about ``(w_e / w₁)^¼`` frames
    instead of Eq. 7's ``(w₂ / w₁)^¼`` (1.5 frames at the paper's weights),
    so planting a foot adds no jerk (it also smooths the correction inside a
    stance, where targets that cannot all be met would make it jump).

    Parameters
    ----------
    fk : ChainFK
        The limb's forward kinematics (the rest of the body fixed).
    x0 : (F, V) float ndarray
        The unconstrained solve (:func:`eq7_track` of ``qbar``, within the limits):
        the start, and what the correction is measured from.
    qbar : (F, V) float ndarray
        The predicted means of the limb's DOFs.
    low, high : (V,) float ndarray
        Joint limits.
    frames, effector : (N,) int ndarray
        Frame and effector (index into ``fk``'s effectors) of each constraint.
    target : (N, 3) float ndarray
        Its target position, metres.
    weight : (N,) float ndarray
        Its weight relative to ``stiffness``.
    w1, w2 : float
        Lau Eq. 7's weights.
    w_ease : float
        Smoothness weight of the correction from ``x0``.
    stiffness : float
        ``ρ``, per m² (1 mm off costs ``ρ · 1e-6``, as ``√(ρ · 1e-6 / w₁)`` rad off ``q̄``).
    max_iter : int
        Gauss–Newton steps at most (:func:`projected_gauss_newton`).

    Returns
    -------
    LimbSolve
    """
    F, V = x0.shape
    N = len(frames)
    s1, s2, se = np.sqrt(w1), np.sqrt(w2), np.sqrt(w_ease)
    sc = np.sqrt(stiffness * np.asarray(weight, dtype=np.float64))[:, None]  # (N, 1)
    D2 = sparse.kron(second_difference(F), sparse.identity(V), format="csr")
    n_eff = np.arange(N)
    lo, hi = np.tile(low, F), np.tile(high, F)
    steps = np.concatenate([np.zeros((1, V)), _FD_STEP * np.eye(V)])  # (V + 1, V)
    J_fixed = sparse.vstack([s1 * sparse.identity(F * V), s2 * D2, se * D2]).tocsr()
    ease0 = se * (D2 @ np.asarray(x0, dtype=np.float64).ravel())
    cols = (frames[None, :, None] * V + np.arange(V)[:, None, None])  # (V, N, 1)
    cols = np.broadcast_to(cols, (V, N, 3))
    rows = np.broadcast_to(np.arange(3 * N).reshape(1, N, 3), (V, N, 3))

    def effector_positions(X: np.ndarray) -> np.ndarray:
        return fk(X[frames], frames)[n_eff, effector]

    def residuals(x: np.ndarray) -> np.ndarray:
        X = x.reshape(F, V)
        d2 = D2 @ x
        return np.concatenate([s1 * (X - qbar).ravel(), s2 * d2, se * d2 - ease0,
                               (sc * (effector_positions(X) - target)).ravel()])

    def jacobian(x: np.ndarray) -> sparse.csr_matrix:
        X = x.reshape(F, V)
        Q = (X[frames][None] + steps[:, None]).reshape(-1, V)  # ((V + 1) N, V)
        P = fk(Q, np.tile(frames, V + 1)).reshape(V + 1, N, -1, 3)[:, n_eff, effector]
        d = sc[None] * (P[1:] - P[0]) / _FD_STEP  # (V, N, 3)
        Jc = sparse.csr_matrix((d.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * N, F * V))
        return sparse.vstack([J_fixed, Jc]).tocsr()

    start = np.clip(x0, low, high).ravel()
    if N == 0:
        return LimbSolve(q=start.reshape(F, V), error=np.zeros(0))
    x, _ = projected_gauss_newton(residuals, jacobian, start, lo, hi, max_iter=max_iter)
    X = x.reshape(F, V)
    err = np.linalg.norm(effector_positions(X) - target, axis=1)
    return LimbSolve(q=X, error=err)


def projected_gauss_newton(
    residuals, jacobian, x0: np.ndarray, low: np.ndarray, high: np.ndarray, *,
    max_iter: int, ftol: float = 1e-10,
) -> tuple[np.ndarray, int]:
    """Bound-constrained nonlinear least squares by projected Gauss–Newton steps.

    Each step solves the Gauss–Newton normal equations ``JᵀJ δ = −Jᵀr`` by a
    sparse LU factorisation (:func:`scipy.sparse.linalg.splu`) over the
    variables not held at a bound (a bound holds a variable whose gradient
    points outwards), projects ``x + α δ`` onto the bounds and halves ``α``
    until the cost falls.  On the limb problems of :func:`solve_limb` (a few
    hundred to a few thousand variables, block-banded ``JᵀJ``, targets 10³
    times stiffer than Eq. 7's terms) this converges in tens of steps where
    :func:`scipy.optimize.least_squares` (``trf`` with ``lsmr``, the sparse
    option) spent hundreds of inner iterations per step.

    Parameters
    ----------
    residuals : callable
        ``x (n,) -> r (m,)``.
    jacobian : callable
        ``x (n,) -> J (m, n)`` sparse.
    x0 : (n,) float ndarray
        Start, within the bounds.
    low, high : (n,) float ndarray
        Bounds (``±inf``: none).
    max_iter : int
        Gauss–Newton steps at most.
    ftol : float
        Stop when a step lowers the cost by less than this fraction.

    Returns
    -------
    x : (n,) float ndarray
    steps : int
    """
    x = np.clip(x0, low, high)
    r = residuals(x)
    cost = float(r @ r)
    n = x.size
    steps = 0
    while steps < max_iter:
        steps += 1
        J = jacobian(x)
        g = J.T @ r
        held = ((x <= low) & (g > 0)) | ((x >= high) & (g < 0))
        free = np.flatnonzero(~held)
        if free.size == 0:
            break
        H = (J.T @ J).tocsc()[free][:, free]
        H = H + sparse.identity(free.size, format="csc") * (1e-12 * H.diagonal().max() + 1e-15)
        delta = np.zeros(n)
        delta[free] = splu(H).solve(-g[free])
        alpha, accepted = 1.0, False
        while alpha >= 1.0 / 64:
            xn = np.clip(x + alpha * delta, low, high)
            rn = residuals(xn)
            cn = float(rn @ rn)
            if cn < cost:
                accepted = True
                break
            alpha /= 2
        if not accepted:
            break
        drop = cost - cn
        x, r, cost = xn, rn, cn
        if drop <= ftol * max(cost, 1e-300):
            break
    return x, steps
