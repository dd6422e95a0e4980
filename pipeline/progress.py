"""Run progress on stderr: a bar on a terminal, plain lines otherwise; stage warnings once.

:class:`Progress` shows the run on ``rich.progress``: one bar for the tasks
(done/total, hits, computed, failed) and, under it, one line per running task
that reports progress of its own (``ctx.progress``), removed when the task
ends.  On a stream that is not a terminal it prints plain lines: one per
computed, failed or skipped task and one per tenth of a task's own progress.

A task's ``ctx.progress`` calls reach the command through a
:class:`ProgressReporter` (rate-limited where the task runs: at most
:attr:`ProgressReporter.EVERY_S` apart, and always the last one) and the
executor's transport (:func:`~mocapflow.pipeline.executors.progress_sink`).

Stage warnings (``ctx.warn``) travel in the task records; :func:`warning_lines`
turns a run's records into one line per distinct message, with a count, the
tasks when it repeats and the stage's "what to do" hint when it gave one.
:class:`StageWarningFilter` keeps the same warnings out
of the ``mocapflow`` logger's handlers of the command and of worker processes
(printed there as well, every warning showed twice, or once per worker line).
"""

from __future__ import annotations

import functools
import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any, TextIO

from mocapflow.pipeline import context
from mocapflow.pipeline.context import split_hint

__all__ = ["Progress", "ProgressReporter", "StageWarningFilter", "warning_lines"]

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
        task or several) gets ``" (×N in K tasks: also A, B and M more)"``; a
        warning with a hint (``ctx.warn(message, hint=...)``) ends with
        ``" — what to do: hint"``.
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
    for text, (count, names) in groups.items():
        msg, hint = split_hint(text)
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
        if hint:
            line += f"{context.HINT_SEP}{hint}"
        lines.append(line)
    return lines


def _fmt_seconds(s: float) -> str:
    if s < 60:
        return f"{s:.1f}s"
    m, s = divmod(int(s), 60)
    return f"{m}m{s:02d}s" if m < 60 else f"{m // 60}h{m % 60:02d}m"


def _task_name(node: Any, part: Any) -> str:
    return f"{node}/{part}" if part is not None else str(node)


class ProgressReporter:
    """The ``ctx.progress`` hook of one task: forwards updates to a sink, rate-limited.

    An update is sent when :attr:`EVERY_S` seconds passed since the last one
    sent, or when it completes its work (``done >= total``); :meth:`flush` (the
    engine calls it when the stage returns) sends the last update if it was
    held back.  A sink that raises is dropped: progress never fails a stage.

    Parameters
    ----------
    sink : callable
        ``sink(message)`` with a dict of plain values (msgpack-safe): ``fields``
        and ``done``, ``total``, ``label``.
    fields : dict
        Identify the task (the engine: ``run``, ``index``, ``node``, ``part``).
    every : float, optional
        Seconds between updates (default :attr:`EVERY_S`).

    Attributes
    ----------
    sent : int
        Updates sent so far.
    """

    #: Seconds between two updates of a task (at most ~4 a second).
    EVERY_S = 0.25

    def __init__(self, sink: Callable[[dict[str, Any]], None], fields: dict[str, Any], *,
                 every: float | None = None) -> None:
        self.sink: Callable[[dict[str, Any]], None] | None = sink
        self.fields = dict(fields)
        self.every = self.EVERY_S if every is None else float(every)
        self.sent = 0
        self._last = -float("inf")
        self._pending: tuple[int, int, str] | None = None

    def __call__(self, done: int, total: int, label: str = "") -> None:
        if self.sink is None:
            return
        now = time.monotonic()
        if now - self._last >= self.every or (total > 0 and done >= total):
            self._last = now
            self._send(done, total, label)
        else:
            self._pending = (done, total, label)

    def flush(self) -> None:
        """Send the last update if the rate limit held it back."""
        if self._pending is not None and self.sink is not None:
            self._send(*self._pending)

    def _send(self, done: int, total: int, label: str) -> None:
        self._pending = None
        try:
            self.sink({**self.fields, "done": int(done), "total": int(total),
                       "label": str(label)})
            self.sent += 1
        except Exception:  # no listener, a closed connection: progress is best effort
            self.sink = None


