"""A committed store entry as an ``xarray.DataTree`` (:func:`open_entry`).

Every output of an entry is a Zarr group with named dimensions, coordinate
arrays and consolidated metadata (see :mod:`mocapflow.pipeline.store_zarr`), so
each opens as an ``xarray.Dataset`` without reading any chunk (arrays are lazy,
Dask-backed).  The entry is found by the graph node and part that produced it,
through the manifests of the store (``node`` / ``part`` fields), the same
entries ``mocapflow show`` finds by key.

xarray is an optional dependency (``pip install 'mocapflow[xarray]'``); it is
imported only when :func:`open_entry` is called.
"""

from __future__ import annotations

import os
from typing import Any

from mocapflow.pipeline.store import EntryNotFoundError, Store, StoreError

__all__ = ["EntryAmbiguousError", "find_node_entry", "open_entry"]


class EntryAmbiguousError(StoreError, LookupError):
    """Several committed entries were produced by one node and part (give ``part``)."""


def _as_store(store: Store | str | os.PathLike) -> Store:
    if isinstance(store, Store):
        return store
    if isinstance(store, (str, os.PathLike)):
        return Store(os.fspath(store))
    raise TypeError(f"store: expected a path, URL or Store, got {type(store).__name__}")


def find_node_entry(store: Store, node: str, part: str | None = None) -> tuple[str, str]:
    """The committed ``(stage, key)`` of ``node`` (and ``part``).

    Parameters
    ----------
    store : Store
    node : str
        Graph node name (the manifest's ``node``).
    part : str, optional
        Part name such as ``"seed=0"``; may be left out when the node's entries
        all have one part.  When a node/part was committed several times (e.g.
        with different parameters), the entry of its most recent run record is
        taken, else the most recently committed.

    Raises
    ------
    EntryNotFoundError
        No committed entry of that node (and part); the message lists the nodes.
    EntryAmbiguousError
        ``part`` left out and the node has entries of several parts.
    """
    found = []
    for stage, key in store.entries():
        man = store.manifest(stage, key) or {}
        if man.get("node") == node and (part is None or man.get("part") == part):
            found.append((man, stage, key))
    if not found:
        mans = (store.manifest(s, k) or {} for s, k in store.entries())
        nodes = sorted({str(m.get("node") or "?") for m in mans})
        what = f"node {node!r}" + (f" part {part!r}" if part is not None else "")
        raise EntryNotFoundError(
            f"no committed entry of {what} in store {store.root} "
            f"(nodes with entries: {', '.join(nodes) or 'none'})"
        )
    parts = sorted({str(m.get("part")) for m, _, _ in found})
    if part is None and len(parts) > 1:
        raise EntryAmbiguousError(
            f"node {node!r} has entries of {len(parts)} parts ({', '.join(parts[:5])}"
            f"{'…' if len(parts) > 5 else ''}); pass part="
        )
    if len(found) > 1:
        rec = store.last_task_record(node, found[0][0].get("part"))
        for _, stage, key in found:
            if rec and rec.get("key") == key:
                return stage, key
        found.sort(key=lambda f: str(f[0].get("committed_at")))
    return found[-1][1], found[-1][2]


def _import_xarray() -> Any:
    try:
        import xarray  # noqa: PLC0415 (optional, heavy)
    except ImportError:
        raise ImportError(
            "mocapflow.open_entry needs xarray: pip install 'mocapflow[xarray]'"
        ) from None
    if not hasattr(xarray, "DataTree"):
        raise ImportError(
            f"mocapflow.open_entry needs xarray>=2024.10 (DataTree), found {xarray.__version__}"
        )
    return xarray


def open_entry(store: Store | str | os.PathLike, node: str, part: str | None = None) -> Any:
    """Open the committed entry of a graph node as an ``xarray.DataTree``.

    Parameters
    ----------
    store : Store or str or path-like
        The store, or its root (a local directory or an fsspec URL).
    node : str
        Graph node name (as in ``mocapflow status`` / the manifest).
    part : str, optional
        Part name, e.g. ``"seed=0"`` or ``"trial=walk1"``; needed when the node
        has several parts (see :func:`find_node_entry`).

    Returns
    -------
    xarray.DataTree
        One child per output, named like it, each an ``xarray.Dataset`` with
        the output's arrays as lazy data variables, its coordinates (``frame``,
        ``time``, ``marker``, ``joint``, ``xyz``, …) and the output's
        ``mocapflow`` attrs (type, codec attrs).  The root's attrs are
        ``stage``, ``key``, ``node``, ``part``, ``path`` and ``committed_at``.

    Raises
    ------
    ImportError
        xarray (>= 2024.10) is not installed.
    EntryNotFoundError, EntryAmbiguousError
        See :func:`find_node_entry`.

    Examples
    --------
    >>> tree = mocapflow.open_entry("store", "capture", "seed=0")  # doctest: +SKIP
    >>> tree["markers"]["positions"].sel(marker="LASI", xyz="z")   # doctest: +SKIP
    """
    xr = _import_xarray()
    st = _as_store(store)
    stage, key = find_node_entry(st, node, part)
    man = st.require(stage, key)
    zstore = st.backend.zarr_store(st.entry_location(stage, key))
    children = {
        out: xr.open_zarr(zstore, group=out, consolidated=True, zarr_format=3)
        for out in sorted(man["outputs"])
    }
    tree = xr.DataTree.from_dict(children)
    tree.attrs = {
        "stage": stage,
        "key": key,
        "node": man.get("node"),
        "part": man.get("part"),
        "path": st.entry_path(stage, key),
        "committed_at": man.get("committed_at"),
    }
    return tree
