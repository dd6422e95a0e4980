"""Pen strokes: UCI Character Trajectories CSV, Omniglot stroke files, our strokes CSV.

UCI Character Trajectories (``uci_chartraj_mv_subset.csv``)
-----------------------------------------------------------
Columns ``letter, example, sample, force, vx, vy, x, y`` at 200 Hz; one
:class:`~mocapflow.stages.motion.datatypes.Strokes` per ``(letter, example)`` with every row
kept (``points`` = ``x, y``, ``times`` = ``sample / 200`` s).  Each character is
**one stroke** (``stroke_starts == [0]``): the UCI collection kept only characters
written with a single pen-down segment, and the ``force`` column cannot mark
pen-up samples — it is the smoothed time derivative of the tip force (it goes
negative, and inside strokes it decays through 1e-10 … 1e-15 into exact-zero runs
while the pen keeps moving, e.g. 'n' example 5, samples 71–88).  The leading rows
with zero force and zero velocity (3–54 per character) are the pen at rest
before writing; they are kept so the sample counts match the source
(letter 'a': 136–143 samples).

Omniglot (``characterNN/<image>_<drawer>.txt``)
-----------------------------------------------
``START``, then strokes of ``x,y,t_ms`` rows each closed by ``BREAK``.  One
Strokes per file: ``stroke_starts`` at each stroke, ``times`` in seconds (as
recorded: browser timestamps, occasionally non-monotonic), ``rate`` estimated as
1000 / median positive within-stroke time step (ms).

mocapflow strokes CSV (:func:`write_strokes_csv` / :func:`read_strokes_csv`)
-------------------------------------------------------------------------------
``# mocapflow-strokes 1`` then, per example, ``# example <i> <json meta>`` (rate,
attrs, whether times exist) and the table ``example,stroke,x,y,t`` with floats in
shortest round-trip ``repr``, so a write/read round trip is exact.
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.stages.motion.datatypes import Strokes

__all__ = [
    "UCI_RATE",
    "StrokesFileError",
    "read_omniglot",
    "read_strokes_csv",
    "read_strokes_file",
    "read_uci_chartraj",
    "write_strokes_csv",
]

#: Sampling rate of the UCI Character Trajectories data (Hz).
UCI_RATE = 200.0
_MAGIC = "# mocapflow-strokes 1"
_UCI_REQUIRED = ("letter", "example", "sample", "x", "y")


class StrokesFileError(ValueError):
    """A stroke file is empty or malformed (the message names the file and line)."""


def _fail(path: Path, msg: str, line: int | None = None) -> StrokesFileError:
    where = f"{path}" + (f", line {line}" if line is not None else "")
    return StrokesFileError(f"{where}: {msg}")


def _read_lines(path: Path) -> list[str]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as e:
        raise _fail(path, f"cannot read ({e.strerror or e})") from None
    except UnicodeDecodeError:
        raise _fail(path, "not a text file") from None
    if not text.strip():
        raise _fail(path, "empty file")
    return text.splitlines()


# --------------------------------------------------------------------------- UCI


def _parse_table(path: Path, lines: list[str], required: Sequence[str]) -> tuple[list[str], list]:
    """Split a CSV (no quoting) into a header and rows, checking field counts."""
    body = [(i + 1, ln) for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")]
    if not body:
        raise _fail(path, "no CSV header")
    hline, header = body[0][0], [h.strip().lower() for h in body[0][1].split(",")]
    missing = [c for c in required if c not in header]
    if missing:
        raise _fail(path, f"CSV header lacks column(s) {missing} (has {header})", hline)
    rows = []
    for lineno, ln in body[1:]:
        fields = [f.strip() for f in ln.split(",")]
        if len(fields) != len(header):
            raise _fail(path, f"expected {len(header)} fields, got {len(fields)}", lineno)
        rows.append((lineno, fields))
    if not rows:
        raise _fail(path, "no data rows")
    return header, rows


def _floats(
    path: Path, lineno: int, fields: list[str], cols: list[int], names, *, nan_ok: int = 0
) -> list[float]:
    """The finite numbers of ``fields[cols]``; the last ``nan_ok`` columns may also be
    empty or NaN (a missing time)."""
    out = []
    for k, c in enumerate(cols):
        may_be_nan = k >= len(cols) - nan_ok
        try:
            v = float(fields[c]) if fields[c] != "" or not may_be_nan else math.nan
        except ValueError:
            msg = f"column {names[c]!r}: {fields[c]!r} is not a number"
            raise _fail(path, msg, lineno) from None
        if not (math.isfinite(v) or (may_be_nan and math.isnan(v))):
            raise _fail(path, f"column {names[c]!r}: {fields[c]!r} is not finite", lineno)
        out.append(v)
    return out


def read_uci_chartraj(path: str | os.PathLike, *, letter: str | None = None) -> list[Strokes]:
    """Read the UCI Character Trajectories CSV: one Strokes per (letter, example).

    Parameters
    ----------
    path : str or path-like
        CSV with columns ``letter, example, sample, x, y`` (``force, vx, vy`` ignored).
    letter : str, optional
        Keep only this letter.

    Returns
    -------
    list of Strokes
        In file order; ``points (N, 2)`` = ``x, y`` of every row, ``stroke_starts``
        = ``[0]`` (single pen-down segment, see the module docstring), ``rate`` 200,
        ``times (N,)`` = ``sample / 200`` s, ``attrs`` ``letter``, ``example``,
        ``source``, ``unit`` (``"uci"``: cumulative sum of the normalised velocities).

    Raises
    ------
    StrokesFileError
        Empty file, missing columns, wrong field count, non-numeric value,
        samples not numbered 0, 1, 2 … within an example, or no row for ``letter``.
    """
    path = Path(path)
    header, rows = _parse_table(path, _read_lines(path), _UCI_REQUIRED)
    ci = {c: header.index(c) for c in _UCI_REQUIRED}
    groups: dict[tuple[str, int], list] = {}
    for lineno, f in rows:
        let = f[ci["letter"]]
        if letter is not None and let != letter:
            continue
        try:
            ex = int(f[ci["example"]])
            smp = int(f[ci["sample"]])
        except ValueError:
            raise _fail(path, "example and sample must be integers", lineno) from None
        x, y = _floats(path, lineno, f, [ci["x"], ci["y"]], header)
        g = groups.setdefault((let, ex), [])
        if smp != len(g):
            raise _fail(
                path, f"letter {let!r} example {ex}: sample {smp}, expected {len(g)}", lineno
            )
        g.append((x, y))
    if not groups:
        raise _fail(path, f"no rows for letter {letter!r}" if letter else "no data rows")
    out = []
    for (let, ex), xy in groups.items():
        pts = np.asarray(xy, dtype=np.float64)
        out.append(
            Strokes(
                points=pts,
                stroke_starts=np.zeros(1, np.int64),
                rate=UCI_RATE,
                times=np.arange(len(pts)) / UCI_RATE,
                attrs={"letter": let, "example": ex, "source": path.name, "unit": "uci"},
            )
        )
    return out


# --------------------------------------------------------------------------- Omniglot


_OMNIGLOT_CHAR = re.compile(r"character(\d+)$", re.IGNORECASE)


def read_omniglot(path: str | os.PathLike) -> Strokes:
    """Read one Omniglot stroke file (``START``, ``x,y,t_ms`` rows, ``BREAK`` after each stroke).

    Parameters
    ----------
    path : str or path-like
        ``.../characterNN/<image>_<drawer>.txt``.

    Returns
    -------
    Strokes
        ``points (N, 2)`` as recorded (pixels, y negative downwards),
        ``stroke_starts (S,)``, ``times (N,)`` in seconds, ``rate`` = 1000 /
        median positive within-stroke step in ms (NaN if no stroke has two
        samples), ``attrs`` ``source``, ``character`` (directory name), ``drawer``,
        and ``letter`` when the file lies under a ``*latin*`` directory
        (character01 = ``"a"`` …).

    Raises
    ------
    StrokesFileError
        Empty file, missing ``START``, a row that is not three numbers, or no stroke.
    """
    path = Path(path)
    lines = _read_lines(path)
    first = next((i for i, ln in enumerate(lines) if ln.strip()), None)
    if first is None or lines[first].strip() != "START":
        raise _fail(path, "an Omniglot stroke file starts with START", (first or 0) + 1)
    rows: list[tuple[float, float, float]] = []
    starts: list[int] = []
    open_stroke = False
    for i in range(first + 1, len(lines)):
        s = lines[i].strip()
        if not s:
            continue
        if s == "BREAK":
            open_stroke = False
            continue
        if s == "START":
            raise _fail(path, "second START", i + 1)
        parts = s.split(",")
        try:
            x, y, t = (float(p) for p in parts)
        except ValueError:
            raise _fail(path, f"expected 'x,y,t_ms', got {s[:40]!r}", i + 1) from None
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(t)):
            raise _fail(path, f"stroke sample 'x,y,t_ms' is not finite: {s[:40]!r}", i + 1)
        if not open_stroke:
            starts.append(len(rows))
            open_stroke = True
        rows.append((x, y, t))
    if not rows:
        raise _fail(path, "no stroke samples")
    arr = np.asarray(rows, dtype=np.float64)
    t = arr[:, 2] / 1000.0
    same = np.ones(len(arr) - 1, bool)
    same[np.asarray(starts[1:], dtype=np.int64) - 1] = False
    dt = np.diff(arr[:, 2])[same]
    dt = dt[dt > 0]
    rate = 1000.0 / float(np.median(dt)) if dt.size else math.nan
    attrs: dict[str, Any] = {"source": path.name, "character": path.parent.name, "unit": "px"}
    stem = path.stem.rsplit("_", 1)
    if len(stem) == 2 and stem[1].isdigit():
        attrs["drawer"] = int(stem[1])
    m = _OMNIGLOT_CHAR.match(path.parent.name)
    if m and "latin" in path.parent.parent.name.lower() and 1 <= int(m.group(1)) <= 26:
        attrs["letter"] = chr(ord("a") + int(m.group(1)) - 1)
    return Strokes(
        points=arr[:, :2], stroke_starts=np.asarray(starts), rate=rate, times=t, attrs=attrs
    )


# --------------------------------------------------------------------------- our CSV


def write_strokes_csv(strokes_list: Sequence[Strokes], path: str | os.PathLike) -> Path:
    """Write strokes as one CSV that :func:`read_strokes_csv` reads back exactly.

    Parameters
    ----------
    strokes_list : sequence of Strokes
        Examples ``0 … K-1`` (a single Strokes is accepted too).
    path : str or path-like

    Returns
    -------
    Path
        The file.  Columns ``example,stroke,x,y,t`` (``t`` empty without times);
        one ``# example <i> {json}`` line per example carries ``rate`` and ``attrs``.
    """
    if isinstance(strokes_list, Strokes):
        strokes_list = [strokes_list]
    path = Path(path)
    out = [_MAGIC]
    for i, s in enumerate(strokes_list):
        meta = {"rate": _jnum(s.rate), "times": s.times is not None, "attrs": s.attrs}
        out.append(f"# example {i} {json.dumps(meta, sort_keys=True, default=_jdefault)}")
    out.append("example,stroke,x,y,t")
    for i, s in enumerate(strokes_list):
        stroke = np.zeros(len(s.points), np.int64)
        stroke[s.stroke_starts[1:]] = 1
        stroke = np.cumsum(stroke)
        t = s.times if s.times is not None else [None] * len(s.points)
        for k, (x, y), tt in zip(stroke, s.points.tolist(), t):
            ts = "" if tt is None else repr(float(tt))
            out.append(f"{i},{k},{x!r},{y!r},{ts}")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".csv", prefix=f".{path.stem}-", dir=path.parent)
    with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as f:
        f.write("\n".join(out) + "\n")
    os.replace(tmp, path)
    return path


def _jnum(v: float) -> float | str:
    return v if math.isfinite(v) else repr(v)


def _jdefault(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"attrs value of type {type(o).__name__} is not JSON")


def _meta(meta: Any) -> dict:
    """A ``# example`` line's JSON: an object with a rate (a number > 0, or NaN), an
    ``attrs`` object and a ``times`` flag; ``TypeError`` saying what is wrong otherwise."""
    if not isinstance(meta, dict):
        raise TypeError(f"expected a JSON object, got {type(meta).__name__}")
    rate = meta.get("rate")
    try:
        rate = float(rate)
    except (TypeError, ValueError):
        raise TypeError(f"rate {rate!r} is not a number") from None
    if not (rate > 0 and math.isfinite(rate)) and not math.isnan(rate):
        raise TypeError(f"rate {meta.get('rate')!r} is not a finite number > 0")
    if not isinstance(meta.get("attrs", {}), dict):
        raise TypeError(f"attrs is a {type(meta['attrs']).__name__}, not an object")
    if not isinstance(meta.get("times", False), bool):
        raise TypeError(f"times is {meta['times']!r}, not true or false")
    return meta


def read_strokes_csv(path: str | os.PathLike) -> list[Strokes]:
    """Read a file written by :func:`write_strokes_csv`.

    Returns
    -------
    list of Strokes
        In example order, equal to what was written.

    Raises
    ------
    StrokesFileError
        Not a mocapflow strokes CSV, bad meta line, bad row, or examples without rows.
    """
    path = Path(path)
    lines = _read_lines(path)
    if lines[0].strip() != _MAGIC:
        raise _fail(path, f"not a mocapflow strokes CSV (first line is not {_MAGIC!r})", 1)
    metas: dict[int, dict] = {}
    for i, ln in enumerate(lines):
        if ln.startswith("# example "):
            try:
                _, _, idx, blob = ln.split(" ", 3)
                metas[int(idx)] = _meta(json.loads(blob))
            except (ValueError, RecursionError):  # JSONDecodeError is a ValueError
                raise _fail(path, "malformed '# example' line", i + 1) from None
            except TypeError as e:
                raise _fail(path, f"'# example' line: {e}", i + 1) from None
    header, rows = _parse_table(path, lines, ("example", "stroke", "x", "y", "t"))
    ci = [header.index(c) for c in ("x", "y", "t")]
    data: dict[int, list] = {k: [] for k in metas}
    for lineno, f in rows:
        try:
            ex, st = int(f[header.index("example")]), int(f[header.index("stroke")])
        except ValueError:
            raise _fail(path, "example and stroke must be integers", lineno) from None
        if ex not in data:
            raise _fail(path, f"example {ex} has no '# example' line", lineno)
        data[ex].append((st, *_floats(path, lineno, f, ci, header, nan_ok=1)))
    out = []
    for ex in sorted(metas):
        if not data[ex]:
            raise _fail(path, f"example {ex} has no rows")
        arr = np.asarray(data[ex], dtype=np.float64)
        st = arr[:, 0].astype(np.int64)
        starts = np.concatenate([[0], np.flatnonzero(np.diff(st)) + 1])
        meta = metas[ex]
        out.append(
            Strokes(
                points=arr[:, 1:3],
                stroke_starts=starts,
                rate=float(meta["rate"]),
                times=arr[:, 3] if meta.get("times") else None,
                attrs=meta.get("attrs", {}),
            )
        )
    return out


# --------------------------------------------------------------------------- dispatch


def read_strokes_file(path: str | os.PathLike, *, letter: str | None = None) -> list[Strokes]:
    """Read any supported stroke file, detected by content.

    A mocapflow strokes CSV (magic first line), a UCI CSV (header with ``letter``
    and ``example``) or an Omniglot file (first line ``START``, or any ``.txt``).

    Returns
    -------
    list of Strokes
        Filtered by ``letter`` where the examples carry one.
    """
    path = Path(path)
    lines = _read_lines(path)
    head = next(ln.strip() for ln in lines if ln.strip())
    if head == _MAGIC:
        items = read_strokes_csv(path)
    elif head == "START" or path.suffix.lower() == ".txt":
        items = [read_omniglot(path)]
    elif {"letter", "example"} <= {h.strip().lower() for h in head.split(",")}:
        return read_uci_chartraj(path, letter=letter)
    else:
        raise _fail(path, "not a stroke file (UCI CSV, Omniglot START/BREAK or mocapflow CSV)", 1)
    if letter is not None:
        items = [s for s in items if s.attrs.get("letter", letter) == letter]
        if not items:
            raise _fail(path, f"no example of letter {letter!r}")
    return items
