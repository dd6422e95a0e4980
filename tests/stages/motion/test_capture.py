"""Dense-marker capture simulator: ground truth, skin motion, occlusion, fragmentation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.codecs import decode, encode
from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.motion.rotations import quat_identity
from mocapflow.stages.motion.simulate.body import skin, skinning_transforms
from mocapflow.stages.motion.simulate.capsules import procedural_body
from mocapflow.stages.motion.simulate.capture import simulate_capture
from mocapflow.stages.motion.simulate.markers import REGIONS
from mocapflow.stages.motion.simulate.optical import (
    fragment_capture,
    marker_visibility,
    segment_distance,
)
from mocapflow.stages.motion.simulate.skeleton import procedural_skeleton
from tests.stages.conftest import WALK_CAPTURE_NOISE, simulated_capture

DATA = Path(__file__).resolve().parents[3] / ".." / "shared" / "data"
NOISE = WALK_CAPTURE_NOISE


def test_capture_shapes_labels_and_noise(sim):
    m, tr = sim.markers, sim.truth
    F, M = 200, 120
    assert m.positions.shape == (F, M, 3) and tr["positions"].shape == (F, M, 3)
    assert m.labels == tr["labels"] and m.rate == 120.0
    # observations = truth + N(0, noise): the measured standard deviation within 10 %
    vis = m.visible
    resid = (m.positions - tr["positions"])[vis]
    assert np.std(resid) == pytest.approx(NOISE, rel=0.1)
    # labelled runs cross the label frame, which is the frame with most visible markers
    lf = tr["label_frame"]
    assert lf == int(np.argmax(tr["visible"].sum(1)))
    assert vis[lf].all(), "every marker is labelled in the calibration pose"
    assert (vis <= tr["visible"]).all()
    # occlusion removes a realistic share (walk: 1-10 %)
    assert 0.90 < tr["visible"].mean() < 0.995


def test_fragments_are_runs_of_their_true_marker(sim):
    m, tr = sim.markers, sim.truth
    fm = tr["fragment_marker"]
    assert len(fm) == m.fragments.shape[1] > 0
    fvis = np.isfinite(m.fragments).all(-1)
    for u in range(len(fm)):
        f = np.flatnonzero(fvis[:, u])
        assert len(f) and np.all(np.diff(f) == 1), "fragments are contiguous"
        if fm[u] >= 0:
            err = np.linalg.norm(m.fragments[f, u] - tr["positions"][f, fm[u]], axis=1)
            assert err.max() < 6 * NOISE
            assert not np.isfinite(m.positions[f, fm[u]]).any(), "labelled and unlabelled overlap"
        else:  # ghosts float 4-10 cm off the skin, away from every marker
            d = np.linalg.norm(m.fragments[f, u][:, None] - tr["positions"][f], axis=-1)
            assert d.min() > 0.02
    # every visible sample is in exactly one trajectory
    covered = m.visible.copy()
    for u in np.flatnonzero(fm >= 0):
        covered[fvis[:, u], fm[u]] = True
    assert (covered == tr["visible"]).all()


def test_markers_ride_on_the_true_mesh(sim):
    tr, mesh = sim.truth, sim.mesh
    assert mesh.vertices.shape[0] == 200 and mesh.faces.shape[1] == 3
    corners = mesh.faces[tr["marker_face"]]  # (M, 3)
    for f in (0, 100, 199):
        skin_pt = np.einsum("mc,mcx->mx", tr["marker_barycentric"], mesh.vertices[f][corners])
        d = np.linalg.norm(tr["positions"][f] - skin_pt, axis=1)
        # the marker centre sits marker_radius (7 mm) above the skin, up to LBS blending
        assert np.median(d) == pytest.approx(tr["marker_radius"], abs=0.002)
        assert d.max() < 0.03


def test_known_non_rigid_skin_motion():
    kw = dict(n_markers=60, n_frames=150, motion="dynamic", rng=3, body_vertices=1200,
              noise=0.0, ghost_rate=0.0, break_rate=0.0)
    rigid = simulated_capture(bulge=0.0, jiggle=0.0, breathing=0.0, **kw)
    soft = simulated_capture(**kw)
    assert np.array_equal(rigid.truth["marker_face"], soft.truth["marker_face"])
    d = np.linalg.norm(soft.truth["positions"] - rigid.truth["positions"], axis=-1)
    assert 0.005 < d.max() < 0.06  # bulges, jiggle and breathing: mm to a few cm
    # without them the markers follow linear-blend skinning exactly
    R, p = skinning_transforms(rigid.body, rigid.motion)
    lbs = skin(rigid.body, R, p, points=rigid.truth["bind_pose"],
               weights=rigid.truth["marker_weights"])
    assert np.abs(lbs - rigid.truth["positions"]).max() < 1e-12
    assert np.abs(lbs - soft.truth["positions"]).max() > 0.005


def test_segment_distance_matches_brute_force():
    rng = np.random.default_rng(0)
    p0, p1, q0, q1 = (rng.normal(size=(60, 3)) for _ in range(4))
    d, t = segment_distance(p0, p1, q0, q1)
    s = np.linspace(0, 1, 201)
    P = p0[:, None] + s[None, :, None] * (p1 - p0)[:, None]
    Q = q0[:, None] + s[None, :, None] * (q1 - q0)[:, None]
    brute = np.linalg.norm(P[:, :, None] - Q[:, None, :], axis=-1).min((1, 2))
    assert np.all(d <= brute + 1e-12) and np.allclose(d, brute, atol=1e-2)
    assert ((t >= 0) & (t <= 1)).all()


def test_visibility_by_ray_casting():
    sk = procedural_skeleton()
    body = procedural_body(sk, n_vertices=1500)
    mot = Motion(sk, np.array([[0.0, 0.93, 0.0]]), quat_identity((1, sk.n_joints)), 120.0)
    R, p = skinning_transforms(body, mot)
    v = skin(body, R, p)[0]
    chest = np.array([0.0, 0.93 + 0.35, 0.0])
    front = v[np.argmax(np.where(np.abs(v[:, 0]) < 0.03, v[:, 2] - 10 * np.abs(v[:, 1] - chest[1]),
                                 -np.inf))]
    marker = (front + [0, 0, 0.007])[None, None]
    normal = np.array([[[0.0, 0.0, 1.0]]])
    cam_front = np.array([[0.0, 1.3, 3.0]])
    cam_back = np.array([[0.0, 1.3, -3.0]])
    cam_side_front = np.array([[2.5, 1.3, 1.5]])
    seen = [marker_visibility(marker, normal, body, R, p, c)[0, 0] for c in
            (cam_front, cam_back, cam_side_front)]
    assert seen == [1, 0, 1]
    # a marker on the back does not face a camera in front
    assert marker_visibility(marker, -normal, body, R, p, cam_front)[0, 0] == 0
    # inner left thigh: the right leg hides it from the right, not from the front right
    lu = sk.index("LeftUpLeg")
    h = 0.93 - 0.30
    sel = np.flatnonzero((body.part == lu) & (np.abs(v[:, 1] - h) < 0.06))
    i = sel[np.argmin(v[sel, 0] + np.abs(v[sel, 2]))]  # innermost, mid-depth
    n_i = np.array([[[-1.0, 0.0, 0.0]]])
    m3 = (v[i] + [-0.007, 0, 0])[None, None]
    assert marker_visibility(m3, n_i, body, R, p, np.array([[-3.0, h, 0.0]]))[0, 0] == 0
    assert marker_visibility(m3, n_i, body, R, p, np.array([[-2.0, h, 2.5]]))[0, 0] == 1


def test_fragment_capture_breaks_runs_and_labels_the_label_frame():
    F, M = 10, 2
    obs = np.random.default_rng(0).normal(size=(F, M, 3))
    vis = np.ones((F, M), bool)
    vis[3:5, 0] = False  # marker 0: runs [0,3) and [5,10)
    vis[:, 1] = [0, 1, 1, 1, 0, 1, 1, 0, 0, 1]
    lab, frags, fm, lf = fragment_capture(obs, vis, rate=100.0, rng=np.random.default_rng(1),
                                          break_rate=0.0, ghost_rate=0.0)
    assert lf == 1  # the first frame with the most visible markers
    assert np.isfinite(lab[:3, 0, 0]).all() and not np.isfinite(lab[3:, 0, 0]).any()
    assert np.isfinite(lab[1:4, 1, 0]).all() and np.isfinite(lab[:, 1, 0]).sum() == 3
    assert np.array_equal(lab[:3, 0], obs[:3, 0])
    runs = sorted((int(np.flatnonzero(np.isfinite(frags[:, u, 0]))[0]), int(fm[u]))
                  for u in range(frags.shape[1]))
    assert runs == [(5, 0), (5, 1), (9, 1)]


def test_stage_is_seeded_and_stores(tmp_path):
    kw = dict(n_markers=40, n_frames=80, motion="walk", body_vertices=1000)
    a = simulate_capture(**kw, seed=0, ctx=Context(part="sim", seed=0))
    b = simulate_capture(**kw, seed=0, ctx=Context(part="sim", seed=0))
    c = simulate_capture(**kw, seed=1, ctx=Context(part="sim", seed=1))
    assert np.array_equal(a["markers"].positions, b["markers"].positions, equal_nan=True)
    assert not np.array_equal(a["markers"].positions, c["markers"].positions, equal_nan=True)
    for key in ("markers", "truth", "mesh", "motion"):
        enc = encode(a[key])
        back = decode(enc)
        assert type(back) is type(a[key])
    truth = decode(encode(a["truth"]))
    assert np.array_equal(truth["positions"], a["truth"]["positions"])
    assert truth["region_names"] == list(REGIONS)


def test_bad_requests():
    with pytest.raises(ValueError, match="n_markers"):
        simulated_capture(n_markers=2, n_frames=10)
    with pytest.raises(ValueError, match="motion: .swim. is not one of"):
        simulated_capture(n_markers=10, n_frames=10, motion="swim")


@pytest.mark.skipif(not (DATA / "mesh" / "makehuman_base.obj").exists(), reason="no shared data")
def test_makehuman_capture():
    sim = simulated_capture(n_markers=80, n_frames=30, motion="walk", rng=0,
                                 body_mesh=str(DATA / "mesh" / "makehuman_base.obj"))
    assert sim.mesh.vertices.shape == (30, 13380, 3)
    assert sim.truth["visible"].mean() > 0.8
    assert sim.markers.visible[sim.truth["label_frame"]].all()
