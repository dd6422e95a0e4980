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

from mocapflow.pipeline.show import EntryAmbiguousError, find_node_entry
from mocapflow.pipeline.store import Store

__all__ = ["EntryAmbiguousError", "find_node_entry", "open_entry"]


def _as_store(store: Store | str | os.PathLike) -> Store:
    if isinstance(store, Store):
        return store
    if isinstance(store, (str, os.PathLike)):
        return Store(os.fspath(store))
    raise TypeError(f"store: expected a path, URL or Store, got {type(store).__name__}")


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
