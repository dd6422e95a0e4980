"""Constrained multi-resolution texture synthesis (Moradoff 2002, chapter 3)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import uniform_filter1d

from mocapflow.pipeline import Context
from mocapflow.pipeline.codecs import decode, encode, find_exporter
from mocapflow.pipeline.config import load_config
from mocapflow.stages.metrics import quality as M
from mocapflow.stages.motion.contacts import contact_thresholds, toe_indices
from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.motion.kinematics import forward_kinematics, motion_positions
from mocapflow.stages.motion.rotations import heading_split, quat_angle, quat_rotate
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.texture.assemble import assemble_motion
from mocapflow.stages.texture.graph import graph_path
from mocapflow.stages.texture.neighbourhood import level_view
from mocapflow.stages.texture.pyramid import build_pyramid, level_positions, root_features
from mocapflow.stages.texture.root import (
    PathCurve,
    apply_foot_ik,
    figure_eight,
    foot_corrections,
    leg_chains,
    two_bone_ik,
)
from mocapflow.stages.texture.search import Gap, LevelSearch, SearchParams, ahead_usage
from mocapflow.stages.texture.stickfigure import StickStrip, cycle_period, stickfigure
from mocapflow.stages.texture.synth import ConstraintError, UnreachableGapError, synth

RATE = 30.0


@pytest.fixture(scope="module")
def walk() -> Motion:
    return procedural_walk(300, rate=RATE, seed=3, variation=0.08)


@pytest.fixture(scope="module")
def pyr(walk):
    return build_pyramid(walk, levels=3)


def _local_pose(motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """Heading-free local rotations and root-relative FK positions."""
    rot = motion.rotations.copy()
    _, rot[:, 0] = heading_split(rot[:, 0])
    pos = level_positions(motion.skeleton, rot, motion.root_position[:, 1], motion.translations)
    return rot, pos


# --------------------------------------------------------------------------- constraints


def test_constrained_frames_exact_before_and_within_tolerance_after_smoothing(run_synth, pyr, walk):
    cons = [[10, 5], [150, 200], [40, 333], [290, 397]]
    r = run_synth(pyr, walk, length=400, constraints=cons)
    src = r["source_index"]
    assert src.shape == (400,) and src.dtype == np.int64
    for i, j in cons:
        assert src[j] == i  # exact before smoothing
    assert r["report"]["n_seams"] > 0 and any(k > 0 for k in r["report"]["smoothing"]["widening"])
    rot_o, pos_o = _local_pose(r["motion"])
    rot_i, pos_i = _local_pose(walk)
    i = np.array([c[0] for c in cons])
    j = np.array([c[1] for c in cons])
    angle = np.degrees(quat_angle(rot_o[j], rot_i[i]))
    assert angle.max() <= 1.0
    assert np.linalg.norm(pos_o[j] - pos_i[i], axis=-1).max() <= 0.01
    assert r["report"]["constraint_max_angle_deg"] <= 1.0
    assert r["report"]["constraint_max_fk_m"] <= 0.01
    # the first constraint is placed where its input frame was in the world
    np.testing.assert_allclose(r["motion"].root_position[5], walk.root_position[10], atol=1e-9)


def test_any_output_length_and_the_output_is_a_motion_on_the_input_skeleton(run_synth, pyr, walk):
    r = run_synth(pyr, walk, length=333)
    m = r["motion"]
    assert m.n_frames == 333 and m.skeleton is walk.skeleton and m.rate == RATE
    assert r["source_index"].min() >= 0 and r["source_index"].max() < walk.n_frames
    norms = np.linalg.norm(m.rotations, axis=-1)
    np.testing.assert_allclose(norms, 1.0, atol=1e-9)
    assert r["report"]["meetings"] == {}  # no constraint: no two-sided gap


def test_seeds_give_different_variants_and_the_same_seed_the_same(run_synth, pyr, walk):
    a = run_synth(pyr, walk, seed=1, length=360)["source_index"]
    b = run_synth(pyr, walk, seed=1, length=360)["source_index"]
    c = run_synth(pyr, walk, seed=2, length=360)["source_index"]
    np.testing.assert_array_equal(a, b)
    assert np.mean(a != c) > 0.3


def test_adaptive_smoothing_removes_the_jerk_of_bad_seams(pyr, walk):
    # random 30-frame chunks: every transition is a real discontinuity
    starts = np.random.default_rng(0).integers(0, 270, size=8)
    src = (starts[:, None] + np.arange(30)).ravel()
    seams = M.seams_from_source(src)
    mask = M.seam_mask(src.size, seams)
    jerk_in = M.jerk_p99(motion_positions(walk), RATE)
    raw, _ = assemble_motion(pyr, walk, src, smoothing=False, foot_ik=False)
    smooth, rep = assemble_motion(pyr, walk, src, foot_ik=False)
    assert M.jerk_p99(motion_positions(raw), RATE, mask=mask) / jerk_in > 5.0
    assert M.jerk_p99(motion_positions(smooth), RATE, mask=mask) / jerk_in < 1.3
    sm = rep["smoothing"]
    assert all(sm["passed"]) and min(sm["widening"]) >= 1  # each seam needed widening
    # frames far from every seam are untouched
    far = ~M.seam_mask(src.size, seams, radius=20)
    assert far.any()
    np.testing.assert_allclose(smooth.rotations[far, 1:], raw.rotations[far, 1:], atol=1e-12)


def test_synthesized_seams_stay_below_the_jerk_target(run_synth, pyr, walk):
    r = run_synth(pyr, walk, length=400, constraints=[[20, 10], [200, 300]])
    seams = M.seams_from_source(r["source_index"])
    assert seams.size
    mask = M.seam_mask(400, seams)
    jerk_in = M.jerk_p99(motion_positions(walk), RATE)
    raw, _ = assemble_motion(pyr, walk, r["source_index"], smoothing=False)
    jerk_raw = M.jerk_p99(motion_positions(raw), RATE, mask=mask) / jerk_in
    jerk_out = M.jerk_p99(motion_positions(r["motion"]), RATE, mask=mask) / jerk_in
    assert jerk_out < 1.3 and jerk_out < jerk_raw
    assert np.mean(r["report"]["smoothing"]["passed"]) >= 0.9


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        (dict(constraints=[[300, 10]]), r"input frame 300 is outside the input \(frames 0-299\)"),
        (dict(constraints=[[-1, 10]]), "input frame -1 is outside"),
        (dict(constraints=[[10, 400]]), r"output \(400 frames\) is shorter than the constraints"),
        (dict(constraints=[[10, 8], [50, 10]]), "closer than the coarsest level can separate"),
        (dict(constraints=[[10, 8], [50, 8]]), "two constraints on output frame 8"),
        (dict(constraints=[[10]]), r"expected \[input_frame, output_frame\]"),
    ],
)
def test_bad_constraints_raise_clear_errors(run_synth, pyr, walk, kw, match):
    with pytest.raises(ConstraintError, match=match):
        run_synth(pyr, walk, length=400, **kw)


def test_pyramid_mismatches_raise(run_synth, pyr, walk):
    other = procedural_walk(200, rate=RATE, seed=1)
    with pytest.raises(ValueError, match="pyramid has 300 frames but the motion has 200"):
        run_synth(pyr, other, length=100)
    with pytest.raises(ValueError, match="filter_size 6 differs"):
        run_synth(pyr, walk, length=100, filter_size=6)
    with pytest.raises(ValueError, match="levels must be in 1-3"):
        run_synth(pyr, walk, length=100, levels=4)


# --------------------------------------------------------------------------- variety


@pytest.fixture(scope="module")
def varied() -> Motion:
    """A 10-cycle walk whose cycles differ like a capture's: no jump is near-perfect."""
    return procedural_walk(300, rate=RATE, seed=3, variation=0.3)


