"""Graph configs: overrides, seeds, and one-line FILE:LINE: key: problem errors."""

from __future__ import annotations

import time

import pytest

from mocapflow.pipeline.config import ConfigError, load_config, parse_config
from mocapflow.pipeline.testing import write_config


def _load(tmp_path, text, **kw):
    return load_config(write_config(tmp_path / "g.yaml", text), **kw)


def test_sets_and_parts_override(tmp_path, data_dir):
    path = write_config(tmp_path / "g.yaml", f"""\
        params: {{amount: 1}}
        parts: [{data_dir}/*.txt]
        nodes:
          read: {{stage: toy_read_file, inputs: {{path: part}}}}
          add: {{stage: toy_add, inputs: {{values: read.values}},
                params: {{amount: ${{params.amount}}}}}}
          src: {{stage: toy_source}}
        """)
    cfg = load_config(path, sets=["params.amount=4", "src.n=3", "src.value=2"],
                      parts=[str(data_dir / "trial001.txt")])
    assert cfg.nodes["add"].params["amount"] == 4.0
    assert cfg.nodes["src"].params == {"n": 3, "value": 2.0, "noise": 0.0, "seed": 0}
    assert cfg.parts == [str(data_dir / "trial001.txt")]
    assert cfg.overrides["set"]["src.n"] == 3


BAD = [
    # (yaml, line, key, message fragment)
    ("graf: x\nnodes:\n  a: {stage: toy_source}\n", 1, "graf", "did you mean 'graph'"),
    ("nodes:\n  a:\n    stage: toy_source\n    parms: {}\n", 4, "nodes.a.parms",
     "unknown node key (did you mean 'params'?)"),
    ("nodes:\n  a:\n    stage: toy_sourse\n", 3, "nodes.a.stage",
     "unknown stage 'toy_sourse' (did you mean toy_source"),
    ("nodes:\n  a:\n    stage: toy_source\n    params:\n      nn: 3\n", 5, "nodes.a.params.nn",
     "did you mean 'n'"),
    ("nodes:\n  a:\n    stage: toy_source\n    params:\n      n: three\n", 5, "nodes.a.params.n",
     "expected an integer, got 'three'"),
    ("nodes:\n  a:\n    stage: toy_add\n", 3, "nodes.a.inputs.values", "is not wired"),
    ("nodes:\n  a:\n    stage: toy_add\n    inputs:\n      values: b.values\n", 5,
     "nodes.a.inputs.values", "unknown node 'b'"),
    ("nodes:\n  s: {stage: toy_source}\n  a:\n    stage: toy_add\n    inputs:\n"
     "      values: s.valeus\n", 6, "nodes.a.inputs.values", "has no output 'valeus'"),
    ("nodes:\n  a:\n    stage: toy_add\n    inputs: {values: b.values}\n  b:\n"
     "    stage: toy_scale\n    inputs:\n      values: a.values\n", 4, "nodes.a.inputs.values",
     "cycle a -> b -> a"),
    ("parts: [/no/such/file.txt]\nnodes:\n  r: {stage: toy_read_file, inputs: {path: part}}\n",
     1, "parts[0]", "missing input file '/no/such/file.txt'"),
    ("parts:\n  - /no/such/dir/*.txt\nnodes:\n  r: {stage: toy_read_file, inputs: {path: part}}\n",
     2, "parts[0]", "no file matches"),
    ("nodes:\n  r: {stage: toy_read_file, inputs: {path: part}}\n", 2, "nodes.r.inputs.path",
     "config has no parts"),
    ("nodes:\n  a: {stage: toy_source\n  b: 1\n", 3, "yaml", "malformed YAML"),
    ("nodes:\n  a: {stage: toy_source}\n  a: {stage: toy_source}\n", 3, "yaml",
     "duplicate key 'a'"),
    ("nodes:\n  a:\n    stage: toy_source\n    params: {n: '${params.m}'}\n", 4,
     "nodes.a.params.n", "unknown shared param ${params.m}"),
    ("nodes:\n  a:\n    stage: toy_add\n    inputs: {values: s.values}\n    seeds: [1, 1]\n"
     "  s: {stage: toy_source}\n", 5, "nodes.a.seeds[1]", "duplicate seed 1"),
    ("nodes:\n  a:\n    stage: toy_source\n    seeds: {count: 0}\n", 4, "nodes.a.seeds.count",
     "positive integer"),
    ("nodes:\n  a:\n    stage: toy_offset\n    inputs: {values: s.values}\n    params:\n"
     "      offset_file: /no/such.txt\n  s: {stage: toy_source}\n", 6,
     "nodes.a.params.offset_file", "missing input file"),
    ("targets: [nope]\nnodes:\n  a: {stage: toy_source}\n", 1, "targets[0]", "unknown node"),
    ("- just\n- a list\n", 1, "", "must be a YAML mapping"),
    ("nodes:\n  off: {stage: toy_source}\n", 2, "nodes.False", "quote the name"),
]


