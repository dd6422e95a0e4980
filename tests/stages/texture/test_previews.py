"""Previews people can read (issue 16, item 4): strip, video and joint-angle plot.

A short synthesis of the CMU walk ``cmu_131_02`` at 30 fps (240 frames, two
constraints, a straight path along +z) is rendered by ``stickfigure`` with the
report, source track and input wired.  Before: the top view took its scale from
the whole motion's range on the vertical axis (the walk's travel), so the figure
was small in its panel (bbox 22-43 % of the panel here, a few pixels on long walks); no path,
no marks; the MP4 was 192 x 192 px with one figure and no floor.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from mocapflow.pipeline import Context
from mocapflow.pipeline.codecs import decode, encode, find_exporter
from mocapflow.stages.motion.ingest import ingest_bvh
from mocapflow.stages.texture.pyramid import build_pyramid
from mocapflow.stages.texture.stickfigure import COLOURS, leg_angles, stickfigure
from mocapflow.stages.texture.synth import synth
from tests.stages.texture.conftest import seeded_context

RATE = 30.0
CONSTRAINTS = [[20, 40], [100, 190]]  # input frames at the file's 120 fps, output at 30 fps
PATH = [[0.0, 0.0], [0.0, 3.0]]
VIDEO_STEP = 2


def _rgb(hex_colour: str) -> np.ndarray:
    return np.array([int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)])


def _near(img: np.ndarray, hex_colour: str, tol: int = 40) -> np.ndarray:
    """Pixels within ``tol`` (per channel) of a colour."""
    return (np.abs(img.astype(int) - _rgb(hex_colour)) <= tol).all(axis=-1)


def _figure_pixels(img: np.ndarray) -> np.ndarray:
    """Bones: dark, or the constrained frames' red."""
    return (img.max(axis=-1) < 80) | _near(img, COLOURS["constraint"])


def _crop(img: np.ndarray, box: list[int], inset: int = 2) -> np.ndarray:
    x0, y0, x1, y1 = box
    return img[y0 + inset:y1 - inset, x0 + inset:x1 - inset]


@pytest.fixture(scope="module")
def run(shared_data):
    motion = ingest_bvh(str(shared_data / "bvh" / "cmu_131_02.bvh"), rate=RATE,
                        ctx=Context())["motion"]
    r = synth(build_pyramid(motion, levels=3), motion, seed=0, ctx=seeded_context(0),
              length=240, levels=3, constraints=CONSTRAINTS, path=PATH, output_rate=RATE)
    strip = stickfigure(r["motion"], r["report"], r["source_index"], motion, n_panels=8,
                        path=PATH, video=True, video_step=VIDEO_STEP, video_max_frames=60,
                        ctx=Context())["strip"]
    return motion, r, strip


def test_top_view_is_scaled_by_the_figure_and_draws_the_path_and_root_trace(run):
    _, r, strip = run
    top = strip.attrs["panels"]["top"]
    assert len(top) == len(strip.frames) >= 8
    shares = []
    for box in top:
        pan = _crop(strip.image, box)
        ys, xs = np.nonzero(_figure_pixels(pan))
        shares.append(max(np.ptp(xs) / pan.shape[1], np.ptp(ys) / pan.shape[0]))
        assert shares[-1] >= 0.3, (box, shares[-1])
        # the path runs along +z: a vertical green line through the panel (a few pixels
        # wide, over most of its height); the root trace in blue too
        gy, gx = np.nonzero(_near(pan, COLOURS["path"], tol=30))
        assert gy.size > 40 and np.ptp(gy) > 0.5 * pan.shape[0]
        assert np.ptp(gx) < 0.06 * pan.shape[1], np.ptp(gx)
        assert _near(pan, COLOURS["root"], tol=30).sum() > 20
    assert np.median(shares) >= 0.45, shares  # (before: 0.22-0.43 on this synthesis)
    # without a path no green at all (the colour check can fail)
    bare = stickfigure(r["motion"], n_panels=3, views=["top"], angles=False,
                       ctx=Context())["strip"]
    for box in bare.attrs["panels"]["top"]:
        assert _near(_crop(bare.image, box), COLOURS["path"], tol=30).sum() == 0


