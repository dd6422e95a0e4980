"""mocapflow: declarative motion-capture pipelines under Dask over content-addressed Zarr stores.

The engine lives in :mod:`mocapflow.pipeline`, the motion-capture domain in
:mod:`mocapflow.stages`.

From Python:

* :func:`run` (``mocapflow.run(config, parts=..., set={...}, store=...)``) runs a
  graph and returns a :class:`Results`, the outputs of each ``(node, part)`` as
  domain objects (:mod:`mocapflow.pipeline.api`);
* :class:`Context` is what a stage receives as ``ctx`` (a stage called directly
  makes one itself);
* :func:`open_entry` (``mocapflow.open_entry(store, node, part=None)``) opens a
  committed entry as an ``xarray.DataTree`` (needs the ``xarray`` extra).

Each is imported on first use, so ``import mocapflow`` stays cheap.
"""

import importlib
from typing import Any

__version__ = "0.1.0"

__all__ = ["Context", "Results", "__version__", "open_entry", "run"]

_LAZY = {
    "Context": "mocapflow.pipeline.context",
    "Results": "mocapflow.pipeline.api",
    "open_entry": "mocapflow.pipeline.entry_xarray",
    "run": "mocapflow.pipeline.api",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'mocapflow' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])
