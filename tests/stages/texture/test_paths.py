"""Closed paths and loops close; feet stay planted on paths (issue 16, item 2).

The figure-8 walk (``pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh``) resampled to 30 fps
and synthesized at that rate (532 frames, 2x the input; output at the synthesis
rate), looped on a closed figure-8 spline path (``figure_eight(2.0)``, 24.4 m).
Before: the wrap (frame 531 -> 0) jumped 3.49 / 3.98 / 3.64 m and 41 / 75 / 75 deg
(seeds 0, 1, 2), the root was 12.7 / 14.9 / 15.7 cm from the path (mean) and the
toe-skate ratio was 1.51 / 1.26 / 1.38, with no warning.  Now the travel is paced
to whole laps (one stride scale), the trajectory is computed on the loop repeated
on both sides, the sway is kept around the path and the legs take up the stride
change (foot IK with ``PATH_IK`` weights).

The wrap step is compared with the median of the steps around it (2 before, 2
after): at 30 fps the gait makes ordinary steps differ from the loop's median
step by up to 4.4 cm and 8 deg (90th percentile 2.1 cm and 2.5 deg), so the loop's
median alone cannot tell a closed wrap from an ordinary step; the wrap must also
be no further from the loop's median than the 90th percentile of ordinary steps.
"""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.metrics import quality as M
from mocapflow.stages.motion.contacts import contact_thresholds, toe_indices
from mocapflow.stages.motion.ingest import ingest_bvh
from mocapflow.stages.motion.kinematics import motion_positions
from mocapflow.stages.motion.rotations import heading_split
from mocapflow.stages.texture.pyramid import build_pyramid
from mocapflow.stages.texture.root import PathCurve, figure_eight
from mocapflow.stages.texture.synth import synth
from tests.stages.texture.conftest import seeded_context

RATE = 30.0
LENGTH = 532
SEEDS = (0, 1, 2)


def _run(pyr, motion, seed: int, **params):
    """``synth`` outputs and the warnings it gave."""
    ctx = seeded_context(seed)
    warnings: list[str] = []
    ctx.warn = warnings.append
    r = synth(pyr, motion, seed=seed, ctx=ctx, output_rate=RATE, **params)
    return r, warnings


@pytest.fixture(scope="module")
def walk8(shared_data):
    path = shared_data / "bvh" / "pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh"
    motion = ingest_bvh(str(path), rate=RATE, ctx=Context())["motion"]
    return motion, build_pyramid(motion, levels=4)


@pytest.fixture(scope="module")
def skate_in(walk8):
    """Toe indices, input contact thresholds and the input's toe skate (m/s)."""
    motion, _ = walk8
    pos = motion_positions(motion)
    toes = toe_indices(motion.skeleton)
    h, s = contact_thresholds(pos, toes, motion.rate)
    ref = M.foot_skate(pos, toes, motion.rate, height_threshold=h, speed_threshold=s)
    return toes, h, s, ref


def _skate_ratio(out, skate_in) -> float:
    toes, h, s, ref = skate_in
    pos = motion_positions(out)
    return M.foot_skate(pos, toes, out.rate, height_threshold=h, speed_threshold=s) / ref


def _steps(out) -> tuple[np.ndarray, np.ndarray]:
    """Cyclic root steps: ground distance (m) and signed heading change (deg), ``t -> t +
    1``, the last one the wrap ``L - 1 -> 0``.  (Signed: the figure-8 starts at its
    crossing, where the turn changes sides — e.g. -0.81, -0.00, +0.76 deg — and absolute
    turns would make the wrap look like a dip.)"""
    g = out.root_position[:, [0, 2]]
    h, _ = heading_split(out.rotations[:, 0])
    dist = np.linalg.norm(np.roll(g, -1, axis=0) - g, axis=1)
    turn = np.degrees(np.angle(np.exp(1j * (np.roll(h, -1) - h))))
    return dist, turn


