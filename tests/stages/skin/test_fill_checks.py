"""The blend's checks on its members beyond their validation copies (issue 15 item 6,
:mod:`mocapflow.stages.skin.fill_checks`): members far from the others or off the
trajectory at the gap's ends, rigid-partner distances, jumps and erratic members — on
synthetic takes with known answers.  The same checks on the real shared C3Ds, through the
blend, are in ``test_fill_blend.py``."""

from __future__ import annotations

import numpy as np

import mocapflow.stages.skin.fill_blend as fb
import mocapflow.stages.skin.fill_checks as fc


def test_a_member_far_from_all_the_others_in_the_gap_is_left_out():
    """Five members of one 40-frame run: four within 1 mm of the truth, the third (a
    spline, say) 20 mm off although its validation copies scored it at 0.5 mm like the
    rest: it is flagged (20 mm > 5 x (0.5 + 0.5) mm from the others' median) and no other
    member is.  Off by 4 mm, within 5 x (0.5 + 0.5) mm, it is flagged too: the four
    others' weighted mean is known to 0.25 mm, so it lies 7 deviations from it (> 5,
    ``CONSENSUS_FACTOR``); off by 2 mm (3.6 deviations) it stays.  With only two members
    left weighted, nothing is flagged; a member already at weight 0 is not compared.  When
    the far member holds the weight (the LPSI case below), it is still the one flagged:
    with the others' blend-weighted mean as the median test's reference, the far member
    is that mean for every other member, which then looks as far off as it (the
    best-validated other was flagged); the weighted-mean test flags the member farthest
    in deviations, and the far one's are the largest."""
    rng = np.random.default_rng(3)
    L = 40
    truth = np.cumsum(rng.normal(0, 0.002, (L, 3)), 0)
    est = truth[None] + rng.uniform(-0.0005, 0.0005, (5, L, 3))
    est = est[:, :, None]  # (K, F, M=1, 3)
    runs = [(0, 0, L)]
    mse = np.full((5, 1), 0.0005**2)
    w = np.ones((5, 1))
    far = est.copy()
    far[2, :, 0] += [0.02, 0, 0]
    flagged = fc._outlying_estimates(far, runs, mse, w)
    np.testing.assert_array_equal(flagged[:, 0], [False, False, True, False, False])
    near = est.copy()
    near[2, :, 0] += [0.004, 0, 0]
    np.testing.assert_array_equal(fc._outlying_estimates(near, runs, mse, w)[:, 0],
                                  [False, False, True, False, False])
    nearer = est.copy()
    nearer[2, :, 0] += [0.002, 0, 0]
    assert not fc._outlying_estimates(nearer, runs, mse, w).any()
    two = np.array([[1.0], [0], [1], [0], [0]])
    assert not fc._outlying_estimates(far, runs, mse, two).any()
    w0 = w.copy()
    w0[2] = 0.0
    assert not fc._outlying_estimates(far, runs, mse, w0).any()
    # the LPSI case's validated errors (mm): the far member 0.04, the others 0.3-1.2, the
    # best of them 1 mm off the other way: the others' weighted mean flagged that one
    mse_lead = (np.array([[1.2], [0.45], [0.04], [0.45], [0.3]]) * 1e-3) ** 2
    w_lead = fb._blend_weights(mse_lead)
    assert w_lead[2, 0] > 100 * w_lead[[0, 1, 3, 4], 0].sum()
    far[4, :, 0] -= [0.001, 0, 0]
    flagged = fc._outlying_estimates(far, runs, mse_lead, w_lead)
    np.testing.assert_array_equal(flagged[:, 0], [False, False, True, False, False])