@pytest.mark.parametrize("text, line, key, fragment", BAD, ids=[b[3][:30] for b in BAD])
def test_bad_configs_name_file_line_key(tmp_path, text, line, key, fragment):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_config(path)
    msg = str(e.value)
    assert "\n" not in msg
    prefix = f"{path}:{line}: " + (f"{key}: " if key else "")
    assert msg.startswith(prefix), msg
    assert fragment in msg, msg
    assert (e.value.line, e.value.key) == (line, key)


@pytest.mark.parametrize("sets, fragment", [
    (["nope.n=1"], "--set nope.n: unknown node 'nope'"),
    (["a.nn=1"], "--set a.nn: unknown param for stage 'toy_source' (did you mean 'n'?)"),
    (["a.n=[1, 2]"], "--set a.n: param toy_source.n: expected an integer, got [1, 2]"),
    (["a.n"], "--set a.n: expected NODE.PARAM=VALUE"),
    (["params.nn=2"], "--set params.nn: unknown shared param (did you mean 'n'?)"),
])
def test_bad_sets_name_the_override(tmp_path, sets, fragment):
    with pytest.raises(ConfigError) as e:
        _load(tmp_path, "params: {n: 1}\nnodes:\n  a: {stage: toy_source}\n", sets=sets)
    assert str(e.value).startswith("<command line>: ")
    assert fragment in str(e.value)


def test_parts_override_missing_file(tmp_path):
    with pytest.raises(ConfigError, match=r"^<command line>: --parts: missing input file"):
        _load(tmp_path, "nodes:\n  r: {stage: toy_read_file, inputs: {path: part}}\n",
              parts=[str(tmp_path / "none.txt")])


def test_seeds_from_the_command_line():
    """``--set NODE.seeds=…`` sets the fan-out without editing the YAML (issue 16 item 5)."""
    text = "nodes:\n  a: {stage: toy_source, seeds: {count: 3}}\n  b: {stage: toy_source}\n"
    assert parse_config(text).nodes["a"].seeds == [0, 1, 2]
    for value, want in (("5", [0, 1, 2, 3, 4]), ("[0, 7, 9]", [0, 7, 9]),
                        ("{count: 2}", [0, 1]), ("null", None)):
        assert parse_config(text, sets=[f"a.seeds={value}"]).nodes["a"].seeds == want
    cfg = parse_config(text, sets=["b.seeds=2"])  # a node without seeds: gets a fan-out
    assert cfg.nodes["b"].seeds == [0, 1] and cfg.nodes["a"].seeds == [0, 1, 2]
    assert parse_config(text, sets=["a.seeds=null", "a.seed=4"]).nodes["a"].params["seed"] == 4
    for value, fragment in (("[1, 1]", "--set a.seeds[1]: duplicate seed 1"),
                            ("0", "--set a.seeds.count: expected a positive integer, got 0"),
                            ("x", "--set a.seeds: expected a non-empty list of seeds")):
        with pytest.raises(ConfigError) as e:
            parse_config(text, sets=[f"a.seeds={value}"])
        assert str(e.value).startswith(f"<command line>: {fragment}"), str(e.value)
    with pytest.raises(ConfigError, match="seed is set per task by seeds:"):
        parse_config(text, sets=["a.seed=4"])


def test_seeds_count_and_list(tmp_path):
    cfg = parse_config("nodes:\n  a: {stage: toy_source, seeds: {count: 3}}\n"
                       "  b: {stage: toy_source, seeds: [7, 9]}\n")
    assert cfg.nodes["a"].seeds == [0, 1, 2]
    assert cfg.nodes["b"].seeds == [7, 9]
    with pytest.raises(ConfigError, match="seed is set per task by seeds:"):
        parse_config("nodes:\n  a: {stage: toy_source, seeds: [1], params: {seed: 3}}\n")


# --------------------------------------------------------------------------- numbers, fan-out

NUMBERS = [
    # (params flow mapping, key, message fragment)
    ("{value: .inf}", "value", "param toy_source.value: expected a finite number, got inf"),
    ("{value: -.inf}", "value", "expected a finite number, got -inf"),
    ("{value: .nan}", "value", "expected a finite number, got nan"),
    ("{value: " + "9" * 400 + ".0}", "value", "expected a finite number, got inf"),
    ("{value: 1.0e+14}", "value", "100000000000000.0 is out of range (at most 1e12"),
    ("{n: 100000000000000}", "n", "100000000000000 is out of range (at most 1e12"),
    ("{value: -1000000000001}", "value", "-1000000000001 is out of range"),
    ("{n: 3.0}", "n", "expected an integer, got 3.0"),
    ("{seed: 4294967296}", "seed", "a seed must be in [0, 2**32), got 4294967296"),
    ("{seed: -1}", "seed", "a seed must be in [0, 2**32), got -1"),
]


