"""Keys of tasks: what goes into a task's cache key, computed the same on the driver and in workers.

A task's key (:func:`~mocapflow.pipeline.keys.task_key`) is made of the stage
identity, its code fingerprint (:func:`stage_fingerprint`, or the stage's
version pin), the validated params (``FilePath`` params by file content), the
part id, the *digests* of its inputs (:func:`key_inputs`: upstream output
digests, raw files by content, from :func:`hash_files`) and the versions of
result-changing packages.  Node names, paths, the store and the run id are not
in it.

The driver hashes raw files when it plans (:func:`hash_files`, memoised); the
worker that computes a task checks that the files it reads still have those
digests (:func:`read_inputs_check`, then :meth:`InputFiles.recheck` before the
commit), so an input overwritten after planning never gets an entry keyed by
its old content.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from mocapflow.pipeline import fingerprint, keys, registry
from mocapflow.pipeline.config import filepath_params, resolve_stage
from mocapflow.pipeline.graph import Graph
from mocapflow.pipeline.keys import content_digest
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.wires import FilesWire, FileWire, TaskWire, Wire

__all__ = [
    "InputChangedError",
    "InputFiles",
    "compute_key",
    "content_digest",
    "hash_files",
    "key_inputs",
    "key_params",
    "read_inputs_check",
    "stage_fingerprint",
]


def stage_fingerprint(spec: registry.StageSpec) -> str:
    """``"pin:<version>"`` for a pinned stage, else the fingerprint of the code it reaches.

    :func:`~mocapflow.pipeline.fingerprint.code_fingerprint` of the stage function:
    every definition its source statically reaches.  In-project modules are those
    of the top-level package of the stage's module
    (``mocapflow`` for the built-in families).  The engine's own modules are left
    out: a stage imports ``mocapflow.pipeline`` for its decorator and context, and
    an engine edit must not invalidate every entry.  Engine changes that alter what
    a stage computes (RNG seeding, output encoding) bump ``keys.KEY_FORMAT``.
    """
    if spec.version is not None:
        return f"pin:{spec.version}"
    return fingerprint.code_fingerprint(
        f"{spec.module}:{spec.func.__qualname__}",
        package=spec.module.split(".", 1)[0],
        exclude=("mocapflow.pipeline",),
    )


def key_inputs(inputs: Mapping[str, Wire], file_digests: Mapping[str, str | None],
               upstream: Callable[[int, str], str | None]) -> tuple[dict, dict, list[str]]:
    """(input digests, input kinds, names of inputs whose digest is not known yet).

    Parameters
    ----------
    inputs : dict
        ``input -> wire``.
    file_digests : dict
        ``path -> digest`` (``None``: unreadable).
    upstream : callable
        ``(task index, output) -> digest`` or ``None`` while it is not known.

    Raises
    ------
    FileNotFoundError
        An input file has no digest.
    """
    digests: dict[str, Any] = {}
    kinds: dict[str, str] = {}
    pending: list[str] = []

    def fdig(path: str) -> str:
        d = file_digests.get(path)
        if d is None:
            raise FileNotFoundError(f"input file not found: {path}")
        return d

    for name, w in inputs.items():
        if isinstance(w, FileWire):
            digests[name], kinds[name] = fdig(w.path), "file"
        elif isinstance(w, FilesWire):
            digests[name], kinds[name] = [fdig(p) for p in w.paths], "file"
        elif isinstance(w, TaskWire):
            d = upstream(w.index, w.output)
            kinds[name] = "upstream"
            if d is None:
                pending.append(name)
            digests[name] = d
        else:
            ds = [upstream(s.index, s.output) for s in w.sources]
            kinds[name] = "upstream"
            if any(d is None for d in ds):
                pending.append(name)
            digests[name] = ds
    return digests, kinds, pending


def key_params(params: Mapping[str, Any], file_params: Sequence[str],
               file_digests: Mapping[str, str | None]) -> dict[str, Any]:
    """Params for the key: ``FilePath`` params are replaced by their content digest."""
    out = dict(params)
    for p in file_params:
        v = out.get(p)
        if v is not None:
            d = file_digests.get(str(v))
            if d is None:
                raise FileNotFoundError(f"param {p}: file not found: {v}")
            out[p] = {"file": d}
    return out


def compute_key(spec: registry.StageSpec, *, params: Mapping[str, Any], part: str | None,
                inputs: Mapping[str, Any], kinds: Mapping[str, str],
                file_digests: Mapping[str, str | None]) -> tuple[str, dict]:
    """Key and components of a task (identical on the driver and in workers)."""
    return keys.task_key(
        stage=spec.name,
        fingerprint=stage_fingerprint(spec),
        params=key_params(params, filepath_params(spec), file_digests),
        part=part,
        inputs=inputs,
        versions=keys.package_versions(),
        input_kinds=kinds,
    )


def hash_files(graph: Graph, store: Store) -> dict[str, str | None]:
    """Content digests of every raw file the graph reads (memoised in the store).

    Returns
    -------
    dict
        ``path -> digest`` (``None`` for a file that cannot be read; the task
        reading it fails with that reason).
    """
    paths: list[str] = []
    for t in graph.tasks:
        paths.extend(t.files())
        for p in filepath_params(resolve_stage(t.stage)):
            if t.params.get(p) is not None:
                paths.append(str(t.params[p]))
    memo = store.load_file_memo()
    before = dict(memo)
    out: dict[str, str | None] = {}
    dirs: dict[str, str] = {}  # each folder resolved once in this pass
    for p in dict.fromkeys(paths):
        try:
            out[p] = keys.file_digest(p, memo, dirs=dirs)
        except OSError:
            out[p] = None
    if memo != before:
        try:
            store.save_file_memo({k: v for k, v in memo.items() if before.get(k) != v})
        except OSError:
            pass
    return out


# --------------------------------------------------------------------------- what workers read


class InputChangedError(RuntimeError):
    """An input file no longer has the content the task's key was computed from."""


