"""Gaussian multi-resolution tree (Moradoff §3.4)."""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.codecs import decode, encode
from mocapflow.stages.motion.kinematics import forward_kinematics
from mocapflow.stages.motion.rotations import (
    heading_split,
    quat_angle,
    quat_from_axis_angle,
    quat_multiply,
    yaw_quaternion,
)
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.texture.pyramid import (
    Pyramid,
    PyramidError,
    binomial_filter,
    build_pyramid,
    downsample,
    downsample_quaternions,
    pyramid,
    root_features,
)
from mocapflow.stages.texture.root import integrate_root


@pytest.fixture(scope="module")
def walk():
    return procedural_walk(160, rate=30.0, seed=2)


def test_binomial_filter_values_and_errors():
    np.testing.assert_allclose(binomial_filter(4), np.array([1, 3, 3, 1]) / 8)
    np.testing.assert_allclose(binomial_filter(2), [0.5, 0.5])
    for bad in (0, 3, 5):
        with pytest.raises(PyramidError, match="filter_size"):
            binomial_filter(bad)


def test_downsample_keeps_linear_signals_at_node_times():
    # node k of the next level stands for time 2k + 0.5; a symmetric filter keeps ramps
    x = 3.0 * np.arange(40.0) - 7.0
    y = downsample(x, 4)
    assert y.shape == (20,)
    k = np.arange(1, 19)  # interior nodes (edges are clamped)
    np.testing.assert_allclose(y[k], 3.0 * (2 * k + 0.5) - 7.0, atol=1e-12)
    assert downsample(np.arange(41.0), 4).shape == (21,)


def test_downsample_quaternions_is_the_geodesic_midpoint_and_sign_blind():
    axis = np.array([0.3, 1.0, -0.2])
    t = np.arange(32.0)
    q = quat_from_axis_angle(np.broadcast_to(axis, (32, 3)), 0.07 * t)
    flipped = q.copy()
    flipped[1::3] *= -1  # the filter must not care about quaternion signs
    for src in (q, flipped):
        c = downsample_quaternions(src[:, None, :], 4)[:, 0]
        k = np.arange(1, 15)
        want = quat_from_axis_angle(np.broadcast_to(axis, (k.size, 3)), 0.07 * (2 * k + 0.5))
        assert np.max(quat_angle(c[k], want)) < 1e-9


def test_heading_split_recovers_yaw_and_leaves_no_twist():
    rng = np.random.default_rng(0)
    h = np.cumsum(rng.normal(0.0, 0.3, 50))  # crosses ±pi: must come back unwrapped
    axes = np.column_stack([np.ones(50), np.zeros(50), rng.normal(0, 0.3, 50)])
    tilt = quat_from_axis_angle(axes, rng.uniform(-0.4, 0.4, 50))
    heading, local = heading_split(quat_multiply(yaw_quaternion(h), tilt))
    np.testing.assert_allclose(heading, h, atol=1e-9)
    assert np.max(np.abs(local[:, 2])) < 1e-12  # no y component: no twist left


def test_root_features_integrate_back_to_the_trajectory(walk):
    heading, _ = heading_split(walk.rotations[:, 0])
    yaw, vel, height = root_features(walk.root_position, heading)
    h2, ground = integrate_root(yaw, vel, heading0=heading[0], origin=walk.root_position[0, [0, 2]])
    np.testing.assert_allclose(h2, heading, atol=1e-9)
    np.testing.assert_allclose(ground, walk.root_position[:, [0, 2]], atol=1e-9)
    np.testing.assert_allclose(height, walk.root_position[:, 1])


def test_levels_sizes_and_positions_are_fk_of_the_heading_free_pose(walk):
    p = build_pyramid(walk, levels=4, filter_size=4)
    assert [lev.n_nodes for lev in p.levels] == [160, 80, 40, 20]
    lev0 = p.levels[0]
    root = np.zeros((160, 3))
    root[:, 1] = walk.root_position[:, 1]
    want, _ = forward_kinematics(walk.skeleton, lev0.rotations, root)
    np.testing.assert_allclose(lev0.positions, want, atol=1e-12)
    # the rotations differ from the input only by the root's heading
    heading, _ = heading_split(walk.rotations[:, 0])
    back = quat_multiply(yaw_quaternion(heading), lev0.rotations[:, 0])
    assert np.max(quat_angle(back, walk.rotations[:, 0])) < 1e-9
    assert np.max(quat_angle(lev0.rotations[:, 1:], walk.rotations[:, 1:])) < 1e-9


def test_pyramid_features_do_not_depend_on_where_the_motion_is(walk):
    """Turning and moving the whole take leaves every level's features unchanged."""
    turn = yaw_quaternion(np.full(walk.n_frames, 1.3))
    rot = walk.rotations.copy()
    rot[:, 0] = quat_multiply(turn, rot[:, 0])
    c, s = np.cos(1.3), np.sin(1.3)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    moved = walk.replace(rotations=rot, root_position=walk.root_position @ R.T + [4.0, 0, -2.0])
    a = build_pyramid(walk, levels=3)
    b = build_pyramid(moved, levels=3)
    for la, lb in zip(a.levels, b.levels):
        for name in ("yaw_rate", "velocity", "height", "positions"):
            np.testing.assert_allclose(getattr(la, name), getattr(lb, name), atol=1e-9)


def test_too_short_or_bad_levels_raise_clear_errors(walk):
    short = walk.replace(
        root_position=walk.root_position[:30], rotations=walk.rotations[:30]
    )
    with pytest.raises(PyramidError, match=r"30 frames is too short for 4 levels.*at most 3 lev"):
        build_pyramid(short, levels=4)
    assert build_pyramid(short, levels=3).n_levels == 3  # the advice holds
    tiny = walk.replace(root_position=walk.root_position[:3], rotations=walk.rotations[:3])
    with pytest.raises(PyramidError, match=r"3 frames is too short to synthesize from: it needs "
                                           r"at least 8 frames"):
        build_pyramid(tiny, levels=1)
    with pytest.raises(PyramidError, match="levels must be >= 1"):
        build_pyramid(walk, levels=0)


def test_codec_round_trip_and_stage(walk):
    out = pyramid(walk, levels=3, filter_size=4, ctx=Context(part="walk"))
    p = out["pyramid"]
    assert isinstance(p, Pyramid) and p.n_levels == 3 and p.filter_size == 4
    back = decode(encode(p))
    assert back.n_levels == 3 and back.rate == 30.0
    for la, lb in zip(p.levels, back.levels):
        for name in ("rotations", "yaw_rate", "velocity", "height", "positions"):
            np.testing.assert_array_equal(getattr(la, name), getattr(lb, name))
