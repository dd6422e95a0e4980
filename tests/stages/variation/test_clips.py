"""Variation clips: the Clips type and codec, motion and strokes <-> DOF trajectories."""

import numpy as np
import pytest

from mocapflow.pipeline.codecs import decode, digest_encoded, encode
from mocapflow.stages.motion.rotations import (
    euler_continuity,
    euler_to_quat,
    quat_angle,
    quat_multiply,
    quat_rotate,
    quat_to_euler,
)
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.variation.clips import Clips, clips_from_motions, clips_to_motions, make_clips
from mocapflow.stages.variation.dofs import dofs_to_motion, motion_to_dofs
from tests.stages.variation.conftest import positions


def test_motion_dofs_round_trip_and_constants(walk):
    dofs, names, psi, pos = motion_to_dofs(walk)
    assert dofs.shape == (480, len(names)) and len(set(names)) == len(names)
    back = dofs_to_motion(dofs, names, walk.skeleton, rate=60.0, origin=[psi[0], *pos[0]])
    assert np.abs(positions(back) - positions(walk)).max() < 1e-9
    c = make_clips([dofs[:200], dofs[200:]], names, rate=60.0)
    # a constant DOF is dropped from the trajectories and restored by full()
    const = [n for n in names if np.ptp(dofs[:, names.index(n)]) <= 1e-8]
    assert const and c.attrs["constant_dofs"] == const
    assert c.n_dofs == len(names) - len(const)
    np.testing.assert_array_equal(c.full(1), dofs[200:])


def test_heading_root_is_path_independent():
    # the same walk turned by 90° and moved: every DOF except nothing changes
    m = procedural_walk(120, rate=60.0, seed=1)
    turn = euler_to_quat(np.array([0.0, np.pi / 2, 0.0]), "XYZ")
    rot = m.rotations.copy()
    rot[:, 0] = quat_multiply(turn, rot[:, 0])
    moved = m.replace(rotations=rot, root_position=quat_rotate(turn, m.root_position) + [3, 0, 1])
    a, names, _, _ = motion_to_dofs(m)
    b, _, psi, _ = motion_to_dofs(moved)
    assert np.abs(a - b).max() < 1e-9
    assert psi[0] == pytest.approx(motion_to_dofs(m)[2][0] + np.pi / 2, abs=1e-9)


def test_euler_continuity_through_gimbal_branch():
    # yaw (middle axis of "XYZ") sweeping through ±180°: the canonical Euler triple
    # jumps branches; the continuous track must not, and must still be the same rotation
    t = np.linspace(0, 2 * np.pi, 200)
    e = np.stack([0.1 * np.sin(3 * t), 0.9 * t, 0.2 * np.cos(2 * t)], axis=1)
    q = euler_to_quat(e, "XYZ")
    raw = quat_to_euler(q, "XYZ")
    cont = euler_continuity(raw[:, None, :])[:, 0]
    assert np.abs(np.diff(raw, axis=0)).max() > 1.0  # the canonical track jumps
    assert np.abs(np.diff(cont, axis=0)).max() < 0.05  # the continuous one does not
    assert quat_angle(euler_to_quat(cont, "XYZ"), q).max() < 1e-9


def test_clips_codec_round_trip(walk):
    c = clips_from_motions([walk], cuts=[np.array([0, 70, 140, 210])], cyclic=True)
    e = encode(c)
    back = decode(e)
    assert isinstance(back, Clips) and back.n_clips == 3 and back.cyclic
    for a, b in zip(c.trajectories, back.trajectories):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(back.origins, c.origins)
    assert back.skeleton.names == walk.skeleton.names and back.names == c.names
    assert digest_encoded(encode(back)) == digest_encoded(e)
    # each clip rebuilds its piece of the take exactly
    m1 = clips_to_motions(back)[1]
    assert np.abs(positions(m1) - positions(walk)[70:140]).max() < 1e-9
