"""Up axis and facing detection (stages/motion/axes.py) on the real C3D files."""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.motion.axes import (
    AxisError,
    axis_vector,
    detect_forward,
    detect_up,
    frame_basis,
    parse_axis,
)
from mocapflow.stages.motion.formats.c3d import read_c3d, write_c3d
from mocapflow.stages.motion.ingest import IngestError, ingest_bvh, ingest_c3d

#: file -> (up, what decided it); checked by eye against the labels (head above feet)
EXPECTED = {
    "btkdata_PiG_Calibration-FlatFoot-Hole.c3d": ("+z", "parameters"),
    "btkdata_c3dorg_Eb015pr.c3d": ("+z", "parameters"),
    # the file says Y_SCREEN -Z, but its floor is at z = 0 below the body
    "ezc3d-testFiles_Qualisys.c3d": ("+z", "parameters+floor"),
    "pyomeca_markers_analogs.c3d": ("+z", "parameters"),
    # no X_SCREEN / Y_SCREEN: from the data (seated athlete, floor at z = 0)
    "ktk_kinematics_basket_sprint.c3d": ("+z", "data"),
}
R_ZY = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def test_parse_axis_and_vectors():
    assert parse_axis("Z") == "+z" and parse_axis(" -y") == "-y" and parse_axis("+X") == "+x"
    assert np.array_equal(axis_vector("-y"), [0, -1, 0])
    for bad in ("up", "", "xy", 3, None, "++z"):
        with pytest.raises(AxisError, match="expected x, y or z"):
            parse_axis(bad)
    R = frame_basis("+z", "-y")
    assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(R @ [0, 1, 0], [0, 0, 1]) and np.allclose(R @ [0, 0, 1], [0, -1, 0])
    assert np.allclose(frame_basis("+y", "+z"), np.eye(3))
    with pytest.raises(AxisError, match="along the up axis"):
        frame_basis("+z", "-z")


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_up_axis_of_the_real_files(shared_data, name):
    out = ingest_c3d(str(shared_data / "c3d" / name), ctx=(c := Context()))
    up, source = EXPECTED[name]
    m = out["markers"]
    assert (m.attrs["up"], out["report"]["axes"]["up"]) == (up, source)
    assert m.attrs["forward"][1] != up[1]
    assert any("Y_SCREEN says -Z" in w for w in c.warnings) == (source == "parameters+floor")
    # the data alone, rotated to Y-up, finds +y where the body is tall enough to say
    if name != "pyomeca_markers_analogs.c3d":  # upper body + a box: no floor, no long axis
        both = np.concatenate([m.positions, m.fragments], axis=1) @ R_ZY.T
        assert detect_up(both)[0] == "+y"



def test_two_subjects_apart_are_not_one_tall_body(shared_data):
    """Two subjects 3 m apart, named by label prefixes (kineticstoolkit's two-player
    tennis serve, Z up, was read +y: their spread along y beat a body's height); the
    largest subject's markers decide, as one subject alone does."""
    from mocapflow.stages.motion.ingest import markers_axes  # noqa: PLC0415

    m = read_c3d(shared_data / "c3d" / "ezc3d-testFiles_Qualisys.c3d")
    attrs = {k: v for k, v in m.attrs.items() if k != "c3d_parameters"}  # no Y_SCREEN
    P = np.concatenate([m.positions, m.positions + [0.0, 3.0, 0.0]], axis=1)
    two = m.replace(positions=P, labels=[f"A:{lb}" for lb in m.labels]
                    + [f"B:{lb}" for lb in m.labels],
                    fragments=np.zeros((m.n_frames, 0, 3)), fragment_labels=[], attrs=attrs,
                    residuals=None)
    alone = m.replace(fragments=np.zeros((m.n_frames, 0, 3)), fragment_labels=[],
                      attrs=attrs)
    got, ev = markers_axes(two)
    assert got.attrs["up"] == markers_axes(alone)[0].attrs["up"] == "+z"
    assert ev["up"]["subject"] == "A"
    assert detect_up(P)[0] != "+z"  # all markers at once: the spread wins


def test_facing_from_landmarks_travel_and_params(shared_data):
    m = read_c3d(shared_data / "c3d" / "btkdata_PiG_Calibration-FlatFoot-Hole.c3d")
    fwd, ev = detect_forward(m.positions, m.labels, up="+z")
    assert (fwd, ev["source"]) == ("-y", "landmarks")  # ASI in front of PSI along -y
    # a walk: the direction of travel (Eb015pr walks along +y)
    w = read_c3d(shared_data / "c3d" / "btkdata_c3dorg_Eb015pr.c3d")
    assert detect_forward(w.positions, w.labels, up="+z") == ("+y", {"source": "travel"})
    assert detect_forward(w.positions, w.labels, up="+z", forward="-x")[0] == "-x"
    with pytest.raises(AxisError, match="along the up axis"):
        detect_forward(w.positions, w.labels, up="+z", forward="z")


def test_given_axes_win_and_bad_ones_are_one_line(shared_data):
    path = str(shared_data / "c3d" / "btkdata_c3dorg_Eb015pr.c3d")
    m = ingest_c3d(path, up="-x", forward="+y", ctx=Context())["markers"]
    got = (m.attrs["up"], m.attrs["forward"], m.attrs["axes_source"]["up"])
    assert got == ("-x", "+y", "param")
    with pytest.raises(IngestError, match=r"Eb015pr.c3d: up: expected x, y or z"):
        ingest_c3d(path, up="vertical", ctx=Context())
    bvh = str(shared_data / "bvh" / "cmu_131_02.bvh")
    mo = ingest_bvh(bvh, ctx=Context())["motion"]
    assert (mo.attrs["up"], mo.attrs["forward"]) == ("+y", "+z")
    assert ingest_bvh(bvh, up="z", forward="-y", ctx=Context())["motion"].attrs["up"] == "+z"
    with pytest.raises(IngestError, match="along the up axis"):
        ingest_bvh(bvh, up="y", forward="-y", ctx=Context())


def test_written_c3d_says_its_up_axis(tmp_path, shared_data):
    """A capture without X_SCREEN / Y_SCREEN (e.g. simulated, Y-up) gets them on export,
    so the file reads back with its up axis; a source's own values are kept."""
    ktk = read_c3d(shared_data / "c3d" / "ktk_kinematics_basket_sprint.c3d")
    m = ktk.replace(attrs={**ktk.attrs, "up": "+y"})
    p = write_c3d(m, tmp_path / "a.c3d", unit="m")
    back = ingest_c3d(str(p), ctx=Context())
    assert back["report"]["axes"]["up"] == "parameters" and back["markers"].attrs["up"] == "+y"
    q = read_c3d(shared_data / "c3d" / "ezc3d-testFiles_Qualisys.c3d")
    p = write_c3d(q.replace(attrs={**q.attrs, "up": "+z"}), tmp_path / "q.c3d")
    tree = read_c3d(p).attrs["c3d_parameters"]["POINT"]["parameters"]
    assert tree["Y_SCREEN"]["value"] == ["-Z"]  # the source's parameter, untouched
