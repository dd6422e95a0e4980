"""Where a store's bytes live: the :class:`Backend` protocol and its two implementations.

The store reaches its root only through a backend: read and write small
documents, list, remove, measure, and hand Zarr a store for one entry.

* :class:`LocalBackend`: a directory tree on this machine.  ``write_atomic`` is a
  write to a temporary name and ``os.replace``; the store itself publishes
  entries with ``os.rename`` (only local roots can).  It never follows a
  symlink below the root: documents are opened with ``O_NOFOLLOW`` (and only
  when they are regular files, so a FIFO cannot block a reader),
  :meth:`~LocalBackend.real_dir` checks every directory between the root and
  an entry, and :meth:`~LocalBackend.odd_files` lists symlinks and special
  files inside one (``verify`` reports them; nothing reads through them).
* :class:`FsspecBackend`: any fsspec filesystem (``memory://``, ``s3://``, ...).
  No atomic rename: documents are written in place.
* :class:`KeySink`: where :mod:`~mocapflow.pipeline.store_zarr` puts the Zarr keys
  of an entry being written (relative keys under one base path of a backend).
* :func:`parse_storage_options`: the fsspec options of a URL root from
  ``--storage-option KEY=VALUE`` items and ``$MOCAPFLOW_STORAGE_OPTIONS`` (JSON).
  They reach the filesystem only: the store pickles them to its workers, and no
  cache key, digest, manifest or run record contains them.

fsspec is imported when a :class:`FsspecBackend` is made, not with this module:
a local store never needs it, and it costs about 60 ms at import.
"""

from __future__ import annotations

import errno
import json
import os
import posixpath
import shutil
import stat
import uuid
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from typing import Any, Protocol

from mocapflow.pipeline import store_zarr
from mocapflow.pipeline.config_yaml import parse_yaml_value

__all__ = [
    "STORAGE_OPTIONS_ENV",
    "Backend",
    "FsspecBackend",
    "KeySink",
    "LocalBackend",
    "parse_storage_options",
]

#: Environment variable holding fsspec storage options as a JSON object.
STORAGE_OPTIONS_ENV = "MOCAPFLOW_STORAGE_OPTIONS"

#: fsspec protocols whose first path segment is a bucket (container) that must exist.
_BUCKET_PROTOCOLS = frozenset({"s3", "s3a", "gs", "gcs", "az", "abfs", "abfss"})


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

    def subdirs(self, path: str) -> list[str]:
        """Sorted names of the real (not symlinked) subdirectories of a directory."""

    def is_file(self, path: str) -> bool:
        """Whether ``path`` is a regular file (a symlink is not)."""

    def real_dir(self, path: str) -> bool:
        """Whether ``path`` and every directory between the root and it are real directories."""

    def odd_files(self, path: str) -> list[tuple[str, str]]:
        """``(relative path, what it is)`` of each symlink or special file under ``path``."""

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

    def probe(self) -> None:
        """Reach the root once (raise ``OSError`` of one line if it cannot be used)."""


#: Most bytes one ``read(2)`` returns on Linux.
_MAX_READ = 0x7FFFF000


