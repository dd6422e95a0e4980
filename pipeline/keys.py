"""Cache keys: canonical type-tagged JSON, content digests, code fingerprints.

A task's key is the blake2b digest of the canonical encoding of its
*components*: stage identity, code fingerprint, validated params, part id,
content digests of its inputs and the versions of the packages that change
results.  Everything here is stable across interpreters and machines (no
``hash()``, no ``dask.base.tokenize``).

* :func:`canonical` — type-tagged JSON bytes: ``1``, ``1.0``, ``"1"`` and
  ``True`` encode differently, dict order does not matter, floats are exact.
* :func:`file_digest` — streamed content digest of an input file, memoised by
  ``(realpath, size, mtime_ns, inode, ctime_ns)``.
* code fingerprints live in :mod:`mocapflow.pipeline.fingerprint`.
* :func:`task_key` / :func:`diff_components` — the key and a readable account
  of which component changed (for ``mocapflow explain``).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import stat
import threading
import time
from collections.abc import Callable, Mapping
from importlib import metadata
from typing import Any

import numpy as np

__all__ = [
    "KEY_LENGTH",
    "RESULT_PACKAGES",
    "canonical",
    "clear_caches",
    "content_digest",
    "diff_components",
    "digest",
    "digest_of",
    "file_digest",
    "package_versions",
    "real_path",
    "task_key",
]

#: Hex characters of a task key (128 bits).
KEY_LENGTH = 32
#: Packages whose version changes numerical results (part of every key).
RESULT_PACKAGES = ("numpy", "scipy", "ezc3d")
#: Version of the key layout; bump to invalidate every stored entry.
KEY_FORMAT = 1
#: A file modified less than this many seconds before it was hashed is not
#: memoised (its mtime may not yet reflect a second write in the same tick).
RACY_WINDOW_S = 1.0

_LOCK = threading.Lock()
_FILE_MEMO: dict[tuple[str, int, int, int], str] = {}
_VERSIONS: dict[tuple[str, ...], dict[str, str]] = {}


def clear_caches() -> None:
    """Forget memoised file digests and package versions."""
    with _LOCK:
        _FILE_MEMO.clear()
        _VERSIONS.clear()


# --------------------------------------------------------------------------- canonical


def _tag(obj: Any) -> Any:
    """Type-tagged, JSON-ready tree of ``obj`` (see :func:`canonical`)."""
    if obj is None:
        return None
    if isinstance(obj, (bool, np.bool_)):
        return ["bool", bool(obj)]
    if isinstance(obj, (int, np.integer)):
        return ["int", str(int(obj))]
    if isinstance(obj, (float, np.floating)):
        return ["float", float(obj).hex()]
    if isinstance(obj, (complex, np.complexfloating)):
        c = complex(obj)
        return ["complex", c.real.hex(), c.imag.hex()]
    if isinstance(obj, str):
        return ["str", obj]
    if isinstance(obj, (list, tuple)):
        return ["list", [_tag(v) for v in obj]]
    if isinstance(obj, Mapping):
        items = [(_tag(k), _tag(v)) for k, v in obj.items()]
        items.sort(key=lambda kv: _dumps(kv[0]))
        return ["dict", [[k, v] for k, v in items]]
    if isinstance(obj, np.ndarray):
        if obj.dtype.hasobject:
            return ["ndarray-object", list(obj.shape), [_tag(v) for v in obj.ravel().tolist()]]
        arr = np.ascontiguousarray(obj)
        if arr.dtype.byteorder == ">":
            arr = arr.astype(arr.dtype.newbyteorder("<"))
        return ["ndarray", arr.dtype.str, list(arr.shape), digest(arr.tobytes())]
    raise TypeError(
        f"cannot build a cache key from a {type(obj).__name__} ({obj!r:.60}); "
        "use None, bool, int, float, str, lists, dicts or numpy arrays"
    )


def _dumps(tree: Any) -> str:
    return json.dumps(tree, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


#: How ``json.dumps(..., ensure_ascii=False)`` writes a str (quotes and escapes).
_json_str = json.encoder.encode_basestring


def _encode(obj: Any) -> str:
    """``_dumps(_tag(obj))``, written directly for the plain types of keys.

    Same text, about five times faster: each dict key is encoded once (the
    encoding is also its sort key) and no tagged tree is built.  Numpy values,
    arrays, subclasses and other mappings take the general path.
    """
    t = type(obj)
    if t is str:
        return '["str",' + _json_str(obj) + "]"
    if t is dict:
        return _encode_items([(_encode(k), _encode(v)) for k, v in obj.items()])
    if t is int:
        return '["int","' + str(obj) + '"]'
    if t is float:
        return '["float","' + obj.hex() + '"]'
    if t is list or t is tuple:
        return '["list",[' + ",".join([_encode(v) for v in obj]) + "]]"
    if obj is None:
        return "null"
    if t is bool:
        return '["bool",true]' if obj else '["bool",false]'
    return _dumps(_tag(obj))


def _first(kv: tuple[str, str]) -> str:
    return kv[0]


def _encode_items(items: list[tuple[str, str]]) -> str:
    """The encoding of a dict from its ``(encoded key, encoded value)`` pairs (sorted here)."""
    items.sort(key=_first)
    return '["dict",[' + ",".join(["[" + k + "," + v + "]" for k, v in items]) + "]]"


#: Encodings of the flat ``str -> str`` dicts every task of a run shares (package
#: versions, input kinds), by ``tuple(items)``: a no-op run of 30,001 tasks encodes
#: them once each, not 30,001 times.
_SHARED: dict[tuple, str] = {}
_SHARED_KEYS = frozenset({"versions", "input_kinds"})


def _encode_shared(d: Mapping[str, str]) -> str:
    """``_encode(dict(d))``, memoised (``d``: a flat dict of strings)."""
    k = tuple(d.items())
    text = _SHARED.get(k)
    if text is None:
        text = _encode(dict(d))
        if len(_SHARED) < 4096:
            _SHARED[k] = text
    return text


def canonical(obj: Any) -> bytes:
    """Canonical, type-tagged JSON encoding of a params / key structure.

    Parameters
    ----------
    obj : None, bool, int, float, complex, str, list, tuple, dict, numpy scalar or ndarray
        Nested freely.  Tuples encode as lists; dict keys may be any of these
        types and are sorted by their encoding.

    Returns
    -------
    bytes
        UTF-8 JSON in which every value carries its type (``1``, ``1.0``,
        ``"1"`` and ``True`` all differ), floats are written exactly with
        ``float.hex`` (so NaN, ±inf and -0.0 are stable), and arrays are
        represented by dtype, shape and a digest of their bytes.

    Raises
    ------
    TypeError
        For any other type (the message names it).
    """
    return _encode(obj).encode("utf-8", errors="surrogatepass")


def digest(data: bytes | str) -> str:
    """blake2b-256 hex digest of bytes (``str`` is UTF-8 encoded)."""
    if isinstance(data, str):
        data = data.encode("utf-8", errors="surrogatepass")
    return hashlib.blake2b(data, digest_size=32).hexdigest()


def digest_of(obj: Any) -> str:
    """``digest(canonical(obj))``."""
    return digest(canonical(obj))


# --------------------------------------------------------------------------- files


def _hash_file(path: str) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, lambda: hashlib.blake2b(digest_size=32)).hexdigest()


def real_path(path: str, dirs: dict[str, str] | None = None) -> str:
    """``os.path.realpath(path)``, resolving each directory once with ``dirs``.

    ``dirs`` (``abspath of a directory -> its realpath``) is filled as paths are
    resolved: the files of one folder then cost one ``lstat`` each, not one per
    path component (10,000 takes of a session: 0.03 s, not 0.3 s).  Keep it for
    one pass over the files only (a directory may be re-linked later).
    """
    if dirs is None or ".." in path.split(os.sep):  # ".." after a link: realpath's order
        return os.path.realpath(path)
    head, tail = os.path.split(os.path.join(os.getcwd(), path))
    rhead = dirs.get(head)
    if rhead is None:
        rhead = dirs[head] = os.path.realpath(head)
    full = os.path.join(rhead, tail)
    return os.path.realpath(full) if os.path.islink(full) else full


def file_digest(path: str | os.PathLike, memo: dict | None = None, *,
                dirs: dict[str, str] | None = None) -> str:
    """Content digest (blake2b-256 hex) of a file, streamed and memoised.

    Parameters
    ----------
    path : str or path-like
        A file, or a directory (digest over its sorted relative names and the
        digests of the files under it).
    memo : dict, optional
        Persistent memo ``realpath -> [size, mtime_ns, inode, ctime_ns, digest]``
        (the runner keeps it in the store).  Read, and updated in place.
    dirs : dict, optional
        Directory realpaths of this pass over the files (:func:`real_path`).

    Returns
    -------
    str
        The digest; memoised in-process by ``(realpath, size, mtime_ns, inode,
        ctime_ns)``: ``ctime`` changes on every write and cannot be set back, so
        a file rewritten with its size and ``mtime`` kept (``cp -p``, ``touch -r``)
        is hashed again.  Files modified within :data:`RACY_WINDOW_S` of hashing
        are not memoised.

    Raises
    ------
    FileNotFoundError
        When ``path`` does not exist (the message names it).
    """
    real = real_path(os.fspath(path), dirs)
    try:
        st = os.stat(real)
    except FileNotFoundError:
        raise FileNotFoundError(f"input file not found: {os.fspath(path)}") from None
    if stat.S_ISDIR(st.st_mode):
        return _dir_digest(real, lambda f: file_digest(f, memo))
    sig = (real, st.st_size, st.st_mtime_ns, st.st_ino, st.st_ctime_ns)
    with _LOCK:
        hit = _FILE_MEMO.get(sig)
    if hit is not None:
        return hit
    if memo is not None:
        rec = memo.get(real)
        if isinstance(rec, (list, tuple)) and len(rec) == 5 and list(rec[:4]) == list(sig[1:]):
            with _LOCK:
                _FILE_MEMO[sig] = str(rec[4])
            return str(rec[4])
    d = _hash_file(real)
    if time.time() - st.st_mtime_ns / 1e9 >= RACY_WINDOW_S:
        with _LOCK:
            _FILE_MEMO[sig] = d
        if memo is not None:
            memo[real] = [st.st_size, st.st_mtime_ns, st.st_ino, st.st_ctime_ns, d]
    return d


def _dir_digest(real: str, digest_file: Callable[[str], str]) -> str:
    """Digest of a directory: its sorted relative file names and ``digest_file`` of each."""
    items = []
    for dirpath, dirnames, filenames in os.walk(real):
        dirnames.sort()
        for name in sorted(filenames):
            full = os.path.join(dirpath, name)
            rel = os.path.relpath(full, real).replace(os.sep, "/")
            items.append([rel, digest_file(full)])
    return digest_of(["directory", items])


def content_digest(path: str | os.PathLike) -> str:
    """What ``path`` holds now, read in full: :func:`file_digest`'s value without its memos.

    Raises
    ------
    OSError
        The file (or a file under the directory) cannot be read.
    """
    real = os.path.realpath(os.fspath(path))
    if os.path.isdir(real):
        return _dir_digest(real, content_digest)
    return _hash_file(real)


# --------------------------------------------------------------------------- versions


def package_versions(names: tuple[str, ...] = RESULT_PACKAGES) -> dict[str, str]:
    """Installed versions of the packages that change results (``"absent"`` if missing)."""
    names = tuple(names)
    with _LOCK:
        hit = _VERSIONS.get(names)
    if hit is not None:
        return dict(hit)
    out = {}
    for n in names:
        try:
            out[n] = metadata.version(n)
        except metadata.PackageNotFoundError:
            out[n] = "absent"
    with _LOCK:
        _VERSIONS[names] = out
    return dict(out)


# --------------------------------------------------------------------------- keys


def task_key(
    *,
    stage: str,
    fingerprint: str,
    params: Mapping[str, Any],
    part: str | None,
    inputs: Mapping[str, str | list[str]],
    versions: Mapping[str, str],
    input_kinds: Mapping[str, str] | None = None,
) -> tuple[str, dict]:
    """Cache key of one task and the components it is made of.

    Parameters
    ----------
    stage : str
        Registry name of the stage.
    fingerprint : str
        :func:`code_fingerprint` of its module, or ``"pin:<version>"`` when the
        stage pins a manual version.
    params : dict
        Validated params (defaults filled).
    part : str or None
        Part id (``None`` for a gather task).
    inputs : dict
        ``input name -> digest`` or list of digests (gather): upstream output
        digests, or file content digests for ``FilePath`` inputs.
    versions : dict
        :func:`package_versions`.
    input_kinds : dict, optional
        ``input name -> "upstream" | "file"``; only used to word
        :func:`diff_components` (it is part of the components, and fixed by the
        stage signature anyway).

    Returns
    -------
    key : str
        First :data:`KEY_LENGTH` hex characters of ``digest_of(components)``.
    components : dict
        ``{"format", "stage", "code", "params", "part", "inputs", "versions"}``
        (plus ``"input_kinds"`` when given).  Node names, the store path, the
        worker count and the run id are deliberately not part of it.
    """
    components: dict[str, Any] = {
        "format": KEY_FORMAT,
        "stage": stage,
        "code": fingerprint,
        "params": dict(params),
        "part": part,
        "inputs": {k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in inputs.items()},
        "versions": dict(versions),
    }
    if input_kinds is not None:
        components["input_kinds"] = dict(input_kinds)
    # digest_of(components), with the parts all tasks share encoded once
    text = _encode_items([(_encode(k), _encode_shared(v) if k in _SHARED_KEYS else _encode(v))
                          for k, v in components.items()])
    return digest(text)[:KEY_LENGTH], components


def _short(value: Any, limit: int = 60) -> str:
    if isinstance(value, str) and len(value) == 64 and all(c in "0123456789abcdef" for c in value):
        return value[:8] + ".."
    if isinstance(value, float) and math.isnan(value):
        text = "nan"
    else:
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _same(a: Any, b: Any) -> bool:
    try:
        return canonical(a) == canonical(b)
    except TypeError:
        return a == b


def _diff_params(old: Any, new: Any, path: str, out: list[str]) -> None:
    if _same(old, new):
        return
    if isinstance(old, Mapping) and isinstance(new, Mapping):
        for k in sorted(set(old) | set(new), key=str):
            sub = f"{path}.{k}" if path else str(k)
            if k not in old:
                out.append(f"param {sub} added (= {_short(new[k])})")
            elif k not in new:
                out.append(f"param {sub} removed (was {_short(old[k])})")
            else:
                _diff_params(old[k], new[k], sub, out)
        return
    out.append(f"param {path}: {_short(old)} -> {_short(new)}")


def _diff_input(name: str, old: Any, new: Any, kind: str | None) -> str:
    what = {"file": "file content digest", "upstream": "upstream output digest"}.get(
        kind or "", "digest"
    )
    if isinstance(old, list) and isinstance(new, list):
        if len(old) != len(new):
            return f"input {name} changed ({len(old)} -> {len(new)} items)"
        changed = [i for i, (a, b) in enumerate(zip(old, new)) if a != b]
        idx = ", ".join(map(str, changed[:5])) + (", ..." if len(changed) > 5 else "")
        return f"input {name} changed ({len(changed)} of {len(new)} items: {what} at {idx})"
    return f"input {name} changed ({what} {_short(old)} -> {_short(new)})"


def diff_components(old: Mapping[str, Any] | None, new: Mapping[str, Any]) -> list[str]:
    """What changed between two key components, in words (for ``explain``).

    Parameters
    ----------
    old, new : dict
        Components as returned by :func:`task_key` (or read back from JSON).

    Returns
    -------
    list of str
        E.g. ``"param alpha1: 0.5 -> 0.7"``, ``"code of stage clean changed"``,
        ``"input markers changed (upstream output digest ab12.. -> cd34..)"``,
        ``"package numpy 2.3 -> 2.4"``, ``"part changed: a -> b"``.  Empty when
        they are the same.
    """
    if not old:
        return ["no previous record"]
    out: list[str] = []
    stage = new.get("stage")
    if old.get("stage") != stage:
        out.append(f"stage {old.get('stage')} -> {stage}")
    oc, nc = old.get("code"), new.get("code")
    if oc != nc:
        if str(oc).startswith("pin:") or str(nc).startswith("pin:"):
            out.append(f"version pin of stage {stage}: {_short(oc)} -> {_short(nc)}")
        else:
            out.append(f"code of stage {stage} changed ({_short(oc)} -> {_short(nc)})")
    _diff_params(old.get("params", {}), new.get("params", {}), "", out)
    if old.get("part") != new.get("part"):
        out.append(f"part changed: {old.get('part')} -> {new.get('part')}")
    oi, ni = old.get("inputs", {}) or {}, new.get("inputs", {}) or {}
    kinds = new.get("input_kinds") or old.get("input_kinds") or {}
    for name in sorted(set(oi) | set(ni)):
        if name not in oi:
            out.append(f"input {name} added")
        elif name not in ni:
            out.append(f"input {name} removed")
        elif oi[name] != ni[name]:
            out.append(_diff_input(name, oi[name], ni[name], kinds.get(name)))
    ov, nv = old.get("versions", {}) or {}, new.get("versions", {}) or {}
    for name in sorted(set(ov) | set(nv)):
        if ov.get(name) != nv.get(name):
            out.append(f"package {name} {ov.get(name, 'absent')} -> {nv.get(name, 'absent')}")
    known = {"stage", "code", "params", "part", "inputs", "versions", "input_kinds"}
    for name in sorted((set(old) | set(new)) - known, key=str):
        if not _same(old.get(name), new.get(name)):
            out.append(f"{name} changed: {_short(old.get(name))} -> {_short(new.get(name))}")
    return out

