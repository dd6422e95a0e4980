"""One task: seeded contexts, retries, stage contract violations."""

from __future__ import annotations

import os

import numpy as np
import pytest

from mocapflow.pipeline import codecs
from mocapflow.pipeline.context import Context
from mocapflow.pipeline.registry import stage
from mocapflow.pipeline.runner import run
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.testing import assert_stage_contract, toy_source, write_config


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


def test_output_dims_name_a_bare_ndarray_output():
    """``@stage(output_dims=...)``: a bare ndarray output is stored with those dimension
    names, not ``dim_0 …``; a wrong axis count or an unknown output is refused."""
    from mocapflow.pipeline.execute import _encode_outputs  # noqa: PLC0415
    from mocapflow.pipeline.registry import find_stage  # noqa: PLC0415

    @stage("dims_probe_stage", outputs=("track", "other"), output_dims={"track": ("frame",)})
    def dims_probe_stage(*, n: int = 3) -> dict:
        return {"track": np.arange(n), "other": np.zeros((2, 2))}

    spec = find_stage("dims_probe_stage")
    enc = _encode_outputs(spec, dims_probe_stage(n=4))
    assert enc["track"].arrays["data"][1] == ("frame",)
    assert enc["other"].arrays["data"][1] == ("dim_0", "dim_1")
    assert np.array_equal(codecs.decode(enc["track"]), np.arange(4))
    with pytest.raises(ValueError, match="output_dims names 1 axes, the array has 2"):
        _encode_outputs(spec, {"track": np.zeros((2, 2)), "other": np.zeros(1)})
    with pytest.raises(TypeError, match="output_dims for unknown outputs"):
        stage("dims_probe_bad", outputs=("a",), output_dims={"b": ("x",)})(lambda: {})


@stage("toy_optional_input_test", outputs=("values",))
def _optional_input(values, offset=None, *, scale: float = 1.0):
    """An input that may be left unwired (``offset``)."""
    out = np.asarray(values, dtype=np.float64) * scale
    return {"values": out if offset is None else out + np.asarray(offset)}


def test_optional_inputs_may_be_left_unwired(tmp_path, store, graph_of):
    """An input defaulting to None: unwired in a graph (or left out in Python) it is None;
    wired, it is loaded as any input; an input with another default is refused."""
    cfg = write_config(tmp_path / "o.yaml", """\
        nodes:
          src: {stage: toy_source, params: {n: 4}}
          alone: {stage: toy_optional_input_test, inputs: {values: src.values},
                  params: {scale: 2.0}}
          both: {stage: toy_optional_input_test,
                 inputs: {values: src.values, offset: src.values}}
        """)
    r = run(graph_of(cfg), store)
    assert r.ok
    src = codecs.decode(store.load("toy_source", r.records[0]["key"], "values"))
    got = {rec["node"]: codecs.decode(store.load("toy_optional_input_test", rec["key"], "values"))
           for rec in r.records if rec["node"] != "src"}
    np.testing.assert_array_equal(got["alone"], 2 * src)
    np.testing.assert_array_equal(got["both"], 2 * src)
    np.testing.assert_array_equal(_optional_input(src)["values"], src)  # Python call
    with pytest.raises(TypeError, match="input 'b' may only default to None"):
        @stage("toy_bad_default_test", outputs=("v",))
        def _bad(a, b=1.0):
            return {"v": a}
