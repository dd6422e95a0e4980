"""Running one task: key → cache check → load inputs → call the stage → encode → commit.

Each (node, part) is one task.  :func:`execute_task` (module-level, picklable)
runs on whatever executor the run uses, from a :class:`TaskSpec` (everything a
worker needs, small and picklable) and the records of its upstream tasks.  It
computes the task's key (:mod:`~mocapflow.pipeline.task_keys`: upstream *output
digests*, so an upstream change that leaves an output identical leaves the task
a hit), returns at once on a committed entry, otherwise loads its inputs from
the store, calls the stage with a seeded :class:`~mocapflow.pipeline.context.Context`,
encodes and commits the outputs with a manifest, retrying as the stage allows.
It returns a :class:`TaskRecord` (never raises for stage errors): a small
reference to the entry, not the data.

What goes into an entry depends only on the key: before the stage runs, the
worker re-reads its raw input files and checks their content digests against
the planned ones, and checks them again before the commit
(:func:`~mocapflow.pipeline.task_keys.read_inputs_check`); the stage runs with
BLAS and OpenMP pools at one thread (:func:`single_threaded_blas`), so its
floating-point results do not depend on the thread count; times and the host go
to the manifest (``timings``, with the stage's own ``ctx.timer`` steps under
``timings["steps"]``), never into an output.
"""

from __future__ import annotations

import importlib
import socket
import time
import traceback
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from mocapflow.pipeline import codecs, keys, registry
from mocapflow.pipeline.blas import single_threaded_blas
from mocapflow.pipeline.config import resolve_stage
from mocapflow.pipeline.context import Context
from mocapflow.pipeline.executors import CallOutcome, progress_sink, task_mapper
from mocapflow.pipeline.graph import task_name
from mocapflow.pipeline.progress import ProgressReporter
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.task_keys import (
    InputChangedError,
    compute_key,
    key_inputs,
    read_inputs_check,
)
from mocapflow.pipeline.wires import FilesWire, FileWire, TasksWire, TaskWire, Wire

__all__ = [
    "OK",
    "TaskRecord",
    "TaskSpec",
    "execute_task",
    "load_input",
    "manifest_digests",
    "single_threaded_blas",
    "worker_stage",
]

#: Statuses of a task whose outputs are committed.
OK = ("hit", "computed")


@dataclass(frozen=True)
class TaskRecord:
    """What one task did: its key, status and output digests (a reference, never data).

    Attributes
    ----------
    index : int
        Task index in the graph.
    node, stage : str
    part : str or None
    status : {"hit", "computed", "failed", "skipped"}
        (``"missing"`` only for a placeholder of an upstream task that never reported.)
    key : str or None
        ``None`` when the key could not be computed.
    components : dict or None
        Key components (:func:`~mocapflow.pipeline.keys.task_key`).
    seconds : float
    error : str or None
        One line (``"ValueError: ..."``) for a failed or skipped task.
    outputs : dict or None
        ``output -> digest`` of a committed entry.
    warnings : tuple of str
        ``ctx.warn`` messages of the stage.
    traceback : str or None
        Of a stage failure (kept in run records).
    timings : dict or None
        ``load``, ``check`` (re-reading the input files), ``compute``, ``encode``,
        ``commit`` seconds of a computed task, and ``steps``: the stage's own
        ``ctx.timer`` steps (``step -> seconds``).
    figures : dict or None
        The stage's ``ctx.figure`` key figures (of a hit: from its manifest).

    Notes
    -----
    ``record["status"]`` and ``record.get("traceback")`` read the fields of
    :meth:`as_dict` (the dict records the engine used before).
    """

    index: int
    node: str
    part: str | None
    stage: str
    status: str
    key: str | None = None
    components: dict[str, Any] | None = None
    seconds: float = 0.0
    error: str | None = None
    outputs: dict[str, str] | None = None
    warnings: tuple[str, ...] = ()
    traceback: str | None = None
    timings: dict[str, Any] | None = None
    figures: dict[str, Any] | None = None

    @property
    def ok(self) -> bool:
        """The task's outputs are committed (a hit or computed)."""
        return self.status in OK

    def as_dict(self) -> dict[str, Any]:
        """JSON form (``traceback`` and ``timings`` only when set)."""
        out: dict[str, Any] = {
            "index": self.index,
            "node": self.node,
            "part": self.part,
            "stage": self.stage,
            "key": self.key,
            "components": self.components,
            "status": self.status,
            "seconds": self.seconds,
            "error": self.error,
            "outputs": self.outputs,
            "warnings": list(self.warnings),
        }
        if self.traceback is not None:
            out["traceback"] = self.traceback
        if self.figures:
            out["figures"] = dict(self.figures)
        if self.timings is not None:
            out["timings"] = self.timings
        return out

    def __getitem__(self, name: str) -> Any:
        return self.as_dict()[name]

    def get(self, name: str, default: Any = None) -> Any:
        """A field of :meth:`as_dict`, or ``default``."""
        return self.as_dict().get(name, default)


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
    inputs: dict[str, Wire]
    deps: tuple[int, ...]
    file_digests: dict[str, str | None]
    run_id: str
    seed: int = 0
    force: bool = False
    workers: int = 1
    expected: dict[str, Any] | None = None

    def record(self, status: str, **fields: Any) -> TaskRecord:
        """A :class:`TaskRecord` of this task."""
        return TaskRecord(index=self.index, node=self.node, part=self.part, stage=self.stage,
                          status=status, **fields)


