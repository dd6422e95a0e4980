"""Graph configs: YAML → a validated graph spec (data only, never executed).

A config names stages, wires their inputs, sets their params and says how they
fan out (see the project README for the format).  Loading it checks
everything the engine can check before running anything; every problem is a
:class:`ConfigError` whose message is one line ``FILE:LINE: key: problem``.

Interpolation
-------------
``${params.NAME}`` is replaced by the shared param ``NAME`` (``params:`` at the top
level) and ``${env:VAR,default}`` by the environment variable ``VAR`` (or
``default``).  A string that is exactly one reference keeps the value's type
(an environment value is then parsed as YAML, like ``--set`` values); a
reference inside a longer string is formatted into it.

Command-line overrides
----------------------
``sets=["node.param=value", ...]`` (values parsed as YAML; ``params.NAME=value``
sets a shared param before interpolation) and ``parts=[glob, ...]`` (replaces the
config's parts).
"""

from __future__ import annotations

import difflib
import glob
import importlib
import json
import os
import re
import types
import typing
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mocapflow.pipeline import registry
from mocapflow.pipeline.registry import FilePath, ParamError, StageSpec

__all__ = [
    "ConfigError",
    "GraphConfig",
    "NodeConfig",
    "filepath_params",
    "load_config",
    "load_stage_modules",
    "parse_config",
    "resolve_stage",
]

TOP_KEYS = ("graph", "description", "params", "parts", "targets", "nodes")
NODE_KEYS = ("stage", "inputs", "params", "seeds", "gather", "description")
#: Environment variable: comma-separated modules imported for their ``@stage``
#: registrations (a quick way to use stage families that are not installed).
STAGE_MODULES_ENV = "MOCAPFLOW_STAGE_MODULES"
CMDLINE = "<command line>"

_NODE_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")
_REF = re.compile(r"\$\{([^}]*)\}")


class ConfigError(ValueError):
    """A problem in a graph config; ``str(err)`` is ``FILE:LINE: key: problem``.

    Parameters
    ----------
    problem : str
        What is wrong.
    file : str
        Config file (or ``<command line>``).
    line : int, optional
        1-based line of the offending key.
    key : str, optional
        Dotted key path (``nodes.clean.params.alpha1``).
    """

    def __init__(
        self, problem: str, *, file: str = "", line: int | None = None, key: str = ""
    ) -> None:
        self.problem = problem
        self.file = file
        self.line = line
        self.key = key
        where = file + (f":{line}" if line else "")
        parts = [p for p in (where, key, problem) if p]
        super().__init__(": ".join(parts).replace("\n", " "))


# --------------------------------------------------------------------------- YAML with lines


class _LDict(dict):
    """A mapping that remembers the 1-based line of each key."""

    line: int = 0

    def __init__(self, *a: Any, **k: Any) -> None:
        super().__init__(*a, **k)
        self.lines: dict[Any, int] = {}


class _LList(list):
    """A sequence that remembers the 1-based line of each item."""

    line: int = 0

    def __init__(self, *a: Any, **k: Any) -> None:
        super().__init__(*a, **k)
        self.lines: list[int] = []


class _Loader(yaml.SafeLoader):
    """SafeLoader whose mappings and sequences carry line numbers."""


def _construct_mapping(loader: _Loader, node: yaml.MappingNode) -> _LDict:
    loader.flatten_mapping(node)
    out = _LDict()
    out.line = node.start_mark.line + 1
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        if not isinstance(key, (str, int, float, bool)) and key is not None:
            raise yaml.constructor.ConstructorError(
                None, None, "a key must be a scalar", key_node.start_mark
            )
        if key in out:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r}", key_node.start_mark
            )
        out[key] = loader.construct_object(value_node, deep=True)
        out.lines[key] = key_node.start_mark.line + 1
    return out


def _construct_sequence(loader: _Loader, node: yaml.SequenceNode) -> _LList:
    out = _LList()
    out.line = node.start_mark.line + 1
    for item in node.value:
        out.append(loader.construct_object(item, deep=True))
        out.lines.append(item.start_mark.line + 1)
    return out


