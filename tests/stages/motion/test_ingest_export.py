"""Ingest stages (direct calls, exact codec round trip) and exporters."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.codecs import decode, digest_encoded, encode, find_exporter
from mocapflow.pipeline.registry import get_stage, validate_params
from mocapflow.stages.motion.datatypes import Markers, Motion, Strokes, StrokesSet
from mocapflow.stages.motion.formats.c3d import read_c3d
from mocapflow.stages.motion.formats.strokes import StrokesFileError, read_strokes_csv
from mocapflow.stages.motion.ingest import (
    MAX_UPSAMPLE,
    IngestError,
    amc_skeleton_path,
    ingest_amc,
    ingest_bvh,
    ingest_c3d,
    ingest_strokes,
    ingest_strokes_set,
)

ROOT = Path(__file__).resolve().parents[3] / ".." / "shared" / "data"


@pytest.fixture(scope="module")
def ingest_data() -> Path:
    if not ROOT.is_dir():
        pytest.skip("shared data not available")
    return ROOT


def ctx() -> Context:
    return Context(part="test")


def _round_trip(value):
    enc = encode(value)
    back = decode(enc)
    assert digest_encoded(encode(back)) == digest_encoded(enc)
    return back


def _same_markers(a: Markers, b: Markers) -> None:
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.fragments, b.fragments)
    np.testing.assert_array_equal(a.residuals, b.residuals)
    assert (a.labels, a.fragment_labels, a.rate, a.first_frame) == (
        b.labels, b.fragment_labels, b.rate, b.first_frame,
    )  # fmt: skip
    assert a.attrs == b.attrs


def _same_motion(a: Motion, b: Motion) -> None:
    np.testing.assert_array_equal(a.rotations, b.rotations)
    np.testing.assert_array_equal(a.root_position, b.root_position)
    np.testing.assert_array_equal(a.skeleton.offsets, b.skeleton.offsets)
    assert a.skeleton.names == b.skeleton.names and a.skeleton.channels == b.skeleton.channels
    assert a.rate == b.rate and a.attrs == b.attrs


C3D_FILES = [
    "btkdata_PiG_Calibration-FlatFoot-Hole.c3d",
    "btkdata_c3dorg_Eb015pr.c3d",
    "ezc3d-testFiles_Qualisys.c3d",
    "ktk_kinematics_basket_sprint.c3d",
    "ktk_kinematics_racing_full.c3d",
    "pyomeca_markers_analogs.c3d",
]


@pytest.mark.parametrize("name", C3D_FILES)
def test_ingest_c3d_round_trip(ingest_data, name):
    c = ctx()
    out = ingest_c3d(str(ingest_data / "c3d" / name), ctx=c)
    assert set(out) == set(get_stage("ingest_c3d").outputs) == {"markers", "report"}
    _same_markers(out["markers"], _round_trip(out["markers"]))
    assert _round_trip(out["report"]) == out["report"]
    rep = out["report"]
    if name.startswith("ktk_kinematics_racing"):
        assert rep["never_seen"] == [f"Probe{i}" for i in range(1, 7)]
        assert any("never seen" in w for w in c.warnings)
    elif name.startswith("btkdata_PiG"):
        assert (rep["markers"], rep["fragments"], rep["points_in_file"]) == (35, 66, 203)
        assert rep["excluded"] == {"virtual_segment": 76, "model_output": 26}
        assert len(rep["fragment_lengths"]) == 66
    else:
        assert rep["fragments"] == 0 and rep["excluded"] == {}
        assert not [w for w in c.warnings if "up axis" not in w]  # see test_axes.py


def test_markers_exporter(ingest_data, tmp_path):
    m = ingest_c3d(str(ingest_data / "c3d" / "ktk_kinematics_racing_full.c3d"), ctx=ctx())[
        "markers"
    ]
    paths = find_exporter("markers")(m, tmp_path, "racing")
    assert paths == [tmp_path / "racing.c3d", tmp_path / "racing.trc"]
    back = read_c3d(paths[0])
    assert back.attrs["source_unit"] == "m"  # the source unit is kept
    assert back.labels == m.labels and back.n_frames == 700
    np.testing.assert_allclose(back.positions, m.positions, atol=1e-6, rtol=0)
    np.testing.assert_array_equal(back.visible, m.visible)


def test_ingest_strokes_selection(ingest_data):
    csv = str(ingest_data / "strokes" / "uci_chartraj_mv_subset.csv")
    s = ingest_strokes(csv, letter="a", example=3, ctx=ctx())["strokes"]
    assert isinstance(s, Strokes) and len(s.points) == 138
    assert s.attrs["letter"] == "a" and s.attrs["example"] == 3
    back = _round_trip(s)
    np.testing.assert_array_equal(back.points, s.points)
    np.testing.assert_array_equal(back.times, s.times)
    assert back.attrs == s.attrs and back.rate == 200.0
    with pytest.raises(StrokesFileError, match=r"5 examples match letter 'a'.*ingest_strokes_set"):
        ingest_strokes(csv, letter="a", ctx=ctx())
    with pytest.raises(StrokesFileError, match=r"no example 9 of letter 'a' \(examples: \[1, 2"):
        ingest_strokes(csv, letter="a", example=9, ctx=ctx())
    omni = ingest_data / "strokes" / "omniglot_latin" / "character05" / "0687_03.txt"
    o = ingest_strokes(str(omni), ctx=ctx())["strokes"]
    assert o.attrs["letter"] == "e" and len(o.stroke_starts) >= 1


def test_ingest_strokes_set_and_exporters(ingest_data, tmp_path):
    csv = str(ingest_data / "strokes" / "uci_chartraj_mv_subset.csv")
    ex = ingest_strokes_set(csv, letter="a", ctx=ctx())["examples"]
    assert isinstance(ex, StrokesSet) and [len(s.points) for s in ex] == [138, 143, 138, 136, 139]
    back = _round_trip(ex)
    assert all(np.array_equal(a.points, b.points) and a.attrs == b.attrs for a, b in zip(ex, back))
    (p,) = find_exporter("strokes_set")(ex, tmp_path, "a")
    again = read_strokes_csv(p)
    assert [s.attrs for s in again] == [s.attrs for s in ex]
    assert all(np.array_equal(a.points, b.points) for a, b in zip(ex, again))
    (q,) = find_exporter("strokes")(ex[0], tmp_path, "a1")
    assert q.suffix == ".csv" and np.array_equal(read_strokes_csv(q)[0].points, ex[0].points)
    # the exported CSV is itself an ingestable part
    s = ingest_strokes(str(p), example=2, ctx=ctx())["strokes"]
    np.testing.assert_array_equal(s.points, ex[1].points)


def test_param_validation():
    spec = get_stage("ingest_amc")
    assert validate_params(spec, {}) == {"asf": None, "rate": None}
    assert validate_params(get_stage("ingest_bvh"), {"rate": 30}) == {
        "rate": 30.0, "unit": "auto", "up": "auto", "forward": "auto"}
    assert get_stage("ingest_strokes_set").outputs == ("examples",)


def test_amc_skeleton_path():
    assert amc_skeleton_path("/d/cmu_01_01.amc") == Path("/d/cmu_01.asf")
    assert amc_skeleton_path("01_01.amc") == Path("01.asf")
    assert amc_skeleton_path("walk.amc") == Path("walk.asf")


def test_ingest_bvh(ingest_data, tmp_path):
    pytest.importorskip("mocapflow.stages.motion.formats.bvh")
    path = str(ingest_data / "bvh" / "cmu_131_01.bvh")
    m = ingest_bvh(path, ctx=ctx())["motion"]
    assert m.n_frames == 994 and m.rate == pytest.approx(120.0)
    _same_motion(m, _round_trip(m))
    half = ingest_bvh(path, rate=60.0, ctx=ctx())["motion"]
    assert half.rate == 60.0 and half.n_frames == 497  # floor(993 / 2) + 1
    np.testing.assert_allclose(half.root_position, m.root_position[::2], atol=1e-12)
    (out,) = find_exporter("motion")(m, tmp_path, "walk")
    again = ingest_bvh(str(out), ctx=ctx())["motion"]
    assert again.n_frames == 994 and again.skeleton.names == m.skeleton.names
    np.testing.assert_allclose(again.root_position, m.root_position, atol=1e-5)


def test_resample_targets_are_capped_before_allocating(tmp_path):
    """``Frame Time: 1e6`` then ``rate: 120`` asked for 120 million frames (a MemoryError)."""
    head = "HIERARCHY\nROOT A\n{\nOFFSET 0 0 0\nCHANNELS 3 Zrotation Xrotation Yrotation\n}\n"
    p = tmp_path / "slow.bvh"
    p.write_text(head + "MOTION\nFrames: 2\nFrame Time: 1e6\n0 0 0\n0 0 0\n")
    with pytest.raises(IngestError, match=rf"{p}: rate: resampling 2 frames at 1e-06 Hz .* to "
                                          r"120 Hz would make 120000001 frames of 1 joints"):
        ingest_bvh(str(p), rate=120.0, ctx=ctx())
    p.write_text(head + "MOTION\nFrames: 3\nFrame Time: 0.01\n0 0 0\n0 0 0\n0 0 0\n")
    with pytest.raises(IngestError, match=r"rate: resampling 3 frames at 100 Hz"):
        ingest_bvh(str(p), rate=1e12, ctx=ctx())
    with pytest.raises(ValueError, match=r"rate.* finite"):  # the params check, or ours
        ingest_bvh(str(p), rate=float("inf"), ctx=ctx())
    m = ingest_bvh(str(p), rate=100.0 * MAX_UPSAMPLE, ctx=ctx())["motion"]  # the limit: 16x
    assert m.n_frames == 2 * MAX_UPSAMPLE + 1 <= MAX_UPSAMPLE * 3


def test_ingest_amc(ingest_data, tmp_path):
    pytest.importorskip("mocapflow.stages.motion.formats.asf")
    amc = ingest_data / "bvh" / "cmu_11_01.amc"
    m = ingest_amc(str(amc), ctx=ctx())["motion"]  # cmu_11.asf found beside it
    assert m.n_frames == 597 and m.rate == 120.0
    _same_motion(m, _round_trip(m))
    explicit = ingest_amc(str(amc), asf=str(ingest_data / "bvh" / "cmu_11.asf"), ctx=ctx())
    np.testing.assert_array_equal(explicit["motion"].rotations, m.rotations)
    lonely = tmp_path / "cmu_99_01.amc"
    lonely.write_bytes(amc.read_bytes())
    with pytest.raises(FileNotFoundError, match=r"cmu_99\.asf"):
        ingest_amc(str(lonely), ctx=ctx())


def test_default_asf_beside_the_amc_is_part_of_the_cache_key(tmp_path):
    """The sidecar ASF is resolved into the task's params, so editing it recomputes."""
    data = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "bvh"
    if not (data / "cmu_11.asf").is_file():
        pytest.skip("shared data not available")
    for name in ("cmu_11.asf", "cmu_11_01.amc"):
        shutil.copy(data / name, tmp_path / name)
    config = tmp_path / "amc.yaml"
    config.write_text(
        f"graph: amc\nparts: [{tmp_path / 'cmu_11_01.amc'}]\n"
        "nodes:\n  ingest:\n    stage: ingest_amc\n    inputs: {path: part}\n"
    )
    cmd = [sys.executable, "-m", "mocapflow", "run", str(config), "--store",
           str(tmp_path / "store"), "--executor", "sync", "-q", "--json"]

    def statuses():
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
        return [t["status"] for t in json.loads(out)["tasks"]]

    assert statuses() == ["computed"]
    assert statuses() == ["hit"]
    with open(tmp_path / "cmu_11.asf", "a") as f:
        f.write("# an edit to the skeleton file\n")
    assert statuses() == ["computed"]


