"""Nodes × parts → tasks: file parts, seeds, gather, prefix matching, broadcast, selection."""

from __future__ import annotations

import pytest

from mocapflow.pipeline.config import ConfigError, parse_config
from mocapflow.pipeline.graph import build_graph, part_label
from mocapflow.pipeline.wires import FileWire, TasksWire, TaskWire


def _graph(text, targets=None):
    return build_graph(parse_config(text, file="g.yaml"), targets)


def test_file_parts_and_topological_order(data_dir):
    g = _graph(f"""
parts: ["{data_dir}/*.txt"]
nodes:
  total: {{stage: toy_sum, inputs: {{values: scale.values}}, gather: true}}
  scale: {{stage: toy_scale, inputs: {{values: read.values}}}}
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
""")
    files = [str(data_dir / f"trial{i:03d}.txt") for i in range(5)]
    assert g.nodes == ["read", "scale", "total"]
    assert [t.part for t in g.node_tasks("read")] == files
    assert [t.inputs["path"] for t in g.node_tasks("read")] == [FileWire(f) for f in files]
    assert len(g.tasks) == 11
    for t in g.tasks:
        assert all(d < t.index for d in t.deps())
    scale = g.task("scale", files[2])
    assert scale.inputs == {"values": TaskWire(g.task("read", files[2]).index, "values")}
    total = g.task("total", None)
    assert isinstance(total.inputs["values"], TasksWire)
    # ordered by part
    assert [g.tasks[w.index].part for w in total.inputs["values"].sources] == files


def test_seed_fanout_prefix_matching_and_broadcast(data_dir):
    g = _graph(f"""
parts: ["{data_dir}/trial00[01].txt"]
nodes:
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
  noisy: {{stage: toy_source, seeds: [3, 4]}}
  total: {{stage: toy_sum, inputs: {{values: read.values}}, gather: true}}
  flaky:
    stage: toy_flaky
    inputs: {{values: read.values}}
    params: {{marker_dir: x}}
  seeded:
    stage: toy_map
    inputs: {{values: read.values}}
    seeds: {{count: 2}}
    params: {{chunks: 2}}
  both:
    stage: toy_sum
    inputs: {{values: seeded.values}}
  mix:
    stage: toy_offset
    inputs: {{values: seeded.values}}
  below_gather:
    stage: toy_source
    seeds: [5]
""")
    f0, f1 = (str(data_dir / f"trial00{i}.txt") for i in range(2))
    # a source without file input has one task per seed
    assert [t.part for t in g.node_tasks("noisy")] == ["seed=3", "seed=4"]
    assert [t.params["seed"] for t in g.node_tasks("noisy")] == [3, 4]
    assert [t.part for t in g.node_tasks("seeded")] == [
        f"{f0}#seed=0", f"{f0}#seed=1", f"{f1}#seed=0", f"{f1}#seed=1"]
    # the seeded task for part q reads the file-level task whose part is q's prefix
    t = g.task("seeded", f"{f1}#seed=1")
    assert g.tasks[t.inputs["values"].index].part == f1 and t.seed == 1 and "seed" not in t.params
    # downstream of a seeded node: one task per seeded part
    assert [t.part for t in g.node_tasks("mix")] == [t.part for t in g.node_tasks("seeded")]
    assert [t.part for t in g.node_tasks("below_gather")] == ["seed=5"]


