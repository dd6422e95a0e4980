"""The texture graph on a Z-up motion (issue 14): synthesized Y up, given back in its axes."""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.motion.ingest import ingest_bvh
from mocapflow.stages.motion.kinematics import motion_positions, reorient_motion
from mocapflow.stages.texture.pyramid import pyramid
from mocapflow.stages.texture.synth import synth
from tests.stages.texture.conftest import seeded_context

#: Y-up, +Z-facing -> Z-up, -Y-facing (a Vicon-style lab): (x, y, z) -> (x, -z, y).
R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


@pytest.fixture(scope="module")
def walk(shared_data):
    return ingest_bvh(str(shared_data / "bvh" / "cmu_131_02.bvh"), rate=30, ctx=Context())["motion"]


def test_reorient_moves_only_the_root_and_round_trips(walk):
    z = reorient_motion(walk, up="+z", forward="-y")
    assert (z.attrs["up"], z.attrs["forward"]) == ("+z", "-y")
    np.testing.assert_allclose(motion_positions(z), motion_positions(walk) @ R.T, atol=1e-12)
    np.testing.assert_array_equal(z.rotations[:, 1:], walk.rotations[:, 1:])
    back = reorient_motion(z)
    np.testing.assert_allclose(motion_positions(back), motion_positions(walk), atol=1e-12)
    assert reorient_motion(walk) is walk  # already Y up, facing +Z: untouched


def test_z_up_input_synthesizes_the_same_motion_in_its_own_axes(walk):
    z = reorient_motion(walk, up="+z", forward="-y")

    def run(m):
        p = pyramid(m, levels=3, ctx=Context())["pyramid"]
        return synth(p, m, length=64, levels=3, ctx=seeded_context(0))

    out_y, out_z = run(walk), run(z)
    np.testing.assert_array_equal(out_y["source_index"], out_z["source_index"])
    my, mz = out_y["motion"], out_z["motion"]
    assert mz.attrs["up"] == "+z" and mz.attrs["forward"] == "-y"
    py, pz = motion_positions(my), motion_positions(mz)
    np.testing.assert_allclose(pz, py @ R.T, atol=1e-6)  # metres
    # upright in its own axes: the head is above the feet along z
    assert np.ptp(pz[..., 2]) > 0.8 * np.ptp(py[..., 1])
