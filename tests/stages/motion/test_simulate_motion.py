"""Procedural skeleton, walk/run generator and range-of-motion generator."""

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.registry import get_stage
from mocapflow.stages.motion.formats.bvh import read_bvh, write_bvh
from mocapflow.stages.motion.kinematics import end_site_positions, forward_kinematics
from mocapflow.stages.motion.rotations import quat_angle
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.motion.simulate.motion import simulate_range_of_motion, simulate_walk
from mocapflow.stages.motion.simulate.range_of_motion import (
    JOINT_GROUPS,
    procedural_range_of_motion,
)
from mocapflow.stages.motion.simulate.skeleton import ROOT_HEIGHT, procedural_skeleton


def _world(m):
    pos, grot = forward_kinematics(m.skeleton, m.rotations, m.root_position)
    return pos, end_site_positions(m.skeleton, pos, grot)


def _contact_mask(m, side, start="foot_flat"):
    """Frames between foot-flat (ball on the floor) and toe-off of ``side``."""
    ev = m.attrs["gait_events"][side]
    t = np.arange(m.n_frames) / m.rate
    mask = np.zeros(m.n_frames, bool)
    for t0 in ev[start]:
        later = [x for x in ev["toe_off"] if x > t0]
        t1 = later[0] if later else t[-1]
        mask |= (t >= t0) & (t <= t1)
    return mask


def test_skeleton_matches_cmu_names_and_body_size(shared_data):
    sk = procedural_skeleton()
    cmu = read_bvh(shared_data / "bvh" / "cmu_01_01.bvh").skeleton
    assert sk.names == cmu.names
    np.testing.assert_array_equal(sk.parents, cmu.parents)
    np.testing.assert_array_equal(sk.end_parents, cmu.end_parents)
    assert sk.channels == cmu.channels
    rest = np.zeros((1, sk.n_joints, 4))
    rest[..., 0] = 1
    pos, grot = forward_kinematics(sk, rest, np.array([[0, ROOT_HEIGHT, 0]]))
    ends = end_site_positions(sk, pos, grot)
    assert ends[0, :, 1].max() == pytest.approx(1.75)  # top of the head
    assert pos[0, :, 1].min() == pytest.approx(0.02)  # toe joints 2 cm above the floor
    assert pos[0, sk.index("LeftUpLeg"), 0] > 0  # +x is the subject's left


@pytest.fixture(scope="module")
def walk():
    return procedural_walk(1200, rate=120.0, gait="walk", seed=3)


@pytest.mark.parametrize("gait", ["walk", "run"])
def test_feet_planted_no_skate(gait, walk):
    m = walk if gait == "walk" else procedural_walk(900, gait="run", seed=3)
    pos, ends = _world(m)
    sk = m.skeleton
    assert m.attrs["max_reach_error"] < 0.08  # only swing targets may be out of reach
    for side, pre in (("left", "Left"), ("right", "Right")):
        toe = pos[:, sk.index(f"{pre}ToeBase")]
        c = _contact_mask(m, side)
        assert c.sum() > 100
        speed = np.linalg.norm(np.diff(toe[:, [0, 2]], axis=0), axis=1) * m.rate
        both = c[1:] & c[:-1]
        # ball of the foot planted from foot-flat to toe-off: measured ~1e-12 m/s
        assert speed[both].max() < 1e-6
        np.testing.assert_allclose(toe[c, 1], 0.02, atol=1e-9)
        # METRICS.md-style skate: horizontal toe speed where the toe is near the floor
        # (within 1 cm of its standing height) and slow (< 0.5 m/s)
        near = (toe[1:, 1] < 0.03) & (toe[:-1, 1] < 0.03) & (speed < 0.5)
        assert speed[near].mean() < 0.02, speed[near].mean()  # measured 0.007-0.01 m/s
    # nothing goes through the floor
    assert pos[..., 1].min() > -1e-9 and ends[..., 1].min() > -1e-9
    # progression matches the requested speed
    v = (m.root_position[-1, 2] - m.root_position[0, 2]) * m.rate / (m.n_frames - 1)
    assert v == pytest.approx(m.attrs["speed"], rel=0.05)
    if gait == "run":  # flight phases: neither foot on the ground
        st = _contact_mask(m, "left", "heel_strike") | _contact_mask(m, "right", "heel_strike")
        assert (~st).sum() > 0.15 * m.n_frames


def test_gait_looks_like_walking(walk):
    m = walk
    sk = m.skeleton
    ang = lambda j: np.degrees(quat_angle(m.rotations[:, sk.index(j)], [1.0, 0, 0, 0]))  # noqa
    assert 55 < ang("LeftLeg").max() < 80  # peak swing knee flexion (measured 76 deg)
    assert 25 < ang("LeftUpLeg").max() < 55  # hip (flexion + abduction, measured 49 deg)
    h = m.root_position[:, 1]
    assert 0.02 < np.ptp(h) < 0.09  # vertical excursion of the pelvis
    pos, _ = _world(m)
    # arms swing opposite the legs: left hand forward when the left foot is back
    rel = pos - m.root_position[:, None]
    lhand, lfoot = rel[:, sk.index("LeftHand"), 2], rel[:, sk.index("LeftFoot"), 2]
    assert np.corrcoef(lhand, lfoot)[0, 1] < -0.8


