"""Everyday use of the command line: shipped graphs by name from any folder, the data
folder named when a shipped part is missing, help on every flag, ``--json`` wherever a
verb prints results, ``stages NAME`` with the meaning of every param, the config JSON
Schema, ``show`` / ``export`` by NODE/PART, ``-q``."""

from __future__ import annotations

import argparse
import json

import jsonschema
import pytest
import yaml

from mocapflow.pipeline import registry
from mocapflow.pipeline.config import ConfigError, load_config, shipped_configs
from mocapflow.pipeline.config_yaml import load_yaml
from mocapflow.pipeline.stage_docs import config_schema, param_docs

SYNC = ("--executor", "sync")
SHIPPED = ("skin", "texture", "variation", "variation_strokes", "variation_takes")


def test_shipped_graphs_by_name_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert set(shipped_configs()) == set(SHIPPED)  # demo descriptions are not graphs
    cfg = load_config("texture")
    assert cfg.name == "texture" and len(cfg.parts) == 1
    assert cfg.parts[0].endswith("bvh/cmu_131_02.bvh")  # the default data beside the repo
    with pytest.raises(ConfigError, match=r"'textur' \(did you mean 'texture'\?\) \(shipped "
                                          r"graphs: skin, texture"):
        load_config("textur")
    (tmp_path / "texture").write_text("x")  # a file of that name in the folder wins
    with pytest.raises(ConfigError, match="missing 'nodes'|nodes"):
        load_config("texture")


def test_missing_shipped_part_names_the_data_variable(tmp_path, monkeypatch):
    monkeypatch.setenv("MOCAPFLOW_DATA", str(tmp_path / "nowhere"))
    with pytest.raises(ConfigError) as e:
        load_config("texture")
    msg = str(e.value)
    assert "missing input file" in msg and "${env:MOCAPFLOW_DATA}" in msg
    assert f"MOCAPFLOW_DATA={str(tmp_path / 'nowhere')!r}" in msg and "--parts" in msg
    monkeypatch.delenv("MOCAPFLOW_DATA")
    cfg = tmp_path / "c.yaml"  # a config that does not use the variable: no hint
    cfg.write_text("parts: [nope.bvh]\nnodes:\n  i: {stage: ingest_bvh, inputs: {path: part}}\n")
    with pytest.raises(ConfigError) as e:
        load_config(cfg)
    assert "missing input file" in str(e.value) and "MOCAPFLOW_DATA" not in str(e.value)


def _subparsers(parser):
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


def test_every_flag_has_help_and_every_printing_verb_json():
    from mocapflow.pipeline.cli import build_parser

    missing = [f"{verb} {a.option_strings or a.dest}"
               for verb, p in _subparsers(build_parser()).items() for a in p._actions
               if not isinstance(a, argparse._HelpAction) and not (a.help or "").strip()]
    assert missing == []
    no_json = [v for v, p in _subparsers(build_parser()).items()
               if v != "schema" and "--json" not in {o for a in p._actions
                                                     for o in a.option_strings}]
    assert no_json == []


def test_every_stage_param_is_documented():
    registry.discover()
    undocumented = [f"{name}.{p}" for name, s in registry.registered_stages().items()
                    if s.module.startswith("mocapflow.stages.")  # not the engine's toy stages
                    for p in s.params if not param_docs(s.func).get(p)]
    assert undocumented == []


def test_param_docs_reads_numpydoc_entries():
    def f(x, *, a: int = 1, b: float = 2.0, c: bool = False):
        """Do it.

        Parameters
        ----------
        x : array
            Input.
        a, b : number
            Both of them,
            on two lines.
        c : bool

        Returns
        -------
        a : int
            Not a param.
        """

    assert param_docs(f) == {"x": "Input.", "a": "Both of them, on two lines.",
                             "b": "Both of them, on two lines.", "c": ""}


