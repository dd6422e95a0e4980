"""Body regions read from marker labels (the upright fit of sparse captures)."""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.skin.marker_regions import (
    REGION_JOINTS,
    body_facing,
    joint_landmark,
    label_side,
    marker_face,
    marker_region,
    region_vertices,
)
from mocapflow.stages.skin.mesh_fit import template_mesh


@pytest.mark.parametrize(
    ("label", "region"),
    [
        # Plug-in Gait (btkdata PiG, ezc3d read_NOTworking2)
        ("LASI", "pelvis"), ("RPSI", "pelvis"), ("ASI", "pelvis"), ("C7", "upper_trunk"),
        ("T10", "trunk"), ("CLAV", "upper_trunk"), ("STRN", "trunk"), ("RBAK", "trunk"),
        ("LFHD", "head"), ("RBHD", "head"), ("LSHO", "shoulder"), ("LKNE", None),
        ("LUPA1", None), ("RWRA", None),
        # Qualisys sports marker set
        ("L_IAS", "pelvis"), ("R_IPS", "pelvis"), ("CV7", "upper_trunk"), ("TV8", "trunk"),
        ("SXS", "trunk"), ("SNJ", "upper_trunk"), ("R_SCAP", "trunk"), ("L_HDF", "head"),
        ("L_SAJ", "shoulder"), ("L_FME", None), ("R_WAND1", None),
        # ISB-style names with a subject prefix (pyomeca), BTS, kineticstoolkit
        ("Daphnee:ASISr", "pelvis"), ("Daphnee:PSISl", "pelvis"), ("Daphnee:STERl", "trunk"),
        ("Daphnee:XIPH", "trunk"), ("Daphnee:CLAV_AC", "upper_trunk"),
        ("Daphnee:ACRO_tip", "shoulder"),
        ("Daphnee:LASTC", None), ("Daphnee:EPICl", None), ("r asis", "pelvis"),
        ("sacrum", "pelvis"), ("l should", "shoulder"), ("c7", "upper_trunk"), ("r knee 1", None),
        ("Head2", "head"), ("BodyL:TempleL", "head"), ("AcromionR", "shoulder"),
        ("ScapulaL3", "trunk"), ("Sternum", "trunk"), ("ArmL1", None),
        # thigh and shank clusters are not vertebrae or the sacrum
        ("RT1", None), ("LT4", None), ("RS1", None), ("LeftASIS", "pelvis"),
        # the upper trunk: vertebrae T1-T2 and the jugular notch, not T8 or the xiphoid
        ("T1", "upper_trunk"), ("Daphnee:T1", "upper_trunk"), ("Daphnee:T10", "trunk"),
        ("IJ", "upper_trunk"), ("LCLAV", "upper_trunk"), ("PX", "trunk"),
    ],
)  # fmt: skip
def test_marker_region(label, region):
    assert marker_region(label) == region


def test_region_vertices_of_the_template():
    """Each region holds the template's vertices of its joints, at its height: the pelvis
    about the hips, the head on top."""
    mesh = template_mesh(n_vertices=2000, ctx=Context())["mesh"]
    y = mesh.vertices[:, 1]
    masks = region_vertices(mesh.attrs["joint_names"], np.asarray(mesh.attrs["vertex_part"]), y)
    assert set(masks) == set(REGION_JOINTS)
    height = {r: float(np.median(y[m])) for r, m in masks.items()}
    assert height["pelvis"] < height["trunk"] < height["shoulder"] < height["head"]
    # the upper trunk: the chest's upper half, from about the armpits to the neck
    assert height["trunk"] < height["upper_trunk"] and masks["upper_trunk"].sum() > 50
    assert y[masks["upper_trunk"]].min() >= np.median(y[masks["trunk"] & ~masks["pelvis"]])
    assert not (masks["upper_trunk"] & ~masks["trunk"]).any()
    # without heights the upper trunk is left out (it is the upper half of its joints)
    bare = region_vertices(mesh.attrs["joint_names"], np.asarray(mesh.attrs["vertex_part"]))
    assert set(bare) == set(REGION_JOINTS) - {"upper_trunk"}
    assert abs(height["pelvis"]) < 0.1  # the hips at the root
    assert not masks["head"][y < 0.4].any()


