"""Native frame rate and units of the variation output (issue 14).

The model works at the ingest rate (30 fps here, small params); the exported BVHs come
back at the source file's rate (120 fps) with its exact ``Frame Time`` text and in its
unit (the PyMO walk is in inches: written in centimetres it was 2.54x too large).
The ``ik`` stage's ``contacts`` / ``targets`` frames and its report count exported frames.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.codecs import decode, encode
from mocapflow.stages.motion.formats.bvh import read_bvh, write_bvh
from mocapflow.stages.motion.ingest import ingest_bvh
from mocapflow.stages.motion.kinematics import motion_positions
from mocapflow.stages.variation.clips import clips_to_motions, export_clips
from mocapflow.stages.variation.ik import IKError, ik
from mocapflow.stages.variation.inputs import clips
from mocapflow.stages.variation.learn import learn
from mocapflow.stages.variation.sample import sample
from tests.stages.texture.conftest import (
    bvh_frame_count,
    bvh_frame_time_text,
    bvh_skeleton_size,
)

TAKE = "pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh"  # 120 fps, inches


@pytest.fixture(scope="module")
def variation_run(shared_data):
    """``(path, training clips, ik variants)``: the graph's stages with small params."""
    path = shared_data / "bvh" / TAKE
    motion = ingest_bvh(str(path), rate=30, ctx=Context())["motion"]
    train = clips(motion, max_clips=3, ctx=Context())["clips"]
    # calibrate_retention off: the manual toe contact of the constraint-frame test is placed
    # on this variant's right leg (with the calibrated retention the variant differs and
    # the toe's mean position over those frames is 3.9 mm beyond the leg's reach)
    model = learn(train, k=15, kernel_width=2.0, max_parents=2, candidates=3, restarts=0,
                  score="one_step", calibrate_retention=False, ctx=Context())["model"]
    model = decode(encode(model))  # through the store's codecs, as the graph does
    variants = sample(model, count=2, sigma=0.15, noise_time=0.2,
                      ctx=Context(rng=np.random.default_rng(0)))["variants"]
    cleaned = ik(decode(encode(variants)), ctx=Context())["variants"]
    return path, train, decode(encode(cleaned))


def test_clips_carry_the_source_unit_scale_and_rate(variation_run):
    _, train, variants = variation_run
    for c in (train, variants):
        src = c.attrs["source"]
        assert (src["source_unit"], src["source_scale"]) == ("in", 0.0254)
        assert (src["frame_time_text"], src["source_rate"]) == ("0.008333", 120.0)
        assert c.rate == 30.0
    m = clips_to_motions(variants)[0]
    assert m.attrs["source_scale"] == 0.0254 and m.attrs["frame_time_text"] == "0.008333"


def test_variation_exports_at_the_source_rate_frame_time_and_unit(variation_run, tmp_path):
    path, _, variants = variation_run
    paths = export_clips(variants, tmp_path, "variants")
    assert len(paths) == 2
    size_in = bvh_skeleton_size(path)
    for bvh, m30 in zip(paths, clips_to_motions(variants)):
        assert bvh_frame_time_text(bvh) == bvh_frame_time_text(path) == "0.008333"
        assert bvh_frame_count(bvh) == 4 * (m30.n_frames - 1) + 1
        assert abs(bvh_skeleton_size(bvh) / size_in - 1) < 1e-3, (bvh_skeleton_size(bvh), size_in)
        back = read_bvh(bvh)
        assert back.attrs["source_unit"] == "in" and back.rate == 120.0
        # every 4th exported frame is the model's frame (6 decimals of an inch)
        err = np.abs(motion_positions(back)[::4] - motion_positions(m30)).max()
        assert err < 1e-4, err


def test_ik_output_rate_sets_the_export_rate_and_is_checked(variation_run, tmp_path):
    _, _, variants = variation_run
    out = ik(variants, mode="off", output_rate=60, ctx=Context())["variants"]
    assert out.attrs["output_rate"] == 60.0 and out.rate == 30.0
    (bvh, _) = export_clips(out, tmp_path, "v60")
    assert bvh_frame_time_text(bvh) == "0.01666666667"
    assert bvh_frame_count(bvh) == 2 * (clips_to_motions(out)[0].n_frames - 1) + 1
    with pytest.raises(IKError, match="output_rate"):
        ik(variants, mode="off", output_rate=0.0, ctx=Context())


def test_write_bvh_falls_back_to_the_skeletons_source_unit(variation_run, tmp_path):
    path, _, variants = variation_run
    m = clips_to_motions(variants)[0]
    bare = m.replace(attrs={})  # a stage that made a new motion on the source skeleton
    assert bare.skeleton.attrs["source_scale"] == 0.0254
    out = write_bvh(bare, tmp_path / "bare.bvh")
    assert abs(bvh_skeleton_size(out) / bvh_skeleton_size(path) - 1) < 1e-3


# --------------------------------------------------------------------------- constraint frames


