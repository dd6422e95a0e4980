"""Graph configs: YAML → a validated graph spec (data only, never executed).

A config names stages, wires their inputs, sets their params and says how they
fan out (see the project README for the format).  Loading it checks
everything the engine can check before running anything; every problem is a
:class:`ConfigError` whose message is one line ``FILE:LINE: key: problem``.

:func:`parse_config` reads the document with line numbers
(:mod:`~mocapflow.pipeline.config_yaml`), applies shared-param overrides,
interpolates ``${params.NAME}`` and ``${env:VAR,default}``
(:mod:`~mocapflow.pipeline.config_interpolation`), expands parts
(:mod:`~mocapflow.pipeline.config_parts`; a part entry may be a capture session,
:mod:`~mocapflow.pipeline.session`, whose trials' fields are kept in
:attr:`GraphConfig.part_fields`), then validates, in this
order: name and description, parts, nodes (stage, inputs, seeds, gather,
params), wiring, cycles, per-part params, fan-out, targets, file params.

Per-part params
---------------
A node param whose whole value is ``${part.FIELD}`` or ``${part.FIELD,DEFAULT}``
is kept as a :class:`~mocapflow.pipeline.config_interpolation.PartRef` in
:attr:`NodeConfig.part_params`; :attr:`NodeConfig.params` holds its default
(validated here; ``None`` without one).  The graph resolves it per task and
validates each task's params with the stage's validator
(:func:`~mocapflow.pipeline.graph.build_graph`).  Only a node fanned out over
parts (wired to ``part``, or below a node that is, and not a gather) may have
one.

Loading is bounded (see :mod:`~mocapflow.pipeline.config_yaml` for the YAML
limits): a graph fans out to at most :data:`MAX_TASKS` tasks (parts × seeds,
counted per node before any task is made), seeds are integers in
``[0, 2**32)`` (the context keeps 32 bits of a seed), and numbers in params are
checked by :func:`~mocapflow.pipeline.registry.coerce` (finite, at most
:data:`~mocapflow.pipeline.registry.MAX_PARAM_MAGNITUDE` in magnitude).

Command-line overrides
----------------------
``sets=["node.param=value", ...]`` (values parsed as YAML; ``params.NAME=value``
sets a shared param before interpolation; ``node.seeds=…`` replaces the node's
``seeds:`` fan-out: a list of seeds, ``{count: N}``, an integer ``N`` for seeds
``0 … N−1``, or ``null`` for one task) and ``parts=[glob, ...]`` (replaces the
config's parts).
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import re
import types
import typing
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path
from typing import Any

from mocapflow.pipeline import registry
from mocapflow.pipeline.config_interpolation import Budget, PartRef, interpolate
from mocapflow.pipeline.config_parts import expand_parts
from mocapflow.pipeline.config_yaml import (
    MAX_CONFIG_BYTES,
    ConfigError,
    FileErrors,
    LineDict,
    LineList,
    close_match,
    line_of,
    load_yaml,
    parse_yaml_value,
    short,
)
from mocapflow.pipeline.registry import FilePath, ParamError, StageSpec

__all__ = [
    "CMDLINE",
    "MAX_SEED",
    "MAX_TASKS",
    "STAGE_MODULES_ENV",
    "ConfigError",
    "GraphConfig",
    "NodeConfig",
    "PartRef",
    "expand_parts",
    "filepath_params",
    "load_config",
    "load_stage_modules",
    "parse_config",
    "resolve_config",
    "resolve_stage",
    "shipped_configs",
]

TOP_KEYS = ("graph", "description", "params", "parts", "targets", "nodes")
NODE_KEYS = ("stage", "inputs", "params", "seeds", "gather", "description")
#: Environment variable: comma-separated modules imported for their ``@stage``
#: registrations (a quick way to use stage families that are not installed).
STAGE_MODULES_ENV = "MOCAPFLOW_STAGE_MODULES"
CMDLINE = "<command line>"
#: Most tasks a graph may fan out to (every node's parts × seeds, summed).
MAX_TASKS = 1_000_000
#: Seeds are below this (``ctx.rng`` is seeded from 32 bits of the seed).
MAX_SEED = 2**32

_NODE_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")


# --------------------------------------------------------------------------- spec


@dataclass
class NodeConfig:
    """One node of a graph config, validated.

    Attributes
    ----------
    name : str
        Node name (unique in the graph).
    stage : str
        Registered stage name.
    inputs : dict
        ``input -> "part"`` or ``input -> ("node", "output")``.
    params : dict
        Validated params, defaults filled (``seed`` is set per task for ``seeds:``).
    seeds : list of int or None
        Seed fan-out (one task per upstream part and seed): sets the stage's
        ``seed`` param if it has one, and the context's seed in any case.
    gather : bool
        One task over all parts (each input becomes a list ordered by part).
    line : int
        Line of the node in the config.
    part_params : dict
        ``param -> PartRef`` for per-part params (``${part.FIELD,DEFAULT}``); their
        entry in :attr:`params` is the default (``None`` without one).
    """

    name: str
    stage: str
    inputs: dict[str, Any]
    params: dict[str, Any]
    seeds: list[int] | None = None
    gather: bool = False
    line: int = 0
    description: str = ""
    param_lines: dict[str, int] = field(default_factory=dict)
    part_params: dict[str, PartRef] = field(default_factory=dict)

    def upstream(self) -> list[str]:
        """Names of the nodes this node reads from (sorted, unique)."""
        return sorted({w[0] for w in self.inputs.values() if isinstance(w, tuple)})

    @property
    def spec(self) -> StageSpec:
        """The registered stage."""
        return resolve_stage(self.stage)


@dataclass
class GraphConfig:
    """A validated graph config.

    Attributes
    ----------
    name : str
        ``graph:`` name (the file stem when absent).
    path : Path
        The config file.
    params : dict
        Shared params after overrides and interpolation.
    parts : list of str
        Part ids (globs expanded, in config order, duplicates removed): each
        file's normalised path relative to :attr:`root`, or its absolute path
        when it was given as one (see :func:`expand_parts`).
    targets : list of str
        Default target nodes (all nodes when the config names none).
    nodes : dict
        ``name -> NodeConfig`` in topological order (ties in config order).
    overrides : dict
        The command-line overrides applied (``set``, ``parts``).
    root : str or None
        Absolute folder that relative part ids are relative to: the config
        file's folder (the working directory for a config given as text).
        ``None``: part ids are the files' paths.
    part_fields : dict
        ``part id -> {field: value}`` for the trials of capture sessions (an
        ordinary part has none): what ``${part.FIELD}`` params read.
    """

    name: str
    path: Path
    description: str
    params: dict[str, Any]
    parts: list[str]
    targets: list[str]
    nodes: dict[str, NodeConfig]
    overrides: dict[str, Any] = field(default_factory=dict)
    root: str | None = None
    part_fields: dict[str, dict[str, Any]] = field(default_factory=dict)

    def part_path(self, part: str) -> str:
        """The file of part id ``part`` (absolute when :attr:`root` is set)."""
        if self.root is None or os.path.isabs(part):
            return part
        return os.path.normpath(os.path.join(self.root, part))

    @property
    def file(self) -> str:
        """The config path as a string (for messages)."""
        return str(self.path)


# --------------------------------------------------------------------------- stages


def resolve_stage(name: str) -> StageSpec:
    """The stage registered as ``name``, importing only its module where it can.

    See :func:`mocapflow.pipeline.registry.find_stage`.

    Raises
    ------
    KeyError
        Unknown stage (the message has close matches).
    """
    return registry.find_stage(name)


def load_stage_modules(modules: Iterable[str] | None = None, *, discover: bool = False) -> None:
    """Import the modules named in ``MOCAPFLOW_STAGE_MODULES`` (and ``modules``).

    Parameters
    ----------
    modules : iterable of str, optional
        Extra modules to import (their ``@stage`` decorators register them).
    discover : bool
        Also import every family registered under the ``mocapflow.stages`` entry
        points now (otherwise families are imported on demand, see
        :func:`resolve_stage`).
    """
    if discover:
        registry.discover()
    names = list(modules or [])
    names += [m.strip() for m in os.environ.get(STAGE_MODULES_ENV, "").split(",") if m.strip()]
    for name in names:
        try:
            importlib.import_module(name)
        except ImportError as e:
            raise ConfigError(f"cannot import stage module {name!r}: {e}",
                              file=STAGE_MODULES_ENV) from None


def is_filepath_annotation(ann: Any) -> bool:
    """``FilePath`` or ``FilePath | None`` (or a union containing ``FilePath``)."""
    if ann is FilePath:
        return True
    if typing.get_origin(ann) in (typing.Union, types.UnionType):
        return any(a is FilePath for a in typing.get_args(ann))
    return False


def filepath_params(spec: StageSpec) -> tuple[str, ...]:
    """Names of the stage's params annotated ``FilePath`` / ``FilePath | None``."""
    return tuple(n for n, (ann, _) in spec.params.items() if is_filepath_annotation(ann))


