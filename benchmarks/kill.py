"""Crash safety: random SIGKILLs of ``mocapflow run`` on one store, sync and local executors.

Every attempt runs ``mocapflow run`` (a subprocess, its own session) of a toy
graph with fresh work (``--set params.k=<attempt>``: 6 parts × read → add →
sleep, a gather, and 4 seeds × a 2 MB source → scale: 21 new entries), and
kills it with SIGKILL at a random moment of its expected duration (uniform in
5–90 % of an unkilled run of the same executor, measured first):

* ``sync / driver``: the whole process;
* ``local / driver``: the driver and its Dask workers (the process group);
* ``local / worker``: one worker process only (the driver lives on and the run
  goes on or fails; it must not hang).

After every kill ``Store.verify()`` must report nothing (staging debris left
by a killed writer is not a problem; ``gc`` removes it).  At the end every
attempt's graph is run again to completion on the same store (the last one
through the CLI, sync executor), ``verify`` must pass, ``gc`` must clean the
debris, and the output digests of every committed entry must equal those of a
clean store built without kills (no entry keyed by content it does not hold).

Run::

    .venv/bin/python benchmarks/kill.py               # 50 kills, ~4 min on 2 cores
    .venv/bin/python benchmarks/kill.py --kills 10    # a quick look

It prints one table row per executor / kill target and the final checks, and
exits 1 if any check fails.
"""

from __future__ import annotations

import argparse
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import psutil

from mocapflow.pipeline import testing
from mocapflow.pipeline.config import STAGE_MODULES_ENV, load_config
from mocapflow.pipeline.executors import SyncExecutor
from mocapflow.pipeline.graph import build_graph
from mocapflow.pipeline.runner import run
from mocapflow.pipeline.store import Store

CONFIG = """\
graph: kill
params: {k: 0}
parts: [DATA/*.txt]
nodes:
  read: {stage: toy_read_file, inputs: {path: part}}
  add: {stage: toy_add, inputs: {values: read.values}, params: {amount: ${params.k}}}
  slow: {stage: toy_sleep, inputs: {values: add.values}, params: {seconds: 0.05}}
  total: {stage: toy_sum, inputs: {values: slow.values}, gather: true}
  big:
    stage: toy_source
    params: {n: 250000, value: ${params.k}, noise: 1.0}
    seeds: {count: 4}
  scaled: {stage: toy_scale, inputs: {values: big.values}, params: {factor: 3.0}}
"""
PLANS = (("sync", "driver"), ("local", "driver"), ("local", "worker"))


def _cmd(cfg: Path, store: Path, executor: str, k: int) -> list[str]:
    cmd = [sys.executable, "-m", "mocapflow", "run", str(cfg), "--store", str(store),
           "--executor", executor, "--set", f"params.k={k}", "-q"]
    return cmd + (["--workers", "2"] if executor == "local" else [])


def _start(cmd: list[str], env: dict, log: Path) -> subprocess.Popen:
    with log.open("w") as err:  # a file, not a pipe: a chatty run never blocks on it
        return subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=err,
                                start_new_session=True)


def _reap(proc: subprocess.Popen, timeout: float) -> str:
    """Wait for the run; kill its group if it outlives ``timeout``.  Returns the outcome."""
    try:
        code = proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        return "hang"
    _kill_group(proc.pid)  # leftovers (a worker that outlived its driver)
    return "exit 0" if code == 0 else ("killed" if code < 0 else f"exit {code}")


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)
    except ProcessLookupError:
        return
    for _ in range(100):  # wait until every process of the group is gone
        if not any(p.info["pid"] != os.getpid() and _pgid(p.info["pid"]) == pgid
                   for p in psutil.process_iter(["pid"])):
            return
        time.sleep(0.05)


def _pgid(pid: int) -> int | None:
    try:
        return os.getpgid(pid)
    except ProcessLookupError:
        return None


def _workers(pid: int) -> list[psutil.Process]:
    """The driver's Dask worker processes (multiprocessing children running a worker)."""
    try:
        kids = psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []
    out = []
    for p in kids:
        try:
            if "multiprocessing" in " ".join(p.cmdline()):
                out.append(p)
        except psutil.Error:
            continue
    return out


def _kill_once(cmd: list[str], env: dict, target: str, delay: float, log: Path
               ) -> tuple[bool, str]:
    """Start a run, SIGKILL it (or one worker) after ``delay``; (kill delivered, outcome)."""
    proc = _start(cmd, env, log)
    time.sleep(delay)
    if proc.poll() is not None:
        return False, _reap(proc, 5)
    if target == "driver":
        _kill_group(proc.pid)
        proc.wait()
        return True, "killed"
    deadline = time.time() + delay + 5
    victims = _workers(proc.pid)
    while not victims and proc.poll() is None and time.time() < deadline:
        time.sleep(0.1)
        victims = _workers(proc.pid)
    if not victims:
        return False, _reap(proc, 120)
    try:
        random.choice(victims).send_signal(signal.SIGKILL)
    except psutil.NoSuchProcess:
        return False, _reap(proc, 120)
    return True, _reap(proc, 120)


def _reference(cfg: Path, ks: list[int], root: Path) -> dict[tuple[str, str], dict]:
    """``(stage, key) -> output digests`` of a clean store holding every attempt's graph."""
    ref = Store(root)
    for k in ks:
        res = run(build_graph(load_config(cfg, sets=[f"params.k={k}"])), ref,
                  executor=SyncExecutor())
        assert res.ok, res.failed()[:1]
    return {e: _digests(ref, *e) for e in ref.entries()}


