"""Kinematics of a skeleton: forward kinematics, End Sites, resampling.

* :func:`forward_kinematics` — joint world positions and orientations;
  :func:`end_site_positions` — the End Sites';
* :func:`motion_positions` — global joint positions of a motion (the form
  several graphs share);
* :func:`resample_motion` — a motion at another frame rate: slerped rotations
  (``method="slerp"``) or a C²-smooth rotation spline (``method="spline"``, for
  upsampling back to a source rate without velocity kinks at the samples).

Quaternion and Euler conventions are those of
:mod:`mocapflow.stages.motion.rotations`; the rigid fit of point sets is
:mod:`mocapflow.stages.motion.absolute_orientation`.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from mocapflow.stages.motion.axes import frame_basis, parse_axis
from mocapflow.stages.motion.datatypes import Motion, Skeleton
from mocapflow.stages.motion.rotations import (
    heading_split,
    quat_conjugate,
    quat_continuity,
    quat_from_matrix,
    quat_multiply,
    quat_multiply_parts,
    quat_rotate,
    quat_rotate_parts,
    quat_slerp,
    quat_to_matrix,
    yaw_quaternion,
)

__all__ = [
    "LOOP_PAD",
    "end_site_positions",
    "forward_kinematics",
    "loop_continuation",
    "motion_positions",
    "reorient_motion",
    "resample_motion",
]


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
    N = int(np.prod(lead, dtype=np.int64))
    # component-major working arrays (component, joint, frame): every joint of one depth
    # is done at once on contiguous rows (the same arithmetic as quat_multiply/rotate)
    rot = np.ascontiguousarray(rotations.reshape(N, J, 4).transpose(2, 1, 0))
    if translations is None:
        off = np.broadcast_to(np.asarray(skeleton.offsets, dtype=np.float64).T[:, :, None],
                              (3, J, N))
    else:
        translations = np.asarray(translations, dtype=np.float64)
        offsets = np.broadcast_to(skeleton.offsets, lead + (J, 3))
        offsets = np.where(np.isfinite(translations), translations, offsets)
        off = offsets.reshape(N, J, 3).transpose(2, 1, 0)
    grot = np.empty((4, J, N))
    pos = np.empty((3, J, N))
    grot[:, 0] = rot[:, 0]
    pos[:, 0] = np.broadcast_to(root_position, lead + (3,)).reshape(N, 3).T
    parents = np.asarray(skeleton.parents)
    for js in _depth_groups(parents):
        ps = parents[js]
        gp = grot[:, ps]
        grot[:, js] = quat_multiply_parts(gp, rot[:, js])
        pos[:, js] = pos[:, ps] + quat_rotate_parts(gp, off[:, js])
    return (np.ascontiguousarray(pos.transpose(2, 1, 0)).reshape(lead + (J, 3)),
            np.ascontiguousarray(grot.transpose(2, 1, 0)).reshape(lead + (J, 4)))


def _depth_groups(parents: np.ndarray) -> list[np.ndarray]:
    """Non-root joints grouped by depth in the tree (depth 1 first; parents before children)."""
    depth = [0] * len(parents)
    for j in range(1, len(parents)):
        depth[j] = depth[int(parents[j])] + 1
    d = np.asarray(depth)
    return [np.flatnonzero(d == k) for k in range(1, int(d.max(initial=0)) + 1)]


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


def resample_motion(
    motion: Motion, rate: float, *, method: Literal["slerp", "spline"] = "slerp",
    cyclic: bool = False,
) -> Motion:
    """Resample a motion to another frame rate over the same duration.

    ``method="slerp"``: rotations slerped, root position and translations linearly
    interpolated (C⁰: the velocity kinks at every source sample).  ``method="spline"``:
    each joint's rotations by a cubic rotation spline (:class:`scipy.spatial.transform.
    RotationSpline`, cubic in a local rotation-vector tangent space, continuous angular
    rate and acceleration: C²), root position and translations by cubic splines
    (not-a-knot); what to use when going up to a source rate.  The new motion has
    ``floor((F - 1) * rate / motion.rate) + 1`` frames, frame ``k`` at time ``k / rate``.

    Parameters
    ----------
    motion : Motion
        ``F`` frames at ``motion.rate``.
    rate : float
        New frames per second (> 0).
    method : {"slerp", "spline"}
        Interpolant (``"spline"`` needs ``F >= 4``; fewer frames fall back to slerp).
    cyclic : bool
        The motion is a loop (its last frame is followed by its first): it is
        resampled over ``F / motion.rate`` seconds into ``round(F * rate / motion.rate)``
        frames, the interpolant seeing the loop go on at both ends
        (:func:`loop_continuation`), so the last → first step of the result is an
        ordinary step too.

    Returns
    -------
    Motion
        Same skeleton and attrs; ``attrs["resampled_from_rate"]`` records the first
        rate it was resampled from (the source's, kept through later resamples).
    """
    rate = float(rate)
    if not rate > 0:
        raise ValueError(f"resample_motion: rate must be > 0, got {rate}")
    if method not in ("slerp", "spline"):
        raise ValueError(f"resample_motion: method must be 'slerp' or 'spline', got {method!r}")
    F = motion.n_frames
    if rate == motion.rate or F == 0:
        return motion.replace()
    if cyclic and F >= 2:
        pad = min(LOOP_PAD, F)
        n_new = max(int(round(F * rate / motion.rate)), 1)
        u = pad + np.arange(n_new) * (motion.rate / rate)
        motion = loop_continuation(motion, pad)
        F = motion.n_frames
    else:
        duration = (F - 1) / motion.rate
        n_new = int(np.floor(duration * rate + 1e-9)) + 1
        u = np.minimum(np.arange(n_new) * (motion.rate / rate), F - 1)
    rot = quat_continuity(motion.rotations, axis=0)
    if method == "spline" and F >= 4:
        rotations, root, trans = _spline_samples(motion, rot, u)
    else:
        rotations, root, trans = _slerp_samples(motion, rot, u)
    attrs = dict(motion.attrs)
    attrs.setdefault("resampled_from_rate", motion.rate)
    return motion.replace(
        root_position=root, rotations=rotations, rate=rate, translations=trans, attrs=attrs
    )


#: Frames of a loop repeated at each end when it is resampled (the spline's support).
LOOP_PAD = 3


def loop_continuation(motion: Motion, pad: int = LOOP_PAD) -> Motion:
    """A loop with its last ``pad`` frames before its first and its first ``pad`` after its
    last, each copy placed where the loop goes on.

    The copies after the last frame are the first frames moved by the rigid
    continuation ``G``, a turn about the up axis ``y`` and a horizontal
    translation.  A loop that closes in space (its last → first root step within
    3 median steps in ground distance and heading, e.g. a lap of a closed path)
    goes on where it is: ``G`` is the identity (up to whole turns).  Otherwise
    ``G`` puts frame 0's root one step after the last frame, that step the mean of
    the last and the first step (heading and ground velocity).  The copies before
    the first frame are the last frames moved by ``G⁻¹``.  Joint rotations and
    translations are copied as they are (a loop's pose repeats; only the root
    travels).

    Parameters
    ----------
    motion : Motion
        ``F >= 2`` frames, Y up.
    pad : int
        Frames copied at each end (``<= F``).

    Returns
    -------
    Motion
        ``F + 2 pad`` frames: frame ``pad + i`` is frame ``i`` of ``motion``.
    """
    F = motion.n_frames
    pad = int(min(pad, F))
    heading, _ = heading_split(motion.rotations[:, 0])
    p = motion.root_position
    ground = p[:, [0, 2]]
    step = np.median(np.linalg.norm(np.diff(ground, axis=0), axis=1))
    step_turn = np.median(np.abs(np.diff(heading)))
    wrap_turn = float(np.angle(np.exp(1j * (heading[0] - heading[-1]))))
    closes = (np.linalg.norm(ground[0] - ground[-1]) <= 3.0 * step + 1e-9
              and abs(wrap_turn) <= 3.0 * step_turn + 1e-6)
    if closes:  # go on in place (the turn is whole turns)
        turn = heading[-1] + wrap_turn - heading[0]
    else:
        turn = heading[-1] + 0.5 * (heading[-1] - heading[-2] + heading[1] - heading[0]) \
            - heading[0]
    q_turn = yaw_quaternion(turn)
    R = quat_to_matrix(q_turn)
    next_root = p[0] if closes else p[-1] + 0.5 * ((p[-1] - p[-2]) + R @ (p[1] - p[0]))
    shift = next_root - R @ p[0]
    shift[1] = 0.0  # the height is the loop's own

    def moved(idx: np.ndarray, sign: int) -> tuple[np.ndarray, np.ndarray]:
        rot = motion.rotations[idx].copy()
        if sign > 0:
            rot[:, 0] = quat_multiply(q_turn, rot[:, 0])
            root = p[idx] @ R.T + shift
        else:
            rot[:, 0] = quat_multiply(quat_conjugate(q_turn), rot[:, 0])
            root = (p[idx] - shift) @ R
        return root, rot

    before, after = np.arange(F - pad, F), np.arange(pad)
    root_b, rot_b = moved(before, -1)
    root_a, rot_a = moved(after, +1)
    trans = motion.translations
    if trans is not None:
        trans = np.concatenate([trans[before], trans, trans[after]])
    return motion.replace(root_position=np.concatenate([root_b, p, root_a]),
                          rotations=np.concatenate([rot_b, motion.rotations, rot_a]),
                          translations=trans)


def _slerp_samples(motion: Motion, rot: np.ndarray, u: np.ndarray):
    """Rotations ``(N, J, 4)`` slerped, root ``(N, 3)`` and translations lerped at frames ``u``."""
    F = motion.n_frames
    i0 = np.clip(np.floor(u).astype(np.int64), 0, F - 1)
    i1 = np.minimum(i0 + 1, F - 1)
    frac = np.clip(u - i0, 0.0, 1.0)
    rotations = quat_slerp(rot[i0], rot[i1], frac[:, None])
    fr = frac[:, None]
    root = motion.root_position[i0] * (1 - fr) + motion.root_position[i1] * fr
    trans = None
    if motion.translations is not None:
        fr3 = frac[:, None, None]
        trans = motion.translations[i0] * (1 - fr3) + motion.translations[i1] * fr3
    return rotations, root, trans


def _spline_samples(motion: Motion, rot: np.ndarray, u: np.ndarray):
    """Rotations ``(N, J, 4)`` by rotation splines, root and translations by cubic splines.

    ``u`` are fractional source frames; ``rot`` the ``(F, J, 4)`` sign-continuous
    ``(w, x, y, z)`` rotations (SciPy's are ``(x, y, z, w)``).
    """
    F, J = rot.shape[:2]
    t = np.arange(F, dtype=np.float64)
    out = np.empty((u.size, J, 4))
    for j in range(J):
        spline = RotationSpline(t, Rotation.from_quat(rot[:, j][:, [1, 2, 3, 0]]))
        out[:, j] = spline(u).as_quat()[:, [3, 0, 1, 2]]
    rotations = quat_continuity(out, axis=0)
    root = CubicSpline(t, motion.root_position, axis=0)(u)
    trans = None
    if motion.translations is not None:
        trans = CubicSpline(t, motion.translations, axis=0)(u)
    return rotations, root, trans


def motion_positions(motion: Motion) -> np.ndarray:
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


def reorient_motion(motion: Motion, *, up: str = "+y", forward: str = "+z") -> Motion:
    """The same motion in other world axes: rotated so that its up axis and facing
    (``attrs["up"]`` / ``["forward"]``, default Y up facing +Z) become ``up`` / ``forward``.

    Stages written in the Y-up, +Z-facing convention (the texture synthesis) bring a
    motion in with the defaults and take their output back with the source's axes.
    Only the root moves (its translation and rotation); offsets and local rotations
    are untouched, so the skeleton and its size are the same.

    Parameters
    ----------
    motion : Motion
    up, forward : str
        Target axes (signed axis names, :func:`~mocapflow.stages.motion.axes.parse_axis`).

    Returns
    -------
    Motion
        ``motion`` itself when the axes already agree; else a rotated copy with
        ``attrs["up"]`` / ``["forward"]`` set to the targets.
    """
    src_up = parse_axis(motion.attrs.get("up", "+y"))
    src_fwd = parse_axis(motion.attrs.get("forward", "+z"))
    up, forward = parse_axis(up, name="up"), parse_axis(forward, name="forward")
    if (src_up, src_fwd) == (up, forward):
        return motion
    R = frame_basis(up, forward) @ frame_basis(src_up, src_fwd).T
    q = quat_from_matrix(R)
    rot = motion.rotations.copy()
    rot[:, 0] = quat_multiply(np.broadcast_to(q, rot[:, 0].shape), rot[:, 0])
    return motion.replace(root_position=motion.root_position @ R.T, rotations=rot,
                          attrs={**motion.attrs, "up": up, "forward": forward})
