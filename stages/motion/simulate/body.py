"""Skinned body surfaces for synthetic captures: the :class:`Body` type and its posing.

A :class:`Body` is a triangle mesh in a bind pose with linear-blend skinning
weights over the joints of a skeleton, plus a set of coarse *capsules* (one per
bone segment, slightly inside the skin) used as occluders by the capture
simulator.  Bodies are built by

* :func:`~mocapflow.stages.motion.simulate.capsules.procedural_body` — the
  surface of any skeleton, a smooth union of tapered capsules around its bones;
* :func:`~mocapflow.stages.motion.simulate.makehuman.load_makehuman_body` — the
  CC0 MakeHuman base mesh with its CMU-named rig and skin weights.

Posing (here): :func:`skinning_transforms` and :func:`skin` pose a body with a
:class:`~mocapflow.stages.motion.datatypes.Motion` (joints matched by name; a
body whose bind pose differs from the motion's rest pose, e.g. MakeHuman's
A-pose under a T-pose skeleton, is aligned bone by bone with :func:`align_to`).

Coordinates: metres, y up, the body facing +z in its bind pose (the CMU and
MakeHuman convention).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mocapflow.stages.motion.datatypes import Mesh, Motion, Skeleton
from mocapflow.stages.motion.geometry import vertex_normals
from mocapflow.stages.motion.kinematics import forward_kinematics
from mocapflow.stages.motion.rotations import (
    quat_identity,
    quat_multiply,
    quat_rotate,
    quat_to_matrix,
)

__all__ = [
    "Body",
    "BodyError",
    "Capsules",
    "align_to",
    "bind_pose",
    "point_segment_distance",
    "skin",
    "skinning_transforms",
]


class BodyError(ValueError):
    """A body cannot be built or posed (bad skeleton, mesh files, joint names)."""


@dataclass(eq=False)
class Capsules:
    """Tapered capsules around bone segments, in the bind pose.

    Parameters
    ----------
    joint : (C,) int ndarray
        Joint whose transform moves each capsule.
    start, end : (C, 3) float ndarray
        Axis end points (metres).
    radius : (C, 2) float ndarray
        Radius at ``start`` and ``end``.
    depth : (C,) float ndarray
        Front-to-back flattening (1 = round; 0.7 = 30 % thinner along ``forward``).
    forward : (3,) float ndarray
        The body's forward direction in the bind pose.
    """

    joint: np.ndarray
    start: np.ndarray
    end: np.ndarray
    radius: np.ndarray
    depth: np.ndarray
    forward: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))

    def __len__(self) -> int:
        return len(self.joint)


@dataclass(eq=False)
class Body:
    """A skinned body surface.

    Parameters
    ----------
    skeleton : Skeleton
        The body's own skeleton (bind pose = identity local rotations).
    vertices : (V, 3) float ndarray
        Skin in the bind pose (metres).
    faces : (T, 3) int ndarray
        Triangles, wound outward.
    weights : (V, J) float ndarray
        Linear-blend skinning weights (rows sum to 1).
    capsules : Capsules
        Coarse occluders (slightly inside the skin).
    alignment : (J, 4) float ndarray
        Per joint, the rotation from the body's bind pose to the rest pose of the
        skeleton that drives it (identity when they agree).
    attrs : dict
        ``source`` etc.
    """

    skeleton: Skeleton
    vertices: np.ndarray
    faces: np.ndarray
    weights: np.ndarray
    capsules: Capsules
    alignment: np.ndarray | None = None
    attrs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        J = self.skeleton.n_joints
        self.vertices = np.asarray(self.vertices, dtype=np.float64)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        self.weights = np.asarray(self.weights, dtype=np.float64)
        if self.weights.shape != (len(self.vertices), J):
            raise BodyError(f"body: weights must be (V={len(self.vertices)}, J={J}), "
                            f"got {self.weights.shape}")
        if self.alignment is None:
            self.alignment = quat_identity((J,))

    @property
    def n_vertices(self) -> int:
        """Number of vertices ``V``."""
        return len(self.vertices)

    @property
    def part(self) -> np.ndarray:
        """``(V,)`` int: the dominant joint of each vertex (largest skin weight)."""
        return np.argmax(self.weights, axis=1)

    @property
    def normals(self) -> np.ndarray:
        """``(V, 3)`` unit vertex normals in the bind pose."""
        return vertex_normals(self.vertices, self.faces)

    def bind_positions(self) -> np.ndarray:
        """``(J, 3)`` joint positions in the bind pose."""
        return bind_pose(self.skeleton)

    def to_mesh(self) -> Mesh:
        """The bind-pose surface as a :class:`Mesh` (``attrs``: joint names, parts)."""
        return Mesh(self.vertices, self.faces, attrs={
            "joint_names": self.skeleton.names, "vertex_part": self.part.tolist(),
            **self.attrs})


# --------------------------------------------------------------------------- geometry helpers


def bind_pose(skeleton: Skeleton) -> np.ndarray:
    """``(J, 3)`` joint positions with identity rotations and the root at the origin."""
    J = skeleton.n_joints
    pos, _ = forward_kinematics(skeleton, quat_identity((1, J)), np.zeros((1, 3)))
    return pos[0]


def point_segment_distance(
    p: np.ndarray, a: np.ndarray, b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Distance from points to the segment ``a``-``b``.

    Parameters
    ----------
    p : (N, 3) float ndarray
    a, b : (3,) float ndarray
        The segment's ends.

    Returns
    -------
    distance : (N,) float ndarray
    t : (N,) float ndarray
        Parameter in [0, 1] of the closest point ``a + t (b - a)``.
    """
    ab = b - a
    L2 = float(ab @ ab)
    t = np.zeros(len(p)) if L2 < 1e-16 else np.clip((p - a) @ ab / L2, 0.0, 1.0)
    q = a + t[:, None] * ab
    return np.linalg.norm(p - q, axis=1), t


