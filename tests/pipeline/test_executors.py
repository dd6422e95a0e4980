"""Executors: identical digests on sync / local (1 and 2 workers) / an external cluster;
``ctx.map`` on the cluster; failures and ``--fail-fast`` on the cluster; Slurm job script."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from mocapflow.pipeline import codecs
from mocapflow.pipeline.config import load_config
from mocapflow.pipeline.executors import (
    ExecutorError,
    SlurmOptions,
    make_executor,
    slurm_job_script,
)
from mocapflow.pipeline.graph import build_graph
from mocapflow.pipeline.runner import run
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.testing import write_config, write_number_files

MIXED = """\
parts: ["{data}/*.txt"]
targets: [total, nsum]
nodes:
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
  noisy: {{stage: toy_source, seeds: {{count: 2}}, params: {{n: 5, noise: 1.0}}}}
  sq: {{stage: toy_map, inputs: {{values: read.values}}, params: {{chunks: 3}}}}
  total: {{stage: toy_sum, inputs: {{values: sq.values}}, gather: true}}
  nsum: {{stage: toy_sum, inputs: {{values: noisy.values}}, gather: true}}
"""


def _pure(digests):
    """Digests without toy_map's ``pids`` output (which records where the map ran)."""
    return {k: {o: d for o, d in (v or {}).items() if o != "pids"} for k, v in digests.items()}


@pytest.fixture(scope="module")
def client():
    """One LocalCluster (2 single-threaded worker processes) for the module."""
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                           dashboard_address=":0")
    c = Client(cluster, set_as_default=False)
    yield c
    c.close()
    cluster.close()


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    """(config path, sync baseline digests) of a graph with files, seeds, ctx.map, gathers."""
    d = tmp_path_factory.mktemp("mixed")
    write_number_files(d / "data", 4, length=7)
    cfg = write_config(d / "mixed.yaml", MIXED, data=d / "data")
    r = run(build_graph(load_config(cfg)), Store(d / "sync-store"))
    assert r.ok and r.counts["computed"] == 12
    return cfg, _pure(r.digests())


def test_local_two_workers_same_digests_and_ctx_map_on_cluster(mixed, client, tmp_path):
    cfg, want = mixed
    store = Store(tmp_path / "s")
    r = run(build_graph(load_config(cfg)), store, executor=make_executor(client=client))
    assert r.ok and _pure(r.digests()) == want
    workers = {w["pid"] for w in client.scheduler_info()["workers"].values()
               if "pid" in w} or set(client.run(os.getpid).values())
    sq = [x for x in r.records if x["node"] == "sq"]
    pids = {p for x in sq for p in codecs.decode(store.load("toy_map", x["key"], "pids"))}
    assert pids and pids <= workers and os.getpid() not in pids
    vals = codecs.decode(store.load("toy_map", sq[1]["key"], "values"))
    np.testing.assert_array_equal(vals, (np.arange(7.0) + 1) ** 2)
    # a second run on the cluster: all hits, the cluster is not even asked
    again = run(build_graph(load_config(cfg)), store, executor=make_executor(client=client))
    assert again.counts["hit"] == 12


