"""Variation clips: DOF conversion, cycle cutting, the clips stage, similar-input selection."""

from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.codecs import decode, digest_encoded, encode
from mocapflow.stages.motion.datatypes import Strokes
from mocapflow.stages.motion.kinematics import euler_continuity, euler_to_quat, forward_kinematics
from mocapflow.stages.motion.simulate.motion import procedural_walk
from mocapflow.stages.variation.clips import (
    ClipError,
    Clips,
    autocorrelation_period,
    clips,
    clips_from_motions,
    clips_to_motions,
    clips_to_strokes,
    cut_cycles,
    dofs_to_motion,
    heel_strikes,
    likelihood_threshold,
    make_clips,
    motion_to_dofs,
    period_cuts,
    select_similar,
)

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"


def _positions(m):
    return forward_kinematics(m.skeleton, m.rotations, m.root_position)[0]


@pytest.fixture(scope="module")
def walk():
    return procedural_walk(480, rate=60.0, seed=3, variation=0.05)


def test_motion_dofs_round_trip_and_constants(walk):
    dofs, names, psi, pos = motion_to_dofs(walk)
    assert dofs.shape == (480, len(names)) and len(set(names)) == len(names)
    back = dofs_to_motion(dofs, names, walk.skeleton, rate=60.0, origin=[psi[0], *pos[0]])
    assert np.abs(_positions(back) - _positions(walk)).max() < 1e-9
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
    from mocapflow.stages.motion.kinematics import quat_multiply, quat_rotate

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
    from mocapflow.stages.motion.kinematics import quat_angle, quat_to_euler

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
    assert np.abs(_positions(m1) - _positions(walk)[70:140]).max() < 1e-9


def test_heel_strikes_and_cycles_match_ground_truth(walk):
    events = np.array(walk.attrs["gait_events"]["left"]["heel_strike"])
    pos = _positions(walk)
    hs = heel_strikes(pos, walk.skeleton.index("LeftFoot"), walk.rate) / walk.rate
    inside = events[(events > 0.1) & (events < 7.9)]
    # every true heel strike found within 3 frames (0.05 s), nothing spurious
    assert len(hs) == len(inside)
    assert np.abs(hs - inside).max() < 0.05
    cycles, rep = cut_cycles(walk)
    assert rep["method"] == "feet" and len(cycles) >= 5
    periods = np.array(walk.attrs["cycle_periods"])
    assert np.median([b - a for a, b in cycles]) / 60.0 == pytest.approx(
        np.median(periods), rel=0.1
    )


def test_period_cutter_on_generic_signal():
    t = np.arange(400)
    x = np.stack([np.sin(2 * np.pi * t / 40), np.cos(2 * np.pi * t / 40) ** 3], axis=1)
    assert autocorrelation_period(x) == 40
    cuts = period_cuts(x, 40)
    assert np.all(np.abs(np.diff(cuts) - 40) <= 1) and len(cuts) >= 9
    cycles, rep = cut_cycles(dofs=x, rate=40.0, method="period")
    assert rep["method"] == "period" and len(cycles) >= 8
    assert autocorrelation_period(np.random.default_rng(0).standard_normal((5, 2))) == 0


def test_clips_stage_cuts_one_take_and_keeps_files_whole(walk):
    ctx = Context()
    out = clips([walk], ctx=ctx)
    c, rep = out["clips"], out["report"]
    assert c.cyclic and c.n_clips >= 5 and rep["cut"]["method"] == "feet"
    assert all(50 <= n <= 85 for n in c.lengths)
    two = clips([walk, walk.replace(attrs={"source_file": "b.bvh"})], ctx=Context())["clips"]
    assert two.n_clips == 2 and not two.cyclic
    few = clips([walk], max_clips=3, ctx=Context())
    assert few["clips"].n_clips == 3 and len(few["report"]["dropped_atypical"]) >= 2


