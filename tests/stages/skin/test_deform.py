"""Skin deformation (Park & Hodgins 2006 §5.3) and detailed-mesh fitting against ground truth."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from scipy.interpolate import RBFInterpolator
from scipy.spatial import cKDTree

from mocapflow.pipeline import Context
from mocapflow.stages.motion.datatypes import Markers, Mesh
from mocapflow.stages.skin.binding import (
    DeformError,
    bind_mesh,
    blend_smoothing_operator,
    closest_points_on_triangles,
)
from mocapflow.stages.skin.blend import (
    deform_positions,
    frame_coefficients,
    operator_matrix,
    vertex_operator,
)
from mocapflow.stages.skin.deform import deform
from mocapflow.stages.skin.kernels import (
    cubic_bspline,
    dilation,
    quadratic_basis,
    rbf_matrix,
    thin_plate,
    thin_plate_matrix,
)
from mocapflow.stages.skin.mesh_fit import fit_detailed_mesh, fit_mesh, template_mesh
from mocapflow.stages.skin.parts import MODES, evaluate_part, fit_part, prepare_part
from mocapflow.stages.skin.segment import part_frames, segment
from mocapflow.stages.skin.segmentation import Segmentation
from mocapflow.stages.skin.widening import _Rows, _widen_blends
from tests.stages.skin.conftest import deform_limb, grid_cylinder, limb_capture, rot_x, rot_y

#: Tolerance (m) against double-precision references of the non-rigid displacements, which
#: the stage multiplies out in single precision (``blend._NONRIGID``): their rounding is of
#: nanometres on the limb (displacements of centimetres); the rigid mode is exact.
SINGLE = 1e-8


def hard_segmentation(reference, parts, names, faces=None, labels=None):
    """A segmentation with given hard parts (one-hot weights)."""
    M = len(reference)
    weights = np.eye(len(names))[parts]
    origins, axes = part_frames(reference, weights)
    return Segmentation(
        labels=labels or [f"M{i:03d}" for i in range(M)], part_names=names,
        weights=weights, reference=reference,
        faces=np.zeros((0, 3), int) if faces is None else faces, origins=origins, axes=axes,
        triangle_clusters=np.zeros(0 if faces is None else len(faces), int),
    )  # fmt: skip


def one_part_segmentation(reference, faces=None, labels=None):
    """A segmentation with a single part holding every marker."""
    return hard_segmentation(reference, np.zeros(len(reference), int), ["body"], faces, labels)


@pytest.fixture(scope="module")
def limb():
    d = limb_capture(n_frames=90, noise=0.0)
    d["seg"] = segment(d["markers"], d["surface"], ctx=Context())["segmentation"]
    return d


# --------------------------------------------------------------------------- kernels


def test_cubic_bspline_kernel_is_compact_and_smooth():
    r = np.linspace(0, 1.5, 3001)
    phi = cubic_bspline(r)
    assert phi[0] == 1.0
    assert np.all(phi[r >= 1.0] == 0.0) and np.all(phi[r < 1.0] > 0.0)
    assert np.all(np.diff(phi) <= 0)  # monotone
    h = r[1] - r[0]
    d1 = np.diff(phi) / h
    assert np.max(np.abs(np.diff(d1))) < 10 * h * 12  # C1: no jump in the slope
    assert cubic_bspline(np.array([0.5]))[0] == pytest.approx(1.5 / 6)  # B3(1) = 1/6


def test_rbf_matrix_sparse_and_positive_definite(limb):
    ref = limb["surface"].vertices
    sigma = dilation(ref)
    K = rbf_matrix(ref, ref, sigma)
    D = np.linalg.norm(ref[:, None] - ref[None], axis=-1)
    assert K.nnz == np.sum(D < sigma)  # exactly the pairs within the support
    assert np.allclose(K.toarray(), cubic_bspline(D / sigma))
    assert K.nnz < 0.5 * K.shape[0] ** 2
    assert np.linalg.eigvalsh(K.toarray()).min() > 0  # the residual system is solvable


def test_closest_points_match_brute_force():
    rng = np.random.default_rng(3)
    V, F = grid_cylinder(8, 6, jitter=0.2, rng=rng)
    P = rng.normal(0, 0.1, (60, 3)) + [0, 0.3, 0]
    tri, bary, dist = closest_points_on_triangles(P, V, F, k=len(F))
    Q = np.einsum("nc,nci->ni", bary, V[F[tri]])
    assert np.allclose(np.linalg.norm(Q - P, axis=1), dist)
    assert np.all(bary >= -1e-12) and np.allclose(bary.sum(1), 1)
    # brute force on a dense barycentric sampling of every triangle
    u, v = np.meshgrid(np.linspace(0, 1, 31), np.linspace(0, 1, 31))
    keep = u + v <= 1
    W = np.stack([1 - u[keep] - v[keep], u[keep], v[keep]], 1)
    S = np.einsum("sc,tci->tsi", W, V[F]).reshape(-1, 3)
    brute = np.min(np.linalg.norm(P[:, None] - S[None], axis=-1), axis=1)
    assert np.all(dist <= brute + 1e-12) and np.all(brute - dist < 3e-3)


def test_thin_plate_kernel():
    r = np.array([0.0, 1.0, np.e, 0.5])
    assert np.allclose(thin_plate(r), [0.0, 0.0, np.e**2, 0.25 * np.log(0.5)])
    rng = np.random.default_rng(0)
    P = rng.normal(size=(30, 3))
    K = thin_plate_matrix(P, P, 2.0).toarray()
    D = np.linalg.norm(P[:, None] - P[None], axis=-1) / 2.0
    assert np.allclose(K, thin_plate(D)) and np.allclose(K, K.T)
    # same interpolant as scipy's RBFInterpolator (thin_plate_spline, degree 1)
    ref = rng.normal(0, [0.08, 0.15, 0.05], (25, 3))
    vals = np.sin(ref @ [3.0, 5.0, 2.0])[:, None] * [1.0, 0.5, -0.3]
    seg = one_part_segmentation(ref)
    probes = rng.normal(0, [0.08, 0.15, 0.05], (40, 3))
    m = prepare_part(seg, 0, vertices=probes, beta=np.ones((40, 1)),
                     residual_kernel="thin_plate", support_margin=None, clamp_margin=None)
    x = (ref + 0.01 * vals)[None]
    fit = fit_part(m, x, mode="rigid_residual")
    got = evaluate_part(m, fit)[0]
    # scipy interpolates in world coordinates; the fit's rigid part is the identity here
    want = probes + RBFInterpolator(ref, x[0] - ref, kernel="thin_plate_spline")(probes)
    assert np.abs(got - want).max() < 2e-4  # differs only by the kernel's length unit
    # a flat part (coplanar markers) or 3 markers: the polynomial drops the unspanned
    # direction instead of extrapolating off the plane; still exact at the markers
    for flat_n in (20, 3):
        flat = np.c_[rng.uniform(-0.1, 0.1, (flat_n, 2)), np.zeros(flat_n)]
        off = np.c_[rng.uniform(-0.1, 0.1, (30, 2)), rng.uniform(-0.01, 0.01, 30)]
        mf = prepare_part(one_part_segmentation(flat), 0, vertices=off, beta=np.ones((30, 1)),
                          residual_kernel="thin_plate")  # fmt: skip
        xf = (flat + 0.003 * np.sin(flat * 20))[None]
        fit = fit_part(mf, xf, mode="rigid_residual")
        assert np.abs(evaluate_part(mf, fit) - off).max() < 0.01  # data move <= 3 mm
        on = evaluate_part(mf, fit, mf.local, mf.basis(mf.local), mf.kernel.tocsr())
        assert np.abs(on - xf).max() < 1e-12


# --------------------------------------------------------------------------- the model


def test_quadratic_recovers_known_quadratic_deformation():
    rng = np.random.default_rng(4)
    ref = rng.normal(0, [0.08, 0.15, 0.05], (25, 3)) + [0.3, 1.0, 0.1]
    probes = rng.normal(0, [0.08, 0.15, 0.05], (50, 3)) + [0.3, 1.0, 0.1]
    seg = one_part_segmentation(ref)
    A = np.concatenate([np.eye(3), np.zeros((3, 6))], 1) + rng.normal(0, 0.4, (3, 9))
    offset = rng.normal(0, 0.05, 3)
    F = 5
    R = rot_y(np.linspace(0, 2, F)) @ rot_x(np.linspace(0.5, -1, F))
    t = rng.normal(0, 1, (F, 3))

    def truth(p):
        return np.einsum("fij,nj->fni", R, quadratic_basis(p) @ A.T + offset) + t[:, None]

    paper = {"support_margin": None, "clamp_margin": None}  # probes outside the markers too
    model = prepare_part(seg, 0, vertices=probes, beta=np.ones((len(probes), 1)),
                         residual_kernel="thin_plate", **paper)  # fmt: skip
    for mode, exact in [("quadratic", True), ("quadratic_residual", True), ("rigid", False)]:
        fit = fit_part(model, truth(ref), mode=mode)
        err = np.abs(evaluate_part(model, fit) - truth(probes)).max()
        if exact:
            assert err < 1e-9, mode
        else:
            assert err > 1e-3, mode  # rigid cannot represent it
    # the B-spline residual (paper) is exact too: nothing is left for it
    bs = prepare_part(seg, 0, vertices=probes, beta=np.ones((len(probes), 1)),
                      residual_kernel="cubic_bspline", **paper)  # fmt: skip
    fit = fit_part(bs, truth(ref), mode="quadratic_residual")
    assert np.abs(evaluate_part(bs, fit) - truth(probes)).max() < 1e-9
    # the thin-plate residual's linear polynomial makes rigid + residual exact on an affine map
    Aff = np.eye(3) + rng.normal(0, 0.2, (3, 3))
    affine = np.einsum("fij,nj->fni", R, ref @ Aff.T) + t[:, None]
    fit = fit_part(model, affine, mode="rigid_residual")
    assert np.abs(evaluate_part(model, fit) - (np.einsum("fij,nj->fni", R, probes @ Aff.T)
                                               + t[:, None])).max() < 1e-9  # fmt: skip
    # missing markers in some frames (>= 10 visible): still exact
    x = truth(ref)
    x[1, :8] = np.nan
    x[3, 5:12] = np.nan
    fit = fit_part(model, x, mode="quadratic")
    assert np.abs(evaluate_part(model, fit) - truth(probes)).max() < 1e-9


def test_residual_interpolates_markers_exactly(limb):
    seg = limb["seg"]
    x = limb["markers"].positions
    for kernel in ("thin_plate", "cubic_bspline"):
        for mode in ("rigid_residual", "quadratic_residual"):
            for p in range(seg.n_parts):
                m = prepare_part(seg, p, residual_kernel=kernel)
                fit = fit_part(m, x[:, m.members], mode=mode, damping=0.3)
                pred = evaluate_part(m, fit, m.local, m.basis(m.local), m.kernel.tocsr())
                assert np.abs(pred - x[:, m.members]).max() < 1e-9, (kernel, mode)
    # and a mesh vertex placed on a marker lands on that marker (interior marker)
    i = int(np.argmin(np.abs(seg.reference[:, 1] - 0.1)))
    verts = np.concatenate([limb["mesh"].vertices, seg.reference[i : i + 1]])
    faces = limb["mesh"].faces
    out = deform(limb["markers"], seg, Mesh(verts, faces), ctx=Context())
    assert np.abs(out["mesh"].vertices[:, -1] - x[:, i]).max() < SINGLE


def test_modes_against_ground_truth_mesh(limb):
    err = {}
    for mode in MODES:
        ctx = Context()
        out = deform(limb["markers"], limb["seg"], limb["mesh"], mode=mode, ctx=ctx)
        assert out["mesh"].vertices.shape == limb["truth"].shape
        assert out["mesh"].rate == limb["markers"].rate and out["mesh"].attrs["mode"] == mode
        e = np.linalg.norm(out["mesh"].vertices - limb["truth"], axis=-1)
        err[mode] = e.mean() * 1000
        rms = [p["marker_rms_mm"] for p in out["report"]["parts"].values()]
        if mode.endswith("residual"):
            assert max(rms) < 1e-8
        assert not ctx.warnings
    # rigid: > 1 mm mean on this limb (bulge + joint blend not rigid); residuals (B-spline;
    # measured: rigid 1.48, quadratic 1.30, rigid + residual 0.539, quadratic + residual 0.531)
    assert err["rigid"] > 0.8
    assert err["quadratic"] < err["rigid"]
    assert err["rigid_residual"] < 0.6 and err["quadratic_residual"] < err["rigid_residual"]


def test_parallel_map_gives_same_result(limb):
    pool = ThreadPoolExecutor(2)
    ctx = Context(mapper=lambda fn, items: list(pool.map(fn, items)))
    a = deform(limb["markers"], limb["seg"], limb["mesh"], chunk_frames=16, ctx=ctx)
    b = deform(limb["markers"], limb["seg"], limb["mesh"], ctx=Context())
    pool.shutdown()
    assert np.array_equal(a["mesh"].vertices, b["mesh"].vertices)


def test_binding_weights(limb):
    seg = limb["seg"]
    b = bind_mesh(limb["mesh"].vertices, seg)
    assert np.allclose(b.beta.sum(1), 1)
    assert b.distance.max() < 0.01
    # a vertex on a marker takes exactly that marker's alpha (paper: sharpness 1)
    hard = hard_segmentation(seg.reference, seg.hard_labels, seg.part_names, seg.faces)
    w = hard.weights.copy()
    soft = np.flatnonzero(np.abs(seg.reference[:, 1] - 0.3) < 0.03)
    assert soft.size >= 5
    w[soft] = 0.35 + 0.3 * w[soft]  # 0.65 / 0.35
    soft_seg = Segmentation(seg.labels, seg.part_names, w, seg.reference, seg.faces,
                            hard.origins, hard.axes, seg.triangle_clusters)  # fmt: skip
    b2 = bind_mesh(seg.reference[soft], soft_seg, sharpness=1.0, min_weight=0.0)
    assert np.allclose(b2.beta, w[soft], atol=1e-12)
    # sharpened: alpha^4 renormalised, so the dominant part gains
    b4 = bind_mesh(seg.reference[soft], soft_seg, sharpness=4.0, min_weight=0.0)
    assert np.allclose(b4.beta.max(1), 0.65**4 / (0.65**4 + 0.35**4), atol=1e-12)
    # a vertex midway between two hard parts: 50/50 at any sharpness
    e = np.flatnonzero(hard.weights[seg.faces[:, 0]].argmax(1)
                       != hard.weights[seg.faces[:, 1]].argmax(1))[0]  # fmt: skip
    mid = seg.reference[seg.faces[e, :2]].mean(0, keepdims=True)
    for g in (1.0, 4.0):
        bm = bind_mesh(mid, hard, sharpness=g, min_overlap=0.0).beta[0]
        assert np.sort(bm)[-2:] == pytest.approx([0.5, 0.5], abs=1e-9)
    with pytest.raises(DeformError, match="sharpness"):
        bind_mesh(limb["mesh"].vertices, seg, sharpness=0.0)


# --------------------------------------------------------------------------- fallbacks


def test_small_part_falls_back_to_rigid(limb):
    d = limb
    parts = d["parts"].copy()
    parts[-6:] = 2  # a 6-marker part at the tip of the lower segment
    seg = hard_segmentation(d["surface"].vertices, parts, ["upper", "lower", "tip"],
                            d["surface"].faces, d["markers"].labels)  # fmt: skip
    tip = 2
    ctx = Context()
    q = deform(d["markers"], seg, d["mesh"], mode="quadratic", ctx=ctx)
    assert any("'tip'" in w and "under-determined" in w and "rigid" in w for w in ctx.warnings)
    assert q["report"]["parts"]["tip"]["quadratic"] is False
    # the tip's own vertices move exactly as in rigid mode
    r = deform(d["markers"], seg, d["mesh"], mode="rigid", ctx=Context())
    beta = bind_mesh(d["mesh"].vertices, seg).beta
    only_tip = beta[:, tip] == 1.0
    assert only_tip.sum() > 10
    assert np.allclose(q["mesh"].vertices[:, only_tip], r["mesh"].vertices[:, only_tip])


def test_frame_without_markers_is_interpolated(limb):
    # a part translating at constant velocity: a frame with < 3 visible markers gets
    # the midpoint of its neighbours exactly
    ref = limb["surface"].vertices
    seg = one_part_segmentation(ref, limb["surface"].faces, limb["markers"].labels)
    F = 7
    x = ref[None] + np.arange(F)[:, None, None] * np.array([0.01, 0.0, 0.02])
    x[3, 2:] = np.nan  # 2 markers left in frame 3
    mk = Markers(x, limb["markers"].labels, 100.0)
    ctx = Context()
    out = deform(mk, seg, limb["mesh"], mode="quadratic_residual", ctx=ctx)
    msg = [w for w in ctx.warnings if "fewer than 3 usable markers" in w]
    assert msg and "'body'" in msg[0] and "frames (3)" in msg[0]
    v = out["mesh"].vertices
    assert np.isfinite(v).all()
    expected = limb["mesh"].vertices + 3 * np.array([0.01, 0.0, 0.02])
    assert np.abs(v[3] - expected).max() < 1e-9
    # < 10 visible markers in a frame: rigid fit there, quadratic terms interpolated
    x2 = ref[None] + np.arange(F)[:, None, None] * np.array([0.01, 0.0, 0.02])
    x2[5, 6:] = np.nan
    ctx2 = Context()
    out2 = deform(Markers(x2, mk.labels, 100.0), seg, limb["mesh"], ctx=ctx2)
    assert any("quadratic terms interpolated" in w and "(5)" in w for w in ctx2.warnings)
    expected5 = limb["mesh"].vertices + 5 * np.array([0.01, 0, 0.02])
    assert np.abs(out2["mesh"].vertices[5] - expected5).max() < 1e-9
    # never placeable: an error naming the part
    x3 = x.copy()
    x3[:, 2:] = np.nan
    with pytest.raises(DeformError, match="'body'.*cannot be placed"):
        deform(Markers(x3, mk.labels, 100.0), seg, limb["mesh"], ctx=Context())


def test_mesh_not_overlapping_is_an_error(limb):
    with pytest.raises(DeformError, match=r"does not overlap.*decimetres"):
        deform(limb["markers"], limb["seg"], Mesh(limb["mesh"].vertices * 10, limb["mesh"].faces),
               ctx=Context())  # fmt: skip
    with pytest.raises(DeformError, match="does not overlap"):
        moved = limb["mesh"].vertices + [1.0, 0, 0]
        deform(limb["markers"], limb["seg"], Mesh(moved, limb["mesh"].faces), ctx=Context())
    # a mesh that runs on far beyond the markers (found on kineticstoolkit's seated
    # racing static trial, markers on the upper body only): said so, not "fit it first"
    v = limb["mesh"].vertices
    axis = int(np.argmax(np.ptp(v, axis=0)))
    longer = v.copy()
    longer[:, axis] = v[:, axis].min() + 3.0 * (v[:, axis] - v[:, axis].min())
    with pytest.raises(DeformError, match=r"cover only part of the body") as err:
        deform(limb["markers"], limb["seg"], Mesh(longer, limb["mesh"].faces), ctx=Context())
    assert "fit the mesh to the markers first" not in str(err.value)
    with pytest.raises(DeformError, match="lacks 1 markers.*M005"):
        mk = limb["markers"]
        keep = [i for i in range(mk.n_markers) if i != 5]
        deform(mk.replace(positions=mk.positions[:, keep], labels=[mk.labels[i] for i in keep]),
               limb["seg"], limb["mesh"], ctx=Context())  # fmt: skip
    with pytest.raises(DeformError, match="unknown deformation mode"):
        fit_part(prepare_part(limb["seg"], 0), limb["markers"].positions[:, :5], mode="cubic")


# --------------------------------------------------------------------------- mesh fitting


def test_fit_mesh_recovers_the_limb_surface(limb):
    Vr = limb["mesh"].vertices
    template = Vr.copy()
    template[:, [0, 2]] *= 1.12 + 0.05 * np.sin(template[:, 1:2] * 10)  # fatter, wavy
    template = (template @ rot_y(np.deg2rad(8)).T + [0.02, -0.01, 0.015]) * 10  # decimetres
    ctx = Context()
    out = fit_mesh(Mesh(template, limb["mesh"].faces), limb["seg"], ctx=ctx)
    fitted = out["mesh"].vertices
    radius = np.linalg.norm(fitted[:, [0, 2]], axis=1)
    interior = (Vr[:, 1] > 0.05) & (Vr[:, 1] < 0.55)
    assert np.abs(radius[interior] - 0.05).mean() < 0.001  # on the true surface within 1 mm
    assert out["report"]["fitted"]["rms_mm"] < 1.0 < out["report"]["aligned"]["rms_mm"]
    assert out["report"]["scale"] == pytest.approx(0.1, rel=0.1)
    assert any("scaled by" in w for w in ctx.warnings)
    # the fitted mesh binds and deforms
    d = deform(limb["markers"], limb["seg"], out["mesh"], ctx=Context())
    assert np.isfinite(d["mesh"].vertices).all()


def test_fit_mesh_rejects_a_different_shape(limb):
    # a template in another pose (limb bent 90 degrees) cannot be aligned to straight markers
    bent = deform_limb(limb["mesh"].vertices, np.array([np.pi / 2]), np.zeros(1), 0.0)[0]
    with pytest.raises(DeformError, match="does not match the markers"):
        fit_mesh(Mesh(bent, limb["mesh"].faces), limb["seg"], allow_scale=False, ctx=Context())
    with pytest.raises(DeformError, match="unknown markers"):
        fit_mesh(limb["mesh"], limb["seg"], landmarks={"NOPE": 0}, ctx=Context())


def test_fit_detailed_mesh_with_landmarks_is_exact_on_them(limb):
    seg = limb["seg"]
    Vr = limb["mesh"].vertices
    _, idx = cKDTree(Vr).query(seg.reference[:4])
    targets = seg.reference.copy()
    targets[:4] = Vr[idx]  # landmarks: markers 0..3 <-> those vertices
    out, info = fit_detailed_mesh(Vr * 1.05, limb["mesh"].faces, targets,
                                  landmarks=dict(zip(range(4), idx.tolist())))  # fmt: skip
    assert np.abs(out[idx] - targets[:4]).max() < 2e-3
    assert info["fitted"]["rms_mm"] < 1.0


def test_isolated_marker_shrinks_the_dilation(limb):
    # a part whose markers include one far outlier: 2 x max nearest-neighbour distance
    # would make the kernel indefinite; the dilation is reduced (and reported) instead
    seg = limb["seg"]
    ref = seg.reference.copy()
    members = seg.members(0)
    far = members[np.argmax(ref[members, 1])]
    ref[far] += np.array([0.0, 0.0, 0.25])  # 25 cm off the limb
    seg2 = Segmentation(seg.labels, seg.part_names, seg.weights, ref, seg.faces, seg.origins,
                        seg.axes, seg.triangle_clusters)  # fmt: skip
    m = prepare_part(seg2, 0, residual_kernel="cubic_bspline")
    lam = np.linalg.eigvalsh(m.kernel.toarray())
    assert lam[0] > 0 and lam[-1] / lam[0] <= 100
    assert m.sigma < dilation(m.local)
    assert m.messages and "dilation reduced" in m.messages[0] and "'part00'" in m.messages[0]
    xm = limb["markers"].positions[:, m.members]
    fit = fit_part(m, xm, mode="rigid_residual")
    pred = evaluate_part(m, fit, m.local, m.basis(m.local), m.kernel.tocsr())
    assert np.abs(pred - xm).max() < 1e-9  # still interpolates every marker exactly


def test_quadratic_damping(limb):
    seg, x = limb["seg"], limb["markers"].positions
    m = prepare_part(seg, 0)
    plain = fit_part(m, x[:, m.members], mode="quadratic")
    zero = fit_part(m, x[:, m.members], mode="quadratic", damping=0.0)
    damped = fit_part(m, x[:, m.members], mode="quadratic", damping=1.0)
    assert np.array_equal(plain.A, zero.A)  # 0 = the paper's pseudo-inverse
    assert np.linalg.norm(damped.A) < 0.8 * np.linalg.norm(plain.A)  # pulled toward rigid
    big = fit_part(m, x[:, m.members], mode="quadratic", damping=1e9)
    assert np.abs(big.A).max() < 1e-6
    out = deform(limb["markers"], seg, limb["mesh"], quadratic_damping=0.1, ctx=Context())
    assert np.isfinite(out["mesh"].vertices).all()


def test_template_mesh_and_template_frame(limb):
    t = template_mesh(n_vertices=1500, ctx=Context())["mesh"]
    assert 1000 < len(t.vertices) < 2500 and not t.animated
    height = np.ptp(t.vertices[:, 1])
    assert 1.5 < height < 2.0  # metres, y up
    anim = Mesh(np.stack([limb["mesh"].vertices] * 3), limb["mesh"].faces)
    out = fit_mesh(anim, limb["seg"], template_frame=2, ctx=Context())
    assert out["report"]["fitted"]["rms_mm"] < 1.0
    with pytest.raises(DeformError, match="template_frame 5"):
        fit_mesh(anim, limb["seg"], template_frame=5, ctx=Context())


def test_fit_mesh_picks_the_reference_frame_of_an_animated_template(limb):
    # the truth sequence as template: the frame matching the markers' reference is found
    seg = limb_capture(n_frames=30, noise=0.0)
    s = segment(seg["markers"], seg["surface"], ctx=Context())["segmentation"]
    moved = seg["markers"].replace(positions=seg["markers"].positions[[17]])
    ref_mesh = Mesh(seg["truth"], seg["mesh"].faces)
    s17 = Segmentation(s.labels, s.part_names, s.weights, moved.positions[0], s.faces, s.origins,
                       s.axes, s.triangle_clusters)  # fmt: skip
    out = fit_mesh(ref_mesh, s17, allow_scale=False, ctx=Context())
    assert out["report"]["template_frame"] == 17
    assert out["report"]["aligned"]["rms_mm"] < 1.0


def test_operator_blocks_match_sparse_matrix_and_per_part_evaluation(limb):
    seg, x = limb["seg"], limb["markers"].positions[:20]
    V = limb["mesh"].vertices
    beta = bind_mesh(V, seg).beta
    models = [prepare_part(seg, p, vertices=V, beta=beta) for p in range(seg.n_parts)]
    fits = [fit_part(m, x[:, m.members], mode="quadratic_residual") for m in models]
    op = vertex_operator(models, len(V), residual=True)
    got = deform_positions(models, fits, len(V), op, residual=True)
    manual = np.zeros_like(got)
    for m, f in zip(models, fits):
        manual[:, m.vertices] += m.beta[None, :, None] * evaluate_part(m, f)
    assert np.abs(got - manual).max() < SINGLE
    # the sparse matrix is the linear map: exact without the (non-linear) clamp
    for m in models:
        m.clamp_margin = None
    op = vertex_operator(models, len(V), residual=True)
    unclamped = deform_positions(models, fits, len(V), op, residual=True)
    C = frame_coefficients(models, fits, residual=True)
    sparse = (operator_matrix(op) @ C.reshape(C.shape[0], -1)).reshape(len(V), -1, 3)
    assert np.abs(unclamped - sparse.transpose(1, 0, 2)).max() < SINGLE
    with pytest.raises(ValueError, match="disagree"):
        deform_positions(models, fits, len(V), vertex_operator(models, len(V), residual=False),
                         residual=True)  # fmt: skip


def test_fast_path_matches_per_part_reference_with_clamp_and_chunks(limb):
    """deform_positions (β folded into the blocks, clamp on few entries, frame chunks,
    pair-to-vertex sum) against the plain per-part Eq. 8-9 sum, with the clamp acting."""
    seg, x = limb["seg"], limb["markers"].positions  # 90 frames: 3 chunks, the last partial
    V = limb["mesh"].vertices
    beta = bind_mesh(V, seg).beta
    models = [prepare_part(seg, p, vertices=V, beta=beta, clamp_margin=0.1)
              for p in range(seg.n_parts)]  # fmt: skip
    assert seg.n_parts >= 2 and (np.count_nonzero(beta, axis=1) > 1).any()  # blended vertices
    for mode in ("quadratic_residual", "rigid"):
        fits = [fit_part(m, x[:, m.members], mode=mode) for m in models]
        for f in fits:  # a tight bound: the clamp acts on many vertices and frames
            f.marker_deviation = 0.2 * f.marker_deviation
        residual = mode.endswith("residual")
        got = deform_positions(models, fits, len(V), vertex_operator(models, len(V),
                               residual=residual), residual=residual)  # fmt: skip
        ref = np.zeros_like(got)
        for m, f in zip(models, fits):
            ref[:, m.vertices] += m.beta[None, :, None] * evaluate_part(m, f)
        assert got.shape == (90, len(V), 3)
        assert np.abs(got - ref).max() < (SINGLE if residual else 1e-12)  # rigid: no single
        if residual:  # the clamp changed the result (else this test could not fail on it)
            for m in models:
                m.clamp_margin = None
            free = deform_positions(models, fits, len(V), residual=True)
            assert np.abs(free - got).max() > 1e-3
            for m in models:
                m.clamp_margin = 0.1


def test_held_out_points_on_a_bending_bulging_limb():
    # sparse markers (8 x 8) on a limb that bends, twists and bulges; the mesh vertices
    # are points the pipeline never saw, predicted from the markers and compared to truth
    d = limb_capture(n_frames=60, n_around=8, n_rings=8, noise=0.0)
    seg = segment(d["markers"], d["surface"], ctx=Context())["segmentation"]
    V, truth, x = d["mesh"].vertices, d["truth"], d["markers"].positions

    def err(pred):
        return np.linalg.norm(pred - truth, axis=-1).mean() * 1000

    ours = {m: err(deform(d["markers"], seg, d["mesh"], mode=m, ctx=Context())["mesh"].vertices)
            for m in MODES}  # fmt: skip
    thin = {m: err(deform(d["markers"], seg, d["mesh"], mode=m, residual_kernel="thin_plate",
                          ctx=Context())["mesh"].vertices)
            for m in ("rigid_residual", "quadratic_residual")}  # fmt: skip
    disp = (x - seg.reference).transpose(1, 0, 2).reshape(len(x[0]), -1)
    tps = RBFInterpolator(seg.reference, disp, kernel="thin_plate_spline")(V)
    tps = V + tps.reshape(len(V), -1, 3).transpose(1, 0, 2)
    # measured (B-spline default): rigid 1.14, quadratic 0.96, rigid + residual 0.514,
    # quadratic + residual 0.493; thin-plate residual 0.399 / 0.399; global thin-plate RBF
    # 1.81; paper settings 0.77 mm
    qr = ours["quadratic_residual"]
    assert qr < 0.55 and qr < 0.5 * ours["rigid"] and qr < 0.6 * ours["quadratic"]
    assert qr < ours["rigid_residual"]  # the quadratic term helps under the B-spline residual
    assert qr < 0.3 * err(tps)
    assert thin["quadratic_residual"] < 0.45 and thin["quadratic_residual"] < 0.85 * qr
    assert thin["quadratic_residual"] < thin["rigid_residual"] + 0.02  # affine + thin plate
    # the paper's exact settings stay reachable (barycentric beta, Eq. 6, B-spline) and do worse
    paper = deform(d["markers"], seg, d["mesh"], beta_sharpness=1.0, quadratic_damping=0.0,
                   residual_kernel="cubic_bspline", ctx=Context())["mesh"].vertices  # fmt: skip
    assert qr < 0.7 * err(paper) and err(paper) < 0.8 * ours["rigid"]


def test_deform_is_bit_reproducible_across_groupings_chunks_and_threads(limb):
    """Issue 15 item 4: the same bytes whichever vertices are evaluated together, however
    the frames are chunked on an executor and with 1 or 2 BLAS threads (a BLAS product
    rounds a row differently depending on how many rows go with it: with the former
    dense evaluation a vertex evaluated alone differed in the last bit)."""
    from threadpoolctl import threadpool_limits

    seg, markers, mesh = limb["seg"], limb["markers"], limb["mesh"]
    V = mesh.vertices
    with threadpool_limits(1):
        full = deform(markers, seg, mesh, max_blend_stretch=None, ctx=Context())["mesh"].vertices
        sub = np.arange(1, len(V), 3)[::-1]  # another grouping, order and count of vertices
        part = deform(markers, seg, Mesh(V[sub], np.zeros((0, 3), int)),
                      ctx=Context())["mesh"].vertices  # fmt: skip
        alone = [deform(markers, seg, Mesh(V[[k]], np.zeros((0, 3), int)),
                        ctx=Context())["mesh"].vertices for k in (0, 641, 1279)]  # fmt: skip
    assert part.tobytes() == full[:, sub].tobytes()
    for k, one in zip((0, 641, 1279), alone):  # one vertex alone: a BLAS product differed here
        assert one.tobytes() == np.ascontiguousarray(full[:, [k]]).tobytes()
    # blends widened (a low bound: many vertices move again, evaluated apart from the rest)
    runs = []
    with ThreadPoolExecutor(2) as pool:
        for threads, mapper, chunk in ((1, None, 1024), (2, None, 1024),
                                       (2, lambda fn, it: list(pool.map(fn, it)), 7)):
            with threadpool_limits(threads):
                runs.append(deform(markers, seg, mesh, max_blend_stretch=1.3, chunk_frames=chunk,
                                   ctx=Context(mapper=mapper)))  # fmt: skip
    assert runs[0]["report"]["blend_widening"]["vertices"] > 10
    assert np.abs(runs[0]["mesh"].vertices - full).max() > 1e-4  # widening moved them
    for r in runs[1:]:
        assert r["mesh"].vertices.tobytes() == runs[0]["mesh"].vertices.tobytes()


def test_operator_rows_do_not_depend_on_the_other_vertices(limb):
    """deform_positions of a vertex subset (with other weights elsewhere) gives the same
    bytes for those vertices as the whole mesh."""
    seg, x, V = limb["seg"], limb["markers"].positions[:40], limb["mesh"].vertices
    beta = bind_mesh(V, seg, sharpness=4.0).beta
    models = [prepare_part(seg, p) for p in range(seg.n_parts)]
    fits = [fit_part(m, x[:, m.members], mode="quadratic_residual") for m in models]
    whole = deform_positions(models, fits, len(V), vertex_operator(
        models, len(V), residual=True, rest=V, beta=beta), residual=True)  # fmt: skip
    rng = np.random.default_rng(3)
    for size in (1, 7, len(V) // 2):
        sub = rng.choice(len(V), size, replace=False)
        op = vertex_operator(models, size, residual=True, rest=V[sub], beta=beta[sub])
        got = deform_positions(models, fits, size, op, residual=True)
        assert got.tobytes() == np.ascontiguousarray(whole[:, sub]).tobytes()
    with pytest.raises(ValueError, match="together"):
        vertex_operator(models, len(V), residual=True, rest=V)


def _widen_blends_directly(models, fits, mesh, beta, verts, *, max_stretch, steps, residual):
    """:func:`_widen_blends` written out plainly: after every round every triangle whose
    corners blend differently is checked on every frame, and every diffused vertex is moved
    again from its parts' predictions (β = 1, parts in ascending order)."""
    faces, rest, beta, verts = mesh.faces, mesh.vertices, beta.copy(), verts.copy()
    smooth = blend_smoothing_operator(rest, faces)
    ring = (smooth != 0).astype(np.int8).tocsr()
    limit = np.stack([np.maximum(np.linalg.norm(rest[faces[:, (k + 1) % 3]] - rest[faces[:, k]],
                                                axis=1), 1e-12) for k in range(3)], 1)  # fmt: skip
    limit = (max_stretch * limit) ** 2

    def torn():
        over = np.ptp(beta[faces], axis=1).max(1) > 0
        longer = np.zeros(len(faces), bool)
        for k in range(3):
            e = verts[:, faces[:, (k + 1) % 3]] - verts[:, faces[:, k]]
            longer |= (np.einsum("fti,fti->ft", e, e) > limit[:, k]).any(0)
        return np.flatnonzero(over & longer)

    bad, taken, k, before = torn(), 0, 1, np.inf
    torn_before, beta_in, verts_in = len(bad), beta.copy(), verts.copy()
    changed = np.zeros(len(rest), bool)
    while len(bad) and taken < steps:
        k = min(2 * k, 8) if len(bad) >= before else k
        before, k = len(bad), min(k, steps - taken)
        taken += k
        S = np.unique(faces[bad])
        for _ in range(k):
            S = np.unique(ring[S].indices)
        for _ in range(k):
            beta[S] = smooth[S] @ beta
        b = beta[S]
        b[b < 1e-3] = 0.0
        b /= b.sum(1, keepdims=True)
        beta[S], changed[S] = b, True
        moved = np.zeros((len(verts), len(S), 3))
        for p in range(beta.shape[1]):
            sel = np.flatnonzero(b[:, p] > 0)
            if len(sel):
                one = vertex_operator([models[p]], len(sel), residual=residual,
                                      rest=rest[S[sel]], beta=np.ones((len(sel), 1)))  # fmt: skip
                alone = deform_positions([models[p]], [fits[p]], len(sel), one, residual=residual)
                moved[:, sel] += b[sel, p][None, :, None] * alone
        verts[:, S] = moved
        bad = torn()
    if len(bad) >= torn_before:  # no fewer torn triangles: nothing changes
        return beta_in, verts_in, taken, 0, torn_before, len(bad)
    return beta, verts, taken, int(changed.sum()), torn_before, len(bad)


