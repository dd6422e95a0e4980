"""Run a graph: resolve the plan's hits, execute the rest, record the run, check the lock.

:func:`run` hashes the graph's raw files, plans it (:func:`~mocapflow.pipeline.plan.plan`),
and checks a ``--frozen`` lock before anything runs.  The plan's hits become
task records on the driver (a run with nothing to do never starts a cluster);
every other task becomes one executor :class:`~mocapflow.pipeline.executors.Call`
of :func:`~mocapflow.pipeline.execute.execute_task` with a
:class:`~mocapflow.pipeline.execute.TaskSpec` whose file paths are absolute
(workers may run elsewhere).  Every task ends as a
:class:`~mocapflow.pipeline.execute.TaskRecord` in the run record
``runs/<run_id>.json`` (with the host facts and every task's timings, which
never enter an output); the lock's output digests are compared last.

The pieces live in :mod:`~mocapflow.pipeline.task_keys` (keys),
:mod:`~mocapflow.pipeline.execute` (one task), :mod:`~mocapflow.pipeline.plan`
(plan, explain) and :mod:`~mocapflow.pipeline.lock` (lock files).
"""

from __future__ import annotations

import os
import platform
import socket
import sys
import time
import uuid
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from mocapflow.pipeline import registry
from mocapflow.pipeline.config import filepath_params, resolve_stage
from mocapflow.pipeline.execute import OK, TaskRecord, TaskSpec, execute_task
from mocapflow.pipeline.executors import Call, CallOutcome, Executor, SyncExecutor
from mocapflow.pipeline.graph import Graph, Task
from mocapflow.pipeline.lock import Lock, frozen_postcheck, frozen_precheck
from mocapflow.pipeline.plan import TaskPlan, check_force, paused_gc, plan
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.task_keys import hash_files
from mocapflow.pipeline.wires import Wire

__all__ = ["RunResult", "host_facts", "new_run_id", "run"]

#: Fields of each task in a run record (``traceback`` is ``None`` but for failures;
#: ``timings`` only for computed tasks: ``load``, ``check``, ``compute``, ``encode``,
#: ``commit`` and the stage's ``steps``).
RECORD_FIELDS = ("node", "part", "stage", "key", "components", "status", "seconds", "error",
                 "outputs", "warnings", "traceback", "timings", "figures")


def new_run_id() -> str:
    """``YYYYmmddTHHMMSS-<8 hex>`` (UTC), unique per run."""
    return datetime.now(UTC).strftime("%Y%m%dT%H%M%S") + "-" + uuid.uuid4().hex[:8]


@dataclass
class RunResult:
    """Outcome of :func:`run`.

    Attributes
    ----------
    records : list of TaskRecord
        One task record per task, in task order (see
        :func:`~mocapflow.pipeline.execute.execute_task`).
    frozen_problems : list of str
        ``--frozen``: outputs that differ from the lock.
    """

    run_id: str
    records: list[TaskRecord]
    seconds: float
    executor: str
    frozen_problems: list[str] = field(default_factory=list)

    @property
    def counts(self) -> dict[str, int]:
        """``{"hit", "computed", "failed", "skipped"} -> count``."""
        c = {"hit": 0, "computed": 0, "failed": 0, "skipped": 0}
        for r in self.records:
            c[r.status] = c.get(r.status, 0) + 1
        return c

    @property
    def ok(self) -> bool:
        """Every task is a hit or computed (and the lock matched)."""
        return all(r.status in OK for r in self.records) and not self.frozen_problems

    def failed(self) -> list[TaskRecord]:
        """Records of failed tasks."""
        return [r for r in self.records if r.status == "failed"]

    def digests(self) -> dict[tuple[str, str | None], dict[str, str] | None]:
        """``(node, part) -> {output: digest}``."""
        return {(r.node, r.part): r.outputs for r in self.records}


