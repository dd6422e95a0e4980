"""Nodes × parts → tasks: fan-out, gather, part matching, topological order, selection.

Rules (see the README's config format):

* A node wired to ``part`` runs once per file part.  A part id is the file's
  normalised path relative to the config file's folder, or its absolute path
  when the part was given as one (``parts:`` entries are resolved against the
  config's folder, ``--parts`` against the working directory; see
  :func:`~mocapflow.pipeline.config.expand_parts`): the working directory never
  enters a part id, so a graph has the same tasks and keys from any folder.
  Task wires name the absolute file (:meth:`GraphConfig.part_path
  <mocapflow.pipeline.config.GraphConfig.part_path>`).
* Any other node takes its parts from its inputs: the finest part list among
  them (a node below ``seeds:`` has ``"<part>#seed=<s>"`` ids).  The task for part
  ``q`` reads, from an upstream node, the task whose part is ``q`` or a prefix of
  ``q`` before a ``#``; a node with a single task (a gather, or a source without
  file input) is broadcast to every part.
* ``seeds: [..]`` or ``seeds: {count: N}`` fans a node out one task per (part,
  seed), sets its ``seed`` param and gives ``"<part>#seed=<s>"`` (``"seed=<s>"`` for
  a node with a single part).
* ``gather: true`` makes one task over all parts; each input becomes a list
  ordered by part.
* Task inputs are wires (:mod:`~mocapflow.pipeline.wires`): a part's file, every
  part's file (gather), one upstream output, or one output of each upstream
  task (gather).
* A stage may declare *file overrides* (``StageSpec.extra["file_overrides"] =
  {input: param}``): when the node sets ``param`` (a ``FilePath`` param), its
  input wired to ``part`` reads that file instead of each part's file, so the
  node has a single task, broadcast to every part (a range-of-motion trial read
  once for all trials).  Left ``None``, the node runs per part as usual.
* Per-part params (``${part.FIELD,DEFAULT}``, :attr:`NodeConfig.part_params
  <mocapflow.pipeline.config.NodeConfig.part_params>`) take, in each task, the
  field of the task's part (:attr:`GraphConfig.part_fields
  <mocapflow.pipeline.config.GraphConfig.part_fields>`: the fields of a capture
  session's trials), else the default; the task's params are then validated by
  the stage's validator.  A task standing for several parts (one task of a
  node, or a group below) needs the same value from each of them.
* A file override whose param is per-part groups the parts by file: parts
  naming the same file share one task, whose part id is ``"PARAM=FILE"`` (FILE
  the file's id, made like a part id: relative to the config's folder, or
  absolute when the part's id is); parts with no file read their own file in a
  task of their own (their part id).  When every part names the same file the
  node has a single task as above (so a plain part list keeps its tasks and
  keys).  Nodes below take these groups as their parts; a node below both a
  group and its parts matches each part to its group (its tasks are per part).
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from mocapflow.pipeline import registry
from mocapflow.pipeline.config import (
    CMDLINE,
    ConfigError,
    GraphConfig,
    NodeConfig,
    load_config,
    load_stage_modules,
)
from mocapflow.pipeline.wires import FilesWire, FileWire, TasksWire, TaskWire, Wire

__all__ = [
    "Graph",
    "Task",
    "build_graph",
    "file_overrides",
    "load_graph",
    "part_label",
    "task_name",
]


def task_name(node: str, part: str | None) -> str:
    """``node`` or ``node/part`` (how messages name a task)."""
    return node if part is None else f"{node}/{part}"


@dataclass(frozen=True)
class Task:
    """One (node, part) of a graph.

    Attributes
    ----------
    index : int
        Position in :attr:`Graph.tasks` (a topological order).
    node, stage : str
    part : str or None
        Part id; ``None`` for a node with a single task.
    params : dict
        Validated params of the node, ``seed`` set for seed fan-out (when the
        stage has a ``seed`` param).
    seed : int
        Seed of the context (the fan-out seed, else the ``seed`` param, else 0).
    inputs : dict
        ``input -> wire``: :class:`~mocapflow.pipeline.wires.FileWire`,
        ``FilesWire``, ``TaskWire`` or ``TasksWire``.
    """

    index: int
    node: str
    part: str | None
    stage: str
    params: dict[str, Any]
    inputs: dict[str, Wire]
    seed: int = 0

    @property
    def name(self) -> str:
        """``node`` or ``node/part``."""
        return task_name(self.node, self.part)

    def deps(self) -> list[int]:
        """Indices of the upstream tasks (unique, sorted)."""
        return sorted({i for w in self.inputs.values() for i in w.tasks()})

    def files(self) -> list[str]:
        """Raw input files of the task (file inputs only)."""
        return [p for w in self.inputs.values() for p in w.files()]


@dataclass
class Graph:
    """The tasks of a config for a set of targets.

    Attributes
    ----------
    config : GraphConfig
    targets : list of str
        Target nodes; the graph holds them and their ancestors only.
    nodes : list of str
        Selected nodes in topological order.
    node_parts : dict
        ``node -> list of part ids`` (for every node of the config).
    tasks : list of Task
        Topological order (upstream before downstream).
    """

    config: GraphConfig
    targets: list[str]
    nodes: list[str]
    node_parts: dict[str, list[str | None]]
    tasks: list[Task] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._by_id = {(t.node, t.part): t for t in self.tasks}

    def task(self, node: str, part: str | None) -> Task:
        """The task of ``(node, part)``."""
        return self._by_id[(node, part)]

    def node_tasks(self, node: str) -> list[Task]:
        """Tasks of one node, in part order."""
        return [t for t in self.tasks if t.node == node]

    def downstream(self, indices: Iterable[int]) -> set[int]:
        """Indices of every task downstream of ``indices`` (excluded)."""
        children: dict[int, list[int]] = {}
        for t in self.tasks:
            for d in t.deps():
                children.setdefault(d, []).append(t.index)
        out: set[int] = set()
        stack = list(indices)
        while stack:
            for c in children.get(stack.pop(), []):
                if c not in out:
                    out.add(c)
                    stack.append(c)
        return out

    def find(self, spec: str) -> list[Task]:
        """Tasks named by ``NODE`` or ``NODE/PART`` (PART: id, unique suffix or stem).

        Raises
        ------
        KeyError
            Unknown node or no / ambiguous part (the message lists candidates).
        """
        node, _, part = spec.partition("/")
        if node not in self.nodes:
            close = difflib.get_close_matches(node, self.nodes, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise KeyError(f"unknown node {node!r}{hint}")
        tasks = self.node_tasks(node)
        if not part:
            return tasks
        exact = [t for t in tasks if t.part == part]
        if exact:
            return exact
        cands = [t for t in tasks if t.part is not None and (
            t.part.endswith(part) or part_label(t.part) == part or part in t.part)]
        if len(cands) == 1:
            return cands
        if not cands:
            raise KeyError(f"node {node!r} has no part {part!r} (parts: "
                           f"{', '.join(str(t.part) for t in tasks[:5])}"
                           f"{', …' if len(tasks) > 5 else ''})")
        raise KeyError(f"part {part!r} of node {node!r} is ambiguous: "
                       f"{', '.join(str(t.part) for t in cands[:5])}")


def part_label(part: str | None) -> str:
    """A short, file-system-safe label of a part id.

    ``data/cmu_131_02.bvh#seed=3`` → ``cmu_131_02.seed3``; ``seed=2`` → ``seed2``;
    ``None`` → ``all``.
    """
    if part is None:
        return "all"
    head, *rest = part.split("#seed=")
    if head.startswith("seed="):
        label = "seed" + head[len("seed="):]
    else:
        name = head.replace("\\", "/").rstrip("/").rsplit("/", 1)[-1]
        label = name.rsplit(".", 1)[0] if "." in name[1:] else name
    for s in rest:
        label += f".seed{s}"
    return label


# --------------------------------------------------------------------------- matching


def _matcher(parts: Sequence[str | None], alias: Mapping[str, str] | None = None):
    """``q -> p``: the upstream part for ``q`` (exact, prefix before ``#``, or broadcast).

    ``alias`` (of a grouped upstream, see the module docstring) maps a part id to
    the upstream's group first (``"<part>#seed=1"`` → ``"<group>#seed=1"``).
    """
    if len(parts) == 1 and parts[0] is None:
        return lambda q: None
    index = {p: p for p in parts}

    def match(q: str | None) -> str | None | bool:
        if q is None:
            return False
        if alias:
            head, sep, rest = q.partition("#")
            g = alias.get(head)
            if g is not None:
                q = g + sep + rest
        cur = q
        while True:
            if cur in index:
                return cur
            cut = cur.rfind("#")
            if cut < 0:
                return False
            cur = cur[:cut]

    return match


def _covers(fine: Sequence[str | None], coarse: Sequence[str | None],
            alias: Mapping[str, str] | None = None) -> bool:
    match = _matcher(coarse, alias)
    return all(match(q) is not False for q in fine)


def file_overrides(node: NodeConfig) -> dict[str, str]:
    """``input -> file`` for the node's ``part`` inputs that a set param replaces.

    The stage declares ``extra["file_overrides"] = {input: param}``; an entry
    applies when the input is wired to ``part`` and the node's ``param`` is set.
    """
    spec = registry.lookup(node.stage)
    declared = spec.extra.get("file_overrides", {}) if spec is not None else {}
    return {
        iname: str(node.params[param])
        for iname, param in declared.items()
        if node.inputs.get(iname) == "part" and node.params.get(param) is not None
    }


def _per_part_overrides(node: NodeConfig) -> dict[str, str]:
    """``input -> param`` for the node's file overrides whose param is per-part."""
    spec = registry.lookup(node.stage)
    declared = spec.extra.get("file_overrides", {}) if spec is not None else {}
    return {i: p for i, p in declared.items()
            if node.inputs.get(i) == "part" and p in node.part_params}


def _param_error(node: NodeConfig, config: GraphConfig, param: str, problem: str
                 ) -> ConfigError:
    return ConfigError(problem, file=config.file,
                       line=node.param_lines.get(param) or node.line or None,
                       key=f"nodes.{node.name}.params.{param}")


def _part_value(node: NodeConfig, config: GraphConfig, param: str, part: str) -> Any:
    """The value of the per-part param ``param`` for the part ``part``."""
    ref = node.part_params[param]
    fields = config.part_fields.get(part)
    try:
        return ref.value(fields)
    except KeyError:
        have = ", ".join(sorted(fields)) if fields else "none: not from a session"
        raise _param_error(node, config, param, f"part {part} has no field {ref.field!r} "
                           f"(its fields: {have}) and {ref.text} has no default") from None


def _file_id(path: str, config: GraphConfig, absolute: bool) -> str:
    """The id of a file named by a per-part param (made like a part id)."""
    if absolute or config.root is None:
        return os.path.normpath(path).replace(os.sep, "/")
    try:
        return os.path.relpath(path, config.root).replace(os.sep, "/")
    except ValueError:  # another drive (Windows)
        return path.replace(os.sep, "/")


def _groups(node: NodeConfig, config: GraphConfig, param: str
            ) -> tuple[list[str | None], dict[str, str] | None]:
    """(task parts, ``part -> task part``) of a file override with a per-part param."""
    values = [_part_value(node, config, param, q) for q in config.parts]
    if not values or all(v is None for v in values):
        return list(config.parts), None  # every part reads its own file
    if all(v == values[0] for v in values):
        return [None], None  # one file for all: one task, as without ${part.…}
    parts_set = set(config.parts)
    alias: dict[str, str] = {}
    ids: dict[str, str] = {}  # file -> group id
    out: dict[str | None, None] = {}
    for q, v in zip(config.parts, values):
        if v is None:
            g = q
        else:
            g = ids.get(str(v))
            if g is None:
                g = ids[str(v)] = f"{param}={_file_id(str(v), config, os.path.isabs(q))}"
                if g in parts_set:
                    raise _param_error(node, config, param, f"group id {g!r} is also a part id "
                                       "(rename that file)")
        alias[q] = g
        out.setdefault(g, None)
    return list(out), alias


def _node_parts(node: NodeConfig, config: GraphConfig, known: dict[str, list[str | None]],
                aliases: dict[str, dict[str, str] | None]
                ) -> tuple[list[str | None], dict[str, str] | None]:
    """(task parts of the node, ``part -> task part`` when they are groups of parts)."""
    grouped = _per_part_overrides(node)
    overridden = file_overrides(node)
    alias: dict[str, str] | None = None
    if node.gather:
        base: list[str | None] = [None]
    else:
        cands: list[tuple[list[str | None], dict[str, str] | None]] = []
        for iname, w in node.inputs.items():
            if iname in grouped:
                cands.append(_groups(node, config, grouped[iname]))
                continue
            if iname in overridden:
                continue
            cands.append((list(config.parts), None) if w == "part"
                         else (known[w[0]], aliases.get(w[0])))
        if not cands:
            base = [None]
        else:
            base = None  # type: ignore[assignment]
            for cand, cand_alias in sorted(cands, key=lambda ca: len(ca[0]), reverse=True):
                if all(_covers(cand, other, other_alias) for other, other_alias in cands):
                    base, alias = cand, cand_alias
                    break
            if base is None:
                srcs = [("part" if w == "part" else w[0]) for w in node.inputs.values()]
                raise ConfigError(
                    f"inputs fan out over parts that do not match ({', '.join(srcs)})",
                    file=config.file, line=node.line or None, key=f"nodes.{node.name}.inputs")
    if node.seeds is None:
        return base, alias
    return ([f"{q}#seed={s}" if q is not None else f"seed={s}" for q in base
             for s in node.seeds], alias)


def _members(part: str | None, config: GraphConfig, groups: Mapping[str, list[str]] | None
             ) -> list[str]:
    """The parts a task of part id ``part`` stands for."""
    if part is None:
        return list(config.parts)
    head = part.split("#", 1)[0]
    if head.startswith("seed="):
        return list(config.parts)
    if groups is not None and head in groups:
        return groups[head]
    return [head]


def _task_part_params(node: NodeConfig, part: str | None, config: GraphConfig,
                      groups: Mapping[str, list[str]] | None) -> dict[str, Any]:
    """``param -> value`` of the node's per-part params for the task of ``part``."""
    members = _members(part, config, groups)
    out: dict[str, Any] = {}
    for p in node.part_params:
        values = {}
        for q in members:
            v = _part_value(node, config, p, q)
            values.setdefault(repr(v), (q, v))
        if len(values) > 1:
            (q1, v1), (q2, v2) = list(values.values())[:2]
            raise _param_error(node, config, p, f"task {task_name(node.name, part)} stands for "
                               f"several parts that give {node.part_params[p].text} different "
                               f"values ({q1}: {v1!r}, {q2}: {v2!r})")
        out[p] = next(iter(values.values()))[1] if values else node.params.get(p)
    return out


def build_graph(config: GraphConfig, targets: Sequence[str] | None = None) -> Graph:
    """Expand a config into tasks for ``targets`` and their ancestors.

    Parameters
    ----------
    config : GraphConfig
    targets : sequence of str, optional
        Target nodes (default: the config's targets).

    Returns
    -------
    Graph

    Raises
    ------
    ConfigError
        Unknown target, or inputs whose part fan-outs do not match.
    """
    targets = list(targets) if targets else list(config.targets)
    for t in targets:
        if t not in config.nodes:
            close = difflib.get_close_matches(t, list(config.nodes), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ConfigError(f"unknown node {t!r}{hint}", file=CMDLINE, key="--target")
    needed: set[str] = set()
    stack = list(targets)
    while stack:
        n = stack.pop()
        if n not in needed:
            needed.add(n)
            stack.extend(config.nodes[n].upstream())

    node_parts: dict[str, list[str | None]] = {}
    aliases: dict[str, dict[str, str] | None] = {}
    for name, node in config.nodes.items():
        node_parts[name], aliases[name] = _node_parts(node, config, node_parts, aliases)

    tasks: list[Task] = []
    index: dict[tuple[str, str | None], int] = {}
    order = [n for n in config.nodes if n in needed]
    part_match = _matcher(config.parts) if config.parts else None
    matchers: dict[str, Any] = {}  # upstream node -> matcher (built once, not per task)
    for name in order:
        node = config.nodes[name]
        overridden = file_overrides(node)
        grouped = _per_part_overrides(node)
        groups = _invert(aliases[name]) if node.part_params else None
        spec = registry.lookup(node.stage) if node.part_params else None
        for part in node_parts[name]:
            params = dict(node.params)
            over = overridden
            if node.part_params:
                params.update(_task_part_params(node, part, config, groups))
                try:
                    params = registry.validate_params(spec, params)  # type: ignore[arg-type]
                except registry.ParamError as e:
                    p = next((q for q in node.part_params if q in str(e)),
                             next(iter(node.part_params)))
                    raise _param_error(node, config, p, f"part {part}: {e}") from None
                if grouped:
                    over = {i: f for i, f in overridden.items() if i not in grouped}
                    over.update({i: str(params[p]) for i, p in grouped.items()
                                 if params.get(p) is not None})
            inputs = _task_inputs(node, part, config, node_parts, index, over, part_match,
                                  matchers, aliases)
            params = _resolve_sidecars(node.stage, params, inputs)
            seed = params.get("seed") if isinstance(params.get("seed"), int) else 0
            if node.seeds is not None:
                seed = int(part.rsplit("seed=", 1)[1])  # type: ignore[union-attr]
                if "seed" in params:
                    params["seed"] = seed
            t = Task(index=len(tasks), node=name, part=part, stage=node.stage, params=params,
                     inputs=inputs, seed=int(seed or 0))
            index[(name, part)] = t.index
            tasks.append(t)
    return Graph(config=config, targets=targets, nodes=order, node_parts=node_parts,
                 tasks=tasks)


def _task_inputs(node: NodeConfig, part: str | None, config: GraphConfig,
                 node_parts: Mapping[str, list[str | None]],
                 index: Mapping[tuple[str, str | None], int], overridden: Mapping[str, str],
                 part_match: Any, matchers: dict[str, Any],
                 aliases: Mapping[str, Mapping[str, str] | None]) -> dict[str, Wire]:
    """The wires of the task ``(node, part)`` (its upstream tasks are already indexed)."""
    inputs: dict[str, Wire] = {}
    for iname, w in node.inputs.items():
        if iname in overridden:
            inputs[iname] = FileWire(overridden[iname])
            continue
        if w == "part":
            if node.gather:
                inputs[iname] = FilesWire(tuple(config.part_path(p) for p in config.parts))
            else:
                inputs[iname] = FileWire(config.part_path(part_match(part)))
            continue
        up, out = w
        up_parts = node_parts[up]
        if node.gather:
            inputs[iname] = TasksWire(tuple(TaskWire(index[(up, p)], out) for p in up_parts))
        else:
            match = matchers.get(up)
            if match is None:
                match = matchers[up] = _matcher(up_parts, aliases.get(up))
            p = match(part)
            inputs[iname] = TaskWire(index[(up, p)], out)
    return inputs


def _invert(alias: Mapping[str, str] | None) -> dict[str, list[str]] | None:
    """``task part -> parts`` from ``part -> task part``."""
    if alias is None:
        return None
    out: dict[str, list[str]] = {}
    for q, g in alias.items():
        out.setdefault(g, []).append(q)
    return out


def load_graph(path: str | os.PathLike, *, sets: Iterable[str] | Mapping[str, Any] = (),
               parts: Sequence[str] | None = None, targets: Sequence[str] | None = None,
               all_nodes: bool = False) -> Graph:
    """Read a config and expand it into a graph (what every CLI verb does first).

    Parameters
    ----------
    path : path-like
        The YAML file.
    sets, parts
        Overrides, as for :func:`~mocapflow.pipeline.config.load_config`.
    targets : sequence of str, optional
        Target nodes (default: the config's targets).
    all_nodes : bool
        Every node of the config is a target (``targets`` is ignored).

    Returns
    -------
    Graph
        The modules named in ``MOCAPFLOW_STAGE_MODULES`` are imported first.
    """
    load_stage_modules()
    cfg = load_config(path, sets=sets, parts=parts)
    if all_nodes:
        targets = list(cfg.nodes)
    return build_graph(cfg, targets)


def _resolve_sidecars(
    stage: str, params: dict[str, Any], inputs: Mapping[str, Wire]
) -> dict[str, Any]:
    """Fill ``FilePath`` params left ``None`` whose stage declares a sidecar resolver.

    The resolver gets the task's single input file; a resolved path that does not
    exist is left ``None`` (the stage then reports the missing file itself).
    """
    spec = registry.lookup(stage)
    resolvers = spec.extra.get("sidecars", {}) if spec is not None else {}
    files = [w.path for w in inputs.values() if isinstance(w, FileWire)]
    if not resolvers or len(files) != 1:
        return params
    for name, resolve in resolvers.items():
        if params.get(name) is None:
            path = resolve(files[0])
            if os.path.isfile(path):
                params[name] = str(path)
    return params