def test_cycle_to_cycle_variation(walk):
    periods = np.array(walk.attrs["cycle_periods"])
    assert len(periods) >= 9
    assert periods.std() > 0.005  # measured ~0.02 s around 1.1 s
    # peak knee flexion differs between cycles too
    m = walk
    knee = np.degrees(quat_angle(m.rotations[:, m.skeleton.index("LeftLeg")], [1.0, 0, 0, 0]))
    hs = (np.array(m.attrs["gait_events"]["left"]["heel_strike"]) * m.rate).astype(int)
    peaks = [knee[a:b].max() for a, b in zip(hs[:-1], hs[1:])]
    assert np.ptp(peaks) > 0.5
    # without variation the gait is exactly periodic (1.1 s = 132 frames at 120 Hz)
    p = procedural_walk(400, seed=3, variation=0.0)
    assert np.allclose(p.attrs["cycle_periods"], 1.1)
    np.testing.assert_allclose(p.rotations[132:], p.rotations[:-132], atol=1e-9)
    np.testing.assert_allclose(p.root_position[132:, :2], p.root_position[:-132, :2], atol=1e-9)
    np.testing.assert_allclose(p.root_position[132:, 2] - p.root_position[:-132, 2], 1.3 * 1.1)


def test_seeds(walk):
    again = procedural_walk(1200, seed=3)
    np.testing.assert_array_equal(again.rotations, walk.rotations)
    other = procedural_walk(1200, seed=4)
    assert np.abs(other.rotations - walk.rotations).max() > 0.01
    fast = procedural_walk(300, speed=1.8, seed=0)
    assert fast.attrs["speed"] == pytest.approx(1.8, rel=0.05)
    with pytest.raises(ValueError, match="gait must be"):
        procedural_walk(10, gait="hop")


def test_bvh_export_readable(walk, tmp_path):
    out = write_bvh(walk, tmp_path / "walk.bvh")
    back = read_bvh(out)
    assert back.attrs["source_unit"] == "m" and back.rate == 120.0
    p1, e1 = _world(walk)
    p2, e2 = _world(back)
    assert np.abs(p1 - p2).max() < 2e-6 and np.abs(e1 - e2).max() < 2e-6
    bvhio = pytest.importorskip("bvhio")
    sub = procedural_walk(30, seed=3)
    write_bvh(sub, tmp_path / "sub.bvh")
    root = bvhio.readAsHierarchy(str(tmp_path / "sub.bvh"))
    layout = [j for j, _, _ in root.layout()]
    ps, _ = _world(sub)
    for f in (0, 29):
        root.loadPose(f)
        ref = np.array([list(j.PositionWorld) for j in layout])
        assert np.abs(ref - ps[f]).max() < 1e-5 * 1.75


def test_range_of_motion_moves_one_group_at_a_time():
    m = procedural_range_of_motion(600, seed=1)
    sk = m.skeleton
    pos, _ = _world(m)
    np.testing.assert_allclose(m.root_position, [[0, ROOT_HEIGHT, 0]] * 600)
    assert set(m.attrs["group_frames"]) == set(JOINT_GROUPS)

    def descendants(names):
        idx = {sk.index(n) for n in names}
        for j in range(sk.n_joints):
            if sk.parents[j] in idx:
                idx.add(j)
        return idx

    for group, (a, b) in m.attrs["group_frames"].items():
        moving = np.linalg.norm(pos[a:b] - pos[a], axis=-1).max(axis=0) > 1e-9
        allowed = descendants(JOINT_GROUPS[group])
        assert set(np.flatnonzero(moving)) <= allowed, group
        assert moving.sum() >= 2, group
        rot = np.degrees(quat_angle(m.rotations[a:b], m.rotations[a]))
        assert rot[:, [sk.index(n) for n in JOINT_GROUPS[group]]].max() > 20


def test_stages_registered_and_callable():
    assert get_stage("simulate_walk").outputs == ("motion",)
    out = simulate_walk(n_frames=50, gait="run", seed=2, ctx=Context(part=None, seed=2))
    assert out["motion"].n_frames == 50 and out["motion"].attrs["seed"] == 2
    again = simulate_walk(n_frames=50, gait="run", seed=2, ctx=Context(part=None, seed=2))
    np.testing.assert_array_equal(out["motion"].rotations, again["motion"].rotations)
    rom = simulate_range_of_motion(n_frames=60, ctx=Context(part=None))
    assert rom["motion"].n_frames == 60
    assert get_stage("simulate_range_of_motion").outputs == ("motion",)
