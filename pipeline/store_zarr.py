"""Zarr v3 I/O of store entries: what can be stored, how it is chunked, written, read, checked.

An entry is one Zarr group holding one group per output; each output group's
``mocapflow`` attrs hold the :class:`~mocapflow.pipeline.codecs.Encoded` type,
attrs, array names and coord names, and each array carries ``dimension_names``,
chunked along ``frame`` with every other axis whole (:func:`_chunk_layout`).

Entries are self-describing for xarray: the ``Encoded.coords`` (marker labels,
``frame`` numbers, ``time`` in seconds, ``xyz`` component names, …) are extra
arrays of the output group (a 1-D coord named like its dimension is an index
coordinate; the others are listed in the ``coordinates`` attribute of every
data array holding all their dims), and every output group and the entry root
carry consolidated metadata, so ``xarray.open_zarr(entry, group=output)`` opens
with labelled coordinates, reads one metadata document and warns about nothing
(no listing of the entry directory, which holds ``_COMMIT.json``).
:func:`mocapflow.open_entry` opens a whole entry as an ``xarray.DataTree``.

* :func:`normalise` / :func:`output_digests`: the storable form of an output
  (native byte order, ``str`` object arrays as fixed-width unicode, attrs as they
  read back from JSON) and the digests the manifest records;
* :func:`write_entry`: every array of every output, written through an
  in-memory Zarr store whose keys go to a sink in slabs of :data:`SLAB_BYTES`
  (group metadata last, so a reader never sees metadata without its parents);
* :func:`read_output` / :func:`read_outputs`: outputs back as ``Encoded``;
* :func:`expected_keys` / :func:`bad_chunks`: the files an output must consist
  of, and the chunks that fail to decode (for ``verify``);
* :func:`describe_outputs`: shapes, dtypes, dims and chunks (for ``show``).

Zarr is imported inside these functions, not with the module: a run whose
tasks are all cache hits, ``plan``, ``status`` and ``stages`` never open an
entry, and importing Zarr (with fsspec) adds about 0.18 s to every such command
(0.37 s -> 0.55 s for a no-op ``mocapflow run`` of 301 tasks).
"""

from __future__ import annotations

import asyncio
import math
import warnings
from collections.abc import Iterable, Mapping
from itertools import product
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.pipeline.codecs import Encoded, digest_encoded
from mocapflow.pipeline.store_layout import StoreError, check_name

__all__ = [
    "MAX_CHUNK_BYTES",
    "SLAB_BYTES",
    "bad_chunks",
    "describe_outputs",
    "expected_keys",
    "fsspec_store",
    "local_store",
    "normalise",
    "output_digests",
    "read_output",
    "read_outputs",
    "write_entry",
]

#: Largest chunk written (bytes); rows per chunk shrink below ``chunk_frames`` to fit.
MAX_CHUNK_BYTES = 64 << 20
#: Bytes handed to Zarr per write call, and buffered before they go to storage.
SLAB_BYTES = 16 << 20
_STORABLE_KINDS = set("biufcUSMm")


# --------------------------------------------------------------------------- storable form


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


def _normalise_arrays(items: Mapping, output: str, what: str) -> dict:
    out = {}
    for name, item in items.items():
        check_name(name, f"{what} (output {output!r})")
        arr, dims = item
        a = _normalise_array(arr, f"output {output!r} {what} {name!r}")
        dims = tuple(dims)
        if len(dims) != a.ndim or not all(isinstance(d, str) and d for d in dims):
            raise ValueError(
                f"output {output!r} {what} {name!r}: dims {dims} do not name its {a.ndim} axes"
            )
        out[name] = (a, dims)
    return out


def normalise(enc: Encoded, output: str) -> Encoded:
    """The storable form of one output (raises ``TypeError`` / ``ValueError`` naming it).

    Coords are normalised like arrays; a coord named like an array, or whose
    length along a dimension differs from the arrays', is a ``ValueError``.
    """
    if not isinstance(enc, Encoded):
        raise TypeError(f"output {output!r}: expected an Encoded, got {type(enc).__name__}")
    arrays = _normalise_arrays(enc.arrays, output, "array")
    coords = _normalise_arrays(getattr(enc, "coords", None) or {}, output, "coord")
    clash = sorted(set(arrays) & set(coords))
    if clash:
        raise ValueError(f"output {output!r}: coord {clash[0]!r} has the name of an array")
    sizes: dict[str, int] = {}
    for a, dims in arrays.values():
        for d, n in zip(dims, a.shape):
            sizes.setdefault(d, n)
    for name, (a, dims) in coords.items():
        for d, n in zip(dims, a.shape):
            if sizes.setdefault(d, n) != n:
                raise ValueError(
                    f"output {output!r}: coord {name!r} has {n} along {d!r}, the arrays {sizes[d]}"
                )
    try:
        attrs = _plain_json(dict(enc.attrs))
    except TypeError as e:
        raise TypeError(f"output {output!r}: {e}") from None
    return Encoded(str(enc.type), arrays, attrs, coords)


