"""Finding a committed entry by key prefix and describing it (``mocapflow show``).

Only committed entries of the store are found (a symlinked entry directory is
not one), and an entry holding a symlink or special file is refused, not read
through (:meth:`~mocapflow.pipeline.store.Store.odd_paths`).
"""

from __future__ import annotations

import os
from typing import Any

from mocapflow.pipeline.graph import part_label
from mocapflow.pipeline.store import EntryNotFoundError, Store, StoreError
from mocapflow.pipeline.store_zarr import describe_outputs

__all__ = ["AmbiguousEntryError", "EntryAmbiguousError", "entry_summary", "find_entry",
           "find_node_entry"]


class AmbiguousEntryError(StoreError, LookupError):
    """More than one committed entry matches a key prefix."""


class EntryAmbiguousError(StoreError, LookupError):
    """Several committed entries were produced by one node and part (give ``part``)."""


def find_entry(store: Store, entry: str) -> tuple[str, str]:
    """The committed ``(stage, key)`` named by ``STAGE/KEY-PREFIX``, ``KEY-PREFIX``, or
    ``NODE[/PART]`` as in ``mocapflow explain`` (see :func:`find_node_entry`).

    Raises
    ------
    EntryNotFoundError
        No committed entry matches.
    AmbiguousEntryError
        Several do (the message names up to five).
    """
    stage, sep, key = entry.partition("/")
    entries = store.entries()
    if sep:
        cands = [(s, k) for s, k in entries if s == stage and k.startswith(key)]
    else:
        cands = [(s, k) for s, k in entries if k.startswith(entry)]
    if not cands and any(_manifest_node(store, s, k) == stage for s, k in entries):
        return find_node_entry(store, stage, key or None)
    if not cands:
        hint = _linked_hint(store, stage, key) if sep else _linked_hint(store, None, entry)
        raise EntryNotFoundError(f"no committed entry matches in store {store.root}{hint}")
    if len(cands) > 1:
        names = ", ".join(f"{s}/{k[:12]}" for s, k in cands[:5])
        raise AmbiguousEntryError(f"{len(cands)} entries match ({names}…); give more of "
                                  "the key")
    return cands[0]


def _manifest_node(store: Store, stage: str, key: str) -> str | None:
    return (store.manifest(stage, key) or {}).get("node")


def _part_matches(part: str | None, spec: str) -> bool:
    """``spec`` names ``part`` as :meth:`Graph.find` does: the id, a suffix, its label, or
    a substring of it."""
    if part is None:
        return spec == "all"
    return part == spec or part.endswith(spec) or part_label(part) == spec or spec in part


def find_node_entry(store: Store, node: str, part: str | None = None) -> tuple[str, str]:
    """The committed ``(stage, key)`` of ``node`` (and ``part``).

    Parameters
    ----------
    store : Store
    node : str
        Graph node name (the manifest's ``node``).
    part : str, optional
        Part name such as ``"seed=0"``, or any unique suffix, label
        (``cmu_131_02.seed3``) or substring of it; may be left out when the node's
        entries all have one part.  When a node/part was committed several times
        (e.g. with different parameters), the entry of its most recent run record
        is taken, else the most recently committed.

    Raises
    ------
    EntryNotFoundError
        No committed entry of that node (and part); the message lists the nodes.
    EntryAmbiguousError
        ``part`` left out, or matching, entries of several parts.
    """
    mans = [(store.manifest(s, k) or {}, s, k) for s, k in store.entries()]
    found = [f for f in mans if f[0].get("node") == node]
    if part is not None:
        exact = [f for f in found if f[0].get("part") == part]
        found = exact or [f for f in found if _part_matches(f[0].get("part"), part)]
    if not found:
        nodes = sorted({str(m.get("node") or "?") for m, _, _ in mans})
        what = f"node {node!r}" + (f" part {part!r}" if part is not None else "")
        raise EntryNotFoundError(
            f"no committed entry of {what} in store {store.root} "
            f"(nodes with entries: {', '.join(nodes) or 'none'})"
        )
    parts = sorted({str(m.get("part")) for m, _, _ in found})
    if len(parts) > 1:
        raise EntryAmbiguousError(
            f"node {node!r} has entries of {len(parts)} parts" +
            (f" matching {part!r}" if part is not None else "") +
            f" ({', '.join(parts[:5])}{'…' if len(parts) > 5 else ''}); name one"
        )
    if len(found) > 1:
        rec = store.last_task_record(node, found[0][0].get("part"))
        for _, stage, key in found:
            if rec and rec.get("key") == key:
                return stage, key
        found.sort(key=lambda f: str(f[0].get("committed_at")))
    return found[-1][1], found[-1][2]


def _linked_hint(store: Store, stage: str | None, prefix: str) -> str:
    """``" (STAGE/KEY: ... is a symlink ...)"`` when a symlinked entry would have matched."""
    if not store.is_local:
        return ""
    b = store.backend
    base = store.location("entries")
    if os.path.islink(base):
        return f" (entries/ is a symlink to {os.readlink(base)}, not followed)"
    for s in b.listdir(base):
        if stage is not None and s != stage:
            continue
        sd = b.join(base, s)
        if os.path.islink(sd):  # its names are not listed: that would follow it
            return f" (entries/{s} is a symlink to {os.readlink(sd)}, not followed)"
        for k in b.listdir(sd):
            if k.startswith(prefix):
                odd = store.odd_paths(s, k)
                if odd:
                    return f" ({odd[0]})"
    return ""


def entry_summary(store: Store, stage: str, key: str) -> dict[str, Any]:
    """Manifest and outputs of a committed entry, without reading any array data.

    Returns
    -------
    dict
        ``{"entry": "stage/key", "path", "manifest", "outputs": {output: {"type",
        "digest", "arrays": {name: {"shape", "dtype", "dims", "chunks"}}, "attrs"}}}``.

    Raises
    ------
    StoreError
        The entry is not committed, or holds a symlink or special file (not
        read through).
    """
    man = store.require(stage, key)
    described = describe_outputs(store.entry_path(stage, key), sorted(man["outputs"]))
    outputs = {}
    for out, info in sorted(man["outputs"].items()):
        outputs[out] = {"type": info.get("type"), "digest": info.get("digest"),
                        **described[out]}
    return {"entry": f"{stage}/{key}", "path": store.entry_path(stage, key), "manifest": man,
            "outputs": outputs}
