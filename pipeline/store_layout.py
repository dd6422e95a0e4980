"""What every part of the store agrees on: reserved names, name rules, errors, JSON documents.

* :data:`MANIFEST` (``_COMMIT.json``, written last: an entry exists iff it does),
  :data:`WRITER` (``_WRITER.json``, who is writing a staging directory) and
  :data:`FORMAT` (the entry format number written into manifests and group attrs);
* :func:`check_name`: stage, key, output, array and run-id names that are safe as
  path segments and never collide with the reserved files;
* :func:`dump_json`: how the store writes its JSON documents (manifests, writer
  records, run records, the file memo): sorted keys, numpy values converted;
* :class:`StoreError` and :class:`EntryNotFoundError`.
"""

from __future__ import annotations

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
    "StoreError",
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


def dump_json(obj: Any) -> bytes:
    """A store document as bytes: indented, sorted keys, numpy values / paths / sets converted."""
    return json.dumps(obj, indent=1, sort_keys=True, default=_json_default).encode()


def now_iso() -> str:
    """The current UTC time, ISO 8601 with microseconds (``committed_at``)."""
    return datetime.now(UTC).isoformat(timespec="microseconds")
