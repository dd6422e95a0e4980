"""Body regions read from marker labels (the upright fit of sparse captures)."""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.skin.marker_regions import REGION_JOINTS, marker_region, region_vertices
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
