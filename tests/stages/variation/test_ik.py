"""IK clean-up: planted feet within 1 mm, less foot skate, unreachable targets, pass-through."""

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.metrics.quality import foot_skate
from mocapflow.stages.motion.contacts import contact_thresholds, toe_indices
from mocapflow.stages.motion.kinematics import motion_positions
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.motion.simulate.skeleton import procedural_skeleton
from mocapflow.stages.variation.clips import clips_from_motions, clips_to_motions, make_clips
from mocapflow.stages.variation.ik import IKError, ik, limb_of


@pytest.fixture(scope="module")
def skating():
    """A clean procedural walk and a copy whose root velocity wobbles (feet skate)."""
    walk = procedural_walk(90, rate=60.0, seed=2, variation=0.0)
    clean = clips_from_motions([walk])
    fwd = clean.labels.index("Hips:velocity_Z")
    t = clean.trajectories[0].copy()
    t[:, fwd] += 0.002 * np.sin(np.arange(len(t)) * 2 * np.pi / 25)  # ±0.12 m/s
    return clean, clean.replace(trajectories=[t])


def _skate(clips, toes, thr):
    p = motion_positions(clips_to_motions(clips)[0])
    return foot_skate(p, toes, clips.rate, height_threshold=thr[0], speed_threshold=thr[1])


def test_planted_feet_within_a_millimetre_and_less_skate(skating):
    clean, bad = skating
    sk = clean.skeleton
    toes = toe_indices(sk)
    thr = contact_thresholds(motion_positions(clips_to_motions(clean)[0]), toes, clean.rate)
    ctx = Context()
    r = ik(bad, ctx=ctx)
    out, rep = r["variants"], r["report"]
    r = rep["clips"][0]
    assert sum(r["constrained_frames"].values()) > 60
    assert not r["unreachable"] and not ctx.warnings
    assert max(r["max_error"].values()) <= 1e-3
    before, after = _skate(bad, toes, thr), _skate(out, toes, thr)
    assert after < 0.5 * before  # measured: 0.16 -> 0.02 m/s
    # only the leg DOFs moved
    moved = np.abs(out.trajectories[0] - bad.trajectories[0]).max(axis=0) > 1e-9
    names = [n for n, m in zip(bad.labels, moved) if m]
    assert names and all(n.split(":")[0] in {"LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg",
                                            "RightLeg", "RightFoot", "LHipJoint", "RHipJoint"}
                         for n in names)


def test_manual_contacts_hold_the_foot(skating):
    _, bad = skating
    walk = procedural_walk(90, rate=60.0, seed=2, variation=0.0)
    flat = [f for f in walk.attrs["gait_events"]["left"]["foot_flat"] if 0.1 < f < 1.1][0]
    a = int(round(flat * 60))
    r = ik(bad, effectors=["LeftFoot"], contacts={"LeftFoot": [[a, a + 12]]})
    out, rep = r["variants"], r["report"]
    p = motion_positions(clips_to_motions(out)[0])[:, bad.skeleton.index("LeftFoot")]
    p0 = motion_positions(clips_to_motions(bad)[0])[:, bad.skeleton.index("LeftFoot")]
    assert np.abs(p[a : a + 12] - p[a]).max() <= 1e-3
    assert np.abs(p0[a : a + 12] - p0[a]).max() > 5e-3  # it did slide before
    assert rep["clips"][0]["constrained_frames"]["LeftFoot"] == 12


def test_contacts_count_at_the_output_rate(skating):
    """At ``output_rate`` 30 the 60 fps model's contact [a, a + 12) is given as [h, h + 6)."""
    _, bad = skating
    walk = procedural_walk(90, rate=60.0, seed=2, variation=0.0)
    flat = [f for f in walk.attrs["gait_events"]["left"]["foot_flat"] if 0.1 < f < 1.1][0]
    h = int(round(flat * 30))
    r = ik(bad, effectors=["LeftFoot"], contacts={"LeftFoot": [[h, h + 6]]}, output_rate=30)
    out, rep = r["variants"], r["report"]
    clip = rep["clips"][0]
    assert (rep["rate"], rep["output_rate"], clip["output_frames"]) == (60.0, 30.0, 45)
    assert clip["constrained"]["LeftFoot"] == [[h, h + 6]]  # model frames 2h .. 2h + 11
    assert clip["constrained_frames"]["LeftFoot"] == 6
    p = motion_positions(clips_to_motions(out)[0])[:, bad.skeleton.index("LeftFoot")]
    assert np.abs(p[2 * h : 2 * h + 12] - p[2 * h]).max() <= 1e-3
    assert np.abs(p[2 * h + 13 : 2 * h + 20] - p[2 * h]).max() > 1e-3  # released after
    with pytest.raises(IKError, match=r"frame 45 outside motion0's exported frames 0\.\.44 \("):
        ik(bad, targets={"LeftFoot": [[45, 0, 0, 0]]}, output_rate=30)


def test_unreachable_target_is_best_effort_with_a_warning(skating):
    _, bad = skating
    ctx = Context()
    r = ik(bad, effectors=["LeftToeBase"], contacts={"LeftToeBase": []},
           targets={"LeftToeBase": [[10, 5.0, 0.0, 5.0]]}, ctx=ctx)
    out, rep = r["variants"], r["report"]
    un = rep["clips"][0]["unreachable"]
    assert len(un) == 1 and un[0]["frame"] == 10 and un[0]["error"] > 1.0
    assert any("frame 10" in w and "LeftToeBase" in w and "unreachable" in w
               for w in ctx.warnings)
    assert np.isfinite(out.trajectories[0]).all()
    with pytest.raises(IKError, match="NoSuchJoint"):
        ik(bad, effectors=["NoSuchJoint"])
    with pytest.raises(IKError, match="frame 500"):
        ik(bad, targets={"LeftFoot": [[500, 0, 0, 0]]})


def test_stage_passes_strokes_and_off_through_and_limbs():
    s = make_clips([np.random.default_rng(0).normal(size=(20, 2))], ["x", "y"], rate=200.0,
                   kind="strokes")
    out = ik(s, ctx=Context())
    assert out["variants"] is s and "skipped" in out["report"]
    sk = procedural_skeleton()
    assert [sk.names[j] for j in limb_of(sk, sk.index("LeftToeBase"))] == [
        "LHipJoint", "LeftUpLeg", "LeftLeg", "LeftFoot"]
    assert [sk.names[j] for j in limb_of(sk, sk.index("LeftHand"))][-2:] == [
        "LeftArm", "LeftForeArm"]
