"""Reproducible runs: pure outputs, what the worker read, part ids, BLAS threads.

* times go to the manifest and the run record (``ctx.timer``), never into an
  output, so ``--force`` of an unchanged task keeps its digest without a warning;
* an input file overwritten after planning (or while the stage reads it) fails
  the task with one line, and no entry is ever keyed by the old content;
* a part id does not depend on the working directory;
* a stage runs with one BLAS thread whatever the environment says.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from mocapflow.pipeline import Context, FilePath, runner, stage
from mocapflow.pipeline.codecs import decode
from mocapflow.pipeline.config import ConfigError, load_config
from mocapflow.pipeline.execute import single_threaded_blas
from mocapflow.pipeline.graph import build_graph
from mocapflow.pipeline.keys import clear_caches
from mocapflow.pipeline.lock import lock_document, write_lock
from mocapflow.pipeline.plan import plan
from mocapflow.pipeline.runner import run
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.testing import TOY_CONFIG, read_numbers, write_config

# --------------------------------------------------------------------------- test stages


@stage("repro_timed", outputs=("values",))
def repro_timed(path: FilePath, *, ctx: Context) -> dict:
    """Read numbers, timing two named steps (``read`` twice: the seconds add up)."""
    with ctx.timer("read"):
        v = read_numbers(path)
    with ctx.timer("square"):
        v = v**2
    with ctx.timer("read"):
        pass
    return {"values": v}


@stage("repro_rewrites_input", outputs=("values",))
def repro_rewrites_input(path: FilePath) -> dict:
    """Read a file, then (as another writer would, mid-read) rewrite it."""
    v = read_numbers(path)
    Path(path).write_text("99 99 99\n")
    return {"values": v}


@stage("repro_blas_threads", outputs=("threads",))
def repro_blas_threads(path: FilePath) -> dict:
    """The thread count of every BLAS pool of this process, as the stage sees it."""
    return {"threads": np.array([p["num_threads"] for p in threadpool_info()
                                 if p["user_api"] == "blas"])}


ONE_NODE = """\
parts:
  - "{parts}"
nodes:
  a: {{stage: {stage}, inputs: {{path: part}}}}