# --------------------------------------------------------------------------- posing


def _min_rotation(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Quaternion of the smallest rotation taking direction u to v."""
    u = u / np.linalg.norm(u)
    v = v / np.linalg.norm(v)
    c = float(u @ v)
    if c < -0.999999:
        axis = np.cross(u, [1.0, 0, 0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(u, [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return np.array([0.0, *axis])
    q = np.array([1.0 + c, *np.cross(u, v)])
    return q / np.linalg.norm(q)


def align_to(body: Body, skeleton: Skeleton) -> np.ndarray:
    """Per body joint, the rotation from the body's bind pose to ``skeleton``'s rest pose.

    Bones are matched by joint name; each matched bone's direction (to the child
    present in both) is rotated minimally onto the skeleton's.

    Returns
    -------
    (J, 4) float ndarray
    """
    bs = body.skeleton
    bb, sb = bind_pose(bs), bind_pose(skeleton)
    sidx = {n: i for i, n in enumerate(skeleton.names)}
    out = quat_identity((bs.n_joints,))
    for j, name in enumerate(bs.names):
        if name not in sidx or j == 0:
            continue
        best = None
        for c in bs.children(j):
            cn = bs.names[c]
            if cn not in sidx:
                continue
            u = bb[c] - bb[j]
            v = sb[sidx[cn]] - sb[sidx[name]]
            if np.linalg.norm(u) < 1e-4 or np.linalg.norm(v) < 1e-4:
                continue
            cos = u @ v / np.linalg.norm(u) / np.linalg.norm(v)
            if best is None or cos > best[0]:
                best = (cos, u, v)
        if best is not None:
            out[j] = _min_rotation(best[1], best[2])
        else:
            out[j] = out[bs.parents[j]]
    return out


def skinning_transforms(body: Body, motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """World transforms of the body's joints over a motion.

    A body point ``v`` (bind pose) bound to joint ``j`` goes to
    ``R[f, j] @ (v - bind[j]) + p[f, j]``.

    Parameters
    ----------
    body : Body
    motion : Motion
        Its joints are matched to the body's by name; body joints the motion
        lacks follow their parent.  When the skeletons differ, bones are aligned
        with :func:`align_to` and the root translation is scaled by the ratio of
        hip heights.

    Returns
    -------
    R : (F, J, 3, 3) float ndarray
    p : (F, J, 3) float ndarray

    Raises
    ------
    BodyError
        The motion shares no joint name with the body (other than none at all).
    """
    bs, ms = body.skeleton, motion.skeleton
    F = motion.n_frames
    if bs is ms or (bs.names == ms.names and np.allclose(bs.offsets, ms.offsets)):
        pos, grot = forward_kinematics(ms, motion.rotations, motion.root_position,
                                       translations=motion.translations)
        return quat_to_matrix(grot), pos
    sidx = {n: i for i, n in enumerate(ms.names)}
    shared = [n for n in bs.names if n in sidx]
    if len(shared) < 2 or bs.names[0] not in sidx:
        raise BodyError(
            f"the motion's skeleton ({ms.names[:5]}…) does not match the body's joint names "
            f"({bs.names[:5]}…); they must share the root and the bones to drive")
    _, mgrot = forward_kinematics(ms, motion.rotations, motion.root_position,
                                  translations=motion.translations)
    A = align_to(body, ms)
    J = bs.n_joints
    grot = np.empty((F, J, 4))
    pos = np.empty((F, J, 3))
    bb, sb = bind_pose(bs), bind_pose(ms)
    scale = (bb[:, 1].max() - bb[:, 1].min()) / max(sb[:, 1].max() - sb[:, 1].min(), 1e-9)
    for j in range(J):
        name = bs.names[j]
        p = bs.parents[j]
        if name in sidx:
            grot[:, j] = quat_multiply(mgrot[:, sidx[name]], A[j])
        else:
            grot[:, j] = grot[:, p]
        if p < 0:
            pos[:, j] = motion.root_position * scale
        else:
            pos[:, j] = pos[:, p] + quat_rotate(grot[:, p], bs.offsets[j])
    return quat_to_matrix(grot), pos


def skin(
    body: Body,
    R: np.ndarray,
    p: np.ndarray,
    *,
    points: np.ndarray | None = None,
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """Linear-blend skinning.

    Parameters
    ----------
    body : Body
    R : (F, J, 3, 3) float ndarray
    p : (F, J, 3) float ndarray
        From :func:`skinning_transforms`.
    points : (N, 3) float ndarray, optional
        Bind-pose points to skin (default: the body's vertices), or ``(F, N, 3)``
        per-frame bind-space points (pose-space deformations).
    weights : (N, J) float ndarray, optional
        Their weights (default: the body's).

    Returns
    -------
    (F, N, 3) float ndarray
    """
    pts = body.vertices if points is None else np.asarray(points, dtype=np.float64)
    W = body.weights if weights is None else np.asarray(weights, dtype=np.float64)
    bind = body.bind_positions()
    F = R.shape[0]
    out = np.zeros((F, pts.shape[-2], 3))
    for j in np.flatnonzero(W.max(0) > 0):
        idx = np.flatnonzero(W[:, j] > 0)
        moved = _rotate(R[:, j], pts[..., idx, :] - bind[j]) + p[:, j, None]
        out[:, idx] += W[idx, j][None, :, None] * moved
    return out


def _rotate(R: np.ndarray, local: np.ndarray) -> np.ndarray:
    """R (F,3,3) applied to local (N,3) or (F,N,3) -> (F,N,3)."""
    if local.ndim == 2:
        return np.einsum("fij,nj->fni", R, local)
    return np.einsum("fij,fnj->fni", R, local)