class LocalBackend:
    """Storage operations on a local directory tree."""

    is_local = True

    def __init__(self, root: str) -> None:
        self.root = root

    join = staticmethod(os.path.join)

    def read(self, path: str) -> bytes | None:
        """The file's bytes; ``None`` if missing, a symlink or not a regular file."""
        try:
            fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
        except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
            return None
        except OSError as e:
            if e.errno == errno.ELOOP:  # a symlink: never followed
                return None
            raise
        try:  # (plain os calls: this is every task's cache check)
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):
                return None
            data = os.read(fd, st.st_size + 1)  # a regular file reads short only at EOF
            if len(data) > st.st_size or len(data) >= _MAX_READ:  # it grew, or is over 2 GB
                data += b"".join(iter(lambda: os.read(fd, 1 << 24), b""))
            return data
        finally:
            os.close(fd)

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

    def subdirs(self, path: str) -> list[str]:
        try:
            with os.scandir(path) as it:
                return sorted(e.name for e in it if e.is_dir(follow_symlinks=False))
        except (FileNotFoundError, NotADirectoryError):
            return []

    def is_file(self, path: str) -> bool:
        try:
            return stat.S_ISREG(os.lstat(path).st_mode)
        except (FileNotFoundError, NotADirectoryError):
            return False

    def real_dir(self, path: str) -> bool:
        cur = self.root.rstrip(os.sep) or os.sep
        if path.rstrip(os.sep) == cur:
            return True
        if not path.startswith(cur.rstrip(os.sep) + os.sep):
            return False  # not below the root (store paths are joined, never relative)
        for part in path[len(cur.rstrip(os.sep)) + 1:].split(os.sep):
            if part in ("", os.curdir, os.pardir):
                return False
            cur = os.path.join(cur, part)
            try:  # one lstat per level: a symlink is not a directory here
                if not stat.S_ISDIR(os.lstat(cur).st_mode):
                    return False
            except (FileNotFoundError, NotADirectoryError):
                return False
        return True

    def odd_files(self, path: str) -> list[tuple[str, str]]:
        out: list[tuple[str, str]] = []
        todo = [(path, "")]
        while todo:
            d, rel = todo.pop()
            try:
                it = os.scandir(d)
            except (FileNotFoundError, NotADirectoryError):
                continue
            with it:
                for e in it:
                    name = rel + e.name
                    if e.is_symlink():
                        out.append((name, f"a symlink to {_readlink(e.path)}"))
                    elif e.is_dir(follow_symlinks=False):
                        todo.append((e.path, name + "/"))
                    elif not e.is_file(follow_symlinks=False):
                        out.append((name, "not a regular file"))
        return sorted(out)

    def isdir(self, path: str) -> bool:
        return os.path.isdir(path)

    def mtime(self, path: str) -> float | None:
        try:
            return os.stat(path).st_mtime
        except OSError:
            return None

    def rmtree(self, path: str) -> None:
        """Remove a tree (a symlink: the link only); raises what is not "already gone"."""
        if os.path.islink(path):
            self.remove(path)
            return

        def gone_is_fine(func: Any, p: str, exc_info: Any) -> None:
            if not isinstance(exc_info[1], FileNotFoundError):
                raise exc_info[1]

        shutil.rmtree(path, onerror=gone_is_fine)

    def find(self, path: str) -> list[str]:
        out = []
        for dirpath, _, files in os.walk(path):
            rel = os.path.relpath(dirpath, path)
            for f in files:
                out.append(f if rel == "." else f"{rel}/{f}".replace(os.sep, "/"))
        return sorted(out)

    def du(self, path: str) -> int:
        if os.path.islink(path):
            return 0
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

    def probe(self) -> None:
        """Nothing to reach: a local root is created on first write."""


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

    subdirs = listdir  # object stores have no symlinks

    def is_file(self, path: str) -> bool:
        return self.fs.exists(path)

    def real_dir(self, path: str) -> bool:
        return True

    def odd_files(self, path: str) -> list[tuple[str, str]]:
        return []

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

    def probe(self) -> None:
        """List the root once, so that a bad endpoint, option or bucket fails before any work.

        A root that does not exist yet is fine (a new store), but on an object
        store (``s3://``, ``gs://``, ``az://``) its bucket must exist.

        Raises
        ------
        OSError
            One line: what the filesystem said (its own exception type named
            when it is not an ``OSError``, e.g. a connection error), which
            bucket is missing, or that the URL names none (``s3://``: the
            store would be the whole account).
        """
        protocols = self.fs.protocol
        protocols = {protocols} if isinstance(protocols, str) else set(protocols)
        bucket = self.root.strip("/").split("/", 1)[0]
        on_buckets = bool(protocols & _BUCKET_PROTOCOLS)
        if on_buckets and not bucket:
            raise OSError("the URL names no bucket (expected PROTOCOL://BUCKET/PREFIX)")
        try:
            self.fs.ls(self.root, detail=False)
            return
        except FileNotFoundError:
            pass
        except Exception as e:
            raise _one_line_oserror(e) from e
        if not on_buckets:
            return
        try:
            self.fs.info(bucket)
        except FileNotFoundError:
            raise OSError(f"bucket {bucket} does not exist (or is not visible with these "
                          "credentials and storage options)") from None
        except Exception as e:
            raise _one_line_oserror(e) from e


def _one_line_oserror(exc: BaseException) -> OSError:
    """An ``OSError`` saying what ``exc`` said, on one line (its type named if not an OSError)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, OSError):
        return exc if exc.strerror else OSError(text)
    return OSError(f"{type(exc).__name__}: {text}")


def parse_storage_options(items: Sequence[str] = (), env: str | None = None) -> dict[str, Any]:
    """fsspec storage options from ``KEY=VALUE`` items on top of a JSON object.

    Parameters
    ----------
    items : sequence of str
        ``KEY=VALUE`` (``--storage-option``): VALUE is read as YAML (``anon=true``
        is a bool, ``client_kwargs={region_name: eu-west-1}`` a mapping; quote it
        to keep a string: ``key='0123'``); a dotted KEY sets a nested option
        (``client_kwargs.endpoint_url=http://127.0.0.1:9000``).  Later items win.
    env : str, optional
        A JSON object (``$MOCAPFLOW_STORAGE_OPTIONS``), the base the items update.

    Returns
    -------
    dict
        The options (nested mappings merged key by key).

    Raises
    ------
    ValueError
        An item without ``=`` or with an empty key, a JSON that is not an object,
        or a dotted key below an option that is not a mapping.  Messages name
        the key, never a value (values may be secrets).
    """
    opts: dict[str, Any] = {}
    if env is not None and env.strip():
        try:
            doc = json.loads(env)
        except ValueError as e:
            raise ValueError(f"${STORAGE_OPTIONS_ENV} is not valid JSON ({e.msg} at "
                             f"line {e.lineno} column {e.colno})") from None
        if not isinstance(doc, dict):
            raise ValueError(f"${STORAGE_OPTIONS_ENV} must be a JSON object "
                             '(e.g. {"anon": true})')
        _merge(opts, doc)
    for item in items:
        key, sep, text = item.partition("=")
        names = [n.strip() for n in key.split(".")]
        if not sep or not all(names):
            raise ValueError(f"--storage-option {key.strip()!r}{'=…' if sep else ''}: expected "
                             "KEY=VALUE (a dotted KEY sets a nested option)")
        value = parse_yaml_value(text, key=f"--storage-option {key.strip()}")
        where = opts
        for i, name in enumerate(names[:-1]):
            where = where.setdefault(name, {})
            if not isinstance(where, dict):
                raise ValueError(f"--storage-option {key.strip()}: "
                                 f"{'.'.join(names[:i + 1])} is not a mapping")
        _merge(where, {names[-1]: value})
    return opts


def _merge(into: dict[str, Any], new: Mapping[str, Any]) -> None:
    """Update ``into`` with ``new``, merging nested mappings key by key."""
    for k, v in new.items():
        if isinstance(v, Mapping):
            if not isinstance(into.get(k), dict):
                into[k] = {}
            _merge(into[k], v)
        else:
            into[k] = v


def _readlink(path: str) -> str:
    try:
        return os.readlink(path)
    except OSError:
        return "?"


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