def _joinless_case(seed: int = 5):
    """One 40-frame run (frames 10-49) of a marker measured over 60 frames, smooth truth
    (``x (60, 1, 3)``, NaN in the run) and five members within 0.5 mm of it (``est (5, 60,
    1, 3)``, NaN outside the run)."""
    rng = np.random.default_rng(seed)
    F, a, b = 60, 10, 50
    t = np.arange(F) / 100.0
    truth = np.stack([0.1 * np.sin(2 * t), 0.05 * t, 1.0 + 0.02 * np.cos(3 * t)], 1)[:, None]
    x = truth.copy()
    x[a:b] = np.nan
    est = np.full((5, F, 1, 3), np.nan)
    est[:, a:b] = truth[None, a:b] + rng.uniform(-0.0005, 0.0005, (5, b - a, 1, 3))
    return x, truth, est, [(0, a, b)]


def test_boundary_misses_are_the_ends_off_the_carried_trajectory():
    """A member off by (1, 2, 3) mm at the run's first frame and 4 mm at its last misses
    the trajectory carried one frame on (exact on a straight line) by the larger, 4 mm; an
    end with one measured sample before it is left out; none: NaN."""
    F, a, b = 30, 10, 20
    x = np.zeros((F, 1, 3))
    x[:, 0, 0] = np.arange(F) * 0.001  # 1 mm a frame: carried on exactly
    est = np.repeat(x[None, a:b, 0], 2, axis=0)  # (2, 10, 3)
    est[1, 0] += [0.001, 0.002, 0.003]
    est[1, -1] += [0, 0, 0.004]
    x[a:b] = np.nan
    np.testing.assert_allclose(fc._boundary_misses(est, x, 0, a, b), [0, 0.004], atol=1e-12)
    x[a - 2] = np.nan  # the start has one measured sample before it: the end alone
    np.testing.assert_allclose(fc._boundary_misses(est, x, 0, a, b), [0, 0.004], atol=1e-12)
    x[b + 1] = np.nan
    assert np.isnan(fc._boundary_misses(est, x, 0, a, b)).all()


def test_end_excess_is_the_miss_beyond_twice_the_trajectory_s_own():
    """A marker accelerating 0.1 mm a frame² along x: carried on one frame, its measured
    trajectory misses its own next sample by 0.1 mm, so a member's miss at a run's end
    counts beyond 2 x 0.1 mm (``END_REFERENCE_FACTOR``).  The true trajectory (miss 0.1
    mm) has no excess; a member 5 mm off along y at the run's first frame misses by
    √(25 + 0.01) mm, an excess of that less 0.2 mm; at the last frame 3 mm off, less.  An
    end with two measured samples is left out (the start alone counts); none: NaN."""
    F, a, b = 40, 15, 25
    t = np.arange(F, dtype=float)
    x = np.zeros((F, 1, 3))
    x[:, 0, 0] = 0.5 * 1e-4 * t**2  # 0.1 mm a frame² (second difference 1e-4 m)
    est = np.repeat(x[None, a:b, 0], 2, axis=0)  # (2, 10, 3)
    est[1, 0, 1] += 0.005
    est[1, -1, 1] += 0.003
    x[a:b] = np.nan
    start = np.hypot(0.005, 1e-4) - 2e-4
    np.testing.assert_allclose(fc._end_excess(est, x, 0, a, b), [0, start], atol=1e-12)
    x[b + 2] = np.nan  # the end's samples need not be in a row: b, b + 1, b + 3 still count
    np.testing.assert_allclose(fc._end_excess(est, x, 0, a, b), [0, start], atol=1e-12)
    y = x.copy()
    y[: a - 2] = np.nan
    y[b + 2:] = np.nan  # two measured samples on each side: NaN
    assert np.isnan(fc._end_excess(est, y, 0, a, b)).all()
    y = x.copy()
    y[a - fc.END_REACH - 3: a - 2] = np.nan  # the start's third sample beyond END_REACH
    y[b + 2:] = np.nan
    assert np.isnan(fc._end_excess(est, y, 0, a, b)).all()
    x[a - 3] = x[a - 2] - [[1e-4 * (a - 2.5), 0, 0]]  # back, and an outlier behind it:
    x[a - 4, 0, 0] += 0.002  # the reference grows with it (2 mm more): no excess left
    assert fc._end_excess(est, x, 0, a, b)[1] < start - 0.002


