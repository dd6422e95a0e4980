"""Lock files and ``--frozen`` runs: reproduced builds, changed inputs, changed digests."""

from __future__ import annotations

import json

import pytest

from mocapflow.pipeline.lock import FrozenError, lock_document, read_lock, write_lock
from mocapflow.pipeline.runner import run
from mocapflow.pipeline.store import Store


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