def output_digests(outputs: Mapping[str, Encoded]) -> dict[str, str]:
    """Digests of outputs exactly as ``Store.commit`` computes and stores them.

    Arrays are normalised first (native byte order, ``str`` object arrays as
    fixed-width unicode) and attrs as they read back from JSON, so use this,
    not ``digest_encoded`` on the raw :class:`Encoded`, to compare with a manifest.
    """
    return {n: digest_encoded(normalise(e, n)) for n, e in outputs.items()}


# --------------------------------------------------------------------------- write


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
    import zarr.api.asynchronous as za  # noqa: PLC0415 (heavy)
    from zarr.codecs import ZstdCodec  # noqa: PLC0415 (heavy)
    from zarr.storage import MemoryStore  # noqa: PLC0415 (heavy)

    buffer: dict = {}
    mstore = MemoryStore(buffer)
    root = await za.open_group(store=mstore, mode="w", zarr_format=3, attributes=root_attrs)
    for out_name, enc in outputs.items():
        coords = getattr(enc, "coords", None) or {}
        meta = {"type": enc.type, "attrs": enc.attrs, "arrays": sorted(enc.arrays)}
        if coords:
            meta["coords"] = sorted(coords)
        group = await root.create_group(out_name, attributes={"mocapflow": meta})
        # non-index coords (``time`` along ``frame``): named on the data arrays (CF)
        aux = {c: set(d) for c, (_, d) in coords.items() if tuple(d) != (c,)}
        items = {**{n: (*enc.arrays[n], False) for n in sorted(enc.arrays)},
                 **{n: (*coords[n], True) for n in sorted(coords)}}
        for arr_name, (arr, dims, is_coord) in items.items():
            chunks, axis = _chunk_layout(arr.shape, dims, arr.dtype.itemsize, chunk_frames)
            named = [] if is_coord else sorted(c for c, d in aux.items() if d <= set(dims))
            attributes = {"coordinates": " ".join(named)} if named else None
            za_arr = await group.create_array(
                arr_name,
                shape=arr.shape,
                dtype=arr.dtype,
                chunks=chunks,
                dimension_names=dims if dims else None,
                attributes=attributes,
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
    for out_name in outputs:  # each output opens on its own (xarray group=output)
        await za.consolidate_metadata(mstore, path=out_name, zarr_format=3)
    await za.consolidate_metadata(mstore, zarr_format=3)
    _flush(sink, buffer, final=True)


def write_entry(
    sink: Any, outputs: Mapping[str, Encoded], root_attrs: dict, chunk_frames: int
) -> None:
    """Write a whole entry (its outputs in :func:`normalise` form) to ``sink``.

    Parameters
    ----------
    sink : KeySink
        Gets ``put_many({relative key: bytes})``; chunks go as each slab is
        written, the ``zarr.json`` documents in the last call.
    outputs : dict
        ``output name -> Encoded``.
    root_attrs : dict
        Attributes of the entry's root group.
    chunk_frames : int
        Rows per chunk along ``frame`` (see :func:`_chunk_layout`).
    """
    _ignore_zarr_notices()
    _sync(_awrite_entry(sink, outputs, root_attrs, chunk_frames))


def _ignore_zarr_notices() -> None:
    """Ignore, in the whole process, the two notices Zarr gives about what an entry holds on
    purpose: "Consolidated metadata is currently not part in the Zarr format 3
    specification" (xarray opens an output by it) and fixed-width str dtypes having "no
    Zarr V3 specification yet" (they round-trip).  In the whole process because a
    ``warnings.catch_warnings`` block cannot hold them back here: entries written from
    several threads run as coroutines on Zarr's one event-loop thread, and one block's
    exit put the filters back while another entry's write was still inside its own (the
    consolidated-metadata notice leaked now and then from
    ``test_memory_store_runs_on_the_local_cluster_as_threads``)."""
    from zarr.errors import UnstableSpecificationWarning  # noqa: PLC0415 (heavy)

    warnings.filterwarnings("ignore", message="Consolidated metadata", category=UserWarning)
    warnings.filterwarnings("ignore", category=UnstableSpecificationWarning)


# --------------------------------------------------------------------------- read


async def _aopen_output(
    zstore: Any, output: str
) -> tuple[dict, dict[str, Any], dict[str, Any]]:
    """(mocapflow attrs, ``array name -> AsyncArray``, ``coord name -> AsyncArray``)."""
    import zarr.api.asynchronous as za  # noqa: PLC0415 (heavy)

    group = await za.open_group(store=zstore, path=output, mode="r")
    meta = dict(group.attrs).get("mocapflow")
    if not isinstance(meta, dict) or "type" not in meta:
        raise StoreError(f"output {output!r}: group attrs lack the mocapflow type")
    names = list(meta.get("arrays", []))
    cnames = list(meta.get("coords", []))
    opened = await asyncio.gather(
        *(za.open_array(store=zstore, path=f"{output}/{n}", mode="r") for n in names + cnames)
    )
    return meta, dict(zip(names, opened)), dict(zip(cnames, opened[len(names):]))


async def _aread_output(zstore: Any, output: str) -> Encoded:
    """Read one output group back into an :class:`Encoded` (coords included)."""
    meta, arrays, coords = await _aopen_output(zstore, output)

    async def one(a: Any) -> np.ndarray:
        return np.asarray(await a.getitem(...)).reshape(a.shape)

    both = {**arrays, **coords}
    data = dict(zip(both, await asyncio.gather(*(one(a) for a in both.values()))))

    def pairs(items: dict) -> dict:
        return {n: (data[n], tuple(a.metadata.dimension_names or ())) for n, a in items.items()}

    return Encoded(meta["type"], pairs(arrays), meta.get("attrs", {}), pairs(coords))


def read_output(zstore: Any, output: str) -> Encoded:
    """One output of an entry (``zstore``: the entry's Zarr store)."""
    return _sync(_aread_output(zstore, output))


def read_outputs(zstore: Any, outputs: Iterable[str]) -> list[Encoded]:
    """Several outputs of an entry, read concurrently, in the order given."""

    async def all_outputs():
        return await asyncio.gather(*(_aread_output(zstore, n) for n in outputs))

    return _sync(all_outputs())


def describe_outputs(location: str, outputs: Iterable[str]) -> dict[str, dict[str, Any]]:
    """Arrays and coords (shape, dtype, dims, chunks) and attrs of outputs, reading no chunk.

    Parameters
    ----------
    location : str
        The entry's path or URL (:meth:`~mocapflow.pipeline.store.Store.entry_path`).
    outputs : iterable of str

    Returns
    -------
    dict
        ``output -> {"arrays": {name: {"shape", "dtype", "dims", "chunks"}},
        "attrs": {...}}`` (the coord arrays listed after the data arrays).
    """
    import zarr  # noqa: PLC0415 (heavy)

    group = zarr.open_group(location, mode="r")
    out = {}
    for name in outputs:
        g = group[name]
        meta = dict(g.attrs).get("mocapflow", {})
        arrays = {}
        for a_name in (*meta.get("arrays", []), *meta.get("coords", [])):
            a = g[a_name]
            arrays[a_name] = {"shape": list(a.shape), "dtype": str(a.dtype),
                              "dims": list(a.metadata.dimension_names or ()),
                              "chunks": list(a.chunks)}
        out[name] = {"arrays": arrays, "attrs": meta.get("attrs", {})}
    return out


# --------------------------------------------------------------------------- check


def _chunk_keys(output: str, name: str, a: Any) -> dict[str, tuple[slice, ...]]:
    """``relative key -> selection`` of every chunk of array ``a``."""
    out = {}
    grid = [range(math.ceil(s / c)) for s, c in zip(a.shape, a.chunks)]
    for coords in product(*grid):
        sel = tuple(slice(i * c, (i + 1) * c) for i, c in zip(coords, a.chunks))
        out[f"{output}/{name}/" + a.metadata.encode_chunk_key(tuple(coords))] = sel
    return out


def expected_keys(zstore: Any, output: str) -> set[str]:
    """Every file an output consists of (relative to the entry): metadata and all chunks.

    Raises whatever Zarr raises when the output's metadata cannot be read.
    """
    _, arrays, coords = _sync(_aopen_output(zstore, output))
    keys = {f"{output}/zarr.json"}
    for name, a in {**arrays, **coords}.items():
        keys.add(f"{output}/{name}/zarr.json")
        keys |= set(_chunk_keys(output, name, a))
    return keys


async def _abad_chunks(zstore: Any, output: str) -> list[str]:
    _, arrays, coords = await _aopen_output(zstore, output)
    bad = []
    for name, a in {**arrays, **coords}.items():
        for key, sel in _chunk_keys(output, name, a).items():
            try:
                await a.getitem(sel)
            except Exception as e:
                bad.append(f"{key} ({type(e).__name__}: {e})")
    return bad


def bad_chunks(zstore: Any, output: str) -> list[str]:
    """Chunks of an output that fail to decode: ``"<key> (<error>)"`` each."""
    return _sync(_abad_chunks(zstore, output))


# --------------------------------------------------------------------------- Zarr stores


def local_store(path: str) -> Any:
    """A read-only Zarr store on a local directory."""
    from zarr.storage import LocalStore  # noqa: PLC0415 (heavy)

    return LocalStore(path, read_only=True)


def fsspec_store(url: str, storage_options: dict | None) -> Any:
    """A read-only Zarr store on an fsspec URL."""
    from zarr.storage import FsspecStore  # noqa: PLC0415 (heavy)

    return FsspecStore.from_url(url, storage_options=storage_options, read_only=True)


def _sync(coro: Any) -> Any:
    from zarr.core.sync import sync  # noqa: PLC0415 (heavy)

    return sync(coro)
