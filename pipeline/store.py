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

This module holds :class:`Store` (addressing, commit and publish, manifests,
loading); the rest of the store lives in:

* :mod:`~mocapflow.pipeline.store_layout`: reserved names, name rules, errors,
  JSON documents;
* :mod:`~mocapflow.pipeline.store_backends`: the :class:`Backend` protocol, local
  directories and fsspec filesystems;
* :mod:`~mocapflow.pipeline.store_zarr`: Zarr I/O of entries (normalise, chunk,
  write, read, check chunks);
* :mod:`~mocapflow.pipeline.store_maintenance`: verify, writer liveness, gc;
* :mod:`~mocapflow.pipeline.store_runs`: run records and the file-digest memo.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import uuid
from collections.abc import Iterable, Mapping
from typing import Any

from mocapflow.pipeline import store_maintenance
from mocapflow.pipeline.codecs import Encoded, digest_encoded
from mocapflow.pipeline.store_backends import Backend, FsspecBackend, KeySink, LocalBackend
from mocapflow.pipeline.store_layout import (
    FORMAT,
    MANIFEST,
    WRITER,
    EntryNotFoundError,
    StoreError,
    check_name,
    dump_json,
    now_iso,
)
from mocapflow.pipeline.store_runs import RunRecords
from mocapflow.pipeline.store_zarr import (
    normalise,
    output_digests,
    read_output,
    read_outputs,
    write_entry,
)

__all__ = ["EntryNotFoundError", "Store", "StoreError", "output_digests"]