# --------------------------------------------------------------------------- load


def shipped_configs() -> dict[str, Path]:
    """The graphs shipped in the package (``mocapflow.configs``), by name.

    Returns
    -------
    dict
        ``{name: path}`` for every ``<name>.yaml`` of the package that is a graph
        (the demo descriptions ``demo*.yaml`` are not).
    """
    try:
        base = Path(str(files("mocapflow.configs")))
    except (ModuleNotFoundError, TypeError):  # pragma: no cover - not installed
        return {}
    return {p.stem: p for p in sorted(base.glob("*.yaml")) if not p.stem.startswith("demo")}


def resolve_config(config: str | os.PathLike) -> Path:
    """A config path, or the name of a shipped graph (``texture``) as its path.

    A name (no folder, no ``.yaml``) that is not a file in the working directory
    is looked up in :func:`shipped_configs`.

    Raises
    ------
    ConfigError
        Neither a file nor a shipped graph (the message lists the shipped names).
    """
    path = Path(config)
    if path.exists():
        return path
    text = str(config)
    shipped = shipped_configs()
    if os.sep not in text and "/" not in text and not path.suffix:
        if text in shipped:
            return shipped[text]
        names = ", ".join(shipped) or "none installed"
        hint = close_match(text, list(shipped))
        raise ConfigError(f"no config file or shipped graph named {text!r}"
                          f"{hint} (shipped graphs: {names})", file=text)
    return path


