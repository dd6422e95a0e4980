"""Plan / run / explain / lock on the sync executor: caching, early cutoff, failures, frozen."""

from __future__ import annotations

import importlib
import json
import os
import shutil
import sys
import uuid

import numpy as np
import pytest

from mocapflow.pipeline import codecs, fingerprint
from mocapflow.pipeline.context import Context
from mocapflow.pipeline.registry import stage
from mocapflow.pipeline.runner import (
    FrozenError,
    explain,
    lock_document,
    plan,
    read_lock,
    run,
    write_lock,
)
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.testing import assert_stage_contract, toy_source, write_config


def _statuses(result):
    return {(r["node"], r["part"]): r["status"] for r in result.records}


def _by_node(result, status):
    out: dict[str, int] = {}
    for r in result.records:
        if r["status"] == status:
            out[r["node"]] = out.get(r["node"], 0) + 1
    return out


def _total(store, result):
    rec = next(r for r in result.records if r["node"] == "total")
    return codecs.decode(store.load(rec["stage"], rec["key"], "total"))


def test_unchanged_rerun_is_all_hits_and_plan_gives_reasons(toy_config, store, graph_of):
    g = graph_of(toy_config)
    first = plan(g, store)
    assert [p.status for p in first] == ["compute"] * 5 + ["pending"] * 11
    assert all(p.reason.startswith("no entry for key ") for p in first[:5])
    assert first[5].reason == f"upstream read/{first[0].part} will recompute"
    r1 = run(g, store)
    assert r1.ok and r1.counts == {"hit": 0, "computed": 16, "failed": 0, "skipped": 0}
    # files hold i..i+4: total_i = 2 * (5 i + 10 + 5 * amount)
    np.testing.assert_array_equal(_total(store, r1), [2 * (5 * i + 10 + 5) for i in range(5)])
    r2 = run(graph_of(toy_config), store)
    assert r2.counts == {"hit": 16, "computed": 0, "failed": 0, "skipped": 0}
    assert r2.digests() == r1.digests()
    assert [(p.status, p.reason) for p in plan(g, store)] == [("hit", "hit")] * 16
    # every task is in the run record with its key and components
    rec = store.runs()[-1]
    assert rec["run_id"] == r2.run_id and len(rec["tasks"]) == 16
    assert {t["status"] for t in rec["tasks"]} == {"hit"}
    assert all(t["key"] and t["components"]["stage"] == t["stage"] for t in rec["tasks"])


def test_param_change_recomputes_node_and_downstream_only(toy_config, store, graph_of):
    run(graph_of(toy_config), store)
    g = graph_of(toy_config, sets=["add.amount=2.5"])
    reasons = {(p.node, p.status, p.reason) for p in plan(g, store)}
    assert ("add", "compute", "param amount: 1.0 -> 2.5") in reasons
    assert {n for n, s, _ in reasons if s == "hit"} == {"read"}
    ex = explain(g, store, "add/trial003")
    assert len(ex) == 1 and ex[0]["changes"] == ["param amount: 1.0 -> 2.5"]
    ex = explain(g, store, "scale/trial003")
    assert ex[0]["status"] == "pending" and ex[0]["changes"][0].startswith("upstream add/")
    r = run(g, store)
    assert _by_node(r, "computed") == {"add": 5, "scale": 5, "total": 1}
    assert _by_node(r, "hit") == {"read": 5}
    np.testing.assert_array_equal(_total(store, r), [2 * (5 * i + 10 + 12.5) for i in range(5)])
    # after the run nothing changed any more
    assert explain(g, store, "add/trial003")[0]["changes"] == []


