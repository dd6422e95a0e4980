"""Run progress on stderr: a bar on a terminal, plain lines otherwise."""

from __future__ import annotations

import sys
import time
from typing import Any, TextIO

__all__ = ["Progress"]


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
                   f"{c['computed']} computed, {c['failed']} failed, {c['skipped']} skipped "
                   f"in {_fmt_seconds(elapsed)}")
        if self.tty and self._drawn:
            self._write("\r\x1b[2K")
        self._write(summary + "\n")