log = logging.getLogger("mocapflow")


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

    Attributes
    ----------
    root : str
        Absolute local path, or the URL as given.
    backend : Backend
        Storage operations on the root (:mod:`~mocapflow.pipeline.store_backends`).

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
            self.backend: Backend = FsspecBackend(text, storage_options)
            self.root = text
            self._atomic = False
        else:
            path = os.path.abspath(os.path.expanduser(text))
            self.backend = LocalBackend(path)
            self.root = path
            self._atomic = True if atomic_rename is None else bool(atomic_rename)
        self._records = RunRecords(self.backend)

    # ----------------------------------------------------------------- basics

    @property
    def is_local(self) -> bool:
        """Whether the root is a directory on this machine's filesystem."""
        return self.backend.is_local

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

    def location(self, *parts: str) -> str:
        """Backend path of ``parts`` under the root (``location("staging")``)."""
        return self.backend.join(self.backend.root, *parts)

    def entry_location(self, stage: str, key: str) -> str:
        """Backend path of an entry's directory (names checked)."""
        return self.location("entries", check_name(stage, "stage"), check_name(key, "key"))

    def entry_path(self, stage: str, key: str) -> str:
        """Location of an entry's Zarr group (local path or URL)."""
        return self.backend.url(self.entry_location(stage, key))

    # ----------------------------------------------------------------- entries

    def manifest(self, stage: str, key: str) -> dict | None:
        """The entry's manifest, or ``None`` if it is not committed."""
        return self.manifest_at(self.entry_location(stage, key))

    def manifest_at(self, path: str) -> dict | None:
        """The manifest in the entry directory ``path`` (``None``: missing or unreadable)."""
        data = self.backend.read(self.backend.join(path, MANIFEST))
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
        b = self.backend
        out = []
        base = self.location("entries")
        for stage in b.listdir(base):
            for key in b.listdir(b.join(base, stage)):
                if b.exists(b.join(base, stage, key, MANIFEST)):
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
        entry = self.entry_location(stage, key)
        existing = self.manifest(stage, key)
        if existing is not None:
            return {k: v["digest"] for k, v in existing["outputs"].items()}
        encs = {check_name(n, "output"): normalise(e, n) for n, e in outputs.items()}
        digests = {n: digest_encoded(e) for n, e in encs.items()}
        full = dict(manifest)
        full.update(
            stage=stage,
            key=key,
            outputs={n: {"digest": digests[n], "type": encs[n].type} for n in encs},
            committed_at=now_iso(),
            format=FORMAT,
        )
        body = dump_json(full)
        root_attrs = {"mocapflow": {"stage": stage, "key": key, "format": FORMAT}}
        if not self._atomic:
            self._write_in_place(entry, encs, root_attrs, body)
            return digests
        return self._write_staged(stage, key, entry, encs, root_attrs, body, digests)

    def _write_in_place(self, entry: str, encs: Mapping[str, Encoded], root_attrs: dict,
                        body: bytes) -> None:
        """Arrays straight into the entry directory, then the manifest (fsspec roots)."""
        b = self.backend
        w = b.join(entry, WRITER)
        b.write(w, dump_json(store_maintenance.writer_info()))
        try:
            write_entry(KeySink(b, entry), encs, root_attrs, self.chunk_frames)
        finally:
            b.remove(w)  # on failure the debris is gc's (a live writer's is kept)
        b.write(b.join(entry, MANIFEST), body)

    def _write_staged(self, stage: str, key: str, entry: str, encs: Mapping[str, Encoded],
                      root_attrs: dict, body: bytes, digests: dict) -> dict:
        """Arrays and manifest into a fresh staging directory, then publish it."""
        b = self.backend
        staging = self.location("staging", f"{stage}-{key}-{uuid.uuid4().hex[:12]}")
        try:
            os.makedirs(staging)
            w = os.path.join(staging, WRITER)
            b.write(w, dump_json(store_maintenance.writer_info()))
            write_entry(KeySink(b, staging), encs, root_attrs, self.chunk_frames)
            os.unlink(w)
            b.write(os.path.join(staging, MANIFEST), body)
            os.makedirs(os.path.dirname(entry), exist_ok=True)
            return self._publish(staging, entry, stage, key, digests)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise

    def _publish(self, staging: str, entry: str, stage: str, key: str, digests: dict) -> dict:
        """Rename a complete staging directory into place; a lost race keeps the winner."""
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
            self.discard(entry)  # a broken directory without a manifest
        raise StoreError(f"could not publish entry {stage}/{key} at {entry}")

    def discard(self, path: str) -> None:
        """Remove a directory so that it disappears at once (local: rename, then delete)."""
        b = self.backend
        if b.is_local:
            trash = self.location("staging", f"trash-{uuid.uuid4().hex[:12]}")
            os.makedirs(os.path.dirname(trash), exist_ok=True)
            try:
                os.rename(path, trash)
            except FileNotFoundError:
                return
            shutil.rmtree(trash, ignore_errors=True)
        else:
            b.remove(b.join(path, MANIFEST))
            b.rmtree(path)

    def delete(self, stage: str, key: str) -> bool:
        """Remove a committed entry; True if there was one."""
        entry = self.entry_location(stage, key)
        if not self.backend.exists(entry):
            return False
        self.discard(entry)
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
        return read_output(self.backend.zarr_store(self.entry_location(stage, key)), output)

    def load_outputs(self, stage: str, key: str) -> dict[str, Encoded]:
        """Read every output of a committed entry."""
        man = self._require(stage, key)
        names = sorted(man["outputs"])
        zstore = self.backend.zarr_store(self.entry_location(stage, key))
        return dict(zip(names, read_outputs(zstore, names)))

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
        return store_maintenance.verify(self, entries=entries)

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
        return store_maintenance.gc(self, keep=keep, dry_run=dry_run,
                                    staging_min_age_s=staging_min_age_s)

    # ----------------------------------------------------------------- run records

    def write_run(self, run_id: str, record: Mapping[str, Any]) -> str:
        """Write (or replace) the record of a run atomically; returns its location.

        See :meth:`RunRecords.write_run <mocapflow.pipeline.store_runs.RunRecords.write_run>`.
        """
        return self._records.write_run(run_id, record)

    def runs(self) -> list[dict]:
        """Every run record, oldest first."""
        return self._records.runs()

    def last_task_record(
        self, node: str, part: str | None, *, statuses: Iterable[str] | None = None
    ) -> dict | None:
        """The most recent task record of ``(node, part)`` over all runs (with ``run_id``).

        See :meth:`RunRecords.last_task_record
        <mocapflow.pipeline.store_runs.RunRecords.last_task_record>`.
        """
        return self._records.last_task_record(node, part, statuses=statuses)

    def load_file_memo(self) -> dict:
        """The persistent file-digest memo (``realpath -> [size, mtime_ns, inode, digest]``)."""
        return self._records.load_file_memo()

    def save_file_memo(self, memo: Mapping[str, Any]) -> None:
        """Merge ``memo`` into the persistent memo (atomic replace)."""
        self._records.save_file_memo(memo)
