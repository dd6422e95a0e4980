"""The GenMM baseline of ``benchmarks/texture.py`` (``benchmarks/genmm_baseline.py``).

A NumPy reimplementation of GenMM (Li et al., SIGGRAPH 2023) used as the peer in the
texture benchmark: checked here on a tiny synthetic motion (no data files) for what
the benchmark relies on — deterministic per seed, output made of the input's
patches, root speed kept, and GenMM's pyramid lengths.
"""

from __future__ import annotations

import numpy as np
import pytest
from genmm_baseline import (  # (benchmarks/ on sys.path: conftest.py)
    genmm_synthesize,
    pyramid_lengths,
    resample_linear,
)

from mocapflow.stages.metrics import quality as M
from mocapflow.stages.motion.datatypes import Motion, Skeleton
from mocapflow.stages.motion.rotations import quat_from_axis_angle

F_IN, L_OUT = 150, 240


def tiny_motion(n_frames: int = F_IN) -> Motion:
    """7 joints, two sinusoids per joint about a random axis, root walking along +z."""
    names = ["root", "spine", "head", "leg_l", "foot_l", "leg_r", "foot_r"]
    parents = np.array([-1, 0, 1, 0, 3, 0, 5])
    offsets = np.array([[0, 1, 0], [0, 0.2, 0], [0, 0.3, 0], [0.1, -0.1, 0], [0, -0.45, 0],
                        [-0.1, -0.1, 0], [0, -0.45, 0]], dtype=float)
    channels = [["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"]]
    channels += [["Zrotation", "Xrotation", "Yrotation"]] * 6
    skeleton = Skeleton(names, parents, offsets, channels)
    J = len(names)
    rng = np.random.default_rng(7)
    axes = rng.normal(size=(J, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    f1, f2, phase = rng.uniform(0.5, 1.5, J), rng.uniform(1.7, 3.1, J), rng.uniform(0, 6.3, J)
    t = np.arange(n_frames) / 30.0
    angle = (0.6 * np.sin(2 * np.pi * f1 * t[:, None] + phase)
             + 0.3 * np.sin(2 * np.pi * f2 * t[:, None]))
    rotations = quat_from_axis_angle(np.broadcast_to(axes, (n_frames, J, 3)), angle)
    root = np.stack([0.3 * np.sin(t), 1.0 + 0.02 * np.sin(6 * t), 1.2 * t], axis=1)
    return Motion(skeleton, root, rotations, 30.0)


@pytest.fixture(scope="module")
def motion() -> Motion:
    return tiny_motion()


@pytest.fixture(scope="module")
def out0(motion):
    return genmm_synthesize(motion, L_OUT, seed=0)


def test_output_shape_and_validity(motion, out0):
    out = out0["motion"]
    assert out.n_frames == L_OUT and out.rate == motion.rate
    assert out.skeleton is motion.skeleton
    assert np.all(np.isfinite(out.rotations)) and np.all(np.isfinite(out.root_position))
    np.testing.assert_allclose(np.linalg.norm(out.rotations, axis=-1), 1.0, atol=1e-6)
    src = out0["source_index"]
    assert src.shape == (L_OUT,) and src.min() >= 0 and src.max() < motion.n_frames
    assert out0["output_lengths"][-1] == L_OUT
    assert len(out0["output_lengths"]) == len(out0["input_lengths"])


def test_deterministic_per_seed(motion, out0):
    again = genmm_synthesize(motion, L_OUT, seed=0)
    np.testing.assert_array_equal(again["motion"].rotations, out0["motion"].rotations)
    np.testing.assert_array_equal(again["motion"].root_position, out0["motion"].root_position)
    other = genmm_synthesize(motion, L_OUT, seed=1)
    assert not np.allclose(other["motion"].rotations, out0["motion"].rotations)


def test_output_is_made_of_input_patches(motion, out0):
    """GANimator local diversity well below random 10-frame chunks of the input."""
    f_in = M.rotation_features(motion)
    local = M.local_diversity(M.rotation_features(out0["motion"]), f_in)
    rng = np.random.default_rng(0)
    starts = rng.integers(0, F_IN - 10, L_OUT // 10)
    shuffled = (starts[:, None] + np.arange(10)).ravel()
    local_shuffle = M.local_diversity(f_in[shuffled], f_in)
    assert local < 0.5 * local_shuffle


def test_root_speed_and_height_kept(motion, out0):
    def speed(m):
        return np.linalg.norm(np.diff(m.root_position[:, [0, 2]], axis=0), axis=1).mean()

    out = out0["motion"]
    assert speed(out) == pytest.approx(speed(motion), rel=0.1)
    np.testing.assert_allclose(out.root_position[0, [0, 2]], motion.root_position[0, [0, 2]])
    lo, hi = motion.root_position[:, 1].min(), motion.root_position[:, 1].max()
    assert np.all((out.root_position[:, 1] > lo - 0.05) & (out.root_position[:, 1] < hi + 0.05))


def test_pyramid_lengths_match_released_genmm():
    """cmu_131_02 at 30 fps (312 frames) → 1024 frames: the levels GenMM itself logged."""
    ratio = 11 * 5 / 312
    assert pyramid_lengths(312, ratio, 0.75) == [55, 73, 97, 129, 172, 229, 305, 312]
    assert pyramid_lengths(1024, ratio, 0.75) == [181, 241, 321, 428, 571, 761, 1015, 1024]


def test_resample_linear_half_pixel():
    x = np.arange(4, dtype=float)[:, None]
    np.testing.assert_allclose(resample_linear(x, 2)[:, 0], [0.5, 2.5])
    np.testing.assert_allclose(resample_linear(x, 7, align_corners=True)[:, 0],
                               np.linspace(0, 3, 7))
