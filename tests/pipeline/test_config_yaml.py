"""Line-aware, bounded YAML loading: configs are data only, aliases work but cannot explode,
deep nesting and huge numbers are one-line errors that name the key."""

from __future__ import annotations

import re
import time

import pytest

from mocapflow.pipeline.config import ConfigError, load_config
from mocapflow.pipeline.config_yaml import MAX_DEPTH, load_yaml, parse_yaml_value
from mocapflow.pipeline.testing import write_config


def _load(tmp_path, text, **kw):
    return load_config(write_config(tmp_path / "g.yaml", text), **kw)


def _error(tmp_path, text, **kw) -> ConfigError:
    path = tmp_path / "g.yaml"
    path.write_text(text)
    t0 = time.perf_counter()
    with pytest.raises(ConfigError) as e:
        load_config(path, **kw)
    assert time.perf_counter() - t0 < 5.0, "bounded loading took too long"
    assert "\n" not in str(e.value)
    return e.value


def test_configs_are_data_only(tmp_path):
    err = _error(tmp_path, "nodes:\n  a: !!python/object/apply:os.system [echo hi]\n")
    assert re.match(r".*g\.yaml:2: nodes\.a: unknown tag '!!python/object/apply:os\.system'",
                    str(err))


def test_anchors_aliases_and_merge_keys_work(tmp_path):
    cfg = _load(tmp_path, """\
        params:
          d: &d {n: 3, value: 2.0}
        nodes:
          a: {stage: toy_source, params: *d}
          b: {stage: toy_source, params: {<<: *d, n: 5}}
          c: {stage: toy_source, params: {<<: [{n: 7}, *d]}}
        """)
    assert cfg.nodes["a"].params["n"] == 3 and cfg.nodes["a"].params["value"] == 2.0
    assert cfg.nodes["b"].params["n"] == 5  # an own key overrides the merged one
    assert cfg.nodes["c"].params["n"] == 7  # the first merged mapping wins
    err = _error(tmp_path, "params:\n  d: &d {n: 1}\nnodes:\n"
                 "  a: {stage: toy_source, params: {<<: *d, value: 1.0, value: 2.0}}\n")
    assert (err.line, err.key) == (4, "yaml") and "duplicate key 'value'" in str(err)


def _laughs(levels: int) -> str:
    lines = ["l0: &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol, lol]"]
    lines += [f"l{i}: &l{i} [" + ", ".join([f"*l{i - 1}"] * 10) + "]" for i in range(1, levels)]
    return "\n".join(lines) + "\n"


BOUNDED = [
    # (id, text, line, key, fragment)
    ("billion laughs under an unknown top-level key", _laughs(9) + "nodes: {}\n", 5, "l4[7]",
     "expands to more than 100,000 YAML nodes (alias *l3 names 11,111 nodes)"),
    ("merge-key bomb", "m0: &m0 {k: 1}\n" + "".join(
        f"m{i}: &m{i} {{<<: [*m{i - 1}, *m{i - 1}], k{i}: {i}}}\n" for i in range(1, 40))
     + "nodes: {}\n", 14, "m13.<<[1]", "expands to more than 100,000 YAML nodes"),
    ("recursive alias", "params:\n  a: &a [1, *a]\nnodes: {}\n", 2, "params.a[1]",
     "alias *a refers to a node that contains it"),
    ("20,000 nested flow lists", "nodes:\n  a: " + "[" * 20_000 + "]" * 20_000 + "\n", 2,
     "nodes.a", f"nesting deeper than {MAX_DEPTH} levels"),
    ("2,000 nested block mappings", "params:\n" + "".join(
        "  " * (k + 1) + f"k{k}:\n" for k in range(2_000)) + "nodes: {}\n", 66,
     "params.k0.k1.k2", f"nesting deeper than {MAX_DEPTH} levels"),
    ("nesting through aliases", "params:\n" + "".join(
        f"  a{k}: &a{k} [{'*a' + str(k - 1) if k else 1}]\n" for k in range(80)) + "nodes: {}\n",
     63, "params.a61[0]", "nesting deeper than 64 levels (through alias *a60)"),
    ("a 400-digit integer", "nodes:\n  a: {stage: toy_source, params: {value: " + "9" * 400
     + "}}\n", 2, "nodes.a.params.value", "an integer of 400 characters is out of range"),
    ("a 5,000-digit integer", "params: {n: " + "9" * 5000 + "}\nnodes: {}\n", 1, "params.n",
     "an integer of 5,000 characters is out of range"),
    ("!!set", "params: {s: !!set {a, b}}\nnodes: {}\n", 1, "params.s",
     "tag !!set is not allowed in a config"),
    ("!!binary", "params: {s: !!binary aGVsbG8=}\nnodes: {}\n", 1, "params.s",
     "tag !!binary is not allowed"),
    ("unknown tag", "params: {s: !grow 3}\nnodes: {}\n", 1, "params.s", "unknown tag '!grow'"),
    ("a NUL character", "nodes:\n  a: \x00\n", 2, "yaml", "unacceptable character #x0000"),
]


@pytest.mark.parametrize("text, line, key, fragment", [b[1:] for b in BOUNDED],
                         ids=[b[0] for b in BOUNDED])
def test_loading_is_bounded_one_line_errors(tmp_path, text, line, key, fragment):
    err = _error(tmp_path, text)
    assert str(err).startswith(f"{tmp_path / 'g.yaml'}:{line}: {key}"), str(err)
    assert fragment in str(err), str(err)
    assert len(str(err)) < 700


def test_a_legit_alias_heavy_config_loads_fast(tmp_path):
    # 100 nodes sharing one 200-item list: 20,000 nodes after expansion, well under the cap
    text = "params:\n  table: &t [" + ", ".join(map(str, range(200))) + "]\n  uses: [" + \
        ", ".join(["*t"] * 100) + "]\nnodes:\n  a: {stage: toy_source}\n"
    t0 = time.perf_counter()
    cfg = _load(tmp_path, text)
    assert time.perf_counter() - t0 < 2.0
    assert cfg.params["uses"][99][199] == 199


def test_dates_stay_text_and_lines_are_kept():
    doc = load_yaml("a: 2024-01-01\nb:\n  - x\n  - 2\n", "f.yaml")
    assert doc == {"a": "2024-01-01", "b": ["x", 2]}
    assert doc.lines == {"a": 1, "b": 2} and doc["b"].lines == [3, 4]


def test_command_line_values_are_bounded(tmp_path):
    assert parse_yaml_value("{a: [1, 2]}") == {"a": [1, 2]}
    assert type(parse_yaml_value("{a: [1, 2]}")) is dict
    assert parse_yaml_value("[unclosed") == "[unclosed"  # not YAML: the text itself
    path = write_config(tmp_path / "g.yaml", "nodes:\n  a: {stage: toy_source}\n")
    with pytest.raises(ConfigError, match=r"^<command line>: --set a\.n: nesting deeper than 64"):
        load_config(path, sets=["a.n=" + "[" * 20_000 + "]" * 20_000])
    with pytest.raises(ConfigError, match=r"^<command line>: --set a\.value: param "
                                          r"toy_source\.value: expected a finite number"):
        load_config(path, sets=["a.value=.nan"])


def test_oversized_config_is_refused_unread(tmp_path):
    path = tmp_path / "huge.yaml"
    with path.open("wb") as f:
        f.truncate(17 << 20)  # sparse: nothing is written or read
    with pytest.raises(ConfigError, match=r"huge\.yaml: config is larger than 16 MiB$"):
        load_config(path)
