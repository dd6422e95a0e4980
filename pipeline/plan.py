"""Plan and explain: which tasks are cache hits, and why the others would run.

:func:`plan` computes every task's key without running anything: a task whose
upstream tasks are all hits has a known key (a hit if its entry is committed);
a task below one that will recompute is *pending* (its key depends on outputs
not computed yet, and may still turn out a hit by early cutoff).  Reasons
compare a task's key components with its last run record (``param x: 1 -> 2``,
``input y changed``, ``code of stage z changed``).  :func:`explain` does the same
for the tasks of one ``NODE[/PART]``, :func:`task_status` says which tasks are
up to date and how they last ran, and :func:`gc_keep_set` names the entries
``gc --keep-config`` / ``--keep-runs`` keep.
"""

from __future__ import annotations

import contextlib
import difflib
import gc
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from mocapflow.pipeline import keys
from mocapflow.pipeline.config import CMDLINE, ConfigError, filepath_params, resolve_stage
from mocapflow.pipeline.execute import OK, manifest_digests
from mocapflow.pipeline.graph import Graph, Task
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.task_keys import (
    compute_key,
    hash_files,
    key_inputs,
    key_params,
    stage_fingerprint,
)

__all__ = [
    "TaskPlan",
    "check_force",
    "explain",
    "gc_keep_set",
    "last_components",
    "last_records",
    "plan",
    "task_status",
]


@dataclass
class TaskPlan:
    """What :func:`plan` predicts for one task.

    Attributes
    ----------
    status : {"hit", "compute", "pending"}
        ``pending``: an upstream task will recompute, so the key is not known
        yet (it may still turn out a hit by early cutoff).
    reason : str
        ``"hit"``, ``"no entry for key …"``, ``"param x: 1 -> 2"``, ``"input y changed …"``,
        ``"upstream n/p will recompute"``, ``"forced (--force)"``, ``"input file not found …"``.
    """

    index: int
    node: str
    part: str | None
    stage: str
    status: str
    reason: str
    key: str | None = None
    components: dict | None = None
    outputs: dict[str, str] | None = None
    changes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        """JSON form."""
        return {"node": self.node, "part": self.part, "stage": self.stage,
                "status": self.status, "reason": self.reason, "key": self.key,
                "changes": self.changes}


def last_records(store: Store, *, statuses: Iterable[str] | None = OK
                 ) -> dict[tuple[str, str | None], dict]:
    """The most recent task record of every (node, part) over all runs, in one pass.

    Parameters
    ----------
    statuses : iterable of str, optional
        Only records with these statuses (default hit/computed; ``None``: any).

    Returns
    -------
    dict
        ``(node, part) -> task record`` (with ``run_id``).
    """
    wanted = set(statuses) if statuses is not None else None
    out: dict[tuple[str, str | None], dict] = {}
    for rec in store.runs():  # oldest first: later runs overwrite
        for task in rec.get("tasks") or []:
            if not isinstance(task, dict) or (wanted is not None
                                              and task.get("status") not in wanted):
                continue
            out[(task.get("node"), task.get("part"))] = {**task, "run_id": rec.get("run_id")}
    return out


