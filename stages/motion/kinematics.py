"""Kinematics: quaternion algebra, Euler angles, forward kinematics, absolute orientation.

Also the motion helpers several graphs share: :func:`motion_positions` (global
joint positions of a motion), :func:`heading_split` / :func:`yaw_quaternion` (the
root's heading about the up axis and the rest), :func:`euler_continuity`
(continuous Euler tracks) and :func:`resample_motion`.

Conventions
-----------
* Quaternions are ``(..., 4)`` float arrays ``(w, x, y, z)``: Hamilton product,
  *active* rotations (``quat_rotate(q, v)`` turns the vector ``v``), unit norm.
  ``quat_multiply(a, b)`` applies ``b`` first, then ``a``.
* Euler angles follow BVH: ``order`` is the rotation-channel order string (e.g.
  ``"ZXY"``) and the rotation is ``R = R_Z(a0) @ R_X(a1) @ R_Y(a2)`` (intrinsic
  rotations about the moving axes, angles given in channel order).  The 6
  Tait-Bryan (``XYZ`` ...) and the 6 proper Euler (``ZXZ`` ...) orders are supported.
* Every function broadcasts over leading axes; nothing loops over frames.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

if TYPE_CHECKING:  # pragma: no cover
    from mocapflow.stages.motion.datatypes import Motion, Skeleton

__all__ = [
    "EULER_ORDERS",
    "DegenerateFitError",
    "absolute_orientation",
    "absolute_orientation_batch",
    "end_site_positions",
    "euler_continuity",
    "heading_split",
    "motion_positions",
    "yaw_quaternion",
    "euler_to_quat",
    "forward_kinematics",
    "quat_angle",
    "quat_average",
    "quat_conjugate",
    "quat_continuity",
    "quat_exp",
    "quat_from_6d",
    "quat_from_axis_angle",
    "quat_from_matrix",
    "quat_from_rotvec",
    "quat_identity",
    "quat_inverse",
    "quat_log",
    "quat_multiply",
    "quat_normalize",
    "quat_rotate",
    "quat_slerp",
    "quat_to_6d",
    "quat_to_euler",
    "quat_to_matrix",
    "quat_to_rotvec",
    "resample_motion",
]

#: The 12 supported rotation orders (6 Tait-Bryan, 6 proper Euler).
EULER_ORDERS: tuple[str, ...] = (
    "XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX",
    "XYX", "XZX", "YXY", "YZY", "ZXZ", "ZYZ",
)  # fmt: skip

_AXIS = {"X": 0, "Y": 1, "Z": 2}


class DegenerateFitError(ValueError):
    """Absolute orientation is undetermined (fewer than 3 non-collinear points)."""


# --------------------------------------------------------------------------- algebra


def quat_identity(shape: tuple[int, ...] = ()) -> np.ndarray:
    """Identity quaternions.

    Parameters
    ----------
    shape : tuple of int
        Leading shape.

    Returns
    -------
    q : (*shape, 4) float ndarray
    """
    q = np.zeros((*shape, 4))
    q[..., 0] = 1.0
    return q


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` (rotation ``b`` first, then ``a``).

    Parameters
    ----------
    a, b : (..., 4) float ndarray
        Broadcastable quaternions ``(w, x, y, z)``.

    Returns
    -------
    (..., 4) float ndarray
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate ``(w, -x, -y, -z)``.

    Parameters
    ----------
    q : (..., 4) float ndarray

    Returns
    -------
    (..., 4) float ndarray
    """
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_inverse(q: np.ndarray) -> np.ndarray:
    """Multiplicative inverse (conjugate over squared norm; any non-zero quaternion).

    Parameters
    ----------
    q : (..., 4) float ndarray

    Returns
    -------
    (..., 4) float ndarray
    """
    q = np.asarray(q, dtype=np.float64)
    return quat_conjugate(q) / np.sum(q * q, axis=-1, keepdims=True)


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Scale to unit norm (zero quaternions become NaN).

    Parameters
    ----------
    q : (..., 4) float ndarray

    Returns
    -------
    (..., 4) float ndarray
    """
    q = np.asarray(q, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors by unit quaternions.

    Parameters
    ----------
    q : (..., 4) float ndarray
        Unit quaternions.
    v : (..., 3) float ndarray
        Vectors (broadcast against ``q``'s leading axes).

    Returns
    -------
    (..., 3) float ndarray
        ``R(q) @ v``.
    """
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    w = q[..., :1]
    u = q[..., 1:]
    uv = np.cross(u, v)
    return v + 2.0 * (w * uv + np.cross(u, uv))


