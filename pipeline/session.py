"""Capture sessions: a day's trials, each with its subject's ROM, static and template files.

A session file lists trials and, for each, *fields*: the subject, the
range-of-motion (ROM) trial, the static trial, the label template, notes…  It
is given as a part entry (``parts:`` or ``--parts``): its trials become the
parts, and each part's fields are what ``${part.FIELD}`` params of the graph
read (see :mod:`~mocapflow.pipeline.config_parts` and the README).

YAML (a ``.yaml`` / ``.yml`` file with a top-level ``trials:`` key)::

    subjects:                       # optional: fields every trial of the subject inherits
      S01: {rom: S01/rom.c3d, static: S01/static.c3d}
      S02: {rom: S02/rom.c3d}
    trials:                         # required: one mapping per trial
      - {trial: S01/walk01.c3d, subject: S01}
      - {trial: S02/run01.c3d, subject: S02, notes: "marker 12 loose"}

A trial's own fields win over its subject's; a field set to ``null`` removes
the inherited value.  When ``subjects:`` is given, every trial's ``subject:``
must be one of them.

CSV (a ``.csv`` file whose first header cell is ``trial``; or any file named
``*.session.csv``)::

    trial,subject,rom,static
    S01/walk01.c3d,S01,S01/rom.c3d,S01/static.c3d
    S02/run01.c3d,S02,S02/rom.c3d,

An empty cell is no value (the field is absent for that trial).

Every field but :data:`TEXT_FIELDS` is a file path: relative paths are
resolved against the session file's folder, the value kept is the absolute,
normalised path, and the file must exist.  Each problem is a
:class:`~mocapflow.pipeline.config_yaml.ConfigError` naming the session
``FILE:LINE``, the key and the trial.  Reading is bounded: at most
:data:`~mocapflow.pipeline.config_yaml.MAX_CONFIG_BYTES` of text,
:data:`MAX_TRIALS` trials and :data:`MAX_FIELDS` fields per trial (a YAML
session also has the YAML loader's node limit: 10,000 trials with a few
fields each are well within it; a CSV session has no such limit).
"""

from __future__ import annotations

import csv
import io
import os
import re
from dataclasses import dataclass, field
from typing import Any

from mocapflow.pipeline.config_yaml import (
    MAX_CONFIG_BYTES,
    FileErrors,
    close_match,
    line_of,
    load_yaml,
    short,
)

__all__ = ["MAX_FIELDS", "MAX_TRIALS", "TEXT_FIELDS", "Session", "Trial", "is_session",
           "read_session"]

#: Fields that are text, not file paths.
TEXT_FIELDS = ("subject", "notes", "condition", "description")
#: Most trials in one session (the most tasks a graph may have).
MAX_TRIALS = 1_000_000
#: Most fields of one trial (CSV columns).
MAX_FIELDS = 64
_TOP_KEYS = ("subjects", "trials", "description")
_FIELD = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_TRIALS_KEY = re.compile(rb"^trials[ \t]*:", re.MULTILINE)


@dataclass(frozen=True)
class Trial:
    """One trial of a session.

    Attributes
    ----------
    path : str
        The trial file, absolute and normalised.
    text : str
        The path as written in the session.
    line : int
        Line of the trial in the session file.
    fields : dict
        ``field -> value`` (absolute path for path fields, text for
        :data:`TEXT_FIELDS`), the subject's fields inherited.
    """

    path: str
    text: str
    line: int
    fields: dict[str, Any] = field(default_factory=dict)


@dataclass
class Session:
    """A session file, read and checked.

    Attributes
    ----------
    path : str
        The session file.
    trials : list of Trial
        In file order.
    subjects : dict
        ``subject -> fields`` (YAML ``subjects:``; empty for CSV).
    """

    path: str
    trials: list[Trial]
    subjects: dict[str, dict[str, Any]] = field(default_factory=dict)


def is_session(path: str) -> bool:
    """Whether the file ``path`` is a session (see the module docstring).

    A ``.yaml``/``.yml`` file whose text has a top-level ``trials:`` key, a
    ``.csv`` whose first header cell is ``trial``, or a file named
    ``*.session.csv`` / ``*.session.yaml`` / ``*.session.yml`` (whose problems are
    then errors).  Only the first bytes of a CSV are read; a larger YAML file than
    a config may be is not a session.
    """
    low = path.lower()
    if low.endswith((".session.csv", ".session.yaml", ".session.yml")):
        return True
    try:
        if low.endswith((".yaml", ".yml")):
            if os.path.getsize(path) > MAX_CONFIG_BYTES:
                return False
            with open(path, "rb") as f:
                return _TRIALS_KEY.search(f.read()) is not None
        if low.endswith(".csv"):
            with open(path, "rb") as f:
                head = f.read(4096).decode("utf-8-sig", errors="replace")
            first = head.splitlines()[0] if head else ""
            cell = next(csv.reader([first]), [""])
            return bool(cell) and cell[0].strip().lower() == "trial"
    except OSError:
        return False
    return False


