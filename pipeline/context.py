"""The context a stage receives: seeded randomness, parallel map, warnings, step timings.

Stages take it as the keyword-only ``ctx`` parameter.  Everything random in a
stage must come from ``ctx.rng`` (seeded from the ``seed`` param and the part
id), so stochastic stages stay pure and cacheable.  Work that splits naturally
(per body part, per marker, per DBN node, per frame chunk) goes through
``ctx.map``, which the engine backs with the same executor the run uses.
Timings of a stage's own steps go through ``ctx.timer`` (the engine keeps them
in the entry manifest and the run record): an output must never carry a time.
"""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import logging
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["HINT_SEP", "Context", "part_seed", "split_hint"]

log = logging.getLogger("mocapflow")

#: Between a warning's message and its "what to do" hint in ``Context.warnings``,
#: the manifests and the run records (which keep warnings as plain strings).
HINT_SEP = " — what to do: "


def split_hint(warning: str) -> tuple[str, str | None]:
    """A stored warning's message and its hint (``None`` without one).

    Parameters
    ----------
    warning : str
        As :meth:`Context.warn` stored it.

    Returns
    -------
    tuple of (str, str or None)
    """
    msg, sep, hint = str(warning).partition(HINT_SEP)
    return (msg, hint) if sep else (msg, None)


def part_seed(seed: int, part: str | None) -> list[int]:
    """Entropy for ``numpy.random.default_rng`` from a seed and a part id.

    Parameters
    ----------
    seed : int
        The stage's ``seed`` param (0 when the stage has none).
    part : str or None
        Part id; ``None`` for gather tasks.

    Returns
    -------
    list of int
        Stable across interpreters and machines (blake2b, not ``hash``).
    """
    h = hashlib.blake2b((part or "").encode(), digest_size=8).digest()
    return [int(seed) & 0xFFFFFFFF, int.from_bytes(h, "little")]


def _takes_on_done(mapper: Callable[..., Any]) -> bool:
    """Whether ``mapper`` accepts an ``on_done`` keyword (see :class:`Context`)."""
    try:
        params = inspect.signature(mapper).parameters
    except (TypeError, ValueError):
        return False
    return "on_done" in params or any(
        p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


@dataclass
class Context:
    """Per-task context handed to a stage.

    Parameters
    ----------
    part : str or None
        Part id of the task (a file path, ``seed=3``, ``file#seed=3``); ``None``
        for a gather task.
    seed : int
        The ``seed`` param of the stage (0 if it has none).
    mapper : callable, optional
        ``mapper(fn, items) -> list`` (results in item order); the engine
        passes one that fans out on the run's executor.  A mapper that also
        takes an ``on_done`` keyword (``on_done(i)`` called as item ``i``
        finishes) lets :meth:`map` report progress as items complete.
        Defaults to a sequential map.
    progress_hook : callable, optional
        ``progress_hook(done, total, label)``, called by :meth:`progress`; the
        engine sets one that forwards (rate-limited) to the command's display.
    rng : numpy.random.Generator, optional
        The generator ``ctx.rng``; by default one seeded from ``seed`` and
        ``part`` (:func:`part_seed`).  The engine never passes one; it is for
        Python callers that need a stream of their own.

    Attributes
    ----------
    figures : dict
        ``name -> number or short text`` set by :meth:`figure`: the few key
        figures of the task's result that ``mocapflow run`` prints in its summary
        table (kept in the manifest and the run record, never in an output).
    timings : dict
        ``step -> seconds`` measured by :meth:`timer` (the engine stores them in
        the manifest's ``timings["steps"]`` and in the run record).
    """

    part: str | None = None
    seed: int = 0
    mapper: Callable[..., list[Any]] | None = None
    progress_hook: Callable[[int, int, str], None] | None = None
    warnings: list[str] = field(default_factory=list)
    workers: int = 1
    rng: np.random.Generator | None = None
    timings: dict[str, float] = field(default_factory=dict)
    figures: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.rng is None:
            self.rng = np.random.default_rng(part_seed(self.seed, self.part))

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any], *,
            progress: str | None = None) -> list[Any]:
        """Apply ``fn`` to every item, in parallel where the executor allows.

        ``fn`` must be a picklable (module-level) function or a
        ``functools.partial`` of one; results come back in item order.  With
        ``progress`` (a label), items done are reported through
        :meth:`progress`: after each item when the map is sequential, as items
        complete when the mapper takes ``on_done`` (the engine's does), else
        at the start and the end.
        """
        items = list(items)
        n = len(items)
        if self.mapper is None or n <= 1:
            out = []
            for i, x in enumerate(items):
                out.append(fn(x))
                if progress is not None:
                    self.progress(i + 1, n, progress)
            return out
        if progress is None:
            return list(self.mapper(fn, items))
        self.progress(0, n, progress)
        done = 0
        if _takes_on_done(self.mapper):
            def on_done(i: int) -> None:
                nonlocal done
                done += 1
                self.progress(done, n, progress)

            out = list(self.mapper(fn, items, on_done=on_done))
        else:
            out = list(self.mapper(fn, items))
        if done != n:
            self.progress(n, n, progress)
        return out

    def warn(self, message: str, hint: str | None = None) -> None:
        """Record a warning; the engine stores it in the entry manifest and prints it.

        Parameters
        ----------
        message : str
            What happened.
        hint : str, optional
            What to do about it (or why it may not matter), printed after the
            message; stored in the same string, after :data:`HINT_SEP`.
        """
        text = str(message) + (f"{HINT_SEP}{hint}" if hint else "")
        self.warnings.append(text)
        log.warning("%s%s", f"[{self.part}] " if self.part else "", text)

    @contextlib.contextmanager
    def timer(self, step: str) -> Iterator[None]:
        """Time a named step of the stage: ``with ctx.timer("fill"): ...``.

        The seconds add up over every use of one name (a step run per pass).
        They are kept in :attr:`timings`, which the engine stores with the
        entry's manifest and the run record, never in an output: an output that
        carries a time differs on every run, in every store.
        """
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.timings[step] = self.timings.get(step, 0.0) + time.perf_counter() - t0

    def figure(self, name: str, value: float | int | str) -> None:
        """Report a key figure of the result (``ctx.figure("holes filled", 412)``).

        Figures are derived from the outputs, so they are as reproducible as the
        outputs; they go to the manifest and the run summary, not into a key or a
        digest.  Numbers are kept as given, text cut to 40 characters.
        """
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            value = str(value)
        self.figures[str(name)] = value[:40] if isinstance(value, str) else value

    def progress(self, done: int, total: int, label: str = "") -> None:
        """Report progress of long work inside the stage (``done`` of ``total`` ``label``).

        Cheap enough to call per item of a loop: the engine forwards a few
        updates a second (and always the last) to the command's display.  It
        never enters an output, a key or a manifest; without a hook it does
        nothing.
        """
        if self.progress_hook is not None:
            self.progress_hook(int(done), int(total), str(label))

    def child_rng(self, *key: int) -> np.random.Generator:
        """An independent generator for sub-task ``key`` (for work inside ``map``)."""
        return np.random.default_rng([*part_seed(self.seed, self.part), *map(int, key)])
