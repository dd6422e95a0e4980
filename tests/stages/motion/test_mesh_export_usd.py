"""USD export of meshes (usd-core) and the vertex data of the VTP series and USD file."""

from __future__ import annotations

import builtins
import subprocess
import sys

import numpy as np
import pytest

from mocapflow.pipeline.codecs import ExportFormatError
from mocapflow.stages.motion.datatypes import Mesh
from mocapflow.stages.motion.formats import usd as usd_mod
from mocapflow.stages.motion.formats.meshcache import read_pc2
from mocapflow.stages.motion.formats.usd import (
    UsdError,
    UsdUnavailableError,
    read_usd,
    usd_available,
    write_usd,
)
from mocapflow.stages.motion.mesh_export import export_mesh, vertex_data
from tests.stages.skin.conftest import deform_limb, grid_cylinder

pxr = pytest.importorskip("pxr")
PARTS = ["upper", "lower"]


@pytest.fixture(scope="module")
def walk_mesh():
    """A bending, twisting limb: 48 vertices, 12 frames at 30 Hz, two labelled parts."""
    P, faces = grid_cylinder(8, 6)
    n = 12
    t = np.linspace(0, 1, n)
    V = deform_limb(P, np.deg2rad(60) * t, np.deg2rad(20) * np.sin(2 * np.pi * t), 0.2)
    V = V + np.array([1.5, 0.0, -2.0])  # off the origin: relative error on real magnitudes
    labels = (P[:, 1] > 0.3).astype(int)
    w = np.stack([1.0 - P[:, 1], P[:, 1]], axis=1)  # (V, 2) floats
    return Mesh(V, faces, rate=30.0, attrs={
        "vertex_part": labels.tolist(), "part_names": PARTS, "vertex_weight": w.tolist(),
        "marker_face": [0, 3, 5],  # per marker, not per vertex: not vertex data
        "source": "test"})


def rel_err(a, b):
    return np.abs(np.asarray(a, dtype=np.float64) - b).max() / np.abs(b).max()


def test_usd_alone_round_trips_points_faces_time_units_and_primvars(tmp_path, walk_mesh):
    m = walk_mesh
    files = export_mesh(m, tmp_path, "skin", formats=("usd",))
    assert [f.name for f in files] == ["skin.usdc"] and sorted(tmp_path.iterdir()) == files
    assert files[0].read_bytes()[:8] == b"PXR-USDC"  # the binary crate, not text
    back = read_usd(files[0])
    n, V = m.vertices.shape[:2]
    assert back.vertices.shape == (n, V, 3) and back.vertices.dtype == np.float32
    assert rel_err(back.vertices, m.vertices) < 1e-6  # float32 of every frame
    assert np.array_equal(back.faces, m.faces)
    assert np.array_equal(back.times, np.arange(n))
    assert back.time_codes_per_second == back.frames_per_second == 30.0
    assert (back.start_time_code, back.end_time_code) == (0.0, n - 1.0)
    assert back.meters_per_unit == 1.0 and back.up_axis == "Y"
    assert np.array_equal(back.primvars["vertex_part"], m.attrs["vertex_part"])
    assert back.names == {"vertex_part": PARTS}
    assert rel_err(back.primvars["vertex_weight"], np.asarray(m.attrs["vertex_weight"])) < 1e-6
    assert "marker_face" not in back.primvars and back.path == "/skin/mesh"


def test_usd_read_with_pxr_directly_samples_frames_and_interpolates(tmp_path, walk_mesh):
    from pxr import Usd, UsdGeom

    m = walk_mesh
    (p,) = export_mesh(m, tmp_path, "skin", formats=("usd",))
    stage = Usd.Stage.Open(str(p))
    assert stage.GetDefaultPrim().GetPath() == "/skin"
    mesh = UsdGeom.Mesh.Get(stage, "/skin/mesh")
    points, extent = mesh.GetPointsAttr(), mesh.GetExtentAttr()
    for i in (0, 5, 11):
        got = np.asarray(points.Get(Usd.TimeCode(i)))
        assert rel_err(got, m.vertices[i]) < 1e-6
        box = np.asarray(extent.Get(Usd.TimeCode(i)))
        assert np.allclose(box, [m.vertices[i].min(0), m.vertices[i].max(0)], atol=1e-6)
    # time code i is frame i: half-way between two samples USD interpolates linearly
    mid = np.asarray(points.Get(Usd.TimeCode(4.5)))
    assert rel_err(mid, (m.vertices[4] + m.vertices[5]) / 2) < 1e-6
    assert rel_err(np.asarray(points.Get()), m.vertices[0]) < 1e-6  # default: rest pose
    assert mesh.GetSubdivisionSchemeAttr().Get() == "none"
    assert np.array_equal(np.asarray(mesh.GetFaceVertexCountsAttr().Get()), [3] * len(m.faces))
    var = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("vertex_part")
    assert var.GetInterpolation() == "vertex"
    assert np.array_equal(np.asarray(var.Get()), m.attrs["vertex_part"])


