"""Pyramid levels by frame rate (issue 16, items 1 and "Must show" speed).

The pyramid had 4 levels at any rate: at a take's native 120 fps the coarsest
node spans 8 frames (67 ms) instead of 267 ms, the coarse plan has 4x the nodes
and two to three times the seams, and synthesis is slow (salsa, 4,096 frames,
seeds 0-2: 2.6-3.6 s of CPU against 0.56-0.85 s with 6 levels).  The default
(``levels=None``) is now 4 at 30 fps and one more per doubling, so a 120 fps take
gets the 30 fps take's plan: the same seams per second, exact constraints and
smooth seams at both rates.
"""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.metrics import quality as M
from mocapflow.stages.motion.ingest import ingest_bvh
from mocapflow.stages.motion.kinematics import motion_positions
from mocapflow.stages.texture.pyramid import (
    LEVELS_AT_30,
    MIN_COARSE_NODES,
    PyramidError,
    build_pyramid,
    levels_for_rate,
    pyramid,
)
from mocapflow.stages.texture.smoothing import SMOOTHING_RATE
from mocapflow.stages.texture.synth import synth
from tests.stages.texture.conftest import seeded_context

#: [input frame at 120 fps, output frame] per output rate: the same moments.
CONSTRAINTS = {30: [[100, 12], [600, 375]], 120: [[100, 48], [600, 1500]]}
SECONDS = 2048 / 120


def test_levels_for_rate_adds_one_level_per_doubling():
    assert LEVELS_AT_30 == 4
    assert [levels_for_rate(r) for r in (15, 24, 30, 60, 100, 120, 240)] == [3, 4, 4, 5, 6, 6, 7]
    assert levels_for_rate(1.0) == 2  # never below 2
    # a short motion keeps MIN_COARSE_NODES coarsest nodes: 100 frames -> 4 levels (13 nodes)
    assert levels_for_rate(120, n_frames=100) == 4
    assert -(-100 // 2 ** 3) >= MIN_COARSE_NODES > -(-100 // 2 ** 4)
    for bad in (0.0, -30.0, float("nan")):
        with pytest.raises(PyramidError, match="rate must be a positive number"):
            levels_for_rate(bad)


@pytest.fixture(scope="module")
def walk_at(shared_data):
    path = shared_data / "bvh" / "pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh"
    return {r: ingest_bvh(str(path), rate=None if r == 120 else r, ctx=Context())["motion"]
            for r in (30, 120)}


def test_default_pyramid_levels_follow_the_rate(walk_at):
    assert build_pyramid(walk_at[30]).n_levels == 4
    assert pyramid(walk_at[120], ctx=Context())["pyramid"].n_levels == 6
    assert build_pyramid(walk_at[120], levels=3).n_levels == 3  # explicit levels kept


@pytest.fixture(scope="module")
def runs(walk_at):
    """Per rate: the input and the synth reports of seeds 0 and 1 (default levels)."""
    out = {}
    for rate, m in walk_at.items():
        out[rate] = m, [synth(build_pyramid(m), m, length=round(SECONDS * rate),
                              constraints=CONSTRAINTS[rate], seed=seed, output_rate=rate,
                              ctx=seeded_context(seed)) for seed in (0, 1)]
    return out


def test_30_and_120_fps_agree_in_seams_and_constraint_error(runs):
    seams = {}
    for rate, (m, rs) in runs.items():
        jin = M.jerk_p99(motion_positions(m), m.rate)
        radius = int(5 * rate / SMOOTHING_RATE)  # ±5 frames at 30 fps
        for r in rs:
            rep, src = r["report"], r["source_index"]
            assert all(rep["smoothing"]["passed"])
            assert rep["constraint_max_angle_deg"] < 1e-6
            for i, o in rep["constraints_synthesis"]:
                assert src[o] == i
            mask = M.seam_mask(len(src), M.seams_from_source(src), radius=radius)
            assert M.jerk_p99(motion_positions(r["motion"]), rate, mask=mask) <= 1.0 * jin
        seams[rate] = np.mean([r["report"]["n_seams"] for r in rs])
    # the same plan in time: seams of the 34-s output within 30 % (4 levels at 120: 2x)
    assert seams[120] == pytest.approx(seams[30], rel=0.3), seams