def quat_from_axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Quaternion of a rotation by ``angle`` (radians) about ``axis``.

    Parameters
    ----------
    axis : (..., 3) float ndarray
        Rotation axes (normalised here).
    angle : (...) float ndarray

    Returns
    -------
    (..., 4) float ndarray
    """
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    half = 0.5 * np.asarray(angle, dtype=np.float64)[..., None]
    return np.concatenate([np.cos(half), np.sin(half) * axis], axis=-1)


def quat_log(q: np.ndarray) -> np.ndarray:
    """Quaternion logarithm of unit quaternions: ``axis * theta / 2``.

    Parameters
    ----------
    q : (..., 4) float ndarray
        Unit quaternions (``q`` and ``-q`` give different logs).

    Returns
    -------
    (..., 3) float ndarray
    """
    q = np.asarray(q, dtype=np.float64)
    v = q[..., 1:]
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    w = q[..., :1]
    half = np.arctan2(n, w)
    small = n < 1e-12
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(small, 1.0 / np.where(w == 0, 1.0, w), half / np.where(small, 1.0, n))
    return v * scale


def quat_exp(v: np.ndarray) -> np.ndarray:
    """Quaternion exponential of pure quaternions ``(0, v)``.

    Parameters
    ----------
    v : (..., 3) float ndarray
        ``axis * theta / 2``.

    Returns
    -------
    (..., 4) float ndarray
        ``(cos|v|, sin|v| v/|v|)``.
    """
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.concatenate([np.cos(n), np.sinc(n / np.pi) * v], axis=-1)


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation vectors ``axis * theta`` with ``theta`` in ``[0, pi]``.

    Parameters
    ----------
    q : (..., 4) float ndarray

    Returns
    -------
    (..., 3) float ndarray
    """
    q = np.asarray(q, dtype=np.float64)
    q = np.where(q[..., :1] < 0, -q, q)
    return 2.0 * quat_log(q)


def quat_from_rotvec(r: np.ndarray) -> np.ndarray:
    """Unit quaternions from rotation vectors ``axis * theta``.

    Parameters
    ----------
    r : (..., 3) float ndarray

    Returns
    -------
    (..., 4) float ndarray
    """
    return quat_exp(0.5 * np.asarray(r, dtype=np.float64))


def quat_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotations (radians, in ``[0, pi]``).

    Parameters
    ----------
    a, b : (..., 4) float ndarray
        Unit quaternions (sign ignored).

    Returns
    -------
    (...) float ndarray
    """
    d = quat_multiply(quat_conjugate(a), b)
    return 2.0 * np.arctan2(np.linalg.norm(d[..., 1:], axis=-1), np.abs(d[..., 0]))


def quat_slerp(a: np.ndarray, b: np.ndarray, t: np.ndarray | float) -> np.ndarray:
    """Spherical linear interpolation along the shorter arc.

    Parameters
    ----------
    a, b : (..., 4) float ndarray
        Unit quaternions (broadcastable).
    t : float or (...) float ndarray
        Interpolation parameter, 0 gives ``a``, 1 gives ``b`` (or ``-b``).

    Returns
    -------
    (..., 4) float ndarray
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)[..., None]
    d = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(d < 0, -b, b)
    d = np.abs(d)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    s = np.sin(theta)
    near = s < 1e-8
    s_safe = np.where(near, 1.0, s)
    wa = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / s_safe)
    wb = np.where(near, t, np.sin(t * theta) / s_safe)
    return quat_normalize(wa * a + wb * b)


