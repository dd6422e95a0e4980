"""Where a store's bytes live: the :class:`Backend` protocol and its two implementations.

The store reaches its root only through a backend: read and write small
documents, list, remove, measure, and hand Zarr a store for one entry.

* :class:`LocalBackend`: a directory tree on this machine.  ``write_atomic`` is a
  write to a temporary name and ``os.replace``; the store itself publishes
  entries with ``os.rename`` (only local roots can).
* :class:`FsspecBackend`: any fsspec filesystem (``memory://``, ``s3://``, ...).
  No atomic rename: documents are written in place.
* :class:`KeySink`: where :mod:`~mocapflow.pipeline.store_zarr` puts the Zarr keys
  of an entry being written (relative keys under one base path of a backend).

fsspec is imported when a :class:`FsspecBackend` is made, not with this module:
a local store never needs it, and it costs about 60 ms at import.
"""

from __future__ import annotations

import os
import posixpath
import shutil
import uuid
from collections.abc import Mapping
from datetime import UTC, datetime
from typing import Any, Protocol

from mocapflow.pipeline import store_zarr

__all__ = ["Backend", "FsspecBackend", "KeySink", "LocalBackend"]


class Backend(Protocol):
    """Storage operations the store needs on its root.

    Paths are backend paths (``root`` joined with parts by :meth:`join`); a
    missing file or directory is never an error for reading, listing or removal.
    """

    is_local: bool
    root: str

    def join(self, *parts: str) -> str:
        """Join path parts with the backend's separator."""

    def read(self, path: str) -> bytes | None:
        """The file's bytes, or ``None`` if there is no such file."""

    def write(self, path: str, data: bytes) -> None:
        """Write a file, creating its parent directories."""

    def write_atomic(self, path: str, data: bytes) -> None:
        """Write a file so that readers see the old or the new content, never a part."""

    def put_many(self, base: str, items: Mapping[str, bytes]) -> None:
        """Write ``relative key -> bytes`` (``/``-separated keys) under ``base``."""

    def remove(self, path: str) -> None:
        """Remove one file."""

    def exists(self, path: str) -> bool:
        """Whether a file or directory exists."""

    def listdir(self, path: str) -> list[str]:
        """Sorted names in a directory (empty when it does not exist)."""

    def isdir(self, path: str) -> bool:
        """Whether ``path`` is a directory."""

    def mtime(self, path: str) -> float | None:
        """Modification time (epoch seconds), or ``None`` when unknown."""

    def rmtree(self, path: str) -> None:
        """Remove a directory and everything under it."""

    def find(self, path: str) -> list[str]:
        """Every file under ``path``, as sorted ``/``-separated relative paths."""

    def du(self, path: str) -> int:
        """Bytes used under ``path``."""

    def url(self, path: str) -> str:
        """The path as users see it (a local path, or a URL with its protocol)."""

    def zarr_store(self, path: str) -> Any:
        """A read-only Zarr store rooted at ``path``."""


class LocalBackend:
    """Storage operations on a local directory tree."""

    is_local = True

    def __init__(self, root: str) -> None:
        self.root = root

    join = staticmethod(os.path.join)

    def read(self, path: str) -> bytes | None:
        try:
            with open(path, "rb") as f:
                return f.read()
        except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
            return None

    def write(self, path: str, data: bytes) -> None:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "wb") as f:
            f.write(data)

    def write_atomic(self, path: str, data: bytes) -> None:
        d, base = os.path.split(path)
        os.makedirs(d, exist_ok=True)
        tmp = os.path.join(d, f".{base}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}")
        try:
            with open(tmp, "wb") as f:
                f.write(data)
            os.replace(tmp, path)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise

    def put_many(self, base: str, items: Mapping[str, bytes]) -> None:
        made: set[str] = set()
        for rel, data in items.items():
            path = os.path.join(base, *rel.split("/"))
            d = os.path.dirname(path)
            if d not in made:
                os.makedirs(d, exist_ok=True)
                made.add(d)
            with open(path, "wb") as f:
                f.write(data)

    def remove(self, path: str) -> None:
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass

    def exists(self, path: str) -> bool:
        return os.path.exists(path)

    def listdir(self, path: str) -> list[str]:
        try:
            return sorted(os.listdir(path))
        except (FileNotFoundError, NotADirectoryError):
            return []

    def isdir(self, path: str) -> bool:
        return os.path.isdir(path)

    def mtime(self, path: str) -> float | None:
        try:
            return os.stat(path).st_mtime
        except OSError:
            return None

    def rmtree(self, path: str) -> None:
        shutil.rmtree(path, ignore_errors=True)

    def find(self, path: str) -> list[str]:
        out = []
        for dirpath, _, files in os.walk(path):
            rel = os.path.relpath(dirpath, path)
            for f in files:
                out.append(f if rel == "." else f"{rel}/{f}".replace(os.sep, "/"))
        return sorted(out)

    def du(self, path: str) -> int:
        total = 0
        for dirpath, _, files in os.walk(path):
            for f in files:
                try:
                    total += os.lstat(os.path.join(dirpath, f)).st_size
                except OSError:
                    pass
        return total

    def url(self, path: str) -> str:
        return path

    def zarr_store(self, path: str) -> Any:
        return store_zarr.local_store(path)