def test_constrained_frames_are_lettered_panels_and_seams_are_on_the_timeline(run):
    _, r, strip = run
    rep = r["report"]
    cons = strip.attrs["constraints"]
    assert [c["letter"] for c in cons] == ["A", "B"]
    assert [c["output_frame"] for c in cons] == rep["constraint_output_frames"] == [40, 190]
    assert [c["input_frame"] for c in cons] == [i for i, _ in rep["constraints_synthesis"]]
    assert strip.attrs["seams"] == rep["seams"] and len(rep["seams"]) >= 2
    # constrained frames are panels, drawn red; the other panels have no red
    side = dict(zip(strip.frames, strip.attrs["panels"]["side"]))
    assert {40, 190} <= set(side)
    for f, box in side.items():
        red = _near(_crop(strip.image, box), COLOURS["constraint"]).sum()
        assert (red > 100) if f in (40, 190) else (red == 0), (f, red)
    # each seam is a purple line at its frame on the timeline
    (x0, y0, x1, y1), = strip.attrs["panels"]["timeline"]
    purple = _near(strip.image[y0:y1], COLOURS["seam"], tol=30).any(axis=0)
    n = rep["output_frames"]
    for s in rep["seams"]:
        x = x0 + (s + 0.5) / n * (x1 - x0)
        assert purple[int(x) - 2:int(x) + 3].any(), s
    assert purple[:x0].sum() == 0 and purple[x0:x1].sum() < 4 * len(rep["seams"]) + 4


def test_video_shows_input_and_output_side_by_side_on_a_floor_grid(run):
    motion, r, strip = run
    video = strip.video
    assert video.shape[0] == 60 and video.shape[1] >= 480
    assert strip.rate == RATE / VIDEO_STEP
    N, H, W, _ = video.shape
    for k in (0, 30, 59):
        frame = video[k]
        dark = ndimage.binary_dilation(frame.max(axis=-1) < 80, iterations=2)
        lab, n = ndimage.label(dark)
        boxes = ndimage.find_objects(lab)
        figures = sorted(b[1].start for b in boxes if b[0].stop - b[0].start > 0.25 * H)
        assert len(figures) == 2, (k, figures)  # two stick figures (text is small)
        assert figures[0] < W / 2 <= figures[1]  # one in each half: input | output
        grid = _near(frame, COLOURS["grid"], tol=12)
        for half in (grid[:, :W // 2], grid[:, W // 2:]):
            assert half.sum() > 0.005 * half.size
            assert np.ptp(np.nonzero(half.any(axis=0))[0]) > 0.8 * half.shape[1]
    # the constrained frame 40 is flagged red in the output, frame 100 is not
    body = slice(0, int(0.88 * H))
    flagged = _near(video[40 // VIDEO_STEP, body, W // 2:], COLOURS["constraint"]).sum()
    plain = _near(video[100 // VIDEO_STEP, body], COLOURS["constraint"]).sum()
    assert flagged > 200 and plain == 0, (flagged, plain)


def test_angle_plot_letters_the_constraints_on_output_and_input(run, tmp_path):
    motion, r, strip = run
    assert strip.angles is not None and strip.angles.shape[0] >= 400
    assert _near(strip.angles, COLOURS["constraint"]).sum() > 100
    lettered = [(c["letter"], c["output_frame"], c["input_frame"])
                for c in strip.attrs["constraints"]]
    assert len(lettered) == 2
    names, out_ang = leg_angles(r["motion"])
    _, in_ang = leg_angles(motion)
    assert len(names) == 4 and any("knee" in n.lower() for n in names)
    for _, j, i in lettered:  # a constrained output pose is its input pose: same angles
        np.testing.assert_allclose(out_ang[j], in_ang[i], atol=1.0)
    back = decode(encode(strip))
    np.testing.assert_array_equal(back.angles, strip.angles)
    assert back.attrs["constraints"] == strip.attrs["constraints"]
    files = find_exporter("stickstrip")(strip, tmp_path, "walk")
    assert [f.name for f in files] == ["walk.png", "walk.mp4", "walk_angles.png"]
    assert all(f.stat().st_size > 1000 for f in files)
