"""The up axis through the skin graph: a Z-up Vicon capture and its copy rotated to Y-up
give the same cleaned markers (up to the rotation), the same fitted body, and the same
upright rendering."""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.motion.axes import axis_vector
from mocapflow.stages.motion.ingest import ingest_c3d
from mocapflow.stages.skin.clean import clean
from mocapflow.stages.skin.deform import deform
from mocapflow.stages.skin.mesh_fit import fit_mesh, template_mesh
from mocapflow.stages.skin.render import _camera, offscreen_available, render
from mocapflow.stages.skin.rom import match_markers
from mocapflow.stages.skin.segment import segment

ezc3d = pytest.importorskip("ezc3d")
OK, WHY = offscreen_available()
PIG = "btkdata_PiG_Calibration-FlatFoot-Hole.c3d"
#: Z-up -> Y-up: (x, y, z) -> (x, z, -y), a proper rotation about +X.
R_ZY = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _rotated_copy(src, dst) -> None:
    """The C3D ``src`` with its points rotated Z-up -> Y-up and ``POINT:Y_SCREEN`` +Y."""
    c = ezc3d.c3d(str(src))
    p = c["data"]["points"]
    p[:3] = np.einsum("ij,jmf->imf", R_ZY, p[:3])
    c["data"]["points"] = p
    c["parameters"]["POINT"]["Y_SCREEN"]["value"] = ["+Y"]
    c["parameters"]["POINT"]["X_SCREEN"]["value"] = ["+X"]
    c.write(str(dst))


def _graph(path) -> dict:
    """ingest -> clean -> segment -> fit -> deform of one capture, every output kept."""
    c = Context()
    out = {"ingest": ingest_c3d(str(path), ctx=c)}
    out["clean"] = clean(out["ingest"]["markers"], ctx=c)
    m = out["clean"]["markers"]
    seg = segment(m, out["clean"]["surface"], ctx=c)["segmentation"]
    fit = fit_mesh(template_mesh(ctx=c)["mesh"], seg, marker_offset=0.007, ctx=c)["mesh"]
    matched = match_markers(m, seg, ctx=c)["markers"].take_frames(slice(0, 300, 60))
    out.update(seg=seg, fit=fit, matched=matched,
               mesh=deform(matched, seg, fit, ctx=c)["mesh"])
    return out


@pytest.fixture(scope="module")
def both(shared_data, tmp_path_factory):
    src = shared_data / "c3d" / PIG
    if not src.exists():
        pytest.skip(f"{PIG} not in the shared data")
    dst = tmp_path_factory.mktemp("up") / "pig_yup.c3d"
    _rotated_copy(src, dst)
    return _graph(src), _graph(dst)


def test_up_and_forward_are_read_from_the_file(both):
    z, y = both
    assert z["ingest"]["markers"].attrs["up"] == "+z"
    assert y["ingest"]["markers"].attrs["up"] == "+y"
    assert z["ingest"]["report"]["axes"]["up"] == "parameters"
    # facing from the ASI/PSI landmarks, rotated with the data
    fz, fy = (axis_vector(g["ingest"]["markers"].attrs["forward"]) for g in both)
    assert z["ingest"]["report"]["axes"]["forward"] == "landmarks"
    assert np.allclose(R_ZY @ fz, fy)
    assert z["seg"].attrs["up"] == "+z" and z["fit"].attrs["up"] == "+z"


def test_cleaned_markers_are_equal_up_to_the_rotation(both):
    z, y = (g["clean"]["markers"] for g in both)
    assert z.labels == y.labels and z.n_frames == y.n_frames
    assert np.array_equal(np.isnan(z.positions), np.isnan(y.positions))
    ok = np.isfinite(z.positions).all(-1)
    err = np.linalg.norm(z.positions[ok] @ R_ZY.T - y.positions[ok], axis=-1)
    assert err.max() < 1e-9  # metres (measured 1.7e-15): clean is rotation-equivariant
    assert np.array_equal(z.status, y.status)


def test_fitted_and_deformed_bodies_are_equal_up_to_the_rotation_and_upright(both):
    z, y = both
    err = np.linalg.norm(z["mesh"].vertices @ R_ZY.T - y["mesh"].vertices, axis=-1)
    assert err.max() < 1e-6  # metres (measured 7e-14): the template is rotated in first
    for g in both:
        v = g["fit"].vertices
        up = axis_vector(g["fit"].attrs["up"])
        height = np.ptp(v @ up)
        assert 1.55 < height < 1.9, height  # the body stands along the capture's up axis
        # its head is at the top: the head markers are near the fitted mesh's top
        m = g["clean"]["markers"]
        head = m.positions[0, [m.labels.index(n) for n in ("LFHD", "RFHD")]] @ up
        assert np.all((v @ up).max() - head < 0.1)


def test_projected_bounding_box_is_upright_in_the_camera(both):
    """The camera's image vertical is the capture's up axis (the bug: the Z-up file
    lay flat, its vertical along the image's depth or width)."""
    for g in both:
        mesh, markers = g["mesh"], g["matched"]
        panel = [{"vertices": mesh.vertices, "faces": mesh.faces}]
        focal, _, d, upv = _camera(panel, view="front", up=markers.attrs["up"],
                                   forward=markers.attrs["forward"], follow=True,
                                   width=160, height=120)
        right = np.cross(-d, upv)
        rel = mesh.vertices[0] - focal[0, 0]  # panel 0, frame 0
        h, w = np.ptp(rel @ upv), np.ptp(rel @ right)
        assert np.allclose(upv, axis_vector(markers.attrs["up"]))
        # T-pose: the arm span is about the height; lying flat the image height would
        # be the body's depth (~0.4 m)
        assert h > 1.55 and 0.7 < w / h < 1.4, (h, w)
        # front view: the camera is on the side the body faces
        assert d @ axis_vector(markers.attrs["forward"]) > 0.9


@pytest.mark.skipif(not OK, reason=f"no off-screen OpenGL context here: {WHY}")
def test_renders_are_the_same_image(both):
    frames = []
    for g in both:
        out = render(g["mesh"], g["matched"], width=160, height=120, stride=2, ctx=Context())
        frames.append(out["video"].frames.astype(np.int16))
    a, b = frames
    fg = (a < 250).any(-1)
    assert fg.mean() > 0.05  # something was drawn
    assert np.abs(a - b).mean() < 0.5  # of 255: the same picture
    rows = np.flatnonzero(fg[0].any(1))
    assert rows.size > 0.5 * a.shape[1]  # the body spans the image height
