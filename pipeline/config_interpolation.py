"""``${...}`` interpolation in graph configs.

``${params.NAME}`` is replaced by the shared param ``NAME`` (``params:`` at the top
level, interpolated itself; a reference cycle is an error) and
``${env:VAR,default}`` by the environment variable ``VAR`` (or ``default``).  A
string that is exactly one reference keeps the value's type (an environment
value is then parsed as YAML, like ``--set`` values); a reference inside a
longer string is formatted into it (non-strings as JSON).  Line information of
the loaded document is kept, so later errors still name their line.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from typing import Any

from mocapflow.pipeline.config_yaml import (
    REF,
    FileErrors,
    LineDict,
    LineList,
    close_match,
    line_of,
    parse_yaml_value,
)

__all__ = ["interpolate"]


def _resolve_ref(ref: str, params: Mapping[str, Any], env: Mapping[str, str], c: FileErrors,
                 key: str, line: int | None, stack: tuple[str, ...]) -> Any:
    ref = ref.strip()
    if ref.startswith("env:"):
        body = ref[4:]
        var, sep, default = body.partition(",")
        var = var.strip()
        if not var:
            raise c.err(key, f"empty environment reference ${{{ref}}}", line)
        if var in env:
            return parse_yaml_value(env[var])
        if sep:
            return parse_yaml_value(default.strip())
        raise c.err(key, f"environment variable {var} is not set and has no default", line)
    if ref.startswith("params."):
        name = ref[len("params."):]
        if name in stack:
            raise c.err(key, f"circular reference ${{{ref}}}", line)
        if name not in params:
            raise c.err(key, f"unknown shared param ${{{ref}}}{close_match(name, params)}", line)
        return interpolate(params[name], params, env, c, key, line, (*stack, name))
    raise c.err(key, f"cannot interpolate ${{{ref}}} "
                "(use ${params.NAME} or ${env:VAR,default})", line)


def interpolate(value: Any, params: Mapping[str, Any], env: Mapping[str, str], c: FileErrors,
                key: str, line: int | None, stack: tuple[str, ...] = ()) -> Any:
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
    """
    if isinstance(value, str):
        whole = REF.fullmatch(value.strip())
        if whole:
            return _resolve_ref(whole.group(1), params, env, c, key, line, stack)
        if "${" not in value:
            return value

        def sub(m: re.Match) -> str:
            v = _resolve_ref(m.group(1), params, env, c, key, line, stack)
            return v if isinstance(v, str) else json.dumps(v)

        return REF.sub(sub, value)
    if isinstance(value, dict):
        out = LineDict()
        out.line = getattr(value, "line", line or 0)
        for k, v in value.items():
            kl = line_of(value, k) or line
            out[k] = interpolate(v, params, env, c, f"{key}.{k}" if key else str(k), kl, stack)
            out.lines[k] = kl or 0
        return out
    if isinstance(value, list):
        out_l = LineList()
        out_l.line = getattr(value, "line", line or 0)
        for i, v in enumerate(value):
            il = line_of(value, i) or line
            out_l.append(interpolate(v, params, env, c, f"{key}[{i}]", il, stack))
            out_l.lines.append(il or 0)
        return out_l
    return value
