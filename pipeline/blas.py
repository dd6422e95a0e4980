"""BLAS and OpenMP thread pools at one thread while a stage runs (:func:`single_threaded_blas`).

Used by the engine around every task (:func:`~mocapflow.pipeline.execute.execute_task`)
and by a stage called from Python (:func:`~mocapflow.pipeline.registry.call`), so a
stage gives the same bits either way, on any machine.
"""

from __future__ import annotations

import contextlib
import sys
import threading
from collections.abc import Iterator
from typing import Any

from threadpoolctl import ThreadpoolController

__all__ = ["single_threaded_blas"]

_BLAS_LOCK = threading.Lock()
#: ``depth``: tasks of this process inside :func:`single_threaded_blas`; ``limiter``:
#: what restores the pools; ``controller``/``modules``: the pools found, and
#: ``len(sys.modules)`` when they were looked up (a new import may load a new BLAS).
_BLAS: dict[str, Any] = {"depth": 0, "limiter": None, "controller": None, "modules": -1}


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[None]:
    """BLAS and OpenMP thread pools at one thread while a stage runs in this process.

    A threaded BLAS splits sums (dot products, ``gemv``, LAPACK panels)
    differently for each thread count, so the same stage on the same inputs may
    differ in the last bits between ``OPENBLAS_NUM_THREADS=1`` and ``=2``: with
    one thread per task a stage's outputs do not depend on the machine, the
    environment or the executor (Dask worker processes start with one thread
    already).  Parallelism comes from tasks and ``ctx.map``.  Re-entrant and
    thread-safe: the pools are limited while any task runs and restored after
    the last; the pools are looked up again only when modules were imported
    since (``threadpoolctl``'s lookup costs ~3 ms, the limit ~0.1 ms).
    """
    with _BLAS_LOCK:
        if _BLAS["depth"] == 0:
            if _BLAS["controller"] is None or _BLAS["modules"] != len(sys.modules):
                _BLAS["modules"] = len(sys.modules)
                _BLAS["controller"] = ThreadpoolController()
            _BLAS["limiter"] = _BLAS["controller"].limit(limits=1)
        _BLAS["depth"] += 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _BLAS["depth"] -= 1
            if _BLAS["depth"] == 0:
                _BLAS["limiter"].restore_original_limits()
                _BLAS["limiter"] = None
