"""ASF/AMC: CMU skeleton and 62-DOF motion, cross-check with the same take as BVH, errors."""

import json

import numpy as np
import pytest

from mocapflow.stages.motion.formats.asf import (
    AMCError,
    ASFError,
    amc_dofs,
    asf_amc_to_dofs,
    read_amc,
    read_asf,
)
from mocapflow.stages.motion.formats.bvh import read_bvh, write_bvh
from mocapflow.stages.motion.kinematics import forward_kinematics
from mocapflow.stages.motion.rotations import quat_angle

#: The CMU BVH conversion's names for the ASF bones (same depth-first order).
BVH_NAMES = [
    "Hips", "LHipJoint", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase", "RHipJoint",
    "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase", "LowerBack", "Spine", "Spine1", "Neck",
    "Neck1", "Head", "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand", "LeftFingerBase",
    "LFingers", "LThumb", "RightShoulder", "RightArm", "RightForeArm", "RightHand",
    "RightFingerBase", "RFingers", "RThumb",
]  # fmt: skip
ASF_NAMES = [
    "root", "lhipjoint", "lfemur", "ltibia", "lfoot", "ltoes", "rhipjoint", "rfemur", "rtibia",
    "rfoot", "rtoes", "lowerback", "upperback", "thorax", "lowerneck", "upperneck", "head",
    "lclavicle", "lhumerus", "lradius", "lwrist", "lhand", "lfingers", "lthumb", "rclavicle",
    "rhumerus", "rradius", "rwrist", "rhand", "rfingers", "rthumb",
]  # fmt: skip


@pytest.fixture(scope="module")
def take(shared_data):
    d = shared_data / "bvh"
    sk = read_asf(d / "cmu_01.asf")
    return sk, read_amc(d / "cmu_01_01.amc", sk), read_bvh(d / "cmu_01_01.bvh")


def test_read_asf(take):
    sk = take[0]
    assert sk.names == ASF_NAMES
    info = sk.attrs["asf"]
    assert info["units"] == {"mass": 1.0, "length": 0.45, "angle": "deg"}
    assert info["root"]["order"] == ["TX", "TY", "TZ", "RX", "RY", "RZ"]
    lf = info["bones"]["lfemur"]
    assert lf["dof"] == ["rx", "ry", "rz"] and lf["axis"] == [0.0, 0.0, 20.0]
    assert lf["limits"] == [[-160.0, 20.0], [-70.0, 70.0], [-60.0, 70.0]]
    assert info["bones"]["lclavicle"]["dof"] == ["ry", "rz"]
    assert 6 + sum(len(b["dof"]) for b in info["bones"].values()) == 62
    # ltibia's joint sits at the end of lfemur: direction * length, in metres
    scale = 0.0254 / 0.45
    np.testing.assert_allclose(
        sk.offsets[sk.index("ltibia")], np.array([0.34202, -0.939693, 0]) * 7.1578 * scale
    )
    assert len(sk.end_parents) == 7
    json.dumps(sk.attrs)  # attrs must be JSON for the store


def test_amc_dofs(shared_data, take):
    sk = take[0]
    d = shared_data / "bvh"
    X, names = amc_dofs(d / "cmu_01_01.amc", sk)
    assert X.shape == (2751, 62) and len(names) == 62
    assert names[:7] == [
        "root.tx",
        "root.ty",
        "root.tz",
        "root.rx",
        "root.ry",
        "root.rz",
        "lowerback.rx",
    ]
    np.testing.assert_array_equal(
        X[0, :6], [9.37216, 17.8693, -17.3198, -2.01677, -7.59696, -3.23164]
    )
    X11, names11 = asf_amc_to_dofs(d / "cmu_11.asf", d / "cmu_11_01.amc")
    assert X11.shape == (597, 62) and names11 == names
    np.testing.assert_array_equal(X11[0, :3], [12.2047, 17.4653, -40.3148])