def load_config(
    path: str | os.PathLike,
    *,
    sets: Iterable[str] | Mapping[str, Any] = (),
    parts: Sequence[str] | None = None,
    env: Mapping[str, str] | None = None,
) -> GraphConfig:
    """Read and validate a graph config.

    Parameters
    ----------
    path : path-like
        The YAML file, or the name of a shipped graph (:func:`resolve_config`).
    sets : iterable of ``"node.param=value"`` or mapping ``{"node.param": value}``
        Overrides (string values are parsed as YAML).  ``params.NAME`` sets a
        shared param.
    parts : sequence of str, optional
        Paths/globs replacing the config's ``parts:``.
    env : mapping, optional
        Environment for ``${env:...}`` (default ``os.environ``).

    Returns
    -------
    GraphConfig

    Raises
    ------
    ConfigError
        With ``FILE:LINE: key: problem``.
    """
    path = resolve_config(path)
    file = str(path)
    try:
        if path.stat().st_size > MAX_CONFIG_BYTES:
            raise ConfigError(f"config is larger than {MAX_CONFIG_BYTES >> 20} MiB", file=file)
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError("config file not found", file=file) from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"cannot read config: {e}", file=file) from None
    return parse_config(text, file=file, path=path, sets=sets, parts=parts, env=env)


def _parse_sets(sets: Iterable[str] | Mapping[str, Any]) -> list[tuple[str, str, Any]]:
    items: list[tuple[str, str, Any]] = []
    if isinstance(sets, Mapping):
        pairs = [(str(k), v) for k, v in sets.items()]
    else:
        pairs = []
        for s in sets:
            lhs, eq, rhs = str(s).partition("=")
            if not eq:
                raise ConfigError("expected NODE.PARAM=VALUE", file=CMDLINE, key=f"--set {s}")
            pairs.append((lhs.strip(), parse_yaml_value(rhs, file=CMDLINE,
                                                        key=f"--set {lhs.strip()}")))
    for lhs, value in pairs:
        node, dot, param = lhs.partition(".")
        if not dot or not node or not param:
            raise ConfigError("expected NODE.PARAM=VALUE", file=CMDLINE, key=f"--set {lhs}")
        items.append((node, param, value))
    return items


# --------------------------------------------------------------------------- parse