def test_byte_identical_upstream_output_keeps_downstream_hits(toy_config, data_dir, store,
                                                              graph_of):
    r1 = run(graph_of(toy_config), store)
    f = data_dir / "trial001.txt"
    f.write_text("# a comment that changes the file but not the numbers\n" + f.read_text())
    g = graph_of(toy_config)
    p = {(x.node, x.part): x for x in plan(g, store)}
    changed = p[("read", str(f))]
    assert changed.status == "compute"
    assert changed.reason.startswith("input path changed (file content digest")
    assert p[("add", str(f))].status == "pending"
    r2 = run(g, store)
    assert _by_node(r2, "computed") == {"read": 1}  # early cutoff: add/scale/total stay hits
    assert r2.counts["hit"] == 15
    assert r2.digests() == r1.digests()


def _write_helper_package(root, pkg, body):
    (root / pkg).mkdir(parents=True, exist_ok=True)
    (root / pkg / "__init__.py").write_text("")
    (root / pkg / "helper.py").write_text(body)
    (root / pkg / "stages.py").write_text(
        "from mocapflow.pipeline import stage\n"
        "from .helper import bump\n\n\n"
        f"@stage('toy_helped_{pkg}', outputs=('values',))\n"
        "def helped(values):\n"
        "    return {'values': bump(values)}\n")


def test_helper_module_edit_invalidates_comment_edit_does_not(tmp_path, store, monkeypatch):
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    pkg = f"mfhelp_{uuid.uuid4().hex[:8]}"
    root = tmp_path / "pkgs"
    _write_helper_package(root, pkg, '"""Helper."""\n\n\ndef bump(x):\n    return x + 1  # one\n')
    monkeypatch.syspath_prepend(str(root))
    importlib.import_module(f"{pkg}.stages")
    cfg = write_config(tmp_path / "h.yaml", f"""\
        nodes:
          src: {{stage: toy_source, params: {{n: 4}}}}
          helped: {{stage: toy_helped_{pkg}, inputs: {{values: src.values}}}}
          scale: {{stage: toy_scale, inputs: {{values: helped.values}}}}
        """)
    from mocapflow.pipeline.config import load_config
    from mocapflow.pipeline.graph import build_graph

    assert run(build_graph(load_config(cfg)), store).counts["computed"] == 3
    try:
        # comments, docstrings and formatting only: still hits
        (root / pkg / "helper.py").write_text(
            '"""Helper, reworded at length."""\n# a new comment\n\n\ndef bump(x):\n'
            '    """Add one."""\n    # inner comment\n    return x   +   1\n')
        fingerprint.clear_caches()
        assert [p.status for p in plan(build_graph(load_config(cfg)), store)] == ["hit"] * 3
        # a code change in the helper: the stage that imports it recomputes
        (root / pkg / "helper.py").write_text("def bump(x):\n    return x + 10\n")
        fingerprint.clear_caches()
        g = build_graph(load_config(cfg))
        p = plan(g, store)
        assert [x.status for x in p] == ["hit", "compute", "pending"]
        assert p[1].reason.startswith(f"code of stage toy_helped_{pkg} changed")
        assert explain(g, store, "helped")[0]["changes"][0].startswith("code of stage")
        importlib.reload(importlib.import_module(f"{pkg}.helper"))
        importlib.reload(importlib.import_module(f"{pkg}.stages"))
        r = run(g, store)
        assert _by_node(r, "computed") == {"helped": 1, "scale": 1}
        out = r.records[-1]
        np.testing.assert_array_equal(
            codecs.decode(store.load("toy_scale", out["key"], "values")),
            (np.arange(4.0) + 10) * 2)
    finally:
        fingerprint.clear_caches()


