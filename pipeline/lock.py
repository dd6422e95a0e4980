"""Lock files: the key and output digests of every task, so a build can prove it is reproduced.

``mocapflow lock`` runs a graph and writes :func:`lock_document` (JSON, or YAML
for a ``.yaml`` / ``.yml`` name; default ``<config stem>.lock.json`` next to the
config).  ``mocapflow run --frozen`` reads it back (:func:`read_lock`) and
checks the run against it: before anything runs (:func:`frozen_precheck`: every
task is locked, and every key known now matches), in each task (a key that turns
out different fails the task without running it), and after the run
(:func:`frozen_postcheck`: output digests).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import yaml

from mocapflow.pipeline import keys
from mocapflow.pipeline.execute import OK, TaskRecord
from mocapflow.pipeline.graph import Graph, task_name
from mocapflow.pipeline.plan import TaskPlan

__all__ = [
    "LOCK_FORMAT",
    "FrozenError",
    "default_lock_path",
    "frozen_postcheck",
    "frozen_precheck",
    "lock_document",
    "read_lock",
    "write_lock",
]

LOCK_FORMAT = 1

#: A read lock: ``(node, part) -> locked task``.
Lock = Mapping[tuple[str, str | None], dict]


class FrozenError(ValueError):
    """``run --frozen``: a key or output digest differs from the lock file."""


def default_lock_path(config_path: str | os.PathLike) -> Path:
    """``<config stem>.lock.json`` next to the config (a shipped graph given by name,
    ``texture``: ``./texture.lock.json`` in the working directory)."""
    p = Path(config_path)
    return p.with_name(p.stem + ".lock.json")


def lock_document(graph: Graph, records: Sequence[TaskRecord]) -> dict[str, Any]:
    """A lock of every task's key, components and output digests.

    Raises
    ------
    FrozenError
        If a task has no committed result (it failed or was skipped).
    """
    bad = [r for r in records if r.status not in OK]
    if bad:
        r = bad[0]
        raise FrozenError(f"cannot lock: {r.node}" + (f"/{r.part}" if r.part else "")
                          + f" {r.status}: {r.error}")
    tasks = [{"node": r.node, "part": r.part, "stage": r.stage, "key": r.key,
              "outputs": r.outputs, "components": r.components} for r in records]
    return {
        "mocapflow_lock": LOCK_FORMAT,
        "graph": graph.config.name,
        "config": str(graph.config.path),
        "targets": list(graph.targets),
        "overrides": graph.config.overrides,
        "parts": list(graph.config.parts),
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "tasks": tasks,
    }


def write_lock(path: str | os.PathLike, doc: Mapping[str, Any]) -> Path:
    """Write a lock document (JSON, or YAML when the name ends in .yaml/.yml)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix in (".yaml", ".yml"):
        text = yaml.safe_dump(json.loads(json.dumps(doc)), sort_keys=False)
    else:
        text = json.dumps(doc, indent=1, sort_keys=False) + "\n"
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)
    return path


def read_lock(path: str | os.PathLike) -> dict[tuple[str, str | None], dict]:
    """Read a lock file into ``{(node, part): task}``.

    Raises
    ------
    FrozenError
        Missing or malformed lock file.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FrozenError(f"{path}: lock file not found (run `mocapflow lock` first)") from None
    try:
        if path.suffix in (".yaml", ".yml"):
            doc = yaml.safe_load(text)
        else:
            doc = json.loads(text)
    except ValueError as e:
        raise FrozenError(f"{path}: malformed lock file ({e})") from None
    if not isinstance(doc, dict) or doc.get("mocapflow_lock") != LOCK_FORMAT:
        raise FrozenError(f"{path}: not a mocapflow lock file (format {LOCK_FORMAT})")
    return {(t["node"], t.get("part")): t for t in doc.get("tasks", [])}


def frozen_precheck(plans: Sequence[TaskPlan], lock: Lock) -> None:
    """Before a ``--frozen`` run: every task is locked and every key known now matches.

    Raises
    ------
    FrozenError
        Naming the first problem (and how many more there are).
    """
    problems = []
    for p in plans:
        want = lock.get((p.node, p.part))
        if want is None:
            problems.append(f"{task_name(p.node, p.part)}: not in the lock file")
        elif p.key is not None and p.key != want["key"]:
            why = "; ".join(keys.diff_components(want.get("components"), p.components or {}))
            problems.append(f"{task_name(p.node, p.part)}: key differs from the lock ({why})")
        elif p.status == "compute" and p.key is None:
            problems.append(f"{task_name(p.node, p.part)}: {p.reason}")
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise FrozenError(f"frozen: {problems[0]}{more}")


def frozen_postcheck(records: Sequence[TaskRecord], lock: Lock) -> list[str]:
    """After a ``--frozen`` run: committed tasks whose key or output digests differ."""
    problems = []
    for r in records:
        want = lock.get((r.node, r.part))
        if want is None or r.status not in OK:
            continue
        name = task_name(r.node, r.part)
        if r.key != want["key"]:
            problems.append(f"{name}: key differs from the lock")
        elif r.outputs != want["outputs"]:
            diff = sorted(o for o in set(r.outputs) | set(want["outputs"])
                          if r.outputs.get(o) != want["outputs"].get(o))
            problems.append(f"{name}: output {', '.join(diff)} digest differs from the lock")
    return problems