@pytest.mark.parametrize(
    ("label", "face"),
    [("LASI", "front"), ("L_IAS", "front"), ("Daphnee:ASISr", "front"), ("STRN", "front"),
     ("SXS", "front"), ("CLAV", "front"), ("LPSI", "back"), ("R_IPS", "back"),
     ("sacrum", "back"), ("C7", "back"), ("TV8", "back"), ("RBAK", "back"),
     ("Daphnee:SCAP_IA", "back"), ("LFHD", None), ("LSHO", None), ("LKNE", None)],
)  # fmt: skip
def test_marker_face(label, face):
    assert marker_face(label) == face


def test_body_facing_from_front_and_back_markers():
    """The pelvis' ASIS ahead of its PSIS and the sternum ahead of C7 give the facing, off
    the up axis; a set with no such pair gives none."""
    up = np.array([0.0, 0.0, 1.0])
    labels = ["LASI", "RASI", "LPSI", "RPSI", "STRN", "C7", "LKNE"]
    ref = np.array([[0.1, 0.12, 1.0], [0.1, -0.12, 1.0], [-0.08, 0.05, 1.05],
                    [-0.08, -0.05, 1.05], [0.12, 0.0, 1.35], [-0.1, 0.0, 1.5],
                    [0.0, 0.1, 0.5]])  # fmt: skip
    np.testing.assert_allclose(body_facing(labels, ref, up), [1.0, 0.0, 0.0], atol=1e-12)
    turned = ref @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).T
    np.testing.assert_allclose(body_facing(labels, turned, up), [0.0, 1.0, 0.0], atol=1e-12)
    assert body_facing(["LASI", "LKNE"], ref[[0, 6]], up) is None


@pytest.mark.parametrize(
    ("label", "joint"),
    [("LELB", "elbow"), ("L_HLE", "elbow"), ("R_HME", "elbow"), ("Daphnee:EPICl", "elbow"),
     ("LateralEpicondyleL", "elbow"), ("BodyL:LateralEpicondyleL", "elbow"),
     ("OlecraneR", "elbow"), ("LWRA", "wrist"), ("RWRB", "wrist"), ("R_RSP", "wrist"),
     ("L_UHE", "wrist"), ("Daphnee:STYLu", "wrist"), ("Daphnee:WRIST", "wrist"),
     ("RadialStyloidR", "wrist"), ("LKNE", "knee"), ("L_FLE", "knee"), ("R_FME", "knee"),
     ("RightKnee", "knee"), ("RANK", "ankle"), ("L_FAL", "ankle"), ("R_TAM", "ankle"),
     ("ankleL", "ankle"),
     # clusters, segments and other places are no joint
     ("LTHI", None), ("LTIB", None), ("RSK2", None), ("ArmL1", None), ("LSHO", None),
     ("LASI", None), ("LHEE", None), ("LTOE", None), ("L_FM1", None), ("LFIN", None),
     ("Daphnee:LARM_elb", None), ("BodyL:HandL", None)],
)  # fmt: skip
def test_joint_landmark(label, joint):
    assert joint_landmark(label) == joint


@pytest.mark.parametrize(
    ("label", "side"),
    [("LELB", "Left"), ("RWRA", "Right"), ("L_HLE", "Left"), ("R_FME", "Right"),
     ("LeftKnee", "Left"), ("RightAnkle", "Right"), ("LateralEpicondyleL", "Left"),
     ("RadialStyloidR", "Right"), ("BodyL:LateralEpicondyleL", "Left"), ("knee_R", "Right"),
     ("L.Ankle", "Left"),
     # a lateral (l), medial (m), radial (r) or ulnar (u) suffix is not a side, nor a
     # leading capital of a word
     ("Daphnee:EPICl", None), ("Daphnee:STYLr", None), ("Daphnee:EPICm", None),
     ("LateralEpicondyle", None), ("Lelbow", None)],
)  # fmt: skip
def test_label_side(label, side):
    assert label_side(label) == side