def test_clips_stage_errors_name_the_part(walk):
    other = procedural_walk(100, rate=30.0, seed=2)
    with pytest.raises(ClipError, match="resample"):
        clips([walk, other.replace(attrs={"source_file": "slow.bvh"})], ctx=Context())
    sk = walk.skeleton
    bad = walk.replace(skeleton=sk.__class__(
        names=[n + "_x" for n in sk.names], parents=sk.parents, offsets=sk.offsets,
        channels=sk.channels, end_parents=sk.end_parents, end_offsets=sk.end_offsets,
    ), attrs={"source_file": "odd.bvh"})
    with pytest.raises(ClipError, match="odd.bvh"):
        clips([walk, bad], ctx=Context())
    with pytest.raises(ClipError, match="no input"):
        clips([], ctx=Context())
    with pytest.raises(ClipError, match="non-finite"):
        make_clips([np.array([[0.0, np.nan], [1.0, 2.0]])], ["a", "b"], rate=1.0)
    # a short take with no cycle: used whole, with a warning
    ctx = Context()
    short = clips([procedural_walk(30, rate=60.0)], ctx=ctx)["clips"]
    assert short.n_clips == 1 and any("whole take" in w for w in ctx.warnings)


def test_strokes_clips_round_trip():
    rng = np.random.default_rng(0)
    ss = [Strokes(points=np.cumsum(rng.normal(size=(50 + i, 2)), 0), stroke_starts=[0],
                  rate=200.0, attrs={"letter": "a", "example": i}) for i in range(3)]
    out = clips(ss, letter="a", ctx=Context())["clips"]
    assert out.kind == "strokes" and out.n_clips == 3 and out.labels == ["x", "y"]
    for s, back in zip(ss, clips_to_strokes(out)):
        np.testing.assert_array_equal(back.points, s.points)
    with pytest.raises(ClipError, match="letter 'b'"):
        clips(ss, letter="b", ctx=Context())


@pytest.mark.skipif(not (DATA / "strokes").is_dir(), reason="shared data absent")
def test_uci_letter_a_gives_five_clips():
    from mocapflow.stages.motion.formats.strokes import read_uci_chartraj

    ss = read_uci_chartraj(DATA / "strokes" / "uci_chartraj_mv_subset.csv", letter="a")
    c = clips(ss, ctx=Context())["clips"]
    assert c.n_clips == 5 and sorted(c.lengths) == [136, 138, 138, 139, 143]


@pytest.mark.skipif(not (DATA / "bvh").is_dir(), reason="shared data absent")
def test_shared_walk_take_cuts_into_at_least_four_cycles():
    from mocapflow.stages.motion.formats.bvh import read_bvh
    from mocapflow.stages.motion.kinematics import resample_motion

    m = resample_motion(read_bvh(DATA / "bvh" / "pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh"), 60)
    c = clips(m, ctx=Context())["clips"]
    # the figure-8 walk: 8 full left-foot cycles of about 1 s
    assert c.n_clips >= 4 and c.cyclic
    assert all(50 <= n <= 70 for n in c.lengths)


def _cycle(T, D, gain, warp, rng):
    u = np.arange(T) / T
    s = u + warp * np.sin(2 * np.pi * u + rng.uniform(0, 6)) / (2 * np.pi)
    ph = np.linspace(0, np.pi, D, endpoint=False)
    return gain * np.sin(2 * np.pi * s[:, None] + ph)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_similar_input_selection_removes_the_outlier_first(seed):
    rng = np.random.default_rng(seed)
    D = 3
    names = [f"d{i}" for i in range(D)]

    def good():
        return (_cycle(40, D, 1 + 0.05 * rng.standard_normal(D), 0.1, rng)
                + 0.02 * rng.standard_normal((40, D)))

    trusted = make_clips([good() for _ in range(8)], names, rate=40.0, cyclic=True)
    thr = likelihood_threshold(trusted, splits=6, k=8)
    assert np.isfinite(thr)
    assert likelihood_threshold(trusted, splits=6, k=8, percentile=50.0) > thr
    odd = 0.5 * _cycle(40, D, 1.0, 0.0, rng)[:, ::-1] + 0.8  # other shape and level
    labels = [f"g{i}" for i in range(7)] + ["odd"]
    cand = make_clips([good() for _ in range(7)] + [odd], names, rate=40.0, cyclic=True,
                      names=labels)
    kept, removed = select_similar(cand, thr, k=8)
    assert removed and removed[0]["name"] == "odd" and removed[0]["log_likelihood"] < thr
    assert "odd" not in kept.names and len(kept.names) >= 4
    if seed == 1:  # this set: only the outlier goes
        assert kept.names == labels[:7]
