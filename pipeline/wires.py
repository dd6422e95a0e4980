"""Wires: where each input of a task comes from.

:func:`~mocapflow.pipeline.graph.build_graph` gives every task one wire per
input:

* :class:`FileWire`: a raw file, by path (a part's file, or a file override);
* :class:`FilesWire`: every part's file, in part order (a gather over parts);
* :class:`TaskWire`: one output of one upstream task;
* :class:`TasksWire`: one output of each of several upstream tasks, in part
  order (a gather).

Files enter a task's key by content digest and upstream tasks by output digest
(:mod:`~mocapflow.pipeline.task_keys`); the stage receives a path, a list of
paths, a value or a list of values.  Wires are small, frozen and picklable:
they travel to workers inside a :class:`~mocapflow.pipeline.execute.TaskSpec`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["FileWire", "FilesWire", "TaskWire", "TasksWire", "Wire"]


@dataclass(frozen=True)
class FileWire:
    """A raw input file.

    Attributes
    ----------
    path : str
        As given in the config (or made absolute for workers).
    """

    path: str

    def files(self) -> tuple[str, ...]:
        """The file paths this wire reads."""
        return (self.path,)

    def tasks(self) -> tuple[int, ...]:
        """Indices of the upstream tasks this wire reads."""
        return ()

    def with_paths(self, fn: Callable[[str], str]) -> FileWire:
        """The same wire with every path mapped through ``fn``."""
        return FileWire(fn(self.path))


@dataclass(frozen=True)
class FilesWire:
    """Every part's file, in part order (an input wired to ``part`` of a gather node).

    Attributes
    ----------
    paths : tuple of str
    """

    paths: tuple[str, ...]

    def files(self) -> tuple[str, ...]:
        """The file paths this wire reads."""
        return self.paths

    def tasks(self) -> tuple[int, ...]:
        """Indices of the upstream tasks this wire reads."""
        return ()

    def with_paths(self, fn: Callable[[str], str]) -> FilesWire:
        """The same wire with every path mapped through ``fn``."""
        return FilesWire(tuple(fn(p) for p in self.paths))


@dataclass(frozen=True)
class TaskWire:
    """One output of one upstream task.

    Attributes
    ----------
    index : int
        The upstream task's index in :attr:`Graph.tasks <mocapflow.pipeline.graph.Graph.tasks>`.
    output : str
        Its output name.
    """

    index: int
    output: str

    def files(self) -> tuple[str, ...]:
        """The file paths this wire reads."""
        return ()

    def tasks(self) -> tuple[int, ...]:
        """Indices of the upstream tasks this wire reads."""
        return (self.index,)

    def with_paths(self, fn: Callable[[str], str]) -> TaskWire:
        """This wire (it reads no file)."""
        return self


@dataclass(frozen=True)
class TasksWire:
    """One output of each of several upstream tasks, in part order (a gather).

    Attributes
    ----------
    sources : tuple of TaskWire
    """

    sources: tuple[TaskWire, ...]

    def files(self) -> tuple[str, ...]:
        """The file paths this wire reads."""
        return ()

    def tasks(self) -> tuple[int, ...]:
        """Indices of the upstream tasks this wire reads."""
        return tuple(s.index for s in self.sources)

    def with_paths(self, fn: Callable[[str], str]) -> TasksWire:
        """This wire (it reads no file)."""
        return self


#: Any wire.
Wire = FileWire | FilesWire | TaskWire | TasksWire