def parse_config(
    text: str,
    *,
    file: str = "<string>",
    path: Path | None = None,
    sets: Iterable[str] | Mapping[str, Any] = (),
    parts: Sequence[str] | None = None,
    env: Mapping[str, str] | None = None,
) -> GraphConfig:
    """Validate config text (see :func:`load_config`)."""
    c = FileErrors(file)
    env = os.environ if env is None else env
    set_items = _parse_sets(sets)
    doc = _load_document(text, c)
    shared = _shared_params(doc, set_items, env, c)
    doc_i = _interpolate_document(doc, shared, env, c)
    name, description = _name_and_description(doc_i, doc, path, c)
    root = os.path.abspath(path.parent if path is not None else os.curdir)
    part_fields: dict[str, dict[str, Any]] = {}
    part_ids = _part_ids(doc_i, doc, parts, c, root, part_fields)
    nodes = _parse_nodes(doc_i, doc, set_items, bool(part_ids), c)
    _check_part_params(nodes, doc_i["nodes"], c)
    _check_fan_out(nodes, doc_i["nodes"], len(part_ids), c)
    targets = _targets(doc_i, doc, nodes, c)
    _check_file_params(nodes, c)
    return GraphConfig(
        name=name,
        path=path if path is not None else Path(file),
        description=description,
        params=shared,
        parts=part_ids,
        targets=targets,
        nodes=nodes,
        overrides=_overrides(set_items, parts),
        root=root,
        part_fields=part_fields,
    )


def _load_document(text: str, c: FileErrors) -> LineDict:
    """The YAML document: a mapping of known top-level keys, with ``nodes:``."""
    doc = load_yaml(text, c.file)
    if not isinstance(doc, dict):
        raise c.err("", "a graph config must be a YAML mapping with a nodes: key",
                    getattr(doc, "line", 1))
    for k in doc:
        if k not in TOP_KEYS:
            raise c.err(str(k), f"unknown top-level key{close_match(k, TOP_KEYS)}",
                        line_of(doc, k))
    if "nodes" not in doc:
        raise c.err("nodes", "missing (a graph needs at least one node)", 1)
    return doc


def _shared_params(doc: LineDict, set_items: list[tuple[str, str, Any]],
                   env: Mapping[str, str], c: FileErrors) -> dict[str, Any]:
    """``params:`` with ``--set params.NAME=...`` applied, each value interpolated."""
    shared_raw = doc.get("params") or LineDict()
    if not isinstance(shared_raw, dict):
        raise c.err("params", "must be a mapping", line_of(doc, "params"))
    shared_raw = LineDict(shared_raw) if not isinstance(shared_raw, LineDict) else shared_raw
    for node, param, value in set_items:
        if node == "params" and "params" not in (doc.get("nodes") or {}):
            if param not in shared_raw:
                raise ConfigError(f"unknown shared param{close_match(param, shared_raw)} "
                                  f"(shared params: {', '.join(map(str, shared_raw)) or 'none'})",
                                  file=CMDLINE, key=f"--set params.{param}")
            shared_raw[param] = value
    shared: dict[str, Any] = {}
    budget = Budget()
    for k, v in shared_raw.items():
        shared[k] = interpolate(v, shared_raw, env, c, f"params.{k}", line_of(shared_raw, k),
                                (str(k),), budget=budget, depth=2)
    return shared


def _interpolate_document(doc: LineDict, shared: Mapping[str, Any], env: Mapping[str, str],
                          c: FileErrors) -> LineDict:
    """Every top-level value but ``params:``, interpolated (lines kept)."""
    rest = {k: v for k, v in doc.items() if k != "params"}
    rest_i = LineDict()
    rest_i.lines = dict(doc.lines)
    budget = Budget()
    for k, v in rest.items():
        rest_i[k] = interpolate(v, shared, env, c, str(k), line_of(doc, k), budget=budget,
                                depth=1)
    return rest_i


def _name_and_description(doc_i: LineDict, doc: LineDict, path: Path | None, c: FileErrors
                          ) -> tuple[str, str]:
    """``graph:`` (default: the file stem) and ``description:``."""
    name = doc_i.get("graph", path.stem if path is not None else "graph")
    if not isinstance(name, str):
        raise c.err("graph", "must be a string", line_of(doc, "graph"))
    description = doc_i.get("description", "") or ""
    if not isinstance(description, str):
        raise c.err("description", "must be a string", line_of(doc, "description"))
    return name, description


def _part_ids(doc_i: LineDict, doc: LineDict, parts: Sequence[str] | None, c: FileErrors,
              root: str, fields: dict[str, dict[str, Any]]) -> list[str]:
    """Part ids from ``--parts`` (when given: relative to the working directory) or
    ``parts:`` (relative to the config's folder ``root``), expressed relative to ``root``
    (the fields of session trials go to ``fields``)."""
    if parts is not None:
        return expand_parts(list(parts), FileErrors(CMDLINE), "--parts", relative_to=root,
                            fields=fields)
    raw_parts = doc_i.get("parts") or []
    if isinstance(raw_parts, str):
        raw_parts = LineList([raw_parts])
        raw_parts.lines = [line_of(doc, "parts") or 0]
    if not isinstance(raw_parts, list):
        raise c.err("parts", "must be a list of paths/globs", line_of(doc, "parts"))
    try:
        return expand_parts(raw_parts, c, "parts", getattr(raw_parts, "lines", None), base=root,
                            relative_to=root, fields=fields)
    except ConfigError as e:
        hint = _env_hint(doc.get("parts"))
        if not hint:
            raise
        raise ConfigError(e.problem + hint, file=e.file, line=e.line, key=e.key) from None


