"""Where tasks run: ``sync`` (in-process), ``local`` (LocalCluster), an existing
Dask cluster (``--address`` / ``--scheduler-file``) or Slurm (dask-jobqueue).

An executor runs a list of :class:`Call` (one per (node, part)), each a picklable
module-level function whose extra positional arguments are the results of its
dependencies.  Results are small references, never data: anything with a
``status`` and an ``index`` (the engine's are
:class:`~mocapflow.pipeline.execute.TaskRecord`); for a call it could not run
(it raised, or was cancelled) an executor reports a :class:`CallOutcome`.  ``ctx.map`` inside a
stage uses the same executor: :func:`task_mapper` returns a map that submits the
sub-items to the cluster from inside the task (``distributed.worker_client``),
or ``None`` (a plain map) outside a worker.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "Call",
    "CallOutcome",
    "DistributedExecutor",
    "Executor",
    "ExecutorError",
    "SlurmOptions",
    "SyncExecutor",
    "make_executor",
    "slurm_job_script",
    "task_mapper",
]

log = logging.getLogger("mocapflow")


class ExecutorError(ValueError):
    """An executor cannot be set up (bad flags, unreachable scheduler, missing package)."""


@dataclass(frozen=True)
class Call:
    """One task for an executor.

    Attributes
    ----------
    index : int
        Task index (the results dict is keyed by it).
    key : str
        Dask key (unique per run: includes the run id).
    fn : callable
        Module-level function, called as ``fn(*args, *dep_results)``; its result
        has ``status`` (``"hit"``/``"computed"`` for success) and ``index``.
    args : tuple
        Picklable leading arguments.
    deps : tuple of int
        Indices of the calls whose results are appended to ``args``.
    """

    index: int
    key: str
    fn: Callable[..., Any]
    args: tuple
    deps: tuple[int, ...] = ()


@dataclass(frozen=True)
class CallOutcome:
    """What an executor reports for a call it could not run to a result of its own.

    Attributes
    ----------
    index : int
        The call's index.
    status : {"failed", "skipped"}
    error : str
        ``"TypeName: message"`` of what the call raised, or why it was skipped.
    """

    index: int
    status: str
    error: str


def _failed(call: Call, error: str) -> CallOutcome:
    return CallOutcome(call.index, "failed", error)


def _cancelled(call: Call) -> CallOutcome:
    return CallOutcome(call.index, "skipped", "cancelled (--fail-fast)")


class Executor:
    """Base class: ``run(calls, on_done=..., fail_fast=...) -> {index: result}``."""

    name = "base"
    workers = 1

    def run(self, calls: Sequence[Call], *, on_done: Callable[[Any], None] | None = None,
            fail_fast: bool = False) -> dict[int, Any]:
        raise NotImplementedError

    def describe(self) -> str:
        """One line for logs."""
        return self.name

    def close(self) -> None:
        """Release resources this executor created (never an external cluster)."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class SyncExecutor(Executor):
    """Run every call in this process, in order (calls must be topologically sorted)."""

    name = "sync"

    def run(self, calls: Sequence[Call], *, on_done: Callable[[Any], None] | None = None,
            fail_fast: bool = False) -> dict[int, Any]:
        results: dict[int, Any] = {}
        stop = False
        for call in calls:
            if stop:
                results[call.index] = _cancelled(call)
                continue
            try:
                res = call.fn(*call.args, *[results[d] for d in call.deps])
            except Exception as e:  # the task function catches stage errors itself
                res = _failed(call, f"{type(e).__name__}: {e}")
            results[call.index] = res
            if on_done is not None:
                on_done(res)
            if fail_fast and res.status == "failed":
                stop = True
        return results


