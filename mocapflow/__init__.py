"""mocapflow: declarative motion-capture pipelines under Dask over content-addressed Zarr stores.

The engine lives in :mod:`mocapflow.pipeline`, the motion-capture domain in
:mod:`mocapflow.stages`.
"""

__version__ = "0.1.0"
