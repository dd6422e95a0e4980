"""The coarsest level's table of costs after a settled run (``LevelSearch.after_run_costs``):
``fill`` reads a front's costs from it instead of scoring every input node again, so its
rows must be exactly the costs ``cost`` computes, and a synthesis must not change."""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.texture.neighbourhood import level_view
from mocapflow.stages.texture.pyramid import build_pyramid
from mocapflow.stages.texture.search import LevelSearch, SearchParams
from mocapflow.stages.texture.synth import synthesize_source

LEVELS = 3


@pytest.fixture(scope="module")
def pyr():
    return build_pyramid(procedural_walk(300, rate=30.0, seed=3, variation=0.08), levels=LEVELS)


def _coarsest(pyr, length: int = 600, cyclic: bool = False) -> LevelSearch:
    views = [level_view(pyr.levels[l], 2.0**l) for l in range(LEVELS)]
    n_out = [-(-length // 2**l) for l in range(LEVELS)]
    return LevelSearch(views, LEVELS - 1, n_out, cyclic, None, SearchParams(),
                       np.random.default_rng(0))


@pytest.mark.parametrize("cyclic", [False, True])
def test_table_rows_are_the_costs_of_every_input_node(pyr, cyclic):
    s = _coarsest(pyr, cyclic=cyclic)
    n, S = s.view.n, s.p.slots
    every = np.arange(n)
    checked = 0
    for a in (S - 1, 7, 20, n - 1):
        for t in (S, 30, s.n - S - 1, s.n - 1):
            src = np.full(s.n, -1, dtype=np.int64)
            src[t - S:t] = np.arange(a - S + 1, a + 1)  # a settled run ending at a
            got = s._cost_after_run(src, t)
            if got is None:  # non-cyclic: the finer level's slots of t must exist
                assert not cyclic and 2 * t + S + 1 >= s.n_out[s.l - 1]
                continue
            np.testing.assert_array_equal(got, s.cost(src, t, every))
            checked += 1
    assert checked >= 8


def test_no_table_where_the_window_is_not_a_settled_run_with_nothing_after(pyr):
    s = _coarsest(pyr)
    S, t = s.p.slots, 30
    src = np.full(s.n, -1, dtype=np.int64)
    src[t - S:t] = [4, 5, 9]  # a jump one node back: not settled
    assert s._cost_after_run(src, t) is None
    src[t - S:t] = [7, 8, 9]
    src[t + 2] = 40  # something after it (the other front)
    assert s._cost_after_run(src, t) is None
    src[t + 2] = -1
    assert s._cost_after_run(src, t) is not None
    s.AFTER_RUN_TABLE_NODES = 10  # above the size limit: always computed
    assert s._cost_after_run(src, t) is None and s.after_run_costs() is None


def test_synthesis_is_the_same_with_and_without_the_table(pyr, monkeypatch):
    def run(seed, constraints):
        return synthesize_source(pyr, 600, constraints, levels=LEVELS, cyclic=False,
                                 method="meeting_point", params=SearchParams(),
                                 rng=np.random.default_rng(seed))[0]

    cases = [(0, []), (1, []), (2, [(40, 100), (200, 400)])]
    with_table = [run(seed, c) for seed, c in cases]
    monkeypatch.setattr(LevelSearch, "AFTER_RUN_TABLE_NODES", 0)
    without = [run(seed, c) for seed, c in cases]
    for a, b in zip(with_table, without):
        np.testing.assert_array_equal(a, b)
