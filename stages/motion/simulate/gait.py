"""Procedural walk and run cycles with natural cycle-to-cycle variation.

:func:`procedural_walk` drives
:func:`~mocapflow.stages.motion.simulate.skeleton.procedural_skeleton` from a
gait *phase* (left heel strike at integer phases, right at half phases):

* **timeline** (:class:`_Timeline`, :func:`_draw_cycle_params`) — each cycle
  draws its own period, speed, step width, arm swing, foot clearance, pelvis
  rotation and knee loading (relative standard deviation ``variation``),
  interpolated smoothly over the phase; phase <-> time maps and the pelvis'
  forward progress follow from them;
* **feet** (:func:`_footprints`, :func:`_stance_state`, :func:`_foot_track`) —
  per step a footprint is placed under the pelvis' path; during stance the
  foot rolls heel -> flat -> ball about a fixed pivot (heel point, then the ball
  joint, while the toes stay flat), during swing the ankle follows a Hermite
  curve, relative to the hip, between the toe-off and next heel-strike states
  plus a clearance bump;
* **pelvis and root height** (:func:`_pelvis`, :func:`_root_height`) — pelvis
  yaw, list, tilt and sway are phase sinusoids; the root height is the nominal
  height lowered wherever a stance leg could not reach its foot with at least
  the phase's minimum knee flexion (lowering-only smoothing keeps it reachable);
* **legs** (:func:`_leg_rotations`, :func:`_leg_ik`) — the leg joint angles come
  from an analytic two-link IK, so planted feet do not skate;
* **trunk and arms** (:func:`_trunk_rotations`, :func:`_arm_rotations`) —
  counter-rotating thorax and arm swing opposite the legs, phase sinusoids;
* **record** (:func:`_gait_events`) — heel strikes, foot flats and toe-offs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.ndimage import gaussian_filter1d, minimum_filter1d

from mocapflow.stages.motion.datatypes import Motion, Skeleton
from mocapflow.stages.motion.rotations import (
    euler_to_quat,
    quat_conjugate,
    quat_from_axis_angle,
    quat_identity,
    quat_multiply,
    quat_rotate,
)
from mocapflow.stages.motion.simulate.skeleton import (
    ANKLE_HEIGHT,
    BALL,
    HIP_OFFSET,
    SHANK,
    THIGH,
    procedural_skeleton,
)

__all__ = ["RUN", "WALK", "GaitParams", "procedural_walk"]

_HEEL = np.array([0.0, -ANKLE_HEIGHT, -0.05])  # heel contact point in the foot frame

# --------------------------------------------------------------------------- gait parameters


@dataclass(frozen=True)
class GaitParams:
    """Nominal parameters of a gait (angles in degrees, lengths in metres, times in s)."""

    period: float  # cycle (stride) duration
    speed: float  # forward speed, m/s
    duty: float  # stance fraction of the cycle
    heel_end: float  # end of heel rocker (foot flat), cycle fraction after heel strike
    heel_off: float  # heel rise, cycle fraction after heel strike
    heel_pitch: float  # toe-up pitch at heel strike
    toe_pitch: float  # toe-down pitch at toe-off (negative)
    lift: float  # extra swing clearance of the ankle
    step_width: float  # lateral distance between the feet
    toe_out: float  # foot yaw, outwards
    foot_offset: float  # footprint ahead of the pelvis at mid foot-flat
    knee_min: float  # smallest knee flexion of a stance leg
    knee_load: float  # extra knee flexion peak during loading response
    knee_mid: float  # knee flexion at mid-stance (sets the nominal root height)
    pelvis_yaw: float
    pelvis_list: float
    pelvis_tilt: float
    sway: float  # lateral pelvis sway amplitude
    lean: float  # forward trunk lean
    thorax_yaw: float  # thorax counter-rotation amplitude
    arm_swing: float  # shoulder flexion amplitude
    arm_forward: float  # mean shoulder flexion
    elbow: float  # mean elbow flexion
    elbow_swing: float  # extra elbow flexion with the arm forward
    bounce: float  # extra root lift in flight (run)
    lift_peak: float  # swing fraction at which the clearance bump peaks


WALK = GaitParams(
    period=1.1, speed=1.3, duty=0.62, heel_end=0.10, heel_off=0.36, heel_pitch=18.0,
    toe_pitch=-38.0, lift=0.02, step_width=0.12, toe_out=6.0, foot_offset=0.06,
    knee_min=4.0, knee_load=12.0, knee_mid=8.0, pelvis_yaw=5.0, pelvis_list=4.0,
    pelvis_tilt=2.0, sway=0.025, lean=2.0, thorax_yaw=4.0, arm_swing=18.0, arm_forward=3.0,
    elbow=18.0, elbow_swing=12.0, bounce=0.0, lift_peak=0.5,
)  # fmt: skip
RUN = GaitParams(
    period=0.72, speed=3.2, duty=0.32, heel_end=0.04, heel_off=0.13, heel_pitch=8.0,
    toe_pitch=-45.0, lift=0.22, step_width=0.08, toe_out=4.0, foot_offset=0.08,
    knee_min=12.0, knee_load=28.0, knee_mid=35.0, pelvis_yaw=7.0, pelvis_list=5.0,
    pelvis_tilt=3.0, sway=0.012, lean=9.0, thorax_yaw=8.0, arm_swing=32.0, arm_forward=12.0,
    elbow=80.0, elbow_swing=15.0, bounce=0.08, lift_peak=0.35,
)  # fmt: skip
_GAITS = {"walk": WALK, "run": RUN}

#: Cycle parameters varied from cycle to cycle, with their relative spread factor.
_VARIED = {
    "period": 0.6, "speed": 0.8, "arm_swing": 2.0, "lift": 2.0, "pelvis_yaw": 2.0,
    "knee_load": 2.0, "step_width": 2.0, "elbow": 1.0, "thorax_yaw": 2.0,
}  # fmt: skip


# --------------------------------------------------------------------------- small helpers


def _rx(a: np.ndarray) -> np.ndarray:
    return quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), a)


def _ry(a: np.ndarray) -> np.ndarray:
    return quat_from_axis_angle(np.array([0.0, 1.0, 0.0]), a)


def _rz(a: np.ndarray) -> np.ndarray:
    return quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), a)


def _smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _hermite(p0, d0, p1, d1, u):
    u = u[..., None] if p0.ndim > u.ndim else u
    u2, u3 = u * u, u * u * u
    return (
        (2 * u3 - 3 * u2 + 1) * p0
        + (u3 - 2 * u2 + u) * d0
        + (-2 * u3 + 3 * u2) * p1
        + (u3 - u2) * d1
    )


class _Timeline:
    """Smooth phase <-> time maps and per-cycle parameters."""

    def __init__(
        self, duration: float, gait: GaitParams, params: dict[str, np.ndarray], phase0: float
    ) -> None:
        self.k = np.arange(-3, len(params["period"]) - 3)  # cycle k spans phases [k, k+1)
        periods = params["period"]
        t = np.concatenate([[0.0], np.cumsum(periods)])
        kk = np.concatenate([self.k, [self.k[-1] + 1]]).astype(float)
        t = t - np.interp(phase0, kk, t)  # phase0 at t = 0
        self.t_of = PchipInterpolator(kk, t)
        self.phi_of = PchipInterpolator(t, kk)
        centres = self.k + 0.5
        self.param = {n: PchipInterpolator(centres, v, extrapolate=True) for n, v in params.items()}
        # forward progress of the pelvis: integral of speed over time, 0 at t = 0
        grid = np.linspace(t[0], t[-1], int((t[-1] - t[0]) * 1000) + 2)
        v = self.param["speed"](self.phi_of(grid))
        z = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(grid))])
        self._grid, self._z = grid, z - np.interp(0.0, grid, z)
        self.gait = gait

    def z(self, t: np.ndarray) -> np.ndarray:
        return np.interp(t, self._grid, self._z)


def _draw_cycle_params(
    gait: GaitParams, n_cycles: int, rng: np.random.Generator, variation: float, speed: float | None
) -> dict[str, np.ndarray]:
    base = {n: float(getattr(gait, n)) for n in _VARIED}
    if speed is not None:
        # cadence rises with speed (stride time ~ speed^-0.3 around the nominal gait)
        base["period"] = gait.period * (speed / gait.speed) ** -0.3
        base["speed"] = float(speed)
    out = {}
    for n, f in _VARIED.items():
        z = np.clip(rng.standard_normal(n_cycles), -2.5, 2.5)
        out[n] = base[n] * (1.0 + variation * f * z)
    return out


# --------------------------------------------------------------------------- feet


@dataclass
class _Steps:
    """Footprints of one foot: step i spans phases [offset + i, offset + i + duty)."""

    offset: float
    first: int
    ankle: np.ndarray  # (S, 3) ankle position with the foot flat
    yaw: np.ndarray  # (S,) radians


def _footprints(tl: _Timeline, gait: GaitParams, side: float, offset: float) -> _Steps:
    idx = np.arange(tl.k[0], tl.k[-1] + 1)
    mid = offset + idx + 0.5 * (gait.heel_end + gait.heel_off)
    t_mid = tl.t_of(mid)
    width = tl.param["step_width"](mid)
    ankle = np.stack(
        [side * 0.5 * width, np.full(len(idx), ANKLE_HEIGHT), tl.z(t_mid) + gait.foot_offset],
        axis=1,
    )
    return _Steps(offset, int(idx[0]), ankle, np.full(len(idx), side * np.radians(gait.toe_out)))


def _stance_state(steps: _Steps, i: np.ndarray, s: np.ndarray, gait: GaitParams):
    """Ankle position ``(N, 3)``, pitch ``(N,)`` (toe up > 0) of stance step ``i`` at ``s``."""
    k = i - steps.first
    A = steps.ankle[k]
    yaw = steps.yaw[k]
    ph, pt = np.radians(gait.heel_pitch), np.radians(gait.toe_pitch)
    u_h = np.clip(s / gait.heel_end, 0, 1)
    u_t = np.clip((s - gait.heel_off) / (gait.duty - gait.heel_off), 0, 1)
    pitch = np.where(
        s < gait.heel_end,
        ph * (1 - np.sin(0.5 * np.pi * u_h)),
        np.where(s < gait.heel_off, 0.0, pt * (1 - np.cos(0.5 * np.pi * u_t))),
    )
    pivot = np.where((s < gait.heel_end)[:, None], _HEEL, BALL)
    tilt = _rx(-pitch)
    qy = _ry(yaw)
    # ankle = A + R_yaw (pivot - R_x(-pitch) pivot)
    ankle = A + quat_rotate(qy, pivot - quat_rotate(tilt, pivot))
    return ankle, pitch


def _pelvis(tl: _Timeline, phi: np.ndarray, gait: GaitParams):
    """Pelvis rotation ``(N, 4)``, angles (yaw, list, tilt) and horizontal position ``(N, 2)``."""
    two_pi_phi = 2 * np.pi * phi
    yaw = -np.radians(tl.param["pelvis_yaw"](phi)) * np.cos(two_pi_phi)
    lst = np.radians(gait.pelvis_list) * np.sin(two_pi_phi - 2 * np.pi * 0.05)
    tilt = np.radians(gait.pelvis_tilt) * np.cos(2 * two_pi_phi)
    q = quat_multiply(quat_multiply(_ry(yaw), _rx(tilt)), _rz(lst))
    xz = np.stack([gait.sway * np.sin(two_pi_phi - 2 * np.pi * 0.05), tl.z(tl.t_of(phi))], 1)
    return q, (yaw, lst, tilt), xz


def _hip(tl: _Timeline, phi: np.ndarray, gait: GaitParams, side: float, height) -> np.ndarray:
    """Hip-joint position ``(N, 3)`` at phases ``phi``; ``height(t)`` gives the root height."""
    q, _, xz = _pelvis(tl, phi, gait)
    off = quat_rotate(q, HIP_OFFSET * np.array([side, 1.0, 1.0]))
    root = np.stack([xz[:, 0], height(tl.t_of(phi)), xz[:, 1]], axis=1)
    return root + off


def _foot_track(
    tl: _Timeline, steps: _Steps, phi: np.ndarray, gait: GaitParams, side: float, height=None
):
    """Ankle position, foot pitch, yaw, toe flexion and contact flags per frame.

    The swing ankle follows a Hermite curve between the toe-off and next
    heel-strike states relative to the hip (so it stays within the leg's reach
    and rises with the body in flight) plus a clearance bump.  Without
    ``height`` (the root height as a function of time) only stance is computed.
    """
    rel = phi - steps.offset
    i = np.floor(rel).astype(np.int64)
    s = rel - i
    stance = s < gait.duty
    h = 1e-4
    span = 1.0 - gait.duty
    a_st, p_st = _stance_state(steps, i, np.minimum(s, gait.duty), gait)
    if height is None:
        return {"ankle": a_st, "stance": stance, "s": s}

    def state(step, s_val):
        a, p = _stance_state(steps, step, np.full_like(s, s_val), gait)
        return a - _hip(tl, steps.offset + step + s_val, gait, side, height), p

    a0, p0 = state(i, gait.duty)
    a0m, p0m = state(i, gait.duty - h)
    a1, p1 = state(i + 1, 0.0)
    a1p, p1p = state(i + 1, h)
    d0, d1 = (a0 - a0m) / h * span, (a1p - a1) / h * span
    u = np.clip((s - gait.duty) / span, 0.0, 1.0)
    a_sw = _hermite(a0, d0, a1, d1, u) + _hip(tl, phi, gait, side, height)
    bump = np.sin(np.pi * u ** (np.log(0.5) / np.log(gait.lift_peak))) ** 2
    a_sw[:, 1] += tl.param["lift"](phi) * bump
    p_sw = _hermite(p0, (p0 - p0m) / h * span, p1, (p1p - p1) / h * span, u)
    ankle = np.where(stance[:, None], a_st, a_sw)
    pitch = np.where(stance, p_st, p_sw)
    toe = np.where(
        stance,
        np.minimum(p_st, 0.0),
        np.radians(gait.toe_pitch) * (1 - _smoothstep(u / 0.4)),
    )
    k = np.clip(i - steps.first, 0, len(steps.yaw) - 1)
    return {
        "ankle": ankle,
        "pitch": pitch,
        "yaw": steps.yaw[k],
        "toe": toe,
        "stance": stance,
        "s": s,
        "ball_contact": stance & (s >= gait.heel_end),
    }


# --------------------------------------------------------------------------- legs


def _leg_ik(hip: np.ndarray, ankle: np.ndarray, q_pelvis: np.ndarray):
    """Analytic two-link IK: hip (F,4), knee angle (F,), reach error (F,)."""
    a, b = THIGH, SHANK
    v = quat_rotate(quat_conjugate(q_pelvis), ankle - hip)
    d = np.linalg.norm(v, axis=-1)
    d_c = np.clip(d, abs(a - b) + 1e-6, (a + b) * (1 - 1e-9))
    cos_inner = (a * a + b * b - d_c * d_c) / (2 * a * b)
    knee = np.pi - np.arccos(np.clip(cos_inner, -1, 1))
    uy = -a - b * np.cos(knee)
    uz = -b * np.sin(knee)
    r = np.hypot(v[:, 0], v[:, 1])
    gamma = np.arctan2(v[:, 0], -v[:, 1])
    alpha = np.arctan2(v[:, 2], -r) - np.arctan2(uz, uy)
    q_hip = quat_multiply(_rz(gamma), _rx(alpha))
    return q_hip, knee, d - d_c


def _reach_height(P_xz, q_pelvis, side, ankle, knee_min):
    """Highest root height at which a leg reaches ``ankle`` with knee flexion >= knee_min."""
    hip_off = quat_rotate(q_pelvis, HIP_OFFSET * np.array([side, 1.0, 1.0]))
    L = (THIGH + SHANK) * np.cos(0.5 * knee_min)
    dx = P_xz[:, 0] + hip_off[:, 0] - ankle[:, 0]
    dz = P_xz[:, 1] + hip_off[:, 2] - ankle[:, 2]
    horiz2 = dx * dx + dz * dz
    return ankle[:, 1] - hip_off[:, 1] + np.sqrt(np.maximum(L * L - horiz2, 0.0))


def _knee_min(s: np.ndarray, gait: GaitParams, load: np.ndarray) -> np.ndarray:
    """Minimum stance knee flexion (radians) over the stance sub-phase ``s``."""
    if gait.bounce > 0:  # run: flexion peaks at mid-stance
        bump = np.sin(np.pi * np.clip(s / gait.duty, 0, 1))
    else:  # walk: loading-response peak after heel strike
        bump = np.where(s < 0.3, np.sin(np.pi * np.clip(s / 0.3, 0, 1)), 0.0)
    return np.radians(gait.knee_min + load * bump)


def _lower_smooth(h: np.ndarray, radius: int) -> np.ndarray:
    """Smooth ``h`` without raising it anywhere: erosion, then a truncated Gaussian."""
    if radius < 1:
        return h
    e = minimum_filter1d(h, size=2 * radius + 1, mode="nearest")
    return gaussian_filter1d(e, sigma=radius / 3.0, truncate=3.0, mode="nearest")


# --------------------------------------------------------------------------- walk


def procedural_walk(
    n_frames: int,
    *,
    rate: float = 120.0,
    gait: str = "walk",
    speed: float | None = None,
    seed: int | np.random.Generator = 0,
    variation: float = 0.05,
) -> Motion:
    """A walk or run along +z with natural cycle-to-cycle variation.

    Parameters
    ----------
    n_frames : int
        Frames to generate.
    rate : float
        Frames per second.
    gait : {"walk", "run"}
    speed : float, optional
        Mean forward speed in m/s (default 1.3 walking, 3.2 running); the cycle
        period follows it (stride time ~ speed^-0.3).
    seed : int or numpy.random.Generator
        Seeds the starting phase and the per-cycle variation.
    variation : float
        Relative standard deviation of the per-cycle parameters (period and
        speed get 0.6x and 0.8x of it); 0 gives an exactly periodic gait.

    Returns
    -------
    Motion
        On :func:`procedural_skeleton`, metres, floor at ``y = 0``.  ``attrs``:
        ``source``, ``gait``, ``seed``, ``variation``, ``gait_events`` (per foot,
        times in s of ``heel_strike``, ``foot_flat``, ``toe_off``),
        ``cycle_periods`` (s) and ``max_reach_error`` (m; > 0 only if a target
        was out of the leg's reach).
    """
    if gait not in _GAITS:
        raise ValueError(f"procedural_walk: gait must be 'walk' or 'run', got {gait!r}")
    if n_frames < 1 or not rate > 0:
        raise ValueError(
            f"procedural_walk: need n_frames >= 1 and rate > 0, got {n_frames}, {rate}"
        )
    if speed is not None and not speed > 0:
        raise ValueError(f"procedural_walk: speed must be > 0, got {speed}")
    g = _GAITS[gait]
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    radius = int(round(0.06 * rate))  # root-height smoothing radius, frames
    tl, params, t, pad = _walk_timeline(g, n_frames, rate, speed, variation, radius, rng)
    phi = tl.phi_of(t)
    q_pelvis, (yaw_p, list_p, tilt_p), P_xz = _pelvis(tl, phi, g)
    feet = {name: (side, _footprints(tl, g, side, off)) for name, side, off in _FEET}
    h = _root_height(tl, g, phi, q_pelvis, P_xz, feet, radius)
    height = lambda tt: np.interp(tt, t, h)  # noqa: E731
    tracks = {n: _foot_track(tl, st, phi, g, side, height) for n, (side, st) in feet.items()}
    root = np.stack([P_xz[:, 0], h, P_xz[:, 1]], axis=1)

    sk = procedural_skeleton()
    rot = quat_identity((len(t), sk.n_joints))
    rot[:, 0] = q_pelvis
    max_err = _set_leg_rotations(rot, sk, root, q_pelvis, feet, tracks)
    _set_trunk_rotations(rot, sk, tl, g, phi, yaw_p, list_p, tilt_p)
    _set_arm_rotations(rot, sk, tl, g, phi)

    keep = slice(pad, pad + n_frames)
    root, rot, t, phi = root[keep], rot[keep], t[keep], phi[keep]
    return Motion(
        skeleton=sk,
        root_position=root,
        rotations=rot,
        rate=rate,
        attrs={
            "source": "procedural_walk",
            "gait": gait,
            "seed": seed if isinstance(seed, int) else None,
            "variation": float(variation),
            "speed": float(np.mean(params["speed"])),
            "gait_events": _gait_events(tl, g, phi, t),
            "cycle_periods": _cycle_periods(tl, phi),
            "max_reach_error": max_err,
            "source_unit": "m",
            "source_scale": 1.0,
        },
    )


#: The feet: name, lateral side (+1 left), phase offset of their heel strikes.
_FEET = (("left", 1.0, 0.0), ("right", -1.0, 0.5))


def _walk_timeline(
    g: GaitParams, n_frames: int, rate: float, speed: float | None, variation: float,
    radius: int, rng: np.random.Generator,
) -> tuple[_Timeline, dict[str, np.ndarray], np.ndarray, int]:
    """The cycles of a walk of ``n_frames`` and its frame times, padded at both ends.

    The walk is computed beyond both ends (a swing needs the root height at the
    toe-off before it; the smoothing of radius ``radius`` frames needs its
    radius), so the clip has no edge effects.  Draws the per-cycle parameters,
    then the starting phase, from ``rng``.

    Returns
    -------
    timeline : _Timeline
    params : dict
        Per-cycle parameters (``(n_cycles,)`` arrays).
    t : (n_frames + 2 pad,) float ndarray
        Frame times in s, frame ``pad`` at 0.
    pad : int
    """
    duration = (n_frames - 1) / rate
    period = g.period if speed is None else g.period * (speed / g.speed) ** -0.3
    pad = int(np.ceil((1 - g.duty) * 1.3 * period * rate)) + 2 * radius + 2
    n_cycles = (
        int(np.ceil((duration + 2 * pad / rate) / (period * (1 - 2.5 * 0.6 * variation)))) + 7
    )
    params = _draw_cycle_params(g, n_cycles, rng, variation, speed)
    tl = _Timeline(duration, g, params, phase0=float(rng.uniform(0, 1)))
    t = (np.arange(n_frames + 2 * pad) - pad) / rate
    return tl, params, t, pad


def _root_height(
    tl: _Timeline, g: GaitParams, phi: np.ndarray, q_pelvis: np.ndarray, P_xz: np.ndarray,
    feet: dict[str, tuple[float, _Steps]], radius: int,
) -> np.ndarray:
    """Root height ``(N,)`` per frame: nominal, lowered where a stance leg cannot reach its foot.

    The nominal height stands the legs at the gait's mid-stance knee flexion (a
    run adds a lift peaking mid-flight, a quarter cycle after mid-stance); where
    a stance foot would need a knee straighter than the phase's minimum the root
    comes down, and :func:`_lower_smooth` smooths it without raising it.
    """
    knee_load = tl.param["knee_load"](phi)
    two_pi_phi = 2 * np.pi * phi
    nominal = (
        ANKLE_HEIGHT + (THIGH + SHANK) * np.cos(0.5 * np.radians(g.knee_mid)) - HIP_OFFSET[1]
    )
    h = nominal + g.bounce * 0.5 * (1 - np.cos(2 * two_pi_phi - 2 * np.pi * g.duty))
    for side, steps in feet.values():
        track = _foot_track(tl, steps, phi, g, side)
        reach = _reach_height(P_xz, q_pelvis, side, track["ankle"],
                              _knee_min(track["s"], g, knee_load))
        h = np.where(track["stance"], np.minimum(h, reach), h)
    return _lower_smooth(h, radius)


def _set_leg_rotations(
    rot: np.ndarray, sk: Skeleton, root: np.ndarray, q_pelvis: np.ndarray,
    feet: dict[str, tuple[float, _Steps]], tracks: dict[str, dict[str, np.ndarray]],
) -> float:
    """Hip, knee, ankle and toe rotations of both legs into ``rot (N, J, 4)`` (two-link IK).

    Returns the largest reach error (m; > 0 only where an ankle target was out of
    the leg's reach).
    """
    max_err = 0.0
    for name, (side, _steps) in feet.items():
        track = tracks[name]
        pre = "Left" if side > 0 else "Right"
        hip = root + quat_rotate(q_pelvis, HIP_OFFSET * np.array([side, 1.0, 1.0]))
        q_hip, knee, err = _leg_ik(hip, track["ankle"], q_pelvis)
        max_err = max(max_err, float(np.abs(err).max()))
        q_knee = _rx(knee)
        q_foot_world = quat_multiply(_ry(track["yaw"]), _rx(-track["pitch"]))
        q_shank_world = quat_multiply(quat_multiply(q_pelvis, q_hip), q_knee)
        rot[:, sk.index(f"{pre}UpLeg")] = q_hip
        rot[:, sk.index(f"{pre}Leg")] = q_knee
        rot[:, sk.index(f"{pre}Foot")] = quat_multiply(quat_conjugate(q_shank_world), q_foot_world)
        rot[:, sk.index(f"{pre}ToeBase")] = _rx(track["toe"])
    return max_err


def _set_trunk_rotations(
    rot: np.ndarray, sk: Skeleton, tl: _Timeline, g: GaitParams, phi: np.ndarray,
    yaw_p: np.ndarray, list_p: np.ndarray, tilt_p: np.ndarray,
) -> None:
    """Spine and neck rotations into ``rot``: counter-rotating thorax, lean, list
    compensation (each spread over the three spine joints); head kept level."""
    thorax = np.radians(tl.param["thorax_yaw"](phi)) * np.cos(2 * np.pi * phi)
    spine_yaw = (thorax - yaw_p) / 3.0
    spine_pitch = (np.radians(g.lean) - tilt_p) / 3.0
    spine_roll = -list_p / 3.0
    q_spine = euler_to_quat(np.stack([spine_roll, spine_yaw, spine_pitch], axis=1), "ZYX")
    for n in ("LowerBack", "Spine", "Spine1"):
        rot[:, sk.index(n)] = q_spine
    q_neck = euler_to_quat(
        np.stack(
            [np.zeros_like(thorax), -thorax / 2, -np.full_like(thorax, np.radians(g.lean)) / 2], 1
        ),
        "ZYX",
    )
    rot[:, sk.index("Neck")] = q_neck
    rot[:, sk.index("Head")] = q_neck


def _set_arm_rotations(
    rot: np.ndarray, sk: Skeleton, tl: _Timeline, g: GaitParams, phi: np.ndarray
) -> None:
    """Shoulder and elbow rotations into ``rot``: the arms swing opposite the legs."""
    arm_swing, elbow_mean = tl.param["arm_swing"](phi), tl.param["elbow"](phi)
    lag = 0.03
    cyc = np.cos(2 * np.pi * phi - 2 * np.pi * lag)
    for side, pre in ((1.0, "Left"), (-1.0, "Right")):
        forward = -side * cyc  # +1 with the arm fully forward
        psi = np.radians(g.arm_forward + arm_swing * forward)
        q_arm = quat_multiply(_rx(-psi), _rz(-side * np.radians(82.0)))
        rot[:, sk.index(f"{pre}Arm")] = q_arm
        elbow = np.radians(elbow_mean + g.elbow_swing * np.maximum(forward, 0.0))
        rot[:, sk.index(f"{pre}ForeArm")] = _ry(-side * elbow)


def _gait_events(
    tl: _Timeline, g: GaitParams, phi: np.ndarray, t: np.ndarray
) -> dict[str, dict[str, list[float]]]:
    """Per foot, the times (s) of ``heel_strike``, ``foot_flat`` and ``toe_off`` in the clip."""
    events = {}
    for name, _side, off in _FEET:
        ks = np.arange(np.floor(phi[0] - off) - 1, np.ceil(phi[-1] - off) + 2)
        ev = {}
        for key, s in (("heel_strike", 0.0), ("foot_flat", g.heel_end), ("toe_off", g.duty)):
            tt = tl.t_of(ks + off + s)
            ev[key] = [float(x) for x in tt if 0.0 <= x <= t[-1]]
        events[name] = ev
    return events


def _cycle_periods(tl: _Timeline, phi: np.ndarray) -> list[float]:
    """Durations (s) of the cycles the clip's phases ``phi`` touch."""
    k_in = np.arange(np.floor(phi[0]), np.ceil(phi[-1]) + 1)
    return [float(x) for x in np.diff(tl.t_of(k_in))]
