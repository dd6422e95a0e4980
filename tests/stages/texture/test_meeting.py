"""The thesis's meeting point (Moradoff 2002 §3.5-3.7; issue 16, item 3).

A two-sided gap at the coarsest level grows from both anchors in ONE output,
one node of each front in turn, so the fronts see each other once they are
within a neighbourhood; where they meet, the join is moved within
``meeting_window`` nodes and the arrangement with the lowest *summed* sequence
cost wins (not the meeting node's own cost).  Before: the two fronts grew in
separate copies of the output (alternating had no effect) and the winner was
the meeting node's own cost.
"""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.metrics import quality as M
from mocapflow.stages.motion.ingest import ingest_bvh
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.texture.neighbourhood import level_view
from mocapflow.stages.texture.pyramid import build_pyramid
from mocapflow.stages.texture.search import Gap, LevelSearch, SearchParams
from mocapflow.stages.texture.synth import synth, synthesize_source
from tests.stages.texture.conftest import seeded_context

LEVELS = 3


@pytest.fixture(scope="module")
def pyr():
    return build_pyramid(procedural_walk(300, rate=30.0, seed=3, variation=0.08), levels=LEVELS)


def _search(pyr, params: SearchParams, seed: int = 0, length: int = 600) -> LevelSearch:
    views = [level_view(pyr.levels[k], 2.0**k) for k in range(LEVELS)]
    n_out = [-(-length // 2**k) for k in range(LEVELS)]
    return LevelSearch(views, LEVELS - 1, n_out, False, None, params, np.random.default_rng(seed))


def _two_fronts(s: LevelSearch, A: int, B: int, lo: int, hi: int, m0: int) -> np.ndarray:
    """Left front playing on from input node A at lo, right front playing into B at hi."""
    src = np.full(s.n, -1)
    src[lo], src[hi] = A, B
    src[lo + 1 : m0 + 1] = A + np.arange(1, m0 - lo + 1)
    src[m0 + 1 : hi] = B - np.arange(hi - m0 - 1, 0, -1)
    return src


@pytest.mark.parametrize("A, B", [(3, 70), (10, 30)])
def test_meeting_minimises_the_summed_sequence_cost(pyr, A, B):
    """Known answer by brute force: every join position within the window and every
    input node there, scored by the whole gap's summed neighbourhood cost."""
    s = _search(pyr, SearchParams(k_best=10_000, max_run=0))  # every node competes; no run limit
    s.randomize = False  # take the cheapest (no seeded draw)
    lo, hi, m0, w = 10, 40, 25, s.p.meeting_window
    src0 = _two_fronts(s, A, B, lo, hi, m0)
    src, ranked = src0.copy(), np.full((s.n, 3), -1)
    m = s._meet(src, ranked, Gap(lo, hi, (0, 1)), m0, lo + 1, hi - 1)
    gap = np.arange(lo, hi + 1)
    summed, own = [], []
    for mm in range(m0 - w, m0 + w + 1):
        tr = src0.copy()
        if mm > m0:
            tr[m0:mm] = src0[m0 - 1] + np.arange(1, mm - m0 + 1)
        elif mm < m0:
            tr[mm + 1 : m0 + 1] = src0[m0 + 1] - np.arange(m0 - mm, 0, -1)
        tr[mm] = -1
        c = s.cost(tr, mm, np.arange(s.view.n))
        for v in np.flatnonzero(np.isfinite(c)):
            t2 = tr.copy()
            t2[mm] = v
            summed.append((s.sequence_costs(t2[None], gap)[0], mm, int(v)))
            own.append((c[v], summed[-1][0]))
    best = min(summed)
    chosen = s.sequence_costs(src[None], gap)[0]
    assert chosen == pytest.approx(best[0], rel=1e-9, abs=1e-12)
    assert m == best[1] and src[m] == best[2]
    assert ranked[m, 0] == src[m]
    # the meeting node's own cost would have chosen a worse sequence here
    assert min(own)[1] > best[0] + 1e-6
    # the fronts are kept outside the moved join
    keep = np.r_[lo : min(m, m0), max(m, m0) + 1 : hi + 1]
    np.testing.assert_array_equal(src[keep], src0[keep])


def test_fronts_grow_in_one_output_and_see_each_other(pyr, monkeypatch):
    """While the fronts grow alternately, the last nodes of one have nodes of the other
    inside their neighbourhood (impossible when each front grew in its own copy)."""
    s = _search(pyr, SearchParams())
    lo, hi = 10, 60
    src, ranked = np.full(s.n, -1), np.full((s.n, 3), -1)
    src[lo], src[hi] = 5, 40
    both_sides = []
    fill = s.fill

    def spy(src_, ranked_, t, where):
        near = s._out_values(src_, t + s.off)
        S = s.p.slots
        both_sides.append(bool((near[:S] >= 0).any() and (near[S + 1 :] >= 0).any()))
        assert src_ is src  # one shared output, not a copy per front
        fill(src_, ranked_, t, where)

    monkeypatch.setattr(s, "fill", spy)
    m = s.fill_gap(src, ranked, Gap(lo, hi, (0, 1)), None)
    assert lo < m < hi and (src[lo : hi + 1] >= 0).all()
    assert len(both_sides) == hi - lo - 1
    # only the last S nodes of the two fronts (the meeting) see the other front
    assert sum(both_sides) >= s.p.slots
    assert not any(both_sides[: hi - lo - 1 - 2 * s.p.slots])


def test_alternating_the_fronts_changes_the_result(pyr):
    cons = [(20, 30), (150, 300), (60, 560)]  # (input frame, output frame)
    differ = 0
    for seed in range(4):
        tracks = [
            synthesize_source(pyr, 600, cons, levels=LEVELS, cyclic=False,
                              method="meeting_point", params=SearchParams(alternate=alt),
                              rng=np.random.default_rng(seed))[0]
            for alt in (True, False)
        ]
        for src in tracks:
            for i, j in cons:
                assert src[j] == i  # constraints exact either way
        differ += not np.array_equal(*tracks)
    assert differ >= 2


def test_a_moved_meeting_keeps_max_run_at_the_synthesis_rate(shared_data):
    """The benchmark's constrained case (salsa, output frames counted at 30 fps): moving
    the join could extend a front that already had max_run nodes (seed 2 played 248
    frames verbatim, limit 0.3 x 561 = 168) until joins that lengthen a run past
    max_run were refused."""
    path = shared_data / "bvh" / "cmu_60_01_scaled.bvh"
    motion = ingest_bvh(str(path), rate=30, ctx=Context())["motion"]
    pyr4 = build_pyramid(motion, levels=4)
    for seed in range(6):
        r = synth(pyr4, motion, length=1024, constraints=[[100, 10], [300, 512], [450, 1000]],
                  output_rate=30, foot_ik=False, seed=seed, ctx=seeded_context(seed))
        src = r["source_index"]
        assert M.longest_verbatim_run(src) <= 0.35 * motion.n_frames, seed
        seams = set(M.seams_from_source(src).tolist())
        assert all(t in seams for t in r["report"]["meetings"].values())
