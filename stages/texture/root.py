"""Root trajectory of a synthesized motion (Moradoff §3.10).

The synthesis copies the root as velocities in the heading frame (yaw rate,
horizontal velocity) and an absolute height; the trajectory is their
integral.  To follow a user path (polyline or spline on the ground plane,
e.g. a figure-8) the velocities are rotated into the path's local frame: the
motion's smoothed travel direction is turned onto the path tangent at the
distance travelled so far, the high-frequency sway is kept in the path frame.
``y`` is up; ground-plane points are ``(x, z)``.

Departures from the thesis (§3.10 steers the root only):

* the sway is the heading-frame velocity minus its smoothed part, integrated
  in the new heading and high-passed again; the thesis-like split of the
  world trajectory (minus its smoothed integral) carried the shrinkage of the
  input's own turns as an offset of 10-20 cm across the path;
* a loop on a closed path is paced (:func:`follow_path`, ``cyclic``): its
  travel is scaled by one factor, spread evenly over the motion (the stride
  advance; the cadence is kept), to a whole number of laps, and computed on
  the loop repeated on both sides, so the wrap is an ordinary step; a stride
  change beyond :data:`PACE_TOLERANCE` is reported by the caller.

Feet: smoothing a seam blends two stances, so a toe in contact slides.  The
root correction (:func:`plant_feet`) keeps the mean stance toe moving as in
the input; the residual slide of each toe is then removed by two-bone leg IK
(:func:`foot_corrections`, :func:`apply_foot_ik`): within every contact span a
toe follows the input's own toe steps (none, in blended frames), the
correction is a smooth banded least-squares solution, and the feet keep their
world orientation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.linalg import solveh_banded
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import cKDTree

from mocapflow.stages.motion.contacts import true_runs
from mocapflow.stages.motion.datatypes import Skeleton
from mocapflow.stages.motion.kinematics import forward_kinematics
from mocapflow.stages.motion.rotations import (
    quat_from_rotvec,
    quat_inverse,
    quat_multiply,
    quat_normalize,
    quat_rotate,
)

__all__ = [
    "PACE_TOLERANCE",
    "PathCurve",
    "PathError",
    "apply_foot_ik",
    "chain_kinematics",
    "figure_eight",
    "follow_path",
    "foot_corrections",
    "heading_direction",
    "integrate_root",
    "leg_chains",
    "plant_feet",
    "rotate_xz",
    "toe_displacements",
    "two_bone_ik",
]


class PathError(ValueError):
    """A path param that cannot be followed."""


def heading_direction(heading: np.ndarray) -> np.ndarray:
    """Ground-plane unit vector ``(x, z)`` of a heading (``R_y(h) (0, 0, 1)``).

    Parameters
    ----------
    heading : (...) float ndarray

    Returns
    -------
    (..., 2) float ndarray
    """
    h = np.asarray(heading, dtype=np.float64)
    return np.stack([np.sin(h), np.cos(h)], axis=-1)


def rotate_xz(v: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """``R_y(angle)`` applied to ground-plane vectors ``(x, z)``.

    Parameters
    ----------
    v : (..., 2) float ndarray
    angle : float or float ndarray
        Broadcasts against ``v[..., 0]``.

    Returns
    -------
    (..., 2) float ndarray
    """
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([v[..., 0] * c + v[..., 1] * s, -v[..., 0] * s + v[..., 1] * c], axis=-1)


def integrate_root(
    yaw_rate: np.ndarray,
    velocity: np.ndarray,
    *,
    heading0: float = 0.0,
    origin: np.ndarray | tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Integrate heading-frame root velocities.

    Parameters
    ----------
    yaw_rate : (L,) float ndarray
        Heading change from frame ``t`` to ``t + 1`` (radians).
    velocity : (L, 2) float ndarray
        Displacement ``(x, z)`` from ``t`` to ``t + 1`` in the heading frame of ``t``.
    heading0 : float
        Heading of frame 0.
    origin : (2,) float
        Ground position ``(x, z)`` of frame 0.

    Returns
    -------
    heading : (L,) float ndarray
    ground : (L, 2) float ndarray
        ``(x, z)`` per frame.
    """
    yaw = np.asarray(yaw_rate, dtype=np.float64)
    heading = heading0 + np.concatenate([[0.0], np.cumsum(yaw[:-1])])
    disp = rotate_xz(np.asarray(velocity, dtype=np.float64), heading)
    ground = np.asarray(origin, dtype=np.float64) + np.vstack(
        [np.zeros((1, 2)), np.cumsum(disp[:-1], axis=0)]
    )
    return heading, ground


