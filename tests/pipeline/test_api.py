"""The Python API: ``mocapflow.run`` and its Results, direct stage calls, short reprs."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import numpy as np
import pytest

import mocapflow
from mocapflow.pipeline.api import Outputs, Results, TaskFailedError
from mocapflow.pipeline.config import ConfigError
from mocapflow.pipeline.context import Context
from mocapflow.pipeline.registry import ParamError, lookup
from mocapflow.pipeline.testing import toy_source, write_config
from mocapflow.stages.motion.datatypes import Markers, Mesh, Motion, Skeleton, Strokes, StrokesSet
from mocapflow.stages.motion.simulate.motion import simulate_walk
from mocapflow.stages.skin.clean import clean
from mocapflow.stages.skin.render import Video

ROOT = Path(__file__).resolve().parents[2]
SHARED_DATA = ROOT.parent / "shared" / "data"
LABELS = [f"trial{i:03d}" for i in range(5)]


def test_top_level_exports():
    assert mocapflow.run is __import__("mocapflow.pipeline.api").pipeline.api.run
    assert mocapflow.Results is Results and mocapflow.Context is Context
    assert {"run", "Results", "Context", "open_entry"} <= set(mocapflow.__all__)
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        _ = mocapflow.nope


def test_run_keys_results_by_node_and_part_label(toy_config, tmp_path):
    res = mocapflow.run(toy_config, store=tmp_path / "store")
    assert isinstance(res, Results) and res.ok and res.failures == []
    assert list(res) == [(n, p) for n in ("read", "add", "scale") for p in LABELS] + [
        ("total", "all")]
    assert res.counts == {"hit": 0, "computed": 16, "failed": 0, "skipped": 0}
    assert len(res.records) == 16 and (tmp_path / "store" / "runs" / f"{res.run_id}.json").is_file()
    # trial i holds i..i+4; +1 then x2: part sums 10 i + 30
    np.testing.assert_array_equal(res["total"]["total"], [30.0, 40.0, 50.0, 60.0, 70.0])
    assert res["total"]["report"] == {"parts": 5, "grand_total": 250.0}
    np.testing.assert_array_equal(res["add/trial001"]["values"], [2.0, 3.0, 4.0, 5.0, 6.0])
    np.testing.assert_array_equal(res["scale", "trial002"]["values"], [6.0, 8.0, 10.0, 12.0, 14.0])
    part_id = res.record("read/trial004").part  # the part id names it too
    np.testing.assert_array_equal(res["read", part_id]["values"], [4.0, 5.0, 6.0, 7.0, 8.0])
    assert res.key(("total", None)) == ("total", "all")
    assert "add/trial003" in res and "add/trial009" not in res and "nope" not in res
    with pytest.raises(KeyError,
                       match=r"node 'add' has 5 parts \(trial000, .*res\['add/trial000'\]"):
        res["add"]
    with pytest.raises(KeyError, match="unknown node 'ad' \\(did you mean 'add'\\?\\)"):
        res["ad"]
    with pytest.raises(KeyError, match="has no output 'value' \\(outputs: values\\)"):
        res["add/trial001"]["value"]


def test_run_takes_parts_set_targets_and_a_node_of_one_part(toy_config, data_dir, tmp_path):
    res = mocapflow.run(toy_config, parts=str(data_dir / "trial002.txt"),
                        set={"add.amount": 10.0}, targets="scale", store=tmp_path / "s")
    assert list(res) == [("read", "trial002"), ("add", "trial002"), ("scale", "trial002")]
    np.testing.assert_array_equal(res["scale"]["values"], [24.0, 26.0, 28.0, 30.0, 32.0])


def test_default_store_is_env_then_dot_mocapflow(toy_config, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MOCAPFLOW_STORE", raising=False)
    assert mocapflow.run(toy_config, targets="read").store.root == str(tmp_path / ".mocapflow")
    assert (tmp_path / ".mocapflow" / "runs").is_dir()
    monkeypatch.setenv("MOCAPFLOW_STORE", str(tmp_path / "env_store"))
    res = mocapflow.run(toy_config, targets="read")
    assert res.counts["computed"] == 5 and (tmp_path / "env_store" / "runs").is_dir()


def test_rerun_hits_and_force_recomputes(toy_config, tmp_path):
    first = mocapflow.run(toy_config, store=tmp_path / "store")
    again = mocapflow.run(toy_config, store=tmp_path / "store")
    assert again.counts == {"hit": 16, "computed": 0, "failed": 0, "skipped": 0}
    assert again.run_id != first.run_id
    np.testing.assert_array_equal(again["total"]["total"], first["total"]["total"])
    forced = mocapflow.run(toy_config, store=tmp_path / "store", force="scale")
    assert [r.status for r in forced.records if r.node == "scale"] == ["computed"] * 5
    assert forced.records[0].status == "hit"
    assert mocapflow.run(toy_config, store=tmp_path / "store", force=True).counts["computed"] == 16


FAIL_CONFIG = """\
graph: failing
parts: ["{parts}"]
targets: [scale]
nodes:
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
  check: {{stage: toy_fail_on, inputs: {{values: read.values}}, params: {{pattern: trial001}}}}
  scale: {{stage: toy_scale, inputs: {{values: check.values}}}}
