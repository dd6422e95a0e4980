"""The mocapflow engine: stage graphs, content-addressed Zarr store, executors, CLI.

It knows nothing about motion capture: domain stage families register themselves
through :func:`stage` and :func:`codec` and are discovered by entry point.
"""

from mocapflow.pipeline.codecs import Encoded, codec, exporter
from mocapflow.pipeline.context import Context
from mocapflow.pipeline.registry import FilePath, ParamError, stage

__all__ = ["Context", "Encoded", "FilePath", "ParamError", "codec", "exporter", "stage"]
