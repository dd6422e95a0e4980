"""Export: layout DIR/<node>/<part label>/<output>.<ext>, arrays, JSON values, records;
every written path stays under --to (labels made safe, symlinks out refused)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from mocapflow.pipeline import codecs
from mocapflow.pipeline.codecs import ExportFormatError
from mocapflow.pipeline.config import load_config
from mocapflow.pipeline.export import export_results, safe_label
from mocapflow.pipeline.graph import build_graph
from mocapflow.pipeline.runner import run
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.testing import write_config

SYNC = ("--executor", "sync")


def test_export_layout_and_content(cli, toy_config, tmp_path):
    out_dir = tmp_path / "out"
    code, out, err = cli("export", toy_config, "--to", out_dir, "--store", tmp_path / "s",
                         *SYNC, "--target", "scale", "--target", "total")
    assert code == 0
    total = np.load(out_dir / "total" / "all" / "total.npy")
    np.testing.assert_array_equal(total, [2 * (5 * i + 15) for i in range(5)])
    assert json.loads((out_dir / "total" / "all" / "report.json").read_text()) == {
        "parts": 5, "grand_total": float(total.sum())}
    np.testing.assert_array_equal(np.load(out_dir / "scale" / "trial002" / "values.npy"),
                                  2 * (np.arange(5.0) + 3))
    assert len(out.splitlines()) == 7
    # a record output: attrs as JSON, arrays as .npy
    cfg = write_config(tmp_path / "r.yaml", """\
        nodes:
          src: {stage: toy_source, params: {n: 8}}
          stats: {stage: toy_stats, inputs: {values: src.values}}
        targets: [stats]
        """)
    code, out, err = cli("export", cfg, "--to", out_dir, "--store", tmp_path / "s", *SYNC)
    rec = json.loads((out_dir / "stats" / "all" / "stats.json").read_text())
    assert rec["mean"] == 3.5 and rec["_arrays"]["hist"] == "stats.hist.npy"
    np.testing.assert_array_equal(np.load(out_dir / "stats" / "all" / "stats.hist.npy"),
                                  [2, 2, 2, 2])


def test_safe_label():
    assert safe_label("cmu_131_02.seed3") == "cmu_131_02.seed3"  # ordinary labels unchanged
    assert safe_label("Take 01") == "Take 01"
    assert safe_label("a.seed/../../x") == "a.seed_.._.._x"
    assert safe_label("..") == "_.." and safe_label(".") == "_." and safe_label("") == "_"
    assert safe_label("a\\b\x00c\nd") == "a_b_c_d"
    long = safe_label("é" * 300)
    assert len(long.encode()) <= 200 and long != safe_label("é" * 301)


def test_export_labels_cannot_leave_to(cli, tmp_path, monkeypatch):
    """Part ids whose labels hold ``/`` or ``..``: written under --to, never outside."""
    work = tmp_path / "w"
    (work / "d" / "a#seed=x").mkdir(parents=True)
    (work / "d" / "a#seed=x" / "v.txt").write_text("1 2 3\n")
    monkeypatch.chdir(work)
    cfg = write_config(work / "x.yaml", """\
        parts: ["d/a#seed=x/v.txt"]
        nodes:
          read: {stage: toy_read_file, inputs: {path: part}}
        """)
    code, out, err = cli("export", cfg, "--to", work / "out", "--store", work / "s", *SYNC,
                         "-q")
    assert code == 0 and out == "", err  # -q: no file list
    code, out, err = cli("export", cfg, "--to", work / "out", "--store", work / "s", *SYNC,
                         "--json")
    assert code == 0, err
    written = [Path(p) for p in json.loads(out)["files"]]
    assert written == [work / "out" / "read" / "a.seedx_v.txt" / "values.npy"]  # not a.seedx/v
    assert np.load(written[0]).tolist() == [1.0, 2.0, 3.0]
    # records naming parts that climb out (whatever made them): still under --to
    graph = build_graph(load_config(cfg))
    store = Store(work / "s")
    rec = next(r for r in run(graph, store).records if r.node == "read")
    evil = [replace(rec, part=p) for p in ("x#seed=/../../../../victim", "..", "a\\..\\b")]
    files = export_results(graph, store, evil, work / "out2")
    assert sorted(f.parent.name for f in files) == ["_.", "b", "x.seed_.._.._.._.._victim"]
    assert all(f.resolve().is_relative_to(work / "out2") for f in files)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w"]


def test_export_through_a_symlink_out_of_to_is_refused(cli, toy_config, tmp_path):
    out_dir = tmp_path / "out"
    outside = tmp_path / "outside"
    (out_dir / "total").mkdir(parents=True)
    outside.mkdir()
    (out_dir / "total" / "all").symlink_to(outside)
    code, out, err = cli("export", toy_config, "--to", out_dir, "--store", tmp_path / "s", *SYNC,
                         "--target", "total", "-q")
    assert code == 1 and out == ""
    assert err.strip().splitlines() == [
        f"mocapflow: error: export: {out_dir}/total/all resolves to {outside}, outside the "
        f"export directory {out_dir} (a symlink?); not writing there"]
    assert list(outside.iterdir()) == []
    (out_dir / "total" / "all").unlink()
    (out_dir / "total" / "all").mkdir()
    (out_dir / "total" / "all" / "total.npy").symlink_to(outside / "total.npy")
    code, out, err = cli("export", toy_config, "--to", out_dir, "--store", tmp_path / "s", *SYNC,
                         "--target", "total", "-q")
    assert code == 1 and "is a symlink pointing outside the export directory" in err
    assert list(outside.iterdir()) == []


def test_format_option_reaches_the_exporter_and_bad_ones_are_one_line(cli, toy_config, tmp_path,
                                                                     monkeypatch):
    """``export --format TYPE=F1,F2`` is the exporter's ``formats``; an unknown one is one line."""
    seen = []

    def fake(value, directory, stem, **options):
        seen.append(options.get("formats"))
        if "bad" in (options.get("formats") or ()):
            raise ExportFormatError("unknown format(s) ['bad']; it writes a, b")
        p = directory / f"{stem}.fake"
        p.write_text("x")
        return [p]

    monkeypatch.setitem(codecs._EXPORTERS, "ndarray", fake)
    base = (toy_config, "--store", tmp_path / "s", *SYNC, "-q")
    code, _, err = cli("export", *base, "--to", tmp_path / "o1", "--format", "ndarray=a,b")
    assert code == 0, err
    assert set(seen) == {("a", "b")}
    seen.clear()
    assert cli("export", *base, "--to", tmp_path / "o2")[0] == 0 and set(seen) == {None}
    code, _, err = cli("export", *base, "--to", tmp_path / "o3", "--format", "ndarray=bad")
    assert code == 1 and err == ("mocapflow: error: export: --format ndarray: unknown "
                                 "format(s) ['bad']; it writes a, b\n")
    code, _, err = cli("export", *base, "--to", tmp_path / "o4", "--format", "mesh")
    assert code == 2 and err.startswith("mocapflow: error: --format 'mesh': expected TYPE=")
    # the exporter's own defaults refused (e.g. usd-core missing): the error names no --format

    def refuse(value, directory, stem, **options):
        raise ExportFormatError("needs usd-core")

    monkeypatch.setitem(codecs._EXPORTERS, "ndarray", refuse)
    code, _, err = cli("export", *base, "--to", tmp_path / "o5")
    assert code == 1 and "--format" not in err and err.startswith("mocapflow: error: export: "
                                                                  "ndarray (")
    assert err.rstrip().endswith("needs usd-core")
