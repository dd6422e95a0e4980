"""The clean stage (Park & Hodgins 2006 §4): merge, PCA fill, local-frame smoothing."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.codecs import decode, encode
from mocapflow.stages.metrics.cleaning import gap_mask, region_errors, score_merges
from mocapflow.stages.motion.datatypes import Markers, Mesh
from mocapflow.stages.motion.formats.c3d import read_c3d
from mocapflow.stages.motion.rotations import quat_from_rotvec, quat_to_matrix
from mocapflow.stages.skin.clean import (
    STATUS,
    CleanError,
    _smooth_chunk,
    _smooth_run,
    _smooth_runs,
    clean,
    frame_weights,
    smooth_local,
)
from mocapflow.stages.skin.predict import predict_missing
from mocapflow.stages.skin.surface import MarkerSurface, SurfaceFileError, build_marker_surface
from tests.stages.conftest import WALK_CAPTURE_NOISE

DATA = Path(__file__).resolve().parents[3] / ".." / "shared" / "data"
NOISE = WALK_CAPTURE_NOISE


@pytest.fixture(scope="module")
def cleaned(sim):
    ctx = Context(part="sim")
    res = clean(sim.markers, ctx=ctx)
    out, rep = res["markers"], res["report"]
    surf = MarkerSurface.from_mesh(res["surface"])
    return out, rep, surf, ctx


def perfectly_merged(sim) -> Markers:
    m, tr = sim.markers, sim.truth
    obs = m.positions.copy()
    fv = np.isfinite(m.fragments).all(-1)
    for u in np.flatnonzero(tr["fragment_marker"] >= 0):
        obs[fv[:, u], tr["fragment_marker"][u]] = m.fragments[fv[:, u], u]
    return m.replace(positions=obs, fragments=np.zeros((m.n_frames, 0, 3)), fragment_labels=[])


# --------------------------------------------------------------------------- Table 1 / 2


def test_table1_merges_without_mistakes(sim, cleaned):
    out, rep, surf, ctx = cleaned
    m, tr = sim.markers, sim.truth
    sc = score_merges(rep["merges"], m.fragment_labels, tr["fragment_marker"], m.labels)
    assert sc["wrong"] == 0 and sc["ghosts_merged"] == 0
    assert sc["merged"] >= 0.9 * sc["mergeable"]
    t1 = rep["table1"]
    U = m.fragments.shape[1]
    assert t1["fragments_before"] == m.n_markers + U
    assert t1["fragments_after"] == m.n_markers + U - sc["merged"]
    assert out.fragments.shape[1] == U - sc["merged"]
    # holes: what is still missing after merging; all of them filled
    assert t1["holes"] == int((rep["status"] != STATUS["observed"]).sum()
                              - (rep["status"] == STATUS["merged"]).sum())
    assert t1["left_unfilled"] == 0 and np.isfinite(out.positions).all()
    assert not rep["never_visible"] and not rep["too_few_neighbours"]
    assert ctx.warnings == []


def test_cleaned_capture_is_close_to_the_truth(sim, cleaned):
    out, rep, surf, _ = cleaned
    tr = sim.truth
    st = rep["status"]
    err = np.linalg.norm(out.positions - tr["positions"], axis=-1)
    raw = np.linalg.norm(sim.markers.positions - tr["positions"], axis=-1)[st == 0]
    # measured samples: the local-frame smoother removes noise (raw mean ~0.48 mm)
    assert err[st == 0].mean() < 0.85 * raw.mean()
    assert err[st <= 1].max() < 8 * NOISE
    # filled occlusion holes, normalised by the mean neighbour distance (~12 cm here)
    e = region_errors(out.positions, tr["positions"], st == STATUS["filled"], tr["region"],
                      surf.mean_distance)["all"]
    assert e["unfilled"] == 0 and e["mean"] < 0.1 and e["max"] < 0.4


def test_table2_gaps_in_known_data(sim):
    base = perfectly_merged(sim)
    tr = sim.truth
    rng = np.random.default_rng(5)
    mask = gap_mask(base.visible, tr["reference_pose"], rate=base.rate, duration=0.5,
                    fraction=0.1, clustered=False, rng=rng)
    assert mask.sum() > 400
    gapped = base.replace(positions=np.where(mask[..., None], np.nan, base.positions))
    res = clean(gapped, merge=False, ctx=Context())
    out, rep = res["markers"], res["report"]
    surf = MarkerSurface.from_mesh(res["surface"])
    e = region_errors(out.positions, tr["positions"], mask, tr["region"], surf.mean_distance)
    assert e["all"]["unfilled"] == 0 and rep["fill"]["regression"] > 0.9 * mask.sum()
    # regression fill (default): mean 0.015, max 0.08 of the mean neighbour distance here
    # (200 frames, 120 markers at ~12 cm: little to learn from); 1.6 mm mean
    assert e["all"]["mean"] < 0.02 and e["all"]["max"] < 0.12
    assert e["all"]["mean_mm"] < 2.2
    # the paper's local PCA (fill_model="pca"): mean 0.016, 1.9 mm
    res = clean(gapped, merge=False, fill_model="pca", ctx=Context())
    outp, repp = res["markers"], res["report"]
    ep = region_errors(outp.positions, tr["positions"], mask, tr["region"],
                       surf.mean_distance)["all"]
    assert ep["unfilled"] == 0 and "regression" not in repp["fill"]
    assert ep["mean"] < 0.03 and e["all"]["mean"] < 0.95 * ep["mean"]


def test_gap_mask_places_gaps_after_first_frame():
    rng = np.random.default_rng(0)
    vis = rng.random((300, 40)) < 0.9
    ref = rng.normal(size=(40, 3))
    for clustered in (False, True):
        mask = gap_mask(vis, ref, rate=100.0, duration=0.5, fraction=0.25, clustered=clustered,
                        rng=np.random.default_rng(1), first_frame=120)
        assert not mask[:120].any() and (mask <= vis).all()
        assert len(np.flatnonzero(mask.any(0))) == 10  # ceil(25 % of 40) markers
        runs = mask[120:].sum(0)
        assert runs.max() <= 50 and runs[runs > 0].mean() > 35  # 0.5 s, minus occlusion
    with pytest.raises(ValueError, match="first_frame"):
        gap_mask(vis, ref, rate=100.0, duration=0.5, fraction=0.1, clustered=False,
                 rng=rng, first_frame=300)


# --------------------------------------------------------------------------- exact cases


def rigid_capture(F: int = 60, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Markers on a rigid curved patch turning and translating: (F, M, 3), rest (M, 3)."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(-0.15, 0.15, 7), np.linspace(-0.15, 0.15, 7))
    rest = np.stack([u.ravel(), v.ravel(), 0.5 * (u.ravel() ** 2 + v.ravel() ** 2)], 1)
    rest += rng.normal(0, 0.004, rest.shape)
    rv = np.cumsum(rng.normal(0, 0.05, (F, 3)), axis=0)
    R = quat_to_matrix(quat_from_rotvec(rv))
    t = np.cumsum(rng.normal(0, 0.01, (F, 3)), axis=0)
    return np.einsum("fij,mj->fmi", R, rest) + t[:, None], rest


def test_rigid_motion_is_predicted_and_filled_exactly():
    P, rest = rigid_capture()
    F, M, _ = P.shape
    gapped = P.copy()
    rng = np.random.default_rng(1)
    holes = rng.random((F, M)) < 0.15
    holes[0] = False  # a complete reference frame
    gapped[holes] = np.nan
    surf = build_marker_surface(P[0], positions=gapped)
    E = predict_missing(gapped, P[0], surf.neighbours, rigidity=surf.rigidity)
    ok = holes & np.isfinite(E).all(-1)
    assert ok.sum() > 0.95 * holes.sum()
    assert np.abs(E[ok] - P[ok]).max() < 1e-9
    m = Markers(gapped, [f"p{i}" for i in range(M)], 100.0)
    res = clean(m, merge=False, smooth_iterations=0, ctx=Context())
    out, rep = res["markers"], res["report"]
    assert rep["table1"]["left_unfilled"] == 0
    assert np.abs(out.positions - P).max() < 1e-6


def test_fragments_of_a_rigid_patch_are_merged_back():
    P, rest = rigid_capture(F=80, seed=2)
    F, M, _ = P.shape
    pos = P.copy()
    frags = []
    truth = []
    rng = np.random.default_rng(3)
    starts = []
    for m in rng.choice(M, 12, replace=False):
        a = int(rng.integers(5, 60))
        starts.append(a)
        b = a + int(rng.integers(3, 15))
        pos[a:, m] = np.nan  # labelled run ends at a
        for lo, hi in ((a + 2, b), (b + 3, F)):  # two unlabelled pieces after short gaps
            f = np.full((F, 3), np.nan)
            f[lo:hi] = P[lo:hi, m]
            frags.append(f)
            truth.append(m)
    ghost = np.full((F, 3), np.nan)
    a0 = starts[0]  # in the first marker's 2-frame hole (which stays a hole), 30 cm away
    ghost[a0:a0 + 2] = P[a0:a0 + 2, truth[0]] + [0.3, 0, 0]
    frags.append(ghost)
    truth.append(-1)
    fr = np.stack(frags, axis=1)
    labels = [f"p{i}" for i in range(M)]
    m = Markers(pos, labels, 100.0, fragments=fr,
                fragment_labels=[f"*{u + 1}" for u in range(fr.shape[1])])
    res = clean(m, smooth_iterations=0, ctx=Context())
    out, rep = res["markers"], res["report"]
    sc = score_merges(rep["merges"], m.fragment_labels, np.array(truth), labels)
    assert sc["wrong"] == 0 and sc["merged"] == len(truth) - 1
    rej = {r["fragment"]: r["reason"] for r in rep["rejections"]}
    assert list(rej) == [f"*{len(truth)}"] and "eps1" in rej[f"*{len(truth)}"]
    merged = rep["status"] == STATUS["merged"]
    assert np.abs(out.positions[merged] - P[merged]).max() < 1e-12
    assert np.abs(out.positions - P).max() < 1e-6  # the short gaps filled exactly


def test_smoother_keeps_lines_and_removes_noise():
    t = np.linspace(0, 1, 50)[:, None]
    line = np.hstack([t, 2 * t, -t])
    assert np.abs(_smooth_run(line, 0.1, 20) - line).max() < 1e-12
    rng = np.random.default_rng(0)
    noisy = line + rng.normal(0, 0.01, line.shape)
    out = _smooth_run(noisy, 0.1, 20)
    assert np.std(out - line) < 0.7 * np.std(noisy - line)


def test_runs_smoothed_at_once_equal_each_run_alone():
    """The smoother's vectorised form (every run of every marker in one array) gives,
    bit for bit, each run smoothed on its own by ``x ← x − λ Δ⁴x`` with odd-reflected
    ends (written out here); runs under 5 samples and samples outside the runs stay."""
    rng = np.random.default_rng(3)
    y = rng.normal(0, 0.01, (400, 3)) + np.linspace(0, 1, 400)[:, None]
    starts = np.array([0, 5, 9, 60, 61, 200, 395])
    stops = np.array([5, 9, 60, 61, 180, 395, 400])
    got = _smooth_runs(y, starts, stops, 0.1, 10)
    want = y.copy()
    for a, b in zip(starts, stops):
        if b - a < 5:
            continue
        r = y[a:b].copy()
        for _ in range(10):
            pad = np.concatenate([2 * r[:1] - r[2:0:-1], r, 2 * r[-1:] - r[-2:-4:-1]])
            r -= 0.1 * (pad[:-4] - 4 * pad[1:-3] + 6 * pad[2:-2] - 4 * pad[3:-1] + pad[4:])
        want[a:b] = r
    np.testing.assert_array_equal(got, want)
    assert np.array_equal(got[180:200], y[180:200]) and np.array_equal(got[5:9], y[5:9])
    assert not np.allclose(got[9:60], y[9:60])


def test_smoothing_in_the_local_frame_keeps_fast_rigid_motion():
    P, rest = rigid_capture(F=120)
    # fast spin: smoothing global coordinates would cut corners, the local frame does not
    R = quat_to_matrix(quat_from_rotvec(np.outer(np.linspace(0, 6 * np.pi, 120), [0, 0, 1])))
    P = np.einsum("fij,fmj->fmi", R, P)
    rng = np.random.default_rng(4)
    noisy = P + rng.normal(0, NOISE, P.shape)
    surf = build_marker_surface(noisy[0], positions=noisy)
    out = smooth_local(noisy, surf, smooth_lambda=0.1, smooth_iterations=10)
    assert np.linalg.norm(out - P, axis=-1).mean() < 0.8 * np.linalg.norm(noisy - P,
                                                                              axis=-1).mean()


def test_smoothing_frame_leaves_out_a_rarely_measured_neighbour():
    """A neighbour measured in few frames and badly estimated elsewhere (here
    jumping by 7 cm) must not bend the frame the marker's measurements are smoothed
    in; the marker's own filled run is left as the fill made it (smoothing it in the
    local frame only adds the frame's jitter: issue 15, the real racing capture in
    test_fill_blend.py::test_filled_runs_keep_the_fill)."""
    P, rest = rigid_capture(F=200)
    rng = np.random.default_rng(6)
    X = P + rng.normal(0, NOISE, P.shape)
    surf = build_marker_surface(rest, positions=X)
    m = 24
    ring = surf.neighbours[m][surf.neighbours[m] >= 0]
    bad = int(ring[0])
    measured = np.ones(X.shape[:2], bool)
    measured[60:200, bad] = False  # "filled" in 70 % of the frames...
    X[110:, bad] += [0.05, -0.04, 0.02]  # ...and wrong there: a jump
    measured[80:140, m] = False  # the marker's own filled run
    w = frame_weights(surf.neighbours, surf.rigidity, measured.mean(0))
    k = int(np.flatnonzero(surf.neighbours[m] == bad)[0])
    assert w[m, k] == 0 and (w[m][surf.neighbours[m] >= 0] > 0).sum() == len(ring) - 1
    out = smooth_local(X, surf, measured=measured)
    np.testing.assert_array_equal(out[80:140, m], X[80:140, m])  # the fill, untouched
    raw = np.linalg.norm(X[140:, m] - P[140:, m], axis=-1).mean()
    err = np.linalg.norm(out[140:, m] - P[140:, m], axis=-1).mean()
    assert err < 0.8 * raw  # measurements after the jump: noise removed (0.33 vs 0.48 mm)
    # without the rule the jump bends the frame (each correction is still bounded by
    # MAX_CORRECTION_SIGMA noise deviations: 0.42 mm)
    keep_all = surf.rigidity
    _, leak = _smooth_chunk((X, np.array([m]), surf.neighbours[[m]], keep_all[[m]],
                             surf.reference, 0.1, 10, measured))
    assert np.linalg.norm(leak[140:, 0] - P[140:, m], axis=-1).mean() > 1.15 * err
    # a marker with only 3 neighbours keeps them all
    few = np.array([[1, 2, 3, -1]])
    np.testing.assert_array_equal(
        frame_weights(few, np.array([[1.0, 0.5, 1.0, 0.0]]), np.array([1, 0.1, 1, 1])),
        [[1.0, 0.5, 1.0, 0.0]])


# --------------------------------------------------------------------------- failure paths


def test_never_visible_marker_stays_nan_with_a_warning(sim):
    base = perfectly_merged(sim)
    pos = base.positions.copy()
    pos[:, 7] = np.nan
    ctx = Context()
    res = clean(base.replace(positions=pos), ctx=ctx)
    out, rep = res["markers"], res["report"]
    lab = base.labels[7]
    assert rep["never_visible"] == [lab]
    assert any("never visible" in w and lab in w for w in ctx.warnings)
    assert not np.isfinite(out.positions[:, 7]).any()
    assert (rep["status"][:, 7] == STATUS["missing"]).all()
    others = np.delete(np.arange(base.n_markers), 7)
    assert np.isfinite(out.positions[:, others]).all()


def test_markers_with_fewer_than_three_neighbours(tmp_path):
    P, rest = rigid_capture(F=40)
    M = P.shape[1]
    # the surface file: an isolated triangle (p0, p1, p2), p3 in no triangle, the rest
    # automatic-like strips
    surf = build_marker_surface(P[0])
    faces = [f for f in surf.faces.tolist() if not set(f) & {0, 1, 2, 3}]
    faces.append([0, 1, 2])
    path = tmp_path / "surface.txt"
    path.write_text("\n".join(" ".join(f"p{i}" for i in f) for f in faces))
    pos = P.copy()
    pos[10:20, 1] = np.nan
    pos[10:20, 3] = np.nan
    pos[10:20, 30] = np.nan
    labels = [f"p{i}" for i in range(M)]
    ctx = Context()
    res = clean(Markers(pos, labels, 100.0), surface=str(path), smooth_iterations=0, ctx=ctx)
    out, rep = res["markers"], res["report"]
    assert rep["too_few_neighbours"] == ["p0", "p1", "p2", "p3"]
    assert any("fewer than 3" in w and "p1" in w and "p3" in w for w in ctx.warnings)
    assert not np.isfinite(out.positions[10:20, 3]).any()  # no neighbour: nothing invented
    # two neighbours: the blend's models that need none (rigid capture: exact)
    assert np.abs(out.positions[10:20, 1] - P[10:20, 1]).max() < 1e-6
    assert np.abs(out.positions[10:20, 30] - P[10:20, 30]).max() < 1e-6
    assert rep["unfillable_markers"] == ["p3"] and rep["surface"]["source"] == "surface.txt"
    # the paper's fill alone (no whole-body blend) leaves both
    out = clean(Markers(pos, labels, 100.0), surface=str(path), smooth_iterations=0,
                fill_model="pca", ctx=Context())
    assert out["report"]["unfillable_markers"] == ["p1", "p3"]


def test_reference_frame_with_missing_markers(sim):
    base = perfectly_merged(sim)
    tr = sim.truth
    pos = base.positions.copy()
    frame = 150
    gone = [3, 40, 77]
    pos[frame - 5: frame + 5, gone] = np.nan
    ctx = Context()
    res = clean(base.replace(positions=pos), reference_frame=frame, ctx=ctx)
    out, rep = res["markers"], res["report"]
    surf = MarkerSurface.from_mesh(res["surface"])
    assert rep["reference_frame"] == frame
    carried = [base.labels.index(lb) for lb in rep["reference_carried_over"]]
    missing = np.flatnonzero(~np.isfinite(pos[frame]).all(1))
    assert sorted(carried) == sorted(missing) and set(gone) <= set(carried)
    assert any("missing in reference frame" in w and base.labels[40] in w for w in ctx.warnings)
    # carried-over reference positions are those of the marker at that frame
    # (a rigid fit of its 6 nearest markers from the nearest frame where it was seen)
    d = np.linalg.norm(surf.reference[carried] - tr["positions"][frame, carried], axis=1)
    near = np.array([abs(g - frame) <= 10 for g in rep["reference_carried_over"].values()])
    assert d[near].max() < 0.01 and d.max() < 0.05
    err = np.linalg.norm(out.positions[frame - 5: frame + 5, gone]
                         - tr["positions"][frame - 5: frame + 5, gone], axis=-1)
    assert err.max() < 0.02


def test_bad_requests(tmp_path, sim):
    m = sim.markers
    with pytest.raises(CleanError, match="reference_frame 500 out of range"):
        clean(m, reference_frame=500)
    with pytest.raises(CleanError, match="alpha1 and alpha2 must be positive"):
        clean(m, alpha1=0.0)
    with pytest.raises(CleanError, match="variance"):
        clean(m, variance=1.5)
    with pytest.raises(CleanError, match="max_break must be >= 0"):
        clean(m, max_break=-0.1)
    bad = tmp_path / "surf.txt"
    bad.write_text(f"{m.labels[0]} {m.labels[1]} NOPE\n")
    with pytest.raises(SurfaceFileError, match=r"surf\.txt:1.*'NOPE'"):
        clean(m, surface=str(bad))
    empty = Markers(np.zeros((0, 0, 3)), [], 100.0)
    with pytest.raises(CleanError, match="no labelled markers"):
        clean(empty)


# --------------------------------------------------------------------------- stage contract


def test_stage_outputs_store_and_parallel_map_agrees(sim):
    m = sim.markers
    seq = clean(m, ctx=Context(part="x"))
    with ThreadPoolExecutor(2) as pool:
        ctx = Context(part="x", mapper=lambda fn, items: list(pool.map(fn, items)), workers=2)
        par = clean(m, ctx=ctx)
    assert np.array_equal(seq["markers"].positions, par["markers"].positions, equal_nan=True)
    assert seq["report"]["merges"] == par["report"]["merges"]
    for key in ("markers", "report", "surface"):
        back = decode(encode(seq[key]))
        if key == "report":
            assert np.array_equal(back["status"], seq["report"]["status"])
            assert back["table1"] == seq["report"]["table1"]
    surf = seq["surface"]
    assert isinstance(surf, Mesh) and surf.attrs["labels"] == m.labels
    assert surf.vertices.shape == (m.n_markers, 3)
    ref_frame = seq["report"]["reference_frame"]
    assert surf.attrs["reference_frame"] == ref_frame == int(np.argmax(m.visible.sum(1)))


@pytest.mark.skipif(not (DATA / "c3d").exists(), reason="no shared data")
def test_real_fragmented_pig_file():
    m = read_c3d(DATA / "c3d" / "btkdata_PiG_Calibration-FlatFoot-Hole.c3d")
    res = clean(m, ctx=Context())
    out, rep = res["markers"], res["report"]
    # 64 fragments appear while every labelled marker is present: duplicates/ghosts;
    # *65 and *66 (frames 292-298, during RASI's hole) lie 1.8 m from RASI's prediction
    assert rep["merges"] == []
    reasons = {r["fragment"]: r["reason"] for r in rep["rejections"]}
    assert sum(r.startswith("overlaps every marker") for r in reasons.values()) == 64
    assert reasons["*65"].startswith("entry") and "RASI" in reasons["*65"]
    rasi = m.labels.index("RASI")
    hole = ~m.visible[:, rasi]
    assert hole.sum() == 9 and np.isfinite(out.positions[hole, rasi]).all()
    # the hole sits at the end: the filled RASI continues its last measured position
    assert np.linalg.norm(out.positions[291, rasi] - m.positions[290, rasi]) < 0.01