"""


def _graph(tmp_path: Path, stage_name: str, parts: str):
    cfg = write_config(tmp_path / f"{stage_name}.yaml", ONE_NODE, parts=parts, stage=stage_name)
    return build_graph(load_config(cfg))


def _manifest(store: Store, rec) -> dict:
    return store.manifest(rec.stage, rec.key)


# --------------------------------------------------------------------------- timings


def test_step_timings_go_to_the_manifest_and_run_record_never_to_outputs(tmp_path, data_dir):
    g = _graph(tmp_path, "repro_timed", f"{data_dir}/trial00[01].txt")
    a, b = Store(tmp_path / "a"), Store(tmp_path / "b")
    ra, rb = run(g, a), run(g, b)
    assert ra.ok and rb.ok and ra.counts["computed"] == 2
    # two stores, two runs: the same keys and output digests
    assert ra.digests() == rb.digests()
    assert [r.key for r in ra.records] == [r.key for r in rb.records]
    for r in ra.records:
        steps = _manifest(a, r)["timings"]["steps"]
        assert set(steps) == {"read", "square"} and all(s >= 0 for s in steps.values())
        assert r.timings["steps"] == steps
        assert {"load", "check", "compute", "commit"} <= set(r.timings)
    rec = json.loads(next(Path(a.root).glob("runs/*.json")).read_text())
    assert all(set(t["timings"]["steps"]) == {"read", "square"} for t in rec["tasks"])
    assert rec["host"]["pid"] > 0 and rec["host"]["cwd"] == os.getcwd()
    # --force of an unchanged task: recomputed, same digest, no "deterministic?" warning
    rf = run(g, a, force={"a"})
    assert rf.counts["computed"] == 2 and rf.digests() == ra.digests()
    assert all(not r.warnings for r in rf.records)


def test_context_timer_adds_up_and_survives_an_exception():
    ctx = Context()
    with ctx.timer("x"):
        pass
    with pytest.raises(ValueError), ctx.timer("x"):
        raise ValueError("boom")
    with ctx.timer("y"):
        sum(range(1000))
    assert set(ctx.timings) == {"x", "y"} and ctx.timings["x"] >= 0 and ctx.timings["y"] > 0


# --------------------------------------------------------------------------- what the worker read


def _overwrite_after_planning(monkeypatch, path: Path, text: str, *, keep_stat: bool = False):
    """Make the next ``run`` overwrite ``path`` right after the driver hashed its inputs."""
    real = runner.hash_files

    def hash_then_overwrite(graph, store):
        files = real(graph, store)
        st = path.stat()
        path.write_text(text)
        if keep_stat:  # same size, mtime put back: a stat-based memo cannot see the change
            os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
        monkeypatch.setattr(runner, "hash_files", real)
        return files

    monkeypatch.setattr(runner, "hash_files", hash_then_overwrite)


@pytest.mark.parametrize("keep_stat", [False, True], ids=["new-size", "same-size-and-mtime"])
def test_input_overwritten_between_plan_and_read_is_never_keyed_by_old_content(
        tmp_path, data_dir, store, monkeypatch, keep_stat):
    clear_caches()
    f = data_dir / "trial002.txt"
    old = f.read_text()
    os.utime(f, ns=(0, f.stat().st_mtime_ns - 10**10))  # outside the racy window: memoised
    cfg = write_config(tmp_path / "toy.yaml", TOY_CONFIG, parts=f"{data_dir}/*.txt")
    g = build_graph(load_config(cfg))
    planned = {p.part: p.key for p in plan(g, store) if p.node == "read"}
    new = old.replace("2.0", "9.0") if keep_stat else "7 8 9\n"
    assert len(new) == len(old) or not keep_stat
    _overwrite_after_planning(monkeypatch, f, new, keep_stat=keep_stat)
    r = run(g, store)
    bad = next(x for x in r.records if x.node == "read" and x.part.endswith("trial002.txt"))
    assert bad.status == "failed" and bad.key == planned[bad.part]
    assert bad.error.startswith(f"InputChangedError: input file {f} changed since planning")
    assert "\n" not in bad.error
    assert store.manifest("toy_read_file", planned[bad.part]) is None  # nothing under the old key
    assert r.counts == {"hit": 0, "computed": 12, "failed": 1, "skipped": 3}
    # the next run plans with the new content (the stat memo sees ctime) and computes it
    r2 = run(build_graph(load_config(cfg)), store)
    again = next(x for x in r2.records if x.node == "read" and x.part == bad.part)
    assert r2.ok and again.status == "computed" and again.key != planned[bad.part]
    values = decode(store.load("toy_read_file", again.key, "values"))
    np.testing.assert_array_equal(values, read_numbers(str(f)))


def test_input_rewritten_while_the_stage_reads_it_fails_and_commits_nothing(tmp_path, data_dir,
                                                                          store):
    g = _graph(tmp_path, "repro_rewrites_input", f"{data_dir}/trial001.txt")
    r = run(g, store)
    (rec,) = r.records
    assert rec.status == "failed" and store.entries() == []
    assert rec.error == (f"InputChangedError: input file {data_dir / 'trial001.txt'} changed "
                         "while the task read it; nothing was committed (run again once it is "
                         "stable)")


# --------------------------------------------------------------------------- part ids


def test_part_ids_do_not_depend_on_the_working_directory(tmp_path, data_dir, monkeypatch):
    proj = tmp_path / "proj"
    cfg = write_config(proj / "configs" / "g.yaml",
                       "parts: [../../data/trial00*.txt]\n"
                       "nodes:\n  r: {stage: toy_read_file, inputs: {path: part}}\n")
    store = Store(tmp_path / "store")
    seen = []
    for cwd in (tmp_path, proj, data_dir):
        monkeypatch.chdir(cwd)
        g = build_graph(load_config(os.path.relpath(cfg, cwd)))
        seen.append(([t.part for t in g.tasks], [p.key for p in plan(g, store)]))
        # the wires name the absolute files
        assert [t.inputs["path"].path for t in g.tasks] == [
            str(data_dir / f"trial00{i}.txt") for i in range(5)]
    assert seen[0] == seen[1] == seen[2]
    assert seen[0][0] == [f"../../data/trial00{i}.txt" for i in range(5)]
    # --parts is relative to the working directory, and gives the same id for the same file
    monkeypatch.chdir(data_dir)
    g = build_graph(load_config(cfg, parts=["trial001.txt"]))
    assert [t.part for t in g.tasks] == ["../../data/trial001.txt"]
    # an absolute part keeps its absolute path as id (the demo's parts)
    g = build_graph(load_config(cfg, parts=[str(data_dir / "trial001.txt")]))
    assert [t.part for t in g.tasks] == [str(data_dir / "trial001.txt")]
    # a missing relative part names the folder it was looked for in
    bad = write_config(proj / "configs" / "bad.yaml",
                       "parts: [nope.txt]\nnodes:\n  r: {stage: toy_read_file, inputs: "
                       "{path: part}}\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml:1: parts\[0\]: missing input file "
                                          r"'nope\.txt' \(in '.*/proj/configs'\)"):
        load_config(bad)


def test_a_lock_made_in_one_folder_is_reproduced_from_another(tmp_path, data_dir, monkeypatch,
                                                               cli):
    proj = tmp_path / "proj"
    cfg = write_config(proj / "toy.yaml", TOY_CONFIG, parts="../data/*.txt")
    monkeypatch.chdir(proj)
    code, _, err = cli("lock", "toy.yaml", "--store", tmp_path / "s1", "--executor", "sync", "-q")
    assert code == 0, err
    monkeypatch.chdir(data_dir)
    code, _, err = cli("run", cfg, "--frozen", "--store", tmp_path / "s2", "--executor", "sync",
                       "-q")
    assert code == 0, err
    # every task computed again in the fresh store, and matched the lock
    assert len(Store(tmp_path / "s2").entries()) == 16


def test_frozen_output_mismatch_is_one_line_not_a_traceback(tmp_path, toy_config, cli):
    g = build_graph(load_config(toy_config))
    r = run(g, Store(tmp_path / "s1"))
    doc = lock_document(g, r.records)
    doc["tasks"][0]["outputs"]["values"] = "0" * 64  # as a non-deterministic stage would
    lock = write_lock(tmp_path / "toy.lock.json", doc)
    code, _, err = cli("run", toy_config, "--frozen", "--lock", lock, "--store",
                       tmp_path / "s2", "--executor", "sync", "-q")
    t = doc["tasks"][0]
    assert code == 1
    assert err == (f"mocapflow: error: frozen: {t['node']}/{t['part']}: output values digest "
                   "differs from the lock\n")


# --------------------------------------------------------------------------- BLAS threads


def test_stages_run_with_one_blas_thread_whatever_the_environment(tmp_path, data_dir, store):
    if not any(p["user_api"] == "blas" for p in threadpool_info()):
        pytest.skip("no BLAS library found by threadpoolctl")
    g = _graph(tmp_path, "repro_blas_threads", f"{data_dir}/trial001.txt")
    with threadpool_limits(limits=2, user_api="blas"):
        r = run(g, store)
        after = [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
    (rec,) = r.records
    seen = decode(store.load(rec.stage, rec.key, "threads"))
    assert rec.ok and seen.size and set(seen.ravel().tolist()) == {1}
    assert set(after) == {2}  # restored for the caller


def test_a_stage_called_from_python_runs_with_one_blas_thread(tmp_path, data_dir):
    """Called directly (registry.call), a stage runs as the engine runs it: BLAS at one
    thread (the same bits; on a loaded 2-core machine a threaded SVD of clean's
    whole-body PCA cost 20x), the caller's pools restored after."""
    if not any(p["user_api"] == "blas" for p in threadpool_info()):
        pytest.skip("no BLAS library found by threadpoolctl")
    with threadpool_limits(limits=2, user_api="blas"):
        seen = repro_blas_threads(FilePath(f"{data_dir}/trial001.txt"))["threads"]
        after = [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
    assert seen.size and set(np.asarray(seen).ravel().tolist()) == {1}
    assert set(after) == {2}


def test_blas_limit_is_reentrant_and_restored_after_the_last_task():
    if not any(p["user_api"] == "blas" for p in threadpool_info()):
        pytest.skip("no BLAS library found by threadpoolctl")

    def threads():
        return {p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"}

    with threadpool_limits(limits=2, user_api="blas"):
        with single_threaded_blas():
            with single_threaded_blas():
                assert threads() == {1}
            assert threads() == {1}  # another task still runs
        assert threads() == {2}