def test_up_axis_comes_from_attrs(tmp_path, walk_mesh):
    m = walk_mesh
    z = Mesh(m.vertices, m.faces, rate=m.rate, attrs={**m.attrs, "up": "Z"})
    (p,) = export_mesh(z, tmp_path / "z", "skin", formats=("usd",))
    assert read_usd(p).up_axis == "Z"
    for up, axis in (("+y", "Y"), (2, "Z"), (1, "Y")):
        m2 = Mesh(m.vertices[0], m.faces, attrs={"up": up})
        (p,) = export_mesh(m2, tmp_path / "u", "rest", formats=("usd",))
        assert read_usd(p).up_axis == axis
    bad = Mesh(m.vertices, m.faces, rate=m.rate, attrs={"up": "sideways"})
    with pytest.raises(ExportFormatError, match=r"up='sideways'"):
        export_mesh(bad, tmp_path / "x", "skin", formats=("usd",))
    assert not (tmp_path / "x").exists()  # checked before anything is written


@pytest.mark.parametrize("up", ["-x", "+x", "-y", "-z"])
def test_other_up_axes_are_stood_up_by_the_root_transform(tmp_path, walk_mesh, up):
    """USD has only Y and Z up: a capture whose up is another axis keeps its points and
    gets a root rotation that puts its up on the stage's +Z."""
    from pxr import Usd, UsdGeom  # noqa: PLC0415

    from mocapflow.stages.motion.axes import axis_vector  # noqa: PLC0415

    m = Mesh(walk_mesh.vertices[0], walk_mesh.faces, attrs={"up": up})
    (p,) = export_mesh(m, tmp_path, "rest", formats=("usd",))
    back = read_usd(p)
    assert back.up_axis == "Z" and rel_err(back.vertices, m.vertices) < 1e-6
    stage = Usd.Stage.Open(str(p))
    root = stage.GetDefaultPrim()
    M = np.array(UsdGeom.Xformable(root).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
    R = M[:3, :3].T  # row-vector matrices
    assert np.allclose(R @ axis_vector(up), [0, 0, 1]) and np.isclose(np.linalg.det(R), 1)


def test_static_mesh_usd_is_time_independent(tmp_path, walk_mesh):
    rest = Mesh(walk_mesh.vertices[3], walk_mesh.faces, attrs=walk_mesh.attrs)
    assert [f.suffix for f in export_mesh(rest, tmp_path, "rest")] == [".vtp", ".ply"]
    (p,) = export_mesh(rest, tmp_path / "u", "rest", formats=("usd",))
    back = read_usd(p)
    assert back.vertices.shape == rest.vertices.shape and back.times.size == 0
    assert rel_err(back.vertices, rest.vertices) < 1e-6
    assert np.array_equal(back.primvars["vertex_part"], rest.attrs["vertex_part"])


def test_default_animated_formats_and_vtp_point_data(tmp_path, walk_mesh):
    pv = pytest.importorskip("pyvista")
    m = walk_mesh
    n = m.vertices.shape[0]
    files = export_mesh(m, tmp_path, "skin")
    assert [f.name for f in files[:4]] == ["skin.obj", "skin.pc2", "skin.usdc", "skin.pvd"]
    assert len(files) == 4 + n
    cache, _ = read_pc2(tmp_path / "skin.pc2")
    assert np.array_equal(read_usd(tmp_path / "skin.usdc").vertices, cache)  # same float32
    labels, w = np.asarray(m.attrs["vertex_part"]), np.asarray(m.attrs["vertex_weight"])
    series = pv.get_reader(str(tmp_path / "skin.pvd"))
    for i in (0, 7, n - 1):  # every frame's file carries the (constant) vertex data
        series.set_active_time_point(i)
        frame = series.read()[0]
        assert np.allclose(frame.points, m.vertices[i])
        assert np.array_equal(frame.point_data["vertex_part"], labels)
        assert np.allclose(frame.point_data["vertex_weight"], w, rtol=1e-6)
        assert "marker_face" not in frame.point_data
    static = pv.read(str(export_mesh(Mesh(m.vertices[0], m.faces, attrs=m.attrs),
                                     tmp_path / "s", "rest", formats=("vtp",))[0]))
    assert np.array_equal(static.point_data["vertex_part"], labels)


def test_vertex_data_picks_per_vertex_numeric_attrs(walk_mesh):
    data, names = vertex_data(walk_mesh)
    assert sorted(data) == ["vertex_part", "vertex_weight"]
    assert data["vertex_part"].dtype == np.int32 and data["vertex_weight"].shape == (48, 2)
    assert names == {"vertex_part": PARTS}
    sim = Mesh(walk_mesh.vertices[0], walk_mesh.faces, attrs={
        "vertex_part": walk_mesh.attrs["vertex_part"], "joint_names": ["hip", "knee"],
        "vertex_short": [1, 2], "vertex_ragged": [[1], [1, 2]] * 24, "vertex_name": "x"})
    data, names = vertex_data(sim)
    assert list(data) == ["vertex_part"] and names == {"vertex_part": ["hip", "knee"]}


def test_unknown_format_still_errors(tmp_path, walk_mesh):
    with pytest.raises(ExportFormatError, match=r"\['abc'\]; it writes vtp, ply, pc2, usd"):
        export_mesh(walk_mesh, tmp_path, "skin", formats=("usd", "abc"))
    assert not list(tmp_path.iterdir())


def test_without_usd_core_a_one_line_error_and_no_files(tmp_path, walk_mesh, monkeypatch):
    real_import = builtins.__import__

    def no_pxr(name, *args, **kwargs):
        if name == "pxr" or name.startswith("pxr."):
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_pxr)
    assert not usd_available()
    with pytest.raises(UsdUnavailableError, match=r"pip install usd-core"):
        write_usd(walk_mesh.vertices, walk_mesh.faces, tmp_path / "a.usdc", rate=30.0)
    for formats in (("usd",), None):  # asked for, and the animated default
        opts = {} if formats is None else {"formats": formats}
        with pytest.raises(ExportFormatError, match=r"usd-core") as e:
            export_mesh(walk_mesh, tmp_path / "out", "skin", **opts)
        assert "\n" not in str(e.value) and "mesh=vtp,pc2" in str(e.value)
    assert not (tmp_path / "out").exists()
    # without usd the exporter works as before
    assert export_mesh(walk_mesh, tmp_path / "out", "skin", formats=("pc2",))


