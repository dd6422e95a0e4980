"""Self-describing entries at the engine level: coords, consolidated metadata, open_entry."""

import os
import sys
import warnings

import numpy as np
import pytest

from mocapflow.pipeline.codecs import (
    Encoded,
    canonical_json,
    component_coords,
    decode,
    digest_encoded,
    encode,
    frame_coords,
    label_coord,
)
from mocapflow.pipeline.entry_xarray import EntryAmbiguousError, open_entry
from mocapflow.pipeline.store import EntryNotFoundError
from mocapflow.pipeline.store_zarr import normalise

xr = pytest.importorskip("xarray")

KEY = "a" * 32


def _output(n_frames=5, first=10, rate=50.0):
    data = np.arange(n_frames * 2 * 3, dtype=float).reshape(n_frames, 2, 3)
    coords = {**frame_coords(n_frames, rate, first), "point": label_coord(["p", "q"], "point"),
              **component_coords("xyz")}
    return Encoded("ndarray", {"data": (data, ("frame", "point", "xyz"))}, {}, coords)


def _commit(store, stage="st", key=KEY, node="node", part="p=0", **outs):
    outs = outs or {"pos": _output(), "info": encode({"a": 1})}
    store.commit(stage, key, outs, {"node": node, "part": part})
    return store.entry_path(stage, key)


def test_frame_coords_numbers_and_seconds():
    c = frame_coords(4, 100.0, 704)
    np.testing.assert_array_equal(c["frame"][0], [704, 705, 706, 707])
    np.testing.assert_allclose(c["time"][0], [7.04, 7.05, 7.06, 7.07], rtol=0, atol=1e-12)
    assert c["frame"][1] == c["time"][1] == ("frame",)
    assert "time" not in frame_coords(3, None)


def test_open_zarr_labelled_and_silent(store):
    path = _commit(store)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = xr.open_zarr(path, group="pos")
        root = xr.open_zarr(path)
    assert set(ds.indexes) == {"frame", "point", "xyz"}
    assert "time" in ds.coords and ds["time"].dims == ("frame",)
    np.testing.assert_array_equal(ds["frame"].values, np.arange(10, 15))
    np.testing.assert_allclose(ds["time"].values, np.arange(10, 15) / 50.0, atol=1e-12)
    assert list(ds["point"].values) == ["p", "q"]
    np.testing.assert_array_equal(ds["data"].sel(point="q", xyz="z").values, [5, 11, 17, 23, 29])
    assert not root.data_vars


def test_coords_round_trip_and_decode_ignores_them(store):
    _commit(store)
    enc = store.load("st", KEY, "pos")
    assert sorted(enc.coords) == ["frame", "point", "time", "xyz"]
    np.testing.assert_array_equal(decode(enc), _output().arrays["data"][0])
    assert store.verify() == []


def test_digest_covers_coords_and_is_unchanged_without_them():
    a = normalise(_output(), "o")
    b = normalise(_output(), "o")
    b.coords["point"] = label_coord(["p", "r"], "point")
    assert digest_encoded(a) != digest_encoded(b)
    # no coords: the digest is the pre-coords formula (entries stored before keep theirs)
    import hashlib

    arr = np.arange(6.0)
    plain = Encoded("ndarray", {"data": (arr, ("dim_0",))})
    h = hashlib.blake2b(digest_size=32)
    h.update(canonical_json({"type": "ndarray", "attrs": {}}))
    h.update(canonical_json(["data", arr.dtype.str, [6], ["dim_0"]]))
    h.update(arr.view(np.uint8).data)
    assert digest_encoded(plain) == h.hexdigest()


def test_verify_catches_corrupted_and_missing_coord(store):
    import zarr

    path = _commit(store)
    a = zarr.open_array(os.path.join(path, "pos", "point"), mode="r+")
    a[...] = np.array(["p", "x"])
    problems = store.verify()
    assert len(problems) == 1 and "digest mismatch" in problems[0], problems
    chunk = os.path.join(path, "pos", "time", "c", "0")
    os.remove(chunk)
    assert any("pos/time/c/0" in p for p in store.verify())


def test_record_dims_convention():
    rec = {"seen": np.zeros((4, 2), bool), "w": np.ones(3), "_dims": {"seen": ["frame", "marker"]}}
    enc = encode(rec)
    assert enc.arrays["seen"][1] == ("frame", "marker")
    assert enc.arrays["w"][1] == ("w_dim_0",)
    back = decode(normalise(enc, "r"))
    assert back["_dims"] == {"seen": ["frame", "marker"]}
    with pytest.raises(ValueError, match="names 1 dims for 2 axes"):
        encode({"seen": np.zeros((4, 2)), "_dims": {"seen": ["frame"]}})


def test_normalise_rejects_bad_coords():
    enc = _output()
    enc.coords["data"] = (np.arange(5), ("frame",))
    with pytest.raises(ValueError, match="coord 'data' has the name of an array"):
        normalise(enc, "o")
    enc = _output()
    enc.coords["point"] = label_coord(["p", "q", "r"], "point")
    with pytest.raises(ValueError, match="coord 'point' has 3 along 'point', the arrays 2"):
        normalise(enc, "o")


def test_open_entry_tree(store, tmp_path):
    _commit(store)
    for where in (store, str(tmp_path / "store")):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            tree = open_entry(where, "node", "p=0")
        assert set(tree.children) == {"info", "pos"}
        assert tree.attrs["stage"] == "st" and tree.attrs["key"] == KEY
        assert tree["pos"]["data"].shape == (5, 2, 3)
        assert tree["info"].attrs["mocapflow"]["attrs"] == {"value": {"a": 1}}
    assert set(open_entry(store, "node").children) == {"info", "pos"}  # one part: no part=


def test_open_entry_failures(store, monkeypatch):
    _commit(store)
    _commit(store, key="b" * 32, part="p=1")
    with pytest.raises(EntryNotFoundError, match=r"no committed entry of node 'nope'.*node"):
        open_entry(store, "nope")
    with pytest.raises(EntryNotFoundError, match="part 'p=9'"):
        open_entry(store, "node", "p=9")
    with pytest.raises(EntryAmbiguousError, match="2 parts"):
        open_entry(store, "node")
    assert open_entry(store, "node", "p=1").attrs["key"] == "b" * 32
    with pytest.raises(TypeError, match="store: expected a path"):
        open_entry(3, "node")
    monkeypatch.setitem(sys.modules, "xarray", None)
    with pytest.raises(ImportError, match=r"pip install 'mocapflow\[xarray\]'"):
        open_entry(store, "node", "p=0")


def test_lazy_top_level_export():
    import mocapflow

    assert mocapflow.open_entry is open_entry
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        mocapflow.nope  # noqa: B018