def _env_hint(raw: Any) -> str:
    """`` (set VAR ...)`` for the environment variables that a missing part came from."""
    texts = raw if isinstance(raw, list) else [raw]
    names = sorted({m for t in texts if isinstance(t, str)
                    for m in re.findall(r"\$\{env:([A-Za-z_][A-Za-z0-9_]*)", t)})
    if not names:
        return ""
    said = ", ".join(f"{n}={os.environ[n]!r}" if n in os.environ else f"{n} unset"
                     for n in names)
    return f"; the path comes from ${{env:{names[0]}}} ({said}): set it to the folder " \
           "holding the data, or pass --parts"


def _parse_nodes(doc_i: LineDict, doc: LineDict, set_items: list[tuple[str, str, Any]],
                 has_parts: bool, c: FileErrors) -> dict[str, NodeConfig]:
    """Every node validated, wiring checked, in topological order."""
    raw_nodes = doc_i["nodes"]
    if not isinstance(raw_nodes, dict) or not raw_nodes:
        raise c.err("nodes", "must be a non-empty mapping of node names", line_of(doc, "nodes"))
    node_sets = _node_sets(set_items, raw_nodes)
    for nname in raw_nodes:
        if not isinstance(nname, str):
            raise c.err(f"nodes.{nname}", f"node name {nname!r} is not a string (YAML reads "
                        "yes/no/on/off/true/false and numbers as such: quote the name)",
                        line_of(raw_nodes, nname))
    nodes: dict[str, NodeConfig] = {}
    for nname, body in raw_nodes.items():
        nodes[str(nname)] = _parse_node(str(nname), body, raw_nodes, c, has_parts,
                                        node_sets.get(str(nname), {}))
    _check_wiring(nodes, raw_nodes, c)
    order = _toposort(nodes, raw_nodes, c)
    return {n: nodes[n] for n in order}


def _node_sets(set_items: list[tuple[str, str, Any]], raw_nodes: Mapping[str, Any]
               ) -> dict[str, dict[str, Any]]:
    """``node -> {param: value}`` from ``--set NODE.PARAM=VALUE`` (unknown nodes are errors)."""
    node_sets: dict[str, dict[str, Any]] = {}
    for node, param, value in set_items:
        if node == "params" and "params" not in raw_nodes:
            continue
        if node not in raw_nodes:
            raise ConfigError(f"unknown node {node!r}{close_match(node, raw_nodes)}",
                              file=CMDLINE, key=f"--set {node}.{param}")
        node_sets.setdefault(node, {})[param] = value
    return node_sets


def _targets(doc_i: LineDict, doc: LineDict, nodes: Mapping[str, NodeConfig], c: FileErrors
             ) -> list[str]:
    """``targets:`` (default: every node), each a known node."""
    raw_targets = doc_i.get("targets")
    if raw_targets is None:
        return list(nodes)
    if isinstance(raw_targets, str):
        raw_targets = [raw_targets]
    if not isinstance(raw_targets, list) or not raw_targets:
        raise c.err("targets", "must be a list of node names", line_of(doc, "targets"))
    targets = []
    for i, t in enumerate(raw_targets):
        if t not in nodes:
            raise c.err(f"targets[{i}]", f"unknown node {t!r}{close_match(str(t), nodes)}",
                        line_of(raw_targets, i) or line_of(doc, "targets"))
        targets.append(t)
    return targets


def _check_file_params(nodes: Mapping[str, NodeConfig], c: FileErrors) -> None:
    """Every ``FilePath`` param that is set names an existing file."""
    for n in nodes.values():
        for p in filepath_params(n.spec):
            v = n.params.get(p)
            if v is not None and not os.path.isfile(str(v)):
                raise c.err(f"nodes.{n.name}.params.{p}", f"missing input file {v!r}",
                            n.param_lines.get(p, n.line))


