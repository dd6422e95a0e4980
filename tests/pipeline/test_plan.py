"""Plan and explain: reasons for what would run, against the last run record."""

from __future__ import annotations

import numpy as np

from mocapflow.pipeline.plan import explain, plan
from mocapflow.pipeline.runner import run
from tests.pipeline.helpers import by_node, total_of


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
    assert by_node(r, "computed") == {"add": 5, "scale": 5, "total": 1}
    assert by_node(r, "hit") == {"read": 5}
    np.testing.assert_array_equal(total_of(store, r), [2 * (5 * i + 10 + 12.5) for i in range(5)])
    # after the run nothing changed any more
    assert explain(g, store, "add/trial003")[0]["changes"] == []


def test_reasons_after_a_no_op_run_come_from_the_hits_entries(toy_config, store, graph_of):
    """A hit's run record has no components: plan and explain read its entry's."""
    run(graph_of(toy_config), store)
    run(graph_of(toy_config), store)  # every task a hit: the last record of each
    assert all("components" not in t for t in store.runs()[-1]["tasks"])
    g = graph_of(toy_config, sets=["add.amount=2.5"])
    reasons = {(p.node, p.status, p.reason) for p in plan(g, store)}
    assert ("add", "compute", "param amount: 1.0 -> 2.5") in reasons
    assert explain(g, store, "add/trial003")[0]["changes"] == ["param amount: 1.0 -> 2.5"]
    ex = explain(g, store, "scale/trial003")[0]["changes"]
    assert ex[0].startswith("upstream add/")