def test_batch_with_corrupt_file_reports_part_and_continues(toy_config, data_dir, store,
                                                            graph_of):
    bad = data_dir / "trial002.txt"
    bad.write_text("2 3 x 5 6\n")
    r = run(graph_of(toy_config), store)
    assert not r.ok
    failed = r.failed()
    assert len(failed) == 1 and failed[0]["node"] == "read" and failed[0]["part"] == str(bad)
    assert failed[0]["error"] == f"ValueError: {bad}: line 1: not a number 'x'"
    st = _statuses(r)
    assert st[("add", str(bad))] == st[("scale", str(bad))] == st[("total", None)] == "skipped"
    assert _by_node(r, "computed") == {"read": 4, "add": 4, "scale": 4}
    # the other parts are committed; the run record has the traceback
    assert len(store.entries()) == 12
    rec = store.runs()[-1]
    t = next(t for t in rec["tasks"] if t["status"] == "failed")
    assert "Traceback" in t["traceback"] and "not a number" in t["traceback"]
    # fixing the file: only the broken part and the gather run
    bad.write_text("2 3 4 5 6\n")
    r2 = run(graph_of(toy_config), store)
    assert r2.ok and _by_node(r2, "computed") == {"read": 1, "add": 1, "scale": 1, "total": 1}


def test_fail_fast_stops_early(toy_config, data_dir, store, graph_of):
    (data_dir / "trial001.txt").write_text("oops\n")
    r = run(graph_of(toy_config), store, fail_fast=True)
    assert r.counts == {"hit": 0, "computed": 1, "failed": 1, "skipped": 14}
    assert {x["error"] for x in r.records if x["status"] == "skipped"} == {
        "cancelled (--fail-fast)"}


def test_lock_then_frozen_reproduces_and_detects_changed_input(tmp_path, toy_config, data_dir,
                                                                store, graph_of):
    g = graph_of(toy_config)
    r = run(g, store)
    lock_path = write_lock(tmp_path / "toy.lock.json", lock_document(g, r.records))
    lock = read_lock(lock_path)
    assert len(lock) == 16
    fresh = Store(tmp_path / "fresh")
    r2 = run(graph_of(toy_config), fresh, lock=lock)
    assert r2.ok and r2.counts["computed"] == 16 and r2.digests() == r.digests()
    # a changed input file: refused before anything runs, naming the part
    f = data_dir / "trial003.txt"
    f.write_text("3 4 5 6 8\n")
    other = Store(tmp_path / "other")
    with pytest.raises(FrozenError, match=rf"frozen: read/{f}: key differs from the lock "
                                          r"\(input path changed"):
        run(graph_of(toy_config), other, lock=lock)
    assert other.entries() == []
    # an output digest that differs (a non-deterministic stage) is reported after the run
    f.write_text("3.0 4.0 5.0 6.0 7.0\n")
    doc = json.loads(lock_path.read_text())
    doc["tasks"][7]["outputs"]["values"] = "0" * 64
    lock_path.write_text(json.dumps(doc))
    r3 = run(graph_of(toy_config), Store(tmp_path / "third"), lock=read_lock(lock_path))
    t = doc["tasks"][7]
    assert r3.frozen_problems == [f"{t['node']}/{t['part']}: output values digest differs from "
                                  "the lock"]
    assert not r3.ok


def test_force_recomputes_node_downstream_stays_hits(toy_config, store, graph_of):
    run(graph_of(toy_config), store)
    g = graph_of(toy_config)
    assert {p.reason for p in plan(g, store, force=["add"]) if p.node == "add"} == {
        "forced (--force)"}
    r = run(g, store, force=["add"])
    assert _by_node(r, "computed") == {"add": 5}
    assert _by_node(r, "hit") == {"read": 5, "scale": 5, "total": 1}


