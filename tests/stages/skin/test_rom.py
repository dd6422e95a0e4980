"""Segmenting from a separate range-of-motion trial (Park & Hodgins 2006 §5.2) in the skin graph."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.cli import main
from mocapflow.pipeline.codecs import decode
from mocapflow.pipeline.store import Store
from mocapflow.stages.motion.datatypes import Markers
from mocapflow.stages.motion.formats.c3d import read_c3d, write_c3d
from mocapflow.stages.motion.simulate.capture import simulate_capture
from mocapflow.stages.skin.rom import ingest_rom, match_labels, match_markers
from mocapflow.stages.skin.segmentation import Segmentation
from tests.stages.conftest import simulated_capture

SKIN = Path(__file__).parents[3] / "configs" / "skin.yaml"
SMALL = dict(n_markers=40, n_frames=60, rate=60.0, body_vertices=1200, ghost_rate=0.0)


# --------------------------------------------------------------------------- simulator layout


def _layout(sim):
    t = sim.truth
    return t["labels"], t["bind_pose"], t["marker_face"], t["marker_barycentric"]


def test_same_seed_same_marker_layout_across_motions():
    dyn = simulated_capture(motion="dynamic", rng=3, **SMALL)
    rom = simulated_capture(motion="range_of_motion", rng=3, **SMALL)
    other = simulated_capture(motion="dynamic", rng=4, **SMALL)
    labels, bind, face, bary = _layout(dyn)
    assert _layout(rom)[0] == labels == dyn.markers.labels == rom.markers.labels
    np.testing.assert_array_equal(_layout(rom)[1], bind)
    np.testing.assert_array_equal(_layout(rom)[2], face)
    np.testing.assert_array_equal(_layout(rom)[3], bary)
    # the body is the same too; the motions are not
    np.testing.assert_array_equal(dyn.body.vertices, rom.body.vertices)
    assert np.nanmax(np.abs(dyn.truth["positions"][-1] - rom.truth["positions"][-1])) > 0.05
    # another seed gives another layout (the layout is seeded, just not by the motion)
    assert np.abs(_layout(other)[1] - bind).max() > 0.01


def test_stage_context_rng_gives_the_same_layout_for_the_same_part_id():
    kw = {k: v for k, v in SMALL.items()}
    a = simulate_capture(motion="walk", seed=0, ctx=Context(part="seed=0", seed=0), **kw)
    b = simulate_capture(motion="range_of_motion", seed=0, ctx=Context(part="seed=0", seed=0),
                         **kw)
    np.testing.assert_array_equal(a["truth"]["bind_pose"], b["truth"]["bind_pose"])
    np.testing.assert_array_equal(a["truth"]["marker_face"], b["truth"]["marker_face"])


# --------------------------------------------------------------------------- label matching


def _segmentation(labels):
    M = len(labels)
    ref = np.random.default_rng(0).normal(size=(M, 3))
    return Segmentation(
        labels=labels, part_names=["p0"], weights=np.ones((M, 1)), reference=ref,
        faces=np.array([[0, 1, 2]]), origins=np.zeros((1, 3)), axes=np.eye(3)[None],
        triangle_clusters=np.zeros(1, dtype=np.int64), attrs={},
    )


def test_match_labels_columns_absent_extra():
    cols, absent, extra = match_labels(["a", "b", "c", "x"], ["c", "a", "z", "b"])
    np.testing.assert_array_equal(cols, [2, 0, -1, 1])
    assert absent == ["z"] and extra == ["x"]


def test_match_markers_reorders_fills_absent_and_warns_by_name():
    rng = np.random.default_rng(1)
    pos = rng.normal(size=(5, 4, 3))
    trial = Markers(pos, ["A", "B", "C", "X"], rate=100.0, residuals=np.zeros((5, 4)))
    seg = _segmentation(["C", "A", "Z", "B"])
    ctx = Context(part="t")
    out = match_markers(trial, seg, ctx=ctx)
    m = out["markers"]
    assert m.labels == ["C", "A", "Z", "B"] and m.rate == 100.0
    np.testing.assert_array_equal(m.positions[:, 0], pos[:, 2])
    np.testing.assert_array_equal(m.positions[:, 3], pos[:, 1])
    assert np.isnan(m.positions[:, 2]).all() and np.isnan(m.residuals[:, 2]).all()
    assert out["report"] == {"markers": 4, "matched": 3, "absent": ["Z"], "left_out": ["X"]}
    assert any("lacks 1 markers" in w and "Z" in w for w in ctx.warnings)
    assert any("left out" in w and "X" in w for w in ctx.warnings)
    # the same marker set: no warning, identical positions
    ctx2 = Context(part="t")
    same = match_markers(trial, _segmentation(["A", "B", "C", "X"]), ctx=ctx2)
    np.testing.assert_array_equal(same["markers"].positions, pos)
    assert ctx2.warnings == []


def test_match_markers_rejects_another_marker_set():
    trial = Markers(np.zeros((2, 3, 3)), ["A", "B", "C"], rate=100.0)
    with pytest.raises(ValueError, match=r"lacks 3 of the segmentation's 4 markers.*P, Q, R"):
        match_markers(trial, _segmentation(["A", "P", "Q", "R"]), ctx=Context())


# --------------------------------------------------------------------------- skin graph


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """Two trials (run, walk) and a ROM trial of one body and layout; some markers removed."""
    d = tmp_path_factory.mktemp("rom")
    sims = {name: simulated_capture(motion=motion, rng=0, **SMALL)
            for name, motion in (("run", "dynamic"), ("walk", "walk"),
                                 ("rom", "range_of_motion"))}
    labels = sims["run"].markers.labels
    files = {}
    for name, sim in sims.items():
        mk = sim.markers
        drop = {"rom": labels[5:8], "walk": labels[20:22]}.get(name, [])
        keep = [i for i, lb in enumerate(mk.labels) if lb not in drop]
        mk = mk.replace(positions=mk.positions[:, keep], labels=[mk.labels[i] for i in keep],
                        residuals=None if mk.residuals is None else mk.residuals[:, keep])
        files[name] = d / f"{name}.c3d"
        write_c3d(mk, files[name])
    return files, labels


def _run(tmp_path, capsys, files, *extra):
    capsys.readouterr()
    code = main(["run", str(SKIN), "--store", str(tmp_path / "store"), "--executor", "sync",
                 "--parts", str(files["run"]), "--parts", str(files["walk"]),
                 "--target", "deform", "--set", "template.n_vertices=1500", "--json", "-q",
                 *extra])
    out, err = capsys.readouterr()
    assert code == 0, err[-2000:]
    return json.loads(out)


def test_skin_graph_segments_the_rom_trial_once_for_every_part(captures, tmp_path, capsys):
    files, labels = captures
    doc = _run(tmp_path, capsys, files, "--set", f"params.rom={files['rom']}")
    tasks = doc["tasks"]
    count = Counter(t["node"] for t in tasks)
    assert count == {"ingest": 2, "clean": 2, "rom_ingest": 1, "rom_clean": 1, "segment": 1,
                     "template": 1, "fit": 1, "match": 2, "deform": 2}
    assert all(t["status"] == "computed" for t in tasks)
    (seg,) = [t for t in tasks if t["node"] == "segment"]
    assert seg["part"] is None
    # the same command again is all hits (the ROM read once is keyed by its content)
    assert main(["plan", str(SKIN), "--store", str(tmp_path / "store"), "--parts",
                 str(files["run"]), "--parts", str(files["walk"]), "--target", "deform",
                 "--set", "template.n_vertices=1500", "--set", f"params.rom={files['rom']}",
                 "--json"]) == 0
    plan = json.loads(capsys.readouterr().out)
    assert [t["status"] for t in plan["tasks"]] == ["hit"] * len(tasks)
    # the ROM lacks M006-M008: each trial warns about them by name and deforms without them
    run_part, walk_part = str(files["run"]), str(files["walk"])
    match = {t["part"]: t for t in tasks if t["node"] == "match"}
    for part in (run_part, walk_part):
        warned = " ".join(match[part]["warnings"])
        assert "left out" in warned and all(lb in warned for lb in labels[5:8]), warned
    # the walk trial lacks M021-M022 of the segmentation: missing in every frame
    walk_warn = " ".join(match[walk_part]["warnings"])
    assert "lacks 2 markers" in walk_warn and labels[20] in walk_warn and labels[21] in walk_warn
    assert not any("lacks" in w for w in match[run_part]["warnings"])
    deform = {t["part"]: t for t in tasks if t["node"] == "deform"}
    assert set(deform) == {run_part, walk_part}
    # the missing markers leave no hole in the mesh: every vertex of every frame is finite
    mesh = decode(Store(tmp_path / "store").load("deform", deform[walk_part]["key"], "mesh"))
    assert mesh.vertices.ndim == 3 and mesh.vertices.shape[0] == SMALL["n_frames"]
    assert np.isfinite(mesh.vertices).all()


def test_without_rom_each_trial_segments_itself(captures, tmp_path, capsys):
    files, labels = captures
    doc = _run(tmp_path, capsys, files)
    tasks = doc["tasks"]
    count = Counter(t["node"] for t in tasks)
    assert count["segment"] == 2 and count["fit"] == 2 and count["rom_ingest"] == 2
    # rom_clean of a part is clean of the same part (same key: one cache entry)
    keys = {(t["node"], t["part"]): t["key"] for t in tasks}
    for p in (str(files["run"]), str(files["walk"])):
        assert keys[("rom_clean", p)] == keys[("clean", p)]
        assert [t for t in tasks if t["node"] == "deform" and t["part"] == p][0]["status"] \
            == "computed"
    # nothing absent when a trial is segmented from itself
    for t in tasks:
        if t["node"] == "match":
            assert not any("lacks" in w for w in t["warnings"])


def test_ingest_rom_reports_its_source(captures):
    files, _ = captures
    own = ingest_rom(str(files["run"]), ctx=Context())
    assert own["report"]["segmented_from"] == "trial"
    assert "segmented from itself" in own["report"]["note"]
    rom = ingest_rom(str(files["run"]), rom=str(files["rom"]), ctx=Context())
    assert rom["report"]["segmented_from"] == "rom"
    assert rom["markers"].n_markers == read_c3d(files["rom"]).n_markers == SMALL["n_markers"] - 3
    # the up axis set by hand reaches the ROM trial too (it had no up param: a two-subject
    # take whose up was guessed wrong could be fixed for the trial only)
    auto = ingest_rom(str(files["run"]), rom=str(files["rom"]), ctx=Context())["report"]
    flipped = "+x" if auto["up"][1] != "x" else "+y"
    forced = ingest_rom(str(files["run"]), rom=str(files["rom"]), up=flipped, ctx=Context())
    assert forced["report"]["up"] == flipped and forced["markers"].attrs["up"] == flipped
