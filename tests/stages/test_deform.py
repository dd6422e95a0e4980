"""Skin deformation (Park & Hodgins 2006 §5.3) and detailed-mesh fitting against ground truth."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mocapflow.pipeline import Context
from mocapflow.stages.data import Markers, Mesh
from mocapflow.stages.deform import (
    MODES,
    DeformError,
    bind_mesh,
    closest_points_on_triangles,
    cubic_bspline,
    deform,
    dilation,
    evaluate_part,
    fit_part,
    prepare_part,
    quadratic_basis,
    rbf_matrix,
)
from mocapflow.stages.mesh_fit import fit_detailed_mesh, fit_mesh
from mocapflow.stages.segment import Segmentation, part_frames, segment
from tests.stages.test_segment import deform_limb, grid_cylinder, limb_capture, rot_x, rot_y


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

    model = prepare_part(seg, 0, vertices=probes, beta=np.ones((len(probes), 1)))
    for mode, exact in [("quadratic", True), ("quadratic_residual", True), ("rigid", False)]:
        fit = fit_part(model, truth(ref), mode=mode)
        err = np.abs(evaluate_part(model, fit) - truth(probes)).max()
        if exact:
            assert err < 1e-9, mode
        else:
            assert err > 1e-3, mode  # rigid cannot represent it
    # missing markers in some frames (>= 10 visible): still exact
    x = truth(ref)
    x[1, :8] = np.nan
    x[3, 5:12] = np.nan
    fit = fit_part(model, x, mode="quadratic")
    assert np.abs(evaluate_part(model, fit) - truth(probes)).max() < 1e-9


def test_residual_interpolates_markers_exactly(limb):
    seg = limb["seg"]
    x = limb["markers"].positions
    for mode in ("rigid_residual", "quadratic_residual"):
        for p in range(seg.n_parts):
            m = prepare_part(seg, p)
            fit = fit_part(m, x[:, m.members], mode=mode)
            pred = evaluate_part(m, fit, m.local, m.basis(m.local), m.kernel.tocsr())
            assert np.abs(pred - x[:, m.members]).max() < 1e-10
    # and a mesh vertex placed on a marker lands on that marker (interior marker)
    i = int(np.argmin(np.abs(seg.reference[:, 1] - 0.1)))
    verts = np.concatenate([limb["mesh"].vertices, seg.reference[i : i + 1]])
    faces = limb["mesh"].faces
    out = deform(limb["markers"], seg, Mesh(verts, faces), ctx=Context())
    assert np.abs(out["mesh"].vertices[:, -1] - x[:, i]).max() < 1e-10


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
    # rigid: ~1 mm mean on this limb (bulge + joint blend not rigid); residuals: < 0.5 mm
    assert err["rigid"] > 0.8
    assert err["quadratic"] < err["rigid"]
    assert err["rigid_residual"] < 0.5 and err["quadratic_residual"] < 0.5


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
    # a vertex on a marker takes exactly that marker's alpha
    b2 = bind_mesh(seg.reference[:20], seg)
    assert np.allclose(b2.beta, seg.weights[:20], atol=1e-12)


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
    m = prepare_part(seg2, 0)
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
    from mocapflow.stages.mesh_fit import template_mesh

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
