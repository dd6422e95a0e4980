"""Content-addressed, crash-safe store of stage outputs as Zarr v3 groups.

Layout under the root (a local directory or an fsspec URL)::

    entries/<stage>/<key>/            Zarr v3 group, one per committed task
        zarr.json
        <output>/                     Zarr v3 group per output: attrs hold the
            zarr.json                 Encoded ``type``, ``attrs``, array names
            <array>/zarr.json, c/...  arrays with ``dimension_names``, chunked
                                      along ``frame``, every other axis whole
        _COMMIT.json                  the manifest, written last
    staging/<stage>-<key>-<random>/   entries being written (local roots)
    runs/<run_id>.json                run records
    cache/file_digests.json           persistent file-digest memo

**An entry exists iff its manifest exists.**  On a local root an entry is
written under ``staging/`` (with a ``_WRITER.json`` naming pid, host and start
time), its manifest last, then renamed into place with one ``os.rename``; a
writer that loses a race to the same key deletes its staging copy and succeeds.
On an fsspec URL (no atomic rename) arrays are written in place and the
manifest last.  Zarr reads missing chunks back as the fill value without error,
so :meth:`Store.verify` re-reads entries and compares digests; :meth:`Store.gc`
removes what killed writers left behind.
"""

from __future__ import annotations

import errno
import json
import logging
import math
import os
import posixpath
import re
import shutil
import socket
import threading
import time
import uuid
import warnings
from collections.abc import Iterable, Mapping
from datetime import UTC, datetime
from itertools import product
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.pipeline.codecs import Encoded, digest_encoded, to_jsonable

__all__ = ["EntryNotFoundError", "Store", "StoreError", "output_digests"]

log = logging.getLogger("mocapflow")

MANIFEST = "_COMMIT.json"
WRITER = "_WRITER.json"
FORMAT = 1
#: Largest chunk written (bytes); rows per chunk shrink below ``chunk_frames`` to fit.
MAX_CHUNK_BYTES = 64 << 20
#: Bytes handed to Zarr per write call, and buffered before they go to storage.
SLAB_BYTES = 16 << 20
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.+=\-]*$")
_STORABLE_KINDS = set("biufcUSMm")


class StoreError(Exception):
    """A problem with the store or one of its entries."""


class EntryNotFoundError(StoreError, LookupError):
    """The requested entry (or output) is not committed."""


# --------------------------------------------------------------------------- helpers


def _check_name(name: str, what: str) -> str:
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


def _dump_json(obj: Any) -> bytes:
    return json.dumps(obj, indent=1, sort_keys=True, default=_json_default).encode()


def _now_iso() -> str:
    return datetime.now(UTC).isoformat(timespec="microseconds")