def test_stages_name_prints_every_param_with_its_meaning(cli):
    code, out, _ = cli("stages", "clean")
    assert code == 0 and out.startswith("clean  (mocapflow.stages.skin.clean)")
    assert "    alpha1: float = 0.5\n        Entry tolerance of a fragment" in out
    code, out, _ = cli("stages", "clean", "--json")
    (doc,) = json.loads(out)
    assert doc["params"]["alpha2"]["doc"].startswith("Tolerance over the whole fragment")
    code, out, _ = cli("stages", "texture")  # a family: its stages
    heads = [line.split()[0] for line in out.splitlines() if not line.startswith(" ")]
    assert code == 0 and {"pyramid", "synth"} <= set(heads) and "clean" not in heads
    assert "    loop: bool = False\n        Cyclic output" in out
    code, _, err = cli("stages", "clea")
    assert code == 2 and "did you mean 'clean'" in err and len(err.strip().splitlines()) == 1


def test_config_schema_accepts_shipped_configs_and_catches_mistakes(cli, tmp_path):
    code, _, _ = cli("schema", "--out", tmp_path / "s.json")
    schema = json.loads((tmp_path / "s.json").read_text())
    assert code == 0
    jsonschema.Draft202012Validator.check_schema(schema)
    v = jsonschema.Draft202012Validator(schema)
    for name, path in shipped_configs().items():
        text = path.read_text()
        yaml.safe_load(text)  # plain YAML, as an editor reads it
        assert list(v.iter_errors(json.loads(json.dumps(load_yaml(text, name))))) == [], name
    doc = json.loads(json.dumps(load_yaml(shipped_configs()["skin"].read_text(), "skin")))
    doc["nodes"]["clean"]["params"]["alpha1"] = "lots"  # wrong type
    doc["nodes"]["clean"]["params"]["alpha3"] = 1.0  # unknown param
    doc["nodes"]["segment"]["seeds"] = {"count": 0}
    bad = {(tuple(e.absolute_path)[-1], e.validator) for e in v.iter_errors(doc)}
    assert ("alpha1", "anyOf") in bad and ("params", "additionalProperties") in bad
    assert ("seeds", "anyOf") in bad


def test_show_and_export_by_node_and_part(cli, toy_config, tmp_path):
    s = tmp_path / "s"
    assert cli("run", toy_config, "--store", s, "--target", "scale", *SYNC)[0] == 0
    code, out, _ = cli("show", "scale/trial002", "--store", s, "--json")
    doc = json.loads(out)
    assert code == 0 and doc["manifest"]["node"] == "scale"
    assert doc["manifest"]["part"].endswith("trial002.txt")
    code, _, err = cli("show", "scale", "--store", s)
    assert code == 2 and "has entries of 5 parts" in err
    code, out, err = cli("export", toy_config, "--store", s, "--target", "scale/trial002",
                         "--to", tmp_path / "out", "-q", *SYNC)
    assert code == 0 and out == "" and "exported 1 file(s)" in err
    assert [p.parent.name for p in (tmp_path / "out").rglob("*.*")] == ["trial002"]
    code, out, _ = cli("export", toy_config, "--store", s, "--target", "scale",
                       "--to", tmp_path / "out2", "--json", *SYNC)
    assert code == 0 and len(json.loads(out)["files"]) == 5
    code, _, err = cli("export", toy_config, "--store", s, "--target", "scale/trial999",
                       "--to", tmp_path / "o3", *SYNC)
    assert code == 2 and "has no part 'trial999'" in err


def test_dag_and_lock_json(cli, toy_config, tmp_path):
    code, out, _ = cli("dag", toy_config, "--json")
    doc = json.loads(out)
    assert code == 0 and doc["targets"] == ["total"]
    assert {n["name"]: n["tasks"] for n in doc["nodes"]} == {"read": 5, "add": 5, "scale": 5,
                                                            "total": 1}
    code, out, _ = cli("lock", toy_config, "--store", tmp_path / "s", "--lock",
                       tmp_path / "l.json", "--json", *SYNC)
    assert code == 0 and json.loads(out) == {"lock": str(tmp_path / "l.json"), "tasks": 16}


def test_schema_of_the_toy_stages_types_params():
    registry.discover()
    s = config_schema({"toy_source": registry.get_stage("toy_source")})
    node = s["properties"]["nodes"]["additionalProperties"]
    props = node["allOf"][0]["then"]["properties"]["params"]["properties"]
    assert props["n"]["anyOf"][0] == {"type": "integer"} and props["n"]["default"] == 8
    assert props["value"]["anyOf"][0] == {"type": "number"}
