"""Executors: identical digests on sync / local (1 and 2 workers) / an external cluster;
``ctx.map`` on the cluster; failures and ``--fail-fast`` on the cluster; Slurm job script."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
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
