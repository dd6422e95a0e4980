"""Part entries of a graph config → part ids: paths, globs and sessions, bounded.

``parts:`` entries (and ``--parts``) are file paths, globs or capture sessions
(:mod:`~mocapflow.pipeline.session`: an entry naming a session file gives its
trials as parts, each with its fields).  :func:`expand_parts` turns them into
part ids (see its docstring: ids never depend on the working directory).
Globs are bounded (:func:`bounded_glob`): at most :data:`MAX_GLOB_MATCHES`
matches and, for ``**`` patterns, at most
:data:`MAX_GLOB_ENTRIES` directory entries looked at (and
:data:`MAX_GLOB_SECONDS` of walking), and a symlink that leads
back into a directory being walked is not followed again (Python's ``glob``
follows such a loop until the path is too long, and walks ``/**`` for ever).
"""

from __future__ import annotations

import fnmatch
import glob
import itertools
import os
import re
import stat
import time
from collections.abc import Sequence
from typing import Any

from mocapflow.pipeline.config_yaml import FileErrors, short
from mocapflow.pipeline.session import is_session, read_session

__all__ = ["MAX_GLOB_ENTRIES", "MAX_GLOB_MATCHES", "MAX_GLOB_SECONDS", "GlobLimitError",
           "bounded_glob", "expand_parts"]

#: Most paths one glob may match (the most tasks a graph may have).
MAX_GLOB_MATCHES = 1_000_000
#: Most directory entries a ``**`` glob may look at (a database of 10,000 takes in
#: nested folders is well under it; ``/**`` is far over).
MAX_GLOB_ENTRIES = 200_000
#: Longest a ``**`` glob may walk (seconds; a safety net for slow filesystems).
MAX_GLOB_SECONDS = 60.0


class GlobLimitError(ValueError):
    """A glob over one of the limits (the message says which)."""


def bounded_glob(pattern: str) -> list[str]:
    """``glob.glob(pattern, recursive=True)``, bounded (see the module docstring).

    Patterns without ``**`` go to :func:`glob.iglob` (their walk is as deep as
    the pattern); ``**`` patterns are walked here with the same matching rules
    (``*``, ``?``, ``[...]`` within one name, names starting with ``.`` only
    matched by a pattern starting with ``.``; ``**`` matches zero or more
    directories), following symlinked directories except into a directory
    already on the walked path.

    Raises
    ------
    GlobLimitError
        More than :data:`MAX_GLOB_MATCHES` matches, :data:`MAX_GLOB_ENTRIES`
        entries looked at or :data:`MAX_GLOB_SECONDS` spent.
    """
    if "**" not in pattern:
        out = list(itertools.islice(glob.iglob(pattern), MAX_GLOB_MATCHES + 1))
    else:
        out = _walk_glob(pattern)
    if len(out) > MAX_GLOB_MATCHES:
        raise GlobLimitError(f"matches more than {MAX_GLOB_MATCHES:,} paths (the most tasks a "
                             "graph may have)")
    return out


def _walk_glob(pattern: str) -> list[str]:
    comps = pattern.split(os.sep)
    first = next(i for i, p in enumerate(comps) if glob.has_magic(p))
    top = os.sep.join(comps[:first]) or (os.sep if pattern.startswith(os.sep) else "")
    rest = comps[first:]
    rx = [None if p == "**" else (re.compile(fnmatch.translate(p)) if glob.has_magic(p)
                                  else p) for p in rest]
    found: dict[str, None] = {}
    looked = 0
    deadline = time.monotonic() + MAX_GLOB_SECONDS
    start = _dir_id(top or os.curdir)
    if start is None:
        return []
    # (directory, path as shown, index into rest, (dev, ino) of it and the directories above)
    todo: list[tuple[str, str, int, frozenset]] = [(top or os.curdir, top, 0,
                                                    frozenset([start]))]
    while todo and len(found) <= MAX_GLOB_MATCHES:
        d, shown, i, above = todo.pop()
        if i == len(rest):
            if shown:
                found.setdefault(shown, None)
            continue
        m = rx[i]
        if isinstance(m, str):  # a literal name
            path = os.path.join(d, m)
            if i + 1 == len(rest):
                if os.path.lexists(path):
                    found.setdefault(os.path.join(shown, m) if shown else m, None)
                continue
            sub_id = _dir_id(path)
            if sub_id is not None and sub_id not in above:
                todo.append((path, os.path.join(shown, m) if shown else m, i + 1,
                             above | {sub_id}))
            continue
        if m is None:  # **: zero directories here, or one more level
            todo.append((d, shown, i + 1, above))
        try:
            with os.scandir(d) as it:
                names = [(e.name, e.is_dir()) for e in it]
        except OSError:
            continue
        looked += len(names)
        if looked > MAX_GLOB_ENTRIES:
            raise GlobLimitError(f"looks at more than {MAX_GLOB_ENTRIES:,} files and "
                                 "directories (narrow the pattern)")
        if time.monotonic() > deadline:
            raise GlobLimitError(f"walked for more than {MAX_GLOB_SECONDS:.0f} s (narrow the "
                                 "pattern)")
        hidden_ok = m is not None and rest[i].startswith(".")
        last = i + 1 == len(rest)
        for name, is_dir in names:
            if name.startswith(".") and not hidden_ok:
                continue
            sub = os.path.join(shown, name) if shown else name
            if m is not None and not m.match(name):
                continue
            if last and (m is not None or not is_dir):
                found.setdefault(sub, None)  # (a trailing ** matches files and directories)
            if is_dir and (m is None or not last):
                path = os.path.join(d, name)
                sub_id = _dir_id(path)
                if sub_id is not None and sub_id not in above:  # not a loop back up
                    todo.append((path, sub, i if m is None else i + 1, above | {sub_id}))
    return list(found)


