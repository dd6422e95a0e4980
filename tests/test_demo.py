"""The README's demo command, end to end: every shipped graph on self-generated data."""

import subprocess
from pathlib import Path

import numpy as np
import pytest

from mocapflow.stages.motion.formats.bvh import read_bvh
from mocapflow.stages.motion.formats.c3d import read_c3d

#: The default (quick) demo's budget: the whole demo folder, store included (issue 18).
MAX_BYTES = 150 * 2**20


def _size(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


@pytest.mark.slow
def test_demo_runs_every_graph_and_a_rerun_is_all_hits(demo_run):
    out, cmd, first = demo_run.out, demo_run.cmd, demo_run.proc  # shared with the lock tests
    assert first.returncode == 0, first.stderr[-3000:]
    assert _size(out) <= MAX_BYTES, sorted((_size(d), d.name) for d in out.iterdir())

    capture = read_c3d(out / "data" / "capture" / "seed0" / "markers.c3d")
    assert capture.n_markers >= 300 and len(capture.fragment_labels) > 0
    cleaned = read_c3d(next((out / "skin" / "clean").glob("*/markers.c3d")))
    # cleaning fills holes: fewer missing samples than the raw capture
    assert np.isnan(cleaned.positions).mean() < np.isnan(capture.positions).mean()
    assert next((out / "skin" / "render").glob("*/video.mp4")).stat().st_size > 10_000
    assert next((out / "skin" / "render_modes").glob("*/video.mp4")).stat().st_size > 10_000
    # the animated mesh: one OBJ + PC2 animation, no per-frame files by default
    deform = next((out / "skin" / "deform").glob("*/mesh.obj")).parent
    assert (deform / "mesh.pc2").stat().st_size > 100_000
    assert not list(out.rglob("*.vtp")) and not list(out.rglob("*.pvd"))

    walk = read_bvh(out / "data" / "walk" / "seed0" / "motion.bvh")
    texture = sorted((out / "texture" / "synth").glob("*/motion.bvh"))
    assert len(texture) == 3
    synth = read_bvh(texture[0])
    assert synth.n_frames == 300 and synth.skeleton.names == walk.skeleton.names
    assert len(list((out / "texture" / "strip").glob("*/strip.mp4"))) == 3
    variants = sorted((out / "variation" / "ik").glob("*/*.bvh"))
    assert len(variants) == 5
    plots = {p.name for p in Path(out / "variation" / "plots").glob("*/*.png")}
    assert {"figures_dof_time.png", "figures_dof_dof.png", "figures_pca.png"} <= plots, plots

    # the end of the output says where to look: one line per step, its folder and files
    looks = first.stdout.split("where to look:\n", 1)[1].splitlines()
    for label, want in (("data", "motion.bvh"), ("skin", "video.mp4"), ("texture", "strip.png"),
                        ("variation", ".png")):
        line = next(x for x in looks if x.strip().startswith(f"{label}: "))
        assert f"{out / label}/" in line and want in line, line

    second = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert second.returncode == 0, second.stderr[-3000:]
    step_lines = [line for line in second.stdout.splitlines() if "file(s) in" in line]
    assert len(step_lines) == 4, second.stdout
    assert all("(0 computed," in line for line in step_lines), second.stdout
