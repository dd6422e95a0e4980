"""Rotations: quaternion algebra, Euler angles and rotation tracks.

Conventions
-----------
* Quaternions are ``(..., 4)`` float arrays ``(w, x, y, z)``: Hamilton product,
  *active* rotations (``quat_rotate(q, v)`` turns the vector ``v``), unit norm.
  ``quat_multiply(a, b)`` applies ``b`` first, then ``a``.
* Euler angles follow BVH: ``order`` is the rotation-channel order string (e.g.
  ``"ZXY"``) and the rotation is ``R = R_Z(a0) @ R_X(a1) @ R_Y(a2)`` (intrinsic
  rotations about the moving axes, angles given in channel order).  The 6
  Tait-Bryan (``XYZ`` ...) and the 6 proper Euler (``ZXZ`` ...) orders are supported.
* Every function broadcasts over leading axes; nothing loops over frames
  (except :func:`euler_continuity`, which is sequential by nature).

Sections: quaternion algebra (``quat_*``, with :func:`quat_continuity` for sign
continuity along frames; :func:`quat_multiply_parts` / :func:`quat_rotate_parts`, the
same products on component arrays); Euler angles (:func:`euler_to_quat`,
:func:`quat_to_euler`, :func:`padded_order`); tracks over frames
(:func:`euler_continuity`, :func:`heading_split` / :func:`yaw_quaternion`: the
root's heading about the up axis ``y`` and the rest).
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "EULER_ORDERS",
    "euler_continuity",
    "euler_to_quat",
    "heading_split",
    "padded_order",
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
    "quat_multiply_parts",
    "quat_normalize",
    "quat_rotate",
    "quat_rotate_parts",
    "quat_slerp",
    "quat_to_6d",
    "quat_to_euler",
    "quat_to_matrix",
    "quat_to_rotvec",
    "yaw_quaternion",
]

#: The 12 supported rotation orders (6 Tait-Bryan, 6 proper Euler).
EULER_ORDERS: tuple[str, ...] = (
    "XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX",
    "XYX", "XZX", "YXY", "YZY", "ZXZ", "ZYZ",
)  # fmt: skip

_AXIS = {"X": 0, "Y": 1, "Z": 2}


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
    # components written out (no moveaxis / stack: this is called per joint and per node)
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    parts = quat_multiply_parts([a[..., c] for c in range(4)], [b[..., c] for c in range(4)])
    for c, part in enumerate(parts):
        out[..., c] = part
    return out


def quat_multiply_parts(a, b) -> tuple[np.ndarray, ...]:
    """:func:`quat_multiply` on quaternions given as their four component arrays.

    For callers that keep quaternions component by component (contiguous per
    component, e.g. :func:`~mocapflow.stages.motion.kinematics.forward_kinematics`);
    the same arithmetic, so the same values, as :func:`quat_multiply`.

    Parameters
    ----------
    a, b : sequence of 4 float ndarrays
        ``(w, x, y, z)`` components, broadcastable to one shape.

    Returns
    -------
    tuple of 4 float ndarrays
        ``(w, x, y, z)`` of ``a * b``.
    """
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
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
    out = np.empty(np.broadcast_shapes(q.shape[:-1], v.shape[:-1]) + (3,))
    parts = quat_rotate_parts([q[..., c] for c in range(4)], [v[..., c] for c in range(3)])
    for c, part in enumerate(parts):
        out[..., c] = part
    return out


def quat_rotate_parts(q, v) -> tuple[np.ndarray, ...]:
    """:func:`quat_rotate` on quaternions and vectors given as their component arrays.

    The same arithmetic, so the same values, as :func:`quat_rotate`: ``v + 2 (w (u × v)
    + u × (u × v))`` with ``u = (x, y, z)``, the cross products written out.

    Parameters
    ----------
    q : sequence of 4 float ndarrays
        ``(w, x, y, z)`` of unit quaternions.
    v : sequence of 3 float ndarrays
        ``(x, y, z)`` of the vectors (broadcastable against ``q``'s).

    Returns
    -------
    tuple of 3 float ndarrays
    """
    w, x, y, z = q
    vx, vy, vz = v
    cx = y * vz - z * vy
    cy = z * vx - x * vz
    cz = x * vy - y * vx
    return (
        vx + 2.0 * (w * cx + (y * cz - z * cy)),
        vy + 2.0 * (w * cy + (z * cx - x * cz)),
        vz + 2.0 * (w * cz + (x * cy - y * cx)),
    )


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


def padded_order(axes: str) -> str:
    """A rotation order of fewer than three axes completed with the missing ones.

    Parameters
    ----------
    axes : str
        Rotation axes in channel order (``""``, ``"ZX"``, ``"ZXY"`` ...).

    Returns
    -------
    str
        ``axes`` followed by the absent ones of ``XYZ`` in that order (``"ZX"`` ->
        ``"ZXY"``), so a joint with fewer rotation channels still has an order of
        :data:`EULER_ORDERS` (the padded angles are zero).
    """
    return axes + "".join(a for a in "XYZ" if a not in axes)


# --------------------------------------------------------------------------- tracks


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
