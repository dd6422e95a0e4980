"""BVH read/write: real files round trip, agreement with bvhio, layouts, units, errors."""

import numpy as np
import pytest

from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.motion.formats.bvh import BVH_UNITS, BVHError, guess_unit, read_bvh, write_bvh
from mocapflow.stages.motion.kinematics import end_site_positions, forward_kinematics
from mocapflow.stages.motion.rotations import euler_to_quat, quat_from_axis_angle

# file -> (joints, frames, unit guessed) ; joints/frames as in PROVENANCE.md
BVH_FILES = {
    "cmu_131_01.bvh": (31, 994, "cmu"),
    "cmu_131_02.bvh": (31, 1247, "cmu"),
    "cmu_60_01_scaled.bvh": (43, 2242, "m"),
    "pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh": (23, 1064, "in"),
    "cmu_01_01.bvh": (31, 2752, "cmu"),
}


def _world(m: Motion) -> np.ndarray:
    """Joint and End Site world positions ``(F, J + E, 3)``."""
    pos, grot = forward_kinematics(
        m.skeleton, m.rotations, m.root_position, translations=m.translations
    )
    return np.concatenate([pos, end_site_positions(m.skeleton, pos, grot)], axis=1)


def _height(w: np.ndarray) -> float:
    return float(np.ptp(w[0], axis=0).max())


@pytest.fixture(scope="module")
def motions(shared_data):
    return {name: read_bvh(shared_data / "bvh" / name) for name in BVH_FILES}


@pytest.mark.parametrize("name", list(BVH_FILES))
def test_real_file_reads_with_provenance_counts(motions, name):
    m = motions[name]
    joints, frames, unit = BVH_FILES[name]
    assert m.skeleton.n_joints == joints and m.n_frames == frames
    assert m.rate == 120.0  # .0083333 / 0.008333 snap to 120 Hz
    assert m.attrs["source_unit"] == unit
    assert np.allclose(np.linalg.norm(m.rotations, axis=-1), 1.0, atol=1e-12)
    h = _height(_world(m))
    assert 1.0 < h < 2.0, h  # metres after unit handling


@pytest.mark.parametrize("name", list(BVH_FILES))
def test_round_trip_reproduces_world_positions_and_frame_time(motions, name, tmp_path, shared_data):
    m = motions[name]
    out = write_bvh(m, tmp_path / name)
    m2 = read_bvh(out)
    assert m2.skeleton.names == m.skeleton.names
    assert m2.skeleton.channels == m.skeleton.channels
    assert m2.attrs["frame_time_text"] == m.attrs["frame_time_text"]
    assert m2.attrs["source_unit"] == m.attrs["source_unit"]
    np.testing.assert_allclose(m2.skeleton.offsets, m.skeleton.offsets, atol=1e-9)
    w1, w2 = _world(m), _world(m2)
    err = np.abs(w1 - w2).max() / _height(w1)
    assert err < 1e-6, err
    # the Frame Time line is byte-identical to the source file's
    src = (shared_data / "bvh" / name).read_text().splitlines()
    dst = out.read_text().splitlines()
    line = next(ln for ln in src if ln.strip().startswith("Frame Time"))
    assert line.split()[-1] in [ln.split()[-1] for ln in dst if ln.startswith("Frame Time")]


@pytest.mark.parametrize("name", list(BVH_FILES))
def test_forward_kinematics_agrees_with_bvhio(motions, name, shared_data, tmp_path):
    bvhio = pytest.importorskip("bvhio")
    path = shared_data / "bvh" / name
    m = read_bvh(path, unit=1.0)  # file units, like bvhio; our reader reads every frame
    # bvhio is slow (pure Python per joint and frame): give it 25 of the frames
    lines = path.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.strip().startswith("Frame Time"))
    frames = np.linspace(0, m.n_frames - 1, 25).astype(int)
    subset = lines[: k - 1] + ["Frames: 25", lines[k]] + [lines[k + 1 + f] for f in frames]
    (tmp_path / name).write_text("\n".join(subset) + "\n")
    root = bvhio.readAsHierarchy(str(tmp_path / name))
    layout = [j for j, _, _ in root.layout()]
    assert [j.Name for j in layout] == m.skeleton.names
    pos, _ = forward_kinematics(
        m.skeleton, m.rotations, m.root_position, translations=m.translations
    )
    ref = np.empty((len(frames), m.skeleton.n_joints, 3))
    for k in range(len(frames)):
        root.loadPose(k)
        ref[k] = [list(j.PositionWorld) for j in layout]
    err = np.abs(ref - pos[frames]).max() / _height(pos)
    assert err < 1e-5, err  # bvhio computes in float32


