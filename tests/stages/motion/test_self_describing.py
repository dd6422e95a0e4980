"""Markers / motion / mesh entries open in xarray with labelled coordinates and no warning."""

import warnings
from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline.codecs import decode, encode
from mocapflow.pipeline.entry_xarray import open_entry
from mocapflow.pipeline.store import EntryNotFoundError, Store
from mocapflow.stages.motion.datatypes import Mesh
from mocapflow.stages.motion.formats.bvh import read_bvh
from mocapflow.stages.motion.formats.c3d import read_c3d

xr = pytest.importorskip("xarray")

DATA = Path("/work/shared/data")
QUALISYS = DATA / "c3d" / "ezc3d-testFiles_Qualisys.c3d"
BVH = DATA / "bvh" / "cmu_131_01.bvh"
ANALOGS = DATA / "c3d" / "pyomeca_markers_analogs.c3d"
pytestmark = pytest.mark.skipif(not QUALISYS.exists(), reason="sample data not available")


KEY = "d" * 32


def _open(store, stage, output, value, key=KEY):
    store.commit(stage, key, {output: encode(value)}, {"node": stage, "part": None})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return xr.open_zarr(store.entry_path(stage, key), group=output)


@pytest.fixture(scope="module")
def qualisys():
    return read_c3d(QUALISYS)


def test_markers_frame_time_labels(tmp_path, qualisys):
    m = qualisys
    assert m.first_frame == 704  # the file's first frame (0-based numbering of its header)
    ds = _open(Store(tmp_path / "s"), "ingest_c3d", "markers", m)
    assert set(ds.indexes) >= {"frame", "marker", "fragment", "xyz"}
    np.testing.assert_array_equal(ds["frame"].values, 704 + np.arange(m.n_frames))
    np.testing.assert_allclose(ds["time"].values, (704 + np.arange(m.n_frames)) / m.rate,
                               rtol=0, atol=1e-12)
    assert ds["time"].dims == ("frame",) and "time" in ds["positions"].coords
    assert list(ds["marker"].values) == m.labels
    assert list(ds["xyz"].values) == ["x", "y", "z"]
    j = 3
    got = ds["positions"].sel(marker=m.labels[j], frame=710).values
    np.testing.assert_array_equal(got, m.positions[710 - 704, j])


def test_markers_analog_channels(tmp_path):
    m = read_c3d(ANALOGS)
    assert m.analogs is not None and m.analogs.shape[1] > 0
    ds = _open(Store(tmp_path / "s"), "ingest_c3d", "markers", m)
    labels = m.attrs["c3d_parameters"]["ANALOG"]["parameters"]["LABELS"]["value"]
    assert list(ds["channel"].values) == [s.strip() for s in labels]
    n = m.analog_subframes
    np.testing.assert_allclose(ds["analog_time"].values[: n + 1],
                               (m.first_frame * n + np.arange(n + 1)) / (m.rate * n), atol=1e-12)
    assert ds["analog_time"].values[n] == pytest.approx(ds["time"].values[1], abs=1e-12)


def test_motion_joints_frames(tmp_path):
    mo = read_bvh(BVH)
    ds = _open(Store(tmp_path / "s"), "ingest_bvh", "motion", mo)
    assert list(ds["joint"].values) == mo.skeleton.names
    assert list(ds["wxyz"].values) == ["w", "x", "y", "z"]
    np.testing.assert_array_equal(ds["frame"].values, np.arange(mo.n_frames))  # BVH: 0-based
    np.testing.assert_allclose(ds["time"].values, np.arange(mo.n_frames) / mo.rate, atol=1e-12)
    assert ds.sizes["end_site"] == len(mo.skeleton.end_parents)
    names = mo.skeleton.names
    assert list(ds["end_parent"].values) == [names[p] for p in mo.skeleton.end_parents]
    q = ds["rotations"].sel(joint=names[1], frame=3, wxyz="w").values
    assert q == mo.rotations[3, 1, 0]


def test_mesh_vertex_labels_and_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    verts = rng.normal(size=(6, 4, 3))
    mesh = Mesh(verts, [[0, 1, 2], [0, 2, 3]], rate=30.0, attrs={"vertex_labels": list("abcd")})
    store = Store(tmp_path / "s")
    ds = _open(store, "mesh_stage", "mesh", mesh)
    assert list(ds["vertex"].values) == list("abcd")
    np.testing.assert_allclose(ds["time"].values, np.arange(6) / 30.0, atol=1e-12)
    np.testing.assert_array_equal(ds["vertices"].sel(vertex="c").values, verts[:, 2])
    back = decode(store.load("mesh_stage", KEY, "mesh"))
    np.testing.assert_array_equal(back.vertices, verts)
    assert store.verify() == []


def test_open_entry_children_and_unknown_node(tmp_path, qualisys):
    store = Store(tmp_path / "s")
    store.commit("ingest_c3d", "c" * 32,
                 {"markers": encode(qualisys), "report": encode({"n": 1})},
                 {"node": "ingest", "part": "trial=q"})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tree = open_entry(tmp_path / "s", "ingest", "trial=q")
    assert set(tree.children) == {"markers", "report"}
    assert int(tree["markers"]["frame"][0]) == 704
    with pytest.raises(EntryNotFoundError, match="nodes with entries: ingest"):
        open_entry(store, "capture")