def quat_continuity(q: np.ndarray, axis: int = 0) -> np.ndarray:
    """Flip signs so consecutive quaternions along ``axis`` have a non-negative dot.

    Parameters
    ----------
    q : (..., 4) float ndarray
    axis : int
        Sequence axis (e.g. frames); must not be the last axis.

    Returns
    -------
    (..., 4) float ndarray
        Same rotations, sign-continuous along ``axis``.
    """
    q = np.asarray(q, dtype=np.float64)
    ax = axis % q.ndim
    if ax == q.ndim - 1:
        raise ValueError("quat_continuity: axis must not be the quaternion axis")
    if q.shape[ax] < 2:
        return q.copy()
    qm = np.moveaxis(q, ax, 0)
    d = np.sum(qm[1:] * qm[:-1], axis=-1)
    sign = np.where(d < 0, -1.0, 1.0)
    flips = np.concatenate([np.ones_like(sign[:1]), np.cumprod(sign, axis=0)], axis=0)
    return np.moveaxis(qm * flips[..., None], 0, ax)


def quat_average(q: np.ndarray, weights: np.ndarray | None = None, axis: int = 0) -> np.ndarray:
    """Weighted average rotation (Markley et al. 2007: top eigenvector of ``sum w q q^T``).

    Parameters
    ----------
    q : (..., 4) float ndarray
        Unit quaternions (sign irrelevant).
    weights : ndarray, optional
        Non-negative weights of the shape of ``q.shape[axis]`` (or of
        ``q.shape[:-1]``); NaN quaternions are ignored.
    axis : int
        Axis averaged over.

    Returns
    -------
    (..., 4) float ndarray
        ``q`` without ``axis``; the representative with ``w >= 0``.
    """
    q = np.asarray(q, dtype=np.float64)
    ax = axis % q.ndim
    if ax == q.ndim - 1:
        raise ValueError("quat_average: axis must not be the quaternion axis")
    qm = np.moveaxis(q, ax, 0)
    if weights is None:
        w = np.ones(qm.shape[:-1])
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.ndim == 1:
            w = w.reshape((-1,) + (1,) * (qm.ndim - 2))
        else:
            w = np.moveaxis(w, ax, 0)
        w = np.broadcast_to(w, qm.shape[:-1])
    ok = np.isfinite(qm).all(axis=-1) & np.isfinite(w)
    w = np.where(ok, w, 0.0)
    qz = np.where(ok[..., None], qm, 0.0)
    M = np.einsum("n...,n...i,n...j->...ij", w, qz, qz)
    _, vecs = np.linalg.eigh(M)
    avg = vecs[..., :, -1]
    avg = np.where(avg[..., :1] < 0, -avg, avg)
    empty = ~(w > 0).any(axis=0)
    return np.where(empty[..., None], np.nan, avg)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions.

    Parameters
    ----------
    q : (..., 4) float ndarray

    Returns
    -------
    (..., 3, 3) float ndarray
    """
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = np.moveaxis(q, -1, 0)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    R = np.stack(
        [
            1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
            2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
            2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
        ],
        axis=-1,
    )  # fmt: skip
    return R.reshape(q.shape[:-1] + (3, 3))


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (``w >= 0``) of rotation matrices (Shepperd's method).

    Parameters
    ----------
    R : (..., 3, 3) float ndarray

    Returns
    -------
    (..., 4) float ndarray
    """
    R = np.asarray(R, dtype=np.float64)
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    # the four candidates (each scaled by 4 * its dominant component)
    cands = np.stack(
        [
            np.stack([1 + tr, m21 - m12, m02 - m20, m10 - m01], -1),
            np.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
            np.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], -1),
            np.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )
    pick = np.argmax(np.stack([tr, m00, m11, m22], -1), axis=-1)
    q = np.take_along_axis(cands, pick[..., None, None], axis=-2)[..., 0, :]
    q = quat_normalize(q)
    return np.where(q[..., :1] < 0, -q, q)


def quat_to_6d(q: np.ndarray) -> np.ndarray:
    """6-D rotation representation (Zhou et al. 2019): the first two matrix columns.

    Parameters
    ----------
    q : (..., 4) float ndarray

    Returns
    -------
    (..., 6) float ndarray
        ``[R[:, 0], R[:, 1]]``.
    """
    R = quat_to_matrix(q)
    return np.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)


