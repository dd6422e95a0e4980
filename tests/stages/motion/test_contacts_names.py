"""Feet found by name across rigs (the variation graph's IK clean-up and cycle cuts)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from mocapflow.stages.motion.contacts import foot_joint


@pytest.mark.parametrize(
    ("names", "left", "right"),
    [
        (["Hips", "LeftUpLeg", "LeftFoot", "LeftToeBase", "RightFoot"], 2, 4),  # CMU BVH
        (["root", "lfemur", "lfoot", "ltoes", "rfoot"], 2, 4),  # CMU ASF
        (["Hips", "UpperLeg_L", "LowerLeg_L", "Foot_L", "Toes_L", "Foot_R"], 3, 5),  # Bandai
        (["mixamorig:Hips", "mixamorig:LeftFoot", "mixamorig:RightFoot"], 1, 2),  # Mixamo
        (["pelvis", "thigh.L", "foot.L", "foot.R"], 2, 3),  # Blender (Rigify-like)
        (["l_ankle", "r_ankle"], 0, 1),
        (["Foot Left", "Foot Right"], 0, 1),
        (["Bip01 Pelvis", "Bip01 L Thigh", "Bip01 L Foot", "Bip01 R Foot"], 2, 3),  # 3ds Max
        (["Character1_Hips", "Character1_LeftFoot", "Character1_RightFoot"], 1, 2),  # HumanIK
        (["LeftFootEnd", "LeftToe", "Root", "LowerLeg_L"], -1, -1),  # no foot
    ],
)
def test_foot_joint_names(names, left, right):
    sk = SimpleNamespace(names=names)
    assert (foot_joint(sk, "left"), foot_joint(sk, "right")) == (left, right)
