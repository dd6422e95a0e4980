"""Export: the outputs of a graph's target nodes as ordinary files (``mocapflow export``).

Registered types go through their exporter (:func:`~mocapflow.pipeline.codecs.exporter`:
BVH, C3D, OBJ, PNG/MP4, ...); the engine's own encodings are written as ``.json``
(JSON values, record attrs) and ``.npy`` (arrays).  The layout is
:data:`EXPORT_LAYOUT`.

Every written path stays under the export directory: part labels are made
safe as one directory name (:func:`safe_label`: no ``/``, ``\\``, control
characters, ``.`` or ``..``), each target directory must resolve inside the
export directory and hold no symlink pointing out of it, and every file an
exporter reports is checked again.  A problem is an :class:`ExportError`, one
line naming the path.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.pipeline.codecs import Encoded, ExportFormatError, decode, find_exporter
from mocapflow.pipeline.execute import TaskRecord
from mocapflow.pipeline.graph import Graph, part_label
from mocapflow.pipeline.keys import digest
from mocapflow.pipeline.registry import discover
from mocapflow.pipeline.store import Store

__all__ = ["EXPORT_LAYOUT", "ExportError", "export_results", "export_value", "safe_label"]

EXPORT_LAYOUT = ("Files are written as DIR/<node>/<part label>/<output>.<ext>; the part label "
                 "is the part file's stem, '.seed<S>' appended per seed fan-out, 'seed<S>' for "
                 "a seed-only part and 'all' for a gather node ('-<6 hex>' is appended when two "
                 "parts share a stem). Registered types use their exporter (BVH, C3D, OBJ, "
                 "PNG/MP4, …); JSON outputs become <output>.json, arrays <output>.npy, records "
                 "<output>.json + <output>.<array>.npy.")


#: Longest part label (bytes of the file name; file systems allow 255).
MAX_LABEL_BYTES = 200
_UNSAFE = re.compile(r"[/\\\x00-\x1f\x7f]")


class ExportError(Exception):
    """An output that cannot be written where it belongs (one line naming the path)."""


def safe_label(label: str) -> str:
    """A part label usable as one directory name, unchanged when it already is.

    ``/``, ``\\`` and control characters become ``_``; a label of dots only
    (``.``, ``..``) or empty gets a leading ``_``; a label longer than
    :data:`MAX_LABEL_BYTES` is cut and ends in 6 hex of its digest.
    """
    out = _UNSAFE.sub("_", label)
    if not out.strip("."):
        out = "_" + out
    if len(os.fsencode(out)) > MAX_LABEL_BYTES:
        tail = "-" + digest(label)[:6]
        out = out[:MAX_LABEL_BYTES]
        while len(os.fsencode(out + tail)) > MAX_LABEL_BYTES:
            out = out[:-1]
        out += tail
    return out


def _inside(path: Path, root: Path) -> bool:
    return path.resolve().is_relative_to(root)


def _check_target(target: Path, root: Path) -> None:
    """``target`` (a directory to write into) resolves under ``root`` and links nowhere else."""
    if not _inside(target, root):
        raise ExportError(f"export: {target} resolves to {target.resolve()}, outside the export "
                          f"directory {root} (a symlink?); not writing there")
    if target.is_dir():
        for p in target.iterdir():
            if p.is_symlink() and not _inside(p, root):
                raise ExportError(f"export: {p} is a symlink pointing outside the export "
                                  f"directory {root}; not writing through it")


def export_value(enc: Encoded, value: Any, directory: Path, stem: str, *,
                 formats: Sequence[str] | None = None) -> list[Path]:
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
    formats : sequence of str, optional
        Passed to the type's exporter as its ``formats`` option (its default if ``None``).

    Returns
    -------
    list of Path
        Every file written.
    """
    directory.mkdir(parents=True, exist_ok=True)
    fn = find_exporter(enc.type)
    if fn is not None:
        opts = {} if formats is None else {"formats": tuple(formats)}
        return [Path(p) for p in fn(value, directory, stem, **opts)]
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
                   directory: str | Path, *,
                   formats: Mapping[str, Sequence[str]] | None = None) -> list[Path]:
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
    formats : dict, optional
        ``output type -> file formats`` for exporters that write several (e.g.
        ``{"mesh": ("vtp", "pc2", "ply")}``); others get their defaults.

    Returns
    -------
    list of Path
        Every file written.

    Raises
    ------
    ExportError
        A path that would leave ``directory``, or one that cannot be written
        (full disk, permissions): one line naming it.
    """
    discover()  # every family's codecs and exporters
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ExportError(f"export: cannot create {directory}: {e.strerror or e}") from e
    root = directory.resolve()
    written: list[Path] = []
    for node in graph.targets:
        recs = [r for r in records if r.node == node]
        labels = [safe_label(part_label(r.part)) for r in recs]
        counts: dict[str, int] = {}
        for label in labels:
            counts[label] = counts.get(label, 0) + 1
        for r, label in zip(recs, labels):
            if counts[label] > 1:  # same stem in two folders: add a short part digest
                label = f"{label}-{digest(str(r.part))[:6]}"
            target = directory / node / label
            _check_target(target, root)
            for out, enc in store.load_outputs(r.stage, r.key).items():
                value = decode(enc)
                try:
                    files = export_value(enc, value, target, out,
                                         formats=(formats or {}).get(enc.type))
                except OSError as e:
                    raise ExportError(f"export: cannot write {target / out}.*: "
                                      f"{e.strerror or e}") from e
                except ExportFormatError as e:
                    given = formats and enc.type in formats
                    raise ExportError(f"export: --format {enc.type}: {e}" if given else
                                      f"export: {enc.type} ({node}/{label}/{out}): {e}"
                                      ) from None
                for f in files:
                    if not _inside(Path(f), root):
                        raise ExportError(f"export: the {enc.type} exporter wrote {f}, outside "
                                          f"the export directory {root}")
                written += files
    return written
