"""The session report (``mocapflow report``): the page of a graph's last run, its summary
table with the stages' key figures, the figures of the report providers, notes for
providers that fail, one-line errors; and one real run of the texture graph."""

from __future__ import annotations

import base64
import io
import json
import re
from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline import registry
from mocapflow.pipeline.context import Context
from mocapflow.pipeline.registry import report_figures, stage
from mocapflow.pipeline.report import html_table
from mocapflow.pipeline.testing import write_config

SYNC = ("--executor", "sync")
ROOT = Path(__file__).resolve().parents[2]
BVH = ROOT.parent / "shared" / "data" / "bvh" / "cmu_131_02.bvh"
IMG = re.compile(r'<img alt="[^"]*" src="data:image/png;base64,([A-Za-z0-9+/=]+)">')


@stage("report_toy_figures", outputs=("values",))
def report_toy_figures(values: np.ndarray, *, ctx: Context) -> dict:
    """Pass the values through, reporting their total and count as key figures."""
    values = np.asarray(values)
    ctx.figure("total", float(values.sum()))
    ctx.figure("count", int(values.size))
    return {"values": values}


FIGURE_CONFIG = """\
graph: figs
parts:
  - {parts}
targets: [figs]
nodes:
  read:
    stage: toy_read_file
    inputs: {{path: part}}
  figs:
    stage: report_toy_figures
    inputs: {{values: read.values}}
"""


def _draw_values(outputs, entry):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(3, 2))
    fig.subplots().plot(outputs["values"], "o-")
    return [(f"values of {entry.node}", fig),
            ("table", html_table(["n", "sum"], [[len(outputs["values"]),
                                                 float(np.sum(outputs["values"]))]]))]


@pytest.fixture
def providers(monkeypatch):
    """An empty provider registry for the test (the real ones are put back after)."""
    registry.discover()  # the families register into the real dict, before it is swapped
    monkeypatch.setattr(registry, "_REPORT_PROVIDERS", {})
    return registry._REPORT_PROVIDERS


def _pngs(page: str) -> list[np.ndarray]:
    """Every ``<img>`` of the page decoded (each must be a valid PNG)."""
    import matplotlib.image as mpimg

    out = []
    for b64 in IMG.findall(page):
        raw = base64.b64decode(b64, validate=True)
        assert raw[:8] == b"\x89PNG\r\n\x1a\n"
        out.append(mpimg.imread(io.BytesIO(raw), format="png"))
    return out


def _report(cli, config, store, to, *extra):
    code, out, err = cli("report", config, "--store", store, "--to", to, "--json", *extra)
    assert code == 0, err
    doc = json.loads(out)
    return doc, Path(doc["path"]).read_text(encoding="utf-8")


def test_report_page_has_the_run_its_table_and_provider_figures(cli, toy_config, tmp_path,
                                                                 providers):
    report_figures("toy_scale")(_draw_values)
    s = tmp_path / "s"
    code, out, _ = cli("run", toy_config, "--store", s, *SYNC, "--json", "-q")
    run_id = json.loads(out)["run_id"]
    doc, page = _report(cli, toy_config, s, tmp_path / "out")
    assert Path(doc["path"]) == tmp_path / "out" / f"toy-{run_id}.html"
    assert doc["run_id"] == run_id and doc["notes"] == []
    assert f"toy — run {run_id}" in page and "16 task(s)" in page
    table = page[page.index('id="summary"'):page.index("</table>", page.index('id="summary"'))]
    assert table.count("<tr>") == 17  # header + 16 tasks
    assert table.count(">computed<") == 16
    # 5 scale parts: the first MAX_PARTS_PER_NODE drawn, the rest counted
    images = _pngs(page)
    assert doc["figures"] == len(images) == 4
    assert all(im.shape[0] > 50 and im.shape[1] > 50 and im.std() > 0.01 for im in images)
    assert "… figures of 1 more part(s) of scale not shown" in page
    assert page.count('<table class="data"><tr><th>n</th><th>sum</th>') == 4
    # self-contained: no script, no link to anything outside the page
    assert "<script" not in page and not re.search(r"""(src|href)=["']?(https?:|//|file:)""",
                                                     page)


def test_key_figures_in_the_summary_never_in_the_outputs(cli, tmp_path, data_dir, providers):
    cfg = write_config(tmp_path / "figs.yaml", FIGURE_CONFIG, parts=f"{data_dir}/*.txt")
    s = tmp_path / "s"
    code, out, _ = cli("run", cfg, "--store", s, *SYNC, "--json", "-q")
    tasks = [t for t in json.loads(out)["tasks"] if t["node"] == "figs"]
    assert code == 0 and [list(t["outputs"]) for t in tasks] == [["values"]] * 5
    doc, page = _report(cli, cfg, s, tmp_path / "out")
    assert "<th>count</th><th>total</th>" in page  # (records keep them by name)
    # trial002.txt holds 2 3 4 5 6
    row = next(r for r in page.split("<tr>") if "figs/trial002" in r)
    assert '<td class="num">5</td><td class="num">20</td>' in row
    assert doc["figures"] == 0  # no provider for these stages: the table only


