"""Run on the sync executor: caching, early cutoff, failures, fail-fast, force."""

from __future__ import annotations

import numpy as np

from mocapflow.pipeline.plan import last_components, plan
from mocapflow.pipeline.runner import run
from tests.pipeline.helpers import by_node, total_of


def _statuses(result):
    return {(r["node"], r["part"]): r["status"] for r in result.records}


def test_unchanged_rerun_is_all_hits_and_plan_gives_reasons(toy_config, store, graph_of):
    g = graph_of(toy_config)
    first = plan(g, store)
    assert [p.status for p in first] == ["compute"] * 5 + ["pending"] * 11
    assert all(p.reason.startswith("no entry for key ") for p in first[:5])
    assert first[5].reason == f"upstream read/{first[0].part} will recompute"
    r1 = run(g, store)
    assert r1.ok and r1.counts == {"hit": 0, "computed": 16, "failed": 0, "skipped": 0}
    # files hold i..i+4: total_i = 2 * (5 i + 10 + 5 * amount)
    np.testing.assert_array_equal(total_of(store, r1), [2 * (5 * i + 10 + 5) for i in range(5)])
    r2 = run(graph_of(toy_config), store)
    assert r2.counts == {"hit": 16, "computed": 0, "failed": 0, "skipped": 0}
    assert r2.digests() == r1.digests()
    assert [(p.status, p.reason) for p in plan(g, store)] == [("hit", "hit")] * 16
    # every task is in the run record with its key; a hit's components are its entry's
    rec = store.runs()[-1]
    assert rec["run_id"] == r2.run_id and len(rec["tasks"]) == 16
    assert {t["status"] for t in rec["tasks"]} == {"hit"}
    assert not any("components" in t or "traceback" in t for t in rec["tasks"])
    assert all(t["key"] and t["outputs"] and last_components(store, t)["stage"] == t["stage"]
               for t in rec["tasks"])
    first = store.runs()[-2]["tasks"]  # computed tasks keep theirs
    assert all(t["status"] == "computed" and t["components"]["stage"] == t["stage"]
               for t in first)


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
    assert by_node(r2, "computed") == {"read": 1}  # early cutoff: add/scale/total stay hits
    assert r2.counts["hit"] == 15
    assert r2.digests() == r1.digests()


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
    assert by_node(r, "computed") == {"read": 4, "add": 4, "scale": 4}
    # the other parts are committed; the run record has the traceback
    assert len(store.entries()) == 12
    rec = store.runs()[-1]
    t = next(t for t in rec["tasks"] if t["status"] == "failed")
    assert "Traceback" in t["traceback"] and "not a number" in t["traceback"]
    # fixing the file: only the broken part and the gather run
    bad.write_text("2 3 4 5 6\n")
    r2 = run(graph_of(toy_config), store)
    assert r2.ok and by_node(r2, "computed") == {"read": 1, "add": 1, "scale": 1, "total": 1}


def test_fail_fast_stops_early(toy_config, data_dir, store, graph_of):
    (data_dir / "trial001.txt").write_text("oops\n")
    r = run(graph_of(toy_config), store, fail_fast=True)
    assert r.counts == {"hit": 0, "computed": 1, "failed": 1, "skipped": 14}
    assert {x["error"] for x in r.records if x["status"] == "skipped"} == {
        "cancelled (--fail-fast)"}


def test_force_recomputes_node_downstream_stays_hits(toy_config, store, graph_of):
    run(graph_of(toy_config), store)
    g = graph_of(toy_config)
    assert {p.reason for p in plan(g, store, force=["add"]) if p.node == "add"} == {
        "forced (--force)"}
    r = run(g, store, force=["add"])
    assert by_node(r, "computed") == {"add": 5}
    assert by_node(r, "hit") == {"read": 5, "scale": 5, "total": 1}
