"""What a store remembers besides entries: run records and the file-digest memo.

* ``runs/<run_id>.json``: one record per run (what ran, hit or computed,
  timings, errors with tracebacks), written atomically, read back oldest first;
  parsed records are cached by file signature, so ``plan`` and ``status`` over
  many runs re-read only what changed;
* ``cache/file_digests.json``: ``realpath -> [size, mtime_ns, inode, ctime_ns, digest]``,
  so unchanged input files are not hashed again.

:class:`~mocapflow.pipeline.store.Store` holds one :class:`RunRecords` and
exposes its methods (``write_run``, ``runs``, ``last_task_record``,
``load_file_memo``, ``save_file_memo``).
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Iterable, Mapping
from datetime import UTC, datetime
from typing import Any

from mocapflow.pipeline.store_backends import Backend
from mocapflow.pipeline.store_layout import check_name, dump_json

__all__ = ["RunRecords"]


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


class RunRecords:
    """Run records and the file memo of one store root.

    Parameters
    ----------
    backend : Backend
        The store's backend; records live under ``runs/`` and the memo under
        ``cache/`` of its root.
    """

    def __init__(self, backend: Backend) -> None:
        self.backend = backend
        self._cache: dict[str, tuple[Any, dict]] = {}
        self._lock = threading.Lock()

    def _path(self, *parts: str) -> str:
        return self.backend.join(self.backend.root, *parts)

    # ----------------------------------------------------------------- run records

    def write_run(self, run_id: str, record: Mapping[str, Any]) -> str:
        """Write (or replace) the record of a run atomically; returns its location.

        The record should carry ``started_at`` (epoch seconds or ISO time) and
        ``tasks``: a list of ``{"node", "part", "stage", "key", "components",
        "status", ...}``.
        """
        path = self._path("runs", f"{check_name(run_id, 'run id')}.json")
        rec = dict(record)
        rec.setdefault("run_id", run_id)
        self.backend.write_atomic(path, dump_json(rec, compact=True))
        return self.backend.url(path)

    def runs(self) -> list[dict]:
        """Every run record, oldest first."""
        with self._lock:
            return self._runs_locked()

    def _runs_locked(self) -> list[dict]:
        b = self.backend
        rdir = self._path("runs")
        found: list[tuple[float, str, dict]] = []
        seen = set()
        for name in b.listdir(rdir):
            if not name.endswith(".json") or name.startswith("."):
                continue
            path = b.join(rdir, name)
            sig: Any = None
            if b.is_local:
                try:
                    st = os.stat(path)
                except OSError:
                    continue
                sig = (st.st_mtime_ns, st.st_size)
            cached = self._cache.get(name)
            if sig is not None and cached is not None and cached[0] == sig:
                rec = cached[1]
            else:
                raw = b.read(path)
                try:
                    rec = json.loads(raw) if raw is not None else None
                except ValueError:
                    rec = None
                if not isinstance(rec, dict):
                    continue
                rec.setdefault("run_id", name[: -len(".json")])
                self._cache[name] = (sig, rec)
            seen.add(name)
            mtime = sig[0] / 1e9 if sig else (b.mtime(path) or 0.0)
            found.append((_run_time(rec, mtime), name, rec))
        for name in set(self._cache) - seen:
            self._cache.pop(name, None)
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
        """The persistent file-digest memo (``realpath -> [size, mtime_ns, inode, ctime_ns,
        digest]``)."""
        raw = self.backend.read(self._memo_path())
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
        self.backend.write_atomic(self._memo_path(), dump_json(merged, compact=True))
