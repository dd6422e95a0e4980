"""The demo's deformed body opened in Blender 3.4 as one animation (rest OBJ + PC2 cache).

Blender runs headless (``blender -b``) with its built-in OBJ importer and Mesh Cache
modifier (``tests/stages/skin/blender_meshcache.py``).  Debian's ``blender`` package
is installed in the fixture when it is missing and this is a Debian machine where we
may (root with ``apt-get``); otherwise the test is skipped with the reason.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.stages.motion.test_mesh_export_usd import demo_deformed_mesh

SCRIPT = Path(__file__).with_name("blender_meshcache.py")
FRAME = 100

@pytest.fixture(scope="session")
def blender() -> str:
    """Path of a ``blender`` executable (Debian's, installed here if need be)."""
    found = shutil.which("blender")
    if found:
        return found
    if sys.platform != "linux" or not shutil.which("apt-get") or os.geteuid() != 0:
        pytest.skip("blender is not installed and cannot be installed here (needs root and "
                    "apt-get): `apt-get install blender` to run this test")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    install = ["apt-get", "install", "-y", "-q", "--no-install-recommends", "blender"]
    try:  # about 30 s where the mirror is near; bounded so CI stays in its budget
        p = subprocess.run(install, capture_output=True, text=True, env=env, timeout=240)
        if p.returncode != 0:  # package lists missing on a fresh machine: update once
            subprocess.run(["apt-get", "update", "-q"], capture_output=True, env=env,
                           timeout=120)
            p = subprocess.run(install, capture_output=True, text=True, env=env, timeout=240)
    except subprocess.TimeoutExpired as e:
        pytest.skip(f"installing Debian's blender took over {e.timeout:.0f} s; skipped")
    if p.returncode != 0 or not shutil.which("blender"):
        pytest.skip(f"could not install Debian's blender: {p.stderr.strip()[-300:]}")
    return shutil.which("blender")


@pytest.mark.slow
def test_demo_mesh_imports_into_blender_as_one_animation(demo_run, blender, tmp_path):
    assert demo_run.proc.returncode == 0, demo_run.proc.stderr[-3000:]
    folder = next((demo_run.out / "skin" / "deform").glob("*/mesh.pc2")).parent
    mesh = demo_deformed_mesh(demo_run)  # the same frame, from the store
    ours = mesh.vertices[FRAME]
    out = tmp_path / "blender.json"
    p = subprocess.run([blender, "-b", "--factory-startup", "--python-exit-code", "1",
                        "--python", str(SCRIPT), "--", str(folder / "mesh.obj"),
                        str(folder / "mesh.pc2"), str(FRAME), str(out)],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, (p.stdout[-2000:], p.stderr[-2000:])
    got = json.loads(out.read_text())
    assert got["objects"] == 1 and got["vertices"] == len(ours)
    err = np.abs(np.asarray(got["positions"]) - ours).max()
    assert err < 1e-5, err  # metres (float32 cache)
    # a neighbouring frame differs (the comparison is not trivially true)
    other = mesh.vertices[FRAME + 1]
    assert np.abs(np.asarray(got["positions"]) - other).max() > 1e-4