def run(graph: Graph, store: Store, *, executor: Executor | None = None,
        force: Iterable[str] = (), fail_fast: bool = False,
        lock: Lock | None = None,
        progress: Any = None, run_id: str | None = None,
        command: Sequence[str] | None = None) -> RunResult:
    """Run a graph: plan hits are resolved here, the rest go to the executor.

    Parameters
    ----------
    graph : Graph
    store : Store
    executor : Executor, optional
        Default :class:`~mocapflow.pipeline.executors.SyncExecutor`.
    force : iterable of str
        Nodes to recompute even when cached.
    fail_fast : bool
        Cancel what has not started after the first failure.
    lock : dict, optional
        From :func:`~mocapflow.pipeline.lock.read_lock`: run ``--frozen`` (raise
        :class:`~mocapflow.pipeline.lock.FrozenError` before running anything when
        a key already differs; tasks whose key turns out different fail without
        running; digests are compared after).
    progress : Progress, optional
        Gets ``update(record dict)`` per finished task and ``close()``; if it
        has ``task_progress``, also the running tasks' ``ctx.progress`` updates
        (``task_progress(message)``, possibly from another thread).
    run_id : str, optional
    command : sequence of str, optional
        Recorded in the run record.

    Returns
    -------
    RunResult
        The run record is also written to the store (``runs/<run_id>.json``).
    """
    executor = executor or SyncExecutor()
    run_id = run_id or new_run_id()
    started = time.time()
    t0 = time.perf_counter()
    force = check_force(graph, force)
    files = hash_files(graph, store)
    plans = plan(graph, store, force=force, file_digests=files, reasons=False)
    if lock is not None:
        frozen_precheck(plans, lock)
    known = _hit_records(plans, progress)
    records = dict(known)
    todo = [t for t in graph.tasks if t.index not in known]
    if todo:
        todo_idx = {t.index for t in todo}
        calls = [_call(t, todo_idx, known, store, files, run_id, force, lock, executor.workers)
                 for t in todo]
        records.update(_execute(graph, todo, calls, executor, fail_fast, progress, run_id))
    if progress is not None:
        progress.close()
    ordered = [records[t.index] for t in graph.tasks]
    result = RunResult(run_id=run_id, records=ordered, seconds=time.perf_counter() - t0,
                       executor=executor.describe())
    if lock is not None:
        result.frozen_problems = frozen_postcheck(ordered, lock)
    with paused_gc():  # a record per task: many objects, no cycles
        store.write_run(run_id, _run_record(graph, result, command, started))
    return result


@paused_gc()  # a record per hit: many objects, no cycles
def _hit_records(plans: Sequence[TaskPlan], progress: Any) -> dict[int, TaskRecord]:
    """Records of the tasks the plan found committed (reported to ``progress`` at once)."""
    known: dict[int, TaskRecord] = {}
    for p in plans:
        if p.status == "hit":
            rec = TaskRecord(index=p.index, node=p.node, part=p.part, stage=p.stage,
                             status="hit", key=p.key, components=p.components,
                             outputs=p.outputs)
            known[p.index] = rec
            if progress is not None:  # (what it reads of a hit; no full record per hit)
                progress.update({"status": "hit", "node": p.node, "part": p.part})
    return known


def _call(t: Task, todo_idx: set[int], known: Mapping[int, TaskRecord], store: Store,
          files: Mapping[str, str | None], run_id: str, force: set[str], lock: Lock | None,
          workers: int) -> Call:
    """The executor call of one task that is not a plan hit.

    Its dependencies on other calls are ``deps``; the records of upstream plan
    hits travel in its arguments (``known``).
    """
    sspec = resolve_stage(t.stage)
    deps = tuple(d for d in t.deps() if d in todo_idx)
    kn = {d: known[d] for d in t.deps() if d in known}
    expected = lock.get((t.node, t.part)) if lock is not None else None
    inputs, params, fdig = _absolute_files(t, sspec, files)
    spec = TaskSpec(index=t.index, node=t.node, part=t.part, stage=t.stage,
                    module=sspec.module, params=params, inputs=inputs, deps=deps,
                    file_digests=fdig, run_id=run_id, seed=t.seed, force=t.node in force,
                    workers=workers, expected=expected)
    return Call(index=t.index, key=f"{t.node}-{t.index}-{run_id}", fn=execute_task,
                args=(store, spec, kn), deps=deps, node=t.node, part=t.part)