class Progress:
    """Count finished tasks and show them, with the running tasks' own progress.

    On a terminal (``rich.progress``): a bar
    ``[━━━━━     ] 12/100 hit 9 computed 3 failed 0  0:00:04 ETA 0:00:31`` and
    under it one line per running task that reports progress
    (``node/part  label  ━━━  done/total``), removed when the task ends; a
    failed task gets a line above the bar.  Otherwise one line per computed,
    failed or skipped task (hits are counted, not listed), one line per tenth
    of a task's own progress, and a summary.

    Parameters
    ----------
    total : int
        Number of tasks.
    stream : file, optional
        Default ``sys.stderr``.
    enabled : bool
        ``False`` prints nothing.
    tty : bool, optional
        Force the live display (``True``) or plain lines (``False``); default
        ``stream.isatty()``.
    label : str
        Shown before the bar / in the summary.

    Attributes
    ----------
    inner : list of dict
        The last ``ctx.progress`` update of every task that sent one
        (:meth:`task_progress`), by arrival.
    inner_updates : int
        Updates received.
    """

    WIDTH = 28
    #: Plain lines: a task's own progress is printed once per this fraction of it.
    PLAIN_STEP = 0.1
    #: Seconds between redraws of the task bar for hits and finished tasks.
    REDRAW_S = 0.1

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
        self.inner_updates = 0
        self._inner: dict[Any, dict[str, Any]] = {}
        self._ended: set[Any] = set()
        self._steps: dict[Any, int] = {}
        self._lock = threading.RLock()
        self._live: Any = None
        self._started = False
        self._last_draw = 0.0
        if self.enabled and self.tty:
            self._make_live()
        self.start = time.perf_counter()

    @property
    def inner(self) -> list[dict[str, Any]]:
        with self._lock:
            return list(self._inner.values())

    # ------------------------------------------------------------------ output

    def _write(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # closed pipe: progress is best effort
            self.enabled = False

    def _make_live(self) -> None:
        """The rich display (started on the first update, stopped by :meth:`close`)."""
        from rich import progress as rp  # noqa: PLC0415 (only on a terminal; slow import)
        from rich.console import Console, Group  # noqa: PLC0415
        from rich.live import Live  # noqa: PLC0415

        console = Console(file=self.stream, force_terminal=True, highlight=False)
        self._bar = rp.Progress(
            rp.TextColumn("{task.description}", markup=False),
            _bracket_bar_class()(bar_width=self.WIDTH),
            rp.TextColumn("{task.completed}/{task.total} hit {task.fields[hit]} computed "
                          "{task.fields[computed]} failed {task.fields[failed]}"
                          "{task.fields[skipped]}", markup=False),
            rp.TimeElapsedColumn(), rp.TextColumn("ETA"), rp.TimeRemainingColumn(),
            console=console)
        self._bar_task = self._bar.add_task(self.label or "tasks", total=self.total, hit=0,
                                            computed=0, failed=0, skipped="")
        self._rows = rp.Progress(
            rp.TextColumn("  {task.description}", markup=False),
            rp.TextColumn("{task.fields[label]}", markup=False), rp.BarColumn(bar_width=20),
            rp.MofNCompleteColumn(), console=console)
        self._row_ids: dict[Any, Any] = {}
        self._live = Live(Group(self._bar, self._rows), console=console, transient=True,
                          refresh_per_second=8, redirect_stdout=False,
                          redirect_stderr=self.stream is sys.stderr)

    def _start_live(self) -> None:
        if not self._started:
            self._started = True
            self._live.start()

    def _draw_bar(self, force: bool = False) -> None:
        now = time.perf_counter()
        if not (force or now - self._last_draw >= self.REDRAW_S or self.done == self.total):
            return
        self._last_draw = now
        c = self.counts
        self._bar.update(self._bar_task, completed=self.done, hit=c["hit"],
                         computed=c["computed"], failed=c["failed"],
                         skipped=f" skipped {c['skipped']}" if c["skipped"] else "")

    def bar(self) -> str:
        """The task bar as one line of plain text."""
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

    # ------------------------------------------------------------------ updates

    def update(self, record: dict[str, Any]) -> None:
        """Count one finished task (a task record with ``status``, ``node``, ``part``…)."""
        with self._lock:
            status = record.get("status", "failed")
            self.counts[status] = self.counts.get(status, 0) + 1
            self.done += 1
            self.warnings += len(record.get("warnings") or ())
            key = record.get("index")
            if key is not None:
                self._ended.add(key)
                self._steps.pop(key, None)
            if not self.enabled:
                return
            if self.tty:
                self._start_live()
                if key in self._row_ids:
                    self._rows.remove_task(self._row_ids.pop(key))
                if status == "failed":
                    from rich.text import Text  # noqa: PLC0415

                    self._live.console.print(Text(self._line(record)), soft_wrap=True)
                self._draw_bar()
                return
            if status != "hit":
                self._write(self._line(record) + "\n")

    def task_progress(self, message: dict[str, Any]) -> None:
        """Show one ``ctx.progress`` update of a running task.

        Parameters
        ----------
        message : dict
            ``index`` (or ``node`` and ``part``) of the task, ``done``,
            ``total``, ``label`` (what :class:`ProgressReporter` sends).  An
            update that arrives after its task ended is ignored.
        """
        with self._lock:
            key = message.get("index", (message.get("node"), message.get("part")))
            if key in self._ended:
                return
            self.inner_updates += 1
            self._inner[key] = dict(message)
            if not self.enabled:
                return
            done, total = int(message.get("done", 0)), int(message.get("total", 0))
            label = str(message.get("label") or "")
            name = _task_name(message.get("node", "?"), message.get("part"))
            if self.tty:
                self._start_live()
                row = self._row_ids.get(key)
                if row is None:
                    self._row_ids[key] = self._rows.add_task(
                        name, total=total or None, completed=done, label=label)
                else:
                    self._rows.update(row, total=total or None, completed=done, label=label)
                return
            step = int(done / total / self.PLAIN_STEP) if total > 0 else 0
            if step > self._steps.get(key, 0):
                self._steps[key] = step
                self._write(f"  {name}: {label + ' ' if label else ''}{done}/{total}\n")

    def _line(self, r: dict[str, Any]) -> str:
        name = r.get("node", "?") + (f"/{r['part']}" if r.get("part") is not None else "")
        status = r.get("status", "?")
        secs = r.get("seconds")
        tail = f" {secs:.2f}s" if isinstance(secs, (int, float)) and status == "computed" else ""
        err = f": {r['error']}" if r.get("error") and status in ("failed", "skipped") else ""
        return f"[{self.done}/{self.total}] {status:<8} {name}{tail}{err}"

    def close(self) -> None:
        """Stop the live display and print the summary line."""
        with self._lock:
            if not self.enabled:
                return
            if self._started:
                self._draw_bar(force=True)
                self._live.stop()
                self._started = False
            c = self.counts
            elapsed = time.perf_counter() - self.start
            summary = (f"{self.label + ': ' if self.label else ''}{self.done} tasks: "
                       f"{c['hit']} hit, {c['computed']} computed, {c['failed']} failed, "
                       f"{c['skipped']} skipped"
                       f"{f', {self.warnings} warning(s)' if self.warnings else ''} "
                       f"in {_fmt_seconds(elapsed)}")
            self._write(summary + "\n")


@functools.cache
def _bracket_bar_class() -> type:
    """rich's ``BarColumn`` between brackets (built on first use: a slow import)."""
    from rich.progress import BarColumn  # noqa: PLC0415
    from rich.table import Table  # noqa: PLC0415
    from rich.text import Text  # noqa: PLC0415

    class BracketBar(BarColumn):
        """rich's bar between brackets: ``[━━━━━━     ]``."""

        def render(self, task: Any) -> Any:
            grid = Table.grid(padding=0)
            grid.add_row(Text("["), super().render(task), Text("]"))
            return grid

    return BracketBar
