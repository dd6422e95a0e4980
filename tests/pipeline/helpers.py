"""Plain helpers shared by the engine tests (fixtures live in ``conftest.py``)."""

from __future__ import annotations

import numpy as np

from mocapflow.pipeline import codecs
from mocapflow.pipeline.codecs import Encoded, encode


def by_node(result, status):
    """``node -> number of tasks with status`` in a run result."""
    out: dict[str, int] = {}
    for r in result.records:
        if r["status"] == status:
            out[r["node"]] = out.get(r["node"], 0) + 1
    return out


def total_of(store, result):
    """The ``total`` output of the toy graph's ``total`` node."""
    rec = next(r for r in result.records if r["node"] == "total")
    return codecs.decode(store.load(rec["stage"], rec["key"], "total"))


def sample_outputs(n_frames: int = 10) -> dict[str, Encoded]:
    """Outputs exercising every storable kind: NaNs, empty axes, big-endian, str, complex, ..."""
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(n_frames, 4, 3))
    pos[2, 1] = np.nan
    pos[5:, 3] = np.nan
    markers = Encoded(
        "markers",
        {
            "positions": (pos, ("frame", "marker", "xyz")),
            "residuals": (rng.random((n_frames, 4)).astype(np.float32), ("frame", "marker")),
            "labels": (np.array(["LASI", "RASI", "C7", "T10"]), ("marker",)),
            "fragments": (np.zeros((n_frames, 0, 3)), ("frame", "fragment", "xyz")),
            "flags": (rng.random(n_frames) > 0.5, ("frame",)),
            "ids": (np.arange(n_frames, dtype=">i2"), ("frame",)),  # big-endian in
            "bytes": (np.arange(7, dtype=np.uint8), ("k",)),
            "z": (np.array([1 + 2j, -0.0 - 1j]), ("c",)),
            "times": (np.array(["2024-01-01", "NaT"], dtype="datetime64[ns]"), ("t",)),
            "scalar": (np.array(3.25), ()),
        },
        {"rate": 120.0, "first_frame": np.int64(7), "nan": float("nan"), "big": 2**60,
         "names": ("a",), "by_id": {3: "x"}},
    )
    return {
        "markers": markers,
        "report": encode({"merges": [[1, 2]], "variance": 0.99, "note": "ok"}),
        "record": encode({"basis": rng.normal(size=(3, 5)), "mean": np.zeros(0), "k": 3}),
        "empty": encode(np.zeros((0, 5, 3))),
        "names": Encoded("names", {"n": (np.array(["x", "yy"], dtype=object), ("i",))}, {}),
    }
