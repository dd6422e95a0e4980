"""Progress inside tasks: ``ctx.progress`` reaches the command (sync and Dask), rate-limited,
never in a digest; rich display rows; warnings with hints printed once."""

from __future__ import annotations

import io
import re
import time

import numpy as np
import pytest

from mocapflow.pipeline import cli as cli_module
from mocapflow.pipeline import codecs
from mocapflow.pipeline.config import load_config
from mocapflow.pipeline.context import HINT_SEP, Context
from mocapflow.pipeline.executors import SyncExecutor
from mocapflow.pipeline.graph import build_graph
from mocapflow.pipeline.progress import Progress, ProgressReporter
from mocapflow.pipeline.runner import run
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.testing import write_config, write_number_files

PROG = """\
parts: ["{data}/*.txt"]
nodes:
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
  prog: {{stage: toy_progress, inputs: {{values: read.values}},
         params: {{steps: 100, seconds: {seconds}, message: "{message}", hint: "{hint}"}}}}
"""


class Recording(Progress):
    """A Progress that keeps every inner update it receives (per task, in order)."""

    runs: list[Recording] = []

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.received: dict[object, list[tuple[int, int, str]]] = {}
        Recording.runs.append(self)

    def task_progress(self, message):
        key = (message["node"], message["part"])
        self.received.setdefault(key, []).append(
            (message["done"], message["total"], message["label"]))
        super().task_progress(message)


@pytest.fixture
def recording(monkeypatch):
    Recording.runs = []
    monkeypatch.setattr(cli_module, "Progress", Recording)
    return Recording.runs


def _config(tmp_path, n=2, seconds=1.0, message="", hint=""):
    write_number_files(tmp_path / "data", n)
    return write_config(tmp_path / "p.yaml", PROG, data=tmp_path / "data", seconds=seconds,
                        message=message, hint=hint)


def _check_inner(progress: Recording, n_tasks: int) -> None:
    prog = {k: v for k, v in progress.received.items() if k[0] == "prog"}
    assert len(prog) == n_tasks, progress.received
    for updates in prog.values():
        done = [d for d, _, _ in updates]
        assert 2 <= len(updates) < 100, updates  # rate-limited, not one per call
        assert updates[-1] == (100, 100, "steps"), updates  # always the last one
        assert done == sorted(done)


def test_sync_cli_receives_rate_limited_inner_progress(cli, recording, tmp_path):
    cfg = _config(tmp_path, seconds=1.0)
    code, out, err = cli("run", cfg, "--store", tmp_path / "s", "--executor", "sync")
    assert code == 0, err
    (progress,) = recording
    _check_inner(progress, 2)
    # plain stderr (not a terminal): at most one line per task per tenth, ending at 100/100
    for name in ("trial000.txt", "trial001.txt"):
        lines = [ln for ln in err.splitlines()
                 if re.fullmatch(rf"  prog/\S+{name}: steps \d+/100", ln)]
        assert 1 <= len(lines) <= 10 and lines[-1].endswith("steps 100/100"), err
    assert progress.inner == [] or all(m["done"] == m["total"] for m in progress.inner)


def test_local_cluster_inner_progress_reaches_the_client(cli, recording, tmp_path):
    cfg = _config(tmp_path, seconds=1.0)
    code, out, err = cli("run", cfg, "--store", tmp_path / "s", "--executor", "local",
                         "--workers", "1")
    assert code == 0, err
    (progress,) = recording
    _check_inner(progress, 2)


def test_quiet_prints_no_progress(cli, recording, tmp_path):
    cfg = _config(tmp_path, seconds=0.3, message="toy says", hint="ignore it")
    code, out, err = cli("run", cfg, "--store", tmp_path / "s", "--executor", "sync", "-q")
    assert code == 0, err
    # no progress (task lines, inner lines, summary); the stage warnings stay
    assert [ln.split(":")[0] for ln in err.splitlines()] == ["warning"], err
    assert recording[0].inner_updates >= 2  # received, not shown


def test_progress_never_changes_keys_digests_or_manifests(tmp_path):
    cfg = _config(tmp_path, seconds=0.3)
    graph = build_graph(load_config(cfg))
    seen = Progress(len(graph.tasks), enabled=False)
    a, b = Store(tmp_path / "a"), Store(tmp_path / "b")
    with_progress = run(graph, a, executor=SyncExecutor(), progress=seen)
    without = run(graph, b, executor=SyncExecutor())
    assert seen.inner_updates >= 4  # the first run did report progress
    assert with_progress.digests() == without.digests()
    keys = [(r.stage, r.key) for r in with_progress.records]
    assert keys == [(r.stage, r.key) for r in without.records]
    for stage, key in keys:
        ma, mb = a.manifest(stage, key), b.manifest(stage, key)
        assert set(ma) == set(mb) and "progress" not in str(sorted(ma))


def test_warnings_with_hints_print_once_with_count_and_hint(cli, tmp_path):
    cfg = _config(tmp_path, n=3, seconds=0.0, message="toy parts are small",
                  hint="nothing; toys are small")
    code, out, err = cli("run", cfg, "--store", tmp_path / "s", "--executor", "sync")
    assert code == 0, err
    lines = [ln for ln in err.splitlines() if "toy parts are small" in ln]
    assert len(lines) == 1, err
    assert re.fullmatch(r"warning: prog/\S+trial000\.txt: toy parts are small \(×3 in 3 tasks: "
                        r"also prog/\S+, prog/\S+\) — what to do: nothing; toys are small",
                        lines[0]), lines
    assert "3 warning(s)" in err
    code, out, err = cli("run", cfg, "--store", tmp_path / "s", "--executor", "sync")
    assert code == 0 and "toy parts are small" not in err  # hits: said when computed


