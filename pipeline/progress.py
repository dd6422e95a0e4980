"""Run progress on stderr: a bar on a terminal, plain lines otherwise; stage warnings once.

Stage warnings (``ctx.warn``) travel in the task records; :func:`warning_lines`
turns a run's records into one line per distinct message, with a count and the
tasks when it repeats.  :class:`StageWarningFilter` keeps the same warnings out
of the ``mocapflow`` logger's handlers of the command and of worker processes
(printed there as well, every warning showed twice, or once per worker line).
"""

from __future__ import annotations

import logging
import os
import sys
import time
from collections.abc import Iterable
from typing import Any, TextIO

from mocapflow.pipeline import context

__all__ = ["Progress", "StageWarningFilter", "warning_lines"]

#: Task names listed after a repeated warning (then "and N more").
SHOWN_TASKS = 3
_CONTEXT_FILE = os.path.normcase(os.path.abspath(context.__file__))


class StageWarningFilter(logging.Filter):
    """Drop the log records of ``Context.warn`` (the run reports them from its records)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not (record.funcName == "warn"
                    and os.path.normcase(os.path.abspath(record.pathname)) == _CONTEXT_FILE)


def _field(record: Any, name: str) -> Any:
    if isinstance(record, dict):
        return record.get(name)
    return getattr(record, name, None)


def warning_lines(records: Iterable[Any]) -> list[str]:
    """One line per distinct stage warning of a run, in task order.

    Parameters
    ----------
    records : iterable of TaskRecord or dict
        With ``node``, ``part`` and ``warnings`` (a sequence of str).

    Returns
    -------
    list of str
        ``"warning: NODE/PART: message"``; a message given more than once (by one
        task or several) gets ``" (×N in K tasks: also A, B and M more)"``.
    """
    groups: dict[str, tuple[list[int], dict[str, None]]] = {}
    for r in records:
        warnings = _field(r, "warnings")
        if not warnings:
            continue
        part = _field(r, "part")
        name = str(_field(r, "node")) + (f"/{part}" if part is not None else "")
        for w in warnings:
            count, names = groups.setdefault(str(w), ([0], {}))
            count[0] += 1
            names[name] = None
    lines = []
    for msg, (count, names) in groups.items():
        tasks = list(names)
        line = f"warning: {tasks[0]}: {msg}"
        if count[0] > 1:
            line += f" (×{count[0]}"
            if len(tasks) > 1:
                shown = tasks[1:1 + SHOWN_TASKS]
                rest = len(tasks) - 1 - len(shown)
                line += (f" in {len(tasks)} tasks: also {', '.join(shown)}"
                         + (f" and {rest} more" if rest else ""))
            line += ")"
        lines.append(line)
    return lines


def _fmt_seconds(s: float) -> str:
    if s < 60:
        return f"{s:.1f}s"
    m, s = divmod(int(s), 60)
    return f"{m}m{s:02d}s" if m < 60 else f"{m // 60}h{m % 60:02d}m"


class Progress:
    """Count finished tasks and show them.

    On a TTY a one-line bar ``[#####-----] 12/100 hit 9 computed 3 failed 0 (ETA 4.2s)``
    is redrawn at most 10 times a second; otherwise one line per computed,
    failed or skipped task (hits are counted, not listed) and a summary.

    Parameters
    ----------
    total : int
        Number of tasks.
    stream : file, optional
        Default ``sys.stderr``.
    enabled : bool
        ``False`` prints nothing.
    tty : bool, optional
        Force bar (``True``) or plain lines (``False``); default ``stream.isatty()``.
    label : str
        Shown before the bar / in the summary.
    """

    WIDTH = 28

    def __init__(self, total: int, *, stream: TextIO | None = None, enabled: bool = True,
                 tty: bool | None = None, label: str = "") -> None:
        self.total = total
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        if tty is None:
            try:
                tty = bool(self.stream.isatty())
            except (AttributeError, ValueError):
                tty = False
        self.tty = tty
        self.label = label
        self.counts = {"hit": 0, "computed": 0, "failed": 0, "skipped": 0}
        self.done = 0
        self.warnings = 0
        self.start = time.perf_counter()
        self._last_draw = 0.0
        self._drawn = False

    def _write(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # closed pipe: progress is best effort
            self.enabled = False

    def bar(self) -> str:
        """The bar line (without carriage return)."""
        frac = self.done / self.total if self.total else 1.0
        fill = int(round(frac * self.WIDTH))
        c = self.counts
        elapsed = time.perf_counter() - self.start
        eta = ""
        if 0 < self.done < self.total:
            eta = f" ETA {_fmt_seconds(elapsed / self.done * (self.total - self.done))}"
        head = f"{self.label} " if self.label else ""
        return (f"{head}[{'#' * fill}{'-' * (self.WIDTH - fill)}] {self.done}/{self.total} "
                f"hit {c['hit']} computed {c['computed']} failed {c['failed']}"
                f"{' skipped ' + str(c['skipped']) if c['skipped'] else ''}"
                f" {_fmt_seconds(elapsed)}{eta}")

    def update(self, record: dict[str, Any]) -> None:
        """Count one finished task (a task record with ``status``, ``node``, ``part``…)."""
        status = record.get("status", "failed")
        self.counts[status] = self.counts.get(status, 0) + 1
        self.done += 1
        self.warnings += len(record.get("warnings") or ())
        if not self.enabled:
            return
        if self.tty:
            now = time.perf_counter()
            if now - self._last_draw >= 0.1 or self.done == self.total:
                self._last_draw = now
                self._write("\r\x1b[2K" + self.bar())
                self._drawn = True
            if status == "failed":
                self._write("\r\x1b[2K" + self._line(record) + "\n" + self.bar())
            return
        if status != "hit":
            self._write(self._line(record) + "\n")

    def _line(self, r: dict[str, Any]) -> str:
        name = r.get("node", "?") + (f"/{r['part']}" if r.get("part") is not None else "")
        status = r.get("status", "?")
        secs = r.get("seconds")
        tail = f" {secs:.2f}s" if isinstance(secs, (int, float)) and status == "computed" else ""
        err = f": {r['error']}" if r.get("error") and status in ("failed", "skipped") else ""
        return f"[{self.done}/{self.total}] {status:<8} {name}{tail}{err}"

    def close(self) -> None:
        """Finish the bar / print the summary line."""
        if not self.enabled:
            return
        c = self.counts
        elapsed = time.perf_counter() - self.start
        summary = (f"{self.label + ': ' if self.label else ''}{self.done} tasks: {c['hit']} hit, "
                   f"{c['computed']} computed, {c['failed']} failed, {c['skipped']} skipped"
                   f"{f', {self.warnings} warning(s)' if self.warnings else ''} "
                   f"in {_fmt_seconds(elapsed)}")
        if self.tty and self._drawn:
            self._write("\r\x1b[2K")
        self._write(summary + "\n")
