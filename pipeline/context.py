"""The context a stage receives: seeded randomness, parallel map, warnings, progress.

Stages take it as the keyword-only ``ctx`` parameter.  Everything random in a
stage must come from ``ctx.rng`` (seeded from the ``seed`` param and the part
id), so stochastic stages stay pure and cacheable.  Work that splits naturally
(per body part, per marker, per DBN node, per frame chunk) goes through
``ctx.map``, which the engine backs with the same executor the run uses.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Context", "part_seed"]

log = logging.getLogger("mocapflow")


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
        ``mapper(fn, items) -> list``; the engine passes one that fans out on
        the run's executor.  Defaults to a sequential map.
    progress : callable, optional
        ``progress(done, total, label)`` hook for long work.
    rng : numpy.random.Generator, optional
        The generator ``ctx.rng``; by default one seeded from ``seed`` and
        ``part`` (:func:`part_seed`).  The engine never passes one; it is for
        Python callers that need a stream of their own.
    """

    part: str | None = None
    seed: int = 0
    mapper: Callable[[Callable[[Any], Any], list[Any]], list[Any]] | None = None
    progress_hook: Callable[[int, int, str], None] | None = None
    warnings: list[str] = field(default_factory=list)
    workers: int = 1
    rng: np.random.Generator | None = None

    def __post_init__(self) -> None:
        if self.rng is None:
            self.rng = np.random.default_rng(part_seed(self.seed, self.part))

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> list[Any]:
        """Apply ``fn`` to every item, in parallel where the executor allows.

        ``fn`` must be a picklable (module-level) function or a
        ``functools.partial`` of one; results come back in item order.
        """
        items = list(items)
        if self.mapper is None or len(items) <= 1:
            return [fn(x) for x in items]
        return list(self.mapper(fn, items))

    def warn(self, message: str) -> None:
        """Record a warning; the engine stores it in the entry manifest and prints it."""
        self.warnings.append(str(message))
        log.warning("%s%s", f"[{self.part}] " if self.part else "", message)

    def progress(self, done: int, total: int, label: str = "") -> None:
        """Report progress of long work inside the stage."""
        if self.progress_hook is not None:
            self.progress_hook(done, total, label)

    def child_rng(self, *key: int) -> np.random.Generator:
        """An independent generator for sub-task ``key`` (for work inside ``map``)."""
        return np.random.default_rng([*part_seed(self.seed, self.part), *map(int, key)])