class FsspecBackend:
    """Storage operations on an fsspec filesystem (no atomic rename)."""

    is_local = False

    def __init__(self, url: str, storage_options: dict | None) -> None:
        # only URL roots need fsspec (~60 ms to import)
        from fsspec.core import url_to_fs  # noqa: PLC0415

        self.fs, path = url_to_fs(url, **(storage_options or {}))
        self.root = path.rstrip("/") or "/"
        self.storage_options = storage_options

    join = staticmethod(posixpath.join)

    def read(self, path: str) -> bytes | None:
        try:
            return self.fs.cat_file(path)
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            return None

    def write(self, path: str, data: bytes) -> None:
        try:
            self.fs.makedirs(posixpath.dirname(path), exist_ok=True)
        except Exception:  # object stores have no directories
            pass
        self.fs.pipe_file(path, data)

    write_atomic = write

    def put_many(self, base: str, items: Mapping[str, bytes]) -> None:
        self.fs.pipe({posixpath.join(base, k): v for k, v in items.items()})

    def remove(self, path: str) -> None:
        try:
            self.fs.rm_file(path)
        except FileNotFoundError:
            pass

    def exists(self, path: str) -> bool:
        return self.fs.exists(path)

    def listdir(self, path: str) -> list[str]:
        try:
            names = self.fs.ls(path, detail=False)
        except (FileNotFoundError, NotADirectoryError):
            return []
        return sorted({n.rstrip("/").rsplit("/", 1)[-1] for n in names} - {""})

    def isdir(self, path: str) -> bool:
        return self.fs.isdir(path)

    def mtime(self, path: str) -> float | None:
        try:
            info = self.fs.info(path)
        except (FileNotFoundError, OSError):
            return None
        for k in ("mtime", "LastModified", "last_modified", "created"):
            v = info.get(k)
            if isinstance(v, (int, float)):
                return float(v)
            if isinstance(v, datetime):
                return (v if v.tzinfo else v.replace(tzinfo=UTC)).timestamp()
        return None

    def rmtree(self, path: str) -> None:
        try:
            self.fs.rm(path, recursive=True)
        except FileNotFoundError:
            pass

    def find(self, path: str) -> list[str]:
        try:
            files = self.fs.find(path)
        except FileNotFoundError:
            return []
        base = path.rstrip("/") + "/"
        return sorted(f[len(base) :] if f.startswith(base) else f for f in files)

    def du(self, path: str) -> int:
        try:
            return int(self.fs.du(path, total=True))
        except Exception:
            return 0

    def url(self, path: str) -> str:
        return self.fs.unstrip_protocol(path)

    def zarr_store(self, path: str) -> Any:
        return store_zarr.fsspec_store(self.url(path), self.storage_options)


class KeySink:
    """Zarr keys of one entry being written, put under ``base`` of a backend.

    Parameters
    ----------
    backend : Backend
    base : str
        Backend path of the entry (its staging directory, or the entry itself
        when the store writes in place).
    """

    def __init__(self, backend: Backend, base: str) -> None:
        self.backend = backend
        self.base = base

    def put_many(self, items: Mapping[str, bytes]) -> None:
        """Write ``relative key -> bytes``."""
        self.backend.put_many(self.base, items)