def test_amc_matches_the_bvh_of_the_same_take(take):
    """cmu_01_01.amc vs cmu_01_01.bvh (BVH frame k+1 = AMC frame k, T-pose first).

    The BVH conversion dropped two bone lengths (thorax: Neck sits on Spine1;
    lwrist/rwrist: FingerBase and Thumb sit on the wrist), so positions are
    compared on the joints whose chain is identical and, for every joint, with
    the BVH's own offsets; global rotations are compared for all 31 joints.
    Measured: 0.005 mm and 0.0003 deg (the files' 4-6 printed digits).
    """
    sk, amc, bvh = take
    assert amc.n_frames + 1 == bvh.n_frames == 2752
    assert bvh.skeleton.names == BVH_NAMES
    assert amc.attrs["source_scale"] == pytest.approx(bvh.attrs["source_scale"], rel=1e-12)
    pa, ga = forward_kinematics(sk, amc.rotations, amc.root_position)
    pb, gb = forward_kinematics(bvh.skeleton, bvh.rotations[1:], bvh.root_position[1:])
    same_chain = np.arange(14)  # root, legs, LowerBack, Spine, Spine1
    np.testing.assert_allclose(sk.offsets[same_chain], bvh.skeleton.offsets[same_chain], atol=1e-5)
    err_pos = np.linalg.norm(pa[:, same_chain] - pb[:, same_chain], axis=-1).max()
    assert err_pos < 1e-4, err_pos  # metres
    err_rot = np.degrees(quat_angle(ga, gb)).max()
    assert err_rot < 0.01, err_rot  # degrees, all 31 joints
    pc, _ = forward_kinematics(bvh.skeleton, amc.rotations, amc.root_position)
    err_all = np.linalg.norm(pc - pb, axis=-1).max()
    assert err_all < 1e-4, err_all
    # and the T-pose frame is not part of the AMC take
    assert (
        np.linalg.norm(
            pa[0]
            - forward_kinematics(bvh.skeleton, bvh.rotations[:1], bvh.root_position[:1])[0][0],
            axis=-1,
        ).max()
        > 0.01
    )


def test_amc_to_bvh_round_trip(take, tmp_path):
    sk, amc, _ = take
    part = amc.replace(root_position=amc.root_position[:200], rotations=amc.rotations[:200])
    m2 = read_bvh(write_bvh(part, tmp_path / "amc.bvh"))
    assert m2.attrs["source_unit"] == "cmu"
    p1, _ = forward_kinematics(sk, part.rotations, part.root_position)
    p2, _ = forward_kinematics(m2.skeleton, m2.rotations, m2.root_position)
    assert np.abs(p1 - p2).max() < 1e-6


# --------------------------------------------------------------------------- errors


def _amc_lines(shared_data, n_frames=3):
    lines = (shared_data / "bvh" / "cmu_11_01.amc").read_text().splitlines()
    return lines[: 4 + 30 * n_frames]  # 4 header lines, then 1 + 29 lines per frame


def test_malformed_amc_names_file_and_line(shared_data, tmp_path):
    sk = read_asf(shared_data / "bvh" / "cmu_11.asf")
    good = _amc_lines(shared_data)
    assert read_amc(_write(tmp_path, "ok.amc", good), sk).n_frames == 3
    bad_count = list(good)
    bad_count[40] = "lfemur 1 2"
    bad_bone = list(good)
    bad_bone[40] = "ltail 1 2 3"
    bad_number = list(good)
    bad_number[40] = bad_number[40].split()[0] + " 1 x 3"
    cases = {
        "empty.amc": ([], r"empty\.amc:1: empty file"),
        "count.amc": (bad_count, r"count\.amc:41: bone 'lfemur' has 2 values, expected 3"),
        "bone.amc": (bad_bone, r"bone\.amc:41: unknown bone 'ltail'"),
        "number.amc": (bad_number, r"number\.amc:41: bad number 'x'"),
        "truncated.amc": (good[:-5], r"truncated\.amc:65: frame starting here lacks bones"),
        "headless.amc": (good[:3] + good[5:], r"headless\.amc:4: 'root' before the first frame"),
    }
    for name, (content, pattern) in cases.items():
        with pytest.raises(AMCError, match=pattern):
            read_amc(_write(tmp_path, name, content), sk)
    assert issubclass(AMCError, ASFError) and issubclass(ASFError, ValueError)
    with pytest.raises(AMCError, match="not read from an ASF"):
        read_amc(
            _write(tmp_path, "ok.amc", good),
            read_bvh(shared_data / "bvh" / "cmu_131_01.bvh").skeleton,
        )


def _write(tmp_path, name, lines):
    p = tmp_path / name
    p.write_text("\n".join(lines) + ("\n" if lines else ""))
    return p