def test_ik_targets_count_and_report_in_exported_frames(variation_run, tmp_path):
    """A target at exported frame N (120 fps) is met at frame N of the exported BVH.

    The model runs at 30 fps: N = 20 is model frame 5.  Read as a model frame, 20
    would land at exported frame 80, so the check at N fails on a missing conversion.
    """
    _, _, variants = variation_run
    one = variants.subset([0])
    sk = one.skeleton
    m30 = clips_to_motions(one)[0]
    n_out = 4 * (m30.n_frames - 1) + 1  # 113 exported frames
    left, right = sk.index("LeftHand"), sk.index("RightHand")
    N = 20
    p30 = motion_positions(m30)
    target = p30[N // 4, left] + [0.0, 0.03, 0.02]  # 3.6 cm from the sampled hand
    far = p30[N // 4, right] + [0.0, 5.0, 0.0]  # out of reach
    ctx = Context()
    # range_margin 1 rad (at most half a DOF's range, the default range_fraction): the
    # contact asks the swinging leg for poses beyond the inputs' joint ranges (within the
    # default 0.025 rad the toe stays 5.7 mm off)
    r = ik(one, targets={"LeftHand": [[N, *target]], "RightHand": [[N + 1, *far]]},
           contacts={"RightToeBase": [[33, 47]]}, range_margin=1.0, ctx=ctx)
    rep = r["report"]
    json.dumps(rep, allow_nan=False)  # a JSON output of the stage
    assert (rep["rate"], rep["output_rate"]) == (30.0, 120.0)
    clip = rep["clips"][0]
    assert clip["output_frames"] == n_out
    hand, miss = clip["targets"]
    assert (hand["effector"], hand["frame"], hand["model_frame"], hand["exported_frame"]) == (
        "LeftHand", N, 5, N)
    assert hand["reached"] and hand["error"] <= rep["tolerance"]
    # N + 1 = 21 rounds to model frame 5, exported frame 20; it is reported there
    assert (miss["frame"], miss["model_frame"], miss["exported_frame"]) == (N + 1, 5, N)
    assert not miss["reached"] and miss["error"] > 4.0
    assert [(u["frame"], u["model_frame"]) for u in clip["unreachable"]
            if u["effectors"] == ["RightHand"]] == [(N, 5)]
    assert any(f"RightHand at frame {N} " in w and "frames at 120 fps" in w
               for w in ctx.warnings), ctx.warnings
    # contacts [33, 47) -> model frames 8..11 (rounded) -> exported frames 32..44
    assert clip["constrained"]["RightToeBase"] == [[32, 45]]
    assert clip["constrained"]["LeftHand"] == [[N, N + 1]]  # a target, not a detected contact
    # in the exported BVH (inches, read back in metres), by forward kinematics
    (bvh,) = export_clips(decode(encode(r["variants"])), tmp_path, "ik")
    back = read_bvh(bvh)
    assert back.rate == 120.0 and back.n_frames == n_out
    p120 = motion_positions(back)
    err = np.linalg.norm(p120[N, left] - target)
    assert err <= rep["tolerance"], err  # measured 1.2e-8 m
    (bvh0,) = export_clips(one, tmp_path, "before")
    assert np.linalg.norm(motion_positions(read_bvh(bvh0))[N, left] - target) > 0.03
    toe = sk.index("RightToeBase")
    held = np.linalg.norm(p120[32:45:4, toe] - p120[32, toe], axis=-1).max()
    assert held <= rep["tolerance"], held  # measured 2.9e-8 m on the model frames


def test_ik_target_frames_outside_the_export_are_refused(variation_run):
    _, _, variants = variation_run
    one = variants.subset([0])
    n_out = 4 * (int(one.lengths[0]) - 1) + 1
    for frame in (n_out, -1):
        with pytest.raises(IKError, match=rf"frame {frame} outside variant0's exported frames "
                                          rf"0\.\.{n_out - 1} \(frames at 120 fps\)") as e:
            ik(one, targets={"LeftHand": [[frame, 0.0, 1.0, 0.0]]}, ctx=Context())
        assert "\n" not in str(e.value)
    with pytest.raises(IKError, match="frame 20.5 is not a frame number"):
        ik(one, targets={"LeftHand": [[20.5, 0.0, 1.0, 0.0]]}, ctx=Context())
    with pytest.raises(IKError, match="frames 20 and 21 fall on one model frame 5"):
        ik(one, targets={"LeftHand": [[20, 0.0, 1.0, 0.0], [21, 0.0, 1.0, 0.0]]}, ctx=Context())
    # at output_rate 60 the exported clip has 2 (F - 1) + 1 frames
    sixty = ik(one, mode="off", output_rate=60, ctx=Context())["variants"]
    n60 = 2 * (int(one.lengths[0]) - 1) + 1
    with pytest.raises(IKError, match=rf"0\.\.{n60 - 1} \(frames at 60 fps\)"):
        ik(sixty, targets={"LeftHand": [[n60, 0.0, 1.0, 0.0]]}, ctx=Context())
    ik(sixty, targets={"LeftHand": [[n60 - 1, 0.0, 1.0, 0.0]]}, ctx=Context())  # the last one