# --------------------------------------------------------------------------- BVH axes, static root


def _walk(F: int = 40) -> Motion:
    """A Y-up walk facing +Z: hips at 0.9 m travelling 1 m along +z, legs swinging."""
    from mocapflow.stages.motion.datatypes import Skeleton
    from mocapflow.stages.motion.rotations import quat_from_axis_angle

    names = ["Hips", "Spine", "Head", "LeftUpLeg", "LeftFoot", "RightUpLeg", "RightFoot"]
    offsets = [[0, 0, 0], [0, 0.3, 0], [0, 0.4, 0], [0.1, 0, 0], [0, -0.85, 0],
               [-0.1, 0, 0], [0, -0.85, 0]]
    rot3, root6 = ["Zrotation", "Xrotation", "Yrotation"], ["Xposition", "Yposition", "Zposition"]
    sk = Skeleton(names=names, parents=[-1, 0, 1, 0, 3, 0, 5], offsets=offsets,
                  channels=[root6 + rot3] + [rot3] * 6, end_parents=[2, 4, 6],
                  end_offsets=[[0, 0.15, 0], [0, -0.05, 0.12], [0, -0.05, 0.12]])
    t = np.arange(F) / 30.0
    swing = 0.4 * np.sin(2 * np.pi * t)
    rot = np.zeros((F, 7, 4))
    rot[..., 0] = 1.0
    rot[:, 3] = quat_from_axis_angle(np.array([1.0, 0, 0]), swing)
    rot[:, 5] = quat_from_axis_angle(np.array([1.0, 0, 0]), -swing)
    root = np.stack([0 * t, 0.9 + 0.02 * np.cos(4 * np.pi * t), t * 30 / F], axis=1)
    return Motion(skeleton=sk, root_position=root, rotations=rot, rate=30.0,
                  attrs={"source_scale": 0.01})


