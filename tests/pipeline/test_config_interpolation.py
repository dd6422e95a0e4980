"""``${params.NAME}`` and ``${env:VAR,default}`` interpolation: types kept, formatted in strings."""

from __future__ import annotations

from mocapflow.pipeline.config import load_config
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