def test_gather_output_is_broadcast(data_dir):
    g = _graph(f"""
parts: ["{data_dir}/trial00[012].txt"]
nodes:
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
  total: {{stage: toy_sum, inputs: {{values: read.values}}, gather: true}}
  per: {{stage: toy_add, inputs: {{values: total.total}}, seeds: null}}
  pair: {{stage: toy_sum, inputs: {{values: read.values}}}}
""")
    total = g.task("total", None).index
    assert [t.inputs["values"] for t in g.node_tasks("per")] == [TaskWire(total, "total")]
    g2 = _graph(f"""
parts: ["{data_dir}/trial00[012].txt"]
nodes:
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
  total: {{stage: toy_sum, inputs: {{values: read.values}}, gather: true}}
  src: {{stage: toy_map, inputs: {{values: read.values}}}}
  both: {{stage: toy_offset, inputs: {{values: total.total}}}}
""")
    assert len(g2.node_tasks("both")) == 1
    # a per-part node fed by per-part and gathered inputs: one task per part, gather broadcast
    g3 = build_graph(parse_config(f"""
parts: ["{data_dir}/trial00[012].txt"]
nodes:
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
  total: {{stage: toy_sum, inputs: {{values: read.values}}, gather: true}}
  stats: {{stage: toy_stats, inputs: {{values: read.values}}}}
  final: {{stage: toy_sum, inputs: {{values: stats.summary}}, gather: true}}
"""))
    assert len(g3.node_tasks("stats")) == 3 and len(g3.node_tasks("final")) == 1


def test_broadcast_into_per_part_node(tmp_path):
    from mocapflow.pipeline.registry import stage

    @stage("toy_pair_for_graph_test", outputs=("values",))
    def pair(values, total):
        return {"values": values}

    g = _graph("""
nodes:
  src: {stage: toy_source, seeds: {count: 3}}
  total: {stage: toy_sum, inputs: {values: src.values}, gather: true}
  pair: {stage: toy_pair_for_graph_test, inputs: {values: src.values, total: total.total}}
""")
    total = g.task("total", None).index
    tasks = g.node_tasks("pair")
    assert [t.part for t in tasks] == ["seed=0", "seed=1", "seed=2"]
    assert all(t.inputs["total"] == TaskWire(total, "total") for t in tasks)
    assert [g.tasks[t.inputs["values"].index].part for t in tasks] == ["seed=0", "seed=1", "seed=2"]


def test_mismatched_fanouts_are_an_error():
    from mocapflow.pipeline.registry import stage

    @stage("toy_pair2_for_graph_test", outputs=("values",))
    def pair(a, b):
        return {"values": a}

    with pytest.raises(ConfigError, match=r"^g\.yaml:5: nodes\.p\.inputs: inputs fan out"):
        _graph("""
nodes:
  a: {stage: toy_source, seeds: [1, 2]}
  b: {stage: toy_source, seeds: [3]}
  p: {stage: toy_pair2_for_graph_test, inputs: {a: a.values, b: b.values}}
""")


def test_targets_select_ancestors_only(data_dir):
    text = f"""
parts: ["{data_dir}/*.txt"]
targets: [total]
nodes:
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
  add: {{stage: toy_add, inputs: {{values: read.values}}}}
  side: {{stage: toy_scale, inputs: {{values: read.values}}}}
  total: {{stage: toy_sum, inputs: {{values: add.values}}, gather: true}}
"""
    g = _graph(text)
    assert g.nodes == ["read", "add", "total"] and len(g.tasks) == 11
    g = _graph(text, ["side"])
    assert g.nodes == ["read", "side"] and len(g.tasks) == 10
    with pytest.raises(ConfigError, match=r"--target: unknown node 'sid' \(did you mean 'side'"):
        _graph(text, ["sid"])
    # downstream() follows edges
    read0 = g.task("read", g.node_tasks("read")[0].part).index
    assert {g.tasks[i].node for i in g.downstream([read0])} == {"side"}


def test_find_and_part_label(data_dir):
    g = _graph(f"""
parts: ["{data_dir}/*.txt"]
nodes:
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
  s: {{stage: toy_map, inputs: {{values: read.values}}, seeds: [2]}}
""")
    assert [t.part for t in g.find("read/trial003")] == [str(data_dir / "trial003.txt")]
    assert len(g.find("read")) == 5
    with pytest.raises(KeyError, match="ambiguous"):
        g.find("read/trial00")
    with pytest.raises(KeyError, match="no part"):
        g.find("read/zzz")
    with pytest.raises(KeyError, match="did you mean 'read'"):
        g.find("reed")
    assert part_label(str(data_dir / "trial003.txt") + "#seed=2") == "trial003.seed2"
    assert part_label("seed=4") == "seed4"
    assert part_label(None) == "all"
    assert part_label("a/b.c.bvh") == "b.c"
