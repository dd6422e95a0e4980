"""Motions ↔ joint-angle DOF trajectories (Lau, Bar-Joseph & Kuffner 2009, §4).

Every joint with rotation channels contributes its Euler angles (radians) in the
joint's BVH channel order, made continuous over time (2π unwrapping and the
choice between the two equivalent Euler triples).  With ``root="heading"``
(default) the root is made independent of where the subject walks: the heading
angle ψ about the up axis enters as its rate (``heading_rate``), the rest of the
root orientation as a 2-component swing rotation vector, the horizontal root
translation as a per-frame velocity expressed in the heading frame
(``velocity_*``) and the height as is.  ``root="absolute"`` keeps root position
and Euler angles as they are.  :func:`dofs_to_motion` integrates the heading and
velocities back from an origin (ψ₀, p₀).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from mocapflow.stages.motion.datatypes import Motion, Skeleton
from mocapflow.stages.motion.rotations import (
    euler_continuity,
    euler_to_quat,
    quat_conjugate,
    quat_continuity,
    quat_from_rotvec,
    quat_multiply,
    quat_rotate,
    quat_to_euler,
    quat_to_rotvec,
)

__all__ = ["ClipError", "dofs_to_motion", "motion_to_dofs", "padded_order", "rotation_channels"]

_AXES = "XYZ"


class ClipError(ValueError):
    """Input clips that cannot be used (empty, mismatched, too short)."""


def padded_order(rot: str) -> str:
    """A joint's rotation channel order padded to three axes (``"ZX"`` → ``"ZXY"``)."""
    return rot + "".join(a for a in _AXES if a not in rot)


def _twist(psi: np.ndarray, up: int) -> np.ndarray:
    """Quaternions ``(..., 4)`` of the rotations by ``psi`` about world axis ``up``."""
    q = np.zeros(np.shape(psi) + (4,))
    q[..., 0] = np.cos(0.5 * psi)
    q[..., 1 + up] = np.sin(0.5 * psi)
    return q


def motion_to_dofs(
    motion: Motion, *, root: Literal["heading", "absolute"] = "heading", up: str = "y"
) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray]:
    """Joint-angle DOF trajectory of a motion.

    Parameters
    ----------
    motion : Motion
        ``F`` frames, ``J`` joints.
    root : {"heading", "absolute"}
        Root representation (see module docstring).
    up : {"y", "z"}
        Up axis of the skeleton's world.

    Returns
    -------
    dofs : (F, D_all) float ndarray
        Radians for angles, metres (per frame for velocities).
    names : list of str
        ``D_all`` DOF names ``"<joint>:<channel>"``.
    heading : (F,) float ndarray
        Unwrapped root heading ψ (zeros for ``root="absolute"``).
    position : (F, 3) float ndarray
        Root position.
    """
    u = _AXES.lower().index(up.lower())
    hz = [a for a in range(3) if a != u]
    sk = motion.skeleton
    F = motion.n_frames
    rot = quat_continuity(motion.rotations, axis=0)
    cols: list[np.ndarray] = []
    names: list[str] = []
    psi = np.zeros(F)
    pos = motion.root_position
    rname = sk.names[0]
    if root == "heading":
        q = rot[:, 0]
        psi = np.unwrap(2.0 * np.arctan2(q[:, 1 + u], q[:, 0]))
        swing = quat_multiply(quat_conjugate(_twist(psi, u)), q)
        rv = quat_to_rotvec(swing)
        dpsi = np.zeros(F)
        dp = np.zeros((F, 3))
        if F > 1:
            dpsi[1:] = np.diff(psi)
            dpsi[0] = dpsi[1]
            dp[1:] = np.diff(pos, axis=0)
            dp[0] = dp[1]
        local = quat_rotate(quat_conjugate(_twist(psi, u)), dp)
        cols += [dpsi[:, None], rv[:, hz], local[:, hz], pos[:, u : u + 1]]
        names += [f"{rname}:heading_rate"]
        names += [f"{rname}:swing_{_AXES[a]}" for a in hz]
        names += [f"{rname}:velocity_{_AXES[a]}" for a in hz]
        names += [f"{rname}:{_AXES[u]}position"]
        joints = range(1, sk.n_joints)
    elif root == "absolute":
        cols.append(pos)
        names += [f"{rname}:{a}position" for a in _AXES]
        joints = range(sk.n_joints)
    else:
        raise ClipError(f"unknown root representation {root!r}")
    orders = [(j, sk.rotation_order(j)) for j in joints]
    orders = [(j, o) for j, o in orders if o]
    if orders:
        js = [j for j, _ in orders]
        eul = np.stack(
            [quat_to_euler(rot[:, j], padded_order(o)) for j, o in orders], axis=1
        )  # (F, J', 3)
        proper = np.array([padded_order(o)[0] == padded_order(o)[2] for _, o in orders])
        eul = euler_continuity(eul, proper)
        for k, (_, o) in enumerate(orders):
            cols.append(eul[:, k, : len(o)])
            names += [f"{sk.names[js[k]]}:{a}rotation" for a in o]
    dofs = np.concatenate(cols, axis=1) if cols else np.zeros((F, 0))
    return dofs, names, psi, np.array(pos, dtype=np.float64)