def _signature(path: str) -> tuple[int, ...] | None:
    """``(inode, size, mtime_ns, ctime_ns)`` of a regular file; ``None`` for a directory.

    ``ctime`` changes on every write and cannot be set back by a user, so an
    unchanged signature means unchanged bytes.
    """
    st = os.stat(path)
    if stat.S_ISDIR(st.st_mode):
        return None
    return (st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


@dataclass(frozen=True)
class InputFiles:
    """The raw input files of one task as the worker found them (:func:`read_inputs_check`).

    Attributes
    ----------
    digests : dict
        ``path -> digest`` the key was computed from.
    signatures : dict
        ``path -> (inode, size, mtime_ns, ctime_ns)`` when checked (``None``: a directory).
    """

    digests: dict[str, str]
    signatures: dict[str, tuple[int, ...] | None]

    def recheck(self) -> None:
        """Before the commit: every file is still the one that was checked.

        Raises
        ------
        InputChangedError
            A file was written (or replaced) while the task ran.
        """
        for path, sig in self.signatures.items():
            try:
                same = (_signature(path) == sig if sig is not None
                        else content_digest(path) == self.digests[path])
            except OSError:
                same = False
            if not same:
                raise InputChangedError(
                    f"input file {path} changed while the task read it; nothing was "
                    "committed (run again once it is stable)")


def read_inputs_check(file_digests: Mapping[str, str | None]) -> InputFiles:
    """Check that each input file holds what the key says, by reading it in full now.

    Parameters
    ----------
    file_digests : dict
        ``path -> digest`` of the task's raw files, as planned (``None``: unreadable then).

    Returns
    -------
    InputFiles
        For :meth:`InputFiles.recheck` after the stage has read them.

    Raises
    ------
    InputChangedError
        A file's content differs from its planned digest (or it is gone).
    """
    digests: dict[str, str] = {}
    sigs: dict[str, tuple[int, ...] | None] = {}
    for path, planned in file_digests.items():
        if planned is None:
            continue
        try:
            before = _signature(path)
            now = content_digest(path)
            after = _signature(path)
        except OSError as e:
            raise InputChangedError(f"input file {path} cannot be read since planning "
                                    f"({e.strerror or e}); nothing was committed") from None
        if now != planned:
            raise InputChangedError(
                f"input file {path} changed since planning (content {planned[:12]} when "
                f"planned, {now[:12]} now); nothing was committed (run again to use the "
                "new content)")
        if before != after:
            raise InputChangedError(f"input file {path} changed while the task read it; "
                                    "nothing was committed (run again once it is stable)")
        digests[path], sigs[path] = planned, after
    return InputFiles(digests, sigs)
