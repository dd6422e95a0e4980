"""Keeping a store sound: verify entries, tell live writers from debris, collect garbage.

* :func:`verify` re-reads committed entries and compares them with their
  manifests (Zarr reads a missing chunk back as the fill value without error,
  so only the digests tell), and reports symlinks and special files in the
  entry tree without reading through them;
* :func:`writer_info` is the ``_WRITER.json`` a writer leaves in the directory
  it is filling; :func:`writer_alive` and :func:`debris_verdict` decide from it
  (or from the directory's age) whether that directory is debris;
* :func:`gc` removes staging debris, half-written in-place entries and, given a
  keep set, committed entries nobody needs any more.

:meth:`Store.verify <mocapflow.pipeline.store.Store.verify>` and
:meth:`Store.gc <mocapflow.pipeline.store.Store.gc>` call these.
"""

from __future__ import annotations

import json
import os
import socket
import time
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

from mocapflow.pipeline import store_zarr
from mocapflow.pipeline.codecs import digest_encoded
from mocapflow.pipeline.store_layout import MANIFEST, WRITER

if TYPE_CHECKING:  # the store calls this module; annotations only
    from mocapflow.pipeline.store import Store

__all__ = ["debris_verdict", "gc", "verify", "verify_entry", "writer_alive", "writer_info"]


# --------------------------------------------------------------------------- writers


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


def writer_info() -> dict[str, Any]:
    """What a writer records about itself: ``pid``, ``host``, ``started``, ``proc_start``."""
    pid = os.getpid()
    return {
        "pid": pid,
        "host": socket.gethostname(),
        "started": time.time(),
        "proc_start": _proc_start(pid),
    }


def writer_alive(info: Mapping[str, Any]) -> bool | None:
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


def debris_verdict(store: Store, path: str, min_age: float, now: float) -> bool:
    """Whether a staging dir / manifest-less entry dir may be removed.

    Its writer alive on this host: no; dead on this host: yes; unknown (another
    host, no readable ``_WRITER.json``): once older than ``min_age`` seconds.
    """
    b = store.backend
    raw = b.read(b.join(path, WRITER))
    info = None
    if raw is not None:
        try:
            info = json.loads(raw)
        except ValueError:
            info = None
    if isinstance(info, dict):
        alive = writer_alive(info)
        if alive is True:
            return False
        if alive is False:
            return True
        started = info.get("started")
        if isinstance(started, (int, float)):
            return now - started >= min_age
    mtime = b.mtime(path)
    return mtime is None or now - mtime >= min_age


# --------------------------------------------------------------------------- verify


def verify(store: Store, *, entries: Iterable[tuple[str, str]] | None = None) -> list[str]:
    """Problems of committed entries, one line each (see :meth:`Store.verify`).

    With every entry (``entries`` not given), symlinks where the store keeps
    directories (``entries/``, a stage directory, an entry directory) are
    problems too: such entries are not committed and never read.
    """
    problems: list[str] = []
    if entries is None:
        problems.extend(_linked_dirs(store))
        entries = store.entries()
    for stage, key in entries:
        problems.extend(verify_entry(store, stage, key))
    return problems


def _linked_dirs(store: Store) -> list[str]:
    """``entries/``, stage and entry directories that are symlinks (local roots)."""
    if not store.is_local:
        return []
    base = store.location("entries")
    if os.path.islink(base):
        return [f"entries/ is a symlink to {os.readlink(base)} (not followed)"]
    out = []
    for stage in store.backend.listdir(base):
        sd = os.path.join(base, stage)
        if os.path.islink(sd):
            out.append(f"entries/{stage} is a symlink to {os.readlink(sd)} (not followed)")
            continue
        for key in store.backend.listdir(sd):
            if os.path.islink(os.path.join(sd, key)):
                out.extend(store.odd_paths(stage, key))
    return out


