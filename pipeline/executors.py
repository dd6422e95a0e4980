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

Cluster edges are one-line :class:`ExecutorError` (set-up) or task errors: a
task whose worker died too often (``KilledWorker``) fails with what to try;
``--executor slurm`` without ``sbatch`` fails before anything is submitted; no
worker within ``worker_timeout`` seconds (at start, or all lost during the run)
fails the run or its remaining tasks instead of waiting for ever; a store that
lives in this process's memory (``memory://``) runs the local cluster's workers
as threads of this process and is refused for clusters elsewhere.

Once a cluster is up (local, external or Slurm) the executor reports the
address of its Dask dashboard to ``on_dashboard`` (the command prints it as
``dashboard: URL`` on stderr; bokeh serves it).  Workers open the run's store
from its pickled root and storage options, so every worker reaches the same
store with the same endpoint and credentials.
"""

from __future__ import annotations

import functools
import logging
import os
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from mocapflow.pipeline.progress import StageWarningFilter

__all__ = [
    "Call",
    "CallOutcome",
    "DistributedExecutor",
    "Executor",
    "ExecutorError",
    "SlurmOptions",
    "SyncExecutor",
    "WORKER_TIMEOUT_S",
    "dashboard_link",
    "make_executor",
    "process_local_store",
    "progress_sink",
    "slurm_job_script",
    "task_mapper",
]

log = logging.getLogger("mocapflow")


#: Seconds to wait for a first worker (and, during a run, without any worker) by
#: executor kind; ``None`` waits for ever.  Slurm jobs may queue for a while.
WORKER_TIMEOUT_S = {"local": 60.0, "external": 60.0, "client": 60.0, "slurm": 600.0}


class ExecutorError(ValueError):
    """An executor cannot be set up (bad flags, unreachable scheduler, missing package)."""


def process_local_store(store: Any) -> bool:
    """Whether a store (or store root) lives in this process's memory (``memory://``).

    Worker processes cannot see such a store: each would write to its own.
    """
    root = getattr(store, "root", store)
    return isinstance(root, str) and root.startswith("memory://")


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
    node, part : str, optional
        The task the call runs, for the executor's own outcomes (``CallOutcome``).
    """

    index: int
    key: str
    fn: Callable[..., Any]
    args: tuple
    deps: tuple[int, ...] = ()
    node: str | None = None
    part: str | None = None


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
    node, part : str or None
        Of the call (so a task below it can name it).
    """

    index: int
    status: str
    error: str
    node: str | None = None
    part: str | None = None


def _failed(call: Call, error: str) -> CallOutcome:
    return CallOutcome(call.index, "failed", error, call.node, call.part)


def _cancelled(call: Call, why: str = "cancelled (--fail-fast)") -> CallOutcome:
    return CallOutcome(call.index, "skipped", why, call.node, call.part)


def killed_worker_message(exc: BaseException) -> str:
    """One line for a ``KilledWorker``: what happened and what to try.

    The task name is not in it (the run's message names the node and part).
    """
    tries = getattr(exc, "allowed_failures", None)
    times = "" if not isinstance(tries, int) else " once" if tries == 0 else f" {tries + 1} times"
    last = getattr(getattr(exc, "last_worker", None), "address", None)
    where = f", last on {last}" if last else ""
    return (f"KilledWorker: the worker process running this task died{times}{where} "
            "(out of memory, or a crash in native code?); try fewer --workers (more memory "
            "each), more --slurm-memory, or --executor sync to see the error")


def _error_line(exc: BaseException) -> str:
    """``"TypeName: first line"`` of what a call raised (``KilledWorker`` explained)."""
    if type(exc).__name__ == "KilledWorker":
        return killed_worker_message(exc)
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


class Executor:
    """Base class: ``run(calls, on_done=..., fail_fast=..., on_progress=...) -> {index: result}``.

    ``on_progress(message)``, when given, receives the progress updates the
    calls send through :func:`progress_sink` while they run (in this process).
    """

    name = "base"
    workers = 1

    def run(self, calls: Sequence[Call], *, on_done: Callable[[Any], None] | None = None,
            fail_fast: bool = False,
            on_progress: Callable[[dict[str, Any]], None] | None = None) -> dict[int, Any]:
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
            fail_fast: bool = False,
            on_progress: Callable[[dict[str, Any]], None] | None = None) -> dict[int, Any]:
        previous = _LOCAL_LISTENER[0]
        _LOCAL_LISTENER[0] = on_progress
        try:
            return self._run(calls, on_done, fail_fast)
        finally:
            _LOCAL_LISTENER[0] = previous

    @staticmethod
    def _run(calls: Sequence[Call], on_done: Callable[[Any], None] | None,
             fail_fast: bool) -> dict[int, Any]:
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
    worker_timeout : float or None
        Seconds to wait for a first worker once the cluster is up, and the
        longest a run waits while the cluster has no worker at all (its
        remaining tasks then fail); ``None`` waits for ever.
    in_process : bool or None
        Whether the workers are threads of this process (they then see a
        ``memory://`` store); ``None``: ask the workers when it matters.
    on_dashboard : callable, optional
        Called once the client is up with the dashboard's URL, or ``None`` when
        the scheduler serves no dashboard.
    """

    def __init__(self, client_factory: Callable[[], tuple[Any, Callable[[], None]]], *,
                 name: str, workers: int = 1, description: str = "",
                 worker_timeout: float | None = None, in_process: bool | None = False,
                 on_dashboard: Callable[[str | None], None] | None = None) -> None:
        self._factory = client_factory
        self._client = None
        self._closer: Callable[[], None] | None = None
        self.name = name
        self.workers = workers
        self.worker_timeout = worker_timeout
        self._in_process = in_process
        self._description = description or name
        self.on_dashboard = on_dashboard

    @property
    def client(self):
        """The ``distributed.Client`` (started on first use, with a worker to run on).

        Raises
        ------
        ExecutorError
            No worker joined within ``worker_timeout`` seconds.
        """
        if self._client is None:
            client, closer = self._factory()
            try:
                if self.on_dashboard is not None:
                    self.on_dashboard(dashboard_link(client))
                self._wait_first_worker(client)
                client.register_worker_callbacks(
                    setup=functools.partial(_quiet_worker_logging, os.getpid()))
            except BaseException:
                closer()
                raise
            self._client, self._closer = client, closer
            _quiet_scheduler_log()
            n = len(client.nthreads())
            if n:
                self.workers = n
        return self._client

    def _wait_first_worker(self, client: Any) -> None:
        try:
            client.wait_for_workers(1, timeout=self.worker_timeout)
        except TimeoutError:  # distributed's WorkerStartTimeoutError is one
            raise ExecutorError(
                f"{self._description}: no Dask worker joined within {self.worker_timeout:g} s; "
                f"{_no_worker_hint(self.name)}, or raise --worker-timeout") from None

    def describe(self) -> str:
        return self._description

    def _check_store(self, calls: Sequence[Call]) -> None:
        """Refuse a ``memory://`` store when the workers are other processes."""
        store = next((a for a in calls[0].args if process_local_store(a)), None)
        if store is None:
            return
        if self._in_process is None:
            pids = set(self.client.run(os.getpid).values())
            self._in_process = pids == {os.getpid()}
        if not self._in_process:
            raise ExecutorError(
                f"store {store.root} lives in this process's memory, which the workers of "
                f"the {self._description} cannot see; use a directory or an fsspec URL they "
                "share, or --executor sync / local")

    def run(self, calls: Sequence[Call], *, on_done: Callable[[Any], None] | None = None,
            fail_fast: bool = False,
            on_progress: Callable[[dict[str, Any]], None] | None = None) -> dict[int, Any]:
        """Submit each call once its dependencies are done, with their results as arguments.

        Dependencies are resolved here, not through Dask futures: results are tiny
        references, so tasks carry no data locality and the scheduler balances them
        over every worker.  A call whose dependency failed runs here (it only
        records itself as skipped).  ``on_progress`` receives the workers'
        progress events (topic :data:`PROGRESS_TOPIC`, subscribed for the run;
        called on the client's event loop thread).
        """
        if not calls:
            return {}
        self._check_store(calls)
        client = self.client
        if on_progress is None:
            return self._run(client, calls, on_done, fail_fast)
        client.subscribe_topic(PROGRESS_TOPIC, functools.partial(_on_event, on_progress))
        try:
            return self._run(client, calls, on_done, fail_fast)
        finally:
            client.unsubscribe_topic(PROGRESS_TOPIC)

    def _run(self, client: Any, calls: Sequence[Call], on_done: Callable[[Any], None] | None,
             fail_fast: bool) -> dict[int, Any]:
        from distributed import as_completed  # noqa: PLC0415 (heavy)
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
                    res = _failed(call, _error_line(e))
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
        watch = _WorkerWatch(client, self.worker_timeout)
        while running and not stop:
            batch = ac.next_batch(block=False)
            if not batch:
                lost = watch.lost()
                if lost:
                    client.cancel(list(running.values()))
                    for key in list(running):
                        finish(by_key[key], _failed(by_key[key], lost))
                    running.clear()
                    break
                _wait_ready(ac)
                continue
            watch.alive()
            for fut in batch:
                running.pop(fut.key, None)
                finish(by_key[fut.key], _outcome(by_key[fut.key], fut))
                if stop:
                    break
        if stop and running:
            client.cancel(list(running.values()))
        why = "cancelled (--fail-fast)" if stop else "not run: no Dask worker to run it"
        for i, c in by_index.items():
            if i not in results:
                results[i] = _cancelled(c, why)
        return results

    def close(self) -> None:
        if self._closer is not None:
            try:
                self._closer()
            finally:
                self._closer = None
                self._client = None


def dashboard_link(client: Any) -> str | None:
    """The URL of the Dask dashboard of ``client``'s scheduler, or ``None`` if it has none.

    Every scheduler runs an HTTP server (metrics and health routes) and lists it
    as its ``dashboard`` service, so ``client.dashboard_link`` names a port even
    when the dashboard itself is off (``dashboard_address=None``,
    ``--no-dashboard``, or bokeh missing).  A scheduler in this process (a
    local or Slurm cluster) is asked whether it serves the bokeh dashboard; the
    link of a scheduler elsewhere is returned as it is.
    """
    try:
        link = client.dashboard_link
    except (KeyError, AttributeError, OSError):
        return None
    if not link:
        return None
    scheduler = getattr(getattr(client, "cluster", None), "scheduler", None)
    http_app = getattr(scheduler, "http_application", None)
    if http_app is not None and not getattr(http_app, "applications", True):
        return None  # only the scheduler's own routes: no bokeh application
    return str(link)


def _outcome(call: Call, fut: Any) -> Any:
    """What a finished future reports: its result, or the call's failure or cancellation."""
    try:
        if fut.status == "finished":
            return fut.result()
        if fut.status == "cancelled":
            return _cancelled(call)
        return _failed(call, _error_line(fut.exception()))
    finally:
        fut.release()


def _wait_ready(ac: Any, timeout: float = 0.1) -> None:
    """Block until a future of ``ac`` is ready, or ``timeout`` seconds."""
    cond = getattr(ac, "thread_condition", None)
    if cond is None:  # pragma: no cover - other distributed versions
        time.sleep(0.01)
        return
    with cond:
        if not ac.has_ready():
            cond.wait(timeout=timeout)


def _no_worker_hint(kind: str) -> str:
    if kind == "slurm":
        return "see whether the jobs still queue or failed (squeue, the job logs)"
    if kind == "external":
        return "start workers with `dask worker ADDRESS`"
    return "see the cluster's logs (--debug)"


class _WorkerWatch:
    """Notices a cluster left without any worker for longer than ``timeout`` seconds."""

    CHECK_EVERY_S = 1.0

    def __init__(self, client: Any, timeout: float | None) -> None:
        self.client = client
        self.timeout = timeout
        self._checked = self._seen = time.monotonic()

    def alive(self) -> None:
        """A result came back: there are workers."""
        self._seen = time.monotonic()

    def lost(self) -> str | None:
        """The error of tasks left without a worker, or ``None`` while there are workers."""
        now = time.monotonic()
        if self.timeout is None or now - self._checked < self.CHECK_EVERY_S:
            return None
        self._checked = now
        try:
            if self.client.nthreads():
                self._seen = now
                return None
        except Exception:  # pragma: no cover - scheduler gone: counts as no worker
            pass
        if now - self._seen < self.timeout:
            return None
        return (f"no Dask worker for {self.timeout:g} s (the workers died or their jobs "
                "ended); check the cluster, or raise --worker-timeout")


class _KilledWorkerLogFilter(logging.Filter):
    """Drops the scheduler's errors about a worker that died: the task's record says it.

    (``Task … marked as failed because N workers died``, and ``Couldn't gather
    keys`` for results lost with it, which are computed again.)  Kept when the
    ``mocapflow`` logger shows INFO (``--debug``).
    """

    QUIET = ("workers died while trying to run it", "Couldn't gather keys")

    def filter(self, record: logging.LogRecord) -> bool:
        if logging.getLogger("mocapflow").isEnabledFor(logging.INFO):
            return True
        msg = record.getMessage()
        return not any(q in msg for q in self.QUIET)


def _quiet_scheduler_log() -> None:
    log = logging.getLogger("distributed.scheduler")
    if not any(isinstance(f, _KilledWorkerLogFilter) for f in log.filters):
        log.addFilter(_KilledWorkerLogFilter())


def _quiet_worker_logging(driver_pid: int) -> None:
    """Worker set-up: engine log records on stderr, but not the stages' ``ctx.warn``.

    Stage warnings travel back in the task records and the command prints them
    once (:func:`~mocapflow.pipeline.progress.warning_lines`); printed on the
    worker too, every one showed twice.  Workers that are threads of the driver
    keep its logging as it is.
    """
    if os.getpid() == driver_pid:
        return
    log = logging.getLogger("mocapflow")
    if any(getattr(h, "_mocapflow", False) for h in log.handlers):
        return
    h = logging.StreamHandler(sys.stderr)
    h.setFormatter(logging.Formatter("mocapflow worker: %(levelname)s: %(message)s"))
    h.addFilter(StageWarningFilter())
    h._mocapflow = True  # type: ignore[attr-defined]
    log.addHandler(h)
    log.propagate = False


# --------------------------------------------------------------------------- ctx.progress

#: Dask event topic of the tasks' progress updates (``Worker.log_event``).
PROGRESS_TOPIC = "mocapflow-progress"
#: The in-process listener of :class:`SyncExecutor` while it runs (``[callable or None]``).
_LOCAL_LISTENER: list[Callable[[dict[str, Any]], None] | None] = [None]


def _on_event(on_progress: Callable[[dict[str, Any]], None], event: Any) -> None:
    """Client side: one ``(timestamp, message)`` event of :data:`PROGRESS_TOPIC`."""
    try:
        on_progress(event[1])
    except Exception:  # pragma: no cover - a display error must not break the client
        log.debug("progress listener failed", exc_info=True)


def _log_event(worker: Any, message: dict[str, Any]) -> None:
    worker.log_event(PROGRESS_TOPIC, message)


def progress_sink() -> Callable[[dict[str, Any]], None] | None:
    """Where the current task sends its progress updates.

    Returns
    -------
    callable or None
        Inside a ``distributed`` worker: a function that logs the update as a
        Dask event (:data:`PROGRESS_TOPIC`; the scheduler forwards it to a
        client that subscribed, keeps the last few otherwise).  In a
        :class:`SyncExecutor` run: its ``on_progress`` listener.  ``None``
        when nobody listens.
    """
    try:
        from distributed import get_worker  # noqa: PLC0415 (heavy)

        worker = get_worker()
    except (ImportError, ValueError):
        return _LOCAL_LISTENER[0]
    return functools.partial(_log_event, worker)


# --------------------------------------------------------------------------- ctx.map


def _distributed_map(fn: Callable[[Any], Any], items: list[Any], *,
                     on_done: Callable[[int], None] | None = None) -> list[Any]:
    """Submit ``fn`` over ``items`` to the task's cluster; results in item order.

    With ``on_done``, ``on_done(i)`` is called as item ``i`` finishes (in
    completion order), so the task can report progress while it waits; the
    first item that fails stops the wait and its error is raised.
    """
    from distributed import as_completed, worker_client  # noqa: PLC0415 (heavy)

    with worker_client() as client:
        futs = client.map(fn, items, pure=False)
        if on_done is not None:
            index = {fut.key: i for i, fut in enumerate(futs)}
            for fut in as_completed(futs):
                if fut.status != "finished":
                    break  # gather raises its error
                on_done(index[fut.key])
        return client.gather(futs)


def task_mapper() -> Callable[..., list[Any]] | None:
    """The ``ctx.map`` backend for the current task.

    Returns
    -------
    callable or None
        Inside a ``distributed`` worker: ``map(fn, items, *, on_done=None)``,
        which submits the items to the same cluster (seceding from the worker's
        thread pool while it waits), calls ``on_done(i)`` as item ``i``
        finishes, and returns the results in item order.  Elsewhere ``None``:
        the context maps sequentially.
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
    """Options of ``--executor slurm`` (dask-jobqueue ``SLURMCluster``).

    Attributes
    ----------
    queue : str, optional
        Partition (``#SBATCH -p``).
    cores : int
        Cores per job: one single-threaded worker process each.
    memory : str
        Memory per job (``#SBATCH --mem``), e.g. ``"8GB"``.
    walltime : str
        ``HH:MM:SS`` (``#SBATCH -t``).
    jobs : int
        Number of jobs to submit.
    account : str, optional
        ``#SBATCH -A``.
    gres : str, optional
        Generic resources, e.g. ``"gpu:1"`` (``#SBATCH --gres=gpu:1``).
    log_dir : str, optional
        Folder of the jobs' output and error files (dask-jobqueue ``log_directory``).
    job_extra : sequence of str
        Further ``#SBATCH`` directives, e.g. ``"--constraint=avx2"`` (the
        ``#SBATCH`` prefix is optional).
    extra : dict
        Further ``SLURMCluster`` keyword arguments (they win over the above).
    """

    queue: str | None = None
    cores: int = 4
    memory: str = "8GB"
    walltime: str = "01:00:00"
    jobs: int = 1
    account: str | None = None
    gres: str | None = None
    log_dir: str | None = None
    job_extra: Sequence[str] = ()
    extra: dict[str, Any] = field(default_factory=dict)

    def directives(self) -> list[str]:
        """The extra ``#SBATCH`` directives (without the prefix): ``--gres``, then ``job_extra``.

        Raises
        ------
        ExecutorError
            An empty directive, or one that does not start with ``-``.
        """
        out = [f"--gres={self.gres}"] if self.gres else []
        for d in self.job_extra:
            text = d.strip()
            if text.startswith("#SBATCH"):
                text = text[len("#SBATCH"):].strip()
            if not text.startswith("-") or "\n" in text:
                raise ExecutorError(f"--slurm-job-extra {d!r}: expected one sbatch option such "
                                    "as --constraint=avx2 (the #SBATCH prefix is optional)")
            out.append(text)
        return out

    def cluster_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``SLURMCluster``: one single-threaded worker per core.

        Raises
        ------
        ExecutorError
            A bad directive (:meth:`directives`), or a log folder whose path holds
            whitespace (the ``#SBATCH -o``/``-e`` lines are not quoted).
        """
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
        directives = self.directives()
        if directives:
            kw["job_extra_directives"] = directives
        if self.log_dir:
            log_dir = os.path.abspath(os.path.expanduser(self.log_dir))
            if any(c.isspace() for c in log_dir):  # sbatch would split the unquoted #SBATCH -o
                raise ExecutorError(f"--slurm-log-dir {log_dir!r}: the #SBATCH -o/-e lines "
                                    "cannot hold a path with spaces; choose a folder without")
            kw["log_directory"] = log_dir
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


def _local_factory(workers: int, *, processes: bool = True):
    def start():
        from distributed import Client, LocalCluster  # noqa: PLC0415 (heavy)

        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes,
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

        if shutil.which("sbatch") is None:
            raise ExecutorError(
                "--executor slurm: sbatch is not on PATH (run on a Slurm login node or load "
                "its module; --print-job-script shows the job script without Slurm)")
        cluster = _slurm_cluster(opts)
        try:
            cluster.scale(jobs=opts.jobs)
            client = Client(cluster, set_as_default=False)
        except BaseException:
            cluster.close()
            raise

        def closer() -> None:
            client.close()
            cluster.close()

        return client, closer

    return start


def _timeout(kind: str, worker_timeout: float | None) -> float | None:
    """``worker_timeout`` (``0``: wait for ever), else the kind's default."""
    if worker_timeout is None:
        return WORKER_TIMEOUT_S[kind]
    if worker_timeout < 0:
        raise ExecutorError(f"--worker-timeout must be >= 0 seconds, got {worker_timeout:g}")
    return float(worker_timeout) or None


def make_executor(kind: str = "local", *, workers: int | None = None, address: str | None = None,
                  scheduler_file: str | None = None, slurm: SlurmOptions | None = None,
                  client: Any = None, store: Any = None,
                  worker_timeout: float | None = None,
                  on_dashboard: Callable[[str | None], None] | None = None) -> Executor:
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
    store : Store or str, optional
        The store (or its root) the runs will use: a ``memory://`` store makes
        ``local`` run its workers as threads of this process (worker processes
        would each write to a memory of their own) and is refused by an external
        cluster and Slurm.
    worker_timeout : float, optional
        Seconds to wait for a first worker, and the longest a run goes without
        any worker (default :data:`WORKER_TIMEOUT_S` of the kind; ``0``: wait for ever).
    on_dashboard : callable, optional
        Called with the cluster's dashboard URL (``None``: it serves none) when
        a cluster-backed executor starts; ``sync`` never calls it.

    Returns
    -------
    Executor
        Cluster-backed executors start lazily, on the first run that has work.

    Raises
    ------
    ExecutorError
        Bad options, or a ``memory://`` store for workers in other processes.
    """
    local_store = process_local_store(store)
    if client is not None:
        n = len(client.nthreads()) or 1
        return DistributedExecutor(lambda: (client, lambda: None), name="client", workers=n,
                                   description=f"client {client.scheduler.address}",
                                   worker_timeout=_timeout("client", worker_timeout),
                                   in_process=None, on_dashboard=on_dashboard)
    if address or scheduler_file:
        if address and scheduler_file:
            raise ExecutorError("give --address or --scheduler-file, not both")
        where = address or scheduler_file
        if local_store:
            raise ExecutorError(f"--store {store_root(store)} lives in this process's memory; "
                                f"the workers of the cluster at {where} cannot see it: use a "
                                "directory or an fsspec URL they share")
        return DistributedExecutor(_external_factory(address, scheduler_file), name="external",
                                   workers=workers or 1,
                                   description=f"external cluster {where}",
                                   worker_timeout=_timeout("external", worker_timeout),
                                   on_dashboard=on_dashboard)
    if kind == "sync":
        return SyncExecutor()
    if kind == "local":
        n = workers or os.cpu_count() or 1
        if n < 1:
            raise ExecutorError(f"--workers must be at least 1, got {n}")
        what = "worker threads of this process (memory:// store)" if local_store else \
            "worker processes"
        return DistributedExecutor(_local_factory(n, processes=not local_store), name="local",
                                   workers=n, description=f"local cluster, {n} {what}",
                                   worker_timeout=_timeout("local", worker_timeout),
                                   in_process=local_store, on_dashboard=on_dashboard)
    if kind == "slurm":
        if local_store:
            raise ExecutorError(f"--store {store_root(store)} lives in this process's memory; "
                                "Slurm workers cannot see it: use a directory on a shared "
                                "filesystem or an fsspec URL")
        opts = slurm or SlurmOptions()
        return DistributedExecutor(_slurm_factory(opts), name="slurm",
                                   workers=opts.jobs * opts.cores,
                                   description=f"slurm, {opts.jobs} job(s) × {opts.cores} cores",
                                   worker_timeout=_timeout("slurm", worker_timeout),
                                   on_dashboard=on_dashboard)
    raise ExecutorError(f"unknown executor {kind!r} (sync, local or slurm)")


def store_root(store: Any) -> str:
    """The root of a store, or the root given as a string."""
    return str(getattr(store, "root", store))