def _overrides(set_items: list[tuple[str, str, Any]], parts: Sequence[str] | None
               ) -> dict[str, Any]:
    """The command-line overrides as recorded in run records and locks."""
    overrides: dict[str, Any] = {}
    if set_items:
        overrides["set"] = {f"{a}.{b}": v for a, b, v in set_items}
    if parts is not None:
        overrides["parts"] = list(parts)
    return overrides


# --------------------------------------------------------------------------- nodes


def _parse_node(name: str, body: Any, raw_nodes: Any, c: FileErrors, has_parts: bool,
                sets: dict[str, Any]) -> NodeConfig:
    """One node: stage, inputs, seeds, gather, params (``sets``: its ``--set`` values)."""
    nline = line_of(raw_nodes, name)
    key = f"nodes.{name}"
    spec = _node_stage(name, body, key, nline, c)
    inputs = _node_inputs(body, spec, raw_nodes, has_parts, key, nline, c)
    seeds = None
    sets = dict(sets)
    if "seeds" in sets:  # --set NODE.seeds=...: the node's fan-out from the command line
        raw = sets.pop("seeds")
        if isinstance(raw, int) and not isinstance(raw, bool):
            raw = {"count": raw}  # N: seeds 0 .. N-1
        if raw is not None:
            seeds = _parse_seeds(raw, FileErrors(CMDLINE), f"--set {name}.seeds", None)
    elif "seeds" in body and body["seeds"] is not None:
        seeds = _parse_seeds(body["seeds"], c, f"{key}.seeds", line_of(body, "seeds"))
    gather = body.get("gather", False)
    if not isinstance(gather, bool):
        raise c.err(f"{key}.gather", "must be true or false", line_of(body, "gather"))
    params, lines, part_params = _node_params(name, body, spec, sets, seeds, key, nline, c)
    description = body.get("description", "") or ""
    return NodeConfig(
        name=name,
        stage=body["stage"],
        inputs=inputs,
        params=params,
        seeds=seeds,
        gather=gather,
        line=nline or 0,
        description=str(description),
        param_lines={p: ln for p, ln in lines.items() if ln},
        part_params=part_params,
    )


def _node_stage(name: str, body: Any, key: str, nline: int | None, c: FileErrors
                ) -> StageSpec:
    """The node's stage (the node name and keys checked first)."""
    if not _NODE_NAME.match(name):
        raise c.err(key, "a node name must be letters, digits, _ or - (no dots or slashes)", nline)
    if not isinstance(body, dict):
        raise c.err(key, "a node must be a mapping with a stage: key", nline)
    for k in body:
        if k not in NODE_KEYS:
            raise c.err(f"{key}.{k}", f"unknown node key{close_match(k, NODE_KEYS)}",
                        line_of(body, k))
    if "stage" not in body:
        raise c.err(key, "missing stage:", nline)
    sname = body["stage"]
    sline = line_of(body, "stage")
    if not isinstance(sname, str):
        raise c.err(f"{key}.stage", "must be a stage name", sline)
    try:
        return resolve_stage(sname)
    except KeyError as e:
        raise c.err(f"{key}.stage", str(e.args[0]), sline) from None


def _node_inputs(body: Mapping[str, Any], spec: StageSpec, raw_nodes: Any, has_parts: bool,
                 key: str, nline: int | None, c: FileErrors) -> dict[str, Any]:
    """``input -> "part" | (node, output)``: every input of the stage wired, once."""
    sname = body["stage"]
    raw_inputs = body.get("inputs") or LineDict()
    iline = line_of(body, "inputs") or nline
    if not isinstance(raw_inputs, dict):
        raise c.err(f"{key}.inputs", "must be a mapping input: node.output", iline)
    inputs: dict[str, Any] = {}
    for iname, wire in raw_inputs.items():
        ik = f"{key}.inputs.{iname}"
        il = line_of(raw_inputs, iname)
        if iname not in spec.inputs:
            raise c.err(ik, f"stage {sname!r} has no input {iname!r}"
                        f"{close_match(iname, spec.inputs)}"
                        f" (inputs: {', '.join(spec.inputs) or 'none'})", il)
        if wire == "part":
            if not has_parts:
                raise c.err(ik, "wired to part but the config has no parts (give parts: or "
                            "--parts)", il)
            inputs[iname] = "part"
            continue
        if not isinstance(wire, str) or wire.count(".") != 1:
            raise c.err(ik, f"expected node.output or part, got {short(wire)}", il)
        up, out = wire.split(".")
        if up not in raw_nodes:
            raise c.err(ik, f"unknown node {up!r}{close_match(up, raw_nodes)}", il)
        inputs[iname] = (up, out)
    for iname in spec.inputs:
        if iname not in inputs and iname not in spec.optional_inputs:
            raise c.err(f"{key}.inputs.{iname}", f"input of stage {sname!r} is not wired", iline)
    return inputs