# --------------------------------------------------------------------------- layouts

SYNTHETIC = (
    "HIERARCHY\r\n"
    "ROOT Root\r\n{\r\n"
    "\tOFFSET 1.0 2.0 3.0\r\n"
    "\tCHANNELS 6 Zrotation Xrotation Yrotation Xposition Yposition Zposition\r\n"
    "\tJOINT Slider\r\n\t{\r\n"
    "\t\tOFFSET 0 10 0\r\n"
    "\t\tCHANNELS 4 Yposition Xrotation Zrotation Yrotation\r\n"
    "\t\tJOINT Hinge\r\n\t\t{\r\n"
    "\t\t\tOFFSET 10 0 0\r\n"
    "\t\t\tCHANNELS 1 Zrotation\r\n"
    "\t\t\tEnd Site\r\n\t\t\t{\r\n\t\t\t\tOFFSET 5 0 0\r\n\t\t\t}\r\n"
    "\t\t}\r\n"
    "\t}\r\n"
    "\tJOINT Fixed\r\n\t{\r\n"
    "\t\tOFFSET -10 0 0\r\n"
    "\t\tCHANNELS 0\r\n"
    "\t\tEnd Site\r\n\t\t{\r\n\t\t\tOFFSET 0 -4e1 0\r\n\t\t}\r\n"
    "\t}\r\n"
    "}\r\n"
    "MOTION\r\n"
    "Frames: 2\r\n"
    "Frame Time: 0.04\r\n"
    "0 0 0 1 2 3 10 0 0 0 0\r\n"
    "90 0 0 1e2 0 0 2.5E1 0 0 0 90\r\n"
)


def test_synthetic_layout_values(tmp_path):
    p = tmp_path / "synthetic.bvh"
    p.write_bytes(SYNTHETIC.encode())
    m = read_bvh(p, unit="cm")
    sk = m.skeleton
    assert sk.names == ["Root", "Slider", "Hinge", "Fixed"]
    assert [sk.rotation_order(j) for j in range(4)] == ["ZXY", "XZY", "Z", ""]
    assert m.rate == 25.0 and m.attrs["frame_time_text"] == "0.04"
    np.testing.assert_allclose(m.root_position, [[0.01, 0.02, 0.03], [1.0, 0, 0]])
    assert m.translations is not None  # Slider has a position channel
    np.testing.assert_allclose(m.translations[:, 1], [[0, 0.10, 0], [0, 0.25, 0]])
    w = _world(m) * 100  # back to cm
    # frame 0: all rotations zero
    np.testing.assert_allclose(
        w[0],
        [[1, 2, 3], [1, 12, 3], [11, 12, 3], [-9, 2, 3], [16, 12, 3], [-9, -38, 3]],
        atol=1e-12,
    )
    # frame 1: root 90 deg about Z; Hinge 90 deg about Z
    rz = quat_from_axis_angle(np.array([0, 0, 1.0]), np.pi / 2)
    np.testing.assert_allclose(m.rotations[1, 0], rz, atol=1e-15)
    np.testing.assert_allclose(
        w[1],
        [[100, 0, 0], [75, 0, 0], [75, 10, 0], [100, -10, 0], [70, 10, 0], [140, -10, 0]],
        atol=1e-12,
    )
    # write back: same text layout, same values
    out = write_bvh(m, tmp_path / "out.bvh")
    m2 = read_bvh(out, unit="cm")
    assert m2.skeleton.channels == sk.channels
    np.testing.assert_allclose(_world(m2), _world(m), atol=1e-9)
    assert "OFFSET 1.000000 2.000000 3.000000" in out.read_text()  # original unit


