"""Body regions read from marker labels (the upright fit of sparse captures)."""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.skin.marker_regions import (
    REGION_JOINTS,
    body_facing,
    marker_face,
    marker_region,
    region_vertices,
)
from mocapflow.stages.skin.mesh_fit import template_mesh


@pytest.mark.parametrize(
    ("label", "region"),
    [
        # Plug-in Gait (btkdata PiG, ezc3d read_NOTworking2)
        ("LASI", "pelvis"), ("RPSI", "pelvis"), ("ASI", "pelvis"), ("C7", "trunk"),
        ("T10", "trunk"), ("CLAV", "trunk"), ("STRN", "trunk"), ("RBAK", "trunk"),
        ("LFHD", "head"), ("RBHD", "head"), ("LSHO", "shoulder"), ("LKNE", None),
        ("LUPA1", None), ("RWRA", None),
        # Qualisys sports marker set
        ("L_IAS", "pelvis"), ("R_IPS", "pelvis"), ("CV7", "trunk"), ("TV8", "trunk"),
        ("SXS", "trunk"), ("SNJ", "trunk"), ("R_SCAP", "trunk"), ("L_HDF", "head"),
        ("L_SAJ", "shoulder"), ("L_FME", None), ("R_WAND1", None),
        # ISB-style names with a subject prefix (pyomeca), BTS, kineticstoolkit
        ("Daphnee:ASISr", "pelvis"), ("Daphnee:PSISl", "pelvis"), ("Daphnee:STERl", "trunk"),
        ("Daphnee:XIPH", "trunk"), ("Daphnee:CLAV_AC", "trunk"), ("Daphnee:ACRO_tip", "shoulder"),
        ("Daphnee:LASTC", None), ("Daphnee:EPICl", None), ("r asis", "pelvis"),
        ("sacrum", "pelvis"), ("l should", "shoulder"), ("c7", "trunk"), ("r knee 1", None),
        ("Head2", "head"), ("BodyL:TempleL", "head"), ("AcromionR", "shoulder"),
        ("ScapulaL3", "trunk"), ("Sternum", "trunk"), ("ArmL1", None),
        # thigh and shank clusters are not vertebrae or the sacrum
        ("RT1", None), ("LT4", None), ("RS1", None), ("LeftASIS", "pelvis"),
    ],
)  # fmt: skip
def test_marker_region(label, region):
    assert marker_region(label) == region


def test_region_vertices_of_the_template():
    """Each region holds the template's vertices of its joints, at its height: the pelvis
    about the hips, the head on top."""
    mesh = template_mesh(n_vertices=2000, ctx=Context())["mesh"]
    masks = region_vertices(mesh.attrs["joint_names"], np.asarray(mesh.attrs["vertex_part"]))
    assert set(masks) == set(REGION_JOINTS)
    y = mesh.vertices[:, 1]
    height = {r: float(np.median(y[m])) for r, m in masks.items()}
    assert height["pelvis"] < height["trunk"] < height["shoulder"] < height["head"]
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