def test_a_failing_provider_is_a_note_not_an_abort(cli, toy_config, tmp_path, providers):
    def broken(outputs, entry):
        raise ZeroDivisionError("drawing went wrong")

    def bad_item(outputs, entry):
        return [("not an image", np.zeros(3))]

    report_figures("toy_add")(broken)
    report_figures("toy_scale")(_draw_values)
    report_figures("toy_sum")(bad_item)
    s = tmp_path / "s"
    assert cli("run", toy_config, "--store", s, *SYNC, "-q")[0] == 0
    doc, page = _report(cli, toy_config, s, tmp_path / "out")
    assert doc["figures"] == 4  # toy_scale still drawn
    add_notes = [n for n in doc["notes"] if n.startswith("add/")]
    assert len(add_notes) == 4
    assert "ZeroDivisionError: drawing went wrong" in add_notes[0]
    assert any("total: figure 'not an image' could not be drawn" in n for n in doc["notes"])
    assert page.count('class="note"') >= 6


def test_report_without_a_run_or_with_an_unknown_run_is_one_line(cli, toy_config, tmp_path):
    s = tmp_path / "s"
    code, out, err = cli("report", toy_config, "--store", s, "--to", tmp_path / "out")
    assert code == 2 and out == ""
    assert err.strip().count("\n") == 0
    assert "no run of graph 'toy'" in err and "mocapflow run" in err
    assert not (tmp_path / "out").exists()
    assert cli("run", toy_config, "--store", s, *SYNC, "-q")[0] == 0
    code, _, err = cli("report", toy_config, "--store", s, "--to", tmp_path / "out",
                       "--run-id", "20000101T000000-deadbeef")
    assert code == 2 and "no run 20000101T000000-deadbeef in store" in err


def test_report_takes_the_last_run_or_the_one_named(cli, toy_config, tmp_path, providers):
    s = tmp_path / "s"
    ids = []
    for amount in (1.0, 5.0):
        code, out, _ = cli("run", toy_config, "--store", s, *SYNC, "--json", "-q",
                           "--set", f"params.amount={amount}")
        ids.append(json.loads(out)["run_id"])
    doc, page = _report(cli, toy_config, s, tmp_path / "out")
    assert doc["run_id"] == ids[1] and ids[0] not in page
    doc, page = _report(cli, toy_config, s, tmp_path / "out", "--run-id", ids[0])
    assert doc["run_id"] == ids[0] and Path(doc["path"]).name == f"toy-{ids[0]}.html"
    assert len(list((tmp_path / "out").glob("*.html"))) == 2


def test_html_table_escapes_its_cells():
    t = html_table(["a<b"], [["<script>x</script>"], [1.23456]])
    assert "<script>" not in t and "&lt;script&gt;" in t and "a&lt;b" in t
    assert '<td class="num">1.23</td>' in t


@pytest.fixture(scope="module")
def texture_run(tmp_path_factory):
    """One real run of the texture graph (128 frames, one seed) and its report."""
    if not BVH.is_file():
        pytest.skip(f"sample data {BVH} absent")
    from mocapflow.pipeline.executors import SyncExecutor
    from mocapflow.pipeline.graph import load_graph
    from mocapflow.pipeline.report import render_report
    from mocapflow.pipeline.runner import run
    from mocapflow.pipeline.store import Store

    tmp = tmp_path_factory.mktemp("texture")
    graph = load_graph("texture", parts=[str(BVH)],
                       sets=["synth.length=128", "synth.seeds=1"])
    store = Store(tmp / "store")
    result = run(graph, store, executor=SyncExecutor())
    assert result.ok, [r.error for r in result.failed()]
    return graph, store, result, render_report(graph, store), tmp


def test_texture_report_has_its_figures(texture_run):
    graph, store, result, rep, tmp = texture_run
    synth = next(r for r in result.records if r.node == "synth")
    assert set(synth.figures) >= {"seams", "longest verbatim run"}
    assert rep.run_id == result.run_id and rep.notes == []
    images = _pngs(rep.html)
    assert rep.images == len(images) >= 3  # path, seams/angles, stick-figure strip
    assert all(im.std() > 0.01 for im in images)
    assert "Root path from above" in rep.html and "Synthesis report" in rep.html
    assert f"<td class=\"num\">{synth.figures['seams']}</td>" in rep.html
    path = rep.write(tmp / "out")
    assert path.name == f"texture-{result.run_id}.html" and path.stat().st_size > 20_000


def test_texture_report_with_a_broken_provider_still_written(texture_run, monkeypatch):
    graph, store, result, _, tmp = texture_run
    from mocapflow.pipeline.report import write_report

    def broken(outputs, entry):
        raise KeyError("no such output")

    monkeypatch.setitem(registry._REPORT_PROVIDERS, "synth", broken)
    path = write_report(graph, store, tmp / "broken")
    page = path.read_text()
    assert IMG.findall(page) == []
    assert "the synth figures could not be drawn: KeyError" in page
    assert "<table class=\"data\" id=\"summary\">" in page
