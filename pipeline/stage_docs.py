"""What a stage's params mean, from its docstring, and a JSON Schema of graph configs.

``mocapflow stages [NAME]`` prints every param with its type, default and the
text of its numpydoc ``Parameters`` entry (:func:`param_docs`); ``mocapflow
schema`` writes :func:`config_schema`, a JSON Schema (draft 2020-12) of graph
configs in which each node's ``params`` are checked against its stage's
signature, so an editor with a YAML language server validates a config as it is
typed (``# yaml-language-server: $schema=mocapflow.schema.json``).
"""

from __future__ import annotations

import inspect
import re
import types
import typing
from collections.abc import Callable, Mapping
from typing import Any, Literal, get_args, get_origin

from mocapflow.pipeline.registry import FilePath, StageSpec

__all__ = ["annotation_schema", "config_schema", "param_docs"]

_SECTION = re.compile(r"^\s*([A-Z][A-Za-z ]+)\n\s*-{3,}\s*$", re.M)
_ENTRY = re.compile(r"^(\s*)([A-Za-z_][\w]*(?:\s*,\s*[A-Za-z_][\w]*)*)\s*(?::\s*(.*))?$")
#: A param value that the config interpolates (``${params.alpha1}``) is a string
#: whatever the param's type.
_INTERPOLATED = {"type": "string", "pattern": r"\$\{"}


def param_docs(func: Callable[..., Any]) -> dict[str, str]:
    """The text of each entry of a numpydoc ``Parameters`` section.

    Parameters
    ----------
    func : callable
        A function whose docstring has a ``Parameters`` section; an entry may
        name several parameters (``merge, fill : bool``).

    Returns
    -------
    dict
        ``{name: description}``, the description's lines joined by spaces (the
        type after the colon is left out: the signature gives it).  Names not
        documented are absent.
    """
    doc = inspect.getdoc(func) or ""
    heads = list(_SECTION.finditer(doc))
    out: dict[str, str] = {}
    for i, h in enumerate(heads):
        if h.group(1).strip() not in ("Parameters", "Other Parameters"):
            continue
        end = heads[i + 1].start() if i + 1 < len(heads) else len(doc)
        names: list[str] = []
        text: list[str] = []
        for line in doc[h.end():end].splitlines():
            m = _ENTRY.match(line)
            if m and not m.group(1) and line.strip():
                for n in names:
                    out[n] = " ".join(text)
                names = [n.strip() for n in m.group(2).split(",")]
                text = []
            elif line.strip():
                text.append(line.strip())
        for n in names:
            out[n] = " ".join(text)
    return out


def annotation_schema(ann: Any) -> dict[str, Any]:
    """The JSON Schema of a param annotation (as :func:`registry.coerce` accepts it)."""
    if ann is Any or ann is inspect.Parameter.empty:
        return {}
    origin, args = get_origin(ann), get_args(ann)
    if origin in (typing.Union, types.UnionType):
        return {"anyOf": [annotation_schema(a) for a in args]}
    if origin is Literal:
        return {"enum": list(args)}
    if ann is type(None) or ann is None:
        return {"type": "null"}
    simple = {bool: "boolean", int: "integer", float: "number", str: "string",
              FilePath: "string"}
    if ann in simple:
        return {"type": simple[ann]}
    if origin in (list, tuple) or ann in (list, tuple):
        item = [a for a in args if a is not Ellipsis]
        return {"type": "array", **({"items": annotation_schema(item[0])} if item else {})}
    if origin is dict or ann is dict:
        return {"type": "object",
                **({"additionalProperties": annotation_schema(args[1])} if args else {})}
    return {}


def _param_schema(ann: Any, default: Any, doc: str) -> dict[str, Any]:
    s: dict[str, Any] = {"anyOf": [annotation_schema(ann) or {}, _INTERPOLATED]}
    if doc:
        s["description"] = doc
    if default is not inspect.Parameter.empty and _jsonable(default):
        s["default"] = default
    return s


def _jsonable(v: Any) -> bool:
    if v is None or isinstance(v, (bool, int, float, str)):
        return True
    if isinstance(v, (list, tuple)):
        return all(_jsonable(x) for x in v)
    if isinstance(v, dict):
        return all(isinstance(k, str) and _jsonable(x) for k, x in v.items())
    return False


def config_schema(stages: Mapping[str, StageSpec]) -> dict[str, Any]:
    """A JSON Schema (draft 2020-12) of graph configs for the given stages.

    Parameters
    ----------
    stages : mapping
        ``{name: StageSpec}``, e.g. :func:`registry.registered_stages` after
        discovery.

    Returns
    -------
    dict
        Top-level keys as :mod:`~mocapflow.pipeline.config` reads them; a node's
        ``stage`` is one of the names, and its ``params`` are those of that
        stage (unknown names refused, each typed and described from the
        docstring; ``${...}`` interpolations accepted anywhere).
    """
    per_stage = []
    for name, spec in sorted(stages.items()):
        docs = param_docs(spec.func)
        props = {p: _param_schema(a, d, docs.get(p, "")) for p, (a, d) in spec.params.items()}
        per_stage.append({
            "if": {"properties": {"stage": {"const": name}}, "required": ["stage"]},
            "then": {"properties": {
                "params": {"type": "object", "properties": props,
                           "additionalProperties": False},
                "inputs": {"type": "object",
                           "propertyNames": {"enum": list(spec.inputs)}}}},
        })
    node = {
        "type": "object",
        "required": ["stage"],
        "additionalProperties": False,
        "properties": {
            "stage": {"enum": sorted(stages), "description": "registered stage name"},
            "description": {"type": "string"},
            "inputs": {"type": "object", "description":
                       "input name -> 'part', 'NODE.OUTPUT' or a list of them (gather)"},
            "params": {"type": "object"},
            "seeds": {"anyOf": [
                {"type": "array", "minItems": 1, "uniqueItems": True,
                 "items": {"type": "integer", "minimum": 0, "maximum": 2**32 - 1}},
                {"type": "object", "required": ["count"], "additionalProperties": False,
                 "properties": {"count": {"type": "integer", "minimum": 1}}},
                {"type": "null"}, _INTERPOLATED],
                "description": "seed fan-out: a list of seeds, {count: N} (seeds 0..N-1), "
                               "or null"},
            "gather": {"type": "boolean", "description": "one task over every part"},
        },
        "allOf": per_stage,
    }
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "mocapflow graph config",
        "type": "object",
        "required": ["nodes"],
        "additionalProperties": False,
        "properties": {
            "graph": {"type": "string", "description": "graph name (default: file stem)"},
            "description": {"type": "string"},
            "params": {"type": "object", "description":
                       "shared params, used in nodes as ${params.NAME}"},
            "parts": {"anyOf": [{"type": "string"},
                                {"type": "array", "items": {"type": "string"}}],
                      "description": "input files or globs, relative to the config's folder"},
            "targets": {"type": "array", "items": {"type": "string"}},
            "nodes": {"type": "object", "additionalProperties": node},
        },
    }