def _digests(store: Store, stage: str, key: str) -> dict:
    man = store.manifest(stage, key) or {}
    return {o: v["digest"] for o, v in (man.get("outputs") or {}).items()}


def _timed_run(cmd: list[str], env: dict) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kills", type=int, default=50, help="SIGKILLs to deliver (default 50)")
    ap.add_argument("--seed", type=int, default=0, help="random seed of the kill moments")
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder (stores of "
                    "about 2 GB for 50 kills)")
    args = ap.parse_args(argv)
    random.seed(args.seed)
    tmp = Path(tempfile.mkdtemp(prefix="mocapflow-kill-"))
    testing.write_number_files(tmp / "data", 6, length=2000)
    cfg = tmp / "kill.yaml"
    cfg.write_text(CONFIG.replace("DATA", str(tmp / "data")))
    store_dir = tmp / "store"
    env = {**os.environ, STAGE_MODULES_ENV: "mocapflow.pipeline.testing",
           "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    expect = {ex: _timed_run(_cmd(cfg, tmp / f"warm-{ex}", ex, 10**6), env)
              for ex in ("sync", "local")}
    print(f"unkilled run: sync {expect['sync']:.1f} s, local {expect['local']:.1f} s "
          f"(store {store_dir})", file=sys.stderr)

    rows = {p: {"attempts": 0, "kills": 0, "outcomes": {}, "problems": 0, "debris": 0,
                "errors": {}} for p in PLANS}
    attempted: list[int] = []
    k = 0
    t_start = time.perf_counter()
    while sum(r["kills"] for r in rows.values()) < args.kills and k < 4 * args.kills:
        executor, target = PLANS[k % len(PLANS)]
        row = rows[(executor, target)]
        delay = random.uniform(0.05, 0.9) * expect[executor]
        log = tmp / f"run-{k}.stderr"
        killed, outcome = _kill_once(_cmd(cfg, store_dir, executor, k), env, target, delay, log)
        if outcome.startswith("exit") and outcome != "exit 0":
            last = (log.read_text().strip().splitlines() or ["(nothing on stderr)"])[-1]
            last = re.sub(r"/[\w./-]+", "…", last)[:160]  # paths vary; the message is the point
            row["errors"][last] = row["errors"].get(last, 0) + 1
        attempted.append(k)
        k += 1
        row["attempts"] += 1
        row["kills"] += killed
        row["outcomes"][outcome] = row["outcomes"].get(outcome, 0) + 1
        store = Store(store_dir)
        problems = store.verify()
        row["problems"] += len(problems)
        for p in problems[:3]:
            print(f"verify after kill {k}: {p}", file=sys.stderr)
        row["debris"] = max(row["debris"], len(store.backend.listdir(store.location("staging"))))
    t_kills = time.perf_counter() - t_start

    store = Store(store_dir)
    final_ok = 0
    for kk in attempted[:-1]:
        final_ok += run(build_graph(load_config(cfg, sets=[f"params.k={kk}"])), store,
                        executor=SyncExecutor()).ok
    last = subprocess.run(_cmd(cfg, store_dir, "sync", attempted[-1]), env=env,
                          capture_output=True, text=True)
    final_ok += last.returncode == 0
    problems = store.verify()
    gc = store.gc()
    after_gc = store.verify()
    debris_left = store.backend.listdir(store.location("staging"))
    ref = _reference(cfg, attempted, tmp / "reference")
    ours = {e: _digests(store, *e) for e in store.entries()}
    wrong = [e for e, d in ours.items() if ref.get(e) != d]
    missing = sorted(set(ref) - set(ours))

    print(f"\n{sum(r['kills'] for r in rows.values())} SIGKILLs in {len(attempted)} runs of "
          f"21 new tasks each, {t_kills:.0f} s\n")
    print("| executor | killed | runs | kills delivered | run outcomes | verify problems "
          "after kills | most staging dirs left |")
    print("|---|---|---:|---:|---|---:|---:|")
    for (executor, target), r in rows.items():
        outs = ", ".join(f"{v} {o}" for o, v in sorted(r["outcomes"].items()))
        print(f"| {executor} | {target} | {r['attempts']} | {r['kills']} | {outs} | "
              f"{r['problems']} | {r['debris']} |")
    for (executor, target), r in rows.items():
        for msg, n in sorted(r["errors"].items(), key=lambda kv: -kv[1]):
            print(f"\n{executor} / {target}, {n} run(s) ended: {msg}")
    print(f"\nfinal runs to completion: {final_ok}/{len(attempted)} exit 0 (last via the CLI: "
          f"exit {last.returncode}{': ' + last.stderr.strip()[:200] if last.returncode else ''})")
    print(f"verify after the final runs: {len(problems)} problem(s); gc removed "
          f"{len(gc['staging'])} staging dir(s), {len(gc['incomplete'])} incomplete entr(y/ies); "
          f"verify after gc: {len(after_gc)}; staging left: {len(debris_left)}")
    print(f"committed entries: {len(ours)}; output digests differing from a clean store: "
          f"{len(wrong)}; entries of the clean store missing: {len(missing)}")
    hangs = sum(r["outcomes"].get("hang", 0) for r in rows.values())
    ok = (not problems and not after_gc and not wrong and not missing and not hangs
          and final_ok == len(attempted) and sum(r["problems"] for r in rows.values()) == 0)
    print("PASS" if ok else "FAIL")
    if not args.keep:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