_Loader.add_constructor("tag:yaml.org,2002:map", _construct_mapping)
_Loader.add_constructor("tag:yaml.org,2002:seq", _construct_sequence)


_PLACEHOLDER = "__mocapflow_ref_{}__"
_PLACEHOLDER_RE = re.compile(r"__mocapflow_ref_(\d+)__")


def _protect_refs(text: str) -> tuple[str, list[str]]:
    """Replace ``${...}`` by plain-scalar placeholders so ``{rate: ${params.rate}}`` parses."""
    table: list[str] = []

    def sub(m: re.Match) -> str:
        table.append(m.group(0))
        return _PLACEHOLDER.format(len(table) - 1)

    return _REF.sub(sub, text), table


def _restore_refs(value: Any, table: list[str]) -> Any:
    if isinstance(value, str):
        if "__mocapflow_ref_" not in value:
            return value
        return _PLACEHOLDER_RE.sub(lambda m: table[int(m.group(1))], value)
    if isinstance(value, dict):
        for k in list(value):
            value[k] = _restore_refs(value[k], table)
    elif isinstance(value, list):
        for i, v in enumerate(value):
            value[i] = _restore_refs(v, table)
    return value


def _load_yaml(text: str, file: str) -> Any:
    text, table = _protect_refs(text)
    try:
        return _restore_refs(yaml.load(text, Loader=_Loader), table)  # noqa: S506 - SafeLoader
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        line = mark.line + 1 if mark is not None else None
        problem = " ".join(str(x) for x in (e.context, e.problem) if x) or "malformed YAML"
        raise ConfigError(f"malformed YAML: {problem}", file=file, line=line, key="yaml") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"malformed YAML: {e}", file=file, key="yaml") from None