def test_end_excess_reads_an_end_seen_every_other_frame():
    """The marker of the test above measured after the run only at every other frame (b, b +
    2, b + 4, b + 6) and not at all before it within ``END_REACH``: a straight line through
    two samples 2 frames apart, carried 2 frames on, misses a trajectory accelerating at c
    by c (2 x 4) / 2 = 0.4 mm, the reference; carried one frame back to the run's last
    frame, by c (1 x 3) / 2 = 0.15 mm, within twice that: the true trajectory has no
    excess, a member 3 mm off along y there √(9 + 0.0225) - 0.8 mm.  Read only in a row
    (as before), that end had one sample and the excess was unknown."""
    F, a, b = 40, 15, 25
    t = np.arange(F, dtype=float)
    x = np.zeros((F, 1, 3))
    x[:, 0, 0] = 0.5 * 1e-4 * t**2
    est = np.repeat(x[None, a:b, 0], 2, axis=0)
    est[1, -1, 1] += 0.003
    x[: b] = np.nan
    x[b + 1: b + 7: 2] = np.nan
    want = np.hypot(0.003, 1.5e-4) - 2 * 4e-4
    np.testing.assert_allclose(fc._end_excess(est, x, 0, a, b), [0, want], atol=1e-12)


def test_profile_bins_count_from_the_nearer_measured_end():
    """Samples of a hole over frames 10-29 of 100: distance 0-1 from the nearer end is
    bin 0, 2-4 bin 1, 5-9 bin 2 (``PROFILE_EDGES``); a hole from the take's first frame is
    measured after it only; one of the whole take is in the last bin."""
    f = np.arange(10, 30)
    got = fb._profile_bins(f, np.full(20, 10), np.full(20, 30), 100)
    np.testing.assert_array_equal(got, [0, 0, 1, 1, 1, 2, 2, 2, 2, 2,
                                        2, 2, 2, 2, 2, 1, 1, 1, 0, 0])
    f = np.arange(0, 30)
    got = fb._profile_bins(f, np.zeros(30, int), np.full(30, 30), 100)
    np.testing.assert_array_equal(got[[29, 28, 27, 0]], [0, 0, 1, 4])  # d 0, 1, 2, 29
    assert (fb._profile_bins(f, np.zeros(30, int), np.full(30, 100), 100) == 5).all()