def quat_from_6d(d6: np.ndarray) -> np.ndarray:
    """Inverse of :func:`quat_to_6d` (Gram-Schmidt on the two columns).

    Parameters
    ----------
    d6 : (..., 6) float ndarray

    Returns
    -------
    (..., 4) float ndarray
    """
    d6 = np.asarray(d6, dtype=np.float64)
    a = d6[..., :3] / np.linalg.norm(d6[..., :3], axis=-1, keepdims=True)
    b = d6[..., 3:] - np.sum(a * d6[..., 3:], axis=-1, keepdims=True) * a
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    c = np.cross(a, b)
    return quat_from_matrix(np.stack([a, b, c], axis=-1))


# --------------------------------------------------------------------------- Euler


def _check_order(order: str) -> str:
    o = str(order).upper()
    if o not in EULER_ORDERS:
        raise ValueError(
            f"unknown rotation order {order!r}; expected one of {', '.join(EULER_ORDERS)}"
        )
    return o


def euler_to_quat(angles: np.ndarray, order: str, *, degrees: bool = False) -> np.ndarray:
    """Quaternions of Euler angles in BVH channel order.

    Parameters
    ----------
    angles : (..., 3) float ndarray
        Angles in channel order (``angles[..., 0]`` about ``order[0]``).
    order : str
        One of :data:`EULER_ORDERS`; ``R = R_order[0] @ R_order[1] @ R_order[2]``.
    degrees : bool
        Angles in degrees.

    Returns
    -------
    (..., 4) float ndarray
    """
    o = _check_order(order)
    a = np.asarray(angles, dtype=np.float64)
    if a.shape[-1:] != (3,):
        raise ValueError(f"euler_to_quat: angles must be (..., 3), got {a.shape}")
    if degrees:
        a = np.deg2rad(a)
    half = 0.5 * a
    c, s = np.cos(half), np.sin(half)
    q = None
    for k, letter in enumerate(o):
        qk = np.zeros(a.shape[:-1] + (4,))
        qk[..., 0] = c[..., k]
        qk[..., 1 + _AXIS[letter]] = s[..., k]
        q = qk if q is None else quat_multiply(q, qk)
    return q


def quat_to_euler(q: np.ndarray, order: str, *, degrees: bool = False) -> np.ndarray:
    """Euler angles (BVH channel order) of unit quaternions.

    Parameters
    ----------
    q : (..., 4) float ndarray
    order : str
        One of :data:`EULER_ORDERS`, meaning ``R = R_order[0] @ R_order[1] @ R_order[2]``.
    degrees : bool
        Return degrees.

    Returns
    -------
    (..., 3) float ndarray
        Angles in channel order; the middle angle in ``[-pi/2, pi/2]`` (Tait-Bryan)
        or ``[0, pi]`` (proper Euler); at gimbal lock the last angle is 0.
    """
    o = _check_order(order)
    q = np.asarray(q, dtype=np.float64)
    lead = q.shape[:-1]
    flat = q.reshape(-1, 4)
    if flat.shape[0] == 0:
        return np.zeros(lead + (3,))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # gimbal lock: last angle set to 0
        # upper-case sequence = intrinsic rotations = R_a @ R_b @ R_c
        e = Rotation.from_quat(flat[:, [1, 2, 3, 0]]).as_euler(o, degrees=degrees)
    return e.reshape(lead + (3,))


# --------------------------------------------------------------------------- skeletons


