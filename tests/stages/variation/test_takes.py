"""The clips stage on several takes: cycles of every take, named by take, balanced choice."""

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.motion.formats.bvh import read_bvh
from mocapflow.stages.motion.kinematics import resample_motion
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.variation.clips import make_clips
from mocapflow.stages.variation.inputs import _most_typical, clips
from tests.stages.variation.conftest import DATA


def _takes():
    a = procedural_walk(400, rate=60.0, seed=0).replace(attrs={"source_file": "a.bvh"})
    b = procedural_walk(200, rate=60.0, seed=1).replace(attrs={"source_file": "b.bvh"})
    return a, b


def test_every_take_is_cut_into_cycles_named_by_take():
    a, b = _takes()
    ctx = Context()
    out = clips([a, b], ctx=ctx)
    c, rep = out["clips"], out["report"]
    per_take = {t["take"]: t["n_cycles"] for t in rep["cut"]["takes"]}
    assert per_take["a.bvh"] >= 4 and per_take["b.bvh"] >= 2
    assert c.cyclic and c.n_clips == per_take["a.bvh"] + per_take["b.bvh"]
    assert sum(n.startswith("a.bvh[") for n in c.names) == per_take["a.bvh"]
    assert sum(n.startswith("b.bvh[") for n in c.names) == per_take["b.bvh"]
    assert all(40 <= n <= 90 for n in c.lengths)


def test_most_typical_is_balanced_over_takes():
    a, b = _takes()
    full = clips([a, b], ctx=Context())["clips"]
    n_b = sum(n.startswith("b.bvh[") for n in full.names)
    kept = clips([a, b], max_clips=2 * n_b, ctx=Context())["clips"]
    assert sum(n.startswith("b.bvh[") for n in kept.names) == n_b
    assert sum(n.startswith("a.bvh[") for n in kept.names) == n_b
    # ground truth on a toy set: take 0 holds the 3 most typical clips, take 1 one odd
    # clip; unbalanced choice of 2 would keep two of take 0, balanced keeps one of each
    base = np.sin(np.linspace(0, 2 * np.pi, 30))[:, None] * [1.0, 0.5]
    trajs = [base + 0.01 * i for i in range(3)] + [base * 3.0]
    toy = make_clips(trajs, ["x", "y"], rate=30.0, names=["t0a", "t0b", "t0c", "t1a"])
    sub, dropped = _most_typical(toy, 2, np.array([0, 0, 0, 1]))
    assert sub.names == ["t0b", "t1a"] and dropped == ["t0a", "t0c"]
    assert _most_typical(toy, 2)[0].names == ["t0a", "t0b"]


def test_a_take_without_cycles_is_skipped_with_a_warning():
    a, _ = _takes()
    short = procedural_walk(30, rate=60.0, seed=3).replace(attrs={"source_file": "s.bvh"})
    ctx = Context()
    c = clips([a, short], ctx=ctx)["clips"]
    assert not any(n.startswith("s.bvh") for n in c.names)
    assert any("s.bvh" in w and "skipped" in w for w in ctx.warnings)


@pytest.mark.skipif(not (DATA / "bvh" / "cmu_131_03.bvh").is_file(), reason="shared data absent")
def test_cmu_131_takes_each_contribute_cycles():
    ms = [resample_motion(read_bvh(DATA / "bvh" / f"cmu_131_0{i}.bvh"), 60) for i in (1, 2, 3)]
    rep = clips(ms, max_clips=6, ctx=Context())["report"]
    assert all(t["n_cycles"] >= 2 for t in rep["cut"]["takes"])
    kept = [n.split("[")[0] for n in rep["names"]]
    assert sorted(set(kept)) == [f"cmu_131_0{i}.bvh" for i in (1, 2, 3)]
    assert max(kept.count(k) for k in set(kept)) - min(kept.count(k) for k in set(kept)) <= 1


def test_shipped_takes_config_has_the_three_takes():
    from pathlib import Path

    cfg = Path(__file__).resolve().parents[3] / "configs" / "variation_takes.yaml"
    text = cfg.read_text()
    assert all(f"cmu_131_0{i}.bvh" in text for i in (1, 2, 3)) and "cut: auto" in text
