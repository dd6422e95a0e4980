"""How stage outputs become Zarr arrays + JSON attrs, and back.

The engine stores every output as one Zarr group.  An output value is encoded as
an :class:`Encoded`: named arrays, each with its ``dimension_names``, plus JSON
attrs.  Built in:

* ``ndarray``: one array ``data`` with dims ``dim_0 …``;
* JSON values (dict/list/str/number/bool/None): attrs only;
* ``dict`` holding at least one ndarray (a *record*): ndarray values become
  arrays, the rest attrs.  Axes are named ``<key>_dim_<i>`` unless the record
  names them itself under the reserved key :data:`RECORD_DIMS` (``"_dims"``):
  ``{"positions": x, "_dims": {"positions": ["frame", "marker", "xyz"]}}``.
  The ``_dims`` mapping is stored as an attr, so the record round-trips with it.

Coordinates
-----------
An :class:`Encoded` may carry ``coords``: labels of its axes, ``name -> (array,
dims)`` (marker labels along ``marker``, ``frame`` numbers, ``time`` in seconds
along ``frame``, component names ``x y z`` along ``xyz``, …).  The store writes
them as extra arrays of the output group, so ``xarray.open_zarr`` shows them as
coordinates: a 1-D coord named like its dimension becomes an index; any other
(e.g. ``time`` along ``frame``) is named in the ``coordinates`` attribute of the
data arrays that share its dims (the CF convention xarray follows).  Coords are
descriptive only: :func:`decode` never sees them (a decoder must not need them),
but :func:`digest_encoded` covers them, so ``verify`` catches a corrupted one.

Domain types (markers, motion, mesh, …) register a codec with :func:`codec`;
the engine finds it by the type's registered name, so it never imports them.
Exporters (``mocapflow export``) register the same way with :func:`exporter`.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "COMPONENTS",
    "RECORD_DIMS",
    "Encoded",
    "ExportFormatError",
    "codec",
    "component_coords",
    "decode",
    "digest_encoded",
    "encode",
    "exporter",
    "find_exporter",
    "frame_coords",
    "label_coord",
]


@dataclass
class Encoded:
    """An output ready for storage.

    Attributes
    ----------
    type : str
        Codec name (``ndarray``, ``json``, ``record`` or a registered type).
    arrays : dict
        ``name -> (array, dims)`` with ``len(dims) == array.ndim``.
    attrs : dict
        JSON-serialisable attributes.
    coords : dict
        ``name -> (array, dims)``: axis labels written next to the arrays for
        readers such as xarray (see *Coordinates* in the module docstring); not
        passed to decoders' logic and never required by them.  Names must differ
        from the array names.
    """

    type: str
    arrays: dict[str, tuple[np.ndarray, tuple[str, ...]]] = field(default_factory=dict)
    attrs: dict[str, Any] = field(default_factory=dict)
    coords: dict[str, tuple[np.ndarray, tuple[str, ...]]] = field(default_factory=dict)


#: Reserved record key naming the axes of a record's arrays (``name -> list of dims``).
RECORD_DIMS = "_dims"


def frame_coords(n_frames: int, rate: float | None, first_frame: int = 0) -> dict[str, tuple]:
    """``frame`` numbers and, with a rate, ``time`` in seconds, as :class:`Encoded` coords.

    Parameters
    ----------
    n_frames : int
        ``F``.
    rate : float or None
        Frames per second; ``time`` is left out when ``None`` or not positive.
    first_frame : int
        Source number of the first frame (C3D ``first_frame``; 0 for 0-based sources).

    Returns
    -------
    dict
        ``{"frame": ((F,) int64, ("frame",)), "time": ((F,) float64 s, ("frame",))}``
        with ``time = frame / rate``.
    """
    frame = np.arange(first_frame, first_frame + n_frames, dtype=np.int64)
    out: dict[str, tuple] = {"frame": (frame, ("frame",))}
    if rate is not None and float(rate) > 0:
        out["time"] = (frame / float(rate), ("frame",))
    return out


def label_coord(labels: Any, dim: str) -> tuple[np.ndarray, tuple[str, ...]]:
    """``(str array, (dim,))``: one label per index of ``dim`` (e.g. marker labels)."""
    arr = np.array([str(x) for x in labels], dtype=str) if len(labels) else np.zeros(0, "<U1")
    return arr, (dim,)


#: Component labels of the small fixed axes, as coords (``xyz``, ``wxyz``, ``xy``).
COMPONENTS: dict[str, tuple[str, ...]] = {
    "xyz": ("x", "y", "z"),
    "wxyz": ("w", "x", "y", "z"),
    "xy": ("x", "y"),
    "xz": ("x", "z"),
    "rgb": ("r", "g", "b"),
    "rgba": ("r", "g", "b", "a"),
}


def component_coords(*dims: str) -> dict[str, tuple[np.ndarray, tuple[str, ...]]]:
    """Coords labelling the component axes among ``dims`` (see :data:`COMPONENTS`)."""
    return {d: label_coord(COMPONENTS[d], d) for d in dims if d in COMPONENTS}


@dataclass(frozen=True)
class _Codec:
    name: str
    cls: type
    encode: Callable[[Any], Encoded]
    decode: Callable[[Encoded], Any]


_BY_NAME: dict[str, _Codec] = {}
_BY_CLASS: dict[type, _Codec] = {}
_EXPORTERS: dict[str, Callable[..., list[Path]]] = {}


def codec(name: str, *, encode: Callable[[Any], Encoded], decode: Callable[[Encoded], Any]):
    """Class decorator registering a storage codec for a domain type.

    Parameters
    ----------
    name : str
        Stable type name stored in the entry (never rename it: stored entries
        refer to it).
    encode : callable
        ``obj -> Encoded``.
    decode : callable
        ``Encoded -> obj``; must round-trip exactly.
    """

    def register(cls: type) -> type:
        c = _Codec(name, cls, encode, decode)
        _BY_NAME[name] = c
        _BY_CLASS[cls] = c
        return cls

    return register


class ExportFormatError(ValueError):
    """An exporter's ``formats`` option names a format it does not write (says which it does)."""


