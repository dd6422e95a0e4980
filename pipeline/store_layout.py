"""What every part of the store agrees on: reserved names, name rules, errors, JSON documents.

* :data:`MANIFEST` (``_COMMIT.json``, written last: an entry exists iff it does),
  :data:`WRITER` (``_WRITER.json``, who is writing a staging directory) and
  :data:`FORMAT` (the entry format number written into manifests and group attrs);
* :func:`check_name`: stage, key, output, array and run-id names that are safe as
  path segments and never collide with the reserved files;
* :func:`dump_json`: how the store writes its JSON documents (manifests, writer
  records, run records, the file memo): sorted keys, numpy values converted;
* :class:`StoreError`, :class:`EntryNotFoundError` and :class:`StoreAccessError`
  (the store cannot be written or read: full, read-only, no permission), made by
  :func:`access_error` as one line naming the store.
"""

from __future__ import annotations

import errno
import json
import re
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.pipeline.codecs import to_jsonable

__all__ = [
    "FORMAT",
    "MANIFEST",
    "WRITER",
    "EntryNotFoundError",
    "StoreAccessError",
    "StoreError",
    "access_error",
    "check_name",
    "dump_json",
    "now_iso",
]

MANIFEST = "_COMMIT.json"
WRITER = "_WRITER.json"
FORMAT = 1
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.+=\-]*$")


class StoreError(Exception):
    """A problem with the store or one of its entries."""


class EntryNotFoundError(StoreError, LookupError):
    """The requested entry (or output) is not committed."""


class StoreAccessError(StoreError, OSError):
    """The store cannot be written or read (full disk, read-only, no permission, ...).

    An ``OSError`` too (``errno`` kept), so code that tolerates I/O failures of a
    cache still does; ``str(err)`` is one line naming the store (see
    :func:`access_error`).
    """

    def __init__(self, message: str, code: int | None = None) -> None:
        if code is None:
            OSError.__init__(self, message)
        else:
            OSError.__init__(self, code, message)
        self.message = message

    def __str__(self) -> str:
        return self.message

    def __reduce__(self) -> tuple:
        return (type(self), (self.message, self.errno))


#: How an errno reads in a store error.
_REASONS = {
    errno.ENOSPC: "no space left on device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
}


def access_error(root: str, err: OSError, what: str) -> StoreAccessError:
    """``"store ROOT: REASON (WHAT)"``, e.g. ``store /data/s: no space left on device
    (writing entry clean/1f3a…)``.

    Parameters
    ----------
    root : str
        The store root, as the user gave it (absolute for local roots).
    err : OSError
        What the operating system or filesystem said.
    what : str
        What the store was doing.
    """
    if isinstance(err, StoreAccessError):
        return err
    reason = _REASONS.get(err.errno or -1) or err.strerror or str(err) or type(err).__name__
    if err.errno is not None and err.errno not in _REASONS:
        reason = f"{reason} ({errno.errorcode.get(err.errno, err.errno)})"
    return StoreAccessError(f"store {root}: {reason} ({what})".replace("\n", " "), err.errno)


def check_name(name: str, what: str) -> str:
    """Return ``name`` if it is usable as a path segment of the store, else raise.

    Raises
    ------
    ValueError
        Not letters, digits, ``_ . - + =`` (starting with neither ``.`` nor
        ``__``), or a reserved file name.  The message names ``what`` it is.
    """
    if not isinstance(name, str) or not _NAME.match(name) or name.startswith("__"):
        raise ValueError(
            f"invalid {what} name {name!r}: use letters, digits, '_', '.', '-', '+', '=' "
            "(not starting with '.' or '__')"
        )
    if name in ("zarr.json", MANIFEST, WRITER):
        raise ValueError(f"invalid {what} name {name!r}: reserved")
    return name


def _json_default(x: Any) -> Any:
    if isinstance(x, (np.generic, np.ndarray, Path, tuple)):
        return to_jsonable(x)
    if isinstance(x, (set, frozenset)):
        return sorted(to_jsonable(list(x)), key=str)
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def dump_json(obj: Any, *, compact: bool = False) -> bytes:
    """A store document as bytes: indented, sorted keys, numpy values / paths / sets converted.

    ``compact``: no indentation, for large documents (run records, the file memo):
    Python's C JSON encoder only writes unindented JSON, about five times faster
    and without the pure-Python encoder's peak memory (a 30,001-task run record:
    1.4 s and +175 MB indented, 0.3 s compact).
    """
    if compact:
        return json.dumps(obj, separators=(",", ":"), sort_keys=True,
                          default=_json_default).encode()
    return json.dumps(obj, indent=1, sort_keys=True, default=_json_default).encode()


def now_iso() -> str:
    """The current UTC time, ISO 8601 with microseconds (``committed_at``)."""
    return datetime.now(UTC).isoformat(timespec="microseconds")
