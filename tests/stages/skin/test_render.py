"""Off-screen rendering, video and mesh exporters."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.codecs import ExportFormatError, decode, encode, find_exporter
from mocapflow.stages.motion.datatypes import Mesh
from mocapflow.stages.motion.formats.meshcache import (
    MeshCacheError,
    read_pc2,
    write_obj,
    write_pc2,
)
from mocapflow.stages.motion.mesh_export import export_mesh, write_ply
from mocapflow.stages.skin.deform import deform
from mocapflow.stages.skin.mesh_fit import template_mesh
from mocapflow.stages.skin.render import (
    RenderError,
    Video,
    export_video,
    offscreen_available,
    render,
    render_error,
    render_frames,
    render_modes,
)
from mocapflow.stages.skin.segment import segment
from tests.stages.skin.conftest import limb_capture

OK, WHY = offscreen_available()
needs_gl = pytest.mark.skipif(not OK, reason=f"no off-screen OpenGL context here: {WHY}")


@pytest.fixture(scope="module")
def limb():
    d = limb_capture(n_frames=24, mesh=(24, 30))
    d["markers"] = d["markers"].replace(rate=24.0)
    d["seg"] = segment(d["markers"], d["surface"], ctx=Context())["segmentation"]
    d["deformed"] = deform(d["markers"], d["seg"], d["mesh"], ctx=Context())["mesh"]
    return d


def test_module_import_is_cheap():
    code = (
        "import sys, mocapflow.stages.skin.render; "
        "print([m for m in ('pyvista', 'vtk', 'imageio', 'matplotlib') if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_video_codec_round_trip_and_validation():
    v = Video(np.arange(2 * 4 * 6 * 3, dtype=np.uint8).reshape(2, 4, 6, 3), 12.5, {"k": 1})
    back = decode(encode(v))
    assert isinstance(back, Video) and np.array_equal(back.frames, v.frames)
    assert back.rate == 12.5 and back.attrs == {"k": 1}
    with pytest.raises(ValueError, match="uint8"):
        Video(np.zeros((2, 4, 6, 3)), 10.0)
    assert find_exporter("video") is export_video and find_exporter("mesh") is export_mesh


def test_ply_writer_round_trip(tmp_path, limb):
    pv = pytest.importorskip("pyvista")
    V, F = limb["mesh"].vertices, limb["mesh"].faces
    p = write_ply(V, F, tmp_path / "m.ply")
    back = pv.read(str(p))
    assert np.allclose(back.points, V, atol=1e-7)
    assert np.array_equal(back.faces.reshape(-1, 4)[:, 1:], F)


def test_mesh_exporter_writes_series(tmp_path, limb):
    pv = pytest.importorskip("pyvista")
    m = limb["deformed"]
    files = export_mesh(m, tmp_path, "skin")
    n = m.vertices.shape[0]
    # one animation (rest OBJ + PC2 cache, USD) and the VTP series; per-frame PLY is opt-in
    assert [f.name for f in files[:4]] == ["skin.obj", "skin.pc2", "skin.usdc", "skin.pvd"]
    assert len(files) == 4 + n and not list(tmp_path.glob("skin/*.ply"))
    cache, start = read_pc2(tmp_path / "skin.pc2")
    assert start == 0.0 and cache.shape == m.vertices.shape
    assert np.abs(cache - m.vertices).max() < 1e-6 * max(1.0, np.abs(m.vertices).max())
    rest = pv.read(str(tmp_path / "skin.obj"))  # an OBJ reader we did not write
    assert rest.n_points == m.vertices.shape[1]
    assert np.allclose(rest.points, m.vertices[0], atol=1e-6)
    assert np.array_equal(rest.faces.reshape(-1, 4)[:, 1:], m.faces)
    with_ply = export_mesh(m, tmp_path / "p", "skin", formats=("ply",))
    assert len(with_ply) == n and all(f.suffix == ".ply" for f in with_ply)
    with pytest.raises(ExportFormatError, match="unknown mesh format\\(s\\) \\['abc'\\]"):
        export_mesh(m, tmp_path / "q", "skin", formats=("abc",))
    series = pv.get_reader(str(tmp_path / "skin.pvd"))
    assert len(series.time_values) == n
    assert series.time_values[1] == pytest.approx(1 / m.rate)
    series.set_active_time_point(5)
    assert np.allclose(series.read()[0].points, m.vertices[5])
    assert np.array_equal(series.read()[0].point_data["vertex_part"], m.attrs["vertex_part"])
    static = export_mesh(limb["mesh"], tmp_path, "rest")
    assert sorted(p.suffix for p in static) == [".ply", ".vtp"]
    assert np.allclose(pv.read(str(tmp_path / "rest.vtp")).points, limb["mesh"].vertices)


def test_deformed_mesh_carries_its_part_labels(limb):
    m, seg = limb["deformed"], limb["seg"]
    part = np.asarray(m.attrs["vertex_part"])
    assert m.attrs["part_names"] == seg.part_names and part.shape == (m.vertices.shape[1],)
    # the limb bends at y = 0.3: each side away from the joint is one part, not the same
    y = limb["mesh"].vertices[:, 1]
    upper, lower = np.unique(part[y < 0.22]), np.unique(part[y > 0.38])
    assert len(upper) == 1 and len(lower) == 1 and upper[0] != lower[0]


@needs_gl
def test_render_writes_png_and_mp4(tmp_path, limb):
    imageio = pytest.importorskip("imageio.v2")
    out = render(limb["deformed"], limb["markers"], width=160, height=128, stride=4,
                 view="side", ctx=Context())  # fmt: skip
    v = out["video"]
    assert v.frames.shape == (6, 128, 160, 3) and v.rate == pytest.approx(6.0)
    img = v.frames[2].astype(int)
    white = (img > 245).all(-1)
    assert 0.5 < white.mean() < 0.99  # background plus a body
    blue = (img[..., 2] > img[..., 0] + 60) & (img[..., 2] > 120)
    assert blue.sum() > 20  # marker overlay (blue spheres)
    files = export_video(v, tmp_path, "skin")
    mp4 = tmp_path / "skin.mp4"
    assert files[0] == mp4 and mp4.stat().st_size > 1000
    assert len(files) == 1 + 6 and all(p.stat().st_size > 100 for p in files[1:])
    reader = imageio.get_reader(mp4)
    frames = [f for f in reader]
    reader.close()
    assert len(frames) == 6 and frames[0].shape == (128, 160, 3)
    assert np.abs(frames[2].astype(int) - v.frames[2]).mean() < 8  # lossy but the same picture
    assert np.array_equal(imageio.imread(files[3]), v.frames[2])  # PNG is lossless
    with pytest.raises(RenderError, match="frames"):
        render(limb["deformed"], limb["markers"].replace(positions=limb["markers"].positions[:3]),
               ctx=Context())  # fmt: skip


@needs_gl
def test_render_modes_and_error_map(limb):
    mk = limb["markers"]  # a C3D capture carries residuals: they follow the rendered frames
    mk = mk.replace(residuals=np.zeros(mk.positions.shape[:2]))
    out = render_modes(mk, limb["seg"], limb["mesh"], width=96, height=128,
                       stride=8, ctx=Context())  # fmt: skip
    assert out["video"].frames.shape == (3, 128, 4 * 96, 3)
    assert out["report"]["modes"] == ["rigid", "quadratic", "rigid_residual", "quadratic_residual"]
    panels = np.split(out["video"].frames[1].astype(int), 4, axis=1)
    assert all((p < 200).any() for p in panels)  # every panel shows something
    with pytest.raises(RenderError, match="unknown modes"):
        render_modes(limb["markers"], limb["seg"], limb["mesh"], modes=["cubic"], ctx=Context())
    with pytest.raises(RenderError, match="must not set 'mode'"):
        render_modes(limb["markers"], limb["seg"], limb["mesh"], deform_params={"mode": "rigid"},
                     ctx=Context())  # fmt: skip
    with pytest.raises(RenderError, match="bad deform_params"):
        render_modes(limb["markers"], limb["seg"], limb["mesh"], deform_params={"dampng": 0.1},
                     ctx=Context())  # fmt: skip
    truth = Mesh(limb["truth"], limb["mesh"].faces, rate=24.0)
    err = render_error(limb["deformed"], truth, width=96, height=96, stride=12, clim_mm=2.0,
                       ctx=Context())  # fmt: skip
    direct = np.linalg.norm(limb["deformed"].vertices - limb["truth"], axis=-1) * 1000
    assert err["report"]["mean_mm"] == pytest.approx(direct.mean())
    assert err["report"]["p95_mm"] == pytest.approx(np.percentile(direct, 95))
    assert err["video"].frames.shape == (2, 96, 96, 3)
    # the error travels with the mesh as per-frame point data (all frames, vertex-to-vertex)
    em = err["mesh"]
    assert em.vertices.shape == limb["deformed"].vertices.shape and em.rate == 24.0
    np.testing.assert_allclose(em.point_data["error_mm"], direct, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(em.point_data["part_weights"],
                                  limb["deformed"].point_data["part_weights"])
    # colour varies across the body: the heat map is not a flat colour
    img = err["video"].frames[1].reshape(-1, 3).astype(int)
    body = img[(img < 240).any(1)]
    assert len(np.unique(body // 16, axis=0)) > 5


def test_pc2_reader_refuses_what_is_not_a_full_cache(tmp_path):
    v = np.arange(2 * 4 * 3, dtype=float).reshape(2, 4, 3)
    p = write_pc2(v, tmp_path / "a.pc2", start_frame=3.0)
    back, start = read_pc2(p)
    assert start == 3.0 and np.array_equal(back, v)
    assert p.stat().st_size == 32 + 2 * 4 * 12  # header + float32 xyz per point per sample
    (tmp_path / "short.pc2").write_bytes(p.read_bytes()[:-1])
    with pytest.raises(MeshCacheError, match=r"short\.pc2: header declares 2 samples of 4"):
        read_pc2(tmp_path / "short.pc2")
    (tmp_path / "x.pc2").write_bytes(b"POINTCACHE1\0" + bytes(20))
    with pytest.raises(MeshCacheError, match="not a PC2 file"):
        read_pc2(tmp_path / "x.pc2")


def _silhouette(img: np.ndarray) -> tuple[float, float]:
    """Height and width of the non-white pixels' bounding box, as fractions of the image."""
    body = (img.astype(int) < 235).any(-1)
    rows, cols = np.flatnonzero(body.any(1)), np.flatnonzero(body.any(0))
    if not len(rows):
        return 0.0, 0.0
    return (rows[-1] - rows[0] + 1) / img.shape[0], (cols[-1] - cols[0] + 1) / img.shape[1]