class DistributedExecutor(Executor):
    """Run calls on a ``dask.distributed`` cluster.

    Parameters
    ----------
    client_factory : callable
        ``() -> (client, closer)``; called on the first :meth:`run` (so a run in
        which every task is a cache hit never starts a cluster).  ``closer`` is
        called by :meth:`close` (it must not shut down an external cluster).
    name : str
    workers : int
        Expected number of workers (``Context.workers``).
    """

    def __init__(self, client_factory: Callable[[], tuple[Any, Callable[[], None]]], *,
                 name: str, workers: int = 1, description: str = "") -> None:
        self._factory = client_factory
        self._client = None
        self._closer: Callable[[], None] | None = None
        self.name = name
        self.workers = workers
        self._description = description or name

    @property
    def client(self):
        """The ``distributed.Client`` (started on first use)."""
        if self._client is None:
            self._client, self._closer = self._factory()
            try:
                n = len(self._client.scheduler_info().get("workers", {}))
                if n:
                    self.workers = n
            except Exception:  # pragma: no cover - info only
                pass
        return self._client

    def describe(self) -> str:
        return self._description

    def run(self, calls: Sequence[Call], *, on_done: Callable[[Any], None] | None = None,
            fail_fast: bool = False) -> dict[int, Any]:
        """Submit each call once its dependencies are done, with their results as arguments.

        Dependencies are resolved here, not through Dask futures: results are tiny
        references, so tasks carry no data locality and the scheduler balances them
        over every worker.  A call whose dependency failed runs here (it only
        records itself as skipped).
        """
        from distributed import as_completed  # noqa: PLC0415 (heavy)

        client = self.client
        by_index = {c.index: c for c in calls}
        by_key = {c.key: c for c in calls}
        waiting = {c.index: set(c.deps) for c in calls}
        children: dict[int, list[int]] = {}
        for c in calls:
            for d in c.deps:
                children.setdefault(d, []).append(c.index)
        results: dict[int, Any] = {}
        running: dict[str, Any] = {}
        ac = as_completed([], loop=client.loop)
        stop = False

        def launch(call: Call) -> None:
            dep_results = [results[d] for d in call.deps]
            if any(r.status not in ("hit", "computed") for r in dep_results):
                try:
                    res = call.fn(*call.args, *dep_results)
                except Exception as e:
                    res = _failed(call, f"{type(e).__name__}: {e}")
                finish(call, res)
                return
            fut = client.submit(call.fn, *call.args, *dep_results, key=call.key, pure=False)
            running[fut.key] = fut
            ac.add(fut)

        def finish(call: Call, res: Any) -> None:
            nonlocal stop
            results[call.index] = res
            if on_done is not None:
                on_done(res)
            if fail_fast and res.status == "failed":
                stop = True
            if stop:
                return
            for ch in children.get(call.index, ()):
                waiting[ch].discard(call.index)
                if not waiting[ch]:
                    launch(by_index[ch])

        for c in calls:
            if not c.deps and not stop:
                launch(c)
        for fut in ac:
            running.pop(fut.key, None)
            call = by_key[fut.key]
            if fut.status == "finished":
                res = fut.result()
            elif fut.status == "cancelled":
                res = _cancelled(call)
            else:
                exc = fut.exception()
                res = _failed(call, f"{type(exc).__name__}: {exc}")
            fut.release()
            finish(call, res)
            if stop:
                client.cancel(list(running.values()))
                break
        for i, c in by_index.items():
            if i not in results:
                results[i] = _cancelled(c)
        return results

    def close(self) -> None:
        if self._closer is not None:
            try:
                self._closer()
            finally:
                self._closer = None
                self._client = None


# --------------------------------------------------------------------------- ctx.map


def _distributed_map(fn: Callable[[Any], Any], items: list[Any]) -> list[Any]:
    from distributed import worker_client  # noqa: PLC0415 (heavy)

    with worker_client() as client:
        futs = client.map(fn, items, pure=False)
        return client.gather(futs)


def task_mapper() -> Callable[[Callable[[Any], Any], list[Any]], list[Any]] | None:
    """The ``ctx.map`` backend for the current task.

    Returns
    -------
    callable or None
        Inside a ``distributed`` worker: a map that submits the items to the
        same cluster (seceding from the worker's thread pool while it waits).
        Elsewhere ``None``: the context maps sequentially.
    """
    try:
        from distributed import get_worker  # noqa: PLC0415 (heavy)

        get_worker()
    except (ImportError, ValueError):
        return None
    return _distributed_map


# --------------------------------------------------------------------------- factories