def _to_z_up(m: Motion, *, offsets_too: bool) -> Motion:
    """The same take exported Z-up (+90 deg about X: y -> z, z -> -y); either every offset
    and rotation turned (Blender), or only the root (a converted take, Y-up rest pose)."""
    from dataclasses import replace

    from mocapflow.stages.motion.rotations import quat_from_axis_angle, quat_inverse, quat_multiply

    q = quat_from_axis_angle(np.array([1.0, 0, 0]), np.pi / 2)
    Q = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    rot = m.rotations.copy()
    rot[:, 0] = quat_multiply(q, rot[:, 0])
    sk = m.skeleton
    if offsets_too:
        rot[:, 0] = quat_multiply(rot[:, 0], quat_inverse(q))
        rot[:, 1:] = quat_multiply(quat_multiply(q, rot[:, 1:]), quat_inverse(q))
        sk = replace(sk, offsets=sk.offsets @ Q.T, end_offsets=sk.end_offsets @ Q.T)
    return m.replace(skeleton=sk, rotations=rot, root_position=m.root_position @ Q.T)


@pytest.mark.parametrize("layout", ["y_up", "z_up_blender", "z_up_root_turned"])
def test_ingest_bvh_up_auto_detects_y_and_z_up(tmp_path, layout):
    from mocapflow.stages.motion.formats.bvh import write_bvh
    from mocapflow.stages.motion.kinematics import motion_positions

    walk = _walk()
    m = walk if layout == "y_up" else _to_z_up(walk, offsets_too=layout == "z_up_blender")
    Q = np.eye(3) if layout == "y_up" else np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    np.testing.assert_allclose(motion_positions(m), motion_positions(walk) @ Q.T, atol=1e-12)
    c = ctx()
    got = ingest_bvh(str(write_bvh(m, tmp_path / f"{layout}.bvh")), ctx=c)["motion"]
    want = ("+y", "+z") if layout == "y_up" else ("+z", "-y")
    assert (got.attrs["up"], got.attrs["forward"]) == want
    assert got.attrs["axes_source"]["up_confidence"] == "high" and not c.warnings
    given = ingest_bvh(str(tmp_path / f"{layout}.bvh"), up=want[0], ctx=ctx())["motion"]
    assert given.attrs["forward"] == want[1]  # forward detected for a given up
    assert given.attrs["axes_source"]["up"] == "param"


