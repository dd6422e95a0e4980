"""Plan and run a graph: cache keys, cache checks, stage calls, commits, run records, locks.

Each (node, part) is one task.  :func:`execute_task` (module-level, picklable)
runs on whatever executor the run uses: it computes the task's key from the
stage identity, its code fingerprint (or version pin), the validated params, the
part id, the *output digests* of its upstream tasks / the content digests of its
raw files, and the versions of result-changing packages; returns at once on a
committed entry (a hit); otherwise loads its inputs from the store, calls the
stage, encodes and commits the outputs with a manifest and returns a small
reference ``{stage, key, outputs: {name: digest}, status, ...}``.  Because keys
use output digests, an upstream change that leaves an output identical leaves
everything downstream a hit (early cutoff).

:func:`plan` computes, without running anything, which tasks are hits and why
the others would run.  :func:`run` resolves the plan's hits on the driver (a run
with nothing to do never starts a cluster), submits the rest, records every task
in a run record under ``runs/`` and checks a lock file for ``--frozen`` builds.
"""

from __future__ import annotations

import importlib
import json
import os
import socket
import time
import traceback
import uuid
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from mocapflow.pipeline import codecs, fingerprint, keys, registry
from mocapflow.pipeline.config import ConfigError, filepath_params
from mocapflow.pipeline.config import resolve_stage as find_stage
from mocapflow.pipeline.context import Context
from mocapflow.pipeline.executors import Call, Executor, SyncExecutor, task_mapper
from mocapflow.pipeline.graph import Graph, Task
from mocapflow.pipeline.store import Store

__all__ = [
    "FrozenError",
    "LOCK_FORMAT",
    "RunResult",
    "TaskPlan",
    "TaskSpec",
    "default_lock_path",
    "execute_task",
    "explain",
    "last_records",
    "lock_document",
    "new_run_id",
    "plan",
    "read_lock",
    "run",
    "stage_fingerprint",
    "write_lock",
]

LOCK_FORMAT = 1
OK = ("hit", "computed")


class FrozenError(ValueError):
    """``run --frozen``: a key or output digest differs from the lock file."""


def new_run_id() -> str:
    """``YYYYmmddTHHMMSS-<8 hex>`` (UTC), unique per run."""
    return datetime.now(UTC).strftime("%Y%m%dT%H%M%S") + "-" + uuid.uuid4().hex[:8]


def stage_fingerprint(spec: registry.StageSpec) -> str:
    """``"pin:<version>"`` for a pinned stage, else the fingerprint of the code it reaches.

    :func:`~mocapflow.pipeline.fingerprint.code_fingerprint` of the stage function:
    every definition its source statically reaches.  In-project modules are those
    of the top-level package of the stage's module
    (``mocapflow`` for the built-in families).  The engine's own modules are left
    out: a stage imports ``mocapflow.pipeline`` for its decorator and context, and
    an engine edit must not invalidate every entry.  Engine changes that alter what
    a stage computes (RNG seeding, output encoding) bump ``keys.KEY_FORMAT``.
    """
    if spec.version is not None:
        return f"pin:{spec.version}"
    return fingerprint.code_fingerprint(
        f"{spec.module}:{spec.func.__qualname__}",
        package=spec.module.split(".", 1)[0],
        exclude=("mocapflow.pipeline",),
    )


def resolve_stage(name: str, module: str) -> registry.StageSpec:
    """Find a stage in this process (for workers: import its module, discover only if needed)."""
    try:
        mod = importlib.import_module(module) if module else None
    except ImportError:
        mod = None
    for obj in vars(mod).values() if mod is not None else ():
        spec = getattr(obj, "__mocapflow_stage__", None)
        if isinstance(spec, registry.StageSpec) and spec.name == name:
            return spec
    return find_stage(name)


# --------------------------------------------------------------------------- keys