def read_session(path: str | os.PathLike) -> Session:
    """Read and check a session file (YAML or CSV, by its suffix).

    Parameters
    ----------
    path : path-like
        The session file.

    Returns
    -------
    Session

    Raises
    ------
    ConfigError
        One line ``SESSION:LINE: key: problem`` (a missing file, an unknown
        subject, no ``trial`` column, a malformed file, a session over a limit).
    """
    file = os.fspath(path)
    c = FileErrors(file)
    try:
        if os.path.getsize(file) > MAX_CONFIG_BYTES:
            raise c.err("", f"session is larger than {MAX_CONFIG_BYTES >> 20} MiB")
        with open(file, encoding="utf-8-sig", newline="") as f:
            text = f.read()
    except FileNotFoundError:
        raise c.err("", "session file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise c.err("", f"cannot read session: {e}") from None
    base = os.path.dirname(os.path.abspath(file))
    files = _Files(base, c)
    if file.lower().endswith(".csv"):
        return _read_csv(text, file, c, files)
    return _read_yaml(text, file, c, files)


class _Files:
    """Path fields → absolute paths, each checked once (a ROM shared by 1,000 trials)."""

    def __init__(self, base: str, c: FileErrors) -> None:
        self.base = base
        self.c = c
        self.seen: dict[str, str] = {}

    def resolve(self, value: Any, name: str, key: str, line: int | None, trial: str | None
                ) -> str:
        of = f"trial {short(trial, 100)}: " if trial is not None else ""
        if not isinstance(value, str) or not value.strip():
            raise self.c.err(key, f"{of}{name} must be a file path, got {short(value)}", line)
        value = value.strip()
        hit = self.seen.get(value)
        if hit is not None:
            return hit
        p = os.path.normpath(os.path.join(self.base, os.path.expanduser(value)))
        if not os.path.isfile(p):
            what = "is a directory" if os.path.isdir(p) else "missing file"
            where = f" (in {short(self.base, 200)})" if not os.path.isabs(value) else ""
            raise self.c.err(key, f"{of}{what} {short(value, 200)}{where} ({name})", line)
        self.seen[value] = p
        return p


def _field_value(name: str, value: Any, files: _Files, key: str, line: int | None,
                 trial: str | None) -> Any:
    """A field's value: text for :data:`TEXT_FIELDS`, else an existing file's absolute path."""
    if name in TEXT_FIELDS:
        if isinstance(value, (dict, list)):
            raise files.c.err(key, f"{name} must be text, got {short(value)}", line)
        return str(value)
    return files.resolve(value, name, key, line, trial)


def _check_name(name: Any, c: FileErrors, key: str, line: int | None) -> str:
    if not isinstance(name, str) or not _FIELD.match(name):
        raise c.err(key, f"a field name must be letters, digits and _, got {short(name)}", line)
    return name


def _read_yaml(text: str, file: str, c: FileErrors, files: _Files) -> Session:
    doc = load_yaml(text, file)
    if not isinstance(doc, dict) or "trials" not in doc:
        raise c.err("trials", "a YAML session is a mapping with a trials: list",
                    getattr(doc, "line", 1) or 1)
    for k in doc:
        if k not in _TOP_KEYS:
            raise c.err(str(k), f"unknown session key{close_match(k, _TOP_KEYS)} (keys: "
                        f"{', '.join(_TOP_KEYS)})", line_of(doc, k))
    subjects: dict[str, dict[str, Any]] = {}
    raw_subjects = doc.get("subjects") or {}
    if not isinstance(raw_subjects, dict):
        raise c.err("subjects", "must be a mapping subject: {field: value}",
                    line_of(doc, "subjects"))
    for s, body in raw_subjects.items():
        sk, sl = f"subjects.{s}", line_of(raw_subjects, s)
        if not isinstance(body, dict):
            raise c.err(sk, "must be a mapping of fields (rom:, static:, template: …)", sl)
        fields: dict[str, Any] = {"subject": str(s)}
        for name, v in body.items():
            name = _check_name(name, c, f"{sk}.{name}", line_of(body, name))
            if v is not None and name != "subject":
                fields[name] = _field_value(name, v, files, f"{sk}.{name}",
                                            line_of(body, name), None)
        subjects[str(s)] = fields
    raw_trials = doc["trials"]
    if not isinstance(raw_trials, list) or not raw_trials:
        raise c.err("trials", "must be a non-empty list of {trial: path, …}",
                    line_of(doc, "trials"))
    if len(raw_trials) > MAX_TRIALS:
        raise c.err("trials", f"more than {MAX_TRIALS:,} trials", line_of(doc, "trials"))
    trials: list[Trial] = []
    seen: dict[str, int] = {}
    for i, row in enumerate(raw_trials):
        key, line = f"trials[{i}]", line_of(raw_trials, i)
        if isinstance(row, str):  # a bare path: a trial with no fields of its own
            row = {"trial": row}
        if not isinstance(row, dict):
            raise c.err(key, f"a trial is a mapping {{trial: path, …}}, got {short(row)}", line)
        if "trial" not in row:
            raise c.err(key, "no trial: (the trial's file)", line)
        if len(row) > MAX_FIELDS:
            raise c.err(key, f"more than {MAX_FIELDS} fields", line)
        trial_text = row["trial"]
        tline = line_of(row, "trial") or line
        own: dict[str, Any] = {}
        for name, v in row.items():
            if name == "trial":
                continue
            own[_check_name(name, c, f"{key}.{name}", line_of(row, name) or line)] = v
        fields: dict[str, Any] = {}
        subject = own.get("subject")
        if subject is not None:
            subject = str(subject)
            if raw_subjects and subject not in subjects:
                raise c.err(f"{key}.subject", f"trial {short(trial_text, 100)}: unknown subject "
                            f"{subject!r}{close_match(subject, subjects)} (subjects: "
                            f"{', '.join(subjects)})", line_of(row, "subject") or line)
            fields.update(subjects.get(subject, {"subject": subject}))
        for name, v in own.items():
            if v is None:
                fields.pop(name, None)
            else:
                fields[name] = _field_value(name, v, files, f"{key}.{name}",
                                            line_of(row, name) or line, str(trial_text))
        path = files.resolve(trial_text, "trial", f"{key}.trial", tline, None)
        _add(trials, seen, Trial(path, str(trial_text).strip(), tline or 0, fields), c, key)
    return Session(path=file, trials=trials, subjects=subjects)


def _read_csv(text: str, file: str, c: FileErrors, files: _Files) -> Session:
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        header = next(reader, None)
        if header is None:
            raise c.err("trial", "empty session (the header row must start with trial)", 1)
        header = [h.strip() for h in header]
        if not header or header[0].lower() != "trial":
            raise c.err("trial", "no trial column: the first header cell must be trial "
                        f"(header: {short(','.join(header), 120)})", 1)
        if len(header) > MAX_FIELDS + 1:
            raise c.err("", f"more than {MAX_FIELDS} columns", 1)
        names = [_check_name(h, c, f"column {j + 1}", 1) for j, h in enumerate(header[1:])]
        dup = next((n for j, n in enumerate(names) if n in names[:j]), None)
        if dup is not None or "trial" in names:
            raise c.err(dup or "trial", "column given twice", 1)
        trials: list[Trial] = []
        seen: dict[str, int] = {}
        line = reader.line_num + 1
        for row in reader:
            here, line = line, reader.line_num + 1
            if not any(cell.strip() for cell in row):
                continue  # a blank line
            if len(trials) >= MAX_TRIALS:
                raise c.err("", f"more than {MAX_TRIALS:,} trials", here)
            if len(row) > len(header):
                raise c.err("", f"{len(row)} cells, more than the {len(header)} columns", here)
            trial_text = row[0].strip()
            if not trial_text:
                raise c.err("trial", "empty trial cell", here)
            fields: dict[str, Any] = {}
            for name, cell in zip(names, row[1:]):
                if cell.strip():
                    fields[name] = _field_value(name, cell.strip(), files, name, here,
                                                trial_text)
            path = files.resolve(trial_text, "trial", "trial", here, None)
            _add(trials, seen, Trial(path, trial_text, here, fields), c, "trial")
    except csv.Error as e:
        raise c.err("", f"malformed CSV: {e}", reader.line_num or None) from None
    if not trials:
        raise c.err("trial", "no trials (a header row and one row per trial)", 1)
    return Session(path=file, trials=trials)


def _add(trials: list[Trial], seen: dict[str, int], t: Trial, c: FileErrors, key: str) -> None:
    first = seen.get(t.path)
    if first is not None:
        raise c.err(key, f"trial {short(t.text, 100)} listed twice (first at line {first})",
                    t.line)
    seen[t.path] = t.line
    trials.append(t)