def test_local_one_worker_same_digests(mixed, tmp_path):
    cfg, want = mixed
    with make_executor("local", workers=1) as ex:
        r = run(build_graph(load_config(cfg)), Store(tmp_path / "s"), executor=ex)
        assert ex.workers == 1
    assert r.ok and _pure(r.digests()) == want


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_external_scheduler_and_worker_same_digests(mixed, tmp_path):
    cfg, want = mixed
    sched_file = tmp_path / "scheduler.json"
    port = _free_port()
    procs = [subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
         "--port", str(port), "--no-dashboard", "--scheduler-file", str(sched_file)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_worker", f"tcp://127.0.0.1:{port}",
             "--nthreads", "1", "--nworkers", "1", "--host", "127.0.0.1", "--no-dashboard"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        deadline = time.monotonic() + 30
        while not sched_file.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        ex = make_executor(scheduler_file=str(sched_file))
        ex.client.wait_for_workers(1, timeout=30)
        r = run(build_graph(load_config(cfg)), Store(tmp_path / "s"), executor=ex)
        ex.close()  # closes our client only
        assert r.ok and _pure(r.digests()) == want
        # the same cluster by address, and it is still up after our client closed
        with make_executor(address=f"tcp://127.0.0.1:{port}") as ex2:
            r2 = run(build_graph(load_config(cfg)), Store(tmp_path / "s2"), executor=ex2)
        assert r2.ok and _pure(r2.digests()) == want
        assert procs[0].poll() is None and procs[1].poll() is None
    finally:
        for p in reversed(procs):
            p.kill()
            p.wait(timeout=10)


def test_failures_and_fail_fast_on_the_cluster(client, tmp_path):
    write_number_files(tmp_path / "data", 6)
    cfg = write_config(tmp_path / "f.yaml", """\
        parts: ["{data}/*.txt"]
        nodes:
          read: {{stage: toy_read_file, inputs: {{path: part}}}}
          check: {{stage: toy_fail_on, inputs: {{values: read.values}},
                  params: {{pattern: trial000}}}}
          slow: {{stage: toy_sleep, inputs: {{values: check.values}}, params: {{seconds: 0.4}}}}
        """, data=tmp_path / "data")
    r = run(build_graph(load_config(cfg)), Store(tmp_path / "a"),
            executor=make_executor(client=client))
    assert r.counts == {"hit": 0, "computed": 16, "failed": 1, "skipped": 1}
    bad = r.failed()[0]
    assert bad["node"] == "check" and bad["part"].endswith("trial000.txt")
    assert bad["error"].startswith("ValueError: part ")
    t0 = time.perf_counter()
    r = run(build_graph(load_config(cfg)), Store(tmp_path / "b"),
            executor=make_executor(client=client), fail_fast=True)
    assert r.counts["failed"] == 1
    cancelled = [x for x in r.records if x["error"] == "cancelled (--fail-fast)"]
    assert len(cancelled) >= 2 and "slow" in {x["node"] for x in cancelled}
    assert time.perf_counter() - t0 < 5 * 0.4 / 2 + 1.0


def test_slurm_job_script_renders_without_slurm(toy_config, cli):
    text = slurm_job_script(SlurmOptions(queue="short", cores=2, memory="4GB",
                                         walltime="00:10:00", account="lab"))
    for line in ("#SBATCH -p short", "#SBATCH -A lab", "#SBATCH --cpus-per-task=2",
                 "#SBATCH --mem=4G", "#SBATCH -t 00:10:00", "#SBATCH -J mocapflow"):
        assert line in text, text
    assert "distributed.cli.dask_worker" in text
    assert "--nthreads 1" in text and "--nworkers 2" in text
    assert "export MOCAPFLOW_STAGE_MODULES=mocapflow.pipeline.testing" in text
    code, out, err = cli("run", toy_config, "--executor", "slurm", "--print-job-script",
                         "--slurm-cores", "8", "--slurm-walltime", "02:00:00")
    assert code == 0 and "#SBATCH --cpus-per-task=8" in out and "-t 02:00:00" in out


def test_executor_errors(tmp_path):
    with pytest.raises(ExecutorError, match="unknown executor 'mpi'"):
        make_executor("mpi")
    with pytest.raises(ExecutorError, match="not both"):
        make_executor(address="tcp://127.0.0.1:1", scheduler_file="x.json")
    ex = make_executor(scheduler_file=str(tmp_path / "none.json"))
    with pytest.raises(ExecutorError, match="none.json: no such file"):
        ex.client  # noqa: B018 - connects lazily
    json.dumps({"ok": True})


# --------------------------------------------------------------------------- cluster edges

DIE = """\
parts: ["{data}/trial001.txt"]
nodes:
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
  die: {{stage: toy_die, inputs: {{values: read.values}}, params: {{pattern: trial001}}}}
  after: {{stage: toy_add, inputs: {{values: die.values}}}}
"""


def _error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


def test_killed_worker_is_one_line_naming_node_part_and_what_to_try(cli_env, cli_proc,
                                                                   tmp_path):
    write_number_files(tmp_path / "data", 2)
    cfg = write_config(tmp_path / "die.yaml", DIE, data=tmp_path / "data")
    cli_env["DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES"] = "0"  # one death is enough
    p = cli_proc("run", cfg, "--store", tmp_path / "s", "--workers", "1", "-q")
    out, err = p.communicate(timeout=120)
    lines = _error_lines(err)
    assert p.returncode == 1, err
    assert len(lines) == 1 and "Traceback" not in err, err
    line = lines[0]
    assert line.startswith("mocapflow: error: 1 task(s) failed: die/")
    assert "trial001.txt: KilledWorker: the worker process running this task died once" in line
    assert "try fewer --workers" in line and "--executor sync" in line and "; 1 skipped" in line
    rec = json.loads(next((tmp_path / "s" / "runs").glob("*.json")).read_text())
    status = {t["node"]: (t["status"], t["error"]) for t in rec["tasks"]}
    assert status["read"] == ("computed", None)
    assert status["after"][0] == "skipped"
    assert status["after"][1].startswith("upstream die/") and "trial001.txt failed" in \
        status["after"][1]  # the executor's own outcome names the task below it


def test_slurm_without_sbatch_fails_fast_with_one_line(cli, cli_env, cli_proc, toy_config,
                                                       tmp_path):
    cli_env["PATH"] = str(tmp_path)  # no sbatch here (the command runs by absolute path)
    t0 = time.perf_counter()
    p = cli_proc("run", toy_config, "--store", tmp_path / "s", "--executor", "slurm", "-q")
    out, err = p.communicate(timeout=60)  # it waited for ever before
    assert p.returncode == 2 and time.perf_counter() - t0 < 30
    assert _error_lines(err) == [
        "mocapflow: error: --executor slurm: sbatch is not on PATH (run on a Slurm login node "
        "or load its module; --print-job-script shows the job script without Slurm)"], err
    assert not Store(tmp_path / "s").entries()
    # an all-hit run needs no cluster, so no sbatch either
    assert cli("run", toy_config, "--store", tmp_path / "h", *("--executor", "sync"))[0] == 0
    p = cli_proc("run", toy_config, "--store", tmp_path / "h", "--executor", "slurm", "-q")
    assert p.communicate(timeout=60) and p.returncode == 0


class _Done:
    """A call's result (the executor only reads ``status`` and ``index``)."""

    def __init__(self, index: int) -> None:
        self.status, self.index = "computed", index


def _sleep_call(index: int, seconds: float, *deps) -> _Done:
    time.sleep(seconds)
    return _Done(index)


_RELEASE = threading.Event()


def _held_call(index: int, *deps) -> _Done:
    _RELEASE.wait(30)  # until the test lets it go (in-process workers)
    return _Done(index)


def _after(index: int, *deps) -> _Done:
    """Like the engine's task function: skipped (run where the executor is) below a failure."""
    out = _Done(index)
    if any(d.status != "computed" for d in deps):
        out.status = "skipped"
    return out


def test_no_worker_at_start_times_out():
    from distributed import Client, LocalCluster

    from mocapflow.pipeline.executors import Call

    with LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as cluster, \
            Client(cluster, set_as_default=False) as c:
        ex = make_executor(client=c, worker_timeout=0.5)
        t0 = time.perf_counter()
        with pytest.raises(ExecutorError, match=r"no Dask worker joined within 0\.5 s; .*"
                                                r"or raise --worker-timeout"):
            ex.run([Call(0, "a-0", _sleep_call, (0, 0.0))])
        assert time.perf_counter() - t0 < 10
    with pytest.raises(ExecutorError, match="--worker-timeout must be >= 0"):
        make_executor("local", worker_timeout=-1)
    assert make_executor("local", worker_timeout=0).worker_timeout is None  # 0: for ever
    assert make_executor("slurm").worker_timeout == 600.0


def test_workers_lost_during_a_run_fail_the_remaining_calls():
    from distributed import Client, LocalCluster

    from mocapflow.pipeline.executors import Call

    with LocalCluster(n_workers=1, processes=False, threads_per_worker=1,
                      dashboard_address=":0") as cluster, \
            Client(cluster, set_as_default=False) as c:
        ex = make_executor(client=c, worker_timeout=1.0)
        calls = [Call(0, "first-0", _sleep_call, (0, 0.0), node="first"),
                 Call(1, "long-1", _held_call, (1,), deps=(0,), node="long", part="p"),
                 Call(2, "next-2", _after, (2,), deps=(1,), node="next", part="p")]
        worker = next(iter(cluster.workers.values()))

        def kill() -> None:  # once the long call runs, its (only) worker goes away
            deadline = time.monotonic() + 20
            while not worker.state.executing and time.monotonic() < deadline:
                time.sleep(0.05)
            cluster.sync(worker.close)

        threading.Thread(target=kill, daemon=True).start()
        t0 = time.perf_counter()
        res = ex.run(calls)
        assert time.perf_counter() - t0 < 15  # not for ever
        _RELEASE.set()
    assert res[0].status == "computed"
    assert res[1].status == "failed" and res[1].error.startswith("no Dask worker for 1 s")
    assert (res[1].node, res[1].part) == ("long", "p")
    assert res[2].status == "skipped"  # run here, below the failure, not lost with it


def test_memory_store_runs_on_the_local_cluster_as_threads(mixed, tmp_path, cli, toy_config):
    import uuid

    cfg, want = mixed
    root = f"memory://mf-{uuid.uuid4().hex[:8]}"
    store = Store(root)
    with make_executor("local", workers=2, store=store) as ex:
        assert "threads of this process" in ex.describe()
        r = run(build_graph(load_config(cfg)), store, executor=ex)
        assert r.ok and _pure(r.digests()) == want  # the same digests as a sync run
        again = run(build_graph(load_config(cfg)), store, executor=ex)
    assert again.counts["hit"] == 12
    # the command line passes the store to the executor
    code, out, err = cli("run", toy_config, "--store", f"memory://mf-{uuid.uuid4().hex[:8]}",
                         "--workers", "2", "-q")
    assert code == 0, err


def test_memory_store_refused_where_workers_cannot_see_it(client, toy_config, tmp_path):
    import uuid

    root = f"memory://mf-{uuid.uuid4().hex[:8]}"
    for kw in ({"address": "tcp://127.0.0.1:1"}, {"kind": "slurm"}):
        with pytest.raises(ExecutorError, match=f"--store {root} lives in this process's "
                                                "memory"):
            make_executor(store=root, **kw)
    store = Store(root)
    ex = make_executor(client=client)  # worker processes: asked, then refused
    with pytest.raises(ExecutorError, match=f"store {root} lives in this process's memory"):
        run(build_graph(load_config(toy_config)), store, executor=ex)
    assert store.entries() == []
