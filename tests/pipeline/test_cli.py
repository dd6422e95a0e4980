"""The mocapflow command: JSON output, one-line errors, crash safety, concurrency,
show / verify / gc / lock --frozen, verbs and flags."""

from __future__ import annotations

import json
import os
import re
import signal
import time
from pathlib import Path

import pytest

from mocapflow.pipeline.store import Store
from mocapflow.pipeline.testing import write_config, write_number_files

SYNC = ("--executor", "sync")


def _run_json(cli, *args):
    code, out, err = cli("run", *args, "--json")
    return code, json.loads(out), err


def test_json_documents_parse(cli, toy_config, tmp_path):
    s = tmp_path / "s"
    code, doc, _ = _run_json(cli, toy_config, "--store", s, *SYNC)
    assert code == 0 and doc["ok"] and doc["counts"]["computed"] == 16
    t = doc["tasks"][0]
    assert set(t) >= {"node", "part", "status", "key", "seconds", "error"}
    assert t["status"] == "computed" and len(t["key"]) == 32 and t["error"] is None
    code, out, _ = cli("plan", toy_config, "--store", s, "--json", "--set", "scale.factor=3")
    plan = json.loads(out)["tasks"]
    assert code == 0 and {p["status"] for p in plan} == {"hit", "compute", "pending"}
    assert {p["reason"] for p in plan if p["node"] == "scale"} == {"param factor: 2.0 -> 3.0"}
    code, out, _ = cli("status", toy_config, "--store", s, "--json")
    rows = json.loads(out)["tasks"]
    assert code == 0 and len(rows) == 16
    assert all(r["status"] == "computed" and r["up_to_date"] for r in rows)


BAD = {
    "unknown stage": ("nodes:\n  a:\n    stage: toy_nope\n", 3, "nodes.a.stage"),
    "unknown param": ("nodes:\n  a:\n    stage: toy_source\n    params: {m: 1}\n", 4,
                      "nodes.a.params.m"),
    "mistyped param": ("nodes:\n  a:\n    stage: toy_source\n    params:\n      n: 1.5\n", 5,
                       "nodes.a.params.n"),
    "cycle": ("nodes:\n  a: {stage: toy_add, inputs: {values: b.values}}\n"
              "  b: {stage: toy_add, inputs: {values: a.values}}\n", 2, "nodes.a.inputs.values"),
    "dangling input": ("nodes:\n  s: {stage: toy_source}\n  a:\n    stage: toy_add\n"
                       "    inputs: {values: s.nothing}\n", 5, "nodes.a.inputs.values"),
    "missing input file": ("parts:\n  - does/not/exist.txt\nnodes:\n"
                           "  r: {stage: toy_read_file, inputs: {path: part}}\n", 2, "parts[0]"),
    "malformed yaml": ("nodes:\n  a: [stage: toy_source\n", 3, "yaml"),
}


@pytest.mark.parametrize("kind", list(BAD))
def test_bad_config_one_line_exit_nonzero_nothing_committed(cli, tmp_path, kind):
    text, line, key = BAD[kind]
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(text)
    s = tmp_path / "s"
    code, out, err = cli("run", cfg, "--store", s, *SYNC)
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"mocapflow: error: {cfg}:{line}: {key}: "), lines[0]
    assert "Traceback" not in err
    assert Store(s).entries() == [] and not (s / "runs").exists()


def test_user_errors_are_one_line(cli, tmp_path, toy_config):
    for args, fragment in [
        (("run", tmp_path / "none.yaml", *SYNC), "none.yaml: config file not found"),
        (("run", toy_config, *SYNC, "--set", "add.amount=[1]"),
         "<command line>: --set add.amount: param toy_add.amount: expected a number"),
        (("run", toy_config, *SYNC, "--target", "nope"), "--target: unknown node 'nope'"),
        (("explain", toy_config, "nope"), "explain nope: unknown node 'nope'"),
        (("run", toy_config, *SYNC, "--frozen", "--lock", tmp_path / "x.json"),
         "lock file not found"),
        (("run", toy_config, "--workers", "0"), "--workers must be at least 1"),
        (("show", "zzzz", "--store", tmp_path), "no committed entry matches"),
    ]:
        code, out, err = cli(*args)
        assert code != 0 and len(err.strip().splitlines()) == 1, (args, err)
        assert fragment in err, (args, err)