def _key_inputs(inputs: Mapping[str, tuple], file_digests: Mapping[str, str | None],
                upstream: Callable[[int, str], str | None]) -> tuple[dict, dict, list[str]]:
    """(input digests, input kinds, names of inputs whose digest is not known yet)."""
    digests: dict[str, Any] = {}
    kinds: dict[str, str] = {}
    pending: list[str] = []

    def fdig(path: str) -> str:
        d = file_digests.get(path)
        if d is None:
            raise FileNotFoundError(f"input file not found: {path}")
        return d

    for name, w in inputs.items():
        if w[0] == "file":
            digests[name], kinds[name] = fdig(w[1]), "file"
        elif w[0] == "files":
            digests[name], kinds[name] = [fdig(p) for p in w[1]], "file"
        elif w[0] == "task":
            d = upstream(w[1], w[2])
            kinds[name] = "upstream"
            if d is None:
                pending.append(name)
            digests[name] = d
        else:
            ds = [upstream(i, o) for i, o in w[1]]
            kinds[name] = "upstream"
            if any(d is None for d in ds):
                pending.append(name)
            digests[name] = ds
    return digests, kinds, pending


def _key_params(params: Mapping[str, Any], file_params: Sequence[str],
                file_digests: Mapping[str, str | None]) -> dict[str, Any]:
    """Params for the key: ``FilePath`` params are replaced by their content digest."""
    out = dict(params)
    for p in file_params:
        v = out.get(p)
        if v is not None:
            d = file_digests.get(str(v))
            if d is None:
                raise FileNotFoundError(f"param {p}: file not found: {v}")
            out[p] = {"file": d}
    return out


def compute_key(spec: registry.StageSpec, *, params: Mapping[str, Any], part: str | None,
                inputs: Mapping[str, Any], kinds: Mapping[str, str],
                file_digests: Mapping[str, str | None]) -> tuple[str, dict]:
    """Key and components of a task (identical on the driver and in workers)."""
    return keys.task_key(
        stage=spec.name,
        fingerprint=stage_fingerprint(spec),
        params=_key_params(params, filepath_params(spec), file_digests),
        part=part,
        inputs=inputs,
        versions=keys.package_versions(),
        input_kinds=kinds,
    )


def hash_files(graph: Graph, store: Store) -> dict[str, str | None]:
    """Content digests of every raw file the graph reads (memoised in the store).

    Returns
    -------
    dict
        ``path -> digest`` (``None`` for a file that cannot be read; the task
        reading it fails with that reason).
    """
    paths: list[str] = []
    for t in graph.tasks:
        paths.extend(t.files())
        for p in filepath_params(find_stage(t.stage)):
            if t.params.get(p) is not None:
                paths.append(str(t.params[p]))
    memo = store.load_file_memo()
    before = dict(memo)
    out: dict[str, str | None] = {}
    for p in dict.fromkeys(paths):
        try:
            out[p] = keys.file_digest(p, memo)
        except OSError:
            out[p] = None
    if memo != before:
        try:
            store.save_file_memo({k: v for k, v in memo.items() if before.get(k) != v})
        except OSError:
            pass
    return out


# --------------------------------------------------------------------------- task spec


@dataclass(frozen=True)
class TaskSpec:
    """Everything a worker needs to run one (node, part); small and picklable.

    ``inputs`` wires refer to graph task indices; ``deps`` lists the indices whose
    references are passed positionally after ``known`` to :func:`execute_task`.
    """

    index: int
    node: str
    part: str | None
    stage: str
    module: str
    params: dict[str, Any]
    inputs: dict[str, tuple]
    deps: tuple[int, ...]
    file_digests: dict[str, str | None]
    run_id: str
    seed: int = 0
    force: bool = False
    workers: int = 1
    expected: dict[str, Any] | None = None


def _record(spec: TaskSpec, status: str, **kw: Any) -> dict[str, Any]:
    rec = {
        "index": spec.index,
        "node": spec.node,
        "part": spec.part,
        "stage": spec.stage,
        "key": None,
        "components": None,
        "status": status,
        "seconds": 0.0,
        "error": None,
        "outputs": None,
        "warnings": [],
    }
    rec.update(kw)
    return rec


