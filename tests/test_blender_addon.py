"""The Blender add-on (``mocapflow blender-addon``): packed, installed and used in Blender.

Blender runs headless (``blender -b --factory-startup``) on
``tests/blender_addon_scene.py``, which installs the zip in a throw-away user
folder, points the add-on's "mocapflow command" preference at this interpreter
(``python -m mocapflow``) and uses the add-on's operators as a user would.  Debian's
``blender`` is installed by the shared fixture when missing and possible, else the
Blender tests skip with the reason.  One texture run (the figure-8 walk, 450 frames
at 120 fps, one seed) is shared by the texture checks; the marker and mesh imports
use the demo's outputs (the session's one demo run, as the mesh-cache test).
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest

from mocapflow.blender import ADDON_NAME
from mocapflow.blender.c3d import MISSING, C3DReadError, read_c3d_points, sample_state
from mocapflow.stages.motion.formats.c3d import read_c3d
from tests.stages.motion.test_mesh_export_usd import demo_deformed_mesh
from tests.stages.skin.test_blender_meshcache import blender  # noqa: F401 (fixture)

SCENE = Path(__file__).with_name("blender_addon_scene.py")
DATA = (Path(__file__).resolve().parents[1] / ".." / "shared" / "data").resolve()
WALK = DATA / "bvh" / "pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh"
C3DS = [DATA / "c3d" / "btkdata_c3dorg_Eb015pr.c3d", DATA / "c3d" / "ezc3d-testFiles_Qualisys.c3d"]
LENGTH = 450  # output frames at 120 fps: not a multiple of the pyramid's 2^5
CONSTRAINTS = [(100, 40), (600, 300)]  # (input frame, output frame)
RADIUS = 0.8  # metres: a closed Bezier circle, 5.03 m around
FRAME = 60  # the frame the marker and mesh imports are compared at


def _need(path: Path) -> Path:
    """A shared sample file (``<repo>/../shared/data``); skips the test when absent."""
    if not path.is_file():
        pytest.skip(f"shared sample data not found: {path}")
    return path


def _addon(tmp: Path) -> Path:
    zpath = tmp / "mocapflow_blender.zip"
    p = subprocess.run([sys.executable, "-m", "mocapflow", "blender-addon", "--out", str(zpath)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    return zpath


def _scene(blender: str, tmp: Path, mode: str, *args: str) -> dict:  # noqa: F811
    """Run the scene script in Blender (add-on installed in ``tmp``); its JSON."""
    out = tmp / f"{mode}.json"
    home = tmp / "blender-user"
    env = {**os.environ, "BLENDER_USER_CONFIG": str(home / "config"),
           "BLENDER_USER_SCRIPTS": str(home / "scripts")}
    cmd = shlex.join([sys.executable, "-m", "mocapflow"])
    p = subprocess.run([blender, "-b", "--factory-startup", "--python-exit-code", "1",
                        "--python", str(SCENE), "--", str(_addon(tmp)), cmd,
                        str(tmp / "work"), str(out), mode, *args],
                       capture_output=True, text=True, timeout=600, env=env)
    if p.returncode != 0:  # short lines: a CI log folds long ones
        said = json.loads(out.read_text()).get("error", "") if out.is_file() else ""
        lines = [w for ln in (said or p.stdout + p.stderr).strip().splitlines()[-25:]
                 for w in textwrap.wrap(ln, 200) or [""]]
        pytest.fail(f"Blender scene {mode!r} failed (exit {p.returncode}):\n"
                    + "\n".join(lines), pytrace=False)
    return json.loads(out.read_text())


# --------------------------------------------------------------------------- without Blender


def test_blender_addon_command_writes_the_zip_and_the_folder(tmp_path):
    with zipfile.ZipFile(_addon(tmp_path)) as z:
        names = sorted(z.namelist())
        init = z.read(f"{ADDON_NAME}/__init__.py").decode()
    assert names == [f"{ADDON_NAME}/__init__.py", f"{ADDON_NAME}/c3d.py"]
    assert "bl_info" in init and "def register" in init
    assert "import mocapflow" not in init and "from mocapflow" not in init  # CLI only
    p = subprocess.run([sys.executable, "-m", "mocapflow", "blender-addon", "--out",
                        str(tmp_path / "addons")], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and (tmp_path / "addons" / ADDON_NAME / "c3d.py").is_file()
    p = subprocess.run([sys.executable, "-m", "mocapflow", "blender-addon", "--out",
                        str(tmp_path / "missing" / "x.zip")], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2 and "missing does not exist" in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("path", C3DS, ids=lambda p: p.stem)
def test_addon_c3d_reader_matches_ours(path):
    """The add-on's own C3D reader (no ezc3d in Blender) against mocapflow's."""
    got = read_c3d_points(str(_need(path)))
    ours = read_c3d(path)
    idx = [got.labels.index(lb) for lb in ours.labels]
    pos = np.asarray(got.positions)[:, idx]
    assert pos.shape == ours.positions.shape
    assert np.array_equal(np.isnan(pos), np.isnan(ours.positions))
    assert np.nanmax(np.abs(pos - ours.positions)) < 1e-9  # metres, both from float32
    assert got.rate == ours.rate
    state = np.asarray(sample_state(got))[:, idx]
    assert np.array_equal(state == MISSING, np.isnan(ours.positions[..., 0]))


def test_addon_c3d_reader_rejects_bad_files(tmp_path):
    data = _need(C3DS[0]).read_bytes()
    (tmp_path / "cut.c3d").write_bytes(data[: len(data) // 2])
    with pytest.raises(C3DReadError, match="data block truncated"):
        read_c3d_points(str(tmp_path / "cut.c3d"))
    (tmp_path / "text.c3d").write_bytes(b"not a c3d file" * 100)
    with pytest.raises(C3DReadError, match="not a C3D file"):
        read_c3d_points(str(tmp_path / "text.c3d"))


# --------------------------------------------------------------------------- texture in Blender


@pytest.fixture(scope="module")
def texture(blender, tmp_path_factory) -> dict:  # noqa: F811
    """The add-on's texture run: take imported, 2 ``c:`` markers, a closed curve, 450
    frames; then, in the same Blender session, two BVH files imported as variants."""
    tmp = tmp_path_factory.mktemp("texture")
    variants = [tmp / "variants" / "variant0.bvh", tmp / "variants" / "variant1.bvh"]
    variants[0].parent.mkdir()
    for f in variants:  # one folder, as a variation export's
        f.write_bytes(_need(WALK).read_bytes())
    pairs = ",".join(f"{i}:{j}" for i, j in CONSTRAINTS)
    return _scene(blender, tmp, "texture", str(_need(WALK)), str(LENGTH), pairs, str(RADIUS),
                  ",".join(map(str, variants)))


def test_texture_result_has_the_requested_length(texture):
    assert texture["frame_range"] == [1.0, float(LENGTH)]  # scene frames 1..450
    assert texture["keys"] == [LENGTH]  # one key per frame on every F-curve
    assert texture["fps"] == 120.0  # the take's rate
    assert texture["report"]["output_frames"] == LENGTH and texture["report"]["loop"]
    assert texture["copy"] != texture["source"]  # a copy of the armature


def test_texture_result_holds_the_constraints(texture):
    got = {(c["input"], c["output"]): c for c in texture["constraints"]}
    assert set(got) == set(CONSTRAINTS)
    for c in got.values():  # root-relative pose at the marker's frame vs the input frame
        assert c["max_mm"] < 1.0 and c["max_deg"] < 0.1, c
        assert c["later_deg"] > 1.0, c  # 0.1 s later the pose differs: not trivially true
    markers = dict((name, frame) for name, frame in texture["markers"] if name != "seam")
    for i, j in CONSTRAINTS:
        assert markers[f"c:{i}"] == markers[f"held c:{i}"] == 1 + j
    assert any(name == "seam" for name, _ in texture["markers"])


def test_synthesize_reports_a_bad_scene_in_one_line(texture):
    errors = texture["errors"]
    assert "select the armature of the source take" in errors["no_armature"]
    assert "marker 'c:abc': expected c:<input frame>" in errors["bad_marker"]
    assert "cannot run '/nonexistent/mocapflow'" in errors["no_command"]


def test_texture_result_closes_the_loop_on_the_path(texture):
    # the root's last -> first step is an ordinary step, and the walk follows the circle
    assert texture["root_wrap"] < 1.5 * texture["root_step_median"], texture
    assert texture["root_to_curve_max"] < 0.15  # metres off the circle (hip sway)
    assert abs(texture["root_travel"] / (2 * np.pi * RADIUS) - 1) < 0.1


def test_texture_result_pose_wraps_like_an_ordinary_step(texture):
    # with foot IK on: its corrections are periodic on a loop (root.foot_corrections,
    # cyclic); solved on an open interval the toes jumped 2-2.5x the largest step here
    print(f"body wrap {texture['body_wrap']:.4f} m, largest ordinary step "
          f"{texture['body_step_max']:.4f} m")
    assert texture["body_wrap"] <= texture["body_step_max"], texture


def test_variants_import_as_armatures_on_a_grid(texture):
    got = texture["motions"]
    assert [Path(f).name for f in got["files"]] == ["variant0.bvh", "variant1.bvh"]
    assert got["scales"] == [0.0254, 0.0254]  # the walk is in inches
    assert np.allclose(got["locations"], [[0, 0, 0], [2.0, 0, 0]])  # 2 m apart
    assert got["frames"] == [[1.0, 1064.0]] * 2 and got["fps"] == 120.0


# --------------------------------------------------------------------------- demo outputs


def _store_output(demo_run, node: str, output: str):
    from mocapflow.pipeline import registry
    from mocapflow.pipeline.api import _decode
    from mocapflow.pipeline.show import find_node_entry
    from mocapflow.pipeline.store import Store

    registry.discover()
    store = Store(demo_run.out / "store")
    stage, key = find_node_entry(store, node)
    return _decode(store.load_outputs(stage, key)[output])


@pytest.mark.slow
def test_cleaned_markers_import_as_labelled_empties(demo_run, blender, tmp_path):  # noqa: F811
    assert demo_run.proc.returncode == 0, demo_run.proc.stderr[-3000:]
    c3d = next((demo_run.out / "skin" / "clean").glob("*/markers.c3d"))
    ours = _store_output(demo_run, "clean", "markers")
    got = _scene(blender, tmp_path, "markers", str(c3d), str(FRAME))
    assert got["labels"] == list(ours.labels)  # count and labels, in order
    assert got["fragments"] == list(ours.fragment_labels)
    pos = np.asarray(got["positions"])
    ok = np.isfinite(ours.positions[FRAME]).all(axis=-1)
    assert ok.mean() > 0.8
    assert np.abs(pos[ok] - ours.positions[FRAME][ok]).max() < 1e-5  # metres
    state = np.where(ok, ours.status[FRAME], MISSING)
    assert np.array_equal(got["states"], state)
    assert got["fps"] == pytest.approx(ours.rate)
    assert np.allclose(got["up"], [0, 0, 1], atol=1e-6)  # the file's up (+Y, POINT:Y_SCREEN) is Z


@pytest.mark.slow
def test_deformed_mesh_imports_as_one_animated_object(demo_run, blender, tmp_path):  # noqa: F811
    assert demo_run.proc.returncode == 0, demo_run.proc.stderr[-3000:]
    obj = next((demo_run.out / "skin" / "deform").glob("*/mesh.obj"))
    mesh = demo_deformed_mesh(demo_run)
    got = _scene(blender, tmp_path, "mesh", str(obj), str(FRAME))
    assert got["objects"] == 1 and got["vertices"] == mesh.vertices.shape[1]
    pos = np.asarray(got["positions"])
    assert np.abs(pos - mesh.vertices[FRAME]).max() < 1e-5  # metres (float32 cache)
    assert np.abs(pos - mesh.vertices[FRAME + 1]).max() > 1e-4  # the frame matters
    assert got["frame_end"] == mesh.vertices.shape[0]  # scene frames 1..F
    assert np.allclose(got["up"], [0, 0, 1], atol=1e-6)  # the mesh's up (+Y) is Blender's Z