#: What an upstream task reported: its record, or what the executor says of it.
UpstreamRef = TaskRecord | CallOutcome


def error_line(e: BaseException) -> str:
    """``"TypeName: first line of the message"``."""
    text = str(e).strip().splitlines()
    msg = text[0] if text else ""
    return f"{type(e).__name__}: {msg}" if msg else type(e).__name__


def worker_stage(name: str, module: str) -> registry.StageSpec:
    """Find a stage in this process (for workers: import its module, discover only if needed)."""
    try:
        mod = importlib.import_module(module) if module else None
    except ImportError:
        mod = None
    for obj in vars(mod).values() if mod is not None else ():
        spec = getattr(obj, "__mocapflow_stage__", None)
        if isinstance(spec, registry.StageSpec) and spec.name == name:
            return spec
    return resolve_stage(name)


def manifest_digests(man: Mapping[str, Any]) -> dict[str, str]:
    """``output -> digest`` of a manifest."""
    return {k: (v["digest"] if isinstance(v, dict) else v) for k, v in man["outputs"].items()}


# --------------------------------------------------------------------------- inputs


def _decode(enc: codecs.Encoded) -> Any:
    try:
        return codecs.decode(enc)
    except TypeError:  # a domain type whose family is not imported in this worker yet
        registry.discover()
        return codecs.decode(enc)


def load_input(store: Store, wire: Wire, refs: Mapping[int, TaskRecord]) -> Any:
    """What the stage receives for one wire: a path, paths, a value or values."""
    match wire:
        case FileWire(path=path):
            return path
        case FilesWire(paths=paths):
            return list(paths)
        case TaskWire(index=i, output=o):
            return _decode(store.load(refs[i].stage, refs[i].key, o))
        case TasksWire(sources=sources):
            return [_decode(store.load(refs[s.index].stage, refs[s.index].key, s.output))
                    for s in sources]
    raise TypeError(f"not a wire: {wire!r}")


def _upstream_keys(inputs: Mapping[str, Wire], refs: Mapping[int, TaskRecord]
                   ) -> dict[str, Any]:
    """``input -> "stage/key"`` (or ``"file:path"``, or lists of them) for the manifest."""
    out: dict[str, Any] = {}
    for name, w in inputs.items():
        match w:
            case TaskWire(index=i):
                out[name] = f"{refs[i].stage}/{refs[i].key}"
            case TasksWire(sources=sources):
                out[name] = [f"{refs[s.index].stage}/{refs[s.index].key}" for s in sources]
            case FileWire(path=path):
                out[name] = f"file:{path}"
            case FilesWire(paths=paths):
                out[name] = [f"file:{p}" for p in paths]
    return out


# --------------------------------------------------------------------------- one task