def forward_kinematics(
    skeleton: Skeleton,
    rotations: np.ndarray,
    root_position: np.ndarray,
    *,
    translations: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Joint world positions and orientations.

    A joint's world position is its parent's plus the parent's world rotation
    applied to the joint's offset (or to its per-frame translation, for joints
    with position channels); the root sits at ``root_position``.

    Parameters
    ----------
    skeleton : Skeleton
        ``J`` joints, parents before children.
    rotations : (F, J, 4) float ndarray
        Local joint rotations (unit quaternions).
    root_position : (F, 3) float ndarray
        Root world position.
    translations : (F, J, 3) float ndarray, optional
        Per-frame local translations; where finite they replace the offsets of
        non-root joints.

    Returns
    -------
    positions : (F, J, 3) float ndarray
    global_rotations : (F, J, 4) float ndarray
    """
    rotations = np.asarray(rotations, dtype=np.float64)
    root_position = np.asarray(root_position, dtype=np.float64)
    J = skeleton.n_joints
    if rotations.shape[-2:] != (J, 4):
        raise ValueError(
            f"forward_kinematics: rotations must be (F, {J}, 4), got {rotations.shape}"
        )
    lead = rotations.shape[:-2]
    offsets = np.broadcast_to(skeleton.offsets, lead + (J, 3))
    if translations is not None:
        translations = np.asarray(translations, dtype=np.float64)
        offsets = np.where(np.isfinite(translations), translations, offsets)
    pos = np.empty(lead + (J, 3))
    grot = np.empty(lead + (J, 4))
    pos[..., 0, :] = np.broadcast_to(root_position, lead + (3,))
    grot[..., 0, :] = rotations[..., 0, :]
    parents = skeleton.parents
    for j in range(1, J):
        p = parents[j]
        grot[..., j, :] = quat_multiply(grot[..., p, :], rotations[..., j, :])
        pos[..., j, :] = pos[..., p, :] + quat_rotate(grot[..., p, :], offsets[..., j, :])
    return pos, grot


def end_site_positions(
    skeleton: Skeleton, positions: np.ndarray, global_rotations: np.ndarray
) -> np.ndarray:
    """World positions of the End Sites.

    Parameters
    ----------
    skeleton : Skeleton
    positions : (F, J, 3) float ndarray
        Joint world positions (from :func:`forward_kinematics`).
    global_rotations : (F, J, 4) float ndarray

    Returns
    -------
    (F, E, 3) float ndarray
    """
    ep = skeleton.end_parents
    return positions[..., ep, :] + quat_rotate(global_rotations[..., ep, :], skeleton.end_offsets)


# --------------------------------------------------------------------------- Horn


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
    P = np.where(ok[..., None], P, 0.0)
    c = np.matmul(wn[:, None], P)  # (B, 1, 6) centroids
    P -= c
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
    adj = np.empty_like(A)
    adj[:, _TRIU_I, _TRIU_J] = cof
    adj[:, _TRIU_J, _TRIU_I] = cof
    d = np.abs(cof[:, _TRIU_DIAG])
    col = np.argmax(d, axis=-1)
    return (np.take_along_axis(adj, col[:, None, None], axis=2)[..., 0],
            np.take_along_axis(d, col[:, None], axis=1)[:, 0])


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
    c0 = np.einsum("bj,bj->b", N[:, 0, :], cof[:, :4])
    c1 = -cof[:, _TRIU_DIAG].sum(1)
    c2 = -0.5 * np.einsum("bij,bij->b", N, N)
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
        qn = q[redo] / np.maximum(np.linalg.norm(q[redo], axis=-1), np.finfo(float).tiny)[:, None]
        lr = np.einsum("bi,bij,bj->b", qn, N[redo], qn)
        q[redo], gap[redo] = _adjugate_column(N[redo], lr)
    norm = np.linalg.norm(q, axis=-1)
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
    live = np.flatnonzero(~degenerate)
    degenerate[live] = ~(_spread_ok(Css[live], tol2) & _spread_ok(Cxx[live], tol2))
    live = np.flatnonzero(~degenerate)
    B = len(ok)
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


# --------------------------------------------------------------------------- resampling


def resample_motion(motion: Motion, rate: float) -> Motion:
    """Resample a motion to another frame rate over the same duration.

    Rotations are slerped, root position and translations linearly interpolated.
    The new motion has ``floor((F - 1) * rate / motion.rate) + 1`` frames, frame
    ``k`` at time ``k / rate``.

    Parameters
    ----------
    motion : Motion
        ``F`` frames at ``motion.rate``.
    rate : float
        New frames per second (> 0).

    Returns
    -------
    Motion
        Same skeleton and attrs; ``attrs["resampled_from_rate"]`` records the old rate.
    """
    rate = float(rate)
    if not rate > 0:
        raise ValueError(f"resample_motion: rate must be > 0, got {rate}")
    F = motion.n_frames
    if rate == motion.rate or F == 0:
        return motion.replace()
    duration = (F - 1) / motion.rate
    n_new = int(np.floor(duration * rate + 1e-9)) + 1
    u = np.arange(n_new) * (motion.rate / rate)
    i0 = np.clip(np.floor(u).astype(np.int64), 0, F - 1)
    i1 = np.minimum(i0 + 1, F - 1)
    frac = np.clip(u - i0, 0.0, 1.0)
    rot = quat_continuity(motion.rotations, axis=0)
    rotations = quat_slerp(rot[i0], rot[i1], frac[:, None])
    fr = frac[:, None]
    root = motion.root_position[i0] * (1 - fr) + motion.root_position[i1] * fr
    trans = None
    if motion.translations is not None:
        fr3 = frac[:, None, None]
        trans = motion.translations[i0] * (1 - fr3) + motion.translations[i1] * fr3
    attrs = dict(motion.attrs)
    attrs.setdefault("resampled_from_rate", motion.rate)
    return motion.replace(
        root_position=root, rotations=rotations, rate=rate, translations=trans, attrs=attrs
    )


def yaw_quaternion(angle: np.ndarray) -> np.ndarray:
    """Rotation by ``angle`` (radians) about the up axis ``y``.

    Parameters
    ----------
    angle : (...) float ndarray

    Returns
    -------
    (..., 4) float ndarray
    """
    a = 0.5 * np.asarray(angle, dtype=np.float64)
    z = np.zeros_like(a)
    return np.stack([np.cos(a), z, np.sin(a), z], axis=-1)


def heading_split(root_rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split root rotations into heading (twist about ``y``) and the rest.

    ``q = yaw_quaternion(heading) * local`` with ``local`` free of twist about ``y``.

    Parameters
    ----------
    root_rotations : (F, 4) float ndarray

    Returns
    -------
    heading : (F,) float ndarray
        Radians, unwrapped along frames.
    local : (F, 4) float ndarray
    """
    q = np.asarray(root_rotations, dtype=np.float64)
    heading = np.unwrap(2.0 * np.arctan2(q[:, 2], q[:, 0]))
    local = quat_multiply(yaw_quaternion(-heading), q)
    return heading, local