def test_failed_tasks_exit_nonzero_and_name_the_part(cli, toy_config, data_dir, tmp_path):
    bad = data_dir / "trial003.txt"
    bad.write_text("1 2 three\n")
    s = tmp_path / "s"
    code, doc, err = _run_json(cli, toy_config, "--store", s, *SYNC)
    assert code == 1 and not doc["ok"]
    assert err.strip().splitlines()[-1] == (
        f"mocapflow: error: 1 task(s) failed: read/{bad}: ValueError: {bad}: line 1: not a "
        f"number 'three'; 3 skipped [tracebacks: {s}/runs/{doc['run_id']}.json]")
    assert doc["counts"] == {"hit": 0, "computed": 12, "failed": 1, "skipped": 3}
    code, out, err = cli("run", toy_config, "--store", tmp_path / "s2", *SYNC, "--fail-fast")
    assert code == 1 and f"read/{bad}" in err
    # status shows the failure
    code, out, _ = cli("status", toy_config, "--store", s)
    assert f"failed read/{bad}: ValueError" in out


def test_explain_plan_dag_stages_show(cli, toy_config, tmp_path):
    s = tmp_path / "s"
    cli("run", toy_config, "--store", s, *SYNC)
    code, out, _ = cli("explain", toy_config, "add/trial002", "--store", s, "--set",
                       "add.amount=5")
    assert code == 0 and out.splitlines()[1] == "  param amount: 1.0 -> 5.0"
    code, out, _ = cli("plan", toy_config, "--store", s, "--set", "params.amount=5")
    lines = out.splitlines()
    assert sum(x.startswith("hit ") for x in lines) == 5
    assert sum(x.endswith("param amount: 1.0 -> 5.0") for x in lines) == 5
    code, out, _ = cli("dag", toy_config)
    assert "4 nodes, 16 tasks" in out and re.search(r"total\s+toy_sum\s+gather", out)
    code, out, _ = cli("dag", toy_config, "--dot")
    assert '"add" -> "scale"' in out
    code, out, _ = cli("stages", "--json")
    st = {x["name"]: x for x in json.loads(out)}
    assert st["toy_add"]["params"]["amount"] == {"type": "float", "default": 1.0,
                                                 "required": False,
                                                 "doc": "Added to every value."}
    key = Store(s).entries()[0][1]
    code, out, _ = cli("show", key[:10], "--store", s)
    assert code == 0 and out.startswith("entry ") and "data: float64 (dim_0=5)" in out


def test_lock_and_frozen(cli, toy_config, data_dir, tmp_path):
    code, out, _ = cli("lock", toy_config, "--store", tmp_path / "s", *SYNC)
    lock = Path(out.strip())
    assert code == 0 and lock == toy_config.with_name("toy.lock.json")
    code, doc, _ = _run_json(cli, toy_config, "--store", tmp_path / "fresh", *SYNC, "--frozen")
    assert code == 0 and doc["counts"]["computed"] == 16
    locked = {(t["node"], t["part"]): t["outputs"] for t in json.loads(lock.read_text())["tasks"]}
    assert {(t["node"], t["part"]): t["outputs"] for t in doc["tasks"]} == locked
    f = data_dir / "trial004.txt"
    f.write_text("4 5 6 7 9\n")
    code, out, err = cli("run", toy_config, "--store", tmp_path / "fresh2", *SYNC, "--frozen")
    assert code == 1
    assert err.startswith(f"mocapflow: error: frozen: read/{f}: key differs from the lock "
                          "(input path changed (file content digest")
    assert Store(tmp_path / "fresh2").entries() == []


def test_sigkill_mid_write_leaves_no_partial_entry(cli, cli_proc, tmp_path):
    cfg = write_config(tmp_path / "big.yaml", """\
        nodes:
          big: {stage: toy_source, seeds: {count: 4}, params: {n: 1500000, noise: 1.0}}
          half: {stage: toy_scale, inputs: {values: big.values}, params: {factor: 0.5}}
        """)
    s = tmp_path / "s"
    proc = cli_proc("run", cfg, "--store", s, *SYNC, "-q")
    staging = s / "staging"
    deadline = time.monotonic() + 60
    caught = False
    while time.monotonic() < deadline and proc.poll() is None:
        # wait until a writer has put array data into a staging directory
        try:
            if staging.is_dir() and any(any(d.rglob("c/*")) for d in staging.iterdir()):
                caught = True
                break
        except OSError:  # a staging dir renamed into place while we looked
            pass
        time.sleep(0.002)
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate()
    assert caught and proc.returncode == -signal.SIGKILL
    store = Store(s)
    committed = store.entries()
    assert len(committed) < 8
    for d in (s / "entries").glob("*/*"):  # an entry directory exists only with its manifest
        assert (d / "_COMMIT.json").is_file(), d
    debris = [d for d in staging.iterdir() if d.is_dir()]
    assert debris  # the killed writer's staging directory
    code, _, err = cli("verify", "--store", s)
    assert code == 0 and f"{len(committed)} entries verified" in err
    code, out, _ = cli("gc", "--store", s, "--min-age", "0", "--json")
    assert code == 0 and len(json.loads(out)["staging"]) == len(debris)
    assert not any(d.is_dir() for d in staging.iterdir())
    code, doc, _ = _run_json(cli, cfg, "--store", s, *SYNC, "-q")
    assert code == 0 and doc["counts"] == {"hit": len(committed), "computed":
                                           8 - len(committed), "failed": 0, "skipped": 0}
    assert store.verify() == []