def execute_task(store: Store, spec: TaskSpec, known: Mapping[int, TaskRecord],
                 *dep_refs: UpstreamRef) -> TaskRecord:
    """Run one (node, part): key → cache check → load inputs → stage → commit.

    Parameters
    ----------
    store : Store
    spec : TaskSpec
    known : dict
        Records of upstream tasks resolved before submission (plan hits).
    *dep_refs : TaskRecord or CallOutcome
        What the upstream tasks in ``spec.deps`` reported (results of other tasks).

    Returns
    -------
    TaskRecord
        Status hit, computed, failed or skipped (with ``traceback`` for a
        failure).  Never raises for stage errors.
    """
    t0 = time.perf_counter()
    refs: dict[int, Any] = dict(known)
    refs.update(zip(spec.deps, dep_refs))
    problem = _upstream_problem(refs, {*spec.deps, *known})
    if problem is not None:
        return spec.record("skipped", error=problem, seconds=time.perf_counter() - t0)
    try:
        sspec = worker_stage(spec.stage, spec.module)
        inputs, kinds, _ = key_inputs(spec.inputs, spec.file_digests,
                                      lambda i, o: refs[i].outputs[o])
        key, comps = compute_key(sspec, params=spec.params, part=spec.part, inputs=inputs,
                                 kinds=kinds, file_digests=spec.file_digests)
    except Exception as e:
        return spec.record("failed", error=error_line(e), traceback=traceback.format_exc(),
                           seconds=time.perf_counter() - t0)
    exp = spec.expected
    if exp is not None and exp.get("key") != key:
        why = "; ".join(keys.diff_components(exp.get("components"), comps)) or "key differs"
        return spec.record("failed", error=f"frozen: key differs from the lock ({why})",
                           seconds=time.perf_counter() - t0, key=key, components=comps)
    man = store.manifest(spec.stage, key)
    if man is not None and not spec.force:
        return spec.record("hit", outputs=manifest_digests(man),
                           seconds=time.perf_counter() - t0, key=key, components=comps,
                           figures=man.get("figures") or None)
    return _compute_with_retries(store, spec, sspec, refs, key, comps, man, t0)


def _upstream_problem(refs: Mapping[int, UpstreamRef], indices: set[int]) -> str | None:
    """``"upstream NODE/PART STATUS"`` for the first upstream task that is not OK."""
    for i in sorted(indices):
        r = refs.get(i)
        if r is None:
            return "upstream ? missing"
        if r.status not in OK:
            # an executor's own outcome (a call it could not run) names no node
            up = task_name(str(getattr(r, "node", None)), getattr(r, "part", None))
            return f"upstream {up} {r.status}"
    return None


def _compute_with_retries(store: Store, spec: TaskSpec, sspec: registry.StageSpec,
                          refs: Mapping[int, TaskRecord], key: str, comps: dict,
                          existing: dict | None, t0: float) -> TaskRecord:
    """:func:`_compute`, tried ``1 + retries`` times; the last error is the record's."""
    attempts = 1 + max(0, int(sspec.retries))
    last_exc: BaseException | None = None
    tb = ""
    for attempt in range(1, attempts + 1):
        try:
            return _compute(store, spec, sspec, refs, key, comps, existing, attempt, t0)
        except InputChangedError as e:  # noqa: PERF203 - retry loop; a retry reads the same file
            return spec.record("failed", error=error_line(e), seconds=time.perf_counter() - t0,
                               key=key, components=comps)
        except Exception as e:
            last_exc, tb = e, traceback.format_exc()
    assert last_exc is not None
    err = error_line(last_exc) + (f" (after {attempts} attempts)" if attempts > 1 else "")
    return spec.record("failed", error=err, traceback=tb, seconds=time.perf_counter() - t0,
                       key=key, components=comps)


def _progress_reporter(spec: TaskSpec) -> ProgressReporter | None:
    """The ``ctx.progress`` hook of a task: rate-limited updates to the executor's sink.

    Only the display sees them: never an output, a key or the manifest.
    """
    sink = progress_sink()
    if sink is None:
        return None
    return ProgressReporter(sink, {"run": spec.run_id, "index": spec.index,
                                   "node": spec.node, "part": spec.part})