def figure_eight(radius: float = 2.0, n_points: int = 65) -> np.ndarray:
    """A closed figure-8 on the ground plane (two loops crossing at the origin).

    Parameters
    ----------
    radius : float
        Half width of each loop, metres (loops ``2 radius`` wide, ``4 radius`` long overall).
    n_points : int

    Returns
    -------
    (n_points, 2) float ndarray
        ``(x, z)``; first point equals the last.
    """
    u = np.linspace(0.0, 2.0 * np.pi, n_points)
    pts = np.stack([radius * np.sin(2 * u), 2.0 * radius * np.sin(u)], axis=-1)
    pts[-1] = pts[0]
    return pts


@dataclass
class PathCurve:
    """An arc-length parametrised ground-plane curve.

    Attributes
    ----------
    samples : (M, 2) float ndarray
        Dense points ``(x, z)``.
    s : (M,) float ndarray
        Arc length at each sample.
    closed : bool
        First and last control points coincide (the path wraps).
    """

    samples: np.ndarray
    s: np.ndarray
    closed: bool

    @classmethod
    def from_points(cls, points, *, mode: str = "polyline") -> PathCurve:
        """Build from control points.

        Parameters
        ----------
        points : (N, 2) or (N, 3) array_like
            ``(x, z)`` or ``(x, y, z)`` (``y`` ignored).
        mode : {"polyline", "spline"}
            Straight segments, or a C² cubic spline through the points (periodic when closed).
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] not in (2, 3) or p.shape[0] < 2:
            raise PathError(
                f"path: expected a list of >= 2 points [x, z] or [x, y, z], got {p.shape}"
            )
        if not np.isfinite(p).all():
            raise PathError("path: points must be finite")
        if p.shape[1] == 3:
            p = p[:, [0, 2]]
        keep = np.concatenate([[True], np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-9])
        p = p[keep]
        if p.shape[0] < 2:
            raise PathError("path: all points coincide")
        span = np.ptp(p, axis=0).max()
        closed = p.shape[0] > 3 and np.linalg.norm(p[0] - p[-1]) < 1e-6 * max(span, 1.0)
        if mode == "spline":
            u = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
            if closed:
                p[-1] = p[0]
            cs = CubicSpline(u, p, bc_type="periodic" if closed else "natural", axis=0)
            dense = cs(np.linspace(0.0, u[-1], max(400, 40 * p.shape[0])))
        elif mode == "polyline":
            seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
            n_each = np.maximum(2, np.ceil(seg / 0.02).astype(int))
            dense = np.vstack(
                [np.linspace(a, b, k, endpoint=False) for a, b, k in zip(p[:-1], p[1:], n_each)]
                + [p[-1:]]
            )
        else:
            raise PathError(f"path_mode must be 'polyline' or 'spline', got {mode!r}")
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
        return cls(dense, s, bool(closed))

    @property
    def length(self) -> float:
        """Total arc length, metres."""
        return float(self.s[-1])

    def _wrap(self, s: np.ndarray) -> np.ndarray:
        return np.mod(s, self.length) if self.closed else s

    def point(self, s: np.ndarray) -> np.ndarray:
        """Points at arc lengths ``s`` (extrapolated along the end tangent when open).

        Parameters
        ----------
        s : (...) float ndarray

        Returns
        -------
        (..., 2) float ndarray
        """
        s = self._wrap(np.asarray(s, dtype=np.float64))
        x = np.interp(s, self.s, self.samples[:, 0])
        z = np.interp(s, self.s, self.samples[:, 1])
        out = np.stack([x, z], axis=-1)
        if not self.closed:
            over = np.clip(s - self.length, 0.0, None)[..., None]
            out = out + over * heading_direction(self.tangent_angle(np.array(self.length)))
        return out

    def tangent_angle(self, s: np.ndarray) -> np.ndarray:
        """Heading (``atan2(dx, dz)``) of the tangent at arc lengths ``s``.

        Parameters
        ----------
        s : (...) float ndarray

        Returns
        -------
        (...) float ndarray
            Radians, continuous along the curve samples.
        """
        d = np.gradient(self.samples, self.s, axis=0)
        ang = np.unwrap(np.arctan2(d[:, 0], d[:, 1]))
        s = self._wrap(np.asarray(s, dtype=np.float64))
        return np.interp(np.clip(s, 0.0, self.length), self.s, ang)

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance from points to the curve and the arc length of the closest sample.

        Parameters
        ----------
        points : (N, 2) float ndarray

        Returns
        -------
        distance : (N,) float ndarray
        s : (N,) float ndarray
        """
        d, i = cKDTree(self.samples).query(np.asarray(points, dtype=np.float64))
        return d, self.s[i]