def test_malformed_asf_names_file_and_line(shared_data, tmp_path):
    lines = (shared_data / "bvh" / "cmu_01.asf").read_text().splitlines()
    k_axis = next(i for i, ln in enumerate(lines) if ln.strip().startswith("axis 0 0 20"))
    bad_axis = list(lines)
    bad_axis[k_axis] = "axis 0 0 20 XXZ"
    k_h = next(i for i, ln in enumerate(lines) if ln.strip() == "lfemur ltibia")
    bad_h = list(lines)
    bad_h[k_h] = "lfemur ltibiaa"
    k_len = next(i for i, ln in enumerate(lines) if ln.strip().startswith("length 7.1578"))
    bad_len = list(lines)
    bad_len[k_len] = "length seven"
    k_bd = next(i for i, ln in enumerate(lines) if ln.startswith(":bonedata"))
    cases = {
        "empty.asf": ([], r"empty\.asf:1: empty file"),
        "axis.asf": (bad_axis, rf"axis\.asf:{k_axis + 1}: unknown rotation order 'XXZ'"),
        "hier.asf": (bad_h, rf"hier\.asf:{k_h + 1}: :hierarchy names unknown bone 'ltibiaa'"),
        "len.asf": (bad_len, rf"len\.asf:{k_len + 1}: bad number in length"),
        "trunc.asf": (lines[: k_bd + 5], r"trunc\.asf:\d+: truncated file: bone starting line"),
    }
    for name, (content, pattern) in cases.items():
        with pytest.raises(ASFError, match=pattern):
            read_asf(_write(tmp_path, name, content))


def _asf_edit(shared_data, tmp_path, name, old, new, count=1):
    text = (shared_data / "bvh" / "cmu_01.asf").read_text()
    assert old in text
    return _write(tmp_path, name, text.replace(old, new, count).splitlines())


@pytest.mark.parametrize(("old", "new", "pattern"), [
    ("length 0.45", "length 0", r":\d+: units length must be > 0, got '0'"),
    ("length 0.45", "length 1e-320", r": :units length 1e-320 is too small"),
    ("direction 0.34202 -0.939693 0", "direction nan -0.939693 0", r":\d+: direction is not fin"),
    ("direction 0.34202 -0.939693 0", "direction 0.34202", r":\d+: direction needs 3 numbers"),
    ("length 2.40479", "length -2.40479", r":\d+: length must not be negative"),
    ("length 2.40479", "length 1e308", r": :bonedata: bone 'lhipjoint' \(length 1e\+308\) ends"),
    ("name lfemur\n", "name lhipjoint\n", r":\d+: bone name 'lhipjoint' is used twice"),
    ("id 2 \n", "id inf\n", r":\d+: id is not finite: 'inf'"),
    ("dof rx ry rz\n", "dof rx rx rz\n", r":\d+: dof repeats an axis: rx rx rz"),
    ("position 0 0 0", "position 1e308 0 0", r": :root position is \[.*\] m \(beyond 1e\+06 m"),
])
def test_hostile_asf_fields_name_file_and_field(shared_data, tmp_path, old, new, pattern):
    p = _asf_edit(shared_data, tmp_path, "bad.asf", old, new)
    with pytest.raises(ASFError, match=r"bad\.asf" + pattern):
        read_asf(p)


def test_deep_asf_chain_and_hostile_amc_values(shared_data, tmp_path):
    bones = "".join(
        f"  begin\n    id {i}\n    name b{i}\n    direction 0 1 0\n    length 1\n"
        f"    axis 0 0 0 XYZ\n    dof rx\n  end\n" for i in range(300))
    chain = "".join(f"  {'root' if i == 0 else f'b{i - 1}'} b{i}\n" for i in range(300))
    p = tmp_path / "deep.asf"
    p.write_text(f":units\n  length 0.45\n:root\n  order TX TY TZ RX RY RZ\n  axis XYZ\n"
                 f":bonedata\n{bones}:hierarchy\n  begin\n{chain}  end\n")
    with pytest.raises(ASFError, match=r"deep\.asf: :hierarchy: bone 'b256' nests deeper "
                                       r"than 256 bones"):
        read_asf(p)
    sk = read_asf(shared_data / "bvh" / "cmu_11.asf")
    good = _amc_lines(shared_data)
    for line, pattern in [
        ("upperneck nan 2 3", r"nan\.amc:41: bad number 'nan' for bone 'upperneck'"),
        ("upperneck 1 -inf 3", r"nan\.amc:41: bad number '-inf' for bone 'upperneck'"),
    ]:
        bad = list(good)
        bad[40] = line
        with pytest.raises(AMCError, match=pattern):
            read_amc(_write(tmp_path, "nan.amc", bad), sk)
    bad = list(good)
    bad[4] = "99999999999"
    with pytest.raises(AMCError, match=r"big\.amc:5: frame number 99999999999 is too large"):
        read_amc(_write(tmp_path, "big.amc", bad), sk)