def _error_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    msg = text[0] if text else ""
    return f"{type(e).__name__}: {msg}" if msg else type(e).__name__


def _decode(enc: codecs.Encoded) -> Any:
    try:
        return codecs.decode(enc)
    except TypeError:  # a domain type whose family is not imported in this worker yet
        registry.discover()
        return codecs.decode(enc)


def _load_input(store: Store, wire: tuple, refs: Mapping[int, dict]) -> Any:
    kind = wire[0]
    if kind == "file":
        return wire[1]
    if kind == "files":
        return list(wire[1])
    if kind == "task":
        ref = refs[wire[1]]
        return _decode(store.load(ref["stage"], ref["key"], wire[2]))
    return [_decode(store.load(refs[i]["stage"], refs[i]["key"], o)) for i, o in wire[1]]


def _upstream_keys(inputs: Mapping[str, tuple], refs: Mapping[int, dict]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, w in inputs.items():
        if w[0] == "task":
            r = refs[w[1]]
            out[name] = f"{r['stage']}/{r['key']}"
        elif w[0] == "tasks":
            out[name] = [f"{refs[i]['stage']}/{refs[i]['key']}" for i, _ in w[1]]
        elif w[0] == "file":
            out[name] = f"file:{w[1]}"
        else:
            out[name] = [f"file:{p}" for p in w[1]]
    return out


def _manifest_digests(man: Mapping[str, Any]) -> dict[str, str]:
    return {k: (v["digest"] if isinstance(v, dict) else v) for k, v in man["outputs"].items()}


def execute_task(store: Store, spec: TaskSpec, known: Mapping[int, dict], *dep_refs: dict
                 ) -> dict[str, Any]:
    """Run one (node, part): key → cache check → load inputs → stage → commit.

    Parameters
    ----------
    store : Store
    spec : TaskSpec
    known : dict
        References of upstream tasks resolved before submission (plan hits).
    *dep_refs : dict
        References of the upstream tasks in ``spec.deps`` (results of other tasks).

    Returns
    -------
    dict
        The task record: ``node, part, stage, key, components, status
        (hit|computed|failed|skipped), seconds, error, outputs {name: digest},
        warnings`` (+ ``traceback`` for a failure).  Never raises for stage errors.
    """
    t0 = time.perf_counter()
    refs = dict(known)
    refs.update(zip(spec.deps, dep_refs))
    for i in sorted({*spec.deps, *known}):
        r = refs.get(i) or {"node": "?", "part": None, "status": "missing"}
        if r.get("status") not in OK:
            up = _name(str(r.get("node")), r.get("part"))
            return _record(spec, "skipped", error=f"upstream {up} {r.get('status')}",
                           seconds=time.perf_counter() - t0)
    try:
        sspec = resolve_stage(spec.stage, spec.module)
        inputs, kinds, _ = _key_inputs(
            spec.inputs, spec.file_digests, lambda i, o: refs[i]["outputs"][o])
        key, comps = compute_key(sspec, params=spec.params, part=spec.part, inputs=inputs,
                                 kinds=kinds, file_digests=spec.file_digests)
    except Exception as e:
        return _record(spec, "failed", error=_error_line(e), traceback=traceback.format_exc(),
                       seconds=time.perf_counter() - t0)
    base = {"key": key, "components": comps}
    exp = spec.expected
    if exp is not None and exp.get("key") != key:
        why = "; ".join(keys.diff_components(exp.get("components"), comps)) or "key differs"
        return _record(spec, "failed", error=f"frozen: key differs from the lock ({why})",
                       seconds=time.perf_counter() - t0, **base)
    man = store.manifest(spec.stage, key)
    if man is not None and not spec.force:
        return _record(spec, "hit", outputs=_manifest_digests(man),
                       seconds=time.perf_counter() - t0, **base)

    attempts = 1 + max(0, int(sspec.retries))
    last_exc: BaseException | None = None
    tb = ""
    for attempt in range(1, attempts + 1):
        try:
            return _compute(store, spec, sspec, refs, key, comps, man, attempt, t0)
        except Exception as e:  # noqa: PERF203 - retry loop
            last_exc, tb = e, traceback.format_exc()
    assert last_exc is not None
    err = _error_line(last_exc) + (f" (after {attempts} attempts)" if attempts > 1 else "")
    return _record(spec, "failed", error=err, traceback=tb, seconds=time.perf_counter() - t0,
                   **base)


def _compute(store: Store, spec: TaskSpec, sspec: registry.StageSpec, refs: Mapping[int, dict],
             key: str, comps: dict, existing: dict | None, attempt: int, t0: float) -> dict:
    t_load = time.perf_counter()
    args = [_load_input(store, spec.inputs[name], refs) for name in sspec.inputs]
    kwargs = dict(spec.params)
    ctx = None
    if sspec.wants_ctx:
        ctx = Context(part=spec.part, seed=spec.seed,
                      mapper=task_mapper(), workers=spec.workers)
        kwargs["ctx"] = ctx
    t_call = time.perf_counter()
    result = sspec.func(*args, **kwargs)
    t_enc = time.perf_counter()
    if not isinstance(result, Mapping):
        raise TypeError(f"stage {sspec.name!r} returned a {type(result).__name__}, "
                        f"expected a mapping of outputs {list(sspec.outputs)}")
    missing = [o for o in sspec.outputs if o not in result]
    extra = [o for o in result if o not in sspec.outputs]
    if missing or extra:
        raise ValueError(f"stage {sspec.name!r} returned outputs {sorted(result)}, declared "
                         f"{list(sspec.outputs)}")
    encoded = {}
    for o in sspec.outputs:
        try:
            encoded[o] = codecs.encode(result[o])
        except TypeError as e:
            raise TypeError(f"output {o!r}: {e}") from None
    warnings = list(ctx.warnings) if ctx is not None else []
    manifest = {
        "node": spec.node,
        "part": spec.part,
        "run_id": spec.run_id,
        "components": comps,
        "versions": comps.get("versions"),
        "upstream": _upstream_keys(spec.inputs, refs),
        "warnings": warnings,
        "attempts": attempt,
        "host": socket.gethostname(),
        "timings": {"load": t_call - t_load, "compute": t_enc - t_call},
    }
    if existing is not None:  # --force on a committed entry: replace it only if it differs
        new = {o: codecs.digest_encoded(e) for o, e in encoded.items()}
        old = _manifest_digests(existing)
        if new == old:
            return _record(spec, "computed", key=key, components=comps, outputs=old,
                           warnings=warnings, seconds=time.perf_counter() - t0)
        warnings.append(f"--force: outputs differ from the committed entry {spec.stage}/{key} "
                        "(is the stage deterministic?); replacing it")
        store.delete(spec.stage, key)
    t_commit = time.perf_counter()
    manifest["timings"]["encode"] = t_commit - t_enc
    digests = store.commit(spec.stage, key, encoded, manifest)
    return _record(spec, "computed", key=key, components=comps, outputs=dict(digests),
                   warnings=warnings, seconds=time.perf_counter() - t0,
                   timings={**manifest["timings"], "commit": time.perf_counter() - t_commit})


# --------------------------------------------------------------------------- plan


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


def _check_force(graph: Graph, force: Iterable[str]) -> set[str]:
    force = set(force or ())
    unknown = sorted(force - set(graph.config.nodes))
    if unknown:
        import difflib

        close = difflib.get_close_matches(unknown[0], list(graph.config.nodes), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ConfigError(f"unknown node {unknown[0]!r}{hint}", file="<command line>",
                          key="--force")
    return force


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
        From :func:`hash_files` (computed when not given).
    reasons : bool
        Compare tasks that will compute with their last run record (slower).

    Returns
    -------
    list of TaskPlan
        In task order.
    """
    force = _check_force(graph, force)
    if file_digests is None:
        file_digests = hash_files(graph, store)
    out: list[TaskPlan] = []
    history: dict[tuple[str, str | None], dict] | None = None
    for t in graph.tasks:
        sspec = find_stage(t.stage)

        def upstream(i: int, o: str) -> str | None:
            p = out[i]
            return p.outputs.get(o) if p.outputs is not None else None

        tp = TaskPlan(index=t.index, node=t.node, part=t.part, stage=t.stage, status="compute",
                      reason="")
        out.append(tp)
        try:
            inputs, kinds, pending = _key_inputs(t.inputs, file_digests, upstream)
        except FileNotFoundError as e:
            tp.reason = str(e)
            continue
        if pending:
            ups = [out[i] for i in t.deps() if out[i].outputs is None]
            tp.status = "pending"
            tp.reason = (f"upstream {ups[0].node}" + (f"/{ups[0].part}" if ups[0].part else "")
                         + " will recompute") if ups else "upstream will recompute"
            continue
        try:
            tp.key, tp.components = compute_key(sspec, params=t.params, part=t.part,
                                                inputs=inputs, kinds=kinds,
                                                file_digests=file_digests)
        except FileNotFoundError as e:
            tp.reason = str(e)
            continue
        if t.node in force:
            tp.reason = "forced (--force)"
            continue
        man = store.manifest(t.stage, tp.key)
        if man is not None:
            tp.status, tp.reason, tp.outputs = "hit", "hit", _manifest_digests(man)
            continue
        tp.reason = f"no entry for key {tp.key[:12]}…"
        if reasons:
            if history is None:
                history = last_records(store)
            last = history.get((t.node, t.part))
            if last and last.get("components") and last.get("key") != tp.key:
                tp.changes = keys.diff_components(last["components"], tp.components)
                if tp.changes:
                    tp.reason = "; ".join(tp.changes)
    return out


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
        if p.components is None:
            changes = [p.reason]
            if last and last.get("components") and p.status == "pending":
                # compare what is known: everything but the pending inputs
                sspec = find_stage(t.stage)
                cur = dict(last["components"])
                cur["params"] = _key_params(t.params, filepath_params(sspec), files)
                cur["code"] = stage_fingerprint(sspec)
                cur["versions"] = keys.package_versions()
                changes = [p.reason] + keys.diff_components(last["components"], cur)
        elif last is None:
            changes = ["no previous run of this task"]
        elif last.get("key") == p.key:
            changes = []
        else:
            changes = keys.diff_components(last.get("components"), p.components)
        item["changes"] = changes
        out.append(item)
    return out


# --------------------------------------------------------------------------- locks


def default_lock_path(config_path: str | os.PathLike) -> Path:
    """``<config stem>.lock.json`` next to the config."""
    p = Path(config_path)
    return p.with_name(p.stem + ".lock.json")


def lock_document(graph: Graph, records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """A lock of every task's key, components and output digests.

    Raises
    ------
    FrozenError
        If a task has no committed result (it failed or was skipped).
    """
    bad = [r for r in records if r.get("status") not in OK]
    if bad:
        r = bad[0]
        raise FrozenError(f"cannot lock: {r['node']}" + (f"/{r['part']}" if r.get("part") else "")
                          + f" {r.get('status')}: {r.get('error')}")
    tasks = [{"node": r["node"], "part": r["part"], "stage": r["stage"], "key": r["key"],
              "outputs": r["outputs"], "components": r["components"]} for r in records]
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
        import yaml

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
            import yaml

            doc = yaml.safe_load(text)
        else:
            doc = json.loads(text)
    except ValueError as e:
        raise FrozenError(f"{path}: malformed lock file ({e})") from None
    if not isinstance(doc, dict) or doc.get("mocapflow_lock") != LOCK_FORMAT:
        raise FrozenError(f"{path}: not a mocapflow lock file (format {LOCK_FORMAT})")
    return {(t["node"], t.get("part")): t for t in doc.get("tasks", [])}


def _name(node: str, part: str | None) -> str:
    return node if part is None else f"{node}/{part}"


def _frozen_precheck(graph: Graph, plans: Sequence[TaskPlan],
                     lock: Mapping[tuple[str, str | None], dict]) -> None:
    problems = []
    for p in plans:
        want = lock.get((p.node, p.part))
        if want is None:
            problems.append(f"{_name(p.node, p.part)}: not in the lock file")
        elif p.key is not None and p.key != want["key"]:
            why = "; ".join(keys.diff_components(want.get("components"), p.components or {}))
            problems.append(f"{_name(p.node, p.part)}: key differs from the lock ({why})")
        elif p.status == "compute" and p.key is None:
            problems.append(f"{_name(p.node, p.part)}: {p.reason}")
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise FrozenError(f"frozen: {problems[0]}{more}")


def _frozen_postcheck(records: Sequence[Mapping[str, Any]],
                      lock: Mapping[tuple[str, str | None], dict]) -> list[str]:
    problems = []
    for r in records:
        want = lock.get((r["node"], r["part"]))
        if want is None or r.get("status") not in OK:
            continue
        if r["key"] != want["key"]:
            problems.append(f"{_name(r['node'], r['part'])}: key differs from the lock")
        elif r["outputs"] != want["outputs"]:
            diff = sorted(o for o in set(r["outputs"]) | set(want["outputs"])
                          if r["outputs"].get(o) != want["outputs"].get(o))
            problems.append(f"{_name(r['node'], r['part'])}: output {', '.join(diff)} digest "
                            "differs from the lock")
    return problems


# --------------------------------------------------------------------------- run


@dataclass
class RunResult:
    """Outcome of :func:`run`.

    Attributes
    ----------
    records : list of dict
        One task record per task, in task order (see :func:`execute_task`).
    frozen_problems : list of str
        ``--frozen``: outputs that differ from the lock.
    """

    run_id: str
    records: list[dict[str, Any]]
    seconds: float
    executor: str
    frozen_problems: list[str] = field(default_factory=list)

    @property
    def counts(self) -> dict[str, int]:
        """``{"hit", "computed", "failed", "skipped"} -> count``."""
        c = {"hit": 0, "computed": 0, "failed": 0, "skipped": 0}
        for r in self.records:
            c[r["status"]] = c.get(r["status"], 0) + 1
        return c

    @property
    def ok(self) -> bool:
        """Every task is a hit or computed (and the lock matched)."""
        return all(r["status"] in OK for r in self.records) and not self.frozen_problems

    def failed(self) -> list[dict[str, Any]]:
        """Records of failed tasks."""
        return [r for r in self.records if r["status"] == "failed"]

    def digests(self) -> dict[tuple[str, str | None], dict[str, str] | None]:
        """``(node, part) -> {output: digest}``."""
        return {(r["node"], r["part"]): r.get("outputs") for r in self.records}


def run(graph: Graph, store: Store, *, executor: Executor | None = None,
        force: Iterable[str] = (), fail_fast: bool = False,
        lock: Mapping[tuple[str, str | None], dict] | None = None,
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
        From :func:`read_lock`: run ``--frozen`` (raise :class:`FrozenError`
        before running anything when a key already differs; tasks whose key
        turns out different fail without running; digests are compared after).
    progress : Progress, optional
        Gets ``update(record)`` per finished task and ``close()``.
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
    force = _check_force(graph, force)
    files = hash_files(graph, store)
    plans = plan(graph, store, force=force, file_digests=files, reasons=False)
    if lock is not None:
        _frozen_precheck(graph, plans, lock)

    records: dict[int, dict] = {}
    known: dict[int, dict] = {}
    for p in plans:
        if p.status == "hit":
            rec = {"index": p.index, "node": p.node, "part": p.part, "stage": p.stage,
                   "key": p.key, "components": p.components, "status": "hit", "seconds": 0.0,
                   "error": None, "outputs": p.outputs, "warnings": []}
            known[p.index] = rec
            records[p.index] = rec
            if progress is not None:
                progress.update(rec)
    todo = [t for t in graph.tasks if t.index not in known]
    if todo:
        todo_idx = {t.index for t in todo}
        calls = []
        for t in todo:
            sspec = find_stage(t.stage)
            deps = tuple(d for d in t.deps() if d in todo_idx)
            kn = {d: known[d] for d in t.deps() if d in known}
            expected = lock.get((t.node, t.part)) if lock is not None else None
            inputs, params, fdig = _absolute_files(t, sspec, files)
            spec = TaskSpec(index=t.index, node=t.node, part=t.part, stage=t.stage,
                            module=sspec.module, params=params, inputs=inputs, deps=deps,
                            file_digests=fdig, run_id=run_id, seed=t.seed, force=t.node in force,
                            workers=executor.workers,
                            expected=expected)
            key = f"{t.node}-{t.index}-{run_id}"
            calls.append(Call(index=t.index, key=key, fn=execute_task, args=(store, spec, kn),
                              deps=deps))
        def full(t: Task, res: Mapping[str, Any]) -> dict[str, Any]:
            rec = {"index": t.index, "node": t.node, "part": t.part, "stage": t.stage,
                   "key": None, "components": None, "seconds": 0.0, "error": None,
                   "outputs": None, "warnings": []}
            rec.update(res)
            return rec

        def on_done(res: dict) -> None:
            if progress is not None:
                progress.update(full(graph.tasks[res["index"]], res))

        results = executor.run(calls, on_done=on_done, fail_fast=fail_fast)
        for t in todo:
            records[t.index] = full(t, results.get(t.index) or {"status": "skipped",
                                                                 "error": "not run"})
    if progress is not None:
        progress.close()
    ordered = [records[t.index] for t in graph.tasks]
    result = RunResult(run_id=run_id, records=ordered, seconds=time.perf_counter() - t0,
                       executor=executor.describe())
    if lock is not None:
        result.frozen_problems = _frozen_postcheck(ordered, lock)
    store.write_run(run_id, {
        "run_id": run_id,
        "graph": graph.config.name,
        "config": str(Path(graph.config.path).resolve()) if graph.config.path else None,
        "targets": list(graph.targets),
        "overrides": graph.config.overrides,
        "command": list(command) if command is not None else None,
        "executor": executor.describe(),
        "started_at": started,
        "finished_at": time.time(),
        "seconds": result.seconds,
        "counts": result.counts,
        "frozen_problems": result.frozen_problems,
        "tasks": [{k: r.get(k) for k in ("node", "part", "stage", "key", "components", "status",
                                         "seconds", "error", "outputs", "warnings", "traceback")}
                  for r in ordered],
    })
    return result


def _absolute_files(t: Task, sspec: registry.StageSpec, files: Mapping[str, str | None]
                    ) -> tuple[dict[str, tuple], dict[str, Any], dict[str, str | None]]:
    """Inputs and params with absolute file paths (workers may run elsewhere), and digests.

    Keys do not change: files enter them by content digest, parts by their id.
    """
    digests: dict[str, str | None] = {}

    def absolute(path: str) -> str:
        a = os.path.abspath(path)
        digests[a] = files.get(path)
        return a

    inputs: dict[str, tuple] = {}
    for name, w in t.inputs.items():
        if w[0] == "file":
            inputs[name] = ("file", absolute(w[1]))
        elif w[0] == "files":
            inputs[name] = ("files", [absolute(p) for p in w[1]])
        else:
            inputs[name] = w
    params = dict(t.params)
    for p in filepath_params(sspec):
        if params.get(p) is not None:
            params[p] = absolute(str(params[p]))
    return inputs, params, digests
