"""``${params.NAME}`` and ``${env:VAR,default}`` interpolation: types kept, formatted in strings."""

from __future__ import annotations

import re
import time

import pytest

from mocapflow.pipeline.config import ConfigError, load_config
from mocapflow.pipeline.testing import write_config


def _load(tmp_path, text, **kw):
    return load_config(write_config(tmp_path / "g.yaml", text), **kw)


def test_flow_mapping_interpolation_keeps_type(tmp_path, data_dir, monkeypatch):
    monkeypatch.setenv("TOY_N", "7")
    monkeypatch.delenv("TOY_UNSET", raising=False)
    cfg = _load(tmp_path, f"""\
        graph: demo
        params: {{n: 5, amount: 0.25, tag: run}}
        parts: ["{data_dir}/trial00[0-2].txt"]
        nodes:
          src: {{stage: toy_source, params: {{n: ${{params.n}}, value: ${{env:TOY_UNSET,1.5}}}}}}
          env: {{stage: toy_source, params: {{n: ${{env:TOY_N}}}}}}
          add:
            stage: toy_add
            inputs: {{values: src.values}}
            params: {{amount: ${{params.amount}}}}
          flaky:
            stage: toy_flaky
            inputs: {{values: src.values}}
            params: {{marker_dir: "out/${{params.tag}}-${{params.n}}"}}
        """)
    assert cfg.name == "demo"
    assert cfg.nodes["src"].params["n"] == 5 and type(cfg.nodes["src"].params["n"]) is int
    assert cfg.nodes["src"].params["value"] == 1.5
    assert cfg.nodes["env"].params["n"] == 7  # env value parsed as YAML -> int
    assert cfg.nodes["add"].params["amount"] == 0.25
    assert cfg.nodes["flaky"].params["marker_dir"] == "out/run-5"
    assert cfg.parts == [str(data_dir / f"trial00{i}.txt") for i in range(3)]
    assert cfg.targets == list(cfg.nodes)  # no targets: every node


# --------------------------------------------------------------------------- bounds

BOMBS = {
    "lists doubling": ("params:\n" + "".join(
        f"  p{k}: [${{params.p{k + 1}}}, ${{params.p{k + 1}}}]\n" for k in range(30))
        + "  p30: x\n", "params.p0", "references expand to more than 100,000 values"),
    "strings doubling": ("params:\n" + "".join(
        f"  p{k}: \"${{params.p{k + 1}}}${{params.p{k + 1}}}\"\n" for k in range(12))
        + "  p12: " + "x" * 100_000 + "\n", "params.p0", "references expand to more than 16 MiB"),
    "a chain of 2,000 references": ("params:\n" + "".join(
        f"  p{k}: ${{params.p{k + 1}}}\n" for k in range(2000)) + "  p2000: 1\n", "params.p0",
        "more than 32 ${params.NAME} references in a chain (${params.p0} -> ... -> "
        "${params.p32})"),
    "nesting through references": ("params:\n" + "".join(
        f"  p{k}: [${{params.p{k + 1}}}]\n" for k in range(30)) + "  p30: [[[[[[[[[[1]]]]]]]]]]\n"
        "  q: [[[[[[[[[[[[[[[[[[[[[[[[[[[[[[${params.p0}]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]\n",
        "params.q", "nesting deeper than 64 levels"),
}


@pytest.mark.parametrize("kind", list(BOMBS))
def test_interpolation_is_bounded(tmp_path, kind):
    text, key, fragment = BOMBS[kind]
    path = write_config(tmp_path / "g.yaml", text + "nodes:\n  a: {stage: toy_source}\n")
    t0 = time.perf_counter()
    with pytest.raises(ConfigError) as e:
        load_config(path)
    assert time.perf_counter() - t0 < 5.0
    msg = str(e.value)
    assert re.match(rf"{re.escape(str(path))}:\d+: {re.escape(key)}", msg), msg
    assert fragment in msg and "\n" not in msg


def test_an_environment_value_is_bounded_and_names_the_reference(tmp_path, monkeypatch):
    monkeypatch.setenv("TOY_DEEP", "[" * 20_000 + "]" * 20_000)
    path = write_config(tmp_path / "g.yaml",
                        "nodes:\n  a:\n    stage: toy_source\n    params: {n: '${env:TOY_DEEP}'}\n")
    with pytest.raises(ConfigError, match=r"g\.yaml:4: nodes\.a\.params\.n: nesting deeper"):
        load_config(path)