def motion_positions(motion) -> np.ndarray:
    """Global joint positions of a motion (forward kinematics).

    Parameters
    ----------
    motion : Motion

    Returns
    -------
    (F, J, 3) float ndarray
        Metres.
    """
    pos, _ = forward_kinematics(
        motion.skeleton, motion.rotations, motion.root_position, translations=motion.translations
    )
    return pos


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def euler_continuity(angles: np.ndarray, proper: np.ndarray | bool = False) -> np.ndarray:
    """Make Euler angle tracks continuous over frames.

    Each frame takes, of its two equivalent triples (``(a, b, c)`` and
    ``(a + π, π - b, c + π)``, or ``(a + π, -b, c + π)`` for proper Euler
    orders), each shifted by multiples of 2π, the one closest to the
    previous frame.

    Parameters
    ----------
    angles : (F, ..., 3) float ndarray
        Radians, channel order.
    proper : bool or (...) bool ndarray
        Proper Euler order (first axis == last axis), per track.

    Returns
    -------
    (F, ..., 3) float ndarray
    """
    e = np.asarray(angles, dtype=np.float64)
    if e.shape[0] < 2:
        return e.copy()
    proper = np.broadcast_to(np.asarray(proper, dtype=bool), e.shape[1:-1])
    alt = e.copy()
    alt[..., 0] += np.pi
    alt[..., 1] = np.where(proper, -e[..., 1], np.pi - e[..., 1])
    alt[..., 2] += np.pi
    out = np.empty_like(e)
    out[0] = e[0]
    for t in range(1, e.shape[0]):
        prev = out[t - 1]
        c1 = prev + _wrap(e[t] - prev)
        c2 = prev + _wrap(alt[t] - prev)
        use2 = ((c2 - prev) ** 2).sum(-1) < ((c1 - prev) ** 2).sum(-1) - 1e-12
        out[t] = np.where(use2[..., None], c2, c1)
    return out