def _dir_id(path: str) -> tuple[int, int] | None:
    """``(st_dev, st_ino)`` of a directory (symlinks followed), else ``None``."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino) if stat.S_ISDIR(st.st_mode) else None


def expand_parts(entries: Sequence[Any], c: FileErrors, key: str,
                 lines: Sequence[int] | None = None, *, base: str | None = None,
                 relative_to: str | None = None,
                 fields: dict[str, dict[str, Any]] | None = None) -> list[str]:
    """Expand part entries (paths, globs or session files) into part ids.

    Parameters
    ----------
    entries : sequence of str
    c : FileErrors
    key : str
        Config key of the entries (for messages).
    lines : sequence of int, optional
    base : str, optional
        Folder relative entries are resolved against (default: the working directory).
    relative_to : str, optional
        Folder the ids of relative entries are expressed relative to (default:
        the paths as found).

    Returns
    -------
    list of str
        Part ids, duplicates removed: an absolute entry gives the file's
        normalised absolute path; a relative one the file's normalised path
        relative to ``relative_to`` (``/``-separated).  The working directory
        never enters an id: a config names the same parts, with the same ids
        (and so the same keys), from any folder.
    """
    out: list[str] = []
    seen: set[str] = set()
    for i, entry in enumerate(entries):
        line = lines[i] if lines is not None and i < len(lines) else None
        k = f"{key}[{i}]" if lines is not None else key
        if not isinstance(entry, str) or not entry:
            raise c.err(k, f"a part must be a file path or glob, got {short(entry)}", line)
        where = (os.path.join(base, entry) if base is not None and not os.path.isabs(entry)
                 else entry)
        if glob.has_magic(entry):
            try:
                matches = bounded_glob(where)
            except GlobLimitError as e:
                raise c.err(k, f"{short(entry)}: {e}", line) from None
            found = sorted(p for p in matches if os.path.isfile(p))
            if not found:
                raise c.err(k, f"no file matches {short(entry)}{_in(where, entry, base)}", line)
        else:
            if not os.path.exists(where):
                raise c.err(k, f"missing input file {short(entry, 200)}{_in(where, entry, base)}",
                            line)
            if os.path.isdir(where):
                raise c.err(k, f"{entry!r} is a directory (use a glob such as {entry}/*.bvh)",
                            line)
            if is_session(where):
                _add_session(where, os.path.isabs(entry), relative_to, out, seen, fields)
                continue
            found = [where]
        for p in found:
            pid = _part_id(p, absolute=os.path.isabs(entry), relative_to=relative_to)
            if pid not in seen:
                seen.add(pid)
                out.append(pid)
    return out


def _add_session(path: str, absolute: bool, relative_to: str | None, out: list[str],
                 seen: set[str], fields: dict[str, dict[str, Any]] | None) -> None:
    """Append the trials of the session ``path`` to ``out`` (and their fields)."""
    session = read_session(path)
    c = FileErrors(session.path)
    for t in session.trials:
        pid = _part_id(t.path, absolute=absolute or os.path.isabs(t.text),
                       relative_to=relative_to)
        if pid not in seen:
            seen.add(pid)
            out.append(pid)
        elif fields is not None and fields.get(pid, t.fields) != t.fields:
            raise c.err("trial", f"trial {short(t.text, 100)} is already a part with other "
                        "fields (from another session)", t.line)
        if fields is not None and t.fields:
            fields[pid] = dict(t.fields)


def _in(where: str, entry: str, base: str | None) -> str:
    """`` (in FOLDER)`` when a relative entry was resolved against the folder ``base``."""
    return f" (in {short(base, 200)})" if base is not None and where != entry else ""


def _part_id(path: str, *, absolute: bool, relative_to: str | None) -> str:
    """The id of a part file (see :func:`expand_parts`)."""
    if absolute or relative_to is None:
        return os.path.normpath(path).replace(os.sep, "/")
    try:
        rel = os.path.relpath(os.path.abspath(path), relative_to)
    except ValueError:  # another drive (Windows): no relative path exists
        return os.path.abspath(path).replace(os.sep, "/")
    return rel.replace(os.sep, "/")