def test_default_output_is_a_new_arrangement_not_a_copy(run_synth, varied):
    """2× the walk: short verbatim runs, the whole input used, smooth seams.

    With the previous draw window (a fixed number of cost units around the
    natural successor, which always costs 0) this input was replayed in one
    300-frame run.
    """
    walk, pyr = varied, build_pyramid(varied, levels=3)
    F, L = walk.n_frames, 2 * walk.n_frames
    jerk_in = M.jerk_p99(motion_positions(walk), RATE)
    f_in = M.rotation_features(walk, heading_free=True)
    for seed in (0, 1):
        r = run_synth(pyr, walk, seed=seed, length=L)
        src = r["source_index"]
        # the input is never replayed for more than ~1/3 of its length (max_run 0.3)
        assert M.longest_verbatim_run(src) <= 0.35 * F
        seams = M.seams_from_source(src)
        assert seams.size >= 10
        assert M.coverage(M.rotation_features(r["motion"], heading_free=True), f_in) >= 0.95
        mask = M.seam_mask(L, seams)
        assert M.jerk_p99(motion_positions(r["motion"]), RATE, mask=mask) / jerk_in <= 1.3
    # without the variety knobs the synthesis falls back to a near-verbatim copy
    r0 = run_synth(pyr, walk, seed=0, length=L, variety=0.0, max_run=0.0)
    assert M.longest_verbatim_run(r0["source_index"]) >= 0.9 * F


