"""File overrides: a node reads one file named by a param once and is broadcast to every part."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline import FilePath, stage
from mocapflow.pipeline.codecs import decode
from mocapflow.pipeline.config import parse_config
from mocapflow.pipeline.graph import build_graph, file_overrides
from mocapflow.pipeline.runner import run
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.testing import read_numbers
from mocapflow.pipeline.wires import FileWire, TasksWire, TaskWire


@stage("toy_read_shared", outputs=("values",))
def toy_read_shared(path: FilePath, *, shared: FilePath | None = None) -> dict:
    """Numbers of ``path`` (the engine passes ``shared`` there when it is set)."""
    return {"values": read_numbers(path)}


toy_read_shared.__mocapflow_stage__.extra["file_overrides"] = {"path": "shared"}


def _config(data_dir: Path, shared: Path | None) -> str:
    value = "null" if shared is None else f'"{shared}"'
    return f"""
params: {{shared: {value}}}
parts: ["{data_dir}/trial00[012].txt"]
nodes:
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
  ref: {{stage: toy_read_shared, inputs: {{path: part}}, params: {{shared: ${{params.shared}}}}}}
  ref_scaled: {{stage: toy_scale, inputs: {{values: ref.values}}, params: {{factor: 10.0}}}}
  diff: {{stage: toy_add, inputs: {{values: read.values}}, params: {{amount: 1.0}}}}
  both: {{stage: toy_sum, inputs: {{values: ref_scaled.values}}, gather: true}}
"""


@pytest.fixture
def shared_file(tmp_path: Path) -> Path:
    p = tmp_path / "shared.txt"
    p.write_text("100 200 300\n")
    return p


def _graph(text: str, targets=None):
    return build_graph(parse_config(text, file="g.yaml"), targets)


def test_override_makes_one_task_broadcast_to_every_part(data_dir, shared_file):
    g = _graph(_config(data_dir, shared_file), ["ref_scaled", "diff", "both"])
    files = [str(data_dir / f"trial{i:03d}.txt") for i in range(3)]
    (ref,) = g.node_tasks("ref")
    assert ref.part is None
    assert ref.inputs == {"path": FileWire(str(shared_file))}
    assert file_overrides(g.config.nodes["ref"]) == {"path": str(shared_file)}
    (scaled,) = g.node_tasks("ref_scaled")  # single upstream task: a single task
    assert scaled.part is None and scaled.deps() == [ref.index]
    # per-part nodes are unaffected
    assert [t.part for t in g.node_tasks("read")] == files
    assert [t.inputs["path"] for t in g.node_tasks("read")] == [FileWire(f) for f in files]
    # a gather over a broadcast node reads its one task
    (both,) = g.node_tasks("both")
    assert both.inputs["values"] == TasksWire((TaskWire(scaled.index, "values"),))


def test_broadcast_task_feeds_every_part_of_a_mixed_node(data_dir, shared_file):
    text = _config(data_dir, shared_file) + (
        "  mixed: {stage: toy_stats, inputs: {values: ref.values}}\n"
        "  pair: {stage: toy_sum, inputs: {values: diff.values}, gather: true}\n"
    )
    g = _graph(text, ["mixed", "pair"])
    (ref,) = g.node_tasks("ref")
    assert [t.inputs["values"] for t in g.node_tasks("mixed")] == [TaskWire(ref.index, "values")]


def test_no_override_keeps_one_task_per_part(data_dir):
    g = _graph(_config(data_dir, None), ["ref_scaled"])
    files = [str(data_dir / f"trial{i:03d}.txt") for i in range(3)]
    assert [t.part for t in g.node_tasks("ref")] == files
    assert [t.inputs["path"] for t in g.node_tasks("ref")] == [FileWire(f) for f in files]
    assert [t.part for t in g.node_tasks("ref_scaled")] == files
    assert file_overrides(g.config.nodes["ref"]) == {}


def test_override_applies_only_to_part_wires(data_dir, shared_file):
    # wired to an upstream node, not to `part`: the declared override does not apply
    text = f"""
parts: ["{data_dir}/trial000.txt"]
nodes:
  src: {{stage: toy_read_file, inputs: {{path: part}}}}
  ref: {{stage: toy_read_shared, inputs: {{path: part}}, params: {{shared: "{shared_file}"}}}}
"""
    g = _graph(text)
    assert file_overrides(g.config.nodes["src"]) == {}
    assert g.node_tasks("ref")[0].part is None


def test_missing_override_file_is_a_config_error(data_dir, tmp_path):
    from mocapflow.pipeline.config import ConfigError

    with pytest.raises(ConfigError, match=r"nodes\.ref\.params\.shared.*missing input file"):
        _graph(_config(data_dir, tmp_path / "nope.txt"))


def test_run_computes_the_shared_node_once_and_keys_it_by_content(data_dir, shared_file,
                                                                  tmp_path):
    store = Store(tmp_path / "store")
    g = _graph(_config(data_dir, shared_file), ["ref_scaled", "diff"])
    res = run(g, store)
    by_node: dict[str, list[dict]] = {}
    for r in res.records:
        by_node.setdefault(r["node"], []).append(r)
    assert [r["status"] for r in by_node["ref"]] == ["computed"]
    assert [r["status"] for r in by_node["ref_scaled"]] == ["computed"]
    assert len(by_node["diff"]) == 3
    r = by_node["ref_scaled"][0]
    values = decode(store.load("toy_scale", r["key"], "values"))
    np.testing.assert_array_equal(values, [1000.0, 2000.0, 3000.0])
    # 1 ref + 1 ref_scaled + 3 read + 3 diff; a rerun is all hits
    again = run(_graph(_config(data_dir, shared_file), ["ref_scaled", "diff"]), store)
    assert again.counts == {"hit": 8, "computed": 0, "failed": 0, "skipped": 0}
    # new content in the shared file: only the shared node and its consumer recompute
    shared_file.write_text("1 2 3\n")
    third = run(_graph(_config(data_dir, shared_file), ["ref_scaled", "diff"]), store)
    computed = sorted(r["node"] for r in third.records if r["status"] == "computed")
    assert computed == ["ref", "ref_scaled"]


def test_dag_shows_the_file_read_once(cli, data_dir, shared_file, tmp_path):
    cfg = tmp_path / "g.yaml"
    cfg.write_text(_config(data_dir, shared_file))
    code, out, err = cli("dag", cfg, "--target", "ref_scaled", "--target", "diff")
    assert code == 0, err
    (ref,) = [line for line in out.splitlines() if line.strip().startswith("ref ")]
    assert "×1" in ref and "path=file:shared.txt" in ref
    (read,) = [line for line in out.splitlines() if line.strip().startswith("read ")]
    assert "×3" in read and "path=part" in read