def _compute(store: Store, spec: TaskSpec, sspec: registry.StageSpec,
             refs: Mapping[int, TaskRecord], key: str, comps: dict, existing: dict | None,
             attempt: int, t0: float) -> TaskRecord:
    """Load the inputs, call the stage, encode its outputs and commit them (one attempt).

    The raw input files are checked against their planned digests before the
    stage runs and again before the commit (:class:`InputChangedError` otherwise).
    """
    t_load = time.perf_counter()
    args = [load_input(store, spec.inputs[name], refs) if name in spec.inputs else None
            for name in sspec.inputs]  # an unwired optional input is None
    kwargs = dict(spec.params)
    ctx = None
    reporter = None
    if sspec.wants_ctx:
        reporter = _progress_reporter(spec)
        ctx = Context(part=spec.part, seed=spec.seed, mapper=task_mapper(),
                      workers=spec.workers, progress_hook=reporter)
        kwargs["ctx"] = ctx
    t_check = time.perf_counter()
    files = read_inputs_check(spec.file_digests)
    t_call = time.perf_counter()
    try:
        with single_threaded_blas():
            result = sspec.func(*args, **kwargs)
    finally:
        if reporter is not None:
            reporter.flush()  # the last update, if the rate limit held it back
    t_enc = time.perf_counter()
    encoded = _encode_outputs(sspec, result)
    files.recheck()
    warnings = list(ctx.warnings) if ctx is not None else []
    timings: dict[str, Any] = {"load": t_check - t_load, "check": t_call - t_check,
                               "compute": t_enc - t_call}
    if ctx is not None and ctx.timings:
        timings["steps"] = dict(ctx.timings)
    figures = dict(ctx.figures) if ctx is not None else {}
    manifest = _manifest(spec, refs, comps, warnings, attempt, timings)
    if figures:
        manifest["figures"] = figures
    if existing is not None:  # --force on a committed entry: replace it only if it differs
        new = {o: codecs.digest_encoded(e) for o, e in encoded.items()}
        old = manifest_digests(existing)
        if new == old:
            return spec.record("computed", key=key, components=comps, outputs=old,
                               warnings=tuple(warnings), seconds=time.perf_counter() - t0,
                               timings=timings, figures=figures or None)
        warnings.append(f"--force: outputs differ from the committed entry {spec.stage}/{key} "
                        "(is the stage deterministic?); replacing it")
        store.delete(spec.stage, key)
    t_commit = time.perf_counter()
    manifest["timings"]["encode"] = t_commit - t_enc
    digests = store.commit(spec.stage, key, encoded, manifest)
    return spec.record("computed", key=key, components=comps, outputs=dict(digests),
                       warnings=tuple(warnings), seconds=time.perf_counter() - t0,
                       timings={**manifest["timings"], "commit": time.perf_counter() - t_commit},
                       figures=figures or None)


def _encode_outputs(sspec: registry.StageSpec, result: Any) -> dict[str, codecs.Encoded]:
    """The stage's outputs, checked against its declaration and encoded for storage."""
    if not isinstance(result, Mapping):
        raise TypeError(f"stage {sspec.name!r} returned a {type(result).__name__}, "
                        f"expected a mapping of outputs {list(sspec.outputs)}")
    missing = [o for o in sspec.outputs if o not in result]
    extra = [o for o in result if o not in sspec.outputs]
    if missing or extra:
        raise ValueError(f"stage {sspec.name!r} returned outputs {sorted(result)}, declared "
                         f"{list(sspec.outputs)}")
    encoded = {}
    dims = sspec.extra.get("output_dims", {})
    for o in sspec.outputs:
        try:
            encoded[o] = codecs.encode(result[o])
        except TypeError as e:
            raise TypeError(f"output {o!r}: {e}") from None
        if o in dims and encoded[o].type == "ndarray":  # declared names for dim_0 …
            arr, old = encoded[o].arrays["data"]
            if len(dims[o]) != len(old):
                raise ValueError(f"stage {sspec.name!r} output {o!r}: output_dims names "
                                 f"{len(dims[o])} axes, the array has {len(old)}")
            encoded[o].arrays["data"] = (arr, dims[o])
    return encoded


def _manifest(spec: TaskSpec, refs: Mapping[int, TaskRecord], comps: dict, warnings: list[str],
              attempt: int, timings: dict[str, Any]) -> dict[str, Any]:
    """The manifest fields the task adds (the store adds stage, key, outputs, format).

    ``warnings`` is kept by reference: a warning added before the commit is in it.
    """
    return {
        "node": spec.node,
        "part": spec.part,
        "run_id": spec.run_id,
        "components": comps,
        "versions": comps.get("versions"),
        "upstream": _upstream_keys(spec.inputs, refs),
        "warnings": warnings,
        "attempts": attempt,
        "host": socket.gethostname(),
        "timings": timings,
    }
