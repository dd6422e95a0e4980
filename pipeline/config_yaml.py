"""Line-aware, bounded YAML for graph configs, and the errors that point into them.

Every problem found in a config is a :class:`ConfigError` whose message is one
line ``FILE:LINE: key: problem``.  To name the line, configs are loaded with a
safe loader whose mappings and sequences remember the line of each key and
item (:class:`LineDict`, :class:`LineList`, read with :func:`line_of`).
``${...}`` references are protected while YAML parses the text (so a flow mapping
``{rate: ${params.rate}}`` parses) and put back afterwards; they are resolved by
:mod:`~mocapflow.pipeline.config_interpolation`.

Loading is bounded, so no config can hang the loader or exhaust memory:

* at most :data:`MAX_CONFIG_BYTES` of text;
* at most :data:`MAX_NODES` YAML nodes *after alias expansion*: anchors and
  aliases (``&a`` / ``*a``, merge keys ``<<: *a``) work, but every use of an
  alias counts the whole node it names, so a billion-laughs or merge-key bomb is
  refused at once (the sizes are counted, never expanded); an alias to a node
  that contains it is refused;
* at most :data:`MAX_DEPTH` levels of nesting (through aliases too), so deep
  nesting is an error, never a ``RecursionError``;
* only JSON-like values: an integer of more than :data:`MAX_INT_CHARS`
  characters, ``!!binary``, ``!!set``, ``!!omap``, ``!!pairs`` and unknown tags are
  errors; timestamps stay strings.

Each limit is reported as a :class:`ConfigError` naming the line and the key
path where it was crossed.  The events come from libyaml when PyYAML has it
(about 30 times faster than the pure-Python parser), composed and constructed
in Python, where the limits are enforced.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable
from typing import Any

import yaml
from yaml.composer import Composer
from yaml.constructor import ConstructorError, SafeConstructor
from yaml.nodes import MappingNode, ScalarNode, SequenceNode
from yaml.resolver import Resolver

__all__ = [
    "MAX_CONFIG_BYTES",
    "MAX_DEPTH",
    "MAX_INT_CHARS",
    "MAX_NODES",
    "REF",
    "ConfigError",
    "FileErrors",
    "LineDict",
    "LineList",
    "close_match",
    "line_of",
    "load_yaml",
    "parse_yaml_value",
    "short",
]

#: A ``${...}`` reference (group 1: what is inside the braces; no brace or newline
#: inside, so a text of many unclosed ``${`` is scanned in linear time).
REF = re.compile(r"\$\{([^{}\n]*)\}")
#: Largest config file read (bytes).
MAX_CONFIG_BYTES = 16 << 20
#: Most YAML nodes in one document, counting each alias as the whole node it names.
MAX_NODES = 100_000
#: Deepest nesting of mappings and sequences (aliases included).
MAX_DEPTH = 64
#: Longest integer scalar (characters; ``2**64`` has 20 digits).
MAX_INT_CHARS = 100
#: Longest key path and problem text in a :class:`ConfigError` (characters).
_MAX_KEY, _MAX_PROBLEM = 120, 400
_MERGE = "tag:yaml.org,2002:merge"


def short(value: Any, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters (messages stay one short line)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _cut(text: str, limit: int) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "…"


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

    Notes
    -----
    The key is cut to 120 characters and the problem to 400, so the message
    is always one readable line.
    """

    def __init__(
        self, problem: str, *, file: str = "", line: int | None = None, key: str = ""
    ) -> None:
        self.problem = problem
        self.file = file
        self.line = line
        self.key = key
        where = file + (f":{line}" if line else "")
        parts = [p for p in (where, _cut(key, _MAX_KEY), _cut(problem, _MAX_PROBLEM)) if p]
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
    name = str(name)
    if len(name) > 200:  # difflib is quadratic; nothing that long is a typo
        return ""
    m = difflib.get_close_matches(name, [str(o) for o in options], n=1)
    return f" (did you mean {m[0]!r}?)" if m else ""


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


class _LimitError(yaml.MarkedYAMLError):
    """A document over one of the loader's limits, or a value it refuses (``key``: where)."""

    def __init__(self, problem: str, mark: Any, key: str) -> None:
        super().__init__(problem=problem, problem_mark=mark)
        self.key = key