def test_a_member_off_at_the_gap_ends_is_left_out_sooner(monkeypatch):
    """The end-miss rules, with the test against the others' weighted mean off
    (``CONSENSUS_FACTOR`` infinite; what it adds is at the end).  Validated at 2 mm each, a
    member whose error grows from 3 mm at the run's ends to 23 mm in its middle (17 mm RMS
    from the others: 4.2 x its scale of 2 + 2 mm) is left out: it misses the trajectory at
    the ends by more than twice the others do, so 3 x its scale is the bound, not 5
    (without the measured positions it stays).  An error of that size that vanishes at the
    ends (a spline's shape) stays.  A member 10 mm off throughout, validated at 1.5 mm where
    the others are at 4 mm, lies within 3 x its scale of them but misses the ends by 10 mm >
    2 x (1.5 + < 0.9) mm: out; validated at 1 mm, 4 x better than every other member, it
    stays (``BOUNDARY_GUARD`` 3).  Two such members are both left out (the test repeats on
    the rest).  With the weighted-mean test on, the two 17 mm members go with or without
    the positions (7.4-7.5 deviations from the others' mean, known to 1 mm); the member 10 mm
    off and validated at 1 mm still stays (4.5 deviations)."""
    x, truth, est, runs = _joinless_case()
    L = 40
    bump = np.sin(np.linspace(0, np.pi, L))[:, None] * [0.02, 0, 0]
    w = np.ones((5, 1))
    mse = np.full((5, 1), 0.002**2)
    grown = est.copy()
    grown[1, 10:50, 0] += bump + [0.003, 0, 0]
    joined = est.copy()
    joined[1, 10:50, 0] += 1.2 * bump  # 24 mm in the middle, 0 at the ends
    d = np.sqrt(np.mean(np.sum((joined[1, 10:50, 0] - truth[10:50, 0]) ** 2, -1)))
    assert 3 * 0.004 < d < 5 * 0.004, d
    offset = est.copy()
    offset[3, 10:50, 0] += [0.010, 0, 0]
    mse_c = np.array([[0.004], [0.004], [0.004], [0.0015], [0.004]]) ** 2
    # validated at 1 mm, 4 x better than every other member: its misses do not hand the
    # run to members the copies scored far worse (ktk racing's head)
    mse_g = np.array([[0.004], [0.004], [0.004], [0.001], [0.004]]) ** 2
    with monkeypatch.context() as mp:
        mp.setattr(fc, "CONSENSUS_FACTOR", np.inf)
        np.testing.assert_array_equal(fc._outlying_estimates(grown, runs, mse, w, x)[:, 0],
                                      [False, True, False, False, False])
        assert not fc._outlying_estimates(grown, runs, mse, w).any()  # no positions: 5 x
        assert not fc._outlying_estimates(joined, runs, mse, w, x).any()
        np.testing.assert_array_equal(fc._outlying_estimates(offset, runs, mse_c, w, x)[:, 0],
                                      [False, False, False, True, False])
        assert not fc._outlying_estimates(offset, runs, mse_g, w, x).any()
        two = grown.copy()
        two[4, 10:50, 0] -= bump + [0.003, 0, 0]
        np.testing.assert_array_equal(fc._outlying_estimates(two, runs, mse, w, x)[:, 0],
                                      [False, True, False, False, True])
        # pyomeca's box marker (1 s hole): the local fill and the whole-body PCA agree, 10 mm
        # off in the middle and joined at the ends; the spline 60 mm off; the rigid-body
        # fill right (validated 0.1 mm; the nearest-donor one repeats it, weight 0).  The
        # spline goes; of the three left, the two that agree would outvote the right one by
        # distance alone (7 mm from their mean > 5 x (0.1 + 1.1) mm), so that test is not
        # repeated
        box = est.copy()
        box[0, 10:50, 0] += 0.5 * bump
        box[1, 10:50, 0] += 0.5 * bump
        box[2, 10:50, 0] += 3.0 * bump
        mse_box = (np.array([[0.9], [1.3], [2.2], [0.1], [0.1]]) * 1e-3) ** 2
        w_box = np.array([[1.0], [1], [1], [1], [0]])
        np.testing.assert_array_equal(
            fc._outlying_estimates(box, runs, mse_box, w_box, x)[:, 0],
            [False, False, True, False, False])
    for positions in (x, None):
        np.testing.assert_array_equal(
            fc._outlying_estimates(grown, runs, mse, w, positions)[:, 0],
            [False, True, False, False, False])
        np.testing.assert_array_equal(
            fc._outlying_estimates(joined, runs, mse, w, positions)[:, 0],
            [False, True, False, False, False])
    assert not fc._outlying_estimates(offset, runs, mse_g, w, x).any()
    np.testing.assert_array_equal(fc._outlying_estimates(two, runs, mse, w, x)[:, 0],
                                  [False, True, False, False, True])
    np.testing.assert_array_equal(fc._outlying_estimates(box, runs, mse_box, w_box, x)[:, 0],
                                  [False, False, True, False, False])


