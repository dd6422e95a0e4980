"""``${...}`` interpolation in graph configs.

``${params.NAME}`` is replaced by the shared param ``NAME`` (``params:`` at the top
level, interpolated itself; a reference cycle is an error) and
``${env:VAR,default}`` by the environment variable ``VAR`` (or ``default``).  A
string that is exactly one reference keeps the value's type (an environment
value is then parsed as YAML, like ``--set`` values); a reference inside a
longer string is formatted into it (non-strings as JSON).  Line information of
the loaded document is kept, so later errors still name their line.

A node param whose whole value is ``${part.FIELD}`` or ``${part.FIELD,DEFAULT}``
is a per-part param: it becomes a :class:`PartRef` (its ``DEFAULT`` interpolated
now: a literal read as YAML, ``${params.NAME}``, ``${env:VAR}``, or ``null``), which
the graph resolves per task to the part's field (the fields of a capture
session, :mod:`~mocapflow.pipeline.session`).  ``${part.…}`` anywhere else is an
error.

Interpolation is bounded like YAML loading (a reference may name a value that
holds references, so a few lines could otherwise expand without end): one pass
makes at most :data:`~mocapflow.pipeline.config_yaml.MAX_NODES` values and
:data:`~mocapflow.pipeline.config_yaml.MAX_CONFIG_BYTES` characters of
formatted text (:class:`Budget`), nests at most
:data:`~mocapflow.pipeline.config_yaml.MAX_DEPTH` levels, and follows chains of
at most :data:`MAX_REF_CHAIN` references.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from mocapflow.pipeline.config_yaml import (
    MAX_CONFIG_BYTES,
    MAX_DEPTH,
    MAX_NODES,
    REF,
    FileErrors,
    LineDict,
    LineList,
    close_match,
    line_of,
    parse_yaml_value,
)

__all__ = ["MAX_REF_CHAIN", "Budget", "PartRef", "interpolate"]

#: Longest chain of ``${params.NAME}`` references (a param naming a param naming ...).
MAX_REF_CHAIN = 32


#: Where ``${part.…}`` may stand: the whole value of a node param.
_PART_KEY = re.compile(r"^nodes\.[^.\[]+\.params\.[^.\[]+$")
_PART_REF = re.compile(r"^\$\{part\.([A-Za-z_][A-Za-z0-9_]*)\s*(?:,(.*))?\}$", re.DOTALL)


@dataclass(frozen=True)
class PartRef:
    """A per-part param value ``${part.FIELD}`` / ``${part.FIELD,DEFAULT}``.

    Attributes
    ----------
    field : str
        The part's field it reads.
    default : any
        The value for a part without the field (already interpolated).
    has_default : bool
        Whether a default was given (without one every part needs the field).
    text : str
        The reference as written (for messages).
    """

    field: str
    default: Any = None
    has_default: bool = False
    text: str = ""

    def value(self, fields: Mapping[str, Any] | None) -> Any:
        """The value for a part with ``fields``.

        Raises
        ------
        KeyError
            The part has no such field and there is no default.
        """
        if fields and self.field in fields:
            return fields[self.field]
        if self.has_default:
            return self.default
        raise KeyError(self.field)


class Budget:
    """What one interpolation pass may still make: values and characters of text."""

    def __init__(self, nodes: int = MAX_NODES, chars: int = MAX_CONFIG_BYTES) -> None:
        self.nodes = nodes
        self.chars = chars

    def spend(self, c: FileErrors, key: str, line: int | None, *, nodes: int = 0,
              chars: int = 0) -> None:
        """Take ``nodes`` values and ``chars`` characters, or raise naming ``key``."""
        self.nodes -= nodes
        self.chars -= chars
        if self.nodes < 0:
            raise c.err(key, f"${{...}} references expand to more than {MAX_NODES:,} values",
                        line)
        if self.chars < 0:
            raise c.err(key, "${...} references expand to more than "
                        f"{MAX_CONFIG_BYTES >> 20} MiB of text", line)


def _resolve_ref(ref: str, params: Mapping[str, Any], env: Mapping[str, str], c: FileErrors,
                 key: str, line: int | None, stack: tuple[str, ...], budget: Budget,
                 depth: int) -> Any:
    ref = ref.strip()
    if ref.startswith("env:"):
        body = ref[4:]
        var, sep, default = body.partition(",")
        var = var.strip()
        if not var:
            raise c.err(key, f"empty environment reference ${{{ref}}}", line)
        if var in env:
            return parse_yaml_value(env[var], file=c.file, key=key, line=line)
        if sep:
            return parse_yaml_value(default.strip(), file=c.file, key=key, line=line)
        raise c.err(key, f"environment variable {var} is not set and has no default", line)
    if ref.startswith("params."):
        name = ref[len("params."):]
        if name in stack:
            raise c.err(key, f"circular reference ${{{ref}}}", line)
        if name not in params:
            raise c.err(key, f"unknown shared param ${{{ref}}}{close_match(name, params)}", line)
        if len(stack) >= MAX_REF_CHAIN:
            raise c.err(key, f"more than {MAX_REF_CHAIN} ${{params.NAME}} references in a chain "
                        f"(${{params.{stack[0]}}} -> ... -> ${{{ref}}})", line)
        return interpolate(params[name], params, env, c, key, line, (*stack, name),
                           budget=budget, depth=depth)
    if ref.startswith("part."):
        raise c.err(key, f"${{{ref}}} must be the whole value of a node param "
                    "(nodes.NODE.params.PARAM: ${part.FIELD} or ${part.FIELD,DEFAULT})", line)
    raise c.err(key, f"cannot interpolate ${{{ref}}} "
                "(use ${params.NAME}, ${env:VAR,default} or, as a node param, "
                "${part.FIELD,default})", line)


def _part_ref(text: str, params: Mapping[str, Any], env: Mapping[str, str], c: FileErrors,
              key: str, line: int | None, stack: tuple[str, ...], budget: Budget,
              depth: int) -> PartRef:
    """``${part.FIELD[,DEFAULT]}`` (the whole value of a node param) → :class:`PartRef`."""
    m = _PART_REF.fullmatch(text)
    if m is None:
        raise c.err(key, f"malformed per-part reference {text[:80]!r} (expected "
                    "${part.FIELD} or ${part.FIELD,DEFAULT})", line)
    if not _PART_KEY.match(key):
        raise c.err(key, f"{text[:80]} must be the whole value of a node param "
                    "(nodes.NODE.params.PARAM)", line)
    name, raw = m.group(1), m.group(2)
    if raw is None:
        return PartRef(name, None, False, text)
    raw = raw.strip()
    if raw.startswith("${part."):
        raise c.err(key, f"the default of ${{part.{name},…}} cannot be another ${{part.…}}",
                    line)
    if "${" in raw:
        default = interpolate(raw, params, env, c, key, line, stack, budget=budget,
                              depth=depth)
    else:
        default = parse_yaml_value(raw, file=c.file, key=key, line=line)
    return PartRef(name, default, True, text)


def interpolate(value: Any, params: Mapping[str, Any], env: Mapping[str, str], c: FileErrors,
                key: str, line: int | None, stack: tuple[str, ...] = (), *,
                budget: Budget | None = None, depth: int = 0) -> Any:
    """Interpolate ``${...}`` references in ``value`` (recursively), keeping line info.

    Parameters
    ----------
    value : any
        A loaded config value (:class:`~mocapflow.pipeline.config_yaml.LineDict`,
        ``LineList``, scalars).
    params : mapping
        Shared params (``${params.NAME}``).
    env : mapping
        Environment (``${env:VAR}``).
    c : FileErrors
        Errors name this file.
    key : str
        Dotted key of ``value`` (for messages).
    line : int or None
        Its line.
    stack : tuple of str
        Shared params being resolved (to detect cycles).
    budget : Budget, optional
        What the pass may still make (default: a fresh one for this value).
    depth : int
        Nesting level of ``value`` in the document (a top-level value: 1).

    Raises
    ------
    ConfigError
        Unknown or circular references, unset variables, and a pass over its
        :class:`Budget`, :data:`~mocapflow.pipeline.config_yaml.MAX_DEPTH` or
        :data:`MAX_REF_CHAIN`.
    """
    budget = Budget() if budget is None else budget
    budget.spend(c, key, line, nodes=1)
    if depth > MAX_DEPTH:
        raise c.err(key, f"nesting deeper than {MAX_DEPTH} levels", line)
    if isinstance(value, str):
        if value.lstrip().startswith("${part."):
            return _part_ref(value.strip(), params, env, c, key, line, stack, budget, depth)
        whole = REF.fullmatch(value.strip())
        if whole:
            return _resolve_ref(whole.group(1), params, env, c, key, line, stack, budget, depth)
        if "${" not in value:
            return value

        def sub(m: re.Match) -> str:
            v = _resolve_ref(m.group(1), params, env, c, key, line, stack, budget, depth)
            text = v if isinstance(v, str) else json.dumps(v)
            budget.spend(c, key, line, chars=len(text))
            return text

        return REF.sub(sub, value)
    if isinstance(value, dict):
        out = LineDict()
        out.line = getattr(value, "line", line or 0)
        for k, v in value.items():
            kl = line_of(value, k) or line
            out[k] = interpolate(v, params, env, c, f"{key}.{k}" if key else str(k), kl, stack,
                                 budget=budget, depth=depth + 1)
            out.lines[k] = kl or 0
        return out
    if isinstance(value, list):
        out_l = LineList()
        out_l.line = getattr(value, "line", line or 0)
        for i, v in enumerate(value):
            il = line_of(value, i) or line
            out_l.append(interpolate(v, params, env, c, f"{key}[{i}]", il, stack,
                                     budget=budget, depth=depth + 1))
            out_l.lines.append(il or 0)
        return out_l
    return value
