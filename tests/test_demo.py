"""The README's demo command, end to end: every shipped graph on self-generated data."""

import subprocess
from pathlib import Path

import numpy as np
import pytest

from mocapflow.stages.motion.formats.bvh import read_bvh
from mocapflow.stages.motion.formats.c3d import read_c3d


@pytest.mark.slow
def test_demo_runs_every_graph_and_a_rerun_is_all_hits(demo_run):
    out, cmd, first = demo_run.out, demo_run.cmd, demo_run.proc  # shared with the lock tests
    assert first.returncode == 0, first.stderr[-3000:]

    capture = read_c3d(out / "data" / "capture" / "seed0" / "markers.c3d")
    assert capture.n_markers >= 300 and len(capture.fragment_labels) > 0
    cleaned = read_c3d(next((out / "skin" / "clean").glob("*/markers.c3d")))
    # cleaning fills holes: fewer missing samples than the raw capture
    assert np.isnan(cleaned.positions).mean() < np.isnan(capture.positions).mean()
    assert next((out / "skin" / "render").glob("*/video.mp4")).stat().st_size > 10_000
    assert list((out / "skin" / "deform").glob("*/mesh.pvd"))

    walk = read_bvh(out / "data" / "walk" / "seed0" / "motion.bvh")
    texture = sorted((out / "texture" / "synth").glob("*/motion.bvh"))
    assert len(texture) == 5
    synth = read_bvh(texture[0])
    assert synth.n_frames == 600 and synth.skeleton.names == walk.skeleton.names
    variants = sorted((out / "variation" / "ik").glob("*/*.bvh"))
    assert len(variants) == 15
    assert list(Path(out / "variation" / "plots").glob("*/*.png"))

    second = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert second.returncode == 0, second.stderr[-3000:]
    step_lines = [line for line in second.stdout.splitlines() if "file(s) in" in line]
    assert len(step_lines) == 4, second.stdout
    assert all("(0 computed," in line for line in step_lines), second.stdout