#: Largest stride change (fraction of the motion's own travel) a loop on a closed path
#: may need to close on a whole number of laps before :func:`follow_path` reports it.
PACE_TOLERANCE = 0.25


def _gauss(x: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return x
    return gaussian_filter1d(x, sigma, axis=0, mode="nearest")


def _smooth_angle(angle: np.ndarray, keep: np.ndarray, sigma: float) -> np.ndarray:
    """Angles ``(n,)`` smoothed on the unit circle, frames outside ``keep`` interpolated."""
    idx = np.arange(angle.shape[0])
    z = np.exp(1j * angle)
    zr = np.interp(idx, idx[keep], z.real[keep])
    zi = np.interp(idx, idx[keep], z.imag[keep])
    return np.unwrap(np.angle(_gauss(zr, sigma) + 1j * _gauss(zi, sigma)))


def follow_path(
    yaw_rate: np.ndarray,
    velocity: np.ndarray,
    curve: PathCurve,
    rate: float,
    *,
    cyclic: bool = False,
    travel_window: float = 0.5,
    min_speed: float = 0.1,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Root trajectory following a path by rotating velocities into its local frame.

    The motion's travel (its velocity smoothed over ``travel_window``) becomes
    progress along the path's arc length; the heading keeps its angle to the
    travel direction; the sway (heading-frame velocity minus its smoothed part,
    integrated in the new heading and high-passed again) is added around the
    path, so the root stays on the path up to the gait's own sway.

    A loop (``cyclic``) on a closed path is paced: the travel is scaled by one
    factor (the stride advance, spread evenly over the motion) so that the
    motion covers a whole number of laps, and the trajectory is computed on
    the loop repeated on both sides, so the wrap (last frame → first) is a
    step like any other.  The legs take up the stride change (foot IK).

    Parameters
    ----------
    yaw_rate : (L,) float ndarray
    velocity : (L, 2) float ndarray
        Heading-frame velocities of the synthesized motion (per frame).
    curve : PathCurve
    rate : float
        Frames per second.
    cyclic : bool
        The motion loops (frame ``L - 1`` is followed by frame 0).
    travel_window : float
        Gaussian sigma (seconds) separating travel from sway.
    min_speed : float
        Travel speed (m/s) below which the travel direction is taken from the neighbours.

    Returns
    -------
    heading : (L,) float ndarray
    ground : (L, 2) float ndarray
    info : dict
        ``distance`` the motion travels (its own pace; with the wrap step when
        ``cyclic``), ``path_length``, ``beyond_end`` (frames past an open path's
        end), ``laps`` and ``pace`` (stride scale; 1 unless a loop on a closed path).
    """
    yaw = np.asarray(yaw_rate, dtype=np.float64)
    vel = np.asarray(velocity, dtype=np.float64)
    L = yaw.shape[0]
    sigma = travel_window * rate
    # a loop: its copies on both sides, so every filter sees the loop continue
    m = int(np.ceil((5.0 * sigma + 2.0) / L)) if cyclic else 0
    if m:
        yaw, vel = np.tile(yaw, 2 * m + 1), np.tile(vel, (2 * m + 1, 1))
    heading, _ = integrate_root(yaw, vel)
    mid = slice(m * L, (m + 1) * L)
    travel = _gauss(rotate_xz(vel, heading), sigma)
    speed = np.linalg.norm(travel, axis=1)
    s = np.concatenate([[0.0], np.cumsum(speed[:-1])])
    s -= s[m * L]
    distance = float(speed[mid].sum()) if cyclic else float(s[L - 1])
    laps, pace = 0, 1.0
    if cyclic and curve.closed and distance > 0:
        laps = max(1, int(round(distance / curve.length)))
        pace = laps * curve.length / distance
        s *= pace
    alpha = np.arctan2(travel[:, 0], travel[:, 1])
    moving = speed * rate >= min_speed
    phi = curve.tangent_angle(s)
    if moving.any():
        psi = _smooth_angle(np.angle(np.exp(1j * (phi - alpha))), moving, 0.5 * sigma)
    else:
        psi = np.full(s.shape, phi[m * L] - heading[m * L])
    new_heading = heading + psi
    # sway: the high-frequency velocity, integrated in the new heading, drift removed
    sway = np.vstack([np.zeros((1, 2)), np.cumsum(
        rotate_xz(vel - _gauss(vel, sigma), new_heading)[:-1], axis=0)])
    sway -= _gauss(sway, sigma)
    new_ground = curve.point(s) + sway
    beyond = 0 if curve.closed else int(np.sum(s[mid] > curve.length))
    return new_heading[mid], new_ground[mid], {
        "distance": distance,
        "path_length": curve.length,
        "beyond_end": beyond,
        "laps": laps,
        "pace": float(pace),
    }


def toe_displacements(
    yaw_rate: np.ndarray, velocity: np.ndarray, toe_local: np.ndarray
) -> np.ndarray:
    """Per-frame toe displacement in the heading frame of each frame.

    Parameters
    ----------
    yaw_rate : (L,) float ndarray
    velocity : (L, 2) float ndarray
        Root displacement ``t → t+1`` in the heading frame of ``t``.
    toe_local : (L, T, 2) float ndarray
        Toe ground position relative to the root in each frame's heading frame.

    Returns
    -------
    (L, T, 2) float ndarray
        ``velocity[t] + R_y(yaw[t]) toe[t+1] - toe[t]`` (the last frame repeats).
    """
    nxt = np.concatenate([toe_local[1:], toe_local[-1:]], axis=0)
    d = rotate_xz(nxt, yaw_rate[:, None]) - toe_local + velocity[:, None, :]
    d[-1] = d[-2] if d.shape[0] > 1 else d[-1]
    return d


def plant_feet(
    yaw_rate: np.ndarray,
    velocity: np.ndarray,
    toe_local: np.ndarray,
    displacement: np.ndarray,
    contact: np.ndarray,
    *,
    cyclic: bool = False,
    smooth: float = 2.0,
) -> np.ndarray:
    """Root velocities that keep the stance toes moving as in the input.

    Smoothing a seam changes the pose; with the copied root velocity a toe in
    contact would slide.  On every frame where a toe is in contact (and in the
    next frame), the root velocity is chosen so that the toe moves as its
    source moved in the input (the mean correction when both toes are down).
    Frames copied verbatim are left unchanged.

    Parameters
    ----------
    yaw_rate : (L,) float ndarray
    velocity : (L, 2) float ndarray
        Root velocities (heading frame) of the output.
    toe_local : (L, T, 2) float ndarray
        Output toe positions relative to the root, heading frame.
    displacement : (L, T, 2) float ndarray
        Per output frame, the toe displacement of its source in the input
        (:func:`toe_displacements` of the input at the source frame; a mix of two
        source frames where a seam is cross-faded).
    contact : (L, T) bool ndarray
        Per output frame, the input toe contacts of its source.
    cyclic : bool
    smooth : float
        Gaussian sigma (frames) applied to the accumulated root offset (the
        caller scales it with the rate: 2 at 30 fps).

    Returns
    -------
    (L, 2) float ndarray
    """
    contact = contact & np.roll(contact, -1, axis=0)
    if not cyclic:
        contact[-1] = False
    current = toe_displacements(yaw_rate, velocity, toe_local)
    corr = displacement - current  # (L, T, 2)
    n = contact.sum(axis=1)
    mean = np.where(
        n[:, None] > 0,
        np.sum(np.where(contact[..., None], corr, 0.0), axis=1) / np.maximum(n, 1)[:, None],
        0.0,
    )
    # the root offset the corrections add up to, smoothed so the root stays smooth
    offset = np.vstack([np.zeros((1, 2)), np.cumsum(mean, axis=0)])
    if smooth > 0:
        offset = gaussian_filter1d(offset, smooth, axis=0, mode="nearest")
    return velocity + np.diff(offset, axis=0)


# --------------------------------------------------------------------------- foot contact IK


def leg_chains(skeleton, toes: list[int] | np.ndarray) -> list[tuple[int, int, int]]:
    """Two-bone leg chains ``(hip, knee, ankle)`` ending at (or above) each toe.

    A joint named like a toe hangs below its ankle (its parent); a foot or
    ankle joint used as the toe is the ankle itself.

    Parameters
    ----------
    skeleton : Skeleton
    toes : sequence of int
        Contact joints (:func:`~mocapflow.stages.motion.contacts.toe_indices`).

    Returns
    -------
    list of (int, int, int)

    Raises
    ------
    ValueError
        A toe without three ancestors.
    """
    chains = []
    for t in toes:
        t = int(t)
        ankle = skeleton.parents[t] if "toe" in skeleton.names[t].lower() else t
        knee = skeleton.parents[ankle] if ankle >= 0 else -1
        hip = skeleton.parents[knee] if knee >= 0 else -1
        if min(ankle, knee, hip) < 0:
            raise ValueError(
                f"joint {skeleton.names[t]!r}: no hip-knee-ankle chain above it for foot IK"
            )
        chains.append((int(hip), int(knee), int(ankle)))
    return chains


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotations taking directions ``a`` onto ``b`` ((n, 3) -> (n, 4))."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = np.arctan2(s, np.sum(a * b, axis=-1, keepdims=True))
    rv = np.where(s > 1e-12, axis / np.maximum(s, 1e-12) * angle, 0.0)
    return quat_from_rotvec(rv)


def two_bone_ik(
    hip: np.ndarray,
    knee: np.ndarray,
    ankle: np.ndarray,
    target: np.ndarray,
    *,
    hinge: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """World rotations that bring an ankle onto a target (analytic two-bone IK).

    The knee bends about the leg's plane normal until the hip–ankle distance
    equals the hip–target distance (clamped to the leg's reach), then the
    whole leg turns about the hip onto the target.

    Parameters
    ----------
    hip, knee, ankle : (n, 3) float ndarray
        Joint positions.
    target : (n, 3) float ndarray
        Wanted ankle positions.
    hinge : (n, 3) float ndarray, optional
        Knee axis used where the leg is straight (no plane).

    Returns
    -------
    r_hip : (n, 4) float ndarray
        World rotation about the hip (applied to thigh, shank and below).
    r_knee : (n, 4) float ndarray
        World rotation about the knee (applied to the shank and below, before ``r_hip``).
    """
    u, v = hip - knee, ankle - knee
    l1 = np.linalg.norm(u, axis=-1)
    l2 = np.linalg.norm(v, axis=-1)
    reach = np.linalg.norm(target - hip, axis=-1)
    lo, hi = np.abs(l1 - l2) + 1e-6, l1 + l2 - 1e-6
    want = np.clip(reach, lo, hi)
    cos_now = np.sum(u * v, axis=-1) / np.maximum(l1 * l2, 1e-12)
    cos_want = (l1**2 + l2**2 - want**2) / np.maximum(2 * l1 * l2, 1e-12)
    dtheta = np.arccos(np.clip(cos_want, -1, 1)) - np.arccos(np.clip(cos_now, -1, 1))
    n = np.cross(u, v)
    nn = np.linalg.norm(n, axis=-1, keepdims=True)
    if hinge is not None:
        n = np.where(nn > 1e-6 * np.maximum(l1 * l2, 1e-12)[:, None], n, hinge)
        nn = np.linalg.norm(n, axis=-1, keepdims=True)
    n = n / np.maximum(nn, 1e-12)
    r_knee = quat_from_rotvec(n * dtheta[:, None])
    bent = knee + quat_rotate(r_knee, v)
    r_hip = _rotation_between(bent - hip, target - hip)
    return r_hip, r_knee


def foot_corrections(
    toe_ground: np.ndarray,
    toe_step: np.ndarray,
    contact: np.ndarray,
    *,
    stiffness: float = 1.0,
    decay: float = 0.01,
    min_span: int = 3,
    fixed: np.ndarray | None = None,
    cyclic: bool = False,
) -> np.ndarray:
    """Smooth ground-plane toe corrections that stop the slide of stance toes.

    Per toe and axis the correction ``e`` minimises (a banded least squares)::

        Σ_contact ‖Δ(x + e)_t − s_t‖² + stiffness Σ_t ‖Δ²e_t‖² + decay Σ_t ‖e_t‖²

    where ``x`` is the output toe position, ``s`` the wanted step (the
    input's own toe step at the source frame, usually almost none) and the
    first sum runs over pairs of frames inside one contact span of at least
    ``min_span`` frames.  The second-difference term keeps the legs free of
    jerk, the small decay brings ``e`` back to zero in the swing phases.
    Verbatim spans (which already move as in the input) get no correction.

    Parameters
    ----------
    toe_ground : (L, T, 2) float ndarray
        Output toe positions ``(x, z)``.
    toe_step : (L, T, 2) float ndarray
        Wanted displacement ``t → t+1`` of each toe while in contact.
    contact : (L, T) bool ndarray
    stiffness : float
        Weight of the second differences (frames are the unit of time).
    decay : float
        Weight pulling the corrections to zero.
    min_span : int
        Shorter contact spans are left alone.
    fixed : (L,) bool ndarray, optional
        Frames whose pose must not change (e.g. constrained frames): ``e = 0``.
    cyclic : bool
        The motion loops (frame ``L - 1`` is followed by frame 0): the differences
        and the contact spans wrap, so the corrections are periodic and the loop's
        wrap stays an ordinary step (``toe_step[L - 1]`` is the wanted wrap step).

    Returns
    -------
    (L, T, 2) float ndarray
    """
    L, T = contact.shape
    corr = np.zeros((L, T, 2))
    if L < 3:
        return corr
    if cyclic:
        return _cyclic_foot_corrections(toe_ground, toe_step, contact, stiffness=stiffness,
                                        decay=decay, min_span=min_span, fixed=fixed)
    # second-difference operator D2 (L-2, L): D2ᵀD2 is pentadiagonal
    d2 = np.zeros((3, L))  # upper banded form (u = 2) of stiffness * D2ᵀD2 + decay * I
    c = np.zeros(L)
    c[:-2] += 1
    c[1:-1] += 4
    c[2:] += 1
    d2[2] = stiffness * c + decay
    c1 = np.zeros(L - 1)
    c1[:-1] += -2
    c1[1:] += -2
    d2[1, 1:] = stiffness * c1
    d2[0, 2:] = stiffness
    pen = np.zeros(L)
    if fixed is not None:
        pen = np.where(np.asarray(fixed, bool), 1e6, 0.0)
    for k in range(T):
        pair = np.zeros(L - 1)  # weight of each step t -> t+1 (both frames in one span)
        for a, stop in true_runs(contact[:, k], min_length=min_span):
            pair[a:stop - 1] = 1.0
        if not pair.any():
            continue
        ab = d2.copy()
        # D1ᵀ W D1: tridiagonal
        ab[2, :-1] += pair
        ab[2, 1:] += pair
        ab[1, 1:] += -pair
        ab[2] += pen
        for ax in range(2):
            x = toe_ground[:, k, ax]
            r = pair * (toe_step[:-1, k, ax] - np.diff(x))  # wanted change of Δe
            rhs = np.zeros(L)
            rhs[1:] += r
            rhs[:-1] -= r
            corr[:, k, ax] = solveh_banded(ab, rhs)
    return corr


def _cyclic_pairs(contact: np.ndarray, min_span: int) -> np.ndarray:
    """``(L,)`` weight of each step ``t → (t + 1) mod L`` inside one cyclic contact span
    of at least ``min_span`` frames."""
    L = contact.size
    pair = np.zeros(L)
    if contact.all():
        pair[:] = 1.0
        return pair
    r = int(np.argmin(contact))  # a frame out of contact: no span crosses it
    rolled = np.roll(contact, -r)
    for a, stop in true_runs(rolled, min_length=min_span):
        pair[(np.arange(a, stop - 1) + r) % L] = 1.0
    return pair


def _cyclic_foot_corrections(toe_ground, toe_step, contact, *, stiffness, decay, min_span,
                             fixed) -> np.ndarray:
    """:func:`foot_corrections` on a loop: the same least squares with wrapping
    first and second differences (a sparse periodic system)."""
    import scipy.sparse as sp  # noqa: PLC0415
    from scipy.sparse.linalg import spsolve  # noqa: PLC0415

    L, T = contact.shape
    corr = np.zeros((L, T, 2))
    eye = sp.identity(L, format="csr")
    nxt = sp.csr_matrix((np.ones(L), (np.arange(L), (np.arange(L) + 1) % L)), shape=(L, L))
    D1 = nxt - eye  # (D1 e)_t = e_{t+1} - e_t, wrapping
    D2 = nxt - 2 * eye + nxt.T  # (D2 e)_t = e_{t-1} - 2 e_t + e_{t+1}, wrapping
    pen = np.zeros(L) if fixed is None else np.where(np.asarray(fixed, bool), 1e6, 0.0)
    base = stiffness * (D2.T @ D2) + decay * eye + sp.diags(pen)
    for k in range(T):
        pair = _cyclic_pairs(contact[:, k], min_span)
        if not pair.any():
            continue
        W = sp.diags(pair)
        A = (base + D1.T @ W @ D1).tocsc()
        for ax in range(2):
            x = toe_ground[:, k, ax]
            r = pair * (toe_step[:, k, ax] - D1 @ x)
            corr[:, k, ax] = spsolve(A, D1.T @ r)
    return corr


def chain_kinematics(
    skeleton: Skeleton,
    rotations: np.ndarray,
    root_position: np.ndarray,
    joints,
    *,
    translations: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics of a few joints: only they and their ancestors are computed.

    Joint by joint the arithmetic of
    :func:`~mocapflow.stages.motion.kinematics.forward_kinematics`, so the same values
    as its ``[:, joints]`` (a leg or the toes of a 30-joint body is a third of the work).

    Parameters
    ----------
    skeleton : Skeleton
    rotations : (F, J, 4) float ndarray
    root_position : (F, 3) float ndarray
    joints : sequence of int
        ``G`` joint indices (any order).
    translations : (F, J, 3) float ndarray, optional

    Returns
    -------
    positions : (F, G, 3) float ndarray
    global_rotations : (F, G, 4) float ndarray
    """
    parents = skeleton.parents
    chain: set[int] = set()
    for j in joints:
        j = int(j)
        while j >= 0 and j not in chain:
            chain.add(j)
            j = int(parents[j])
    keep = sorted(chain)  # parents before children, as in the skeleton
    at = {j: k for k, j in enumerate(keep)}
    sub = Skeleton([skeleton.names[j] for j in keep],
                   [at[int(parents[j])] if parents[j] >= 0 else -1 for j in keep],
                   skeleton.offsets[keep], [skeleton.channels[j] for j in keep])
    tr = None if translations is None else translations[:, keep]
    pos, glob = forward_kinematics(sub, rotations[:, keep], root_position, translations=tr)
    cols = [at[int(j)] for j in joints]
    return pos[:, cols], glob[:, cols]


def apply_foot_ik(
    skeleton,
    rotations: np.ndarray,
    root_position: np.ndarray,
    chains: list[tuple[int, int, int]],
    offsets: np.ndarray,
    *,
    translations: np.ndarray | None = None,
) -> np.ndarray:
    """Move each leg's ankle by a ground-plane offset, feet keeping their world orientation.

    Parameters
    ----------
    skeleton : Skeleton
    rotations : (L, J, 4) float ndarray
        Local rotations (root with heading).
    root_position : (L, 3) float ndarray
    chains : list of (hip, knee, ankle)
        From :func:`leg_chains`.
    offsets : (L, T, 2) float ndarray
        Wanted ankle (and toe) displacement ``(x, z)`` per chain.
    translations : (L, J, 3) float ndarray, optional

    Returns
    -------
    (L, J, 4) float ndarray
        Local rotations with the hip, knee and ankle joints of each chain changed.
    """
    rot = np.array(rotations, dtype=np.float64)
    moves = np.abs(offsets).max(axis=-1) > 1e-7  # (L, T)
    frames = np.flatnonzero(moves.any(axis=1))
    # the joints read below: each chain and its hip's parent (the legs' kinematics only)
    need = sorted({int(j) for c in chains for j in c}
                  | {int(skeleton.parents[c[0]]) for c in chains if skeleton.parents[c[0]] >= 0})
    col = np.full(skeleton.n_joints, -1)
    col[need] = np.arange(len(need))
    # one forward kinematics for all legs when no chain moves a joint above another's
    shared = frames.size and _independent_chains(skeleton, chains)
    if shared:
        tr = None if translations is None else translations[frames]
        pos_all, glob_all = chain_kinematics(
            skeleton, rot[frames], root_position[frames], need, translations=tr)
    for k, (hip, knee, ankle) in enumerate(chains):
        if shared:
            sel = np.flatnonzero(moves[frames, k])
            idx, pos, glob = frames[sel], pos_all[sel], glob_all[sel]
        else:
            idx = np.flatnonzero(moves[:, k])
            tr = None if translations is None else translations[idx]
            pos, glob = chain_kinematics(
                skeleton, rot[idx], root_position[idx], need, translations=tr)
        if idx.size == 0:
            continue
        h, kn, an = col[hip], col[knee], col[ankle]  # their columns in pos and glob
        d = np.zeros((idx.size, 3))
        d[:, [0, 2]] = offsets[idx, k]
        hinge = quat_rotate(glob[:, kn], np.array([1.0, 0.0, 0.0]))
        r_hip, r_knee = two_bone_ik(pos[:, h], pos[:, kn], pos[:, an], pos[:, an] + d, hinge=hinge)
        g_hip = quat_multiply(r_hip, glob[:, h])
        g_knee = quat_multiply(r_hip, quat_multiply(r_knee, glob[:, kn]))
        p = skeleton.parents[hip]
        g_par = glob[:, col[p]] if p >= 0 else np.tile([1.0, 0, 0, 0], (idx.size, 1))
        rot[idx, hip] = quat_normalize(quat_multiply(quat_inverse(g_par), g_hip))
        rot[idx, knee] = quat_normalize(quat_multiply(quat_inverse(g_hip), g_knee))
        rot[idx, ankle] = quat_normalize(quat_multiply(quat_inverse(g_knee), glob[:, an]))
    return rot


def _independent_chains(skeleton, chains: list[tuple[int, int, int]]) -> bool:
    """Whether no chain's joint is (or is an ancestor of) a joint of another chain."""
    def above(j: int) -> set[int]:
        out = set()
        while j >= 0:
            out.add(j)
            j = int(skeleton.parents[j])
        return out

    for a, ca in enumerate(chains):
        lineage = set().union(*(above(j) for j in ca))
        if any(set(cb) & lineage for b, cb in enumerate(chains) if b != a):
            return False
    return True