def test_max_run_bounds_the_longest_verbatim_run(run_synth, pyr, walk):
    for max_run, bound in ((0.15, 0.2), (0.3, 0.35)):
        r = run_synth(pyr, walk, seed=2, length=600, max_run=max_run)
        assert M.longest_verbatim_run(r["source_index"]) <= bound * walk.n_frames


def _coarse_search(pyr, params, n_out=None, seed=0):
    views = [level_view(pyr.levels[k], 2.0**k) for k in range(pyr.n_levels)]
    top = pyr.n_levels - 1
    n_out = n_out or [-(-600 // 2**k) for k in range(pyr.n_levels)]
    return LevelSearch(views, top, n_out, False, None, params, np.random.default_rng(seed))


def test_variety_is_a_quantile_of_the_inputs_own_jump_costs(pyr):
    s = _coarse_search(pyr, SearchParams())
    jc = s.jump_costs()
    n, S = s.view.n, s.p.slots
    assert jc.shape == (n,)
    finite = jc[np.isfinite(jc)]
    assert finite.size >= n - 2 and finite.min() > 0  # no jump is as good as continuing
    # ground truth: the per-node search of a verbatim left context, node a = 30
    a, t = 30, 10
    src = np.full(s.n, -1)
    src[t - S : t] = np.arange(a - S + 1, a + 1)
    c = s.cost(src, t, np.arange(n))
    far = np.abs(np.arange(n) - (a + 1)) >= S
    assert jc[a] == pytest.approx(np.min(np.where(far, c, np.inf)), rel=1e-9)
    assert c[a + 1] == pytest.approx(0.0, abs=1e-12)  # the natural successor costs 0
    taus = []
    for q in (0.1, 0.3, 0.7):
        sq = _coarse_search(pyr, SearchParams(variety=q))
        taus.append(sq.jump_threshold())
        assert taus[-1] == pytest.approx(np.quantile(finite, q), rel=1e-9)
    assert taus[0] < taus[1] < taus[2]
    assert _coarse_search(pyr, SearchParams(variety=0.0)).jump_threshold() == 0.0


def test_right_front_forced_jumps_keep_the_output_playing_forwards(pyr):
    """A start gap grows leftwards from its anchor; runs hit max_run and must jump."""
    s = _coarse_search(pyr, SearchParams(max_run=0.2))
    n = s.n
    src = np.full(n, -1)
    ranked = np.full((n, 3), -1)
    src[n - 1] = s.view.n - 1  # anchor: the input's last node at the output's end
    ranked[n - 1, 0] = src[n - 1]
    s.fill_gap(src, ranked, Gap(-1, n - 1, ("start", 0), left=False), None)
    assert (src >= 0).all() and (src < s.view.n).all()
    d = np.diff(src)
    assert not np.any((d <= 0) & (d >= -s.p.slots))  # never frozen or played backwards
    runs = np.diff(np.flatnonzero(np.r_[True, d != 1, True]))
    assert runs.max() <= s.max_run_nodes + 1
    assert (d != 1).sum() >= n // (s.max_run_nodes + 1)  # the forced jumps happened


def test_ahead_usage_counts_the_material_a_candidate_plays_next():
    counts = np.array([0, 0, 3, 3, 0, 0, 0, 1], dtype=float)
    fw = ahead_usage(counts, 3, 1)
    np.testing.assert_allclose(fw[[0, 1, 4, 6, 7]], [1.0, 2.0, 0.0, 0.5, 1.0])
    bw = ahead_usage(counts, 3, -1)
    np.testing.assert_allclose(bw[[0, 2, 4, 7]], [0.0, 1.0, 2.0, 1 / 3])


# --------------------------------------------------------------------------- feet


def test_two_bone_ik_reaches_the_target_and_keeps_the_bones():
    rng = np.random.default_rng(0)
    n = 50
    hip = rng.normal(size=(n, 3)) * 0.1 + [0, 0.9, 0]
    knee = hip + [0, -0.42, 0.15] + rng.normal(size=(n, 3)) * 0.03  # bent: targets in reach
    ankle = knee + [0, -0.38, -0.15] + rng.normal(size=(n, 3)) * 0.03
    target = ankle + np.c_[rng.uniform(-0.1, 0.1, n), np.zeros(n), rng.uniform(-0.1, 0.1, n)]
    r_hip, r_knee = two_bone_ik(hip, knee, ankle, target)
    knee2 = hip + quat_rotate(r_hip, knee - hip)
    ankle2 = knee2 + quat_rotate(r_hip, quat_rotate(r_knee, ankle - knee))
    np.testing.assert_allclose(ankle2, target, atol=1e-9)
    np.testing.assert_allclose(
        np.linalg.norm(knee2 - hip, axis=1), np.linalg.norm(knee - hip, axis=1), atol=1e-12
    )
    # out of reach: the leg stretches towards the target and stops at full length
    far = hip + (target - hip) * 3.0
    r_hip, r_knee = two_bone_ik(hip, knee, ankle, far)
    knee3 = hip + quat_rotate(r_hip, knee - hip)
    ankle3 = knee3 + quat_rotate(r_hip, quat_rotate(r_knee, ankle - knee))
    reach = np.linalg.norm(knee - hip, axis=1) + np.linalg.norm(ankle - knee, axis=1)
    np.testing.assert_allclose(np.linalg.norm(ankle3 - hip, axis=1), reach, atol=1e-5)
    d_want = (far - hip) / np.linalg.norm(far - hip, axis=1, keepdims=True)
    d_got = (ankle3 - hip) / np.linalg.norm(ankle3 - hip, axis=1, keepdims=True)
    np.testing.assert_allclose(d_got, d_want, atol=1e-9)


def test_apply_foot_ik_moves_the_ankles_and_keeps_the_feet(walk):
    m = walk
    toes = toe_indices(m.skeleton)
    chains = leg_chains(m.skeleton, toes)
    assert [m.skeleton.names[j] for j in chains[0]] == ["LeftUpLeg", "LeftLeg", "LeftFoot"]
    offsets = np.zeros((m.n_frames, len(toes), 2))
    offsets[:, 0] = np.random.default_rng(1).uniform(-0.05, 0.05, (m.n_frames, 2))
    rot = apply_foot_ik(m.skeleton, m.rotations, m.root_position, chains, offsets)
    p0, g0 = forward_kinematics(m.skeleton, m.rotations, m.root_position)
    p1, g1 = forward_kinematics(m.skeleton, rot, m.root_position)
    h, k, a = chains[0]
    target = p0[:, a] + np.c_[offsets[:, 0, 0], np.zeros(m.n_frames), offsets[:, 0, 1]]
    leg = np.linalg.norm(p0[:, k] - p0[:, h], axis=1) + np.linalg.norm(p0[:, a] - p0[:, k], axis=1)
    ok = np.linalg.norm(target - p0[:, h], axis=1) < leg - 1e-4  # a straight leg cannot grow
    assert ok.mean() > 0.5
    np.testing.assert_allclose(p1[ok, a], target[ok], atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(p1[~ok, a] - p1[~ok, h], axis=1), leg[~ok], atol=1e-5)
    np.testing.assert_allclose(p1[:, toes[0]] - p1[:, a], p0[:, toes[0]] - p0[:, a], atol=1e-7)
    assert np.degrees(quat_angle(g1[:, a], g0[:, a])).max() < 1e-5  # foot orientation kept
    np.testing.assert_allclose(p1[:, chains[1][2]], p0[:, chains[1][2]], atol=1e-12)


def test_apply_foot_ik_both_legs_equal_one_leg_at_a_time(walk):
    # the legs share one forward kinematics; each leg must come out as when moved alone
    m = walk
    chains = leg_chains(m.skeleton, toe_indices(m.skeleton))
    offsets = np.random.default_rng(2).uniform(-0.05, 0.05, (m.n_frames, 2, 2))
    offsets[::3, 0] = 0.0  # legs moving in different frames
    both = apply_foot_ik(m.skeleton, m.rotations, m.root_position, chains, offsets)
    for k in range(2):
        alone = np.zeros_like(offsets)
        alone[:, k] = offsets[:, k]
        one = apply_foot_ik(m.skeleton, m.rotations, m.root_position, chains, alone)
        np.testing.assert_array_equal(both[:, list(chains[k])], one[:, list(chains[k])])
    # the same chain twice: the second move starts from the first (no shared kinematics)
    twice = apply_foot_ik(m.skeleton, m.rotations, m.root_position, [chains[0]] * 2,
                          np.stack([offsets[:, 0], offsets[:, 0]], axis=1))
    p2, _ = forward_kinematics(m.skeleton, twice, m.root_position)
    p0, _ = forward_kinematics(m.skeleton, m.rotations, m.root_position)
    moved = np.linalg.norm(p2[:, chains[0][2]] - p0[:, chains[0][2]], axis=1)
    want = 2 * np.linalg.norm(offsets[:, 0], axis=1)
    assert np.median(moved / np.maximum(want, 1e-9)) > 0.9


def test_foot_corrections_stop_the_slide_of_stance_toes():
    L = 60
    contact = np.zeros((L, 1), dtype=bool)
    contact[20:36] = True  # a 16-frame stance
    step = np.zeros((L, 1, 2))
    step[:, 0, 0] = 0.001  # the input's own toe roll: 1 mm per frame
    x = np.cumsum(step, axis=0)  # verbatim: the toe already moves as in the input
    np.testing.assert_allclose(foot_corrections(x, step, contact), 0.0, atol=1e-12)
    u = np.clip((np.arange(L) - 25) / 6, 0, 1)
    slide = x.copy()
    slide[:, 0, 0] += 0.03 * (3 * u**2 - 2 * u**3)  # a smoothed seam slides the toe 3 cm

    def residual(e):
        return np.abs(np.diff(slide + e, axis=0)[20:35, 0, 0] - 0.001).sum()

    assert residual(0.0) == pytest.approx(0.03)
    e = foot_corrections(slide, step, contact)
    assert residual(e) < 0.5 * residual(0.0)
    assert np.abs(e[50:]).max() < 0.1 * np.abs(e).max()  # fades out in the swing phase
    # a smaller decay pins harder (and changes the legs more)
    assert residual(foot_corrections(slide, step, contact, decay=1e-3)) < 0.3 * 0.03
    fixed = np.zeros(L, dtype=bool)
    fixed[28] = True
    assert abs(foot_corrections(slide, step, contact, fixed=fixed)[28]).max() < 1e-5


def test_foot_ik_removes_the_skate_the_seams_bring(run_synth, pyr, walk):
    pos_in = motion_positions(walk)
    toes = toe_indices(walk.skeleton)
    h, s = contact_thresholds(pos_in, toes, RATE)
    r = run_synth(pyr, walk, seed=0, length=600)
    raw, _ = assemble_motion(pyr, walk, r["source_index"], foot_ik=False)

    def skate(m):
        pos = motion_positions(m)
        return M.foot_skate(pos, toes, RATE, height_threshold=h, speed_threshold=s)

    sk_in, sk_raw, sk_ik = skate(walk), skate(raw), skate(r["motion"])
    assert sk_ik < sk_raw and sk_ik - sk_in < 0.5 * (sk_raw - sk_in)
    assert sk_ik < 0.05  # m/s on contact frames
    assert r["report"]["foot_ik_max_m"] > 0


# --------------------------------------------------------------------------- graph path


def test_graph_path_fills_gaps_exactly_and_keeps_constraints(run_synth, pyr, walk):
    cons = [[10, 5], [150, 200], [60, 380]]
    r = run_synth(pyr, walk, length=400, method="graph_path", constraints=cons)
    for i, j in cons:
        assert r["source_index"][j] == i
    assert r["report"]["constraint_max_angle_deg"] <= 1.0


def test_graph_path_unreachable_gap_names_the_gap(run_synth, pyr, walk):
    # two output frames 12 apart but 200 input frames apart, and almost no jump edges
    gap = r"gap between output frame ~0 and output frame ~12"
    with pytest.raises(UnreachableGapError, match=gap):
        run_synth(
            pyr,
            walk,
            length=100,
            method="graph_path",
            constraints=[[0, 0], [200, 12]],
            graph_threshold=0.0,
        )


def test_graph_path_dfs_respects_length_ends_and_edges():
    rng = np.random.default_rng(0)
    n = 12
    E = np.full((n, n), np.inf)
    E[np.arange(n - 1), np.arange(1, n)] = 0.0
    E[9, 2] = 0.5  # one jump back: the loop 2 … 9 → 2 has 8 edges
    p = graph_path(E, 16, rng, start=0, end=8)  # 8 straight + one loop
    assert p.size == 17 and p[0] == 0 and p[-1] == 8
    assert np.isfinite(E[p[:-1], p[1:]]).all()
    assert list(p).count(2) == 2
    for steps in (3, 12):  # too short; no loop of 4 edges
        with pytest.raises(UnreachableGapError, match="my gap: unreachable"):
            graph_path(E, steps, rng, start=0, end=8, where="my gap")
    free = graph_path(E, 20, rng, start=None, end=None)  # free ends: any walk of 20 edges
    assert free.size == 21 and np.isfinite(E[free[:-1], free[1:]]).all()


# --------------------------------------------------------------------------- loop, path


def _wrap_jerk(m: Motion, walk: Motion) -> float:
    """Jerk across the loop's wrap (relative to the input's p99).

    The loop is played twice, the second copy placed where the first one's last
    step leads (heading and position continued).
    """
    heading, _ = heading_split(m.rotations[:, 0])
    yaw, _, _ = root_features(m.root_position, heading)
    turn = heading[-1] + yaw[-1] - heading[0]
    c, s = np.cos(turn), np.sin(turn)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    step = m.root_position[-1] - m.root_position[-2]
    step[1] = 0.0
    p1 = motion_positions(m)
    p2 = (p1 - m.root_position[0] * [1, 0, 1]) @ R.T + (m.root_position[-1] + step) * [1, 0, 1]
    both = np.concatenate([p1[-12:], p2[:12]])
    jerk = M.jerk_per_frame(both, RATE)[7:16]  # frames around the wrap
    return float(np.nanmax(jerk) / M.jerk_p99(motion_positions(walk), RATE))


def test_loop_last_to_first_seam_passes_the_smoothing_test(run_synth, pyr, walk):
    L = 360
    # constraints on both sides of the wrap force a transition into the 5 frames
    # between them: 66 → … must reach 50 (a jump back by ~20 frames)
    r = run_synth(pyr, walk, seed=0, length=L, loop=True, constraints=[[50, 2], [66, L - 4]])
    assert r["source_index"][2] == 50 and r["source_index"][L - 4] == 66
    seams = r["report"]["seams"]
    near_wrap = [t for t in seams if t >= L - 3 or t <= 2]
    assert near_wrap  # this seed puts a transition at the wrap
    sm = r["report"]["smoothing"]
    assert all(sm["passed"][seams.index(t)] for t in near_wrap)
    assert _wrap_jerk(r["motion"], walk) <= 1.3
    raw, _ = assemble_motion(pyr, walk, r["source_index"], loop=True, smoothing=False)
    assert _wrap_jerk(raw, walk) > 2.0  # without smoothing the wrap is a visible pop


def test_figure_eight_path_error_and_heading(run_synth, pyr, walk):
    pts = figure_eight(2.0)
    curve = PathCurve.from_points(pts, mode="spline")
    r = run_synth(pyr, walk, length=540, path=pts.tolist(), path_mode="spline")
    ground = r["motion"].root_position[:, [0, 2]]
    d, s = curve.closest(ground)
    assert d.mean() <= 0.05 * curve.length
    inner = slice(15, -15)
    heading, _ = heading_split(r["motion"].rotations[:, 0])
    tangent = curve.tangent_angle(s)
    err = np.degrees(np.abs(np.angle(np.exp(1j * (heading - tangent)))))[inner]
    assert err.mean() <= 10.0
    # travel direction (1 s window) along the tangent too
    v = np.gradient(ground, axis=0)
    v = uniform_filter1d(v, 30, axis=0)
    travel = np.arctan2(v[:, 0], v[:, 1])
    err_t = np.degrees(np.abs(np.angle(np.exp(1j * (travel - tangent)))))[inner]
    assert err_t.mean() <= 10.0
    assert r["report"]["path"]["path_length"] == pytest.approx(curve.length)


def test_bad_path_raises(run_synth, pyr, walk):
    with pytest.raises(ValueError, match="at least|>= 2 points"):
        run_synth(pyr, walk, length=100, path=[[0.0, 0.0]])


# --------------------------------------------------------------------------- stage


def test_stage_outputs_and_randomness_from_ctx(pyr, walk):
    ctx = Context(part="walk#seed=4", seed=4)
    out = synth(pyr, walk, length=200, seed=4, ctx=ctx)
    assert set(out) == {"motion", "source_index", "report"}
    assert out["motion"].n_frames == 200 and out["source_index"].shape == (200,)
    # step times go to the context (the engine's manifest), never into the report
    assert out["report"]["seed"] == 4 and "seconds" not in out["report"]
    assert set(ctx.timings) == {"search", "assemble"} and ctx.timings["search"] > 0
    again = synth(pyr, walk, length=200, seed=4, ctx=Context(part="walk#seed=4", seed=4))
    np.testing.assert_array_equal(out["source_index"], again["source_index"])


def test_search_params_are_exposed_under_the_papers_names():
    p = SearchParams()
    assert (p.slots, p.candidate_range, p.n_parent_matches) == (3, 4, 3)
    assert 2 <= p.k_best <= 3


# --------------------------------------------------------------------------- config, strip


def test_texture_config_wires_ingest_pyramid_synth():
    root = Path(__file__).parents[3]
    data = root / ".." / "shared" / "data"
    if not (data / "bvh" / "cmu_131_02.bvh").exists():
        pytest.skip("shared data not available")
    cfg = load_config(
        root / "configs" / "texture.yaml",
        env={"MOCAPFLOW_DATA": str(data)},
        sets=["synth.constraints=[[10, 5]]", "synth.method=graph_path"],
    )
    assert {"ingest", "pyramid", "synth"} <= set(cfg.nodes)
    synth_node = cfg.nodes["synth"]
    assert synth_node.stage == "synth" and synth_node.seeds == [0, 1, 2, 3, 4]
    for key in ("length", "constraints", "path", "loop", "levels", "filter_size", "method"):
        assert key in synth_node.params
    assert synth_node.params["constraints"] == [[10, 5]]
    assert synth_node.params["method"] == "graph_path"
    assert cfg.nodes["ingest"].stage == "ingest_bvh" and cfg.nodes["ingest"].params["rate"] == 30


def test_stickfigure_strip_and_export(tmp_path, walk):
    short = walk.replace(root_position=walk.root_position[:20], rotations=walk.rotations[:20])
    out = stickfigure(short, n_panels=4, video=True, video_step=5, ctx=Context())["strip"]
    assert isinstance(out, StickStrip) and out.frames == [0, 6, 13, 19]
    assert out.image.dtype == np.uint8 and out.image.ndim == 3 and out.image.shape[2] == 3
    assert out.image.min() < 50 and out.image.max() > 200  # dark bones on a light background
    assert out.video.shape[0] == 4
    back = decode(encode(out))
    np.testing.assert_array_equal(back.image, out.image)
    files = find_exporter("stickstrip")(out, tmp_path, "walk")
    assert [f.suffix for f in files] == [".png", ".mp4"]
    assert all(f.stat().st_size > 1000 for f in files)


def test_stickfigure_panels_show_different_phases_of_the_stride():
    # the demo's case: 600 frames at 30 fps, 10 panels; evenly spaced panels are
    # 66.6 frames apart, about two strides (32.8 frames), so they all show one phase
    walk = procedural_walk(600, rate=RATE, seed=0, variation=0.05)
    strikes = np.asarray(walk.attrs["gait_events"]["left"]["heel_strike"])
    strikes = np.r_[2 * strikes[0] - strikes[1], strikes, 2 * strikes[-1] - strikes[-2]]

    def phase_spread(frames):  # (largest circular gap between phases, distinct tenths)
        cycles = np.interp(np.asarray(frames) / RATE, strikes, np.arange(len(strikes)))
        ph = np.sort(cycles % 1.0)
        return np.diff(np.r_[ph, ph[0] + 1.0]).max(), len(set((ph * 10).astype(int)))

    period = cycle_period(motion_positions(walk))
    assert period == pytest.approx(np.mean(walk.attrs["cycle_periods"]) * RATE, rel=0.02)
    even = np.linspace(0, 599, 10).round().astype(int)
    assert phase_spread(even)[0] > 0.5  # the bug this guards against, reproduced
    frames = stickfigure(walk, n_panels=10, ctx=Context())["strip"].frames
    assert len(frames) == 10 and frames[-1] - frames[0] > 0.8 * 599  # spread over the motion
    gap, tenths = phase_spread(frames)
    assert gap < 0.2 and tenths >= 7, (frames, gap, tenths)
