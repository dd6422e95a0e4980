"""Procedural humanoid motion with known ground truth: walk / run cycles and range of motion.

Skeleton
--------
:func:`procedural_skeleton` is a 31-joint humanoid with the joint names and
hierarchy of the CMU MotionBuilder-friendly BVH files (``cmu_01_01.bvh``:
Hips, LHipJoint, LeftUpLeg, ... LFingers, LThumb, RightShoulder, ...), y up,
x to the subject's left, z forward, metres, 1.75 m tall, standing with the root
at 0.93 m and the arms out (T-pose) at rest.

Gait
----
:func:`procedural_walk` drives the body from a gait *phase* (left heel strike at
integer phases, right at half phases).  Per step a footprint is placed under
the pelvis' path; during stance the foot rolls heel -> flat -> ball about a
fixed pivot (heel point, then the ball joint, while the toes stay flat), during
swing the ankle follows a Hermite curve, relative to the hip, between the
toe-off and next heel-strike states plus a clearance bump.  Pelvis yaw, list, tilt and sway,
counter-rotating thorax and arm swing opposite the legs are phase sinusoids.
The root height is the nominal height lowered wherever a stance leg could not
reach its foot with at least the phase's minimum knee flexion (lowering-only
smoothing keeps it reachable), and the leg joint angles come from an analytic
two-link IK, so planted feet do not skate.  Each cycle draws its own period,
speed, step width, arm swing, foot clearance, pelvis rotation and knee loading
(relative standard deviation ``variation``), interpolated smoothly over the phase.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from mocapflow.pipeline import Context, stage
from mocapflow.stages.motion.datatypes import Motion, Skeleton
from mocapflow.stages.motion.kinematics import (
    euler_to_quat,
    quat_conjugate,
    quat_from_axis_angle,
    quat_identity,
    quat_multiply,
    quat_rotate,
)

__all__ = [
    "GaitParams",
    "JOINT_GROUPS",
    "procedural_range_of_motion",
    "procedural_skeleton",
    "procedural_walk",
    "simulate_range_of_motion",
    "simulate_walk",
]

_THIGH = 0.40
_SHANK = 0.39
_ANKLE_HEIGHT = 0.07
_HIP_OFFSET = np.array([0.09, -0.07, 0.0])  # LeftUpLeg from Hips (via LHipJoint at 0)
_HEEL = np.array([0.0, -_ANKLE_HEIGHT, -0.05])  # heel contact point in the foot frame
_BALL = np.array([0.0, -0.05, 0.13])  # ball (toe-base joint) in the foot frame
ROOT_HEIGHT = _ANKLE_HEIGHT + _SHANK + _THIGH - _HIP_OFFSET[1]  # 0.93

# name, parent, offset (left side; right side mirrors x)
_LEFT_LEG = [
    ("LHipJoint", "Hips", (0.0, 0.0, 0.0)),
    ("LeftUpLeg", "LHipJoint", tuple(_HIP_OFFSET)),
    ("LeftLeg", "LeftUpLeg", (0.0, -_THIGH, 0.0)),
    ("LeftFoot", "LeftLeg", (0.0, -_SHANK, 0.0)),
    ("LeftToeBase", "LeftFoot", tuple(_BALL)),
]
_SPINE = [
    ("LowerBack", "Hips", (0.0, 0.0, 0.0)),
    ("Spine", "LowerBack", (0.0, 0.13, -0.01)),
    ("Spine1", "Spine", (0.0, 0.13, 0.0)),
    ("Neck", "Spine1", (0.0, 0.22, 0.0)),
    ("Neck1", "Neck", (0.0, 0.06, 0.01)),
    ("Head", "Neck1", (0.0, 0.07, 0.01)),
]
_LEFT_ARM = [
    ("LeftShoulder", "Spine1", (0.02, 0.20, 0.0)),
    ("LeftArm", "LeftShoulder", (0.16, 0.03, 0.0)),
    ("LeftForeArm", "LeftArm", (0.29, 0.0, 0.0)),
    ("LeftHand", "LeftForeArm", (0.25, 0.0, 0.0)),
    ("LeftFingerBase", "LeftHand", (0.05, 0.0, 0.0)),
    ("LFingers", "LeftFingerBase", (0.04, 0.0, 0.0)),
    ("LThumb", "LeftHand", (0.03, 0.0, 0.02)),
]
_END_SITES = {
    "LeftToeBase": (0.0, 0.0, 0.06),
    "Head": (0.0, 0.21, 0.0),
    "LFingers": (0.04, 0.0, 0.0),
    "LThumb": (0.03, 0.0, 0.03),
}

#: Joint groups flexed in turn by :func:`procedural_range_of_motion`.
JOINT_GROUPS: dict[str, list[str]] = {
    "left_leg": ["LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase"],
    "right_leg": ["RightUpLeg", "RightLeg", "RightFoot", "RightToeBase"],
    "spine": ["LowerBack", "Spine", "Spine1"],
    "head": ["Neck", "Neck1", "Head"],
    "left_arm": ["LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand"],
    "right_arm": ["RightShoulder", "RightArm", "RightForeArm", "RightHand"],
}


def _mirror(name: str) -> str:
    for a, b in (("Left", "Right"), ("LHip", "RHip"), ("LFing", "RFing"), ("LThumb", "RThumb")):
        if name.startswith(a):
            return b + name[len(a) :]
    return name


def procedural_skeleton() -> Skeleton:
    """The 31-joint CMU-named humanoid (y up, metres, 1.75 m tall).

    Returns
    -------
    Skeleton
        Joint order and names of ``cmu_01_01.bvh``; channels as there (root
        ``X Y Z position, Z Y X rotation``, joints ``Z Y X rotation``); 7 End Sites
        (toes, head, fingers, thumbs).  At rest the body stands with its root at
        the origin (place it with ``root_position = (0, 0.93, 0)``), arms out.
    """
    rows: list[tuple[str, str | None, tuple[float, float, float]]] = [("Hips", None, (0, 0, 0))]
    rows += _LEFT_LEG
    rows += [(_mirror(n), _mirror(p), (-o[0], o[1], o[2])) for n, p, o in _LEFT_LEG]
    rows += _SPINE[:6]
    rows += _LEFT_ARM
    rows += [(_mirror(n), _mirror(p), (-o[0], o[1], o[2])) for n, p, o in _LEFT_ARM]
    names = [r[0] for r in rows]
    parents = [-1 if r[1] is None else names.index(r[1]) for r in rows]
    ends = dict(_END_SITES)
    ends.update({_mirror(k): (-v[0], v[1], v[2]) for k, v in _END_SITES.items() if k != "Head"})
    end_names = [n for n in names if n in ends]
    channels = [["Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation"]]
    channels += [["Zrotation", "Yrotation", "Xrotation"] for _ in names[1:]]
    return Skeleton(
        names=names,
        parents=np.array(parents),
        offsets=np.array([r[2] for r in rows], dtype=np.float64),
        channels=channels,
        end_parents=np.array([names.index(n) for n in end_names]),
        end_offsets=np.array([ends[n] for n in end_names], dtype=np.float64),
        attrs={
            "source": "procedural_skeleton",
            "source_unit": "m",
            "source_scale": 1.0,
            "up": "y",
            "forward": "z",
            "height": 1.75,
        },
    )


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
        from scipy.interpolate import PchipInterpolator

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
        [side * 0.5 * width, np.full(len(idx), _ANKLE_HEIGHT), tl.z(t_mid) + gait.foot_offset],
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
    pivot = np.where((s < gait.heel_end)[:, None], _HEEL, _BALL)
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
    off = quat_rotate(q, _HIP_OFFSET * np.array([side, 1.0, 1.0]))
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
    a, b = _THIGH, _SHANK
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
    hip_off = quat_rotate(q_pelvis, _HIP_OFFSET * np.array([side, 1.0, 1.0]))
    L = (_THIGH + _SHANK) * np.cos(0.5 * knee_min)
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
    from scipy.ndimage import gaussian_filter1d, minimum_filter1d

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
    duration = (n_frames - 1) / rate
    period = g.period if speed is None else g.period * (speed / g.speed) ** -0.3
    radius = int(round(0.06 * rate))  # root-height smoothing radius, frames
    # computed beyond both ends (a swing needs the root height at the toe-off
    # before it; the smoothing needs its radius), so the clip has no edge effects
    pad = int(np.ceil((1 - g.duty) * 1.3 * period * rate)) + 2 * radius + 2
    n_cycles = (
        int(np.ceil((duration + 2 * pad / rate) / (period * (1 - 2.5 * 0.6 * variation)))) + 7
    )
    params = _draw_cycle_params(g, n_cycles, rng, variation, speed)
    tl = _Timeline(duration, g, params, phase0=float(rng.uniform(0, 1)))
    t = (np.arange(n_frames + 2 * pad) - pad) / rate
    phi = tl.phi_of(t)
    two_pi_phi = 2 * np.pi * phi

    # pelvis pose
    pr = {
        n: tl.param[n](phi) for n in ("pelvis_yaw", "arm_swing", "knee_load", "thorax_yaw", "elbow")
    }
    q_pelvis, (yaw_p, list_p, tilt_p), P_xz = _pelvis(tl, phi, g)

    feet = {}
    for name, side, off in (("left", 1.0, 0.0), ("right", -1.0, 0.5)):
        steps = _footprints(tl, g, side, off)
        feet[name] = (side, steps, _foot_track(tl, steps, phi, g, side))

    # root height: nominal, lowered where a stance leg cannot reach its foot
    nominal = (
        _ANKLE_HEIGHT + (_THIGH + _SHANK) * np.cos(0.5 * np.radians(g.knee_mid)) - _HIP_OFFSET[1]
    )
    # run: extra lift peaking mid-flight (a quarter cycle after mid-stance)
    h = nominal + g.bounce * 0.5 * (1 - np.cos(2 * two_pi_phi - 2 * np.pi * g.duty))
    for side, _steps, track in feet.values():
        reach = _reach_height(
            P_xz, q_pelvis, side, track["ankle"], _knee_min(track["s"], g, pr["knee_load"])
        )
        h = np.where(track["stance"], np.minimum(h, reach), h)
    h = _lower_smooth(h, radius)
    height = lambda tt: np.interp(tt, t, h)  # noqa: E731
    feet = {
        n: (side, st, _foot_track(tl, st, phi, g, side, height))
        for n, (side, st, _) in feet.items()
    }
    root = np.stack([P_xz[:, 0], h, P_xz[:, 1]], axis=1)

    sk = procedural_skeleton()
    J = sk.n_joints
    rot = quat_identity((len(t), J))
    rot[:, 0] = q_pelvis
    max_err = 0.0
    for side, _steps, track in feet.values():
        pre = "Left" if side > 0 else "Right"
        hip = root + quat_rotate(q_pelvis, _HIP_OFFSET * np.array([side, 1.0, 1.0]))
        q_hip, knee, err = _leg_ik(hip, track["ankle"], q_pelvis)
        max_err = max(max_err, float(np.abs(err).max()))
        q_knee = _rx(knee)
        q_foot_world = quat_multiply(_ry(track["yaw"]), _rx(-track["pitch"]))
        q_shank_world = quat_multiply(quat_multiply(q_pelvis, q_hip), q_knee)
        rot[:, sk.index(f"{pre}UpLeg")] = q_hip
        rot[:, sk.index(f"{pre}Leg")] = q_knee
        rot[:, sk.index(f"{pre}Foot")] = quat_multiply(quat_conjugate(q_shank_world), q_foot_world)
        rot[:, sk.index(f"{pre}ToeBase")] = _rx(track["toe"])

    # trunk: counter-rotating thorax, lean, list compensation; head kept level
    thorax = np.radians(pr["thorax_yaw"]) * np.cos(two_pi_phi)
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

    # arms swing opposite the legs
    lag = 0.03
    cyc = np.cos(two_pi_phi - 2 * np.pi * lag)
    for side, pre in ((1.0, "Left"), (-1.0, "Right")):
        forward = -side * cyc  # +1 with the arm fully forward
        psi = np.radians(g.arm_forward + pr["arm_swing"] * forward)
        q_arm = quat_multiply(_rx(-psi), _rz(-side * np.radians(82.0)))
        rot[:, sk.index(f"{pre}Arm")] = q_arm
        elbow = np.radians(pr["elbow"] + g.elbow_swing * np.maximum(forward, 0.0))
        rot[:, sk.index(f"{pre}ForeArm")] = _ry(-side * elbow)

    keep = slice(pad, pad + n_frames)
    root, rot, t, phi = root[keep], rot[keep], t[keep], phi[keep]
    events = {}
    for name in feet:
        off = 0.0 if name == "left" else 0.5
        ks = np.arange(np.floor(phi[0] - off) - 1, np.ceil(phi[-1] - off) + 2)
        ev = {}
        for key, s in (("heel_strike", 0.0), ("foot_flat", g.heel_end), ("toe_off", g.duty)):
            tt = tl.t_of(ks + off + s)
            ev[key] = [float(x) for x in tt if 0.0 <= x <= t[-1]]
        events[name] = ev
    k_in = np.arange(np.floor(phi[0]), np.ceil(phi[-1]) + 1)
    periods = np.diff(tl.t_of(k_in))
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
            "gait_events": events,
            "cycle_periods": [float(x) for x in periods],
            "max_reach_error": max_err,
            "source_unit": "m",
            "source_scale": 1.0,
        },
    )


# --------------------------------------------------------------------------- range of motion

# joint -> list of (axis, min deg, max deg) swept in turn
_ROM: dict[str, list[tuple[str, float, float]]] = {
    "UpLeg": [("X", -100.0, 30.0), ("Z", -40.0, 15.0), ("Y", -35.0, 35.0)],
    "Leg": [("X", 0.0, 130.0)],
    "Foot": [("X", -40.0, 20.0), ("Z", -20.0, 20.0)],
    "ToeBase": [("X", -40.0, 30.0)],
    "LowerBack": [("X", -20.0, 40.0), ("Z", -20.0, 20.0), ("Y", -25.0, 25.0)],
    "Spine": [("X", -10.0, 25.0), ("Z", -10.0, 10.0), ("Y", -15.0, 15.0)],
    "Spine1": [("X", -10.0, 20.0), ("Z", -10.0, 10.0), ("Y", -15.0, 15.0)],
    "Neck": [("X", -30.0, 40.0), ("Z", -25.0, 25.0), ("Y", -40.0, 40.0)],
    "Neck1": [("X", -15.0, 15.0)],
    "Head": [("X", -15.0, 15.0), ("Y", -20.0, 20.0)],
    "Shoulder": [("Z", -10.0, 25.0), ("Y", -15.0, 15.0)],
    "Arm": [("Z", -85.0, 60.0), ("Y", -80.0, 80.0), ("X", -60.0, 60.0)],
    "ForeArm": [("Y", -140.0, 0.0), ("X", -80.0, 80.0)],
    "Hand": [("Z", -60.0, 60.0), ("Y", -30.0, 30.0)],
}


def _rom_spec(joint: str) -> list[tuple[str, float, float]]:
    for key in ("UpLeg", "ToeBase", "ForeArm", "Shoulder", "Foot", "Hand", "Arm", "Leg"):
        if joint.endswith(key) and joint not in _ROM:
            spec = _ROM[key]
            if joint.startswith("Right") and key in (
                "UpLeg",
                "Foot",
                "Shoulder",
                "Arm",
                "ForeArm",
                "Hand",
            ):
                # mirror: rotations about y and z change sign on the right side
                spec = [(a, -hi, -lo) if a in "YZ" else (a, lo, hi) for a, lo, hi in spec]
            return spec
    return _ROM.get(joint, [])


def procedural_range_of_motion(
    n_frames: int, *, rate: float = 120.0, seed: int | np.random.Generator = 0
) -> Motion:
    """Each joint group flexed through its range in turn, the body otherwise at rest.

    The frames are split evenly over :data:`JOINT_GROUPS` (order shuffled by
    ``seed``); within a group's block every joint sweeps each of its axes from
    rest to its limits and back (a raised-cosine excursion per axis), joints of
    the group moving together, so every group moves while the others hold still
    (the ground truth of a near-rigid segmentation).

    Parameters
    ----------
    n_frames : int
    rate : float
    seed : int or numpy.random.Generator
        Shuffles the group order and jitters each excursion's amplitude (±15 %).

    Returns
    -------
    Motion
        On :func:`procedural_skeleton`; root fixed at ``(0, 0.93, 0)``.
        ``attrs["group_frames"]``: per group ``[start, stop)`` frame range.
    """
    if n_frames < 1:
        raise ValueError(f"procedural_range_of_motion: n_frames must be >= 1, got {n_frames}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    sk = procedural_skeleton()
    groups = list(JOINT_GROUPS)
    order = [groups[i] for i in rng.permutation(len(groups))]
    rot = quat_identity((n_frames, sk.n_joints))
    # arms hang down outside their own block
    for side, pre in ((1.0, "Left"), (-1.0, "Right")):
        rot[:, sk.index(f"{pre}Arm")] = _rz(np.full(n_frames, -side * np.radians(75.0)))
    bounds = np.linspace(0, n_frames, len(order) + 1).round().astype(int)
    group_frames = {}
    for g_name, start, stop in zip(order, bounds[:-1], bounds[1:]):
        group_frames[g_name] = [int(start), int(stop)]
        n = stop - start
        if n == 0:
            continue
        u = (np.arange(n) + 0.5) / n
        for joint in JOINT_GROUPS[g_name]:
            spec = _rom_spec(joint)
            if not spec:
                continue
            j = sk.index(joint)
            m = len(spec)
            euler = np.zeros((n, 3))
            for k, (axis, lo, hi) in enumerate(spec):
                w = np.clip(u * m - k, 0.0, 1.0)  # this axis' share of the block
                amp = rng.uniform(0.85, 1.0)
                # rest -> hi -> lo -> rest within its share
                e = np.where(w < 0.5, np.sin(2 * np.pi * w) * hi, -np.sin(2 * np.pi * w) * lo)
                e = np.where((w > 0) & (w < 1), e * amp, 0.0)
                euler[:, "ZYX".index(axis)] += np.radians(e)
            q = euler_to_quat(euler, "ZYX")
            rot[start:stop, j] = quat_multiply(rot[start:stop, j], q)
    root = np.tile([0.0, ROOT_HEIGHT, 0.0], (n_frames, 1))
    return Motion(
        skeleton=sk,
        root_position=root,
        rotations=rot,
        rate=rate,
        attrs={
            "source": "procedural_range_of_motion",
            "seed": seed if isinstance(seed, int) else None,
            "group_frames": group_frames,
            "source_unit": "m",
            "source_scale": 1.0,
        },
    )


# --------------------------------------------------------------------------- stages


@stage("simulate_walk", outputs=("motion",))
def simulate_walk(
    *,
    n_frames: int = 600,
    rate: float = 120.0,
    gait: Literal["walk", "run"] = "walk",
    speed: float | None = None,
    variation: float = 0.05,
    seed: int = 0,
    ctx: Context,
) -> dict:
    """Procedural walk or run with cycle-to-cycle variation (see :func:`procedural_walk`).

    Parameters
    ----------
    n_frames : int
    rate : float
    gait : {"walk", "run"}
    speed : float, optional
    variation : float
    seed : int
        Seeds ``ctx.rng``, the only source of randomness.
    ctx : Context

    Returns
    -------
    dict
        ``{"motion": Motion}``.
    """
    motion = procedural_walk(
        n_frames, rate=rate, gait=gait, speed=speed, seed=ctx.rng, variation=variation
    )
    motion.attrs["seed"] = int(seed)
    return {"motion": motion}


@stage("simulate_range_of_motion", outputs=("motion",))
def simulate_range_of_motion(
    *, n_frames: int = 1200, rate: float = 120.0, seed: int = 0, ctx: Context
) -> dict:
    """Joint groups flexed through their range in turn (see :func:`procedural_range_of_motion`).

    Parameters
    ----------
    n_frames : int
    rate : float
    seed : int
        Seeds ``ctx.rng``.
    ctx : Context

    Returns
    -------
    dict
        ``{"motion": Motion}``.
    """
    motion = procedural_range_of_motion(n_frames, rate=rate, seed=ctx.rng)
    motion.attrs["seed"] = int(seed)
    return {"motion": motion}