"""


def test_failed_tasks_warn_and_raise_when_read(tmp_path, data_dir):
    config = write_config(tmp_path / "fail.yaml", FAIL_CONFIG, parts=f"{data_dir}/*.txt")
    with pytest.warns(RuntimeWarning, match=r"^2 task\(s\) of failing did not commit: "
                      r"check/.*trial001.txt failed: ValueError: .*\(and 1 more"):
        res = mocapflow.run(config, store=tmp_path / "store")
    assert not res.ok
    assert [(r.node, r.status) for r in res.failures] == [("check", "failed"), ("scale", "skipped")]
    with pytest.raises(TaskFailedError, match=r"^check/.*trial001.txt failed: ValueError: part"):
        res["check/trial001"]
    with pytest.raises(TaskFailedError, match="scale/.*trial001.txt skipped"):
        res["scale", "trial001"]
    np.testing.assert_array_equal(res["scale/trial003"]["values"], [6.0, 8.0, 10.0, 12.0, 14.0])
    with pytest.raises(TaskFailedError, match="^2 task"):
        res.raise_for_failures()
    assert re.search(r"\n  check  trial001  failed: ValueError: part", repr(res))
    mocapflow.run(config, store=tmp_path / "store", targets="read").raise_for_failures()


def test_bad_config_param_and_workers_raise_before_running(toy_config, tmp_path):
    with pytest.raises(ConfigError, match="add.amount: param toy_add.amount: expected a number, "
                       "got 'lots'"):
        mocapflow.run(toy_config, set={"add.amount": "lots"}, store=tmp_path / "s")
    with pytest.raises(ValueError, match="workers must be at least 1, got 0"):
        mocapflow.run(toy_config, executor="local", workers=0, store=tmp_path / "s")
    assert not (tmp_path / "s").exists()


WALK_CONFIG = """\
graph: walk
targets: [walk]
nodes:
  walk: {stage: simulate_walk, params: {n_frames: 90, rate: 60, seed: 3}}