def test_units(tmp_path):
    p = tmp_path / "synthetic.bvh"
    p.write_text(SYNTHETIC)
    assert read_bvh(p, unit=0.5).skeleton.offsets[1, 1] == 5.0
    assert read_bvh(p, unit="in").skeleton.offsets[1, 1] == pytest.approx(0.254)
    with pytest.raises(BVHError, match="unknown unit 'parsec'"):
        read_bvh(p, unit="parsec")
    # the auto rule: nearest to a 1.7 m body on a log scale
    assert guess_unit(1.75) == "m" and guess_unit(175) == "cm" and guess_unit(1750) == "mm"
    assert guess_unit(68) == "in" and guess_unit(32) == "cmu" and guess_unit(17) == "dm"
    assert BVH_UNITS["cmu"] == pytest.approx(0.056444, rel=1e-5)
    # writing in another unit scales lengths
    m = read_bvh(p, unit="cm")
    out = write_bvh(m, tmp_path / "mm.bvh", unit="mm")
    assert "OFFSET 10.000000 20.000000 30.000000" in out.read_text()
    np.testing.assert_allclose(_world(read_bvh(out, unit="mm")), _world(m), atol=1e-12)


def test_changed_rate_writes_new_frame_time(tmp_path):
    p = tmp_path / "synthetic.bvh"
    p.write_text(SYNTHETIC)
    m = read_bvh(p).replace(rate=50.0)
    text = write_bvh(m, tmp_path / "r.bvh").read_text()
    assert "Frame Time: 0.02\n" in text


def test_writer_refuses_rotation_its_channels_cannot_hold(tmp_path):
    p = tmp_path / "synthetic.bvh"
    p.write_text(SYNTHETIC)
    m = read_bvh(p)
    rot = m.rotations.copy()
    rot[:, 2] = euler_to_quat(np.array([0.3, 0.2, 0.0]), "ZXY")  # Hinge has only Zrotation
    with pytest.raises(BVHError, match="joint 'Hinge' needs axes"):
        write_bvh(m.replace(rotations=rot), tmp_path / "bad.bvh")
    rot = m.rotations.copy()
    rot[:, 3] = euler_to_quat(np.array([0.0, 0.0, 0.1]), "ZXY")  # Fixed has no channels
    with pytest.raises(BVHError, match="joint 'Fixed' rotates"):
        write_bvh(m.replace(rotations=rot), tmp_path / "bad.bvh")
    tr = m.translations.copy()
    tr[:, 1, 0] += 0.5  # Slider has only a Yposition channel
    with pytest.raises(BVHError, match="joint 'Slider' moves along X"):
        write_bvh(m.replace(translations=tr), tmp_path / "bad.bvh")


# --------------------------------------------------------------------------- errors


def _lines():
    return SYNTHETIC.replace("\r\n", "\n").splitlines()


def _write(tmp_path, name, lines):
    p = tmp_path / name
    p.write_text("\n".join(lines) + ("\n" if lines else ""))
    return p