def dofs_to_motion(
    dofs: np.ndarray,
    names: list[str],
    skeleton: Skeleton,
    *,
    rate: float,
    origin: np.ndarray | None = None,
    root: str = "heading",
    up: str = "y",
    translations: np.ndarray | None = None,
    attrs: dict | None = None,
) -> Motion:
    """Inverse of :func:`motion_to_dofs`.

    Parameters
    ----------
    dofs : (F, D_all) float ndarray
    names : list of str
        ``D_all`` DOF names as produced by :func:`motion_to_dofs`.
    skeleton : Skeleton
    rate : float
    origin : (4,) float ndarray, optional
        Heading ψ₀ and root position p₀ of frame 0 (``root="heading"``).
    root, up : str
        As in :func:`motion_to_dofs`.
    translations : (J, 3) float ndarray, optional
        Constant local translations of joints with position channels.
    attrs : dict, optional

    Returns
    -------
    Motion
    """
    dofs = np.asarray(dofs, dtype=np.float64)
    F = dofs.shape[0]
    col = {n: i for i, n in enumerate(names)}
    u = _AXES.lower().index(up.lower())
    hz = [a for a in range(3) if a != u]
    J = skeleton.n_joints
    rot = np.zeros((F, J, 4))
    rot[..., 0] = 1.0
    rname = skeleton.names[0]
    origin = np.zeros(4) if origin is None else np.asarray(origin, dtype=np.float64)
    pos = np.zeros((F, 3))

    def get(n: str) -> np.ndarray:
        return dofs[:, col[n]] if n in col else np.zeros(F)

    if root == "heading":
        dpsi = get(f"{rname}:heading_rate")
        psi = origin[0] + np.concatenate([[0.0], np.cumsum(dpsi[1:])])[:F]
        tw = _twist(psi, u)
        rv = np.zeros((F, 3))
        vel = np.zeros((F, 3))
        for a in hz:
            rv[:, a] = get(f"{rname}:swing_{_AXES[a]}")
            vel[:, a] = get(f"{rname}:velocity_{_AXES[a]}")
        rot[:, 0] = quat_multiply(tw, quat_from_rotvec(rv))
        dp = quat_rotate(tw, vel)
        pos[:] = origin[1:]
        if F > 1:
            pos[1:, hz] += np.cumsum(dp[1:, hz], axis=0)
        pos[:, u] = get(f"{rname}:{_AXES[u]}position")
        joints = range(1, J)
    else:
        for a in range(3):
            pos[:, a] = get(f"{rname}:{_AXES[a]}position")
        joints = range(J)
    for j in joints:
        o = skeleton.rotation_order(j)
        if not o:
            continue
        ang = np.zeros((F, 3))
        for k, a in enumerate(o):
            ang[:, k] = get(f"{skeleton.names[j]}:{a}rotation")
        rot[:, j] = euler_to_quat(ang, padded_order(o))
    trans = None
    if translations is not None:
        trans = np.broadcast_to(np.asarray(translations, dtype=np.float64), (F, J, 3)).copy()
    return Motion(
        skeleton=skeleton,
        root_position=pos,
        rotations=rot,
        rate=rate,
        translations=trans,
        attrs=dict(attrs or {}),
    )


def rotation_channels(motion: Motion, *, up: str = "y") -> tuple[np.ndarray, list[str]]:
    """BVH rotation channels of the non-root joints, continuous over time.

    Parameters
    ----------
    motion : Motion
        ``F`` frames.
    up : {"y", "z"}
        Up axis (only the root's split depends on it; the root is left out).

    Returns
    -------
    angles : (F, C) float ndarray
        Radians, each joint's Euler angles in its BVH channel order
        (:func:`~mocapflow.stages.variation.dofs.motion_to_dofs`).
    names : list of str
        ``C`` names ``"<joint>:<axis>rotation"``.
    """
    dofs, names, _, _ = motion_to_dofs(motion, root="heading", up=up)
    root = motion.skeleton.names[0]
    keep = [i for i, n in enumerate(names)
            if n.endswith("rotation") and n.partition(":")[0] != root]
    return dofs[:, keep], [names[i] for i in keep]