def _partnered_take(F: int = 300, v: float = 0.005):
    """Marker 0 moving along y at ``v`` m a frame with marker 1 held 0.2 m from it along
    x, marker 2 wandering on its own; marker 0 gone over frames 100-139.  Returns the
    truth ``(F, 3, 3)`` and the measured positions (NaN in the gap)."""
    t = np.arange(F)
    x0 = np.stack([0 * t, v * t, 1 + 0 * t], 1).astype(float)
    x2 = np.stack([1 + 0.3 * np.sin(t / 20), 0.5 * np.cos(t / 30), 1 + 0 * t], 1)
    truth = np.stack([x0, x0 + [0.2, 0, 0], x2], 1)
    pos = truth.copy()
    pos[100:140, 0] = np.nan
    return truth, pos


def test_partner_excess_and_jumps_are_what_the_marker_s_samples_never_do():
    """Known answers: an estimate 0.5 m off along its partner's direction lies 0.5 m outside
    the partner's 0.2 m distance at every frame, and steps ~0.5 m from and to the measured
    ends (its first and last samples jump); an estimate 1 m up for one frame lies
    √(0.2² + 1) - 0.2 outside at that frame (RMS over 40 frames) and jumps there (the
    sample and its two neighbours); one given over part of the run alone is judged on
    that part; the truth is at 0 and never jumps."""
    v = 0.005
    truth, pos = _partnered_take(v=v)
    (partners, lo, hi, fast), = fc._take_bounds(pos, np.array([0])).values()
    np.testing.assert_array_equal(partners, [1])  # marker 2 is no rigid partner
    np.testing.assert_allclose([lo[0], hi[0], fast], [0.2, 0.2, v], atol=1e-12)
    good = truth[100:140, 0]
    away = good - [0.5, 0, 0]
    jump = good.copy()
    jump[20, 2] += 1.0
    part = np.where(np.arange(40)[:, None] < 25, away, np.nan)  # off, then no estimate
    e = np.stack([good, away, jump, part])
    x = fc._partner_excess(e, partners, lo, hi, pos[100:140])
    np.testing.assert_allclose(x, [0.0, 0.5, (np.hypot(0.2, 1.0) - 0.2) / np.sqrt(40), 0.5],
                               atol=1e-9)
    j = fc._jumps(e, fast, pos[99, 0], pos[140, 0])
    np.testing.assert_array_equal(np.flatnonzero(j[0]), [])
    np.testing.assert_array_equal(np.flatnonzero(j[1]), [0, 39])
    np.testing.assert_array_equal(np.flatnonzero(j[2]), [19, 20, 21])
    np.testing.assert_array_equal(np.flatnonzero(j[3]), [0])
    # a marker with no partner and no measured step: nothing to go by
    lone = np.where(np.arange(300)[:, None, None] % 2 == 0, pos, np.nan)[:, [0, 2]]
    (p, _, _, f), = fc._take_bounds(lone, np.array([0])).values()
    assert len(p) == 0 and f == np.inf


def test_a_member_jumping_beside_half_its_samples_of_a_run_is_out_of_all_of_it():
    """Known answers on marker 0's 40-frame run: a member whose samples step 0.5 m out
    and back at 6 samples is flagged beside those alone (18 of 40, under
    :data:`fc.ERRATIC_SHARE`); at 7 (21 of 40) on all 40; a member estimating 6 samples,
    one of them off, beside 3 of its 6: on those 6 (the share is of the samples it
    estimates); the truth nowhere.  Without ``erratic`` only the samples beside a jump."""
    assert fc.ERRATIC_SHARE == 0.5
    truth, pos = _partnered_take()
    bounds = fc._take_bounds(pos, np.array([0]))
    est = np.full((4, 300, 3, 3), np.nan)
    est[:, 100:140, 0] = truth[100:140, 0]
    est[1, 100 + np.arange(1, 40, 4)[:6], 0, 0] += 0.5  # samples 1, 5, ..., 21
    est[2, 100 + np.arange(1, 40, 4)[:7], 0, 0] += 0.5  # ... and 25
    est[3, 106:140] = np.nan
    est[3, 103, 0, 0] += 0.5
    runs = [(0, 100, 140)]
    beside = [np.flatnonzero(np.isin(np.arange(40), np.add.outer(k, [-1, 0, 1])))
              for k in (np.arange(1, 40, 4)[:6], np.arange(1, 40, 4)[:7], [3])]
    for erratic, flagged in ((True, [[], beside[0], np.arange(40), np.arange(6)]),
                             (False, [[], beside[0], beside[1], beside[2]])):
        jumps = fc._jumps_in_runs(est, runs, pos, bounds, erratic=erratic)
        assert not jumps[:, :100].any() and not jumps[:, 140:].any() and not jumps[:, :, 1:].any()
        for k in range(4):
            np.testing.assert_array_equal(np.flatnonzero(jumps[k, 100:140, 0]), flagged[k])