try:  # libyaml's event parser; composing and constructing stay in Python (the limits)
    from yaml._yaml import CParser as _EventParser

    def _init_parser(loader: Any, stream: str) -> None:
        _EventParser.__init__(loader, stream)

    _PARSER_BASES: tuple[type, ...] = (_EventParser,)
except ImportError:  # pragma: no cover - PyYAML built without libyaml
    from yaml.parser import Parser
    from yaml.reader import Reader
    from yaml.scanner import Scanner

    def _init_parser(loader: Any, stream: str) -> None:
        Reader.__init__(loader, stream)
        Scanner.__init__(loader)
        Parser.__init__(loader)

    _PARSER_BASES = (Reader, Scanner, Parser)


class _Loader(Composer, *_PARSER_BASES, SafeConstructor, Resolver):
    """Safe loader with line numbers and limits on size, expansion and depth."""

    dict_cls: type = LineDict
    list_cls: type = LineList

    def __init__(self, stream: str) -> None:
        _init_parser(self, stream)
        Composer.__init__(self)
        SafeConstructor.__init__(self)
        Resolver.__init__(self)
        self._nodes = 0
        self._depth = 0
        self._path: list[str] = []
        self._sizes: dict[int, tuple[int, int]] = {}  # id(node) -> (expanded size, height)
        # id(node) -> (id(parent node), path segment): key paths for constructor errors
        self._up: dict[int, tuple[int | None, str]] = {}
        self._own: dict[int, int] = {}  # id(mapping node) -> its own (not merged) pairs

    # ----------------------------------------------------------------- composing (limits)

    def _where(self) -> str:
        return "".join(self._path).lstrip(".")

    def _count(self, n: int, mark: Any, alias: str | None = None) -> None:
        self._nodes += n
        if self._nodes > MAX_NODES:
            how = f" (alias *{alias} names {n:,} nodes)" if alias else ""
            raise _LimitError(f"the document expands to more than {MAX_NODES:,} YAML nodes"
                              f"{how}; an alias bomb?", mark, self._where())

    def compose_node(self, parent: Any, index: Any) -> Any:
        if isinstance(index, ScalarNode):
            seg = "." + _cut(str(index.value), 40)
        elif isinstance(index, int):
            seg = f"[{index}]"
        else:  # the document, or a key
            seg = ""
        self._path.append(seg)
        self._depth += bool(seg)
        try:
            return self._compose_counted(parent, index, self._depth)
        except yaml.MarkedYAMLError as e:
            if isinstance(e, _LimitError) or "maximum nesting depth" not in str(e.problem):
                raise
            raise _LimitError(f"nesting deeper than {MAX_DEPTH} levels (libyaml's own limit)",
                              e.problem_mark, self._where()) from None
        finally:
            self._path.pop()
            self._depth -= bool(seg)

    def _compose_counted(self, parent: Any, index: Any, depth: int) -> Any:
        event = self.peek_event()
        if self.check_event(yaml.AliasEvent):
            target = self.anchors.get(event.anchor)
            if target is not None:  # an undefined alias is the composer's error
                info = self._sizes.get(id(target))
                if info is None:
                    raise _LimitError(f"alias *{event.anchor} refers to a node that contains "
                                      "it (recursive aliases are not allowed)",
                                      event.start_mark, self._where())
                self._count(info[0], event.start_mark, event.anchor)
                if depth + info[1] > MAX_DEPTH:
                    raise _LimitError(f"nesting deeper than {MAX_DEPTH} levels (through alias "
                                      f"*{event.anchor})", event.start_mark, self._where())
            return super().compose_node(parent, index)
        if depth > MAX_DEPTH:
            raise _LimitError(f"nesting deeper than {MAX_DEPTH} levels", event.start_mark,
                              self._where())
        self._count(1, event.start_mark)
        node = super().compose_node(parent, index)
        self._up[id(node)] = (None if parent is None else id(parent), self._path[-1])
        if isinstance(node, SequenceNode):
            kids = node.value
        elif isinstance(node, MappingNode):
            kids = [n for pair in node.value for n in pair]
        else:
            kids = []
        infos = [self._sizes[id(k)] for k in kids]
        self._sizes[id(node)] = (1 + sum(s for s, _ in infos),
                                 1 + max((h for _, h in infos), default=0))
        return node

    # ----------------------------------------------------------------- constructing

    def node_error(self, node: Any, problem: str) -> _LimitError:
        """An error about one node, naming its key path."""
        segs: list[str] = []
        at: int | None = id(node)
        while at is not None and at in self._up and len(segs) <= MAX_DEPTH:
            at, seg = self._up[at]
            segs.append(seg)
        return _LimitError(problem, node.start_mark, "".join(reversed(segs)).lstrip("."))

    def construct_undefined(self, node: Any) -> Any:
        tag = str(node.tag).replace("tag:yaml.org,2002:", "!!")
        raise self.node_error(node, f"unknown tag {short(tag)} (configs hold plain mappings, "
                              "lists and scalars)")

    def flatten_mapping(self, node: MappingNode) -> None:
        if id(node) not in self._own:
            self._own[id(node)] = sum(1 for k, _ in node.value if k.tag != _MERGE)
        super().flatten_mapping(node)