@needs_gl
def test_each_panel_frames_its_own_body():
    """A standing body fills most of the picture's height, in every panel, whatever its
    size and place (the demo's 640x480 render showed it in about a third)."""
    body = template_mesh(n_vertices=800, ctx=Context())["mesh"]
    walk = body.vertices[None] + np.array([0.0, 0.0, 1.0]) * np.linspace(0, 0.4, 3)[:, None, None]
    small = 0.5 * walk + np.array([3.0, 1.0, 0.0])  # a child-sized body, 3 m to the side
    frames = render_frames([{"vertices": walk, "faces": body.faces},
                            {"vertices": small, "faces": body.faces}],
                           width=160, height=120)  # fmt: skip
    for img in (frames[0], frames[-1]):
        for panel in np.split(img, 2, axis=1):
            h, w = _silhouette(panel)
            assert 0.6 <= h < 1.0 and w < 1.0  # most of the height, never cut off
    # a title and a colour bar get room: the body stays clear of the top and bottom rows
    scalars = np.repeat(body.vertices[None, :, 1], 3, axis=0)
    (img, *_) = render_frames([{"vertices": walk, "faces": body.faces, "title": "T",
                                "scalars": scalars, "clim": (-1.0, 1.0)}],
                              width=160, height=120)  # fmt: skip
    h, _ = _silhouette(img[12:-16])
    assert h >= 0.6


