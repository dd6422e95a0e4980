"""Capture sessions as parts: session files, ``${part.FIELD}`` params, per-subject ROM groups."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline import stage
from mocapflow.pipeline.codecs import decode
from mocapflow.pipeline.config import ConfigError, load_config, parse_config
from mocapflow.pipeline.graph import build_graph
from mocapflow.pipeline.runner import run
from mocapflow.pipeline.session import is_session, read_session
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.testing import write_number_files
from mocapflow.pipeline.wires import FileWire

C3D = Path(__file__).resolve().parents[3] / "shared" / "data" / "c3d"


@stage("toy_pair", outputs=("values",))
def toy_pair(values, ref) -> dict:
    """``values + sum(ref)`` (a trial combined with its subject's reference)."""
    return {"values": np.asarray(values) + float(np.asarray(ref).sum())}


@pytest.fixture
def day(tmp_path: Path) -> Path:
    """A capture day: ``day/t000..t003.txt`` trials, ``day/S01/rom.txt``, ``day/S02/rom.txt``."""
    d = tmp_path / "day"
    write_number_files(d, 4, prefix="t")
    for s, v in (("S01", "100 200"), ("S02", "7")):
        (d / s).mkdir()
        (d / s / "rom.txt").write_text(v + "\n")
    (d / "S01" / "static.txt").write_text("1\n")
    return d


SESSION = """\
subjects:
  S01: {rom: S01/rom.txt, static: S01/static.txt}
  S02: {rom: S02/rom.txt}
trials:
  - {trial: t000.txt, subject: S01}
  - {trial: t001.txt, subject: S01, notes: loose marker}
  - {trial: t002.txt, subject: S02}
  - {trial: t003.txt}
"""


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# --------------------------------------------------------------------------- reading


def test_yaml_session_inherits_subject_fields_relative_to_its_folder(day):
    s = read_session(_write(day / "day1.yaml", SESSION + "  - {trial: S02/rom.txt, subject: "
                            "S02, rom: S01/rom.txt, static: null}\n"))
    assert [t.path for t in s.trials] == [str(day / f"t{i:03d}.txt") for i in range(4)] + [
        str(day / "S02" / "rom.txt")]
    assert [t.line for t in s.trials] == [5, 6, 7, 8, 9]
    t0, t1, t2, t3, t4 = (t.fields for t in s.trials)
    assert t0 == {"subject": "S01", "rom": str(day / "S01/rom.txt"),
                  "static": str(day / "S01/static.txt")}
    assert t1 == {**t0, "notes": "loose marker"}  # text fields stay text
    assert t2 == {"subject": "S02", "rom": str(day / "S02/rom.txt")}
    assert t3 == {}
    assert t4 == {"subject": "S02", "rom": str(day / "S01/rom.txt")}  # own field wins
    assert is_session(str(day / "day1.yaml"))


def test_csv_session_reads_columns_and_empty_cells(day):
    p = _write(day / "day1.csv", "trial,subject,rom,static\n"
               "t000.txt,S01,S01/rom.txt,S01/static.txt\n"
               "\n"
               f"t002.txt,S02,{day / 'S02/rom.txt'},\n"
               "t003.txt,,,\n")
    assert is_session(str(p))
    s = read_session(p)
    assert [(Path(t.path).name, t.line) for t in s.trials] == [
        ("t000.txt", 2), ("t002.txt", 4), ("t003.txt", 5)]
    assert s.trials[0].fields == {"subject": "S01", "rom": str(day / "S01/rom.txt"),
                                  "static": str(day / "S01/static.txt")}
    assert s.trials[1].fields == {"subject": "S02", "rom": str(day / "S02/rom.txt")}
    assert s.trials[2].fields == {}
    # a CSV part whose first header cell is not `trial` is an ordinary part
    strokes = _write(day / "strokes.csv", "x,y,t\n0,0,0\n")
    assert not is_session(str(strokes))


@pytest.mark.parametrize("name, text, line, says", [
    ("a.yaml", "trials:\n  - {trial: t000.txt}\n  - {trial: nope.txt, subject: S01}\n", 3,
     "trials[1].trial: missing file 'nope.txt'"),
    ("b.yaml", "subjects:\n  S01: {rom: S01/rom.txt}\ntrials:\n"
     "  - {trial: t000.txt, subject: S01, rom: S09/rom.txt}\n", 4,
     "trials[0].rom: trial 't000.txt': missing file 'S09/rom.txt'"),
    ("c.yaml", "subjects:\n  S01:\n    rom: S01/gone.txt\ntrials: [t000.txt]\n", 3,
     "subjects.S01.rom: missing file 'S01/gone.txt'"),
    ("d.yaml", "subjects:\n  S01: {rom: S01/rom.txt}\ntrials:\n  - {trial: t000.txt}\n"
     "  - {trial: t001.txt, subject: S0l}\n", 5,
     "trials[1].subject: trial 't001.txt': unknown subject 'S0l' (did you mean 'S01'?)"),
    ("e.session.csv", "subject,trial\nS01,t000.txt\n", 1, "no trial column"),
    ("f.csv", "trial,rom\nt000.txt,S01/rom.txt\nt001.txt,S03/rom.txt\n", 3,
     "rom: trial 't001.txt': missing file 'S03/rom.txt'"),
    ("g.csv", "trial,rom\nt000.txt\nt000.txt,S01/rom.txt\n", 3, "listed twice (first at line 2)"),
    ("h.yaml", "trials:\n  - {subject: S01}\n", 2, "trials[0]: no trial:"),
])
def test_bad_session_is_one_line_naming_file_line_and_trial(day, name, text, line, says):
    p = _write(day / name, text)
    with pytest.raises(ConfigError) as e:
        read_session(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}:{line}: "), msg
    assert says in msg and "\n" not in msg


def test_bad_session_given_as_parts_names_the_session(day, tmp_path):
    p = _write(day / "bad.yaml", "trials:\n  - {trial: t000.txt, rom: S01/none.txt}\n")
    cfg = _write(tmp_path / "g.yaml", _TOY)
    with pytest.raises(ConfigError, match=rf"^{p}:2: trials\[0\]\.rom: .*missing file"):
        load_config(cfg, parts=[str(p)])


def test_ten_thousand_trials_read_quickly(day):
    (day / "many").mkdir()
    for i in range(10_000):
        (day / "many" / f"{i}.txt").touch()
    p = _write(day / "big.csv", "trial,subject,rom\n" + "".join(
        f"many/{i}.txt,S01,S01/rom.txt\n" for i in range(10_000)))
    y = _write(day / "big.yaml", "trials:\n" + "".join(
        f"  - {{trial: many/{i}.txt, subject: S01}}\n" for i in range(10_000)))
    t0 = time.perf_counter()
    assert len(read_session(p).trials) == 10_000
    assert len(read_session(y).trials) == 10_000
    assert time.perf_counter() - t0 < 10


# --------------------------------------------------------------------------- parts & params

_TOY = """\
params: {rom: null}
nodes:
  read: {stage: toy_read_file, inputs: {path: part}}
  ref:
    stage: toy_read_ref
    inputs: {path: part}
    params:
      ref: ${part.rom,${params.rom}}
  ref_scaled: {stage: toy_scale, inputs: {values: ref.values}, params: {factor: 10.0}}
  pair: {stage: toy_pair, inputs: {values: read.values, ref: ref_scaled.values}}
"""


def test_session_parts_ids_and_fields_with_plain_parts_mixed(day, tmp_path, monkeypatch):
    _write(day / "day1.yaml", SESSION)
    cfg = _write(tmp_path / "g.yaml", _TOY)
    other = tmp_path / "elsewhere"
    other.mkdir()
    monkeypatch.chdir(other)  # --parts relative to the working directory, ids to the config
    c = load_config(cfg, parts=["../day/day1.yaml", "../day/t000.txt", "../day/S01/rom.txt"])
    assert c.parts == [f"day/t00{i}.txt" for i in range(4)] + ["day/S01/rom.txt"]
    assert c.part_fields["day/t001.txt"]["notes"] == "loose marker"
    assert c.part_fields["day/t002.txt"] == {"subject": "S02", "rom": str(day / "S02/rom.txt")}
    assert "day/t003.txt" not in c.part_fields and "day/S01/rom.txt" not in c.part_fields
    # in parts: (relative to the config's folder)
    c2 = parse_config(_TOY + "parts: [day/day1.yaml]\n", file=str(cfg), path=cfg)
    assert c2.parts == c.parts[:4] and c2.part_fields == c.part_fields


def _runs(cfg: Path, store: Store, parts, targets=("pair",)):
    res = run(build_graph(load_config(cfg, parts=parts), list(targets)), store)
    return res, {(r["node"], r["part"]): r for r in res.records}


def test_two_subjects_each_trial_reads_its_subjects_file_computed_once(day, tmp_path):
    _write(day / "day1.yaml", SESSION)
    cfg = _write(tmp_path / "g.yaml", _TOY)
    g = build_graph(load_config(cfg, parts=[str(day / "day1.yaml")]), ["pair"])
    ref = g.node_tasks("ref")
    s1, s2 = f"ref={day}/S01/rom.txt", f"ref={day}/S02/rom.txt"
    assert [t.part for t in ref] == [s1, s2, f"{day}/t003.txt"]
    assert [t.inputs["path"] for t in ref] == [
        FileWire(str(day / "S01/rom.txt")), FileWire(str(day / "S02/rom.txt")),
        FileWire(str(day / "t003.txt"))]
    assert [t.params["ref"] for t in ref] == [str(day / "S01/rom.txt"),
                                               str(day / "S02/rom.txt"), None]
    # each trial's pair task reads its own subject's group
    by_index = {t.index: t for t in g.tasks}
    ups = [by_index[t.inputs["ref"].index].part for t in g.node_tasks("pair")]
    assert ups == [s1, s1, s2, f"{day}/t003.txt"]

    store = Store(tmp_path / "store")
    res, recs = _runs(cfg, store, [str(day / "day1.yaml")])
    assert res.counts["failed"] == 0
    computed = sorted((n, p) for (n, p), r in recs.items()
                      if n == "ref" and r["status"] == "computed")
    assert computed == sorted([("ref", s1), ("ref", s2), ("ref", f"{day}/t003.txt")])
    out = [decode(store.load("toy_pair", recs[("pair", f"{day}/t00{i}.txt")]["key"], "values"))
           for i in range(4)]
    np.testing.assert_array_equal(out[0], np.arange(5.0) + 3000.0)  # S01: 10 * (100 + 200)
    np.testing.assert_array_equal(out[1], np.arange(1.0, 6.0) + 3000.0)
    np.testing.assert_array_equal(out[2], np.arange(2.0, 7.0) + 70.0)  # S02: 10 * 7
    np.testing.assert_array_equal(out[3], np.arange(3.0, 8.0) + 10 * np.arange(3.0, 8.0).sum())
    # a rerun is all hits
    again, _ = _runs(cfg, store, [str(day / "day1.yaml")])
    assert again.counts["computed"] == 0 and again.counts["hit"] == len(again.records)


def test_keys_do_not_depend_on_the_working_directory(day, tmp_path, monkeypatch):
    _write(day / "day1.yaml", SESSION)
    cfg = _write(tmp_path / "g.yaml", _TOY)
    store = Store(tmp_path / "store")
    keys = []
    for where, session in ((day, "day1.yaml"), (tmp_path, "day/day1.yaml")):
        monkeypatch.chdir(where)
        _, recs = _runs(cfg, store, [session])
        keys.append({k: r["key"] for k, r in recs.items()})
    assert keys[0] == keys[1]
    assert ("ref", "ref=day/S01/rom.txt") in keys[0]  # ids relative to the config's folder


def test_plain_parts_keep_their_tasks_and_keys(day, tmp_path):
    before = _TOY.replace("${part.rom,${params.rom}}", "${params.rom}")
    old = _write(tmp_path / "old.yaml", before)
    new = _write(tmp_path / "new.yaml", _TOY)
    parts = [str(day / "t00*.txt")]
    for sets in ({}, {"params.rom": str(day / "S02/rom.txt")}):
        a = build_graph(load_config(old, parts=parts, sets=sets), ["pair"])
        b = build_graph(load_config(new, parts=parts, sets=sets), ["pair"])
        assert [(t.node, t.part, t.params, t.inputs) for t in a.tasks] == [
            (t.node, t.part, t.params, t.inputs) for t in b.tasks]
        assert len(b.node_tasks("ref")) == (1 if sets else 4)
    store = Store(tmp_path / "store")
    r_old, _ = _runs(old, store, parts)
    r_new, _ = _runs(new, store, parts)
    assert r_new.counts["computed"] == 0 and r_old.counts["computed"] == len(r_old.records)
    # a one-subject session shares the entry of the same file given as params.rom
    one = _write(day / "one.csv", "trial,subject,rom\n" + "".join(
        f"t00{i}.txt,S02,S02/rom.txt\n" for i in range(4)))
    run(build_graph(load_config(old, parts=parts, sets={"params.rom": str(day / "S02/rom.txt")}),
                    ["pair"]), store)
    r_one, recs = _runs(new, store, [str(one)])
    assert r_one.counts["computed"] == 0 and recs[("ref", None)]["status"] == "hit"


def test_part_param_is_validated_per_task(day, tmp_path):
    _write(day / "day1.yaml", SESSION)
    text = _TOY + "  add: {stage: toy_add, inputs: {values: read.values},\n" \
                  "        params: {amount: '${part.subject,1.5}'}}\n"
    cfg = _write(tmp_path / "g.yaml", text)
    plain = build_graph(load_config(cfg, parts=[str(day / "t000.txt")]), ["add"])
    assert plain.node_tasks("add")[0].params["amount"] == 1.5  # the default, validated
    with pytest.raises(ConfigError, match=rf"^{cfg}:12: nodes\.add\.params\.amount: part "
                       rf"{day}/t000.txt: .*amount"):
        build_graph(load_config(cfg, parts=[str(day / "day1.yaml")]), ["add"])


@pytest.mark.parametrize("text, line, says", [
    (_TOY + "  total: {stage: toy_sum, inputs: {values: read.values}, gather: true}\n"
     "  src:\n    stage: toy_source\n    params:\n      n: ${part.n,3}\n", 15,
     "nodes.src.params.n: ${part.n,3} needs a task per part"),
    (_TOY.replace("params: {rom: null}", "params: {rom: '${part.rom}'}"), 1,
     "params.rom: ${part.rom} must be the whole value of a node param"),
    (_TOY.replace("{factor: 10.0}", "{factor: 'x ${part.f}'}"), 9,
     "${part.f} must be the whole value of a node param"),
])
def test_misplaced_part_ref_is_a_config_error(day, tmp_path, text, line, says):
    cfg = _write(tmp_path / "g.yaml", text)
    with pytest.raises(ConfigError) as e:
        load_config(cfg, parts=[str(day / "t000.txt")])
    assert str(e.value).startswith(f"{cfg}:{line}: ") and says in str(e.value), str(e.value)


def test_part_ref_without_default_needs_the_field(day, tmp_path):
    _write(day / "day1.yaml", SESSION)
    cfg = _write(tmp_path / "g.yaml", _TOY.replace("${part.rom,${params.rom}}", "${part.rom}"))
    with pytest.raises(ConfigError, match=rf"^{cfg}:8: nodes\.ref\.params\.ref: part "
                       rf"{day}/t003.txt has no field 'rom'"):
        build_graph(load_config(cfg, parts=[str(day / "day1.yaml")]), ["ref"])


# --------------------------------------------------------------------------- skin


@pytest.mark.skipif(not (C3D / "btkdata_c3dorg_Eb015pr.c3d").exists(), reason="no C3D data")
def test_skin_session_reads_each_subjects_rom(tmp_path, capsys):
    from mocapflow.pipeline.cli import main

    session = _write(tmp_path / "day1.session.yaml", f"""\
subjects:
  S01: {{rom: {C3D}/btkdata_c3dorg_Eb015pr.c3d}}
  S02: {{rom: {C3D}/ktk_kinematics_racing_full.c3d}}
trials:
  - {{trial: {C3D}/pyomeca_markers_analogs.c3d, subject: S01}}
  - {{trial: {C3D}/ezc3d-testFiles_Qualisys.c3d, subject: S02}}
  - {{trial: {C3D}/ktk_kinematics_basket_sprint.c3d, subject: S01}}
""")
    store = tmp_path / "store"
    args = ["run", "skin", "--parts", str(session), "--target", "rom_ingest", "--executor",
            "sync", "--store", str(store), "-q"]
    assert main(args) == 0, capsys.readouterr().err
    (rec,) = Store(store).runs()
    tasks = {t["part"]: t for t in rec["tasks"] if t["node"] == "rom_ingest"}
    assert set(tasks) == {f"rom={C3D}/btkdata_c3dorg_Eb015pr.c3d",
                          f"rom={C3D}/ktk_kinematics_racing_full.c3d"}
    names = {p: decode(Store(store).load("ingest_rom", t["key"], "report"))["path"]
             for p, t in tasks.items()}
    assert names == {p: p.rsplit("/", 1)[1] for p in tasks}
    assert {t["status"] for t in tasks.values()} == {"computed"}
    cwd = os.getcwd()
    try:  # same keys from another folder: all hits
        os.chdir(tmp_path)
        assert main(args) == 0
    finally:
        os.chdir(cwd)
    last = Store(store).runs()[-1]
    assert {t["status"] for t in last["tasks"]} == {"hit"}


def test_group_task_needs_one_value_from_its_parts(day, tmp_path):
    _write(day / "day1.yaml", SESSION)
    cfg = _write(tmp_path / "g.yaml", _TOY + "  check: {stage: toy_fail_on, inputs: {values: "
                 "ref.values}, params: {pattern: '${part.notes,none}'}}\n")
    with pytest.raises(ConfigError, match=r":11: nodes\.check\.params\.pattern: task "
                       rf"check/ref={day}/S01/rom\.txt stands for several parts .*'loose marker'"):
        build_graph(load_config(cfg, parts=[str(day / "day1.yaml")]), ["check"])
    ok = load_config(cfg, parts=[str(day / "day1.yaml")])  # the config itself loads
    assert ok.nodes["check"].params["pattern"] == "none"
