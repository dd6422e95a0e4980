"""IK on the figure-8 walk (issue 17): toes planted at their stance height, jerk at the input's.

A small model of the shared figure-8 take (6 cycles at 60 fps, one-step score, 2
parents) sampled as the shipped config samples (sigma 1, noise_time 0.1 s), cleaned by
the ``ik`` stage at its defaults (the shipped config's ik params).  Skate and jerk are
measured as ``benchmarks/variation.py`` section 2 measures them: the toes' mean
horizontal speed on contact frames with the input's contact thresholds
(:func:`~mocapflow.stages.metrics.quality.foot_skate`), the pooled p99 of the
per-frame mean joint jerk; the chain as section 3: 5 cycles of ``sample(loop=True)``,
the jerk p99 at the joins (±3 frames).

Before (ease 0.25, contacts found below the clip's 5th-percentile toe height, a toe
taking over from the heel held at its height at the switch, unreachable targets held to
the end): held toes up to 7.1 cm above the sampled toe's stance, contacts missed by up
to 7.5 cm.  This small model passes the skate and jerk bounds also before (the full
shipped model did not: ``benchmarks/variation.py --sections 2,3``).  The numbers each
test asserts are in its docstring.
"""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.registry import ParamError
from mocapflow.stages.metrics.gait import join_jerk_p99
from mocapflow.stages.metrics.quality import foot_skate, jerk_per_frame
from mocapflow.stages.motion.contacts import contact_thresholds, toe_indices
from mocapflow.stages.motion.ingest import ingest_bvh
from mocapflow.stages.motion.kinematics import motion_positions
from mocapflow.stages.variation.clips import clips_to_motions
from mocapflow.stages.variation.ik import IKError, ik
from mocapflow.stages.variation.inputs import clips
from mocapflow.stages.variation.learn import learn
from mocapflow.stages.variation.sample import sample

TAKE = "pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh"


@pytest.fixture(scope="module")
def figure8(shared_data):
    """``(inputs, model)``: the take cut as the shipped config cuts it, a small model."""
    motion = ingest_bvh(str(shared_data / "bvh" / TAKE), rate=60, ctx=Context())["motion"]
    train = clips(motion, max_clips=6, ctx=Context())["clips"]
    model = learn(train, k=30, kernel_width=2.0, max_parents=2, candidates=5, restarts=0,
                  score="one_step", ctx=Context())["model"]
    return train, model


@pytest.fixture(scope="module")
def measure(figure8):
    """``(jerk p99, toe skate)`` of clips, with the inputs' contact thresholds."""
    train, _ = figure8
    toes = toe_indices(train.skeleton)
    rate = train.rate
    thr = contact_thresholds(np.concatenate(_positions(train)), toes, rate)

    def of(c):
        ps = _positions(c)
        j = np.concatenate([jerk_per_frame(p, rate)[2:len(p) - 2] for p in ps])
        s = np.nanmean([foot_skate(p, toes, rate, height_threshold=thr[0],
                                   speed_threshold=thr[1]) for p in ps])
        return float(np.percentile(j[np.isfinite(j)], 99)), float(s)

    return of


def _positions(c):
    return [motion_positions(m) for m in clips_to_motions(c)]


def _sampled(model, seed: int, **params):
    return sample(model, sigma=1.0, noise_time=0.1, **params,
                  ctx=Context(rng=np.random.default_rng(seed)))


def _cleaned(model, seed: int, **params):
    """The ``ik`` stage's outputs at its defaults, frames counted at the model's rate."""
    out = _sampled(model, seed, **params)
    return ik(out["variants"], out["predicted"], output_rate=model.clips.rate, ctx=Context())


@pytest.fixture(scope="module")
def cleaned(figure8):
    """Two draws of variants after IK: 10 of seed 1, 6 of seed 2; seed 1's as sampled."""
    _, model = figure8
    return {1: _cleaned(model, 1, count=10), 2: _cleaned(model, 2, count=6),
            "sampled": _sampled(model, 1, count=10)["variants"]}


def test_figure8_toe_skate_and_jerk_after_ik(figure8, measure, cleaned):
    """Toe skate <= 1.2 x the input's and jerk p99 <= 1.5 x for both draws (measured seed
    1: skate 0.77, jerk 0.71; seed 2: 0.82, 0.78; before: skate 1.04 and 1.14, jerk 1.06
    and 0.85), every held contact met within 3 cm (measured 20.3 and 9.7 mm; before 74.5
    and 20.5 mm: targets beyond the leg's reach were held to the end)."""
    train, _ = figure8
    j_in, s_in = measure(train)
    for seed in (1, 2):
        j, s = measure(cleaned[seed]["variants"])
        assert s <= 1.2 * s_in, (seed, s / s_in)
        assert j <= 1.5 * j_in, (seed, j / j_in)
        worst = max(max(c["max_error"].values()) for c in cleaned[seed]["report"]["clips"])
        assert worst <= 0.03, (seed, worst)


def test_figure8_planted_toe_is_held_at_its_stance_height(cleaned):
    """A toe that takes over from the heel is held at its own stance height (the mean over
    its run in the unconstrained solve), not where it hangs when the heel's run ends: every
    held toe run of the 10 variants within 2 cm of the sampled toe's mean height over the
    run (measured 0.5 cm at most; before 7.1 cm)."""
    r, sampled = cleaned[1], cleaned["sampled"]
    assert _held_toe_offset(r, sampled) <= 0.02


def _held_toe_offset(r, sampled) -> float:
    """Metres: the largest |mean height of a held toe run - the sampled toe's over it|."""
    sk = r["variants"].skeleton
    up = "xyz".index(r["variants"].attrs.get("up", "y"))
    return max(
        abs(p[a:b, sk.index(name), up].mean() - q[a:b, sk.index(name), up].mean())
        for c, p, q in zip(r["report"]["clips"], _positions(r["variants"]),
                           _positions(sampled))
        for name, ranges in c["constrained"].items() if "toe" in name.lower()
        for a, b in ranges
    )


def test_figure8_chained_cycles_joins_after_ik(figure8, measure):
    """5 loop cycles cleaned as one chain: jerk p99 at the joins <= 1.5 x the inputs'
    (measured 1.21; before 1.29)."""
    train, model = figure8
    j_in, _ = measure(train)
    v = _cleaned(model, 3, count=5, loop=True)["variants"]
    ps = _positions(v)
    jj = join_jerk_p99(np.concatenate(ps), [len(p) for p in ps], train.rate)
    assert jj <= 1.5 * j_in, jj / j_in


def test_reach_passes_is_checked(figure8):
    _, model = figure8
    out = _sampled(model, 1, count=1)
    with pytest.raises(IKError, match="reach_passes: must be an integer >= 0, got -1"):
        ik(out["variants"], reach_passes=-1, ctx=Context())
    with pytest.raises(ParamError, match="reach_passes"):
        ik(out["variants"], reach_passes=1.5, ctx=Context())
