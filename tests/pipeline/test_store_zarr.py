"""Zarr I/O of entries: bit-exact floats, layout, dimension names, chunking."""

from __future__ import annotations

import os
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest
import zarr

from mocapflow.pipeline import store_zarr
from mocapflow.pipeline.codecs import Encoded, encode
from mocapflow.pipeline.store import Store
from tests.pipeline.helpers import sample_outputs


def test_float64_bits_exact(tmp_path):
    st = Store(tmp_path)
    x = np.array([0.1, -0.0, 5e-324, np.inf, -np.inf, np.nan, 1.7976931348623157e308])
    nan_payload = np.frombuffer(np.uint64(0x7FF8_0000_0000_1234).tobytes(), dtype=np.float64)
    x = np.concatenate([x, nan_payload])
    st.commit("s", "k", {"x": encode(x)}, {})
    assert st.load("s", "k", "x").arrays["data"][0].tobytes() == x.tobytes()


def test_layout_dimension_names_and_chunks(tmp_path):
    st = Store(tmp_path / "s", chunk_frames=4)
    st.commit("clean", "k1", sample_outputs(10), {})
    entry = Path(st.entry_path("clean", "k1"))
    assert (entry / "_COMMIT.json").is_file() and (entry / "zarr.json").is_file()
    g = zarr.open_group(store=str(entry / "markers"), mode="r")
    assert g.metadata.zarr_format == 3
    assert g.attrs["mocapflow"]["type"] == "markers"
    arr = g["positions"]
    assert arr.metadata.dimension_names == ("frame", "marker", "xyz")
    assert arr.chunks == (4, 4, 3)  # chunked along frame only
    assert arr.nchunks == 3 and arr.nchunks_initialized == 3
    assert g["labels"].chunks == (4,)  # no frame axis: one chunk
    assert not (Path(st.root) / "staging").exists() or not os.listdir(Path(st.root) / "staging")


def test_xarray_opens_an_output(tmp_path):
    xr = pytest.importorskip("xarray")
    st = Store(tmp_path / "s", chunk_frames=4)
    outs = {"markers": Encoded("m", {"positions": sample_outputs()["markers"].arrays["positions"]})}
    st.commit("clean", "k1", outs, {})
    ds = xr.open_zarr(st.entry_path("clean", "k1") + "/markers", consolidated=False)
    assert ds["positions"].dims == ("frame", "marker", "xyz")
    np.testing.assert_array_equal(ds["positions"].values, outs["markers"].arrays["positions"][0])


def test_chunk_layout(monkeypatch):
    f = store_zarr._chunk_layout
    assert f((10, 4, 3), ("frame", "m", "xyz"), 8, 4) == ((4, 4, 3), 0)
    assert f((0, 4, 3), ("frame", "m", "xyz"), 8, 4) == ((1, 4, 3), 0)
    assert f((3, 10), ("joint", "frame"), 8, 4) == ((3, 4), 1)
    assert f((5, 6), ("a", "b"), 8, 4) == ((5, 6), None)
    assert f((), (), 8, 4) == ((), None)
    monkeypatch.setattr(store_zarr, "MAX_CHUNK_BYTES", 1000)
    assert f((100, 10), ("a", "b"), 8, 4) == ((12, 10), 0)  # big non-frame array: rows
    assert f((100, 10), ("frame", "b"), 8, 64) == ((12, 10), 0)  # frames capped by bytes


class _Discard:
    def put_many(self, items) -> None:
        pass


def test_zarr_notices_stay_quiet_when_threads_write_at_once():
    """Zarr's notices about what an entry holds on purpose (consolidated metadata, str
    dtypes) are ignored however the writes interleave: entries written from several
    threads run as coroutines on Zarr's one event-loop thread, and a
    ``warnings.catch_warnings`` block around each write let the consolidated-metadata
    notice through when another write's block ended first (8 threads x 30 writes: it
    failed 2 runs of 3)."""
    failures: list[str] = []

    def write(i: int) -> None:
        try:
            for k in range(50):
                enc = Encoded(type="x", arrays={
                    "a": (np.arange(200.0 + k + i).reshape(-1, 1), ("frame", "c")),
                    "s": (np.array(["ab", "cd"]), ("n",))})
                store_zarr.write_entry(_Discard(), {"o1": enc, "o2": enc}, {}, 64)
        except Exception as e:  # noqa: BLE001 (reported below)
            failures.append(repr(e)[:200])

    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        threads = [threading.Thread(target=write, args=(i,)) for i in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert not failures, failures
