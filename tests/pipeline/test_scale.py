"""Engine work at scale, counted (times are measured in ``benchmarks/engine.py --scale``).

A graph of P parts must cost O(P): each upstream matcher built once (not once per
task: 16 s at 10,000 parts), each manifest read and each key computed once in a
no-op re-run, the run record written by the C JSON encoder, and no garbage
collection passes over the plan's objects.
"""

from __future__ import annotations

import gc
import json

from mocapflow.pipeline import graph as graph_mod
from mocapflow.pipeline import keys, plan
from mocapflow.pipeline.config import load_config
from mocapflow.pipeline.runner import run
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.testing import TOY_CONFIG, write_config, write_number_files


def _toy(tmp_path, parts: int):
    files = write_number_files(tmp_path / f"data{parts}", parts)
    return write_config(tmp_path / f"toy{parts}.yaml", TOY_CONFIG,
                        parts=f"{files[0].parent}/*.txt")


def test_graph_builds_each_upstream_matcher_once(tmp_path, monkeypatch):
    built = []
    real = graph_mod._matcher
    monkeypatch.setattr(graph_mod, "_matcher", lambda parts, *a, **k: built.append(len(parts))
                        or real(parts, *a, **k))
    counts = {}
    for parts in (40, 160):
        built.clear()
        g = graph_mod.build_graph(load_config(_toy(tmp_path, parts)))
        counts[parts] = len(built)
        read = {t.part: t.index for t in g.node_tasks("read")}
        for t in g.node_tasks("add"):  # each add reads its own part's read task
            assert t.inputs["values"].index == read[t.part]
    assert counts[40] == counts[160] <= 6  # per node, not per task (was 2 × parts + …)


def test_noop_rerun_reads_each_manifest_and_computes_each_key_once(tmp_path, monkeypatch):
    cfg = _toy(tmp_path, 50)
    store = Store(tmp_path / "s")
    first = run(graph_mod.build_graph(load_config(cfg)), store)
    n = len(first.records)
    assert first.ok and n == 151
    calls = {"manifest": 0, "task_key": 0, "commit": 0}
    for obj, name in ((Store, "manifest"), (keys, "task_key"), (Store, "commit")):
        real = getattr(obj, name)

        def counted(*a, _real=real, _name=name, **kw):
            calls[_name] += 1
            return _real(*a, **kw)

        monkeypatch.setattr(obj, name, counted)
    again = run(graph_mod.build_graph(load_config(cfg)), store)
    assert again.counts["hit"] == n
    assert calls == {"manifest": n, "task_key": n, "commit": 0}
    raw = (tmp_path / "s" / "runs" / f"{again.run_id}.json").read_bytes()
    assert b"\n" not in raw  # written compact (the C encoder), and whole
    assert len(json.loads(raw)["tasks"]) == n


def test_plan_runs_without_garbage_collection_and_restores_it(tmp_path, monkeypatch):
    cfg = _toy(tmp_path, 5)
    store = Store(tmp_path / "s")
    seen = []
    real = Store.manifest
    monkeypatch.setattr(Store, "manifest", lambda self, *a: seen.append(gc.isenabled())
                        or real(self, *a))
    g = graph_mod.build_graph(load_config(cfg))
    assert gc.isenabled()
    plan.plan(g, store)
    assert seen and not any(seen) and gc.isenabled()
    gc.disable()
    try:
        plan.plan(g, store)
        assert not gc.isenabled()  # left as it was
    finally:
        gc.enable()