def _assert_ordinary_wrap(dist: np.ndarray, turn: np.ndarray) -> None:
    """The wrap step (index -1) is the step its two neighbours give (their mean) within 1 cm
    and 1 deg, and no rougher in that sense than the motion's roughest other step.

    (Against the neighbours' mean, not the median of a few steps around it: along the
    figure-8 the turn rate sweeps through extremes, e.g. -1.8, -4.0, [-4.5], -3.7, -2.6
    deg, where a median is a poor guess of the next step; and not against the whole
    motion's median: the path's curvature changes along it.)"""
    for x, tol in ((dist, 0.01), (turn, 1.0)):
        rough = np.abs(x - 0.5 * (np.roll(x, 1) + np.roll(x, -1)))  # cyclic: wrap at -1
        assert rough[-1] <= tol, x[[-3, -2, -1, 0, 1]]
        assert rough[-1] <= rough[:-1].max(), (rough[-1], rough[:-1].max())


@pytest.fixture(scope="module")
def loops(walk8):
    motion, pyr = walk8
    pts = figure_eight(2.0).tolist()
    return [_run(pyr, motion, seed, length=LENGTH, loop=True, path=pts, path_mode="spline")
            for seed in SEEDS]


def test_loop_on_closed_figure_eight_wraps_with_an_ordinary_step(loops):
    for r, warnings in loops:
        dist, turn = _steps(r["motion"])
        assert r["motion"].n_frames == LENGTH  # the user's length, kept
        assert not warnings
        info = r["report"]["path"]
        assert info["laps"] == 1 and 0.75 <= info["pace"] <= 1.25
        _assert_ordinary_wrap(dist, turn)


def test_loop_on_closed_figure_eight_stays_on_the_path_with_planted_feet(loops, skate_in):
    curve = PathCurve.from_points(figure_eight(2.0), mode="spline")
    for r, _ in loops:
        d, _ = curve.closest(r["motion"].root_position[:, [0, 2]])
        assert d.mean() <= 0.10, d.mean()
        assert _skate_ratio(r["motion"], skate_in) <= 1.1


def test_open_path_root_stays_on_the_path(walk8, skate_in):
    """An open S-curve (8 m), no loop: before, the root was 6.8 cm from it (mean) and the
    toe-skate ratio 1.24 (seed 0)."""
    motion, pyr = walk8
    u = np.linspace(0.0, 1.0, 9)
    pts = np.stack([1.5 * np.sin(2 * np.pi * u), 8.0 * u], axis=1)
    curve = PathCurve.from_points(pts, mode="spline")
    r, warnings = _run(pyr, motion, 0, length=150, path=pts.tolist(), path_mode="spline")
    d, _ = curve.closest(r["motion"].root_position[:, [0, 2]])
    assert d.mean() <= 0.10, d.mean()
    assert r["report"]["path"]["pace"] == 1.0  # open paths are not paced
    assert _skate_ratio(r["motion"], skate_in) <= 1.1


def test_loop_on_a_path_it_cannot_follow_warns(walk8):
    motion, pyr = walk8
    # 42.7 m: the loop travels ~28 m, so one lap needs its stride scaled by ~1.5
    r, warnings = _run(pyr, motion, 0, length=LENGTH, loop=True,
                       path=figure_eight(3.5).tolist(), path_mode="spline")
    pace = r["report"]["path"]["pace"]
    assert pace > 1.25
    assert len(warnings) == 1 and "stride scaled by" in warnings[0] and "beyond ±25%" in warnings[0]
    # an open path cannot close a loop
    open_pts = figure_eight(2.0)[:40].tolist()
    _, warnings = _run(pyr, motion, 0, length=200, loop=True, path=open_pts)
    assert any("loop on an open path" in w for w in warnings)


def test_loop_exported_at_the_source_rate_wraps_with_an_ordinary_step(walk8):
    """At the file's 120 fps (the default output rate) the loop is resampled as one: before,
    the wrap stayed one 30 fps step (5.4 cm, 1.6 deg against a 1.2 cm, 0.37 deg median)."""
    motion, pyr = walk8
    ctx = seeded_context(0)
    r = synth(pyr, motion, seed=0, ctx=ctx, length=LENGTH, loop=True,
              path=figure_eight(2.0).tolist(), path_mode="spline")
    out = r["motion"]
    assert out.rate == 120.0 and out.n_frames == 4 * LENGTH  # the same duration, as a loop
    dist, turn = _steps(out)
    _assert_ordinary_wrap(dist, turn)