"""


def test_outputs_are_decoded_domain_objects_equal_to_a_direct_call(tmp_path):
    config = write_config(tmp_path / "walk.yaml", WALK_CONFIG)
    res = mocapflow.run(config, store=tmp_path / "store")
    out = res["walk"]
    assert isinstance(out, Outputs) and list(out) == ["motion"]
    motion = out["motion"]
    assert isinstance(motion, Motion) and motion.n_frames == 90 and motion.rate == 60.0
    assert out["motion"] is motion  # decoded once
    direct = simulate_walk(n_frames=90, rate=60, seed=3)["motion"]  # default ctx: same numbers
    np.testing.assert_array_equal(direct.rotations, motion.rotations)
    np.testing.assert_array_equal(direct.root_position, motion.root_position)
    assert repr(out) == (f"Outputs of walk/all (entry simulate_walk/{res.record('walk').key[:12]}):"
                         f"\n  motion: {motion!r}")
    assert repr(motion) == "Motion(90 frames × 31 joints @ 60 Hz, 1.5 s, root 'Hips')"


def test_results_and_outputs_reprs_are_short(toy_config, tmp_path):
    res = mocapflow.run(toy_config, store=tmp_path / "store")
    lines = repr(res).splitlines()
    assert re.fullmatch(r"Results of toy \(run \S+, 16 tasks: 16 computed\)", lines[0])
    assert lines[1:3] == ["  read   trial000  computed", "  read   trial001  computed"]
    assert lines[-1] == "  total  all       computed" and len(lines) == 17
    assert repr(res["total"]).splitlines()[1:] == [
        "  total: ndarray float64 (5,)", "  report: {'parts': 5, 'grand_total': 250.0}"]


# --------------------------------------------------------------------------- direct calls


def _markers(frames: int = 4, n: int = 3) -> Markers:
    return Markers(np.zeros((frames, n, 3)), [f"M{i}" for i in range(n)], 100.0)


def test_direct_call_validates_params_like_the_engine():
    m = _markers()
    with pytest.raises(ParamError) as e:
        clean(m, alpha1="lots")
    assert str(e.value) == "param clean.alpha1: expected a number, got 'lots'"
    with pytest.raises(ParamError, match=r"^unknown param 'alpha' \(did you mean 'alpha2'\?\) "
                       r"for stage 'clean'$"):
        clean(m, alpha=0.4)
    with pytest.raises(ParamError, match=r"^param clean.fill_model: 'nope' is not one of"):
        clean(m, fill_model="nope")
    with pytest.raises(TypeError, match="stage 'clean': missing input 'markers'"):
        clean(alpha1=0.4)
    with pytest.raises(ParamError, match=r"simulate_walk.speed: 'fast' does not fit float \| None"):
        simulate_walk(speed="fast")


def test_direct_call_keeps_the_function_and_the_engine_bypasses_the_wrapper():
    spec = lookup("clean")
    assert clean.__wrapped__ is spec.func and clean.__mocapflow_stage__ is spec
    assert inspect.signature(clean) == inspect.signature(spec.func)
    assert clean.__doc__ == spec.func.__doc__ and clean.__name__ == "clean"
    assert "def clean(" in inspect.getsource(spec.func)


def test_direct_call_makes_a_context_seeded_from_the_seed_param():
    a = toy_source(n=6, noise=1.0, seed=7)["values"]
    b = toy_source(n=6, noise=1.0, seed=7, ctx=Context(seed=7))["values"]
    c = toy_source(n=6, noise=1.0, seed=8)["values"]
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c) and a[0] != 0.0


# --------------------------------------------------------------------------- reprs


def test_domain_reprs_are_one_short_line():
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(1000, 350, 3))
    pos[rng.random((1000, 350)) < 0.021] = np.nan
    m = Markers(pos, [f"marker_{i}" for i in range(350)], 120, attrs={"up": "+z"})
    filled = m.replace(status=np.where(np.isnan(pos[..., 0]), 2, 0).astype(np.int8))
    assert repr(filled).endswith("2.1% missing, 2.1% filled)")
    skel = Skeleton([f"j{i}" for i in range(40)], np.arange(-1, 39), np.zeros((40, 3)),
                    [["Zrotation"]] * 40, end_parents=[39, 20], end_offsets=np.ones((2, 3)))
    rot = np.zeros((3000, 40, 4))
    rot[..., 0] = 1.0
    motion = Motion(skel, np.zeros((3000, 3)), rot, 120.0, attrs={"up": "+y"})
    mesh = Mesh(np.zeros((500, 6890, 3)), np.tile([0, 1, 2], (13776, 1)), rate=60.0,
                point_data={"error_mm": np.zeros((500, 6890))})
    strokes = Strokes(np.zeros((5000, 2)), [0, 100, 2500], 200.0, attrs={"letter": "a"})
    video = Video(np.zeros((30, 480, 640, 3), np.uint8), 30.0)
    expected = [
        (m, "Markers(1000 frames × 350 markers @ 120 Hz, up +z, 2.1% missing)"),
        (skel, "Skeleton(40 joints, root 'j0', 2 end sites)"),
        (motion, "Motion(3000 frames × 40 joints @ 120 Hz, 25 s, root 'j0', up +y)"),
        (mesh, "Mesh(500 frames × 6890 vertices @ 60 Hz, 13776 faces, point data: error_mm)"),
        (strokes, "Strokes(5000 samples in 3 strokes @ 200 Hz, letter 'a')"),
        (StrokesSet([strokes] * 5), "StrokesSet(5 examples, 25000 samples)"),
        (video, "Video(30 frames of 640×480 px @ 30 Hz)"),
        (Mesh(np.zeros((4, 3)), [[0, 1, 2]]), "Mesh(4 vertices, 1 faces)"),
    ]
    for obj, text in expected:
        assert repr(obj) == text and len(repr(obj)) < 300
    assert len(repr({"markers": m, "motion": motion})) < 300


# --------------------------------------------------------------------------- README


def readme_from_python_block() -> str:
    """The ``python`` block under the README's ``### From Python`` heading."""
    section = (ROOT / "README.md").read_text().split("\n### From Python\n", 1)[1]
    section = re.split(r"\n##+ ", section, maxsplit=1)[0]
    block = re.search(r"```python\n(.*?)```", section, re.S)
    assert block is not None, "no python block under ### From Python"
    return block.group(1)


@pytest.mark.skipif(not SHARED_DATA.is_dir(), reason="sample data ../shared/data absent")
def test_readme_from_python_block_runs_as_written(tmp_path, monkeypatch, capsys):
    code = readme_from_python_block()
    assert "mocapflow.run(" in code and "simulate_walk(" in code
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MOCAPFLOW_STORE", str(tmp_path / "store"))
    monkeypatch.setenv("MOCAPFLOW_DATA", str(SHARED_DATA))
    exec(compile(code, "README.md", "exec"), {"__name__": "__readme__"})
    printed = capsys.readouterr().out
    # every "print(x)   # Type(...)" comment is what the line printed
    shown = re.findall(r"^print\(.*?\)\s+# (\w+\(.*\))$", code, re.M)
    assert len(shown) == 2 and all(s in printed for s in shown), printed
    assert "synth    cmu_131_02.seed0  computed" in printed
    assert (tmp_path / "store" / "runs").is_dir() and not (tmp_path / ".mocapflow").exists()