def exporter(type_name: str):
    """Register ``fn(obj, directory, stem, **options) -> list[Path]`` for a type name.

    An exporter that writes several formats takes a ``formats`` option and raises
    :class:`ExportFormatError` for one it does not know.
    """

    def register(fn: Callable[..., list[Path]]) -> Callable[..., list[Path]]:
        _EXPORTERS[type_name] = fn
        return fn

    return register


def find_exporter(type_name: str) -> Callable[..., list[Path]] | None:
    """The exporter registered for ``type_name`` (``None`` if there is none)."""
    return _EXPORTERS.get(type_name)


def _is_json(x: Any) -> bool:
    if x is None or isinstance(x, (bool, int, str)):
        return True
    if isinstance(x, float):
        return True
    if isinstance(x, (list, tuple)):
        return all(_is_json(v) for v in x)
    if isinstance(x, dict):
        return all(isinstance(k, str) and _is_json(v) for k, v in x.items())
    return False


def to_jsonable(x: Any) -> Any:
    """Convert numpy scalars / small arrays / tuples to plain JSON values.

    Non-finite floats are encoded as the strings ``"NaN"``, ``"Infinity"``,
    ``"-Infinity"`` so the attrs stay strict JSON.
    """
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, np.generic):
        return to_jsonable(x.item())
    if isinstance(x, float) and not math.isfinite(x):
        return "NaN" if math.isnan(x) else ("Infinity" if x > 0 else "-Infinity")
    if isinstance(x, Path):
        return str(x)
    return x


def encode(value: Any) -> Encoded:
    """Encode one stage output for storage (see module docstring)."""
    c = _BY_CLASS.get(type(value))
    if c is None:
        for cls, cand in _BY_CLASS.items():
            if isinstance(value, cls):
                c = cand
                break
    if c is not None:
        enc = c.encode(value)
        enc.type = c.name
        enc.attrs = to_jsonable(enc.attrs)
        return enc
    if isinstance(value, np.ndarray):
        return Encoded("ndarray", {"data": (value, tuple(f"dim_{i}" for i in range(value.ndim)))})
    if isinstance(value, dict) and any(isinstance(v, np.ndarray) for v in value.values()):
        named = value.get(RECORD_DIMS) or {}
        if not isinstance(named, dict):
            raise TypeError(f"record key {RECORD_DIMS!r} must map array names to dim names")
        arrays = {}
        attrs = {}
        for k, v in value.items():
            if isinstance(v, np.ndarray):
                dims = tuple(named.get(k) or (f"{k}_dim_{i}" for i in range(v.ndim)))
                if len(dims) != v.ndim:
                    raise ValueError(
                        f"record {RECORD_DIMS}[{k!r}] names {len(dims)} dims for {v.ndim} axes"
                    )
                arrays[str(k)] = (v, dims)
            else:
                attrs[str(k)] = to_jsonable(v)
        return Encoded("record", arrays, attrs)
    j = to_jsonable(value)
    if _is_json(j):
        return Encoded("json", {}, {"value": j})
    raise TypeError(
        f"cannot store a {type(value).__name__}: register a codec for it with "
        "mocapflow.pipeline.codecs.codec, or return arrays / JSON values"
    )


def decode(enc: Encoded) -> Any:
    """Inverse of :func:`encode`."""
    if enc.type == "ndarray":
        return enc.arrays["data"][0]
    if enc.type == "json":
        return enc.attrs.get("value")
    if enc.type == "record":
        out: dict[str, Any] = dict(enc.attrs)
        out.update({k: a for k, (a, _) in enc.arrays.items()})
        return out
    c = _BY_NAME.get(enc.type)
    if c is None:
        raise TypeError(
            f"no codec registered for stored type {enc.type!r} (is the stage family installed?)"
        )
    return c.decode(enc)


def canonical_json(obj: Any) -> bytes:
    """Canonical JSON bytes (sorted keys, no spaces, UTF-8)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode()


def digest_encoded(enc: Encoded) -> str:
    """Content digest (blake2b-256 hex) of an encoded output.

    Covers the type name, the canonical attrs and, per array in name order, its
    name, dtype, shape, dims and C-order bytes; then, only when there are coords
    (so outputs without them keep their digests), the same per coord after a
    ``"coords"`` marker.
    """
    h = hashlib.blake2b(digest_size=32)
    h.update(canonical_json({"type": enc.type, "attrs": enc.attrs}))

    def arrays(items: dict) -> None:
        for name in sorted(items):
            arr, dims = items[name]
            arr = np.ascontiguousarray(arr)
            h.update(canonical_json([name, arr.dtype.str, list(arr.shape), list(dims)]))
            h.update(arr.reshape(-1).view(np.uint8).data)

    arrays(enc.arrays)
    if enc.coords:
        h.update(b'"coords"')
        arrays(enc.coords)
    return h.hexdigest()