def test_ingest_bvh_up_auto_keeps_y_and_warns_once_on_weak_evidence(tmp_path):
    p = tmp_path / "stick.bvh"  # two joints, no names that say head or feet, no floor
    p.write_text("HIERARCHY\nROOT A\n{\nOFFSET 0 0 0\nCHANNELS 6 Xposition Yposition Zposition "
                 "Zrotation Xrotation Yrotation\nJOINT B\n{\nOFFSET 0 0 100\nCHANNELS 3 Zrotation "
                 "Xrotation Yrotation\nEnd Site\n{\nOFFSET 0 0 70\n}\n}\n}\nMOTION\nFrames: 2\n"
                 "Frame Time: 0.1\n0 500 300 0 0 0 0 0 0\n1 500 300 0 0 0 0 0 0\n")
    c = ctx()
    m = ingest_bvh(str(p), unit="cm", ctx=c)["motion"]  # (auto: a 2-joint unit warning too)
    assert (m.attrs["up"], m.attrs["forward"]) == ("+y", "+z")
    assert m.attrs["axes_source"]["up_confidence"] == "low"
    assert len(c.warnings) == 1 and "up axis +y (BVH's convention) kept" in c.warnings[0]


STATIC_ROOT = """HIERARCHY
ROOT joint_Root
{
  OFFSET 1 2 3
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Hips
  {
    OFFSET 0 90 0
    CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
    JOINT Spine
    {
      OFFSET 0 10 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 50 0
      }
    }
    JOINT LeftFoot
    {
      OFFSET 10 -80 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 0 10
      }
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.0333333
5 0 7 0 0 0 0 90 0 10 20 30 5 0 0 -20 0 0
5 0 7 0 0 0 0 91 40 15 25 35 6 0 0 -10 0 0
5 0 7 0 0 0 3 92 80 20 30 40 7 0 0 0 0 0
"""