def test_filepath_param_is_keyed_by_content(tmp_path, store):
    off = tmp_path / "off.txt"
    off.write_text("1 2\n")
    cfg = write_config(tmp_path / "o.yaml", f"""\
        nodes:
          src: {{stage: toy_source, params: {{n: 3}}}}
          offset: {{stage: toy_offset, inputs: {{values: src.values}},
                params: {{offset_file: "{off}"}}}}
        """)
    from mocapflow.pipeline.config import load_config
    from mocapflow.pipeline.graph import build_graph

    r = run(build_graph(load_config(cfg)), store)
    np.testing.assert_array_equal(
        codecs.decode(store.load("toy_offset", r.records[1]["key"], "values")), [3.0, 4.0, 5.0])
    moved = tmp_path / "moved.txt"
    shutil.copy(off, moved)
    g = build_graph(load_config(cfg, sets=[f"offset.offset_file={moved}"]))
    assert [p.status for p in plan(g, store)] == ["hit", "hit"]  # same content, other path
    moved.write_text("5\n")
    p = plan(build_graph(load_config(cfg, sets=[f"offset.offset_file={moved}"])), store)
    assert p[1].status == "compute" and p[1].reason.startswith("param offset_file.file:")


def test_seeded_stages_are_reproducible_and_match_direct_calls(tmp_path, graph_of):
    cfg = write_config(tmp_path / "s.yaml", """\
        nodes:
          src: {stage: toy_source, seeds: {count: 3}, params: {n: 6, noise: 1.0}}
          sq: {stage: toy_map, inputs: {values: src.values}, params: {chunks: 3}}
        """)
    a, b = Store(tmp_path / "a"), Store(tmp_path / "b")
    ra, rb = run(graph_of(cfg), a), run(graph_of(cfg), b)
    assert ra.digests() == rb.digests()
    srcs = [r for r in ra.records if r["node"] == "src"]
    assert len({r["outputs"]["values"] for r in srcs}) == 3  # every seed differs
    got = codecs.decode(a.load("toy_source", srcs[1]["key"], "values"))
    want = toy_source(n=6, noise=1.0, seed=1, ctx=Context(part="seed=1", seed=1))["values"]
    np.testing.assert_array_equal(got, want)
    sq = next(r for r in ra.records if r["node"] == "sq" and r["part"] == "seed=1")
    np.testing.assert_array_equal(codecs.decode(a.load("toy_map", sq["key"], "values")), want**2)
    assert codecs.decode(a.load("toy_map", sq["key"], "pids")) == [os.getpid()] * 3  # sync map


def test_retries(tmp_path, store, graph_of):
    text = """\
        nodes:
          src: {{stage: toy_source, params: {{n: 2}}}}
          flaky: {{stage: toy_flaky, inputs: {{values: src.values}},
                  params: {{marker_dir: "{d}", fail_times: {k}}}}}
        """
    ok = write_config(tmp_path / "ok.yaml", text, d=tmp_path / "m1", k=2)
    r = run(graph_of(ok), store)
    assert r.ok
    assert store.manifest("toy_flaky", r.records[1]["key"])["attempts"] == 3
    bad = write_config(tmp_path / "bad.yaml", text, d=tmp_path / "m2", k=3)
    r = run(graph_of(bad), store)
    assert r.records[1]["status"] == "failed"
    assert r.records[1]["error"] == "RuntimeError: flaky failure 3 of 3 (after 3 attempts)"


@stage("toy_wrong_outputs_test", outputs=("a", "b"))
def _wrong_outputs(values):
    return {"a": values}


@stage("toy_impure_test", outputs=("values",))
def _impure(*, n: int = 3):
    return {"values": np.random.default_rng().standard_normal(n)}


def test_stage_contract_violations(tmp_path, store, graph_of):
    cfg = write_config(tmp_path / "w.yaml", """\
        nodes:
          src: {stage: toy_source}
          w: {stage: toy_wrong_outputs_test, inputs: {values: src.values}}
        """)
    r = run(graph_of(cfg), store)
    assert r.records[1]["error"] == ("ValueError: stage 'toy_wrong_outputs_test' returned "
                                     "outputs ['a'], declared ['a', 'b']")
    assert not store.has("toy_wrong_outputs_test", r.records[1]["key"] or "x" * 32)
    assert_stage_contract("toy_source", params={"n": 5, "noise": 1.0}, part="p")
    with pytest.raises(AssertionError, match="impure"):
        assert_stage_contract("toy_impure_test")