def test_keep_plausible_leaves_out_members_off_their_rigid_partners():
    """The member 0.5 m off its partner is left out of the run (beyond
    :data:`fc.PLAUSIBILITY_LIMIT`), one 5 cm off stays; where the members left out held all
    the weight, the plausible member estimating all of the run, the least off, takes it;
    where none is plausible, nobody."""
    truth, pos = _partnered_take()
    bounds = fc._take_bounds(pos, np.array([0]))
    est = np.full((4, 300, 3, 3), np.nan)
    est[:, 100:140, 0] = truth[100:140, 0]
    est[1, 100:140, 0] -= [0.5, 0, 0]
    est[2, 100:140, 0] -= [0.05, 0, 0]
    est[3, 100:120, 0] = np.nan  # right, over half the run
    runs = [(0, 100, 140)]
    w = np.ones((4, 1))
    out = fc._keep_plausible(w, est, runs, pos, bounds)
    np.testing.assert_array_equal(out[:, 0], [False, True, False, False])
    np.testing.assert_array_equal(w[:, 0], [1, 0, 1, 1])
    w = np.array([[0.0], [1.0], [0.0], [0.0]])  # the wild one held the weight
    fc._keep_plausible(w, est, runs, pos, bounds)
    np.testing.assert_array_equal(w[:, 0], [1, 0, 0, 0])
    w = np.array([[0.0], [1.0], [0.0], [0.0]])
    wild = np.where(np.isfinite(est), est[1], np.nan)  # every member off
    assert fc._keep_plausible(w, wild, runs, pos, bounds).all()
    assert not w.any()



def test_isolated_spikes_are_single_samples_off_their_trajectory():
    """A smooth trajectory (a 1 m/s arc, 0.05 mm noise, 120 Hz) with one sample pushed 4 mm
    off it (frame 60), one pushed off with the sample two frames later missing (frame 150,
    152 not measured), one on the take's second frame, and a kink: the velocity reversed
    at frame 100 (motion, not a glitch).  Only the two interior pushed samples are spikes;
    the kink's corner lies off its neighbours' midpoint by half its velocity change
    (8.3 mm, 86 x the median), its neighbours, with the corner on that midpoint, half as
    far (contrast 2 < :data:`fc.SPIKE_CONTRAST`: at 1.5 the kink is flagged too)."""
    rng = np.random.default_rng(0)
    F = 200
    t = np.arange(F) / 120.0
    x = np.stack([np.cos(t), np.sin(t), 0.1 * t], axis=1)
    x[100:] = x[100] - (x[100:] - x[100])  # the velocity reversed at frame 100
    x = x + rng.normal(0.0, 5e-5, x.shape)
    for f in (60, 150, 1):
        x[f] += [0.004, 0.0, 0.0]
    x[152] = np.nan
    spikes = fc._isolated_spikes(np.stack([x, x + 1.0], axis=1))
    assert np.flatnonzero(spikes[:, 0]).tolist() == [60, 150]
    assert (spikes[:, 1] == spikes[:, 0]).all()
    corner = np.linalg.norm(x[100] - 0.5 * (x[99] + x[101]))
    assert 0.003 < corner  # far beyond SPIKE_FACTOR x the median: only the contrast spares it
    assert not fc._isolated_spikes(np.full((4, 2, 3), 0.0)).any()  # too short to tell
