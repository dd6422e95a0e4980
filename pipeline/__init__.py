"""The mocapflow engine: stage graphs, content-addressed Zarr store, executors, CLI.

It knows nothing about motion capture: domain stage families register themselves
through :func:`stage` and :func:`codec` and are discovered by entry point.

Modules, by concern:

Stages
    ``registry``      the ``@stage`` decorator, params validation, family discovery
    ``context``       what a stage receives: seeded RNG, ``ctx.map``, warnings, ``ctx.timer``
    ``codecs``        outputs as arrays + JSON attrs (``Encoded``), codecs, exporters
    ``testing``       toy stages, fixtures, a contract test for stage families
Configs and graphs
    ``config_yaml``   line-aware YAML loading; ``ConfigError`` (``FILE:LINE: key: problem``)
    ``config_interpolation``  ``${params.NAME}`` and ``${env:VAR,default}``
    ``config_parts``  part entries → part ids (paths, bounded globs)
    ``config``        parsing and validation of a graph config (``load_config``)
    ``graph``         nodes × parts → tasks (``build_graph``, ``load_graph``)
    ``wires``         where each task input comes from (``FileWire``, ``TaskWire``, …)
Keys
    ``keys``          canonical JSON, digests, file digests, ``task_key``, ``diff_components``
    ``fingerprint``   per-definition code fingerprints
    ``task_keys``     the key of one task: fingerprint, params, input digests, ``hash_files``
Store
    ``store``         ``Store``: addresses, commit and publish, manifests, loading
    ``store_layout``  reserved names, name rules, errors, JSON documents
    ``store_backends`` the ``Backend`` protocol: local directories, fsspec URLs
    ``store_zarr``    Zarr v3 I/O of entries: normalise, chunk, write, read, check
    ``store_maintenance``  verify, writer liveness, gc
    ``store_runs``    run records and the file-digest memo
Execution
    ``execute``       one task: key → cache check → stage → commit (``TaskSpec``, ``TaskRecord``)
    ``executors``     sync, local cluster, existing cluster, Slurm
    ``plan``          plan, explain, status, the gc keep set
    ``lock``          lock files and ``--frozen`` checks
    ``runner``        ``run``: plan hits, executor calls, run records
    ``progress``      the progress bar
Front ends
    ``export``        target outputs as ordinary files
    ``show``          find and describe an entry
    ``demo``          the demo steps
    ``cli``           the ``mocapflow`` command (argument parsing and printing only)
"""

from mocapflow.pipeline.codecs import Encoded, codec, exporter
from mocapflow.pipeline.context import Context
from mocapflow.pipeline.registry import FilePath, ParamError, stage

__all__ = ["Context", "Encoded", "FilePath", "ParamError", "codec", "exporter", "stage"]