def check_force(graph: Graph, force: Iterable[str]) -> set[str]:
    """The ``--force`` nodes as a set (each must be a node of the config)."""
    force = set(force or ())
    unknown = sorted(force - set(graph.config.nodes))
    if unknown:
        close = difflib.get_close_matches(unknown[0], list(graph.config.nodes), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ConfigError(f"unknown node {unknown[0]!r}{hint}", file=CMDLINE, key="--force")
    return force


@contextlib.contextmanager
def paused_gc() -> Iterator[None]:
    """Pause Python's cyclic garbage collector (a context manager and decorator).

    For the driver's bookkeeping of many tasks (plans, run records): a plan of
    30,001 tasks allocates about a million small objects, with no cycles, that
    all survive it; the collector would scan the growing heap again and again
    (0.3 s, a tenth of a no-op run).
    """
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


@paused_gc()
def plan(graph: Graph, store: Store, *, force: Iterable[str] = (),
         file_digests: Mapping[str, str | None] | None = None,
         reasons: bool = True) -> list[TaskPlan]:
    """Predict, without running anything, which tasks are hits and why others would run.

    Parameters
    ----------
    graph : Graph
    store : Store
    force : iterable of str
        Nodes to recompute regardless of the cache.
    file_digests : dict, optional
        From :func:`~mocapflow.pipeline.task_keys.hash_files` (computed when not given).
    reasons : bool
        Compare tasks that will compute with their last run record (slower).

    Returns
    -------
    list of TaskPlan
        In task order.
    """
    force = check_force(graph, force)
    if file_digests is None:
        file_digests = hash_files(graph, store)
    out: list[TaskPlan] = []
    history: dict[tuple[str, str | None], dict] | None = None
    for t in graph.tasks:
        tp = TaskPlan(index=t.index, node=t.node, part=t.part, stage=t.stage, status="compute",
                      reason="")
        out.append(tp)
        if not _plan_key(tp, t, out, file_digests):
            continue
        if t.node in force:
            tp.reason = "forced (--force)"
            continue
        man = store.manifest(t.stage, tp.key)
        if man is not None:
            tp.status, tp.reason, tp.outputs = "hit", "hit", manifest_digests(man)
            continue
        tp.reason = f"no entry for key {tp.key[:12]}…"
        if reasons:
            if history is None:
                history = last_records(store)
            last = history.get((t.node, t.part))
            last_comps = last_components(store, last)
            if last_comps and last.get("key") != tp.key:
                tp.changes = keys.diff_components(last_comps, tp.components)
                if tp.changes:
                    tp.reason = "; ".join(tp.changes)
    return out


def _plan_key(tp: TaskPlan, t: Task, planned: list[TaskPlan],
              file_digests: Mapping[str, str | None]) -> bool:
    """Fill ``tp.key`` and ``tp.components`` if known now; else False (``tp.reason`` says why).

    Upstream digests come from the plans before it (``planned``): known for
    upstream hits, unknown (``pending``) below a task that will recompute.
    """
    sspec = resolve_stage(t.stage)

    def upstream(i: int, o: str) -> str | None:
        p = planned[i]
        return p.outputs.get(o) if p.outputs is not None else None

    try:
        inputs, kinds, pending = key_inputs(t.inputs, file_digests, upstream)
    except FileNotFoundError as e:
        tp.reason = str(e)
        return False
    if pending:
        ups = [planned[i] for i in t.deps() if planned[i].outputs is None]
        tp.status = "pending"
        tp.reason = (f"upstream {ups[0].node}" + (f"/{ups[0].part}" if ups[0].part else "")
                     + " will recompute") if ups else "upstream will recompute"
        return False
    try:
        tp.key, tp.components = compute_key(sspec, params=t.params, part=t.part,
                                            inputs=inputs, kinds=kinds,
                                            file_digests=file_digests)
    except FileNotFoundError as e:
        tp.reason = str(e)
        return False
    return True


def explain(graph: Graph, store: Store, target: str) -> list[dict[str, Any]]:
    """Which key components changed since the last committed run of ``NODE[/PART]``.

    Returns
    -------
    list of dict
        One per task: ``node, part, status, key, last_key, last_run, changes``
        (``changes`` is a list of sentences, empty when nothing changed).

    Raises
    ------
    KeyError
        Unknown node or part (message names the candidates).
    """
    tasks = graph.find(target)
    files = hash_files(graph, store)
    plans = plan(graph, store, reasons=False, file_digests=files)
    history = last_records(store)
    out = []
    for t in tasks:
        p = plans[t.index]
        last = history.get((t.node, t.part))
        item: dict[str, Any] = {"node": t.node, "part": t.part, "status": p.status,
                                "key": p.key, "last_key": last.get("key") if last else None,
                                "last_run": last.get("run_id") if last else None}
        item["changes"] = _changes(t, p, last, last_components(store, last), files)
        out.append(item)
    return out


def last_components(store: Store, last: dict | None) -> dict | None:
    """The key components of a task record: its own, or (a hit's) its entry manifest's."""
    if not last:
        return None
    comps = last.get("components")
    if comps is None and last.get("stage") and last.get("key"):
        man = store.manifest(str(last["stage"]), str(last["key"]))
        comps = man.get("components") if man else None
    return comps if isinstance(comps, dict) else None


def _changes(t: Task, p: TaskPlan, last: dict | None, last_comps: dict | None,
             files: Mapping[str, str | None]) -> list[str]:
    """What changed in the key components of ``t`` since its ``last`` committed record.

    ``last_comps``: that record's components (:func:`last_components`).
    """
    if p.components is None:
        changes = [p.reason]
        if last_comps and p.status == "pending":
            # compare what is known: everything but the pending inputs
            sspec = resolve_stage(t.stage)
            cur = dict(last_comps)
            cur["params"] = key_params(t.params, filepath_params(sspec), files)
            cur["code"] = stage_fingerprint(sspec)
            cur["versions"] = keys.package_versions()
            changes = [p.reason] + keys.diff_components(last_comps, cur)
        return changes
    if last is None:
        return ["no previous run of this task"]
    if last.get("key") == p.key:
        return []
    return keys.diff_components(last_comps, p.components)


def task_status(graph: Graph, store: Store) -> list[dict[str, Any]]:
    """Every task of the graph: up to date now, and how its last run went (``mocapflow status``).

    Returns
    -------
    list of dict
        In task order: ``node, part, stage, status`` (of the last run record,
        ``None`` if never run), ``up_to_date`` (a hit now), ``key`` (now, else the
        last run's), ``seconds, error, last_run``.
    """
    plans = plan(graph, store, reasons=False)
    history = last_records(store, statuses=None)
    rows = []
    for p in plans:
        last = history.get((p.node, p.part))
        rows.append({
            "node": p.node, "part": p.part, "stage": p.stage,
            "status": last.get("status") if last else None,
            "up_to_date": p.status == "hit",
            "key": p.key if p.key is not None else (last.get("key") if last else None),
            "seconds": last.get("seconds") if last else None,
            "error": last.get("error") if last else None,
            "last_run": last.get("run_id") if last else None,
        })
    return rows


def gc_keep_set(store: Store, graphs: Iterable[Graph] = (), *, last_runs: int | None = None
                ) -> set[tuple[str, str]]:
    """The entries ``gc`` keeps: the graphs' current entries and those of the last runs.

    Parameters
    ----------
    store : Store
    graphs : iterable of Graph
        Every task of these graphs whose key is known now (:func:`plan`) is kept
        (load them with ``all_nodes=True`` to keep every node's entries).
    last_runs : int, optional
        Also keep every entry recorded by the last ``last_runs`` run records
        (``0``: none).

    Returns
    -------
    set of (stage, key)
        Pass it as ``Store.gc(keep=...)``.
    """
    keep: set[tuple[str, str]] = set()
    for graph in graphs:
        for p in plan(graph, store, reasons=False):
            if p.key is not None:
                keep.add((p.stage, p.key))
    if last_runs is not None:
        runs = store.runs()
        for rec in runs[-last_runs:] if last_runs > 0 else []:
            for t in rec.get("tasks") or []:
                if t.get("key") and t.get("stage"):
                    keep.add((t["stage"], t["key"]))
    return keep