def test_malformed_files_name_file_and_line(tmp_path):
    lines = _lines()
    cases = {
        "empty.bvh": ([], r"empty\.bvh:1: empty file"),
        "truncated_hierarchy.bvh": (
            lines[:12],
            r"truncated_hierarchy\.bvh:12: truncated hierarchy",
        ),
        "no_motion.bvh": (lines[:29], r"no_motion\.bvh:29: truncated file: no MOTION"),
        "wrong_count.bvh": (
            lines[:-1] + ["90 0 0 1 0 0 25 0 0 90"],
            r"wrong_count\.bvh:34: frame 1 has 10 values, expected 11",
        ),
        "truncated_motion.bvh": (
            lines[:-1],
            r"truncated_motion\.bvh:33: truncated motion: "
            r"'Frames: 2' but only 1 lines after the header",
        ),
        "bad_number.bvh": (
            lines[:-1] + ["90 0 0 1 0 0 25 0 zero 0 90"],
            r"bad_number\.bvh:34: bad number 'zero' in frame 1",
        ),
        "bad_offset.bvh": (
            [ln.replace("OFFSET 0 10 0", "OFFSET 0 1x 0") for ln in lines],
            r"bad_offset\.bvh:8: bad number '1x'",
        ),
        "unknown_channel.bvh": (
            [ln.replace("1 Zrotation", "1 Wrotation") for ln in lines],
            r"unknown_channel\.bvh:13: unknown channel 'Wrotation'",
        ),
        "unknown_order.bvh": (
            [
                ln.replace("Xrotation Zrotation Yrotation", "Xrotation Zrotation Xrotation")
                for ln in lines
            ],
            r"unknown_order\.bvh:9: unknown rotation order 'XZX'",
        ),
        "bad_frames.bvh": (
            [ln.replace("Frames: 2", "Frames: two") for ln in lines],
            r"bad_frames\.bvh:31: Frames: bad frame count 'two'",
        ),
        "no_brace.bvh": (
            [ln for k, ln in enumerate(lines) if k != 2],
            r"no_brace\.bvh:3: joint 'Root': expected '\{', found 'OFFSET'",
        ),
    }
    for name, (content, pattern) in cases.items():
        p = _write(tmp_path, name, content)
        with pytest.raises(BVHError, match=pattern):
            read_bvh(p)
    assert issubclass(BVHError, ValueError)


# --------------------------------------------------------------------------- hostile files


def _chain(depth: int, *, frames: int = 1) -> str:
    out = ["HIERARCHY", "ROOT J0", "{", "OFFSET 0 0 0", "CHANNELS 3 Zrotation Xrotation Yrotation"]
    for i in range(1, depth):
        out += [f"JOINT J{i}", "{", "OFFSET 0 1 0", "CHANNELS 3 Zrotation Xrotation Yrotation"]
    out += ["}"] * depth + ["MOTION", f"Frames: {frames}", "Frame Time: 0.01"]
    return "\n".join(out + [" ".join(["5"] * 3 * depth)] * frames) + "\n"


NINE = (
    "HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n  CHANNELS 0\n}\nMOTION\n"
    "Frames: 2000000000\nFrame Time: 0.0083333\n"
)


def test_declared_frames_are_checked_against_the_file_before_allocating(tmp_path):
    """The issue's 9-line file asked for 45 GiB; channel-less joints cost memory without bytes."""
    p = tmp_path / "nine.bvh"
    p.write_text(NINE)
    with pytest.raises(BVHError, match=r"nine\.bvh:9: truncated motion: 'Frames: 2000000000' "
                                       r"but only 0 lines after the header"):
        read_bvh(p)
    p.write_text(NINE.replace("2000000000", "3") + "\n\n\n")  # blank lines: 3 frames, 0 values
    m = read_bvh(p)
    assert m.n_frames == 3 and np.allclose(m.rotations, [1, 0, 0, 0])
    idle = "".join(f"JOINT J{i}\n{{\nOFFSET 0 1 0\nCHANNELS 0\n}}\n" for i in range(60))
    p.write_text(NINE.replace("}\nMOTION", idle + "}\nMOTION").replace("2000000000", "40000")
                 + "\n" * 40000)
    with pytest.raises(BVHError, match=r"Frames: 40000 frames of 61 joints without CHANNELS"):
        read_bvh(p)
    p.write_text(NINE.replace("2000000000", "0"))
    with pytest.raises(BVHError, match=r"nine\.bvh:8: Frames: 0: a BVH motion needs at least"):
        read_bvh(p)