def _key(loader: _Loader, key_node: Any) -> Any:
    key = loader.construct_object(key_node, deep=True)
    if not isinstance(key, (str, int, float, bool)) and key is not None:
        raise ConstructorError(None, None, "a key must be a scalar", key_node.start_mark)
    return key


def _construct_mapping(loader: _Loader, node: MappingNode) -> dict:
    """A mapping; merged keys (``<<:``) first one wins, own keys override them once each."""
    loader.flatten_mapping(node)
    out = loader.dict_cls()
    lines = getattr(out, "lines", None)
    if lines is not None:
        out.line = node.start_mark.line + 1
    n_own = loader._own.get(id(node), len(node.value))
    cut = len(node.value) - n_own
    own: set = set()
    for i, (key_node, value_node) in enumerate(node.value):
        key = _key(loader, key_node)
        if i < cut:
            if key in out:  # an earlier merged mapping wins
                continue
        elif key in own:
            raise ConstructorError(None, None, f"duplicate key {short(key)}",
                                   key_node.start_mark)
        else:
            own.add(key)
        out[key] = loader.construct_object(value_node, deep=True)
        if lines is not None:
            lines[key] = key_node.start_mark.line + 1
    return out


def _construct_sequence(loader: _Loader, node: SequenceNode) -> list:
    out = loader.list_cls()
    lines = getattr(out, "lines", None)
    if lines is not None:
        out.line = node.start_mark.line + 1
    for item in node.value:
        out.append(loader.construct_object(item, deep=True))
        if lines is not None:
            lines.append(item.start_mark.line + 1)
    return out


def _construct_int(loader: _Loader, node: ScalarNode) -> int:
    text = str(node.value)
    if len(text) > MAX_INT_CHARS:
        raise loader.node_error(node, f"an integer of {len(text):,} characters is out of range")
    return SafeConstructor.construct_yaml_int(loader, node)


def _construct_timestamp(loader: _Loader, node: ScalarNode) -> str:
    return loader.construct_scalar(node)  # dates stay text: configs hold JSON-like values


def _refuse(loader: _Loader, node: Any) -> Any:
    tag = node.tag.replace("tag:yaml.org,2002:", "!!")
    raise loader.node_error(node, f"tag {tag} is not allowed in a config (use plain mappings, "
                            "lists and scalars)")


_Loader.add_constructor(None, _Loader.construct_undefined)
_Loader.add_constructor("tag:yaml.org,2002:map", _construct_mapping)
_Loader.add_constructor("tag:yaml.org,2002:seq", _construct_sequence)
_Loader.add_constructor("tag:yaml.org,2002:int", _construct_int)
_Loader.add_constructor("tag:yaml.org,2002:timestamp", _construct_timestamp)
for _tag in ("binary", "set", "omap", "pairs"):
    _Loader.add_constructor(f"tag:yaml.org,2002:{_tag}", _refuse)


class _PlainLoader(_Loader):
    """The same limits, plain ``dict`` / ``list`` (values given on a command line)."""

    dict_cls = dict
    list_cls = list


_PLACEHOLDER = "__mocapflow_ref_{}__"
_PLACEHOLDER_RE = re.compile(r"__mocapflow_ref_(\d+)__")