@needs_gl
def test_render_colours_by_distance_to_the_true_body(tmp_path, limb):
    """``render(truth=PC2)``: the heat map of each vertex's distance to the true body."""
    mesh = limb["deformed"]
    shifted = mesh.vertices + np.array([0.005, 0.0, 0.0])  # the truth 5 mm to the side
    write_pc2(shifted, tmp_path / "truth.pc2")
    write_obj(shifted[0], mesh.faces, tmp_path / "truth.obj")
    out = render(mesh, limb["markers"], width=96, height=96, stride=12,
                 truth=str(tmp_path / "truth.pc2"), clim_mm=10.0, ctx=Context())  # fmt: skip
    v = out["video"]
    assert v.attrs["kind"] == "error" and v.attrs["mean_mm"] == pytest.approx(5.0, abs=0.01)
    plain = render(mesh, limb["markers"], width=96, height=96, stride=12, ctx=Context())
    assert "mean_mm" not in plain["video"].attrs
    assert np.abs(v.frames.astype(int) - plain["video"].frames).max() > 60  # recoloured
    write_pc2(shifted[:5], tmp_path / "short.pc2")
    write_obj(shifted[0], mesh.faces, tmp_path / "short.obj")
    with pytest.raises(RenderError, match="5 frames but the mesh has 24"):
        render(mesh, limb["markers"], truth=str(tmp_path / "short.pc2"), ctx=Context())
    write_pc2(shifted, tmp_path / "alone.pc2")
    with pytest.raises(RenderError, match="alone"):
        render(mesh, limb["markers"], truth=str(tmp_path / "alone.pc2"), ctx=Context())
