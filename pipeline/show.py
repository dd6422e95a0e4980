"""Finding a committed entry by key prefix and describing it (``mocapflow show``).

Only committed entries of the store are found (a symlinked entry directory is
not one), and an entry holding a symlink or special file is refused, not read
through (:meth:`~mocapflow.pipeline.store.Store.odd_paths`).
"""

from __future__ import annotations

import os
from typing import Any

from mocapflow.pipeline.store import EntryNotFoundError, Store, StoreError
from mocapflow.pipeline.store_zarr import describe_outputs

__all__ = ["AmbiguousEntryError", "entry_summary", "find_entry"]


class AmbiguousEntryError(StoreError, LookupError):
    """More than one committed entry matches a key prefix."""


def find_entry(store: Store, entry: str) -> tuple[str, str]:
    """The committed ``(stage, key)`` named by ``STAGE/KEY-PREFIX`` or ``KEY-PREFIX``.

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
    if not cands:
        hint = _linked_hint(store, stage, key) if sep else _linked_hint(store, None, entry)
        raise EntryNotFoundError(f"no committed entry matches in store {store.root}{hint}")
    if len(cands) > 1:
        names = ", ".join(f"{s}/{k[:12]}" for s, k in cands[:5])
        raise AmbiguousEntryError(f"{len(cands)} entries match ({names}…); give more of "
                                  "the key")
    return cands[0]


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