def test_write_usd_refuses_bad_input(tmp_path, walk_mesh):
    V, F = walk_mesh.vertices, walk_mesh.faces
    with pytest.raises(UsdError, match="positive rate"):
        write_usd(V, F, tmp_path / "a.usdc")
    with pytest.raises(UsdError, match=r"primvar 'p'.*V = 48"):
        write_usd(V, F, tmp_path / "a.usdc", rate=30.0, primvars={"p": np.zeros(47)})
    with pytest.raises(UsdError, match=r"faces index vertices outside \[0, 48\)"):
        write_usd(V, F + 1, tmp_path / "a.usdc", rate=30.0)
    with pytest.raises(UsdError, match="suffix"):
        write_usd(V, F, tmp_path / "a.abc", rate=30.0)
    with pytest.raises(UsdError, match="up must be"):
        write_usd(V[0], F, tmp_path / "a.usda", up="w")
    assert not list(tmp_path.iterdir())
    (tmp_path / "junk.usdc").write_bytes(b"not usd at all")
    with pytest.raises(UsdError, match=r"junk\.usdc: not a USD file"):
        read_usd(tmp_path / "junk.usdc")
    empty = tmp_path / "empty.usda"
    empty.write_text("#usda 1.0\n")
    with pytest.raises(UsdError, match="no UsdGeom.Mesh"):
        read_usd(empty)


def test_rewrite_replaces_the_file(tmp_path, walk_mesh):
    p = tmp_path / "m.usdc"
    write_usd(walk_mesh.vertices, walk_mesh.faces, p, rate=30.0)
    write_usd(walk_mesh.vertices[:3], walk_mesh.faces, p, rate=10.0)
    back = read_usd(p)
    assert back.vertices.shape[0] == 3 and back.time_codes_per_second == 10.0