def test_deep_hierarchy_is_an_error_not_a_recursion(tmp_path):
    p = tmp_path / "deep.bvh"
    p.write_text(_chain(5000))
    with pytest.raises(BVHError, match=r"deep\.bvh:1026: JOINT inside joint 'J255': the "
                                       r"hierarchy nests deeper than 256 joints"):
        read_bvh(p)
    p.write_text(_chain(256, frames=2))  # the deepest accepted, written back (iteratively)
    m = read_bvh(p)
    assert m.n_frames == 2 and list(m.skeleton.parents) == list(range(-1, 255))
    back = read_bvh(write_bvh(m, tmp_path / "back.bvh"))
    assert back.skeleton.names == m.skeleton.names
    np.testing.assert_allclose(back.rotations, m.rotations, atol=1e-9)
    assert "\n" + "\t" * 255 + "JOINT J255\n" in (tmp_path / "back.bvh").read_text()


@pytest.mark.parametrize(("edit", "pattern"), [
    (("OFFSET 0 10 0", "OFFSET 0 inf 0"), r":8: OFFSET of joint 'Slider' is not finite"),
    (("OFFSET 0 10 0", "OFFSET nan 10 0"), r":8: OFFSET of joint 'Slider' is not finite"),
    (("OFFSET 5 0 0", "OFFSET 5 -inf 0"), r":16: OFFSET of End Site of 'Hinge' is not finite"),
    (("OFFSET 0 10 0", "OFFSET 0 1e300 0"), r":6: OFFSET values too large"),
    (("JOINT Fixed", "JOINT Hinge"), r":20: JOINT name 'Hinge' is used twice \(lines 10 and 20\)"),
    (("CHANNELS 1 Zrotation", "CHANNELS 7 Zrotation"), r":13: bad CHANNELS count 7"),
    (("CHANNELS 1 Zrotation", "CHANNELS inf Zrotation"), r":13: bad CHANNELS count inf"),
    (("Frame Time: 0.04", "Frame Time: 1e-320"), r":32: Frame Time: 1e-320 s is too small"),
    (("90 0 0 1e2 0 0", "90 0 0 1e300 0 0"), r": frame 1: a position channel is 1e\+298 m"),
])
def test_non_finite_huge_and_duplicate_fields_name_the_line(tmp_path, edit, pattern):
    p = _write(tmp_path, "bad.bvh", [ln.replace(*edit) for ln in _lines()])
    with pytest.raises(BVHError, match=r"bad\.bvh" + pattern):
        read_bvh(p, unit="cm")


def test_channel_names_any_case_and_named_end_sites_read_as_blender_does(tmp_path):
    """``ZPosition`` / ``ZRotation`` and ``End Site NAME`` (Blender reads both) read like the
    canonical file; writing gives the canonical spelling back."""
    text = SYNTHETIC
    for old, new in [("Xposition Yposition Zposition", "XPOSITION yPosition ZPosition"),
                     ("CHANNELS 1 Zrotation", "CHANNELS 1 ZRotation"),
                     ("\t\t\tEnd Site\r\n", "\t\t\tEnd Site HingeTip\r\n"),
                     ("\t\tEnd Site\r\n\t\t{", "\t\tEnd Site Foot {")]:
        assert text.count(old) == 1
        text = text.replace(old, new)
    (tmp_path / "cased.bvh").write_text(text)
    (tmp_path / "ref.bvh").write_text(SYNTHETIC)
    m = read_bvh(tmp_path / "cased.bvh", unit="cm")
    ref = read_bvh(tmp_path / "ref.bvh", unit="cm")
    assert m.skeleton.channels == ref.skeleton.channels
    assert m.skeleton.channels[0][3:] == ["Xposition", "Yposition", "Zposition"]
    np.testing.assert_array_equal(m.skeleton.end_offsets, [[0.05, 0, 0], [0, -0.4, 0]])
    np.testing.assert_array_equal(_world(m), _world(ref))
    out = write_bvh(m, tmp_path / "out.bvh").read_text()
    assert "Zposition" in out and "ZPosition" not in out and "HingeTip" not in out
    assert out.count("End Site\n") == 2
