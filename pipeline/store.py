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

**A store that cannot be written can still be read.**  Every failure of the
filesystem (full disk, read-only mount, no permission) is a
:class:`~mocapflow.pipeline.store_layout.StoreAccessError`, one line naming the
store root and what it was doing; reading committed entries, plans and run
records writes nothing, and the run record itself is best-effort
(:meth:`Store.write_run` logs one warning when it cannot be written).

**Nothing below a local root is read through a symlink.**  An entry whose
directory (or stage directory) is a symlink is not committed; one holding a
symlink or a special file (FIFO, device) is refused by :meth:`Store.load` and
reported by :meth:`Store.verify` (:meth:`Store.odd_paths`).

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

import contextlib
import errno
import json
import logging
import os
import shutil
import stat
import uuid
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

from mocapflow.pipeline import store_maintenance
from mocapflow.pipeline.codecs import Encoded, digest_encoded
from mocapflow.pipeline.store_backends import Backend, FsspecBackend, KeySink, LocalBackend
from mocapflow.pipeline.store_layout import (
    FORMAT,
    MANIFEST,
    WRITER,
    EntryNotFoundError,
    StoreAccessError,
    StoreError,
    access_error,
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

__all__ = ["EntryNotFoundError", "Store", "StoreAccessError", "StoreError", "output_digests"]

log = logging.getLogger("mocapflow")


def _real_dir(path: str) -> bool:
    return os.path.isdir(path) and not os.path.islink(path)


def _parse_manifest(data: bytes | None) -> dict | None:
    """A manifest document, or ``None`` when missing or not one."""
    if data is None:
        return None
    try:
        man = json.loads(data)
    except ValueError:
        return None
    if not isinstance(man, dict) or not isinstance(man.get("outputs"), dict):
        return None
    return man


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
        Passed to fsspec for URL roots (endpoint, credentials, ...; see
        :func:`~mocapflow.pipeline.store_backends.parse_storage_options`).  They
        travel with the store to Dask workers and never enter a cache key, a
        digest, a manifest or a run record.

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
        self._real_stages: set[str] = set()  # stage dirs seen to be real directories

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

    def probe(self) -> None:
        """Reach the root once (a URL root: its endpoint, options and bucket).

        Raises
        ------
        StoreAccessError
            One line naming the store, e.g. a bucket that does not exist or an
            endpoint that cannot be reached.  A root not created yet is fine.
        """
        with self._io("opening the store"):
            self.backend.probe()

    def location(self, *parts: str) -> str:
        """Backend path of ``parts`` under the root (``location("staging")``)."""
        return self.backend.join(self.backend.root, *parts)

    def entry_location(self, stage: str, key: str) -> str:
        """Backend path of an entry's directory (names checked)."""
        return self.location("entries", check_name(stage, "stage"), check_name(key, "key"))

    def entry_path(self, stage: str, key: str) -> str:
        """Location of an entry's Zarr group (local path or URL)."""
        return self.backend.url(self.entry_location(stage, key))

    @contextlib.contextmanager
    def _io(self, what: str) -> Iterator[None]:
        """Filesystem failures inside become one-line :class:`StoreAccessError` naming the store."""
        try:
            yield
        except StoreError:
            raise
        except OSError as e:
            raise access_error(self.root, e, what) from e

    # ----------------------------------------------------------------- entries

    def manifest(self, stage: str, key: str) -> dict | None:
        """The entry's manifest, or ``None`` if it is not committed.

        An entry whose directory, or a directory above it in the store, is a
        symlink is not committed (it is not followed).
        """
        entry = self.entry_location(stage, key)
        b = self.backend
        try:  # (no context manager: this is the cache check of every task)
            if b.is_local:
                if stage not in self._real_stages:  # entries/ and entries/<stage>, once
                    if not b.real_dir(os.path.dirname(entry)):
                        return None
                    self._real_stages.add(stage)
                if not stat.S_ISDIR(os.lstat(entry).st_mode):
                    return None
            data = b.read(b.join(entry, MANIFEST))
        except (FileNotFoundError, NotADirectoryError):
            return None
        except OSError as e:
            raise access_error(self.root, e, f"reading entry {stage}/{key}") from e
        return _parse_manifest(data)

    def manifest_at(self, path: str) -> dict | None:
        """The manifest in the entry directory ``path`` (``None``: missing or unreadable)."""
        with self._io(f"reading {MANIFEST}"):
            return _parse_manifest(self.backend.read(self.backend.join(path, MANIFEST)))

    def has(self, stage: str, key: str) -> bool:
        """Whether the entry is committed (its manifest exists and parses)."""
        return self.manifest(stage, key) is not None

    def entries(self) -> list[tuple[str, str]]:
        """Every committed ``(stage, key)``, sorted (symlinked directories are not entries)."""
        b = self.backend
        out = []
        base = self.location("entries")
        with self._io("listing entries"):
            if not b.real_dir(base):
                return []
            for stage in b.subdirs(base):
                for key in b.subdirs(b.join(base, stage)):
                    if b.is_file(b.join(base, stage, key, MANIFEST)):
                        out.append((stage, key))
        return out

    def odd_paths(self, stage: str, key: str) -> list[str]:
        """What the store will not read through in an entry, one line each.

        Returns
        -------
        list of str
            ``"STAGE/KEY: ... is a symlink to TARGET (not followed)"`` for a
            symlinked entry directory (or ``entries/`` / stage directory above
            it), and for each symlink or special file (FIFO, device, socket)
            inside the entry.  Empty for fsspec roots and sound entries.
        """
        b = self.backend
        if not b.is_local:
            return []
        where = f"{stage}/{key}"
        entry = self.entry_location(stage, key)
        with self._io(f"reading entry {where}"):
            for d, name in ((self.location("entries"), "entries/"),
                            (os.path.dirname(entry), f"entries/{stage}/"),
                            (entry, "the entry directory")):
                if os.path.islink(d):
                    return [f"{where}: {name} is a symlink to {os.readlink(d)} (not followed)"]
            return [f"{where}: {rel} is {what} (not followed)" for rel, what in b.odd_files(entry)]

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
        with self._io(f"writing entry {stage}/{key}"):
            if not self._atomic:
                self._write_in_place(entry, encs, root_attrs, body)
                return digests
            return self._write_staged(stage, key, entry, encs, root_attrs, body, digests)

    def _write_in_place(self, entry: str, encs: Mapping[str, Encoded], root_attrs: dict,
                        body: bytes) -> None:
        """Arrays straight into the entry directory, then the manifest (fsspec roots)."""
        b = self.backend
        if b.is_local:  # (a local root written in place: never through a symlink)
            self._entry_parent(entry)
            if os.path.islink(entry) or (os.path.lexists(entry) and not os.path.isdir(entry)):
                os.unlink(entry)
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
            self._entry_parent(entry)
            return self._publish(staging, entry, stage, key, digests)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise

    def _entry_parent(self, entry: str) -> None:
        """Make ``entries/<stage>/``, refusing to write through a symlink on the way."""
        parent = os.path.dirname(entry)
        for d in (self.location("entries"), parent):
            if os.path.islink(d):
                raise StoreError(f"store {self.root}: {os.path.relpath(d, self.root)} is a "
                                 f"symlink to {os.readlink(d)}; not writing through it (replace "
                                 "it by a directory)")
        os.makedirs(parent, exist_ok=True)

    def _publish(self, staging: str, entry: str, stage: str, key: str, digests: dict) -> dict:
        """Rename a complete staging directory into place; a lost race keeps the winner.

        A symlink (or file) where the entry belongs is removed first (the link
        only, never what it points to).
        """
        if os.path.islink(entry) or (os.path.lexists(entry) and not os.path.isdir(entry)):
            os.unlink(entry)
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
                self._entry_parent(entry)  # stage dir gc'd meanwhile
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
        if b.is_local and os.path.lexists(path) and not _real_dir(path):
            b.remove(path)  # a symlink (the link only, never its target) or a stray file
        elif b.is_local:
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
        with self._io(f"removing entry {stage}/{key}"):
            there = os.path.lexists(entry) if self.is_local else self.backend.exists(entry)
            if there:
                self.discard(entry)
        return there

    def require(self, stage: str, key: str) -> dict:
        """The manifest of an entry that may be read (committed, no symlink or special file in it).

        Raises
        ------
        EntryNotFoundError
            Not committed (the message says why when the entry directory is a symlink).
        StoreError
            The entry holds a symlink or a special file.
        """
        man = self.manifest(stage, key)
        if man is None:
            odd = self.odd_paths(stage, key)
            raise EntryNotFoundError(
                f"no committed entry {stage}/{key} in store {self.root} "
                + (f"({odd[0].split(': ', 1)[1]})" if odd else
                   f"(expected {self.entry_path(stage, key)}/{MANIFEST})")
            )
        odd = self.odd_paths(stage, key)
        if odd:
            more = f" and {len(odd) - 1} more" if len(odd) > 1 else ""
            raise StoreError(f"entry {odd[0]}{more}; refusing to read it from store {self.root} "
                             "(mocapflow verify lists every such file)")
        return man

    def load(self, stage: str, key: str, output: str) -> Encoded:
        """Read one output of a committed entry."""
        man = self.require(stage, key)
        if output not in man["outputs"]:
            raise EntryNotFoundError(
                f"entry {stage}/{key} has no output {output!r} "
                f"(it has {', '.join(sorted(man['outputs'])) or 'none'})"
            )
        with self._io(f"reading entry {stage}/{key}"):
            return read_output(self.backend.zarr_store(self.entry_location(stage, key)), output)

    def load_outputs(self, stage: str, key: str) -> dict[str, Encoded]:
        """Read every output of a committed entry."""
        man = self.require(stage, key)
        names = sorted(man["outputs"])
        with self._io(f"reading entry {stage}/{key}"):
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
            not match the manifest, and symlinks or special files in the
            entry tree (:meth:`odd_paths`; such an entry is not read).  Staging
            debris is not a problem (see :meth:`gc`).
        """
        with self._io("verifying entries"):
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
        with self._io("collecting garbage"):
            return store_maintenance.gc(self, keep=keep, dry_run=dry_run,
                                        staging_min_age_s=staging_min_age_s)

    # ----------------------------------------------------------------- run records

    def write_run(self, run_id: str, record: Mapping[str, Any], *,
                  required: bool = False) -> str | None:
        """Write (or replace) the record of a run atomically; returns its location.

        See :meth:`RunRecords.write_run <mocapflow.pipeline.store_runs.RunRecords.write_run>`.

        Parameters
        ----------
        run_id : str
        record : mapping
        required : bool
            Raise :class:`StoreAccessError` when the record cannot be written.
            By default the record is best-effort: a store that cannot be
            written (read-only, full) logs one warning and returns ``None``, so
            a run whose every task was a hit still succeeds there, and a task's
            own write failure is what the run reports.
        """
        try:
            with self._io(f"writing the run record runs/{run_id}.json"):
                return self._records.write_run(run_id, record)
        except StoreAccessError as e:
            if required:
                raise
            log.warning("run record not written: %s", e)
            return None

    def has_run(self, run_id: str) -> bool:
        """Whether the record of run ``run_id`` is in the store (``False`` if unknowable)."""
        try:
            return self.backend.is_file(self.location("runs", f"{check_name(run_id, 'run id')}"
                                                               ".json"))
        except OSError:
            return False

    def runs(self) -> list[dict]:
        """Every run record, oldest first."""
        with self._io("reading run records"):
            return self._records.runs()

    def last_task_record(
        self, node: str, part: str | None, *, statuses: Iterable[str] | None = None
    ) -> dict | None:
        """The most recent task record of ``(node, part)`` over all runs (with ``run_id``).

        See :meth:`RunRecords.last_task_record
        <mocapflow.pipeline.store_runs.RunRecords.last_task_record>`.
        """
        with self._io("reading run records"):
            return self._records.last_task_record(node, part, statuses=statuses)

    def load_file_memo(self) -> dict:
        """The persistent file-digest memo (``realpath -> [size, mtime_ns, inode, digest]``)."""
        with self._io("reading the file-digest memo"):
            return self._records.load_file_memo()

    def save_file_memo(self, memo: Mapping[str, Any]) -> None:
        """Merge ``memo`` into the persistent memo (atomic replace).

        Raises
        ------
        StoreAccessError
            The store cannot be written (an ``OSError``: the memo is a cache,
            callers may ignore it).
        """
        with self._io("writing the file-digest memo cache/file_digests.json"):
            self._records.save_file_memo(memo)
