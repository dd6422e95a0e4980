"""Every shipped graph is reproduced: ``lock`` on one store, ``run --frozen`` elsewhere.

Each graph (skin ``clean`` on two shared C3Ds, texture, variation, pen strokes and
the demo) is locked on one store, from the repository, with one executor and BLAS
thread count, then run ``--frozen`` on a fresh store from another working
directory with the other executor and thread count:

========  ==========================================  ===========================
graph     lock (cwd: the repository)                  frozen (cwd: a temp folder)
========  ==========================================  ===========================
configs   ``--executor sync``, BLAS 2 threads         ``--executor local --workers
                                                      1``, BLAS 1 thread
demo      the demo's own run: ``local``, BLAS 1       ``sync``, BLAS 2 threads
========  ==========================================  ===========================

(Dask's worker processes start with one BLAS thread, so the thread count is
varied on the in-process side.)  Exit 0 of ``--frozen`` means every key and
every output digest matched the lock.  The same runs also show that ``--force``
of unchanged tasks keeps their digests without a warning, and that a changed
input makes ``--frozen`` fail with one line.  The commands run in two lanes at
once (about 4 min on 2 cores); the demo's first run is the one ``test_demo.py``
checks.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = (REPO / ".." / "shared" / "data").resolve()
C3DS = ("pyomeca_markers_analogs.c3d", "ezc3d-testFiles_Qualisys.c3d")
MOCAPFLOW = [sys.executable, "-m", "mocapflow"]
#: The shipped config graphs (``clean``: the skin graph's clean target on :data:`C3DS`).
GRAPHS = ("clean", "texture", "variation", "strokes")


@dataclass
class Ran:
    """One command of a lane."""

    name: str
    argv: list[str]
    cwd: Path
    proc: subprocess.CompletedProcess
    seconds: float


def _env(threads: int) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("MOCAPFLOW_STORE", "MOCAPFLOW_DATA")}
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env[var] = str(threads)
    return env


class Lanes:
    """Commands in named lanes; each lane runs in order, the lanes at the same time."""

    def __init__(self) -> None:
        self.lanes: list[list[Callable[[], None]]] = [[], []]
        self.ran: dict[str, Ran] = {}

    def cmd(self, lane: int, name: str, argv: list, *, cwd: Path, threads: int) -> None:
        argv = [str(a) for a in argv]

        def go() -> None:
            t0 = time.perf_counter()
            proc = subprocess.run(argv, cwd=cwd, env=_env(threads), capture_output=True,
                                  text=True, timeout=1500)
            self.ran[name] = Ran(name, argv, cwd, proc, time.perf_counter() - t0)

        self.lanes[lane].append(go)

    def call(self, lane: int, fn: Callable[[], None]) -> None:
        self.lanes[lane].append(fn)

    def run(self) -> None:
        threads = [threading.Thread(target=lambda steps=steps: [s() for s in steps])
                   for steps in self.lanes]
        for t in threads:
            t.start()
        for t in threads:
            t.join()


def _config_commands(lanes: Lanes, base: Path, elsewhere: Path, locks: Path) -> None:
    data = base / "data"
    data.mkdir()
    for name in C3DS:
        shutil.copy(SHARED / "c3d" / name, data / name)
    configs = {"clean": "skin.yaml", "texture": "texture.yaml", "variation": "variation.yaml",
               "strokes": "variation_strokes.yaml"}

    def extra(graph: str, cwd: Path) -> list[str]:
        if graph != "clean":
            return []
        parts = [a for n in C3DS for a in ("--parts", os.path.relpath(data / n, cwd))]
        return ["--target", "clean", *parts]

    def lock(lane: int, graph: str) -> None:
        lanes.cmd(lane, f"{graph}.lock",
                  [*MOCAPFLOW, "lock", f"configs/{configs[graph]}", *extra(graph, REPO),
                   "--lock", locks / f"{graph}.lock.json", "--store", base / "s1",
                   "--executor", "sync", "-q"], cwd=REPO, threads=2)

    def frozen(lane: int, graph: str, name: str | None = None, store: str = "s2") -> None:
        lanes.cmd(lane, name or f"{graph}.frozen",
                  [*MOCAPFLOW, "run", REPO / "configs" / configs[graph], *extra(graph, elsewhere),
                   "--frozen", "--lock", locks / f"{graph}.lock.json", "--store", base / store,
                   "--executor", "local", "--workers", "1", "-q"], cwd=elsewhere, threads=1)

    def force(lane: int, graph: str, node: str) -> None:
        lanes.cmd(lane, f"{graph}.force",
                  [*MOCAPFLOW, "run", f"configs/{configs[graph]}", *extra(graph, REPO),
                   "--force", node, "--store", base / "s1", "--executor", "sync", "-q"],
                  cwd=REPO, threads=2)

    lock(0, "texture")
    frozen(0, "texture")
    lock(1, "variation")
    frozen(1, "variation")
    lock(1, "strokes")
    force(1, "strokes", "learn")  # learn's model carried its timings before
    frozen(1, "strokes")
    lock(0, "clean")
    force(0, "clean", "clean")  # so did clean's report
    frozen(0, "clean")
    changed = data / C3DS[1]
    lanes.call(0, lambda: changed.write_bytes(changed.read_bytes() + b"\0"))
    frozen(0, "clean", "clean.changed", store="s3")


@pytest.fixture(scope="module")
def shipped(tmp_path_factory, demo_run) -> dict[str, Ran]:
    """Lock and frozen runs of every shipped graph (see the module docstring)."""
    base = tmp_path_factory.mktemp("shipped")
    elsewhere = base / "elsewhere"
    elsewhere.mkdir()
    locks = base / "locks"
    lanes = Lanes()
    driver = REPO / "tests" / "frozen_demo.py"
    if demo_run.proc.returncode == 0:
        lanes.cmd(0, "demo.lock", [sys.executable, driver, "lock", "--out", demo_run.out,
                                   "--store", demo_run.out / "store", "--locks", locks / "demo"],
                  cwd=REPO, threads=1)
        lanes.cmd(0, "demo.frozen", [sys.executable, driver, "frozen", "--out", demo_run.out,
                                     "--store", base / "s_demo", "--locks", locks / "demo",
                                     "--executor", "sync"], cwd=elsewhere, threads=2)
    if SHARED.is_dir():
        _config_commands(lanes, base, elsewhere, locks)
    lanes.run()
    for r in sorted(lanes.ran.values(), key=lambda r: r.name):
        print(f"{r.name:18s} exit {r.proc.returncode}  {r.seconds:6.1f} s")
    return lanes.ran


def _ok(r: Ran) -> None:
    assert r.proc.returncode == 0, f"{' '.join(r.argv)} (cwd {r.cwd}):\n{r.proc.stderr[-3000:]}"


def _need(shipped: dict[str, Ran], name: str) -> Ran:
    if name not in shipped:
        pytest.skip(f"{name}: not run (shared sample data not found at {SHARED}, or the demo "
                    "failed)")
    return shipped[name]


@pytest.mark.slow
@pytest.mark.parametrize("graph", [*GRAPHS, "demo"])
def test_lock_then_frozen_on_a_fresh_store_elsewhere_reproduces(shipped, graph):
    lock, frozen = _need(shipped, f"{graph}.lock"), _need(shipped, f"{graph}.frozen")
    _ok(lock)
    _ok(frozen)
    if graph == "demo":  # "<step>: N computed, M hit" per step, every step recomputed
        steps = dict(line.split(": ", 1) for line in frozen.proc.stdout.splitlines())
        assert list(steps) == ["data", "skin", "texture", "variation"], frozen.proc.stdout
        assert all(int(v.split()[0]) > 0 for v in steps.values()), frozen.proc.stdout
        return
    lock_doc = json.loads(Path(lock.argv[lock.argv.index("--lock") + 1]).read_text())
    store = Path(frozen.argv[frozen.argv.index("--store") + 1])
    (record,) = [json.loads(p.read_text()) for p in store.glob("runs/*.json")
                 if json.loads(p.read_text())["graph"] == lock_doc["graph"]]
    # the fresh store computed every task again, and every digest matched the lock
    assert record["counts"]["computed"] == len(lock_doc["tasks"]) > 0
    assert record["frozen_problems"] == []
    assert record["host"]["cwd"] == str(frozen.cwd) != str(REPO)
    # part ids are relative to the config's folder, whichever folder named them
    parts = {t["part"] for t in lock_doc["tasks"] if t["part"]}
    assert parts and not any(p.startswith("/") for p in parts)


@pytest.mark.slow
@pytest.mark.parametrize("graph, node", [("strokes", "learn"), ("clean", "clean")])
def test_force_of_unchanged_tasks_keeps_their_digests_without_a_warning(shipped, graph, node):
    r = _need(shipped, f"{graph}.force")
    _ok(r)
    assert "is the stage deterministic" not in r.proc.stderr


@pytest.mark.slow
def test_a_changed_input_fails_frozen_with_one_line(shipped):
    r = _need(shipped, "clean.changed")
    assert r.proc.returncode == 1
    lines = r.proc.stderr.splitlines()
    assert len(lines) == 1, r.proc.stderr
    assert lines[0].startswith("mocapflow: error: frozen: ingest/") and C3DS[1] in lines[0]
    assert "key differs from the lock (input path changed" in lines[0]
    store = Path(r.argv[r.argv.index("--store") + 1])
    assert not list(store.glob("entries/*/*/_COMMIT.json"))  # refused before anything ran
