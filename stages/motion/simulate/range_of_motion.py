"""Range-of-motion trials: each joint group flexed through its range in turn.

:func:`procedural_range_of_motion` sweeps the joint groups of
:data:`JOINT_GROUPS` of :func:`~mocapflow.stages.motion.simulate.skeleton.procedural_skeleton`
one block of frames at a time, every other joint at rest: the ground truth of a
near-rigid segmentation.
"""

from __future__ import annotations

import numpy as np

from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.motion.rotations import (
    euler_to_quat,
    quat_from_axis_angle,
    quat_identity,
    quat_multiply,
)
from mocapflow.stages.motion.simulate.skeleton import ROOT_HEIGHT, procedural_skeleton

__all__ = ["JOINT_GROUPS", "procedural_range_of_motion"]

#: Joint groups flexed in turn by :func:`procedural_range_of_motion`.
JOINT_GROUPS: dict[str, list[str]] = {
    "left_leg": ["LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase"],
    "right_leg": ["RightUpLeg", "RightLeg", "RightFoot", "RightToeBase"],
    "spine": ["LowerBack", "Spine", "Spine1"],
    "head": ["Neck", "Neck1", "Head"],
    "left_arm": ["LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand"],
    "right_arm": ["RightShoulder", "RightArm", "RightForeArm", "RightHand"],
}


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
        rot[:, sk.index(f"{pre}Arm")] = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]),
                                                      np.full(n_frames, -side * np.radians(75.0)))
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
