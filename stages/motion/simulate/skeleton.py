"""The procedural humanoid skeleton the simulators drive.

:func:`procedural_skeleton` is a 31-joint humanoid with the joint names and
hierarchy of the CMU MotionBuilder-friendly BVH files (``cmu_01_01.bvh``:
Hips, LHipJoint, LeftUpLeg, ... LFingers, LThumb, RightShoulder, ...), y up,
x to the subject's left, z forward, metres, 1.75 m tall, standing with the root
at 0.93 m (:data:`ROOT_HEIGHT`) and the arms out (T-pose) at rest.  The leg
dimensions (:data:`THIGH`, :data:`SHANK`, :data:`ANKLE_HEIGHT`,
:data:`HIP_OFFSET`, :data:`BALL`) are the gait's as well.
"""

from __future__ import annotations

import numpy as np

from mocapflow.stages.motion.datatypes import Skeleton

__all__ = [
    "ANKLE_HEIGHT",
    "BALL",
    "HIP_OFFSET",
    "ROOT_HEIGHT",
    "SHANK",
    "THIGH",
    "procedural_skeleton",
]

#: Leg dimensions (metres): thigh and shank lengths, ankle height above the floor.
THIGH = 0.40
SHANK = 0.39
ANKLE_HEIGHT = 0.07
#: LeftUpLeg from Hips (via LHipJoint at 0).
HIP_OFFSET = np.array([0.09, -0.07, 0.0])
#: The ball of the foot (the toe-base joint) in the foot frame.
BALL = np.array([0.0, -0.05, 0.13])
#: Root height of the rest pose standing on the floor (0.93 m).
ROOT_HEIGHT = ANKLE_HEIGHT + SHANK + THIGH - HIP_OFFSET[1]

# name, parent, offset (left side; right side mirrors x)
_LEFT_LEG = [
    ("LHipJoint", "Hips", (0.0, 0.0, 0.0)),
    ("LeftUpLeg", "LHipJoint", tuple(HIP_OFFSET)),
    ("LeftLeg", "LeftUpLeg", (0.0, -THIGH, 0.0)),
    ("LeftFoot", "LeftLeg", (0.0, -SHANK, 0.0)),
    ("LeftToeBase", "LeftFoot", tuple(BALL)),
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
