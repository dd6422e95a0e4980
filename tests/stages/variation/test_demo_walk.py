"""The demo's variation step on the demo's procedural walk (``mocapflow demo``).

The walk (``configs/demo_data.yaml``: 300 frames at 30 fps, variation 0.05, seed 0)
is read back at 60 fps and cut into 6 near-identical cycles, learned and sampled
with the demo's settings (``configs/variation.yaml`` with the ``configs/demo.yaml``
overrides: restarts 1, candidates 10, max_parents 4; ``learn``'s ``calibrate_retention``
and ``ik``'s ``range_fraction`` at their defaults, which the config used to set).  A model
of near-identical examples must give near-identical variants: before the calibrated retention the
sampled knee ran 1.2 rad (0.81 of its range) past the inputs' range, and the IK
turned the hip twist (a channel spanning 0.001 rad) 25 ranges out.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.motion.export import export_motion_bvh
from mocapflow.stages.motion.ingest import ingest_bvh
from mocapflow.stages.motion.simulate.motion import simulate_walk
from mocapflow.stages.variation.ik import ik
from mocapflow.stages.variation.inputs import clips
from mocapflow.stages.variation.learn import learn
from mocapflow.stages.variation.sample import sample

#: the ``sample`` seeds of the demo (``sample.seeds: 5``)
SEEDS = range(5)
#: how far beyond the inputs' per-DOF range a variant may go, as a fraction of that range
MARGIN = 0.5


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """``(training clips, model)`` of the demo walk, as the demo's graphs make them."""
    walk = simulate_walk(n_frames=300, rate=30.0, gait="walk", variation=0.05, seed=0,
                         ctx=Context(part="seed=0", seed=0))["motion"]
    path = tmp_path_factory.mktemp("demo_walk") / "motion.bvh"
    export_motion_bvh(walk, path)
    motion = ingest_bvh(str(path), rate=60, ctx=Context())["motion"]
    train = clips([motion], cut="auto", root="heading", up="auto", max_clips=6,
                  ctx=Context())["clips"]
    model = learn(train, k=30, kernel_width=2.0, max_parents=4, candidates=10, restarts=1,
                  score="propagated", half_life=0.5, ctx=Context())["model"]
    return train, model


def _sampled(model, seed):
    """The ``sample`` stage's outputs of task ``seed=<seed>`` (config: sigma 1, noise_time 0.1)."""
    return sample(model, count=1, sigma=1.0, noise_time=0.1, seed=seed,
                  ctx=Context(part=f"seed={seed}", seed=seed))


def _excess(train, variants):
    """Largest excess of any frame's DOF beyond the inputs' range, in units of that range."""
    X = np.concatenate(train.trajectories)
    lo, hi = X.min(axis=0), X.max(axis=0)
    V = np.concatenate(variants.trajectories)
    assert variants.labels == train.labels
    return float((np.maximum(V - hi, lo - V).clip(0.0) / (hi - lo)).max())


def test_demo_walk_is_six_near_identical_cycles(demo):
    train, model = demo
    assert train.n_clips == 6 and train.cyclic
    assert train.lengths.tolist() == [65, 65, 68, 65, 66, 67]
    lam = np.array(model.params["retention_dof"])
    assert model.params["retention"] == pytest.approx(0.97716, abs=1e-5)  # half_life 0.5 s
    knee = model.clips.labels.index("LeftLeg:Xrotation")
    assert 0.6 < lam[knee] < 0.9  # calibrated: a half-life of 2-6 frames (measured 0.75)
    assert np.all(lam <= model.params["retention"] + 1e-12)


def test_demo_walk_variants_stay_within_the_inputs_range(demo):
    """Every frame (the first included) of every seed's variant within the inputs' range
    ± half of it (before: 0.40, 0.44, 0.53, 0.81, 0.65; measured 0.07, 0.09, 0.03, 0.08,
    0.14)."""
    train, model = demo
    for seed in SEEDS:
        v = _sampled(model, seed)["variants"]
        assert _excess(train, v) <= MARGIN, seed
        assert _excess(train, v.replace(trajectories=[t[:2] for t in v.trajectories])) <= 0.25


def test_demo_walk_without_the_calibration_runs_away(demo):
    """The half_life retention for every DOF (``calibrate_retention=False``, the structure
    is the same): the knee runs past the margin (measured 0.81 of its range for seed 3)."""
    train, model = demo
    lam = model.params["retention"]
    old = dataclasses.replace(model, params={**model.params,
                                             "retention_dof": [lam] * model.n_dofs})
    worst = max(_excess(train, _sampled(old, seed)["variants"]) for seed in SEEDS)
    assert worst > MARGIN


def test_demo_walk_ik_keeps_the_still_channels_still(demo):
    """After IK (the config's joint limits) every DOF stays within the inputs' range ± half
    of it and PC1 of the inputs' standardised DOFs (Fig. 6) within 1.3 x the inputs' span
    (before: the hip twist 34 ranges out, PC1 at ±45 for inputs at ±6.2)."""
    train, model = demo
    X = np.concatenate(train.trajectories)
    mean, std = X.mean(axis=0), X.std(axis=0)
    _, _, Vt = np.linalg.svd((X - mean) / std, full_matrices=False)
    pc1 = np.abs((X - mean) / std @ Vt[0]).max()
    for seed in SEEDS:
        out = _sampled(model, seed)
        v = ik(out["variants"], out["predicted"], range_margin=0.025,
               ctx=Context(part=f"seed={seed}", seed=seed))["variants"]
        assert _excess(train, v) <= MARGIN + 1e-6, seed
        V = np.concatenate(v.trajectories)
        assert np.abs((V - mean) / std @ Vt[0]).max() <= 1.3 * pc1, seed