@pytest.mark.parametrize("params, key, fragment", NUMBERS, ids=[n[0][:24] for n in NUMBERS])
def test_numbers_are_finite_in_range_and_integral(tmp_path, params, key, fragment):
    path = write_config(tmp_path / "g.yaml", f"nodes:\n  a:\n    stage: toy_source\n"
                                             f"    params: {params}\n")
    with pytest.raises(ConfigError) as e:
        load_config(path)
    assert str(e.value).startswith(f"{path}:4: nodes.a.params.{key}: "), str(e.value)
    assert fragment in str(e.value) and len(str(e.value)) < 300


def test_numbers_at_the_limits_are_accepted(tmp_path):
    cfg = parse_config("nodes:\n  a: {stage: toy_source, params: {n: 1000000000000, "
                       "value: -1.0e+12, seed: 4294967295}}\n"
                       "  b: {stage: toy_clip, inputs: {values: a.values}, params: {lo: 1}}\n")
    assert cfg.nodes["a"].params == {"n": 10**12, "value": -1e12, "noise": 0.0,
                                     "seed": 2**32 - 1}
    assert cfg.nodes["b"].params["lo"] == 1.0 and type(cfg.nodes["b"].params["lo"]) is float


@pytest.mark.parametrize("seeds, key, fragment", [
    ("{count: 100000000}", "nodes.a.seeds.count", "100000000 seeds: more than the 1,000,000 "
                                                   "tasks a graph may have"),
    ("[0, 4294967296]", "nodes.a.seeds[1]", "a seed must be in [0, 2**32), got 4294967296"),
    ("[-3]", "nodes.a.seeds[0]", "a seed must be in [0, 2**32), got -3"),
])
def test_seeds_are_bounded_before_any_list_is_made(tmp_path, seeds, key, fragment):
    path = write_config(tmp_path / "g.yaml", f"nodes:\n  a:\n    stage: toy_source\n"
                                             f"    seeds: {seeds}\n")
    t0 = time.perf_counter()
    with pytest.raises(ConfigError) as e:
        load_config(path)
    assert time.perf_counter() - t0 < 1.0
    assert str(e.value) == f"{path}:4: {key}: {fragment}"


def test_fan_out_cap_names_the_node(tmp_path, data_dir):
    path = write_config(tmp_path / "g.yaml", f"""\
        parts: [{data_dir}/*.txt]
        nodes:
          read: {{stage: toy_read_file, inputs: {{path: part}}}}
          add:
            stage: toy_add
            inputs: {{values: read.values}}
            seeds: {{count: 100000}}
          scale:
            stage: toy_scale
            inputs: {{values: add.values}}
        """)
    with pytest.raises(ConfigError) as e:
        load_config(path)
    assert str(e.value) == (
        f"{path}:8: nodes.scale: fans out to 500,000 tasks: the graph would have 1,000,005 "
        "tasks, more than the 1,000,000 it may have")
    with pytest.raises(ConfigError, match=r"g2\.yaml:7: nodes\.add\.seeds: fans out to 1,000,005 "
                                          r"tasks \(5 per seed × 200,001 seeds\): the graph"):
        load_config(write_config(tmp_path / "g2.yaml",
                                 path.read_text().replace("100000", "200001")))
    cfg = load_config(write_config(tmp_path / "g3.yaml",
                                   path.read_text().replace("100000", "99999")))
    assert len(cfg.nodes["add"].seeds) == 99_999  # 5 + 2 × 499,995 tasks: under the cap


def test_a_chain_of_3000_nodes_sorts_without_recursion():
    text = "nodes:\n" + "".join(
        f"  n{i}: {{stage: toy_add, inputs: {{values: n{i - 1}.values}}}}\n"
        for i in range(3000, 0, -1)) + "  n0: {stage: toy_source}\n"
    cfg = parse_config(text)
    assert list(cfg.nodes) == [f"n{i}" for i in range(3001)]
    cyc = text.replace("  n0: {stage: toy_source}\n",
                       "  n0: {stage: toy_add, inputs: {values: n3000.values}}\n")
    with pytest.raises(ConfigError, match=r"^<string>:2: nodes\.n3000\.inputs\.values: cycle "
                                          r"n3000 -> n0 -> n1 -> n2 "):
        parse_config(cyc)