def verify_entry(store: Store, stage: str, key: str) -> list[str]:
    """Problems of one entry: not committed, misnamed, unreadable, corrupt, missing/extra files.

    An entry holding a symlink or a special file is reported (each such file)
    and not read.
    """
    where = f"{stage}/{key}"
    odd = store.odd_paths(stage, key)
    man = store.manifest(stage, key)
    if man is None:
        return odd or [f"{where}: not committed (no readable {MANIFEST})"]
    if odd:
        return odd
    problems = []
    if man.get("stage") != stage or man.get("key") != key:
        problems.append(
            f"{where}: manifest names {man.get('stage')}/{man.get('key')} instead"
        )
    b = store.backend
    entry = store.entry_location(stage, key)
    zstore = b.zarr_store(entry)
    expected = {MANIFEST, "zarr.json"}
    for out, info in sorted(man["outputs"].items()):
        try:
            expected |= store_zarr.expected_keys(zstore, out)
        except Exception as e:  # metadata unreadable: cannot tell which files belong
            problems.append(f"{where}/{out}: metadata unreadable ({type(e).__name__}: {e})")
            expected |= {f"{out}/{f}" for f in b.find(b.join(entry, out))}
            continue
        try:
            enc = store_zarr.read_output(zstore, out)
        except Exception as e:  # name the chunks that do not decode
            bad = store_zarr.bad_chunks(zstore, out)
            problems.extend(f"{where}: corrupt chunk {c}" for c in bad)
            if not bad:
                problems.append(f"{where}/{out}: unreadable ({type(e).__name__}: {e})")
            continue
        got = digest_encoded(enc)
        if got != info.get("digest"):
            problems.append(
                f"{where}/{out}: digest mismatch (manifest {str(info.get('digest'))[:12]}.., "
                f"data {got[:12]}..): corrupted or missing chunks"
            )
    files = set(b.find(entry))
    for f in sorted(expected - files):
        problems.append(f"{where}: missing file {f}")
    for f in sorted(files - expected):
        problems.append(f"{where}: unexpected file {f}")
    return problems


# --------------------------------------------------------------------------- gc


def gc(
    store: Store,
    *,
    keep: set[tuple[str, str]] | None = None,
    dry_run: bool = False,
    staging_min_age_s: float = 0.0,
) -> dict:
    """Remove debris and, given ``keep``, unreachable entries (see :meth:`Store.gc`)."""
    now = time.time()
    report: dict[str, Any] = {
        "staging": [],
        "incomplete": [],
        "unreachable": [],
        "bytes": 0,
        "dry_run": dry_run,
    }
    _sweep_staging(store, report, staging_min_age_s, now, dry_run)
    _sweep_entries(store, report, keep, staging_min_age_s, now, dry_run)
    return report


def _sweep_staging(store: Store, report: dict, min_age: float, now: float, dry_run: bool
                   ) -> None:
    """Staging directories of dead (or long-unknown) writers go."""
    b = store.backend
    sdir = store.location("staging")
    for name in b.listdir(sdir):
        path = b.join(sdir, name)
        if not b.isdir(path):
            continue
        if debris_verdict(store, path, min_age, now):
            report["staging"].append(b.url(path))
            report["bytes"] += b.du(path)
            if not dry_run:
                b.rmtree(path)


def _sweep_entries(store: Store, report: dict, keep: set[tuple[str, str]] | None,
                   min_age: float, now: float, dry_run: bool) -> None:
    """Entry dirs without a manifest (debris) go, and committed ones not in ``keep``."""
    b = store.backend
    base = store.location("entries")
    for stage in b.subdirs(base) if b.real_dir(base) else ():
        sd = b.join(base, stage)
        for key in b.listdir(sd):
            path = b.join(sd, key)
            if b.is_local and os.path.islink(path):
                bucket = "incomplete"  # a symlink where an entry belongs: the link goes
            elif store.manifest_at(path) is None:
                if not debris_verdict(store, path, min_age, now):
                    continue
                bucket = "incomplete"
            elif keep is not None and (stage, key) not in keep:
                bucket = "unreachable"
            else:
                continue
            report[bucket].append(b.url(path))
            report["bytes"] += b.du(path)
            if not dry_run:
                store.discard(path)
        if not dry_run and b.is_local:
            try:
                os.rmdir(sd)  # only when empty
            except OSError:
                pass
