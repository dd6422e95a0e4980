"""mocapflow: declarative motion-capture pipelines under Dask over content-addressed Zarr stores.

The engine lives in :mod:`mocapflow.pipeline`, the motion-capture domain in
:mod:`mocapflow.stages`.

:func:`open_entry` (``mocapflow.open_entry(store, node, part=None)``) opens a
committed entry as an ``xarray.DataTree`` (needs the ``xarray`` extra); it is
imported on first use, so ``import mocapflow`` stays cheap.
"""

from typing import Any

__version__ = "0.1.0"

__all__ = ["__version__", "open_entry"]


def __getattr__(name: str) -> Any:
    if name == "open_entry":
        from mocapflow.pipeline.entry_xarray import open_entry  # noqa: PLC0415 (lazy)

        return open_entry
    raise AttributeError(f"module 'mocapflow' has no attribute {name!r}")