def _node_params(name: str, body: Mapping[str, Any], spec: StageSpec, sets: dict[str, Any],
                 seeds: list[int] | None, key: str, nline: int | None, c: FileErrors
                 ) -> tuple[dict[str, Any], dict[str, int], dict[str, PartRef]]:
    """(validated params with defaults, ``param -> line`` (0: set on the command line),
    per-part params: ``param -> PartRef``, their default validated in ``params``)."""
    sname = body["stage"]
    raw_params = body.get("params") or LineDict()
    pline = line_of(body, "params") or nline
    if not isinstance(raw_params, dict):
        raise c.err(f"{key}.params", "must be a mapping", pline)
    given = dict(raw_params)
    lines = {p: line_of(raw_params, p) or pline for p in raw_params}
    for p, v in sets.items():
        given[p] = v
        lines[p] = 0
    part_params = {p: v for p, v in given.items() if isinstance(v, PartRef)}
    for p, ref in part_params.items():  # validated as its default (per task: its value)
        if ref.has_default:
            given[p] = ref.default
        else:
            del given[p]
    for p, v in given.items():
        where_file = c.file if lines[p] else CMDLINE
        pk = f"{key}.params.{p}" if lines[p] else f"--set {name}.{p}"
        if p not in spec.params:
            raise ConfigError(f"unknown param for stage {sname!r}{close_match(p, spec.params)}",
                              file=where_file, line=lines[p] or None, key=pk)
        if seeds is not None and p == "seed":
            raise ConfigError("seed is set per task by seeds:", file=where_file,
                              line=lines[p] or None, key=pk)
        try:
            value = registry.coerce(v, spec.params[p][0], where=f"{sname}.{p}")
        except ParamError as e:
            raise ConfigError(str(e), file=where_file, line=lines[p] or None, key=pk) from None
        if p == "seed" and isinstance(value, int) and not 0 <= value < MAX_SEED:
            raise ConfigError(f"a seed must be in [0, 2**32), got {short(value)}",
                              file=where_file, line=lines[p] or None, key=pk)
    if seeds is not None and "seed" in spec.params:
        given.setdefault("seed", seeds[0])
    for p in part_params:
        if p not in spec.params:
            raise c.err(f"{key}.params.{p}", f"unknown param for stage {sname!r}"
                        f"{close_match(p, spec.params)}", lines[p] or None)
        if seeds is not None and p == "seed":
            raise c.err(f"{key}.params.{p}", "seed is set per task by seeds:", lines[p] or None)
    unset = [p for p in part_params if p not in given]  # ${part.F} without a default
    check = spec
    if unset:  # a required param given as ${part.F}: checked per task only
        check = dataclasses.replace(spec, params={k: v for k, v in spec.params.items()
                                                  if k not in unset})
    try:
        params = registry.validate_params(check, given)
    except ParamError as e:
        raise c.err(f"{key}.params", str(e), pline) from None
    if unset:
        params = {p: params.get(p) for p in spec.params}
    return params, lines, part_params


def _parse_seeds(raw: Any, c: FileErrors, key: str, line: int | None) -> list[int]:
    if isinstance(raw, dict):
        if set(raw) != {"count"}:
            raise c.err(key, "expected a list of seeds or {count: N}", line)
        n = raw["count"]
        cline = line_of(raw, "count") or line
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise c.err(f"{key}.count", f"expected a positive integer, got {short(n)}", cline)
        if n > MAX_TASKS:
            raise c.err(f"{key}.count", f"{short(n)} seeds: more than the {MAX_TASKS:,} tasks "
                        "a graph may have", cline)
        return list(range(n))
    if isinstance(raw, bool) or not isinstance(raw, list) or not raw:
        raise c.err(key, "expected a non-empty list of seeds or {count: N}", line)
    seeds: list[int] = []
    seen: set[int] = set()
    for i, s in enumerate(raw):
        sline = line_of(raw, i) or line
        if not isinstance(s, int) or isinstance(s, bool):
            raise c.err(f"{key}[{i}]", f"a seed must be an integer, got {short(s)}", sline)
        if not 0 <= s < MAX_SEED:
            raise c.err(f"{key}[{i}]", f"a seed must be in [0, 2**32), got {short(s)}", sline)
        if s in seen:
            raise c.err(f"{key}[{i}]", f"duplicate seed {s}", sline)
        seen.add(s)
        seeds.append(s)
    return seeds