def _line_of(container: Any, key: Any) -> int | None:
    lines = getattr(container, "lines", None)
    if isinstance(lines, dict):
        return lines.get(key) or getattr(container, "line", None)
    if isinstance(lines, list) and isinstance(key, int) and key < len(lines):
        return lines[key]
    return getattr(container, "line", None)


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
        File parts (globs expanded, in config order, duplicates removed).
    targets : list of str
        Default target nodes (all nodes when the config names none).
    nodes : dict
        ``name -> NodeConfig`` in topological order (ties in config order).
    overrides : dict
        The command-line overrides applied (``set``, ``parts``).
    """

    name: str
    path: Path
    description: str
    params: dict[str, Any]
    parts: list[str]
    targets: list[str]
    nodes: dict[str, NodeConfig]
    overrides: dict[str, Any] = field(default_factory=dict)

    @property
    def file(self) -> str:
        """The config path as a string (for messages)."""
        return str(self.path)


# --------------------------------------------------------------------------- helpers


def resolve_stage(name: str) -> StageSpec:
    """The stage registered as ``name``, discovering the installed families if needed.

    Raises
    ------
    KeyError
        Unknown stage (the message has close matches).
    """
    spec = registry.lookup(name)
    return spec if spec is not None else registry.get_stage(name)


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


def _parse_yaml_value(text: str) -> Any:
    try:
        return yaml.safe_load(text) if text.strip() else None
    except yaml.YAMLError:
        return text


def _close(name: str, options: Iterable[str]) -> str:
    m = difflib.get_close_matches(str(name), [str(o) for o in options], n=1)
    return f" (did you mean {m[0]!r}?)" if m else ""


class _Ctx:
    """Error factory bound to one file."""

    def __init__(self, file: str) -> None:
        self.file = file

    def err(self, key: str, problem: str, line: int | None = None) -> ConfigError:
        return ConfigError(problem, file=self.file, line=line, key=key)


# --------------------------------------------------------------------------- interpolation


def _resolve_ref(ref: str, params: Mapping[str, Any], env: Mapping[str, str], c: _Ctx,
                 key: str, line: int | None, stack: tuple[str, ...]) -> Any:
    ref = ref.strip()
    if ref.startswith("env:"):
        body = ref[4:]
        var, sep, default = body.partition(",")
        var = var.strip()
        if not var:
            raise c.err(key, f"empty environment reference ${{{ref}}}", line)
        if var in env:
            return _parse_yaml_value(env[var])
        if sep:
            return _parse_yaml_value(default.strip())
        raise c.err(key, f"environment variable {var} is not set and has no default", line)
    if ref.startswith("params."):
        name = ref[len("params."):]
        if name in stack:
            raise c.err(key, f"circular reference ${{{ref}}}", line)
        if name not in params:
            raise c.err(key, f"unknown shared param ${{{ref}}}{_close(name, params)}", line)
        return _interpolate(params[name], params, env, c, key, line, (*stack, name))
    raise c.err(key, f"cannot interpolate ${{{ref}}} "
                "(use ${params.NAME} or ${env:VAR,default})", line)


def _interpolate(value: Any, params: Mapping[str, Any], env: Mapping[str, str], c: _Ctx,
                 key: str, line: int | None, stack: tuple[str, ...] = ()) -> Any:
    """Interpolate ``${...}`` references in ``value`` (recursively), keeping line info."""
    if isinstance(value, str):
        whole = _REF.fullmatch(value.strip())
        if whole:
            return _resolve_ref(whole.group(1), params, env, c, key, line, stack)
        if "${" not in value:
            return value

        def sub(m: re.Match) -> str:
            v = _resolve_ref(m.group(1), params, env, c, key, line, stack)
            return v if isinstance(v, str) else json.dumps(v)

        return _REF.sub(sub, value)
    if isinstance(value, dict):
        out = _LDict()
        out.line = getattr(value, "line", line or 0)
        for k, v in value.items():
            kl = _line_of(value, k) or line
            out[k] = _interpolate(v, params, env, c, f"{key}.{k}" if key else str(k), kl, stack)
            out.lines[k] = kl or 0
        return out
    if isinstance(value, list):
        out_l = _LList()
        out_l.line = getattr(value, "line", line or 0)
        for i, v in enumerate(value):
            il = _line_of(value, i) or line
            out_l.append(_interpolate(v, params, env, c, f"{key}[{i}]", il, stack))
            out_l.lines.append(il or 0)
        return out_l
    return value


# --------------------------------------------------------------------------- parts


def expand_parts(entries: Sequence[Any], c: _Ctx, key: str, lines: Sequence[int] | None = None
                 ) -> list[str]:
    """Expand part entries (paths or globs, relative to the working directory).

    Returns
    -------
    list of str
        Part ids: each path as given (globs: as matched), duplicates removed.
    """
    out: list[str] = []
    seen: set[str] = set()
    for i, entry in enumerate(entries):
        line = lines[i] if lines is not None and i < len(lines) else None
        k = f"{key}[{i}]" if lines is not None else key
        if not isinstance(entry, str) or not entry:
            raise c.err(k, f"a part must be a file path or glob, got {entry!r}", line)
        if glob.has_magic(entry):
            found = sorted(p for p in glob.glob(entry, recursive=True) if os.path.isfile(p))
            if not found:
                raise c.err(k, f"no file matches {entry!r}", line)
        else:
            if not os.path.exists(entry):
                raise c.err(k, f"missing input file {entry!r}", line)
            if os.path.isdir(entry):
                raise c.err(k, f"{entry!r} is a directory (use a glob such as {entry}/*.bvh)",
                            line)
            found = [entry]
        for p in found:
            if p not in seen:
                seen.add(p)
                out.append(p)
    return out


# --------------------------------------------------------------------------- main entry


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
        The YAML file.
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
    path = Path(path)
    file = str(path)
    try:
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
            pairs.append((lhs.strip(), _parse_yaml_value(rhs)))
    for lhs, value in pairs:
        node, dot, param = lhs.partition(".")
        if not dot or not node or not param:
            raise ConfigError("expected NODE.PARAM=VALUE", file=CMDLINE, key=f"--set {lhs}")
        items.append((node, param, value))
    return items


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
    c = _Ctx(file)
    env = os.environ if env is None else env
    set_items = _parse_sets(sets)
    doc = _load_yaml(text, file)
    if not isinstance(doc, dict):
        raise c.err("", "a graph config must be a YAML mapping with a nodes: key",
                    getattr(doc, "line", 1))
    for k in doc:
        if k not in TOP_KEYS:
            raise c.err(str(k), f"unknown top-level key{_close(k, TOP_KEYS)}", _line_of(doc, k))
    if "nodes" not in doc:
        raise c.err("nodes", "missing (a graph needs at least one node)", 1)

    # shared params (+ overrides), then interpolate the rest of the document
    shared_raw = doc.get("params") or _LDict()
    if not isinstance(shared_raw, dict):
        raise c.err("params", "must be a mapping", _line_of(doc, "params"))
    shared_raw = _LDict(shared_raw) if not isinstance(shared_raw, _LDict) else shared_raw
    for node, param, value in set_items:
        if node == "params" and "params" not in (doc.get("nodes") or {}):
            if param not in shared_raw:
                raise ConfigError(f"unknown shared param{_close(param, shared_raw)} (shared "
                                  f"params: {', '.join(map(str, shared_raw)) or 'none'})",
                                  file=CMDLINE, key=f"--set params.{param}")
            shared_raw[param] = value
    shared: dict[str, Any] = {}
    for k, v in shared_raw.items():
        shared[k] = _interpolate(v, shared_raw, env, c, f"params.{k}", _line_of(shared_raw, k),
                                 (str(k),))
    rest = {k: v for k, v in doc.items() if k != "params"}
    rest_i = _LDict()
    rest_i.lines = dict(doc.lines)
    for k, v in rest.items():
        rest_i[k] = _interpolate(v, shared, env, c, str(k), _line_of(doc, k))
    doc_i = rest_i

    name = doc_i.get("graph", path.stem if path is not None else "graph")
    if not isinstance(name, str):
        raise c.err("graph", "must be a string", _line_of(doc, "graph"))
    description = doc_i.get("description", "") or ""
    if not isinstance(description, str):
        raise c.err("description", "must be a string", _line_of(doc, "description"))

    # parts
    if parts is not None:
        part_ids = expand_parts(list(parts), _Ctx(CMDLINE), "--parts")
    else:
        raw_parts = doc_i.get("parts") or []
        if isinstance(raw_parts, str):
            raw_parts = _LList([raw_parts])
            raw_parts.lines = [_line_of(doc, "parts") or 0]
        if not isinstance(raw_parts, list):
            raise c.err("parts", "must be a list of paths/globs", _line_of(doc, "parts"))
        part_ids = expand_parts(raw_parts, c, "parts", getattr(raw_parts, "lines", None))

    # nodes
    raw_nodes = doc_i["nodes"]
    if not isinstance(raw_nodes, dict) or not raw_nodes:
        raise c.err("nodes", "must be a non-empty mapping of node names", _line_of(doc, "nodes"))
    node_sets: dict[str, dict[str, Any]] = {}
    for node, param, value in set_items:
        if node == "params" and "params" not in raw_nodes:
            continue
        if node not in raw_nodes:
            raise ConfigError(f"unknown node {node!r}{_close(node, raw_nodes)}", file=CMDLINE,
                              key=f"--set {node}.{param}")
        node_sets.setdefault(node, {})[param] = value

    nodes: dict[str, NodeConfig] = {}
    for nname in raw_nodes:
        if not isinstance(nname, str):
            raise c.err(f"nodes.{nname}", f"node name {nname!r} is not a string (YAML reads "
                        "yes/no/on/off/true/false and numbers as such: quote the name)",
                        _line_of(raw_nodes, nname))
    for nname, body in raw_nodes.items():
        nodes[str(nname)] = _parse_node(str(nname), body, raw_nodes, c, bool(part_ids),
                                        node_sets.get(str(nname), {}))
    _check_wiring(nodes, raw_nodes, c)
    order = _toposort(nodes, raw_nodes, c)
    nodes = {n: nodes[n] for n in order}

    # targets
    raw_targets = doc_i.get("targets")
    if raw_targets is None:
        targets = list(nodes)
    else:
        if isinstance(raw_targets, str):
            raw_targets = [raw_targets]
        if not isinstance(raw_targets, list) or not raw_targets:
            raise c.err("targets", "must be a list of node names", _line_of(doc, "targets"))
        targets = []
        for i, t in enumerate(raw_targets):
            if t not in nodes:
                raise c.err(f"targets[{i}]", f"unknown node {t!r}{_close(str(t), nodes)}",
                            _line_of(raw_targets, i) or _line_of(doc, "targets"))
            targets.append(t)

    # file params must exist
    for n in nodes.values():
        for p in filepath_params(n.spec):
            v = n.params.get(p)
            if v is not None and not os.path.isfile(str(v)):
                raise c.err(f"nodes.{n.name}.params.{p}", f"missing input file {v!r}",
                            n.param_lines.get(p, n.line))

    overrides: dict[str, Any] = {}
    if set_items:
        overrides["set"] = {f"{a}.{b}": v for a, b, v in set_items}
    if parts is not None:
        overrides["parts"] = list(parts)
    return GraphConfig(
        name=name,
        path=path if path is not None else Path(file),
        description=description,
        params=shared,
        parts=part_ids,
        targets=targets,
        nodes=nodes,
        overrides=overrides,
    )


def _parse_node(name: str, body: Any, raw_nodes: Any, c: _Ctx, has_parts: bool,
                sets: dict[str, Any]) -> NodeConfig:
    nline = _line_of(raw_nodes, name)
    key = f"nodes.{name}"
    if not _NODE_NAME.match(name):
        raise c.err(key, "a node name must be letters, digits, _ or - (no dots or slashes)", nline)
    if not isinstance(body, dict):
        raise c.err(key, "a node must be a mapping with a stage: key", nline)
    for k in body:
        if k not in NODE_KEYS:
            raise c.err(f"{key}.{k}", f"unknown node key{_close(k, NODE_KEYS)}", _line_of(body, k))
    if "stage" not in body:
        raise c.err(key, "missing stage:", nline)
    sname = body["stage"]
    sline = _line_of(body, "stage")
    if not isinstance(sname, str):
        raise c.err(f"{key}.stage", "must be a stage name", sline)
    try:
        spec = resolve_stage(sname)
    except KeyError as e:
        raise c.err(f"{key}.stage", str(e.args[0]), sline) from None

    # inputs
    raw_inputs = body.get("inputs") or _LDict()
    iline = _line_of(body, "inputs") or nline
    if not isinstance(raw_inputs, dict):
        raise c.err(f"{key}.inputs", "must be a mapping input: node.output", iline)
    inputs: dict[str, Any] = {}
    for iname, wire in raw_inputs.items():
        ik = f"{key}.inputs.{iname}"
        il = _line_of(raw_inputs, iname)
        if iname not in spec.inputs:
            raise c.err(ik, f"stage {sname!r} has no input {iname!r}{_close(iname, spec.inputs)}"
                        f" (inputs: {', '.join(spec.inputs) or 'none'})", il)
        if wire == "part":
            if not has_parts:
                raise c.err(ik, "wired to part but the config has no parts (give parts: or "
                            "--parts)", il)
            inputs[iname] = "part"
            continue
        if not isinstance(wire, str) or wire.count(".") != 1:
            raise c.err(ik, f"expected node.output or part, got {wire!r}", il)
        up, out = wire.split(".")
        if up not in raw_nodes:
            raise c.err(ik, f"unknown node {up!r}{_close(up, raw_nodes)}", il)
        inputs[iname] = (up, out)
    for iname in spec.inputs:
        if iname not in inputs:
            raise c.err(f"{key}.inputs.{iname}", f"input of stage {sname!r} is not wired", iline)

    # seeds / gather
    seeds = None
    if "seeds" in body and body["seeds"] is not None:
        seeds = _parse_seeds(body["seeds"], c, f"{key}.seeds", _line_of(body, "seeds"))
    gather = body.get("gather", False)
    if not isinstance(gather, bool):
        raise c.err(f"{key}.gather", "must be true or false", _line_of(body, "gather"))

    # params
    raw_params = body.get("params") or _LDict()
    pline = _line_of(body, "params") or nline
    if not isinstance(raw_params, dict):
        raise c.err(f"{key}.params", "must be a mapping", pline)
    given = dict(raw_params)
    lines = {p: _line_of(raw_params, p) or pline for p in raw_params}
    for p, v in sets.items():
        given[p] = v
        lines[p] = 0
    for p, v in given.items():
        where_file = c.file if lines[p] else CMDLINE
        pk = f"{key}.params.{p}" if lines[p] else f"--set {name}.{p}"
        if p not in spec.params:
            raise ConfigError(f"unknown param for stage {sname!r}{_close(p, spec.params)}",
                              file=where_file, line=lines[p] or None, key=pk)
        if seeds is not None and p == "seed":
            raise ConfigError("seed is set per task by seeds:", file=where_file,
                              line=lines[p] or None, key=pk)
        try:
            registry.coerce(v, spec.params[p][0], where=f"{sname}.{p}")
        except ParamError as e:
            raise ConfigError(str(e), file=where_file, line=lines[p] or None, key=pk) from None
    if seeds is not None and "seed" in spec.params:
        given.setdefault("seed", seeds[0])
    try:
        params = registry.validate_params(spec, given)
    except ParamError as e:
        raise c.err(f"{key}.params", str(e), pline) from None
    description = body.get("description", "") or ""
    return NodeConfig(
        name=name,
        stage=sname,
        inputs=inputs,
        params=params,
        seeds=seeds,
        gather=gather,
        line=nline or 0,
        description=str(description),
        param_lines={p: ln for p, ln in lines.items() if ln},
    )


def _parse_seeds(raw: Any, c: _Ctx, key: str, line: int | None) -> list[int]:
    if isinstance(raw, dict):
        if set(raw) != {"count"}:
            raise c.err(key, "expected a list of seeds or {count: N}", line)
        n = raw["count"]
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise c.err(f"{key}.count", f"expected a positive integer, got {n!r}", line)
        return list(range(n))
    if isinstance(raw, bool) or not isinstance(raw, list) or not raw:
        raise c.err(key, "expected a non-empty list of seeds or {count: N}", line)
    seeds: list[int] = []
    for i, s in enumerate(raw):
        if not isinstance(s, int) or isinstance(s, bool):
            raise c.err(f"{key}[{i}]", f"a seed must be an integer, got {s!r}",
                        _line_of(raw, i) or line)
        if s in seeds:
            raise c.err(f"{key}[{i}]", f"duplicate seed {s}", _line_of(raw, i) or line)
        seeds.append(s)
    return seeds


def _check_wiring(nodes: dict[str, NodeConfig], raw_nodes: Any, c: _Ctx) -> None:
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
                            f"{_close(out, outs)} (outputs: {', '.join(outs)})",
                            _line_of(raw_inputs, iname))


def _toposort(nodes: dict[str, NodeConfig], raw_nodes: Any, c: _Ctx) -> list[str]:
    order: list[str] = []
    state: dict[str, int] = {}

    def visit(n: str, path: list[str]) -> None:
        if state.get(n) == 2:
            return
        if state.get(n) == 1:
            cyc = path[path.index(n):] + [n]
            first = cyc[0]
            # name the input of the first node of the cycle that closes it
            nxt = cyc[1]
            iname = next(i for i, w in nodes[first].inputs.items()
                         if isinstance(w, tuple) and w[0] == nxt)
            raw_inputs = raw_nodes[first].get("inputs") or {}
            raise c.err(f"nodes.{first}.inputs.{iname}", f"cycle {' -> '.join(reversed(cyc))}",
                        _line_of(raw_inputs, iname))
        state[n] = 1
        for up in nodes[n].upstream():
            visit(up, [*path, n])
        state[n] = 2
        order.append(n)

    for n in nodes:
        visit(n, [])
    return order