def test_ingest_bvh_drops_a_static_root_whose_child_travels(tmp_path):
    from mocapflow.stages.motion.formats.bvh import read_bvh, write_bvh
    from mocapflow.stages.motion.kinematics import end_site_positions, forward_kinematics

    def world(m):
        pos, grot = forward_kinematics(m.skeleton, m.rotations, m.root_position,
                                       translations=m.translations)
        return pos, end_site_positions(m.skeleton, pos, grot)

    p = tmp_path / "bandai_layout.bvh"
    p.write_text(STATIC_ROOT)
    c = ctx()
    m = ingest_bvh(str(p), up="+y", unit="cm", ctx=c)["motion"]
    assert m.skeleton.names == ["Hips", "Spine", "LeftFoot"]
    assert list(m.skeleton.parents) == [-1, 0, 0] and m.attrs["dropped_root"] == "joint_Root"
    assert c.warnings == ["bandai_layout.bvh: root joint 'joint_Root' never moves and its child "
                          "'Hips' carries the travel: 'Hips' is the root, 'joint_Root' is dropped"]
    # the hips' world position is the static root's position plus its channels (cm -> m)
    np.testing.assert_allclose(m.root_position * 100, [[5, 90, 7], [5, 91, 47], [8, 92, 87]],
                               atol=1e-12)
    ref = read_bvh(p, unit="cm")
    (pos, ends), (ref_pos, ref_ends) = world(m), world(ref)
    np.testing.assert_allclose(pos, ref_pos[:, 1:], atol=1e-9)  # every other joint unchanged
    np.testing.assert_allclose(ends, ref_ends, atol=1e-9)
    back_path = write_bvh(m, tmp_path / "back.bvh")
    back = ingest_bvh(str(back_path), up="+y", ctx=ctx())["motion"]
    assert back.skeleton.names == m.skeleton.names
    np.testing.assert_allclose(world(back)[0], pos, atol=1e-8)
    # the file written keeps the source's hierarchy: the static root put back around Hips,
    # with its offset, channels and values, the Hips' offset and channels as read
    raw = read_bvh(back_path, unit="cm")
    assert raw.skeleton.names == ref.skeleton.names
    assert raw.skeleton.channels == ref.skeleton.channels
    np.testing.assert_allclose(raw.skeleton.offsets, ref.skeleton.offsets, atol=1e-8)
    np.testing.assert_allclose(raw.root_position, ref.root_position, atol=1e-8)
    np.testing.assert_allclose(raw.translations, ref.translations, atol=1e-8)
    np.testing.assert_allclose(world(raw)[0], ref_pos, atol=1e-8)
    # a new motion made on the skeleton alone (the variation graph's variants) keeps it too
    bare = m.replace(attrs={})
    assert "dropped_root_joint" in bare.skeleton.attrs
    again = read_bvh(write_bvh(bare, tmp_path / "bare.bvh"), unit="cm")
    assert again.skeleton.names == ref.skeleton.names
    # a root that moves (or turns) is kept
    p.write_text(STATIC_ROOT.replace("\n5 0 7 0 0 0 3 92", "\n5 0 8 0 0 0 3 92"))
    kept = ingest_bvh(str(p), up="+y", unit="cm", ctx=(c := ctx()))["motion"]
    assert kept.skeleton.names[0] == "joint_Root" and not c.warnings


def test_ingest_bvh_warns_when_few_joints_decide_the_unit(tmp_path):
    """unit auto assumes a 1.7 m body: a skeleton of a few joints (a camera track, a test
    rig) says little about size, so the guess is said, with the way to set it."""
    p = tmp_path / "rig.bvh"
    p.write_text("HIERARCHY\nROOT Cam\n{\n  OFFSET 0 0 0\n  CHANNELS 6 Xposition Yposition "
                 "Zposition Zrotation Xrotation Yrotation\n  End Site\n  {\n    OFFSET 0 0 1\n"
                 "  }\n}\nMOTION\nFrames: 2\nFrame Time: 0.04\n0 150 300 0 0 0\n"
                 "1 150 300 0 0 0\n")
    ctx = Context()
    ingest_bvh(str(p), ctx=ctx)
    assert [w for w in ctx.warnings if "unit" in w and "1 joint(s)" in w and "ingest.unit" in w]
    quiet = Context()
    ingest_bvh(str(p), unit="cm", ctx=quiet)
    assert not [w for w in quiet.warnings if "ingest.unit" in w]