def _protect_refs(text: str) -> tuple[str, list[str]]:
    """Replace ``${...}`` by plain-scalar placeholders so ``{rate: ${params.rate}}`` parses."""
    table: list[str] = []

    def sub(m: re.Match) -> str:
        table.append(m.group(0))
        return _PLACEHOLDER.format(len(table) - 1)

    return REF.sub(sub, text), table


def _restore_refs(value: Any, table: list[str], seen: set[int]) -> Any:
    """Put the ``${...}`` texts back (each shared container, from an alias, once)."""
    if isinstance(value, str):
        if "__mocapflow_ref_" not in value:
            return value
        return _PLACEHOLDER_RE.sub(lambda m: table[int(m.group(1))], value)
    if isinstance(value, (dict, list)):
        if id(value) in seen:
            return value
        seen.add(id(value))
    if isinstance(value, dict):
        for k in list(value):
            value[k] = _restore_refs(value[k], table, seen)
    elif isinstance(value, list):
        for i, v in enumerate(value):
            value[i] = _restore_refs(v, table, seen)
    return value


def _load(text: str, loader_cls: type[_Loader]) -> Any:
    loader = loader_cls(text)
    try:
        return loader.get_single_data()
    except yaml.MarkedYAMLError as e:
        if isinstance(e, _LimitError) or "maximum nesting depth" not in str(e.problem):
            raise
        # libyaml's own limit (1,000 levels), met while it scans ahead
        raise _LimitError(f"nesting deeper than {MAX_DEPTH} levels", e.problem_mark,
                          loader._where()) from None
    finally:
        loader.dispose()


def load_yaml(text: str, file: str) -> Any:
    """Parse config text into :class:`LineDict` / :class:`LineList` (``${...}`` kept as text).

    Raises
    ------
    ConfigError
        Malformed YAML (key ``yaml``, with the line of the problem when known),
        or a document over a limit (key: where it was crossed).
    """
    if len(text) > MAX_CONFIG_BYTES:
        raise ConfigError(f"config is larger than {MAX_CONFIG_BYTES >> 20} MiB", file=file)
    text, table = _protect_refs(text)
    try:
        return _restore_refs(_load(text, _Loader), table, set())
    except _LimitError as e:
        line = e.problem_mark.line + 1 if e.problem_mark is not None else None
        raise ConfigError(str(e.problem), file=file, line=line, key=e.key or "yaml") from None
    except yaml.reader.ReaderError as e:  # a character YAML does not allow
        line = text.count("\n", 0, max(0, e.position)) + 1
        what = f"#x{e.character:04x}" if isinstance(e.character, int) else repr(e.character)
        raise ConfigError(f"malformed YAML: unacceptable character {what} ({e.reason})",
                          file=file, line=line, key="yaml") from None
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        line = mark.line + 1 if mark is not None else None
        problem = " ".join(str(x) for x in (e.context, e.problem) if x) or "malformed YAML"
        raise ConfigError(f"malformed YAML: {problem}", file=file, line=line, key="yaml") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"malformed YAML: {e}", file=file, key="yaml") from None


def parse_yaml_value(text: str, *, file: str = "<command line>", key: str = "",
                     line: int | None = None) -> Any:
    """A command-line or environment value read as YAML (the text itself if that fails).

    Plain ``dict`` / ``list`` values; the loader's limits apply.

    Raises
    ------
    ConfigError
        The value is over a limit (``file``, ``key`` and ``line`` name where it was given).
    """
    if not text.strip():
        return None
    if len(text) > MAX_CONFIG_BYTES:
        raise ConfigError(f"value is larger than {MAX_CONFIG_BYTES >> 20} MiB", file=file,
                          line=line, key=key)
    try:
        return _load(text, _PlainLoader)
    except _LimitError as e:
        raise ConfigError(str(e.problem), file=file, line=line, key=key) from None
    except yaml.YAMLError:
        return text


def line_of(container: Any, key: Any) -> int | None:
    """Line of ``key`` (or item index) in a loaded container, else of the container."""
    lines = getattr(container, "lines", None)
    if isinstance(lines, dict):
        return lines.get(key) or getattr(container, "line", None)
    if isinstance(lines, list) and isinstance(key, int) and key < len(lines):
        return lines[key]
    return getattr(container, "line", None)
