"""Constraints with the meeting-point synthesis on a real take (issue 16, item 3).

The salsa take (``cmu_60_01_scaled.bvh``, 120 fps, synthesised at 30 fps) with
three constraints.  Before the fix the report's ``meetings`` were the coarsest
level's positions ×8, inside verbatim runs after refinement (29 of 40 over 20
seeds), and refinement could join right next to a constrained frame (a seam at
or within one frame of a constraint in 5 of 20 seeds).  The graph path
(``method="graph_path"``) ignored ``max_run``: it replayed 534-552 of the 561
frames verbatim (limit 168); it now keeps the run limit in its search (a run-length
state in the remaining-cost table) and natural edges beside each constraint.
"""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.metrics import quality as M
from mocapflow.stages.motion.ingest import ingest_bvh
from mocapflow.stages.texture.pyramid import build_pyramid
from mocapflow.stages.texture.search import SearchParams
from mocapflow.stages.texture.synth import synth
from tests.stages.texture.conftest import seeded_context

#: [input frame, output frame] at the source rate (120 fps), as a user writes them.
CONSTRAINTS = [[100, 10], [300, 512], [450, 1000]]
SEEDS = range(20)
SLOTS = 3  # the synth default: a constraint keeps this many verbatim frames each side


@pytest.fixture(scope="module", params=[("meeting_point", SEEDS), ("graph_path", SEEDS[:10])],
                ids=["meeting_point", "graph_path"])
def salsa_runs(request, shared_data):
    method, seeds = request.param
    path = shared_data / "bvh" / "cmu_60_01_scaled.bvh"
    motion = ingest_bvh(str(path), rate=30, ctx=Context())["motion"]
    pyr = build_pyramid(motion, levels=4)
    runs = []
    for seed in seeds:
        r = synth(pyr, motion, length=1024, levels=4, constraints=CONSTRAINTS, seed=seed,
                  method=method, foot_ik=False, ctx=seeded_context(seed))
        runs.append((r["source_index"], r["report"]))
    return motion.n_frames, runs


def test_max_run_holds_with_constraints(salsa_runs):
    F, runs = salsa_runs
    longest = max(M.longest_verbatim_run(src) for src, _ in runs)
    assert longest <= (SearchParams().max_run + 0.05) * F, (longest, F)  # + 5 % of the input


def test_finer_levels_keep_max_run(salsa_runs):
    """The finer levels' joins keep ``max_run`` itself, not only the coarsest level:
    before, a join moved later (or one that kept the left line through a short detour)
    lengthened runs to 154 frames with ``max_run`` 0.22 (limit 123) on these takes."""
    F, runs = salsa_runs
    longest = max(M.longest_verbatim_run(src) for src, _ in runs)
    assert longest <= SearchParams().max_run * F + 1, (longest, F)


def test_every_reported_meeting_is_a_seam(salsa_runs):
    _, runs = salsa_runs
    for src, rep in runs:
        seams = set(M.seams_from_source(src).tolist())
        assert set(rep["meetings"]) == {"(0, 1)", "(1, 2)"}
        for key, t in rep["meetings"].items():
            assert t in seams, (key, t, sorted(seams))
        assert rep["seams"] == sorted(seams)


def test_constraints_exact_and_copied_with_their_neighbourhood(salsa_runs):
    _, runs = salsa_runs
    for src, rep in runs:
        seams = M.seams_from_source(src)
        for i, o in rep["constraints_synthesis"]:
            assert src[o] == i
            # no transition within SLOTS frames of a constrained frame
            assert not np.any(np.abs(seams - o) <= SLOTS), (o, seams.tolist())


@pytest.mark.parametrize("method", ["meeting_point", "graph_path"])
@pytest.mark.parametrize("constraints", [[], [[50, 100]]], ids=["free", "one"])
def test_loop_meetings_are_seams(shared_data, method, constraints):
    """Loops: the wrap gap's meeting (a free start without constraints) is followed to
    its seam too (the free anchor is node 0 at every level)."""
    path = shared_data / "bvh" / "pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh"
    motion = ingest_bvh(str(path), rate=30, ctx=Context())["motion"]
    r = synth(build_pyramid(motion, levels=4), motion, length=400, levels=4, loop=True,
              constraints=constraints, method=method, foot_ik=False, ctx=seeded_context(0))
    seams = set(M.seams_from_source(r["source_index"], cyclic=True).tolist())
    assert len(r["report"]["meetings"]) == 1
    assert all(t in seams for t in r["report"]["meetings"].values())
