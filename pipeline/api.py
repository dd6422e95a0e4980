"""The Python API: run a graph and get its outputs back as domain objects.

:func:`run` is ``mocapflow run`` from Python: a config (a YAML path or a
shipped graph's name), overrides, a store and an executor in, a
:class:`Results` out.  :class:`Results` maps each task, ``(node, part label)``,
to its :class:`Outputs`: ``output name -> decoded value`` (``Markers``,
``Motion``, ``Mesh``, an ndarray, a JSON value …), read from the store and
decoded through the output type's codec on first access.

Failed tasks do not raise from :func:`run`: the tasks that did commit stay
usable.  They are reported instead, as a ``RuntimeWarning`` of one line (the
CLI's failure summary), as ``failed`` / ``skipped`` rows of the repr, in
:attr:`Results.failures` and :attr:`Results.ok`; reading the outputs of such a
task raises :class:`TaskFailedError` (one line: the task and its error), and
:meth:`Results.raise_for_failures` raises it for the whole run.  Config and
param errors raise before anything runs (``ConfigError``, ``ParamError``).

Examples
--------
>>> import mocapflow                                                  # doctest: +SKIP
>>> res = mocapflow.run("texture", set={"synth.length": 256, "synth.seeds": 1})  # doctest: +SKIP
>>> res["synth"]["motion"]                                            # doctest: +SKIP
Motion(1021 frames × 31 joints @ 120 Hz, 8.51 s, root 'Hips', up +y)
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from mocapflow.pipeline import codecs, registry
from mocapflow.pipeline.execute import OK, TaskRecord
from mocapflow.pipeline.executors import Executor, make_executor
from mocapflow.pipeline.graph import Graph, load_graph, part_label, task_name
from mocapflow.pipeline.plan import paused_gc
from mocapflow.pipeline.progress import Progress
from mocapflow.pipeline.runner import RunResult
from mocapflow.pipeline.runner import run as run_graph
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.store_backends import STORAGE_OPTIONS_ENV, parse_storage_options

__all__ = ["DEFAULT_STORE", "Outputs", "Results", "TaskFailedError", "run"]

#: Store root when neither ``store=`` nor ``$MOCAPFLOW_STORE`` is given (as the CLI).
DEFAULT_STORE = ".mocapflow"
#: Rows of a :class:`Results` repr before ``… and N more``.
REPR_ROWS = 30
#: Longest repr of one output value in an :class:`Outputs` repr.
VALUE_REPR = 100


class TaskFailedError(RuntimeError):
    """A task whose outputs were asked for failed, or was skipped (one line)."""


def run(config: str | os.PathLike, *, parts: str | Sequence[str] | None = None,
        set: Mapping[str, Any] | Iterable[str] | None = None,  # noqa: A002 (the CLI's --set)
        targets: str | Sequence[str] | None = None, store: Store | str | os.PathLike | None = None,
        executor: str | Executor = "sync", workers: int | None = None,
        force: bool | str | Iterable[str] = False, progress: bool = False) -> Results:
    """Run a graph (``mocapflow run`` from Python) and return its outputs.

    Parameters
    ----------
    config : str or path-like
        A YAML config, or the name of a shipped graph (``"texture"``).
    parts : str or sequence of str, optional
        Files and globs replacing the config's ``parts:`` (``--parts``).
    set : mapping or iterable of str, optional
        Overrides, ``{"synth.length": 256}`` or ``["synth.length=256"]`` (``--set``).
    targets : str or sequence of str, optional
        Target nodes (default: the config's); their ancestors run too.
    store : Store, str or path-like, optional
        The store or its root (a folder or an fsspec URL); default
        ``$MOCAPFLOW_STORE``, else ``./.mocapflow``.
    executor : {"sync", "local", "slurm"} or Executor
        ``"sync"`` runs in this process; a kind is built (and closed) here, an
        :class:`~mocapflow.pipeline.executors.Executor` given is used and left open.
    workers : int, optional
        Workers of a ``"local"`` executor (default: CPU count).
    force : bool, str or iterable of str
        ``True``: recompute every node of the graph; node names: those.
    progress : bool
        Show the CLI's progress on stderr.

    Returns
    -------
    Results
        Every task of the graph, keyed by ``(node, part label)``.

    Raises
    ------
    ConfigError, ParamError
        A bad config, override or param (nothing ran).
    ValueError
        ``workers`` below 1.

    Warns
    -----
    RuntimeWarning
        Some tasks failed or were skipped (one line naming the first); see the
        module notes.
    """
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    with paused_gc():  # a task per part: many objects, no cycles
        graph = load_graph(config, sets=set if set is not None else (),
                           parts=[parts] if isinstance(parts, (str, os.PathLike)) else parts,
                           targets=[targets] if isinstance(targets, str) else targets)
    st = open_store(store)
    if isinstance(force, bool):
        nodes = list(graph.nodes) if force else []
    else:
        nodes = [force] if isinstance(force, str) else list(force)
    bar = Progress(len(graph.tasks), label=graph.config.name) if progress else None
    own = not isinstance(executor, Executor)
    ex = make_executor(executor, workers=workers, store=st) if own else executor
    try:
        result = run_graph(graph, st, executor=ex, force=nodes, progress=bar,
                           command=["mocapflow.run", str(config)])
    finally:
        if own:
            ex.close()
    res = Results(graph, st, result)
    if res.failures:
        warnings.warn(res.failure_summary(), RuntimeWarning, stacklevel=2)
    return res


def open_store(store: Store | str | os.PathLike | None) -> Store:
    """The store ``run`` uses: a :class:`Store`, a root, or the CLI's default.

    A URL root takes its fsspec options from ``$MOCAPFLOW_STORAGE_OPTIONS``.
    """
    if isinstance(store, Store):
        return store
    root = os.fspath(store) if store is not None else (
        os.environ.get("MOCAPFLOW_STORE") or DEFAULT_STORE)
    local = "://" not in root or root.startswith("file://")
    options = None if local else parse_storage_options((), os.environ.get(STORAGE_OPTIONS_ENV))
    st = Store(root, storage_options=options or None)
    st.probe()
    return st


def _decode(enc: codecs.Encoded) -> Any:
    try:
        return codecs.decode(enc)
    except TypeError:  # a domain type whose family is not imported yet
        registry.discover()
        return codecs.decode(enc)


def short_repr(value: Any, limit: int = VALUE_REPR) -> str:
    """One line of at most ``limit`` characters describing ``value`` (never array contents)."""
    if isinstance(value, np.ndarray):
        return f"ndarray {value.dtype} {value.shape}"
    if isinstance(value, Mapping) and len(text := repr(value)) > limit:
        keys = ", ".join(map(str, list(value)[:4])) + (", …" if len(value) > 4 else "")
        return f"{type(value).__name__} of {len(value)} keys: {keys}"[:limit]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        text = repr(value)
        if len(text) > limit:  # a generated repr: field names and shapes only
            fields = [f.name + (f" {np.shape(v)}" if isinstance(v := getattr(value, f.name),
                                                               np.ndarray) else "")
                      for f in dataclasses.fields(value)]
            text = f"{type(value).__name__}({', '.join(fields)})"
    elif not isinstance(value, Mapping):
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"


class Outputs(Mapping[str, Any]):
    """The outputs of one committed task: ``output name -> decoded value``.

    The entry is read on the first access of any output, each output decoded
    on its first access (through its type's codec) and kept.

    Attributes
    ----------
    record : TaskRecord
        The task's record in the run.
    store : Store
    name : str
        ``node/part label``, as the repr shows it.
    """

    def __init__(self, store: Store, record: TaskRecord, name: str | None = None) -> None:
        self.store = store
        self.record = record
        self.name = name or task_name(record.node, record.part)
        self._encoded: dict[str, codecs.Encoded] | None = None
        self._values: dict[str, Any] = {}

    def _names(self) -> list[str]:
        return list(self.record.outputs or {})

    def __getitem__(self, name: str) -> Any:
        if name not in self._values:
            if name not in self._names():
                raise KeyError(f"{self.name} has no output "
                               f"{name!r} (outputs: {', '.join(self._names())})")
            if self._encoded is None:
                self._encoded = self.store.load_outputs(self.record.stage, str(self.record.key))
            self._values[name] = _decode(self._encoded[name])
        return self._values[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._names())

    def __len__(self) -> int:
        return len(self._names())

    def __repr__(self) -> str:
        r = self.record
        head = f"Outputs of {self.name} (entry {r.stage}/{str(r.key)[:12]}):"
        return "\n".join([head, *(f"  {n}: {short_repr(self[n])}" for n in self)])


class Results(Mapping[tuple[str, str], Outputs]):
    """What :func:`run` did, task by task: a mapping ``(node, part label) -> Outputs``.

    Keys are ``(node, part label)`` in task order: the label is the part file's
    stem (``"cmu_131_02.seed0"``, ``"seed1"``, ``"all"`` for a gather node; the
    full part id where two parts of a node share a label).  A lookup also takes
    ``"node"`` (a node of one part), ``"node/part"`` and ``(node, part)`` with
    the part named as ``mocapflow explain`` takes it (id, label, unique suffix).
    Reading a failed or skipped task raises :class:`TaskFailedError`.

    Attributes
    ----------
    graph : Graph
    store : Store
    result : RunResult
    """

    def __init__(self, graph: Graph, store: Store, result: RunResult) -> None:
        self.graph = graph
        self.store = store
        self.result = result
        labels = [(r.node, part_label(r.part)) for r in result.records]
        seen: dict[tuple[str, str], int] = {}
        for k in labels:
            seen[k] = seen.get(k, 0) + 1
        self._by_key: dict[tuple[str, str], TaskRecord] = {}
        self._by_part: dict[tuple[str, str | None], tuple[str, str]] = {}
        for r, k in zip(result.records, labels):
            key = k if seen[k] == 1 else (r.node, str(r.part))
            self._by_key[key] = r
            self._by_part[(r.node, r.part)] = key
        self._outputs: dict[tuple[str, str], Outputs] = {}

    # ------------------------------------------------------------- the run

    @property
    def run_id(self) -> str:
        """Id of the run record (``runs/<run_id>.json`` in the store)."""
        return self.result.run_id

    @property
    def records(self) -> list[TaskRecord]:
        """Every task's record, in task order."""
        return self.result.records

    @property
    def ok(self) -> bool:
        """Every task is a hit or computed."""
        return self.result.ok

    @property
    def failures(self) -> list[TaskRecord]:
        """Records of the tasks that failed or were skipped (their ``error`` says why)."""
        return [r for r in self.result.records if r.status not in OK]

    @property
    def counts(self) -> dict[str, int]:
        """``{"hit", "computed", "failed", "skipped"} -> count``."""
        return self.result.counts

    def failure_summary(self) -> str:
        """One line: how many tasks failed, the first one and its error (``""`` if none)."""
        bad = self.failures
        if not bad:
            return ""
        first = next((r for r in bad if r.status == "failed"), bad[0])
        more = f" (and {len(bad) - 1} more failed or skipped)" if len(bad) > 1 else ""
        return (f"{len(bad)} task(s) of {self.graph.config.name} did not commit: "
                f"{task_name(first.node, first.part)} {first.status}: {first.error}{more}")

    def raise_for_failures(self) -> None:
        """Raise :class:`TaskFailedError` (:meth:`failure_summary`) when a task did not commit."""
        if self.failures:
            raise TaskFailedError(self.failure_summary())

    # ------------------------------------------------------------- mapping

    def key(self, spec: str | tuple[str, str | None]) -> tuple[str, str]:
        """The ``(node, part label)`` key named by ``spec`` (see the class notes).

        Raises
        ------
        KeyError
            Unknown node or part, or a node of several parts named without one
            (the message lists them).
        """
        if isinstance(spec, tuple):
            if spec in self._by_key:
                return spec  # type: ignore[return-value]
            if len(spec) != 2 or not isinstance(spec[0], str):
                raise KeyError(f"expected (node, part), got {spec!r}")
            node, part = spec
            if (node, part) in self._by_part:
                return self._by_part[(node, part)]
            text = node if part is None else f"{node}/{part}"
        elif isinstance(spec, str):
            text = spec
        else:
            raise KeyError(f"expected 'node', 'node/part' or (node, part), got {spec!r}")
        try:
            tasks = self.graph.find(text)
        except KeyError as e:
            raise KeyError(e.args[0]) from None
        if len(tasks) > 1:
            labels = [self._by_part[(t.node, t.part)][1] for t in tasks]
            shown = ", ".join(labels[:5]) + (", …" if len(labels) > 5 else "")
            raise KeyError(f"node {text!r} has {len(tasks)} parts ({shown}): name one, "
                           f"e.g. res[{text + '/' + labels[0]!r}]")
        return self._by_part[(tasks[0].node, tasks[0].part)]

    def record(self, spec: str | tuple[str, str | None]) -> TaskRecord:
        """The task record named by ``spec`` (any status)."""
        return self._by_key[self.key(spec)]

    def __getitem__(self, spec: str | tuple[str, str | None]) -> Outputs:
        key = self.key(spec)
        r = self._by_key[key]
        if r.status not in OK:
            raise TaskFailedError(f"{task_name(r.node, r.part)} {r.status}: {r.error}")
        if key not in self._outputs:
            self._outputs[key] = Outputs(self.store, r, f"{key[0]}/{key[1]}")
        return self._outputs[key]

    def __contains__(self, spec: object) -> bool:
        try:
            self.key(spec)  # type: ignore[arg-type]
        except KeyError:
            return False
        return True

    def __iter__(self) -> Iterator[tuple[str, str]]:
        return iter(self._by_key)

    def __len__(self) -> int:
        return len(self._by_key)

    def __repr__(self) -> str:
        counts = ", ".join(f"{n} {k}" for k, n in self.counts.items() if n)
        lines = [f"Results of {self.graph.config.name} (run {self.run_id}, {len(self)} tasks: "
                 f"{counts or 'none'})"]
        wide = max((len(n) for n, _ in self._by_key), default=0)
        part_w = min(max((len(p) for _, p in self._by_key), default=0), 40)
        for (node, label), r in list(self._by_key.items())[:REPR_ROWS]:
            line = f"  {node:<{wide}}  {label[:40]:<{part_w}}  {r.status}"
            if r.status not in OK and r.error:
                line += f": {r.error[:80]}"
            lines.append(line)
        if len(self) > REPR_ROWS:
            lines.append(f"  … and {len(self) - REPR_ROWS} more")
        return "\n".join(lines)