def _execute(graph: Graph, todo: Sequence[Task], calls: Sequence[Call], executor: Executor,
             fail_fast: bool, progress: Any, run_id: str) -> dict[int, TaskRecord]:
    """Run the calls on the executor; every task of ``todo`` gets a record."""

    def on_done(res: TaskRecord | CallOutcome) -> None:
        if progress is not None:
            progress.update(_as_record(graph.tasks[res.index], res).as_dict())

    inner = getattr(progress, "task_progress", None)
    kw: dict[str, Any] = {}
    if inner is not None:
        def on_progress(message: dict[str, Any]) -> None:
            if message.get("run") == run_id:  # (a shared cluster runs others' tasks too)
                inner(message)

        kw["on_progress"] = on_progress
    results = executor.run(calls, on_done=on_done, fail_fast=fail_fast, **kw)
    return {t.index: _as_record(t, results.get(t.index)) for t in todo}


def _as_record(t: Task, res: TaskRecord | CallOutcome | None) -> TaskRecord:
    """The task's record: what it returned, or what the executor says of a call it lost."""
    if isinstance(res, TaskRecord):
        return res
    status, error = ("skipped", "not run") if res is None else (res.status, res.error)
    return TaskRecord(index=t.index, node=t.node, part=t.part, stage=t.stage, status=status,
                      error=error)


def _run_record(graph: Graph, result: RunResult, command: Sequence[str] | None,
                started: float) -> dict[str, Any]:
    """The run record written to ``runs/<run_id>.json``."""
    return {
        "run_id": result.run_id,
        "graph": graph.config.name,
        "config": str(Path(graph.config.path).resolve()) if graph.config.path else None,
        "targets": list(graph.targets),
        "overrides": graph.config.overrides,
        "command": list(command) if command is not None else None,
        "executor": result.executor,
        "host": host_facts(),
        "started_at": started,
        "finished_at": time.time(),
        "seconds": result.seconds,
        "counts": result.counts,
        "frozen_problems": result.frozen_problems,
        "tasks": [_task_record(r) for r in result.records],
    }


#: Fields a hit's record leaves out: its components are in its entry's manifest
#: (the key names it), and it has no error, traceback or timings.  A no-op run of
#: 30,001 tasks writes a 7 MB record in 0.15 s, not 21 MB in 0.45 s.
_HIT_OMITS = frozenset({"components", "error", "traceback", "timings"})


def _task_record(r: TaskRecord) -> dict[str, Any]:
    """One task of the run record (:data:`RECORD_FIELDS`; a hit's without :data:`_HIT_OMITS`)."""
    d = r.as_dict()
    if r.status == "hit":
        return {k: d.get(k) for k in RECORD_FIELDS if k not in _HIT_OMITS}
    return {k: d.get(k) for k in RECORD_FIELDS}


def host_facts() -> dict[str, Any]:
    """Where a run happened (run records only: never in a key or an output)."""
    return {"hostname": socket.gethostname(), "pid": os.getpid(), "cwd": os.getcwd(),
            "platform": platform.platform(), "python": sys.version.split()[0],
            "cpus": os.cpu_count()}


def _absolute_files(t: Task, sspec: registry.StageSpec, files: Mapping[str, str | None]
                    ) -> tuple[dict[str, Wire], dict[str, Any], dict[str, str | None]]:
    """Inputs and params with absolute file paths (workers may run elsewhere), and digests.

    Keys do not change: files enter them by content digest, parts by their id.
    """
    digests: dict[str, str | None] = {}

    def absolute(path: str) -> str:
        a = os.path.abspath(path)
        digests[a] = files.get(path)
        return a

    inputs = {name: w.with_paths(absolute) for name, w in t.inputs.items()}
    params = dict(t.params)
    for p in filepath_params(sspec):
        if params.get(p) is not None:
            params[p] = absolute(str(params[p]))
    return inputs, params, digests