@pytest.mark.parametrize("mode", ["quadratic_residual", "rigid"])
def test_widen_blends_matches_the_direct_loop(limb, mode):
    """The incremental widening (edges checked again only where an end moved, vertices moved
    again only where their weights changed) gives the same bytes as the plain loop: β,
    positions, steps and reweighted vertices; also when the step budget runs out, and when
    the widening does not tear fewer triangles (then nothing changes)."""
    seg, x, mesh = limb["seg"], limb["markers"].positions, limb["mesh"]
    V, residual = mesh.vertices, mode.endswith("residual")
    beta = bind_mesh(V, seg, sharpness=4.0).beta
    models = [prepare_part(seg, p) for p in range(seg.n_parts)]
    fits = [fit_part(m, x[:, m.members], mode=mode) for m in models]
    verts = deform_positions(models, fits, len(V), vertex_operator(
        models, len(V), residual=residual, rest=V, beta=beta), residual=residual)  # fmt: skip
    widened = kept = 0
    for stretch, steps in ((1.05, 100), (1.05, 3), (1.3, 100), (2.0, 100)):
        kw = {"max_stretch": stretch, "steps": steps, "residual": residual}
        want_beta, want_verts, want_steps, want_n, *want_torn = _widen_blends_directly(
            models, fits, mesh, beta, verts, **kw)
        got_verts = verts.copy()
        got_beta, got_steps, got_n, *got_torn = _widen_blends(models, fits, mesh, beta,
                                                             got_verts, **kw)
        assert want_steps >= min(steps, 2)
        if want_n:  # the blends were widened: fewer torn triangles
            widened += want_n > 10 and want_torn[1] < want_torn[0]
        else:  # as many torn or more (at 1.05 widening blends more triangles): kept as it was
            kept += want_torn[1] >= want_torn[0] > 0
            assert want_verts.tobytes() == verts.tobytes()
        assert (got_steps, got_n, got_torn) == (want_steps, want_n, want_torn)
        assert got_beta.tobytes() == want_beta.tobytes()
        assert got_verts.tobytes() == want_verts.tobytes()
    assert widened and kept  # both outcomes covered


