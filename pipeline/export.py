"""Export: the outputs of a graph's target nodes as ordinary files (``mocapflow export``).

Registered types go through their exporter (:func:`~mocapflow.pipeline.codecs.exporter`:
BVH, C3D, OBJ, PNG/MP4, ...); the engine's own encodings are written as ``.json``
(JSON values, record attrs) and ``.npy`` (arrays).  The layout is
:data:`EXPORT_LAYOUT`.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.pipeline.codecs import Encoded, decode, find_exporter
from mocapflow.pipeline.execute import TaskRecord
from mocapflow.pipeline.graph import Graph, part_label
from mocapflow.pipeline.keys import digest
from mocapflow.pipeline.registry import discover
from mocapflow.pipeline.store import Store

__all__ = ["EXPORT_LAYOUT", "export_results", "export_value"]

EXPORT_LAYOUT = ("Files are written as DIR/<node>/<part label>/<output>.<ext>; the part label "
                 "is the part file's stem, '.seed<S>' appended per seed fan-out, 'seed<S>' for "
                 "a seed-only part and 'all' for a gather node ('-<6 hex>' is appended when two "
                 "parts share a stem). Registered types use their exporter (BVH, C3D, OBJ, "
                 "PNG/MP4, …); JSON outputs become <output>.json, arrays <output>.npy, records "
                 "<output>.json + <output>.<array>.npy.")


def export_value(enc: Encoded, value: Any, directory: Path, stem: str) -> list[Path]:
    """Write one output as ``directory/stem.<ext>`` file(s).

    Parameters
    ----------
    enc : Encoded
        The stored output (its type picks the exporter).
    value : any
        The decoded output (what the exporter receives).
    directory : Path
        Created if needed.
    stem : str
        The output name.

    Returns
    -------
    list of Path
        Every file written.
    """
    directory.mkdir(parents=True, exist_ok=True)
    fn = find_exporter(enc.type)
    if fn is not None:
        return [Path(p) for p in fn(value, directory, stem)]
    written = []
    if enc.type == "ndarray":
        p = directory / f"{stem}.npy"
        np.save(p, enc.arrays["data"][0])
        return [p]
    if enc.type == "json":
        p = directory / f"{stem}.json"
        p.write_text(json.dumps(enc.attrs.get("value"), indent=1) + "\n")
        return [p]
    attrs = dict(enc.attrs)
    if enc.type != "record":
        attrs = {"type": enc.type, "attrs": attrs}
    attrs_arrays = {n: f"{stem}.{n}.npy" for n in enc.arrays}
    if attrs_arrays:
        attrs = {**attrs, "_arrays": attrs_arrays}
    p = directory / f"{stem}.json"
    p.write_text(json.dumps(attrs, indent=1) + "\n")
    written.append(p)
    for n, (a, _) in enc.arrays.items():
        q = directory / attrs_arrays[n]
        np.save(q, a)
        written.append(q)
    return written


def export_results(graph: Graph, store: Store, records: Sequence[TaskRecord],
                   directory: str | Path) -> list[Path]:
    """Write the outputs of the graph's target nodes as files (see :data:`EXPORT_LAYOUT`).

    Parameters
    ----------
    graph : Graph
    store : Store
        Where the records' entries are committed.
    records : sequence of TaskRecord
        Of a run of ``graph`` (:attr:`RunResult.records
        <mocapflow.pipeline.runner.RunResult.records>`).
    directory : str or Path

    Returns
    -------
    list of Path
        Every file written.
    """
    discover()  # every family's codecs and exporters
    directory = Path(directory)
    written: list[Path] = []
    for node in graph.targets:
        recs = [r for r in records if r.node == node]
        labels = [part_label(r.part) for r in recs]
        for r, label in zip(recs, labels):
            if labels.count(label) > 1:  # same stem in two folders: add a short part digest
                label = f"{label}-{digest(str(r.part))[:6]}"
            for out, enc in store.load_outputs(r.stage, r.key).items():
                value = decode(enc)
                written += export_value(enc, value, directory / node / label, out)
    return written