def _proc_start(pid: int) -> int | None:
    """Start time of a process (clock ticks since boot, Linux) to detect pid reuse."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            rest = f.read().rsplit(b")", 1)[1].split()
        return int(rest[19])
    except (OSError, IndexError, ValueError):
        return None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    return True


def _writer_info() -> dict[str, Any]:
    pid = os.getpid()
    return {
        "pid": pid,
        "host": socket.gethostname(),
        "started": time.time(),
        "proc_start": _proc_start(pid),
    }


def _writer_alive(info: Mapping[str, Any]) -> bool | None:
    """True/False for a writer on this host; None when it cannot be checked here."""
    if info.get("host") != socket.gethostname():
        return None
    try:
        pid = int(info["pid"])
    except (KeyError, TypeError, ValueError):
        return None
    if not _pid_alive(pid):
        return False
    recorded = info.get("proc_start")
    if recorded is not None:
        now = _proc_start(pid)
        if now is not None and now != recorded:
            return False  # pid reused by another process
    return True


def _run_time(record: Mapping[str, Any], fallback: float) -> float:
    for k in ("started_at", "started", "time", "finished_at"):
        v = record.get(k)
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return float(v)
        if isinstance(v, str):
            try:
                t = datetime.fromisoformat(v)
            except ValueError:
                continue
            if t.tzinfo is None:
                t = t.replace(tzinfo=UTC)
            return t.timestamp()
    return fallback


def _normalise_array(arr: Any, where: str) -> np.ndarray:
    """Storable form of an array: native byte order, str objects as fixed-width unicode."""
    a = np.asarray(arr)
    if a.dtype.hasobject or a.dtype.kind == "T":
        flat = a.ravel().tolist()
        if not all(isinstance(v, str) for v in flat):
            raise TypeError(
                f"{where}: cannot store an object array (only arrays of str, which are "
                "stored as fixed-width unicode); use a numeric dtype or JSON attrs"
            )
        a = np.array(flat, dtype=str if flat else "<U1").reshape(a.shape)
    if a.dtype.kind not in _STORABLE_KINDS:
        raise TypeError(f"{where}: cannot store dtype {a.dtype} (structured/void arrays)")
    if a.dtype.byteorder == ">":
        a = a.astype(a.dtype.newbyteorder("<"))
    return a


def _plain_json(x: Any) -> Any:
    """Attrs as they will read back from JSON (str keys, lists, Python scalars).

    Unlike :func:`~mocapflow.pipeline.codecs.to_jsonable`, non-finite floats stay
    floats (Zarr writes them as ``NaN`` / ``Infinity`` and reads them back).
    """
    if isinstance(x, Mapping):
        return {str(k): _plain_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain_json(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain_json(x.tolist())
    if isinstance(x, np.generic):
        return _plain_json(x.item())
    if isinstance(x, Path):
        return str(x)
    if x is None or isinstance(x, (bool, int, float, str)):
        return x
    raise TypeError(f"attrs value of type {type(x).__name__} is not JSON: {x!r:.60}")


def _normalise(enc: Encoded, output: str) -> Encoded:
    if not isinstance(enc, Encoded):
        raise TypeError(f"output {output!r}: expected an Encoded, got {type(enc).__name__}")
    arrays = {}
    for name, item in enc.arrays.items():
        _check_name(name, f"array (output {output!r})")
        arr, dims = item
        a = _normalise_array(arr, f"output {output!r} array {name!r}")
        dims = tuple(dims)
        if len(dims) != a.ndim or not all(isinstance(d, str) and d for d in dims):
            raise ValueError(
                f"output {output!r} array {name!r}: dims {dims} do not name its {a.ndim} axes"
            )
        arrays[name] = (a, dims)
    try:
        attrs = _plain_json(dict(enc.attrs))
    except TypeError as e:
        raise TypeError(f"output {output!r}: {e}") from None
    return Encoded(str(enc.type), arrays, attrs)


def output_digests(outputs: Mapping[str, Encoded]) -> dict[str, str]:
    """Digests of outputs exactly as :meth:`Store.commit` computes and stores them.

    Arrays are normalised first (native byte order, ``str`` object arrays as
    fixed-width unicode) and attrs as they read back from JSON, so use this,
    not ``digest_encoded`` on the raw :class:`Encoded`, to compare with a manifest.
    """
    return {n: digest_encoded(_normalise(e, n)) for n, e in outputs.items()}


def _chunk_layout(
    shape: tuple[int, ...], dims: tuple[str, ...], itemsize: int, chunk_frames: int
) -> tuple[tuple[int, ...], int | None]:
    """(chunk shape, chunked axis or None): ``frame`` in ``chunk_frames`` rows, rest whole."""
    if not shape:
        return (), None
    whole = [max(1, s) for s in shape]
    axis = dims.index("frame") if "frame" in dims else None
    if axis is None and itemsize * math.prod(whole) <= MAX_CHUNK_BYTES:
        return tuple(whole), None
    if axis is None:
        axis, limit = 0, shape[0]
    else:
        limit = chunk_frames
    row = itemsize * math.prod(w for i, w in enumerate(whole) if i != axis)
    rows = max(1, min(limit, MAX_CHUNK_BYTES // max(row, 1), max(shape[axis], 1)))
    whole[axis] = rows
    return tuple(whole), axis


def _flush(sink: Any, buffer: dict, *, final: bool = False) -> None:
    """Hand buffered Zarr keys to storage (module-level so tests can slow it down).

    Chunks leave the buffer as they come; ``zarr.json`` documents stay in it
    (Zarr re-creates missing parents' metadata otherwise) until the final flush.
    """
    keys = [k for k in buffer if final or not k.endswith("zarr.json")]
    if keys:
        sink.put_many({k: buffer[k].to_bytes() for k in keys})
        for k in keys:
            del buffer[k]


async def _awrite_entry(
    sink: Any, outputs: Mapping[str, Encoded], root_attrs: dict, chunk_frames: int
) -> None:
    import zarr.api.asynchronous as za
    from zarr.codecs import ZstdCodec
    from zarr.errors import UnstableSpecificationWarning
    from zarr.storage import MemoryStore

    buffer: dict = {}
    root = await za.open_group(
        store=MemoryStore(buffer), mode="w", zarr_format=3, attributes=root_attrs
    )
    for out_name, enc in outputs.items():
        meta = {"type": enc.type, "attrs": enc.attrs, "arrays": sorted(enc.arrays)}
        group = await root.create_group(out_name, attributes={"mocapflow": meta})
        for arr_name in sorted(enc.arrays):
            arr, dims = enc.arrays[arr_name]
            chunks, axis = _chunk_layout(arr.shape, dims, arr.dtype.itemsize, chunk_frames)
            with warnings.catch_warnings():
                # fixed-width str dtypes: "no Zarr V3 specification yet" (they round-trip)
                warnings.filterwarnings("ignore", category=UnstableSpecificationWarning)
                za_arr = await group.create_array(
                    arr_name,
                    shape=arr.shape,
                    dtype=arr.dtype,
                    chunks=chunks,
                    dimension_names=dims if dims else None,
                    compressors=ZstdCodec(level=0, checksum=True),
                    config={"write_empty_chunks": True},
                )
            if arr.size == 0:
                pass
            elif axis is None:
                await za_arr.setitem(..., arr)
            else:
                per_chunk = chunks[axis] * arr.dtype.itemsize
                per_chunk *= math.prod(s for i, s in enumerate(arr.shape) if i != axis)
                step = chunks[axis] * max(1, SLAB_BYTES // max(per_chunk, 1))
                for start in range(0, arr.shape[axis], step):
                    sel = [slice(None)] * arr.ndim
                    sel[axis] = slice(start, start + step)
                    await za_arr.setitem(tuple(sel), arr[tuple(sel)])
                    if start + step < arr.shape[axis]:
                        _flush(sink, buffer)
            _flush(sink, buffer)
    _flush(sink, buffer, final=True)


async def _aopen_output(zstore: Any, output: str) -> tuple[dict, dict[str, Any]]:
    """(mocapflow attrs, ``array name -> AsyncArray``) of one output group."""
    import asyncio

    import zarr.api.asynchronous as za

    group = await za.open_group(store=zstore, path=output, mode="r")
    meta = dict(group.attrs).get("mocapflow")
    if not isinstance(meta, dict) or "type" not in meta:
        raise StoreError(f"output {output!r}: group attrs lack the mocapflow type")
    names = list(meta.get("arrays", []))
    arrays = await asyncio.gather(
        *(za.open_array(store=zstore, path=f"{output}/{n}", mode="r") for n in names)
    )
    return meta, dict(zip(names, arrays))


def _chunk_keys(output: str, name: str, a: Any) -> dict[str, tuple[slice, ...]]:
    """``relative key -> selection`` of every chunk of array ``a``."""
    out = {}
    grid = [range(math.ceil(s / c)) for s, c in zip(a.shape, a.chunks)]
    for coords in product(*grid):
        sel = tuple(slice(i * c, (i + 1) * c) for i, c in zip(coords, a.chunks))
        out[f"{output}/{name}/" + a.metadata.encode_chunk_key(tuple(coords))] = sel
    return out


def _expected_keys(output: str, arrays: Mapping[str, Any]) -> set[str]:
    keys = {f"{output}/zarr.json"}
    for name, a in arrays.items():
        keys.add(f"{output}/{name}/zarr.json")
        keys |= set(_chunk_keys(output, name, a))
    return keys


async def _aread_output(zstore: Any, output: str) -> Encoded:
    """Read one output group back into an :class:`Encoded`."""
    import asyncio

    meta, arrays = await _aopen_output(zstore, output)

    async def one(a: Any) -> np.ndarray:
        return np.asarray(await a.getitem(...)).reshape(a.shape)

    data = await asyncio.gather(*(one(a) for a in arrays.values()))
    enc_arrays = {
        name: (d, tuple(a.metadata.dimension_names or ()))
        for (name, a), d in zip(arrays.items(), data)
    }
    return Encoded(meta["type"], enc_arrays, meta.get("attrs", {}))


async def _abad_chunks(zstore: Any, output: str) -> list[str]:
    """Chunks of an output that fail to decode (named by their keys)."""
    _, arrays = await _aopen_output(zstore, output)
    bad = []
    for name, a in arrays.items():
        for key, sel in _chunk_keys(output, name, a).items():
            try:
                await a.getitem(sel)
            except Exception as e:
                bad.append(f"{key} ({type(e).__name__}: {e})")
    return bad


def _sync(coro: Any) -> Any:
    from zarr.core.sync import sync

    return sync(coro)


# --------------------------------------------------------------------------- backends


class _Local:
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
        from zarr.storage import LocalStore

        return LocalStore(path, read_only=True)


class _DirSink:
    def __init__(self, backend: Any, base: str) -> None:
        self.backend = backend
        self.base = base
        self._made: set[str] = set()

    def put_many(self, items: Mapping[str, bytes]) -> None:
        if not self.backend.is_local:
            self.backend.put_many({posixpath.join(self.base, k): v for k, v in items.items()})
            return
        for rel, data in items.items():
            path = os.path.join(self.base, *rel.split("/"))
            d = os.path.dirname(path)
            if d not in self._made:
                os.makedirs(d, exist_ok=True)
                self._made.add(d)
            with open(path, "wb") as f:
                f.write(data)


class _Fsspec:
    """Storage operations on an fsspec filesystem (no atomic rename)."""

    is_local = False

    def __init__(self, url: str, storage_options: dict | None) -> None:
        from fsspec.core import url_to_fs

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

    def put_many(self, items: Mapping[str, bytes]) -> None:
        self.fs.pipe(dict(items))

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
        from zarr.storage import FsspecStore

        return FsspecStore.from_url(
            self.url(path), storage_options=self.storage_options, read_only=True
        )


# --------------------------------------------------------------------------- store


class Store:
    """A content-addressed store of committed stage outputs.

    Parameters
    ----------
    root : str or path-like
        Local directory (created on first write) or fsspec URL (``memory://x``,
        ``s3://bucket/prefix``).  ``file://`` URLs are treated as local paths.
    chunk_frames : int
        Rows per chunk along an axis named ``frame`` (other axes stay whole;
        fewer rows when a chunk would exceed 64 MiB).  Does not change digests.
    atomic_rename : bool, optional
        Commit through ``staging/`` + ``os.rename``.  Default: True for local
        roots; fsspec URLs are always written in place, manifest last.
    storage_options : dict, optional
        Passed to fsspec for URL roots.

    Notes
    -----
    Safe to use from many processes and threads at once; pickles as its root
    and options only.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        *,
        chunk_frames: int = 1024,
        atomic_rename: bool | None = None,
        storage_options: dict | None = None,
    ) -> None:
        if int(chunk_frames) < 1:
            raise ValueError(f"chunk_frames must be >= 1, got {chunk_frames}")
        self.chunk_frames = int(chunk_frames)
        self._options = {
            "chunk_frames": self.chunk_frames,
            "atomic_rename": atomic_rename,
            "storage_options": storage_options,
        }
        text = os.fspath(root)
        if text.startswith("file://"):
            text = text[len("file://") :]
        if "://" in text:
            if atomic_rename:
                raise ValueError(f"atomic_rename needs a local store root, not {text!r}")
            self._b: _Local | _Fsspec = _Fsspec(text, storage_options)
            self.root = text
            self._atomic = False
        else:
            path = os.path.abspath(os.path.expanduser(text))
            self._b = _Local(path)
            self.root = path
            self._atomic = True if atomic_rename is None else bool(atomic_rename)
        self._runs_cache: dict[str, tuple[Any, dict]] = {}
        self._runs_lock = threading.Lock()

    # ----------------------------------------------------------------- basics

    @property
    def is_local(self) -> bool:
        """Whether the root is a directory on this machine's filesystem."""
        return self._b.is_local

    def __getstate__(self) -> dict:
        return {"root": self.root, **self._options}

    def __setstate__(self, state: dict) -> None:
        root = state.pop("root")
        self.__init__(root, **state)

    def __repr__(self) -> str:
        return f"Store({self.root!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Store) and (self.root, self._options) == (
            other.root,
            other._options,
        )

    def __hash__(self) -> int:
        return hash(self.root)

    def _path(self, *parts: str) -> str:
        return self._b.join(self._b.root, *parts)

    def _entry(self, stage: str, key: str) -> str:
        return self._path("entries", _check_name(stage, "stage"), _check_name(key, "key"))

    def entry_path(self, stage: str, key: str) -> str:
        """Location of an entry's Zarr group (local path or URL)."""
        return self._b.url(self._entry(stage, key))

    # ----------------------------------------------------------------- entries

    def manifest(self, stage: str, key: str) -> dict | None:
        """The entry's manifest, or ``None`` if it is not committed."""
        data = self._b.read(self._b.join(self._entry(stage, key), MANIFEST))
        if data is None:
            return None
        try:
            man = json.loads(data)
        except ValueError:
            return None
        if not isinstance(man, dict) or not isinstance(man.get("outputs"), dict):
            return None
        return man

    def has(self, stage: str, key: str) -> bool:
        """Whether the entry is committed (its manifest exists and parses)."""
        return self.manifest(stage, key) is not None

    def entries(self) -> list[tuple[str, str]]:
        """Every committed ``(stage, key)``, sorted."""
        out = []
        base = self._path("entries")
        for stage in self._b.listdir(base):
            for key in self._b.listdir(self._b.join(base, stage)):
                if self._b.exists(self._b.join(base, stage, key, MANIFEST)):
                    out.append((stage, key))
        return out

    def commit(
        self, stage: str, key: str, outputs: Mapping[str, Encoded], manifest: Mapping[str, Any]
    ) -> dict[str, str]:
        """Write an entry once: arrays first, manifest last, then (locally) rename.

        Parameters
        ----------
        stage, key : str
            Entry address.
        outputs : dict
            ``output name -> Encoded``.
        manifest : dict
            Key components, timings, versions, upstream keys, warnings, ...
            (JSON; numpy scalars and tuples are converted).

        Returns
        -------
        dict
            ``output name -> digest`` (:func:`~mocapflow.pipeline.codecs.digest_encoded`).
            If the entry already exists (e.g. a concurrent run won the race) its
            digests are returned and nothing is written.
        """
        entry = self._entry(stage, key)
        existing = self.manifest(stage, key)
        if existing is not None:
            return {k: v["digest"] for k, v in existing["outputs"].items()}
        encs = {_check_name(n, "output"): _normalise(e, n) for n, e in outputs.items()}
        digests = {n: digest_encoded(e) for n, e in encs.items()}
        full = dict(manifest)
        full.update(
            stage=stage,
            key=key,
            outputs={n: {"digest": digests[n], "type": encs[n].type} for n in encs},
            committed_at=_now_iso(),
            format=FORMAT,
        )
        body = _dump_json(full)
        root_attrs = {"mocapflow": {"stage": stage, "key": key, "format": FORMAT}}
        if not self._atomic:
            w = self._b.join(entry, WRITER)
            self._b.write(w, _dump_json(_writer_info()))
            try:
                _sync(_awrite_entry(_DirSink(self._b, entry), encs, root_attrs, self.chunk_frames))
            finally:
                self._b.remove(w)  # on failure the debris is gc's (a live writer's is kept)
            self._b.write(self._b.join(entry, MANIFEST), body)
            return digests
        staging = self._path("staging", f"{stage}-{key}-{uuid.uuid4().hex[:12]}")
        try:
            os.makedirs(staging)
            w = os.path.join(staging, WRITER)
            self._b.write(w, _dump_json(_writer_info()))
            _sync(_awrite_entry(_DirSink(self._b, staging), encs, root_attrs, self.chunk_frames))
            os.unlink(w)
            self._b.write(os.path.join(staging, MANIFEST), body)
            os.makedirs(os.path.dirname(entry), exist_ok=True)
            return self._publish(staging, entry, stage, key, digests)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise

    def _publish(self, staging: str, entry: str, stage: str, key: str, digests: dict) -> dict:
        for _ in range(3):
            try:
                os.rename(staging, entry)
                return digests
            except FileNotFoundError:
                if not os.path.isdir(staging):
                    raise StoreError(
                        f"staging directory {staging} vanished while writing {stage}/{key} "
                        "(a concurrent gc from another host?)"
                    ) from None
                os.makedirs(os.path.dirname(entry), exist_ok=True)  # stage dir gc'd meanwhile
                continue
            except OSError as e:
                if e.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                    raise
            won = self.manifest(stage, key)
            if won is not None:  # another writer committed the same key first
                shutil.rmtree(staging, ignore_errors=True)
                theirs = {k: v["digest"] for k, v in won["outputs"].items()}
                if theirs != digests:
                    log.warning(
                        "entry %s/%s was committed concurrently with different output digests "
                        "(is the stage deterministic?); keeping the first",
                        stage,
                        key,
                    )
                return theirs
            self._discard(entry)  # a broken directory without a manifest
        raise StoreError(f"could not publish entry {stage}/{key} at {entry}")

    def _discard(self, path: str) -> None:
        """Remove a directory so that it disappears at once (local: rename, then delete)."""
        if self._b.is_local:
            trash = self._path("staging", f"trash-{uuid.uuid4().hex[:12]}")
            os.makedirs(os.path.dirname(trash), exist_ok=True)
            try:
                os.rename(path, trash)
            except FileNotFoundError:
                return
            shutil.rmtree(trash, ignore_errors=True)
        else:
            self._b.remove(self._b.join(path, MANIFEST))
            self._b.rmtree(path)

    def delete(self, stage: str, key: str) -> bool:
        """Remove a committed entry; True if there was one."""
        entry = self._entry(stage, key)
        if not self._b.exists(entry):
            return False
        self._discard(entry)
        return True

    def _require(self, stage: str, key: str) -> dict:
        man = self.manifest(stage, key)
        if man is None:
            raise EntryNotFoundError(
                f"no committed entry {stage}/{key} in store {self.root} "
                f"(expected {self.entry_path(stage, key)}/{MANIFEST})"
            )
        return man

    def load(self, stage: str, key: str, output: str) -> Encoded:
        """Read one output of a committed entry."""
        man = self._require(stage, key)
        if output not in man["outputs"]:
            raise EntryNotFoundError(
                f"entry {stage}/{key} has no output {output!r} "
                f"(it has {', '.join(sorted(man['outputs'])) or 'none'})"
            )
        zstore = self._b.zarr_store(self._entry(stage, key))
        return _sync(_aread_output(zstore, output))

    def load_outputs(self, stage: str, key: str) -> dict[str, Encoded]:
        """Read every output of a committed entry."""
        import asyncio

        man = self._require(stage, key)
        names = sorted(man["outputs"])
        zstore = self._b.zarr_store(self._entry(stage, key))

        async def all_outputs():
            return await asyncio.gather(*(_aread_output(zstore, n) for n in names))

        return dict(zip(names, _sync(all_outputs())))

    # ----------------------------------------------------------------- verify / gc

    def verify(self, *, entries: Iterable[tuple[str, str]] | None = None) -> list[str]:
        """Re-read committed entries and check them against their manifests.

        Parameters
        ----------
        entries : iterable of (stage, key), optional
            Default: every committed entry.

        Returns
        -------
        list of str
            One line per problem (empty when all is well): missing or unexpected
            files (chunks, metadata), unreadable outputs, output digests that do
            not match the manifest.  Staging debris is not a problem (see
            :meth:`gc`).
        """
        problems: list[str] = []
        for stage, key in self.entries() if entries is None else entries:
            problems.extend(self._verify_entry(stage, key))
        return problems

    def _verify_entry(self, stage: str, key: str) -> list[str]:
        where = f"{stage}/{key}"
        man = self.manifest(stage, key)
        if man is None:
            return [f"{where}: not committed (no readable {MANIFEST})"]
        problems = []
        if man.get("stage") != stage or man.get("key") != key:
            problems.append(
                f"{where}: manifest names {man.get('stage')}/{man.get('key')} instead"
            )
        entry = self._entry(stage, key)
        zstore = self._b.zarr_store(entry)
        expected = {MANIFEST, "zarr.json"}
        for out, info in sorted(man["outputs"].items()):
            try:
                expected |= _expected_keys(out, _sync(_aopen_output(zstore, out))[1])
            except Exception as e:  # metadata unreadable: cannot tell which files belong
                problems.append(f"{where}/{out}: metadata unreadable ({type(e).__name__}: {e})")
                expected |= {f"{out}/{f}" for f in self._b.find(self._b.join(entry, out))}
                continue
            try:
                enc = _sync(_aread_output(zstore, out))
            except Exception as e:  # name the chunks that do not decode
                bad = _sync(_abad_chunks(zstore, out))
                problems.extend(f"{where}: corrupt chunk {b}" for b in bad)
                if not bad:
                    problems.append(f"{where}/{out}: unreadable ({type(e).__name__}: {e})")
                continue
            got = digest_encoded(enc)
            if got != info.get("digest"):
                problems.append(
                    f"{where}/{out}: digest mismatch (manifest {str(info.get('digest'))[:12]}.., "
                    f"data {got[:12]}..): corrupted or missing chunks"
                )
        files = set(self._b.find(entry))
        for f in sorted(expected - files):
            problems.append(f"{where}: missing file {f}")
        for f in sorted(files - expected):
            problems.append(f"{where}: unexpected file {f}")
        return problems

    def _debris_verdict(self, path: str, min_age: float, now: float) -> bool:
        """Whether a staging dir / manifest-less entry dir may be removed."""
        raw = self._b.read(self._b.join(path, WRITER))
        info = None
        if raw is not None:
            try:
                info = json.loads(raw)
            except ValueError:
                info = None
        if isinstance(info, dict):
            alive = _writer_alive(info)
            if alive is True:
                return False
            if alive is False:
                return True
            started = info.get("started")
            if isinstance(started, (int, float)):
                return now - started >= min_age
        mtime = self._b.mtime(path)
        return mtime is None or now - mtime >= min_age

    def gc(
        self,
        *,
        keep: set[tuple[str, str]] | None = None,
        dry_run: bool = False,
        staging_min_age_s: float = 0.0,
    ) -> dict:
        """Remove debris and, given ``keep``, unreachable entries.

        Parameters
        ----------
        keep : set of (stage, key), optional
            When given, committed entries not in it are removed too.
        dry_run : bool
            Report only.
        staging_min_age_s : float
            Staging dirs (and manifest-less entry dirs) whose writer is alive on
            this host are always kept; those whose writer is dead on this host are
            removed; those whose writer cannot be checked (other host, no
            ``_WRITER.json``) are removed once older than this.

        Returns
        -------
        dict
            ``{"staging": [...], "incomplete": [...], "unreachable": [...],
            "bytes": int, "dry_run": bool}`` (paths removed, or that would be).
        """
        now = time.time()
        report: dict[str, Any] = {
            "staging": [],
            "incomplete": [],
            "unreachable": [],
            "bytes": 0,
            "dry_run": dry_run,
        }
        sdir = self._path("staging")
        for name in self._b.listdir(sdir):
            path = self._b.join(sdir, name)
            if not self._b.isdir(path):
                continue
            if self._debris_verdict(path, staging_min_age_s, now):
                report["staging"].append(self._b.url(path))
                report["bytes"] += self._b.du(path)
                if not dry_run:
                    self._b.rmtree(path)
        base = self._path("entries")
        for stage in self._b.listdir(base):
            sd = self._b.join(base, stage)
            for key in self._b.listdir(sd):
                path = self._b.join(sd, key)
                if self._manifest_at(path) is None:
                    if not self._debris_verdict(path, staging_min_age_s, now):
                        continue
                    bucket = "incomplete"
                elif keep is not None and (stage, key) not in keep:
                    bucket = "unreachable"
                else:
                    continue
                report[bucket].append(self._b.url(path))
                report["bytes"] += self._b.du(path)
                if not dry_run:
                    self._discard(path)
            if not dry_run and self._b.is_local:
                try:
                    os.rmdir(sd)  # only when empty
                except OSError:
                    pass
        return report

    def _manifest_at(self, path: str) -> dict | None:
        data = self._b.read(self._b.join(path, MANIFEST))
        try:
            man = json.loads(data) if data is not None else None
        except ValueError:
            return None
        return man if isinstance(man, dict) and isinstance(man.get("outputs"), dict) else None

    # ----------------------------------------------------------------- run records

    def write_run(self, run_id: str, record: Mapping[str, Any]) -> str:
        """Write (or replace) the record of a run atomically; returns its location.

        The record should carry ``started_at`` (epoch seconds or ISO time) and
        ``tasks``: a list of ``{"node", "part", "stage", "key", "components",
        "status", ...}``.
        """
        path = self._path("runs", f"{_check_name(run_id, 'run id')}.json")
        rec = dict(record)
        rec.setdefault("run_id", run_id)
        self._b.write_atomic(path, _dump_json(rec))
        return self._b.url(path)

    def runs(self) -> list[dict]:
        """Every run record, oldest first."""
        with self._runs_lock:
            return self._runs_locked()

    def _runs_locked(self) -> list[dict]:
        rdir = self._path("runs")
        found: list[tuple[float, str, dict]] = []
        seen = set()
        for name in self._b.listdir(rdir):
            if not name.endswith(".json") or name.startswith("."):
                continue
            path = self._b.join(rdir, name)
            sig: Any = None
            if self._b.is_local:
                try:
                    st = os.stat(path)
                except OSError:
                    continue
                sig = (st.st_mtime_ns, st.st_size)
            cached = self._runs_cache.get(name)
            if sig is not None and cached is not None and cached[0] == sig:
                rec = cached[1]
            else:
                raw = self._b.read(path)
                try:
                    rec = json.loads(raw) if raw is not None else None
                except ValueError:
                    rec = None
                if not isinstance(rec, dict):
                    continue
                rec.setdefault("run_id", name[: -len(".json")])
                self._runs_cache[name] = (sig, rec)
            seen.add(name)
            mtime = sig[0] / 1e9 if sig else (self._b.mtime(path) or 0.0)
            found.append((_run_time(rec, mtime), name, rec))
        for name in set(self._runs_cache) - seen:
            self._runs_cache.pop(name, None)
        found.sort(key=lambda t: (t[0], t[1]))
        return [r for _, _, r in found]

    def last_task_record(
        self, node: str, part: str | None, *, statuses: Iterable[str] | None = None
    ) -> dict | None:
        """The most recent task record of ``(node, part)`` over all runs.

        Parameters
        ----------
        node : str
        part : str or None
        statuses : iterable of str, optional
            Only records with one of these statuses (e.g. ``{"hit", "computed"}``).

        Returns
        -------
        dict or None
            A copy of the task record, with ``run_id`` added.
        """
        wanted = set(statuses) if statuses is not None else None
        for rec in reversed(self.runs()):
            for task in reversed(rec.get("tasks") or []):
                if not isinstance(task, dict):
                    continue
                if task.get("node") == node and task.get("part") == part:
                    if wanted is not None and task.get("status") not in wanted:
                        continue
                    out = dict(task)
                    out.setdefault("run_id", rec.get("run_id"))
                    return out
        return None

    # ----------------------------------------------------------------- file memo

    def _memo_path(self) -> str:
        return self._path("cache", "file_digests.json")

    def load_file_memo(self) -> dict:
        """The persistent file-digest memo (``realpath -> [size, mtime_ns, inode, digest]``)."""
        raw = self._b.read(self._memo_path())
        if raw is None:
            return {}
        try:
            memo = json.loads(raw)
        except ValueError:
            return {}
        return memo if isinstance(memo, dict) else {}

    def save_file_memo(self, memo: Mapping[str, Any]) -> None:
        """Merge ``memo`` into the persistent memo (atomic replace)."""
        merged = self.load_file_memo()
        merged.update(memo)
        self._b.write_atomic(self._memo_path(), _dump_json(merged))