def test_rows_store_across_blocks():
    """_Rows keeps rows appended across its growing blocks; take/put by row index."""
    rng = np.random.default_rng(5)
    store, kept = _Rows(4, first_block=3), []
    for k in (2, 5, 1, 9):  # blocks of 3, 6, 12 rows: appends straddle them
        rows = rng.standard_normal((4, k, 3))  # frame-major, as deform_positions returns
        assert (store.append(rows) == np.arange(store.n - k, store.n)).all()
        kept.append(rows.transpose(1, 0, 2))
    kept = np.concatenate(kept)
    assert len(store.blocks) == 3 and store.n == len(kept) == 17
    index = rng.permutation(17)[:8]
    assert store.take(index).tobytes() == kept[index].tobytes()
    store.put(index[:4], -kept[index[:4]])
    kept[index[:4]] *= -1
    assert store.take(np.arange(17)).tobytes() == kept.tobytes()
    for rows in (np.arange(3, 9), index):  # into a given array: within one block, across
        out = np.full((len(rows), 4, 3), np.nan)
        assert store.take(rows, out) is out and out.tobytes() == kept[rows].tobytes()


def test_deform_modules_import_one_way():
    """The stage (deform) imports the vertex evaluation (blend) and the blend widening
    (widening); the widening may import blend; blend imports neither."""
    import ast
    import importlib

    def skin_imports(name):
        tree = ast.parse(open(importlib.import_module(f"mocapflow.stages.skin.{name}").__file__,
                              encoding="utf-8").read())  # fmt: skip
        return {n.module.rsplit(".", 1)[1] for n in ast.walk(tree)
                if isinstance(n, ast.ImportFrom) and (n.module or "").startswith(
                    "mocapflow.stages.skin.")}  # fmt: skip

    deform_imports, widening_imports = skin_imports("deform"), skin_imports("widening")
    assert {"blend", "widening"} <= deform_imports
    assert "blend" in widening_imports and "deform" not in widening_imports
    assert not {"deform", "widening"} & skin_imports("blend")
