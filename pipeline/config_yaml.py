"""Line-aware YAML for graph configs, and the errors that point into them.

Every problem found in a config is a :class:`ConfigError` whose message is one
line ``FILE:LINE: key: problem``.  To name the line, configs are loaded with a
``SafeLoader`` whose mappings and sequences remember the line of each key and
item (:class:`LineDict`, :class:`LineList`, read with :func:`line_of`).
``${...}`` references are protected while YAML parses the text (so a flow mapping
``{rate: ${params.rate}}`` parses) and put back afterwards; they are resolved by
:mod:`~mocapflow.pipeline.config_interpolation`.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable
from typing import Any

import yaml

__all__ = [
    "REF",
    "ConfigError",
    "FileErrors",
    "LineDict",
    "LineList",
    "close_match",
    "line_of",
    "load_yaml",
    "parse_yaml_value",
]

#: A ``${...}`` reference (group 1: what is inside the braces).
REF = re.compile(r"\$\{([^}]*)\}")


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


class FileErrors:
    """Error factory bound to one file: ``errors.err(key, problem, line)``."""

    def __init__(self, file: str) -> None:
        self.file = file

    def err(self, key: str, problem: str, line: int | None = None) -> ConfigError:
        """A :class:`ConfigError` at ``line`` of this file."""
        return ConfigError(problem, file=self.file, line=line, key=key)


def close_match(name: str, options: Iterable[str]) -> str:
    """``" (did you mean 'x'?)"`` for the closest of ``options``, or ``""``."""
    m = difflib.get_close_matches(str(name), [str(o) for o in options], n=1)
    return f" (did you mean {m[0]!r}?)" if m else ""


def parse_yaml_value(text: str) -> Any:
    """A command-line or environment value read as YAML (the text itself if that fails)."""
    try:
        return yaml.safe_load(text) if text.strip() else None
    except yaml.YAMLError:
        return text


# --------------------------------------------------------------------------- YAML with lines


class LineDict(dict):
    """A mapping that remembers the 1-based line of each key."""

    line: int = 0

    def __init__(self, *a: Any, **k: Any) -> None:
        super().__init__(*a, **k)
        self.lines: dict[Any, int] = {}


class LineList(list):
    """A sequence that remembers the 1-based line of each item."""

    line: int = 0

    def __init__(self, *a: Any, **k: Any) -> None:
        super().__init__(*a, **k)
        self.lines: list[int] = []


class _Loader(yaml.SafeLoader):
    """SafeLoader whose mappings and sequences carry line numbers."""


def _construct_mapping(loader: _Loader, node: yaml.MappingNode) -> LineDict:
    loader.flatten_mapping(node)
    out = LineDict()
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


def _construct_sequence(loader: _Loader, node: yaml.SequenceNode) -> LineList:
    out = LineList()
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

    return REF.sub(sub, text), table


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


def load_yaml(text: str, file: str) -> Any:
    """Parse config text into :class:`LineDict` / :class:`LineList` (``${...}`` kept as text).

    Raises
    ------
    ConfigError
        Malformed YAML (key ``yaml``, with the line of the problem when known).
    """
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


def line_of(container: Any, key: Any) -> int | None:
    """Line of ``key`` (or item index) in a loaded container, else of the container."""
    lines = getattr(container, "lines", None)
    if isinstance(lines, dict):
        return lines.get(key) or getattr(container, "line", None)
    if isinstance(lines, list) and isinstance(key, int) and key < len(lines):
        return lines[key]
    return getattr(container, "line", None)