def test_two_concurrent_runs_on_one_store(cli_proc, tmp_path):
    write_number_files(tmp_path / "data", 6)
    cfg = write_config(tmp_path / "c.yaml", """\
        parts: ["{data}/*.txt"]
        nodes:
          read: {{stage: toy_read_file, inputs: {{path: part}}}}
          slow: {{stage: toy_sleep, inputs: {{values: read.values}}, params: {{seconds: 0.05}}}}
          noisy: {{stage: toy_source, seeds: {{count: 4}}, params: {{n: 200000, noise: 1.0}}}}
          total: {{stage: toy_sum, inputs: {{values: slow.values}}, gather: true}}
        """, data=tmp_path / "data")
    s = tmp_path / "s"
    procs = [cli_proc("run", cfg, "--store", s, "--json", "-q", *SYNC),
             cli_proc("run", cfg, "--store", s, "--json", "-q", "--executor", "local",
                      "--workers", "1")]
    docs = []
    for p in procs:
        out, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
        docs.append(json.loads(out))
    digests = [{(t["node"], t["part"]): t["outputs"] for t in d["tasks"]} for d in docs]
    assert digests[0] == digests[1] and len(digests[0]) == 17
    store = Store(s)
    assert len(store.entries()) == 17 and store.verify() == []


def test_gc_keep_config_removes_unreachable(cli, toy_config, tmp_path):
    s = tmp_path / "s"
    cli("run", toy_config, "--store", s, *SYNC)
    cli("run", toy_config, "--store", s, *SYNC, "--set", "scale.factor=3")
    assert len(Store(s).entries()) == 22
    code, out, _ = cli("gc", "--store", s, "--keep-config", toy_config, "--dry-run", "--json")
    assert code == 0 and len(json.loads(out)["unreachable"]) == 6
    assert len(Store(s).entries()) == 22
    cli("gc", "--store", s, "--keep-config", toy_config)
    assert len(Store(s).entries()) == 16
    code, doc, _ = _run_json(cli, toy_config, "--store", s, *SYNC)
    assert doc["counts"]["hit"] == 16


def test_verify_detects_a_missing_chunk(cli, toy_config, tmp_path):
    s = tmp_path / "s"
    cli("run", toy_config, "--store", s, *SYNC)
    chunk = next((s / "entries" / "toy_scale").glob("*/values/data/c/0"))
    chunk.unlink()
    code, out, err = cli("verify", "--store", s)
    assert code == 1 and "missing file values/data/c/0" in out
    assert err.strip() == f"mocapflow: error: verify: 2 problem(s) in {s}"


def test_verbs_and_flags_keep_their_names():
    from mocapflow.pipeline.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "verb")
    assert set(sub.choices) == {"run", "plan", "status", "explain", "dag", "stages", "show",
                                "export", "verify", "gc", "lock", "demo", "schema", "report",
                                "blender-addon"}
    run_flags = {o for a in sub.choices["run"]._actions for o in a.option_strings}
    assert run_flags >= {"--store", "--parts", "--set", "--target", "--force", "--fail-fast",
                         "--json", "--executor", "--workers", "--address", "--scheduler-file",
                         "--frozen", "--lock", "--slurm-queue", "--slurm-cores",
                         "--slurm-memory", "--slurm-walltime", "--slurm-jobs",
                         "--print-job-script", "--debug"}
    args = parser.parse_args(["run", "c.yaml", "--set", "a.b=1", "--set", "c.d=x",
                              "--parts", "x/*.bvh", "--parts", "y.bvh", "--target", "t"])
    assert args.sets == ["a.b=1", "c.d=x"] and args.parts == ["x/*.bvh", "y.bvh"]
    assert args.executor == "local" and args.targets == ["t"]


def test_version_prints_the_installed_version(capsys):
    from importlib.metadata import version

    from mocapflow.pipeline.cli import main

    with pytest.raises(SystemExit) as exit_:  # argparse's version action, as for --help
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"mocapflow {version('mocapflow')}"