def test_importing_the_exporter_does_not_import_pxr():
    code = ("import sys, mocapflow.stages.motion.mesh_export; "
            "print([m for m in ('pxr', 'pyvista') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    assert usd_mod.__name__.endswith("formats.usd")


def demo_deformed_mesh(demo_run):
    """The demo's deformed body, read from its store (the demo exports OBJ + PC2 only)."""
    from mocapflow.pipeline import registry
    from mocapflow.pipeline.api import _decode
    from mocapflow.pipeline.show import find_node_entry
    from mocapflow.pipeline.store import Store

    registry.discover()
    store = Store(demo_run.out / "store")
    stage, key = find_node_entry(store, "deform")
    return _decode(store.load_outputs(stage, key)["mesh"])


@pytest.mark.slow
def test_demo_deformed_mesh_usd(demo_run, tmp_path):
    assert demo_run.proc.returncode == 0, demo_run.proc.stderr[-3000:]
    paths = export_mesh(demo_deformed_mesh(demo_run), tmp_path, "mesh", formats=("usd", "pc2"))
    (usdc,) = [p for p in paths if p.suffix == ".usdc"]
    back = read_usd(usdc)
    cache, _ = read_pc2(usdc.with_suffix(".pc2"))
    assert back.vertices.shape == cache.shape and back.vertices.shape[1] > 4_000  # 5,000 (quick)
    assert np.array_equal(back.vertices, cache)
    assert back.time_codes_per_second == back.frames_per_second > 0
    part = back.primvars["vertex_part"]
    assert part.shape == (cache.shape[1],) and 0 <= part.min()
    assert part.max() < len(back.names["vertex_part"])


def test_usd_passes_usd_cores_validators(tmp_path, walk_mesh):
    from pxr import Usd, UsdValidation

    (p,) = export_mesh(walk_mesh, tmp_path, "skin", formats=("usd",))
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    assert len(validators) >= 10  # usd-core's stage metadata, geometry, schema checks
    errors = UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(p)))
    assert [e.GetMessage() for e in errors] == []
    # and they fail a layer without the metersPerUnit and upAxis we write
    bare = tmp_path / "bare.usda"
    bare.write_text('#usda 1.0\n(\n    defaultPrim = "m"\n)\ndef Mesh "m"\n{\n}\n')
    assert UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(bare)))


def test_point_data_travels_per_frame_into_vtp_usd_and_the_store(tmp_path, walk_mesh):
    """``Mesh.point_data``: static ``(V, k)`` weights and per-frame ``(F, V)`` errors go
    into every VTP file (that frame's values) and into USD primvars (time-sampled)."""
    import pyvista as pv  # noqa: PLC0415

    from mocapflow.pipeline.codecs import decode, encode  # noqa: PLC0415

    F, V = walk_mesh.vertices.shape[:2]
    rng = np.random.default_rng(0)
    weights = rng.random((V, 3)).astype(np.float32)
    error = rng.random((F, V)).astype(np.float32) * 10
    m = Mesh(walk_mesh.vertices, walk_mesh.faces, rate=walk_mesh.rate, attrs=walk_mesh.attrs,
             point_data={"part_weights": weights, "error_mm": error})
    back = decode(encode(m))
    assert sorted(back.point_data) == ["error_mm", "part_weights"]
    assert np.array_equal(back.point_data["error_mm"], error)
    files = export_mesh(m, tmp_path, "skin", formats=("vtp", "usd"))
    for i in (0, F - 1):
        poly = pv.read(tmp_path / "skin" / f"skin_{i:05d}.vtp")
        np.testing.assert_array_equal(poly.point_data["error_mm"], error[i])
        np.testing.assert_array_equal(poly.point_data["part_weights"], weights)
    u = read_usd(next(f for f in files if f.suffix == ".usdc"))
    np.testing.assert_array_equal(u.primvars["error_mm"], error)
    np.testing.assert_array_equal(u.primvars["part_weights"], weights)
    with pytest.raises(ValueError, match=r"point_data 'bad': expected \(V,\)"):
        Mesh(walk_mesh.vertices, walk_mesh.faces, point_data={"bad": np.zeros(V + 1)})
    with pytest.raises(ValueError, match="identifier"):
        Mesh(walk_mesh.vertices, walk_mesh.faces, point_data={"a b": np.zeros(V)})