def _check_fan_out(nodes: Mapping[str, NodeConfig], raw_nodes: Any, n_parts: int,
                   c: FileErrors) -> None:
    """At most :data:`MAX_TASKS` tasks in all (counted per node, in topological order).

    A node runs once per part of its finest input (once with no input, or as a
    gather), times its seeds; inputs that a file override replaces do not count.
    """
    fan: dict[str, int] = {}
    total = 0
    for name, n in nodes.items():
        overridden = n.spec.extra.get("file_overrides", {})
        base = 1
        if not n.gather:
            for iname, w in n.inputs.items():
                param = overridden.get(iname, "")
                if (w == "part" and n.params.get(param) is not None
                        and param not in n.part_params):
                    continue  # read once from the file the param names
                base = max(base, n_parts if w == "part" else fan[w[0]])
        seeds = len(n.seeds) if n.seeds is not None else 1
        fan[name] = base * seeds
        total += fan[name]
        if total > MAX_TASKS:
            body = raw_nodes[name]
            how = f" ({base:,} per seed × {seeds:,} seeds)" if seeds > 1 else ""
            key, line = (f"nodes.{name}.seeds", line_of(body, "seeds")) if seeds > 1 else (
                f"nodes.{name}", n.line or None)
            raise c.err(key, f"fans out to {fan[name]:,} tasks{how}: the graph would have "
                        f"{total:,} tasks, more than the {MAX_TASKS:,} it may have", line)


def _check_part_params(nodes: Mapping[str, NodeConfig], raw_nodes: Any, c: FileErrors
                       ) -> None:
    """``${part.FIELD}`` params only on nodes fanned out over parts (not gathers or sources)."""
    per_part: dict[str, bool] = {}
    for name, n in nodes.items():
        per_part[name] = not n.gather and any(
            w == "part" or per_part[w[0]] for w in n.inputs.values())
        if n.part_params and not per_part[name]:
            p = next(iter(n.part_params))
            why = "a gather" if n.gather else "not fanned out over parts (no part input upstream)"
            raise c.err(f"nodes.{name}.params.{p}", f"{n.part_params[p].text} needs a task per "
                        f"part, but node {name!r} has one task: it is {why}",
                        n.param_lines.get(p) or n.line or None)


def _check_wiring(nodes: dict[str, NodeConfig], raw_nodes: Any, c: FileErrors) -> None:
    for n in nodes.values():
        raw_inputs = raw_nodes[n.name].get("inputs") or {}
        for iname, wire in n.inputs.items():
            if not isinstance(wire, tuple):
                continue
            up, out = wire
            outs = nodes[up].spec.outputs
            if out not in outs:
                raise c.err(f"nodes.{n.name}.inputs.{iname}",
                            f"node {up!r} (stage {nodes[up].stage!r}) has no output {out!r}"
                            f"{close_match(out, outs)} (outputs: {', '.join(outs)})",
                            line_of(raw_inputs, iname))


def _toposort(nodes: dict[str, NodeConfig], raw_nodes: Any, c: FileErrors) -> list[str]:
    """Upstream before downstream (ties in config order); iterative, so chains of any length."""
    order: list[str] = []
    state: dict[str, int] = {}  # 1: on the path being visited, 2: done
    for root in nodes:
        if state.get(root):
            continue
        state[root] = 1
        stack = [(root, iter(nodes[root].upstream()))]
        while stack:
            n, ups = stack[-1]
            up = next(ups, None)
            if up is None:
                stack.pop()
                state[n] = 2
                order.append(n)
            elif state.get(up) == 1:
                path = [m for m, _ in stack]
                _raise_cycle(path[path.index(up):] + [up], nodes, raw_nodes, c)
            elif not state.get(up):
                state[up] = 1
                stack.append((up, iter(nodes[up].upstream())))
    return order


def _raise_cycle(cyc: list[str], nodes: dict[str, NodeConfig], raw_nodes: Any,
                 c: FileErrors) -> None:
    """The error of a cycle, at the input of its first node that closes it."""
    first, nxt = cyc[0], cyc[1]
    iname = next(i for i, w in nodes[first].inputs.items()
                 if isinstance(w, tuple) and w[0] == nxt)
    raw_inputs = raw_nodes[first].get("inputs") or {}
    raise c.err(f"nodes.{first}.inputs.{iname}", f"cycle {' -> '.join(reversed(cyc))}",
                line_of(raw_inputs, iname))
