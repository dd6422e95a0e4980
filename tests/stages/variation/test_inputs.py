"""The clips stage: cutting one take, whole files, strokes, errors naming the part."""

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.motion.datatypes import Strokes
from mocapflow.stages.motion.formats.bvh import read_bvh
from mocapflow.stages.motion.formats.strokes import read_uci_chartraj
from mocapflow.stages.motion.kinematics import resample_motion
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.variation.clips import ClipError, clips_to_strokes, make_clips
from mocapflow.stages.variation.inputs import clips
from tests.stages.variation.conftest import DATA


def test_clips_stage_cuts_one_take_and_keeps_files_whole(walk):
    ctx = Context()
    out = clips([walk], ctx=ctx)
    c, rep = out["clips"], out["report"]
    assert c.cyclic and c.n_clips >= 5 and rep["cut"]["method"] == "feet"
    assert all(50 <= n <= 85 for n in c.lengths)
    two = clips([walk, walk.replace(attrs={"source_file": "b.bvh"})], cut="none",
                ctx=Context())["clips"]
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
    ss = read_uci_chartraj(DATA / "strokes" / "uci_chartraj_mv_subset.csv", letter="a")
    c = clips(ss, ctx=Context())["clips"]
    assert c.n_clips == 5 and sorted(c.lengths) == [136, 138, 138, 139, 143]


@pytest.mark.skipif(not (DATA / "bvh").is_dir(), reason="shared data absent")
def test_shared_walk_take_cuts_into_at_least_four_cycles():
    m = resample_motion(read_bvh(DATA / "bvh" / "pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh"), 60)
    c = clips(m, ctx=Context())["clips"]
    # the figure-8 walk: 8 full left-foot cycles of about 1 s
    assert c.n_clips >= 4 and c.cyclic
    assert all(50 <= n <= 70 for n in c.lengths)