def test_context_warn_stores_hint_in_the_string():
    ctx = Context(part="p")
    ctx.warn("plain")
    ctx.warn("with advice", hint="do this")
    assert ctx.warnings == ["plain", f"with advice{HINT_SEP}do this"]


def test_reporter_rate_limit_last_update_and_dead_sink():
    got = []
    rep = ProgressReporter(got.append, {"index": 1}, every=3600.0)
    for i in range(1, 51):
        rep(i, 100, "x")
    assert [m["done"] for m in got] == [1]  # the rest held back
    rep.flush()
    assert [m["done"] for m in got] == [1, 50]  # the held-back last one
    rep(100, 100, "x")  # completion always goes through
    assert got[-1] == {"index": 1, "done": 100, "total": 100, "label": "x"} and rep.sent == 3

    def broken(msg):
        raise ConnectionError("no listener")

    dead = ProgressReporter(broken, {})
    dead(1, 2)
    dead(2, 2)  # no raise: progress never fails a stage
    assert dead.sent == 0 and dead.sink is None


def _last_frame(text: str) -> str:
    """The last frame the live display drew before it stopped (ANSI codes removed)."""
    body = text.rsplit("\x1b[?25h", 1)[0]
    frame = re.split(r"\r\x1b\[2K", body)[-1]
    return re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", frame)


def test_terminal_shows_a_row_per_running_task_until_it_ends():
    buf = io.StringIO()
    p = Progress(3, stream=buf, tty=True)
    p.update({"node": "read", "part": "a", "status": "hit"})
    p.task_progress({"index": 1, "node": "learn", "part": "a.bvh", "done": 7, "total": 20,
                     "label": "transition nodes"})
    p.task_progress({"index": 2, "node": "render", "part": "b.c3d", "done": 40, "total": 120,
                     "label": "frames"})
    time.sleep(0.3)  # a refresh of the live display
    mid = buf.getvalue()
    p.update({"index": 1, "node": "learn", "part": "a.bvh", "status": "computed",
              "seconds": 1.0})
    p.task_progress({"index": 1, "node": "learn", "part": "a.bvh", "done": 20, "total": 20,
                     "label": "late"})  # arrives after its task ended: ignored
    p.close()
    clean = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", mid)
    assert re.search(r"learn/a\.bvh\s+transition nodes .* 7/20", clean), clean
    assert re.search(r"render/b\.c3d\s+frames .* 40/120", clean), clean
    last = _last_frame(buf.getvalue())
    assert "render/b.c3d" in last and "learn/a.bvh" not in last, last
    assert re.search(r"\] 2/3 hit 1 computed 1 failed 0", last), last
    assert re.search(r"\n?2 tasks: 1 hit, 1 computed, 0 failed, 0 skipped in \S+\n\Z",
                     buf.getvalue())


MAP_SLEEP = """\
parts: ["{data}/*.txt"]
nodes:
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
  msl: {{stage: toy_map_sleep, inputs: {{values: read.values}},
        params: {{items: 8, seconds: 0.4}}}}
"""


def test_local_cluster_ctx_map_reports_items_as_they_complete(cli, recording, tmp_path):
    write_number_files(tmp_path / "data", 1)
    cfg = write_config(tmp_path / "m.yaml", MAP_SLEEP, data=tmp_path / "data")
    code, out, err = cli("run", cfg, "--store", tmp_path / "s", "--executor", "local",
                         "--workers", "2")
    assert code == 0, err
    (progress,) = recording
    ((key, updates),) = [(k, v) for k, v in progress.received.items() if k[0] == "msl"]
    done = [d for d, _, _ in updates]
    assert {t for _, t, _ in updates} == {8} and {lb for _, _, lb in updates} == {"items"}
    assert any(0 < d < 8 for d in done), updates  # not only 0/8 then 8/8
    assert done == sorted(done) and updates[-1] == (8, 8, "items"), updates
    store = Store(tmp_path / "s")
    (entry,) = [k for s, k in store.entries() if s == "toy_map_sleep"]
    values = codecs.decode(store.load("toy_map_sleep", entry, "values"))
    np.testing.assert_array_equal(values, np.arange(8) ** 2)  # item order


def test_context_map_passes_on_done_to_a_mapper_that_takes_it():
    got = []

    def mapper(fn, items, *, on_done=None):
        out = [fn(x) for x in items]
        for i in reversed(range(len(items))):  # completion order differs from item order
            on_done(i)
        return out

    ctx = Context(mapper=mapper, progress_hook=lambda d, t, lb: got.append((d, t)))
    assert ctx.map(abs, [-1, -2, -3], progress="x") == [1, 2, 3]
    assert got == [(0, 3), (1, 3), (2, 3), (3, 3)]
    got.clear()
    plain = Context(mapper=lambda fn, items: [fn(x) for x in items],
                    progress_hook=lambda d, t, lb: got.append((d, t)))
    assert plain.map(abs, [-1, -2], progress="x") == [1, 2]
    assert got == [(0, 2), (2, 2)]  # a two-argument mapper: start and end only