@dataclass
class SlurmOptions:
    """Options of ``--executor slurm`` (dask-jobqueue ``SLURMCluster``)."""

    queue: str | None = None
    cores: int = 4
    memory: str = "8GB"
    walltime: str = "01:00:00"
    jobs: int = 1
    account: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def cluster_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``SLURMCluster``: one single-threaded worker per core."""
        kw: dict[str, Any] = {
            "cores": self.cores,
            "processes": self.cores,
            "memory": self.memory,
            "walltime": self.walltime,
            "job_name": "mocapflow",
            "scheduler_options": {"dashboard_address": ":0"},
        }
        if self.queue:
            kw["queue"] = self.queue
        if self.account:
            kw["account"] = self.account
        env = os.environ.get("MOCAPFLOW_STAGE_MODULES")
        if env:
            kw["job_script_prologue"] = [f"export MOCAPFLOW_STAGE_MODULES={env}"]
        kw.update(self.extra)
        return kw


def _slurm_cluster(opts: SlurmOptions):
    try:
        from dask_jobqueue import SLURMCluster  # noqa: PLC0415 (heavy)
    except ImportError as e:  # pragma: no cover - dependency declared
        raise ExecutorError(f"--executor slurm needs dask-jobqueue ({e})") from None
    return SLURMCluster(**opts.cluster_kwargs())


def slurm_job_script(opts: SlurmOptions) -> str:
    """The batch script each Slurm job runs (no Slurm needed to render it)."""
    cluster = _slurm_cluster(opts)
    try:
        return cluster.job_script()
    finally:
        cluster.close()


def _local_factory(workers: int):
    def start():
        from distributed import Client, LocalCluster  # noqa: PLC0415 (heavy)

        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=":0", silence_logs=logging.ERROR)
        client = Client(cluster, set_as_default=False)

        def closer() -> None:
            client.close()
            cluster.close()

        return client, closer

    return start


def _external_factory(address: str | None, scheduler_file: str | None):
    def start():
        from distributed import Client  # noqa: PLC0415 (heavy)

        try:
            if scheduler_file:
                if not os.path.exists(scheduler_file):
                    raise ExecutorError(f"--scheduler-file {scheduler_file}: no such file")
                client = Client(scheduler_file=scheduler_file, timeout="20s",
                                set_as_default=False)
            else:
                client = Client(address, timeout="20s", set_as_default=False)
        except ExecutorError:
            raise
        except OSError as e:
            where = scheduler_file or address
            raise ExecutorError(f"cannot reach the Dask scheduler at {where}: {e}") from None
        return client, client.close  # never shut down the external cluster

    return start


def _slurm_factory(opts: SlurmOptions):
    def start():
        from distributed import Client  # noqa: PLC0415 (heavy)

        cluster = _slurm_cluster(opts)
        cluster.scale(jobs=opts.jobs)
        client = Client(cluster, set_as_default=False)

        def closer() -> None:
            client.close()
            cluster.close()

        return client, closer

    return start


def make_executor(kind: str = "local", *, workers: int | None = None, address: str | None = None,
                  scheduler_file: str | None = None, slurm: SlurmOptions | None = None,
                  client: Any = None) -> Executor:
    """Build an executor from command-line style options.

    Parameters
    ----------
    kind : {"sync", "local", "slurm"}
        Ignored when ``address``, ``scheduler_file`` or ``client`` is given.
    workers : int, optional
        ``local``: number of single-threaded worker processes (default: CPU count).
    address, scheduler_file : str, optional
        An existing cluster (never shut down by mocapflow).
    slurm : SlurmOptions, optional
    client : distributed.Client, optional
        Use this client (tests, notebooks); not closed.

    Returns
    -------
    Executor
        Cluster-backed executors start lazily, on the first run that has work.
    """
    if client is not None:
        n = len(client.scheduler_info().get("workers", {})) or 1
        return DistributedExecutor(lambda: (client, lambda: None), name="client", workers=n,
                                   description=f"client {client.scheduler.address}")
    if address or scheduler_file:
        if address and scheduler_file:
            raise ExecutorError("give --address or --scheduler-file, not both")
        return DistributedExecutor(_external_factory(address, scheduler_file), name="external",
                                   workers=workers or 1,
                                   description=f"external cluster {address or scheduler_file}")
    if kind == "sync":
        return SyncExecutor()
    if kind == "local":
        n = workers or os.cpu_count() or 1
        if n < 1:
            raise ExecutorError(f"--workers must be at least 1, got {n}")
        return DistributedExecutor(_local_factory(n), name="local", workers=n,
                                   description=f"local cluster, {n} worker processes")
    if kind == "slurm":
        opts = slurm or SlurmOptions()
        return DistributedExecutor(_slurm_factory(opts), name="slurm",
                                   workers=opts.jobs * opts.cores,
                                   description=f"slurm, {opts.jobs} job(s) × {opts.cores} cores")
    raise ExecutorError(f"unknown executor {kind!r} (sync, local or slurm)")
