"""Skin deformation (Park & Hodgins 2006 §5) on a simulated dense capture with ground truth.

One run prints five tables (``--graph-path`` prints its own, 5 below, instead):

1. segmentation of a range-of-motion trial against the simulator's parts
   (each marker's dominant skin-weight joint): adjusted Rand index over all
   markers and over the markers whose dominant weight is > 0.8 (the rest are
   blended across joints by construction, so "their" joint is a matter of taste);
2. held-out markers: markers removed from the whole pipeline (surface,
   segmentation, deformation) and predicted as if they were mesh vertices on a
   different (dynamic) trial; mean and p95 error in mm for the four modes and
   for baselines run in the same process: linear-blend skinning and
   dual-quaternion skinning driven by the same part transforms and weights, and
   one global thin-plate RBF (scipy ``RBFInterpolator``) on displacements; plus
   the paper's exact settings and one-change ablations of the stage defaults
   (β sharpness, quadratic damping, residual kernel), then the same errors
   broken down by how the held-out marker binds (one part or a part boundary;
   distance to its marker-surface triangle);
3. detailed mesh against the simulator's true mesh, per vertex over the trial:
   the true reference-pose mesh bound directly, and a perturbed template fitted
   with ``fit_mesh``; with the artifacts of each mode on the true mesh (triangles
   stretched > 3x, flipped against the rigid mode; the modes run the stage's
   default blend widening, ``max_blend_stretch=2.5``, and rows without it,
   ``None``, show what it changes; table 2 cannot show it: held-out points have
   no triangles);
4. throughput: frames per second deforming a ~13k-vertex mesh from 350 markers,
   in one process, with 2 worker processes (the stage's ``ctx.map``) and with 2
   threads of the process (the stage's ``threads``), with a plain NumPy linear-blend
   skinning of the same mesh as the in-process reference; BLAS at one thread, as the
   engine runs stages; best of 3 calls, and the first call's frames per CPU-second
   (fresh memory for the output and the work arrays, which a stage pays once per task).

Markers are the simulator's true skin-marker centres plus its measurement noise
(no occlusion: the deformation is measured, not the cleaning).

5. ``--graph-path`` (alone): the animated detailed mesh against the simulator's true
   body through the skin graph's own path and stage params (configs/skin.yaml):
   ``simulate_capture`` (range of motion + dynamic run of one subject, occlusion,
   fragments, ghosts, noise; the subject's shape drawn from the seed as in
   ``benchmarks/fit_mesh.py``) -> ``clean`` -> ``segment`` (ROM) -> ``template_mesh``
   (procedural or MakeHuman) -> ``fit_mesh`` (allen, with the automatic anatomical
   landmarks) -> ``match_markers`` -> ``deform`` (four modes); per template x seed x
   mode the mean / p95 distance of the deformed vertices to the true surface and of
   the true vertices to the deformed surface (mm) over the run's frames after the
   T-pose calibration (every 8th with ``--quick``, 4th otherwise), with the breakdown
   rows: the fitted rest mesh against the true rest mesh (registration), the true
   rest mesh through the same deform (no registration error), and the fitted mesh
   driven by the true marker positions (no cleaning error).  Seeds 3-5 (held out;
   0-2 for tuning).

Run: ``python benchmarks/deform.py`` (``--quick`` for a small run; ``--throughput``
for table 4 alone, 900 frames; with ``--quick`` on the small simulated body's
segmentation; ``--graph-path [--quick] [--seeds ...] [--templates ...]`` for table 5,
about 2 minutes per seed and template with ``--quick``).
"""

from __future__ import annotations

import argparse
import inspect
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path
from unittest import mock

import numpy as np
from scipy.interpolate import RBFInterpolator

from mocapflow.pipeline import Context
from mocapflow.pipeline.config import load_config
from mocapflow.pipeline.execute import single_threaded_blas
from mocapflow.stages.metrics.mesh import flipped_triangles, stretched_triangles
from mocapflow.stages.motion.datatypes import Markers, Mesh
from mocapflow.stages.motion.rotations import quat_from_matrix, quat_multiply, quat_rotate
from mocapflow.stages.motion.simulate import capture as sim_capture
from mocapflow.stages.motion.simulate.body import skin, skinning_transforms
from mocapflow.stages.motion.simulate.capsules import procedural_body
from mocapflow.stages.motion.simulate.capture import capture_motion, simulate_capture
from mocapflow.stages.motion.simulate.markers import place_markers
from mocapflow.stages.motion.simulate.skin_dynamics import SkinDynamics
from mocapflow.stages.skin.binding import DeformError, bind_mesh, closest_points_on_triangles
from mocapflow.stages.skin.clean import clean
from mocapflow.stages.skin.deform import deform
from mocapflow.stages.skin.mesh_fit import fit_mesh, skeleton_bones, template_mesh
from mocapflow.stages.skin.parts import MODES, evaluate_part, fit_part, prepare_part
from mocapflow.stages.skin.registration import anatomical_landmarks
from mocapflow.stages.skin.rom import match_markers
from mocapflow.stages.skin.segment import segment
from mocapflow.stages.skin.segmentation import adjusted_rand_index
from mocapflow.stages.skin.surface import build_marker_surface

RATE = 120.0
if str(Path(__file__).resolve().parent) not in sys.path:  # fit_mesh.py beside this file
    sys.path.insert(0, str(Path(__file__).resolve().parent))


# --------------------------------------------------------------------------- data


def simulate(*, n_markers, body_vertices, rom_frames, test_frames, seed, noise=0.0003,
             marker_radius=0.007):  # fmt: skip
    """One body and marker layout, two trials (range of motion, treadmill run), truth."""
    rng = np.random.default_rng(seed)
    rom = capture_motion("range_of_motion", rom_frames, rate=RATE, rng=rng)
    run = capture_motion("dynamic", test_frames, rate=RATE, rng=rng)
    body = procedural_body(rom.skeleton, n_vertices=body_vertices)
    sites = place_markers(body, n_markers, rng=rng)
    nb = body.normals
    if isinstance(sites, np.ndarray):  # vertex indices (older simulator API)
        skin_pts, skin_n, skin_w = body.vertices[sites], nb[sites], body.weights[sites]
    else:  # SurfacePoints: points inside triangles
        skin_pts, skin_n, skin_w = sites.points(body), sites.normals(body), sites.weights(body)
    skin_part = np.argmax(skin_w, axis=1)
    mpts = skin_pts + marker_radius * skin_n
    pts = np.concatenate([body.vertices, mpts])
    nrm = np.concatenate([nb, skin_n])
    W = np.concatenate([body.weights, skin_w])
    part = np.concatenate([body.part, skin_part])
    dyn = SkinDynamics()
    out = {"body": body, "part": skin_part, "weights": skin_w, "rom_motion": rom}
    for name, mot in (("rom", rom), ("test", run)):
        R, p = skinning_transforms(body, mot)
        allpos = dyn.apply(body, mot, R, p, pts, nrm, W, part, rng=rng)
        true = allpos[:, body.n_vertices :]
        out[name] = {
            "mesh": allpos[:, : body.n_vertices],
            "true": true,
            "observed": true + rng.normal(0.0, noise, true.shape),
        }
    return out


def labels_of(idx):
    return [f"M{i + 1:03d}" for i in idx]


def link_cycle(faces, v):
    """The one-ring of marker ``v`` as an ordered cycle, or None (boundary / non-manifold)."""
    star = faces[(faces == v).any(1)]
    if len(star) < 3:
        return None
    edges = [tuple(int(c) for c in f if c != v) for f in star]
    nbr: dict[int, list[int]] = {}
    for a, b in edges:
        nbr.setdefault(a, []).append(b)
        nbr.setdefault(b, []).append(a)
    if any(len(x) != 2 for x in nbr.values()):
        return None
    start = edges[0][0]
    cycle, prev = [start], None
    while True:
        nxt = [x for x in nbr[cycle[-1]] if x != prev][0] if prev is not None else nbr[start][0]
        if nxt == start:
            break
        prev = cycle[-1]
        cycle.append(nxt)
        if len(cycle) > len(nbr):
            return None
    return cycle if len(cycle) == len(nbr) else None


def choose_held_out(faces, n_markers, count, rng):
    """``count`` markers, no two adjacent, each with a closed one-ring."""
    order = rng.permutation(n_markers)
    held, blocked = [], set()
    for v in order:
        if v in blocked or link_cycle(faces, v) is None:
            continue
        held.append(int(v))
        blocked |= {int(v)} | {int(c) for f in faces[(faces == v).any(1)] for c in f}
        if len(held) == count:
            break
    return np.sort(np.array(held))


def surface_without(faces, held):
    """Faces of the marker surface with ``held`` removed and each hole fanned closed."""
    keep_f = faces[~np.isin(faces, held).any(1)]
    fans = []
    for v in held:
        c = link_cycle(faces, v)
        fans += [(c[0], c[i], c[i + 1]) for i in range(1, len(c) - 1)]
    return np.concatenate([keep_f, np.array(fans, dtype=np.int64).reshape(-1, 3)])


def segment_markers(rom_obs, keep, faces, **kw):
    """Segmentation of the kept markers on the ROM trial (frame 0 = T-pose) over ``faces``."""
    remap = np.full(rom_obs.shape[1], -1)
    remap[keep] = np.arange(len(keep))
    X = rom_obs[:, keep]
    surf = Mesh(X[0], remap[faces], attrs={"labels": labels_of(keep)})
    mk = Markers(X, labels_of(keep), RATE)
    ctx = Context()
    out = segment(mk, surf, ctx=ctx, **kw)
    return out["segmentation"], out["report"], ctx.warnings


# --------------------------------------------------------------------------- baselines


def part_world_transforms(seg, x):
    """Per-part rigid transforms (the ``rigid`` mode's) as world maps ``x = M v + b``."""
    Ms, bs = [], []
    for p in range(seg.n_parts):
        m = prepare_part(seg, p)
        fit = fit_part(m, x[:, m.members], mode="rigid")
        M = fit.R @ m.axes.T  # (F, 3, 3)
        Ms.append(M)
        bs.append(fit.d - M @ m.origin)
    return np.stack(Ms, 1), np.stack(bs, 1)  # (F, P, 3, 3), (F, P, 3)


def lbs(points, beta, M, b):
    """Linear blend skinning of rest ``points (N, 3)`` with weights ``beta (N, P)``."""
    moved = np.einsum("fpij,nj->fnpi", M, points) + b[:, None]
    return np.einsum("np,fnpi->fni", beta, moved)


def dqs(points, beta, M, b):
    """Dual-quaternion skinning (Kavan et al. 2008) with the same transforms and weights."""
    qr = quat_from_matrix(M)  # (F, P, 4)
    t = np.concatenate([np.zeros(b.shape[:-1] + (1,)), b], -1)
    qd = 0.5 * quat_multiply(t, qr)
    pivot = np.argmax(beta, axis=1)  # align signs with each point's main part
    sign = np.sign(np.einsum("fpk,fnk->fnp", qr, qr[:, pivot]))
    sign[sign == 0] = 1
    br = np.einsum("np,fnp,fpk->fnk", beta, sign, qr)
    bd = np.einsum("np,fnp,fpk->fnk", beta, sign, qd)
    norm = np.linalg.norm(br, axis=-1, keepdims=True)
    br, bd = br / norm, bd / norm
    conj = br * np.array([1, -1, -1, -1])
    trans = 2 * quat_multiply(bd, conj)[..., 1:]
    return quat_rotate(br, np.broadcast_to(points, br.shape[:-1] + (3,))) + trans


def global_rbf(ref, x, query):
    """One thin-plate RBF on displacements per frame (all frames in one solve)."""
    F = x.shape[0]
    disp = (x - ref[None]).transpose(1, 0, 2).reshape(len(ref), F * 3)
    out = RBFInterpolator(ref, disp, kernel="thin_plate_spline")(query)
    return out.reshape(len(query), F, 3).transpose(1, 0, 2) + query[None]


_DEFAULTS = {k: v.default for k, v in inspect.signature(deform).parameters.items()}
DEFAULT = {"sharpness": _DEFAULTS["beta_sharpness"], "damping": _DEFAULTS["quadratic_damping"],
           "kernel": _DEFAULTS["residual_kernel"], "support": _DEFAULTS["support_margin"],
           "clamp": _DEFAULTS["clamp_margin"],
           "widen": _DEFAULTS["max_blend_stretch"]}  # the stage's defaults
PAPER = {"sharpness": 1.0, "damping": 0.0, "kernel": "cubic_bspline", "support": None,
         "clamp": None, "widen": None}  # Park & Hodgins exactly (no support box, clamp, widening)
OTHER_KERNEL = "thin_plate" if DEFAULT["kernel"] == "cubic_bspline" else "cubic_bspline"


def ours(seg, x, points, mode, *, sharpness, damping, kernel, support=DEFAULT["support"],
         clamp=DEFAULT["clamp"], widen=None):
    """Our prediction of rest ``points`` (mesh vertices) for one mode and settings.

    ``widen`` (the stage's ``max_blend_stretch``) is ignored: widening a blend needs the
    mesh's triangles and held-out points have none (table 3 measures it)."""
    beta = bind_mesh(points, seg, min_overlap=0.0, sharpness=sharpness).beta
    out = np.zeros((x.shape[0], len(points), 3))
    for p in range(seg.n_parts):
        sel = np.flatnonzero(beta[:, p] > 0)
        if sel.size == 0:
            continue
        m = prepare_part(seg, p, vertices=points, beta=beta, residual_kernel=kernel,
                         support_margin=support, clamp_margin=clamp)
        fit = fit_part(m, x[:, m.members], mode=mode, damping=damping)
        out[:, sel] += beta[sel, p][None, :, None] * evaluate_part(m, fit)
    return out


def settings_label(st):
    """Short description of the settings that differ from the stage's defaults."""
    diff = [f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}"
            for k, v in st.items() if v != DEFAULT[k]]  # fmt: skip
    return ", ".join(diff) or "defaults"


# --------------------------------------------------------------------------- tables


def err_stats(pred, truth):
    e = np.linalg.norm(pred - truth, axis=-1) * 1000
    return float(e.mean()), float(np.percentile(e, 95))


def print_table(title, header, rows):
    print(f"\n## {title}\n")
    print("| " + " | ".join(header) + " |")
    print("|" + "|".join("---" for _ in header) + "|")
    for r in rows:
        print("| " + " | ".join(str(c) for c in r) + " |")


def segmentation_table(sim, rom_obs, full_faces):
    """Table 1: the segmentation of the ROM trial against the simulator's parts.

    Returns the segmentation with the stage's defaults."""
    n_markers = rom_obs.shape[1]
    allm = np.arange(n_markers)
    truth = sim["part"]
    clear = sim["weights"].max(1) > 0.8
    rows = []
    seg_default = None
    for kw in ({}, {"n_parts": 17}, {"merge_rms": None}):
        t = time.perf_counter()
        seg, rep, _ = segment_markers(rom_obs, allm, full_faces, **kw)
        dt = time.perf_counter() - t
        if not kw:
            seg_default = seg
        hl = seg.hard_labels
        rows.append([
            ", ".join(f"{k}={v}" for k, v in kw.items()) or "defaults", rep["n_clusters"],
            seg.n_parts, f"{adjusted_rand_index(hl, truth):.3f}",
            f"{adjusted_rand_index(hl[clear], truth[clear]):.3f}",
            len(rep["boundary_markers"]), f"{dt:.1f}",
        ])  # fmt: skip
    print_table(
        f"Segmentation vs simulator parts ({len(np.unique(truth))} dominant joints; "
        f"{clear.sum()} markers with dominant weight > 0.8)",
        ["params", "mean-shift clusters", "parts", "ARI all", "ARI weight>0.8",
         "boundary markers", "s"], rows)  # fmt: skip
    return seg_default


def held_out_table(sim, rom_obs, full_faces, *, folds, seed):
    """Table 2: held-out markers predicted as mesh vertices, ours (modes, paper, ablations)
    and the baselines, then the errors by how the held-out markers bind."""
    n_markers = rom_obs.shape[1]
    allm = np.arange(n_markers)
    rng = np.random.default_rng(seed + 100)
    x_test_all = sim["test"]["observed"]
    true_test = sim["test"]["true"]
    variants = {  # name -> (mode, settings)
        **{m: (m, DEFAULT) for m in MODES},
        "quadratic_residual, paper (barycentric beta, Eq. 6 pinv, B-spline)":
            ("quadratic_residual", PAPER),
        "quadratic_residual, beta sharpness 1 (barycentric)":
            ("quadratic_residual", {**DEFAULT, "sharpness": 1.0}),
        "quadratic_residual, damping 0 (Eq. 6 pinv)":
            ("quadratic_residual", {**DEFAULT, "damping": 0.0}),
        f"quadratic_residual, {OTHER_KERNEL} kernel":
            ("quadratic_residual", {**DEFAULT, "kernel": OTHER_KERNEL}),
        f"rigid_residual, {OTHER_KERNEL} kernel":
            ("rigid_residual", {**DEFAULT, "kernel": OTHER_KERNEL}),
    }  # fmt: skip
    methods = [*variants, "LBS (same parts)", "DQS (same parts)",
               "LBS (same parts, barycentric beta)", "global thin-plate RBF"]  # fmt: skip
    errs = {m: [] for m in methods}
    times = {m: 0.0 for m in methods}
    n_parts, bind_d = [], []  # per held-out marker: parts it binds to, distance to its triangle
    for _ in range(folds):
        held = choose_held_out(full_faces, n_markers, n_markers // 10, rng)
        keep = np.setdiff1d(allm, held)
        seg, _, _ = segment_markers(rom_obs, keep, surface_without(full_faces, held))
        ref_h = rom_obs[0, held]  # held-out "vertices" in the reference pose
        b1 = bind_mesh(ref_h, seg, min_overlap=0.0, sharpness=1.0)
        n_parts.append((b1.beta > 0).sum(1))
        bind_d.append(b1.distance)
        x = x_test_all[:, keep]
        for name, (mode, st) in variants.items():
            t = time.perf_counter()
            pred = ours(seg, x, ref_h, mode, **st)
            times[name] += time.perf_counter() - t
            errs[name].append(np.linalg.norm(pred - true_test[:, held], axis=-1))
        t = time.perf_counter()
        M, b = part_world_transforms(seg, x)
        t_tr = time.perf_counter() - t
        beta = bind_mesh(ref_h, seg, min_overlap=0.0, sharpness=DEFAULT["sharpness"]).beta
        for name, fn, bt in (("LBS (same parts)", lbs, beta), ("DQS (same parts)", dqs, beta),
                             ("LBS (same parts, barycentric beta)", lbs, b1.beta)):
            t = time.perf_counter()
            pred = fn(ref_h, bt, M, b)
            times[name] += time.perf_counter() - t + t_tr
            errs[name].append(np.linalg.norm(pred - true_test[:, held], axis=-1))
        t = time.perf_counter()
        pred = global_rbf(seg.reference, x, ref_h)
        times["global thin-plate RBF"] += time.perf_counter() - t
        errs["global thin-plate RBF"].append(np.linalg.norm(pred - true_test[:, held], axis=-1))
    rows = []
    for m in methods:
        e = np.concatenate([a.ravel() for a in errs[m]]) * 1000
        rows.append([m, f"{e.mean():.2f}", f"{np.percentile(e, 95):.2f}", f"{e.max():.1f}",
                     f"{times[m]:.2f}"])  # fmt: skip
    best = min(methods, key=lambda m: float(rows[methods.index(m)][1]))
    print_table(
        f"Held-out markers ({n_markers // 10} per fold x {folds} folds, predicted on the run "
        f"trial; defaults: beta sharpness {DEFAULT['sharpness']:g}, quadratic damping "
        f"{DEFAULT['damping']:g}, {DEFAULT['kernel']} residual; lowest mean: {best})",
        ["method", "mean mm", "p95 mm", "max mm", "s"], rows)
    binding_table(errs, np.concatenate(n_parts), np.concatenate(bind_d) * 1000)


def binding_table(errs, n_parts, bind_d):
    """Where the held-out error is: markers binding to one part vs across a part boundary,
    and by the distance (mm) to the marker-surface triangle they bind to (holes -> far
    triangles)."""
    groups = {
        "binds to 1 part": n_parts == 1, "binds to >= 2 parts": n_parts >= 2,
        "triangle < 5 mm away": bind_d < 5, "triangle 5-15 mm away": (bind_d >= 5) & (bind_d < 15),
        "triangle >= 15 mm away": bind_d >= 15,
    }  # fmt: skip
    cols = ["quadratic_residual, paper (barycentric beta, Eq. 6 pinv, B-spline)",
            "quadratic_residual", "rigid", "global thin-plate RBF"]  # fmt: skip
    rows = []
    for g, sel in groups.items():
        row = [g, int(sel.sum())]
        for m in cols:
            e = np.concatenate(errs[m], axis=1)[:, sel] * 1000
            row.append(f"{e.mean():.2f} / {np.percentile(e, 95):.2f}" if e.size else "-")
        rows.append(row)
    print_table("Held-out error by binding (mean / p95 mm)",
                ["held-out markers", "n", "paper q+r", "q+r (defaults)", "rigid (defaults)",
                 "global TPS"], rows)  # fmt: skip


def true_mesh_table(sim, seg, mk_test):
    """Table 3: the detailed mesh against the simulator's true mesh, per vertex: the true
    rest mesh bound directly (modes, paper, ablations, DQS, global TPS) and a perturbed
    template fitted with ``fit_mesh``."""
    x_test_all = mk_test.positions
    rest_true = sim["rom"]["mesh"][0]
    faces = sim["body"].faces
    true_mesh = sim["test"]["mesh"]
    rows = []
    rigid = deform(mk_test, seg, Mesh(rest_true, faces), mode="rigid", ctx=Context())
    # flipped triangles are counted against the default rigid mode (widened, like the
    # stage's own test)
    artifacts = partial(mesh_artifacts, faces, rest_true, rigid["mesh"].vertices)
    for mode in MODES:
        t = time.perf_counter()
        out = rigid if mode == "rigid" else deform(mk_test, seg, Mesh(rest_true, faces),
                                                   mode=mode, ctx=Context())  # fmt: skip
        dt = time.perf_counter() - t
        rows.append([f"true rest mesh, {mode}", *(f"{v:.2f}" for v in
                     err_stats(out["mesh"].vertices, true_mesh)),
                     *artifacts(out["mesh"].vertices), "" if mode == "rigid" else f"{dt:.1f}"])
    for label, st in (("paper (barycentric beta, Eq. 6 pinv, B-spline)", PAPER),
                      ("beta sharpness 1", {**DEFAULT, "sharpness": 1.0}),
                      (f"{OTHER_KERNEL} kernel", {**DEFAULT, "kernel": OTHER_KERNEL}),
                      ("no blend widening (max_blend_stretch None)", {**DEFAULT, "widen": None})):
        out = deform(mk_test, seg, Mesh(rest_true, faces), beta_sharpness=st["sharpness"],
                     quadratic_damping=st["damping"], residual_kernel=st["kernel"],
                     support_margin=st["support"], clamp_margin=st["clamp"],
                     max_blend_stretch=st["widen"], ctx=Context())  # fmt: skip
        rows.append([f"true rest mesh, quadratic_residual, {label}",
                     *(f"{v:.2f}" for v in err_stats(out["mesh"].vertices, true_mesh)),
                     *artifacts(out["mesh"].vertices), ""])
    out = deform(mk_test, seg, Mesh(rest_true, faces), mode="rigid", max_blend_stretch=None,
                 ctx=Context())  # fmt: skip
    rows.append(["true rest mesh, rigid, no blend widening (max_blend_stretch None)",
                 *(f"{v:.2f}" for v in err_stats(out["mesh"].vertices, true_mesh)),
                 *artifacts(out["mesh"].vertices), ""])
    beta = bind_mesh(rest_true, seg).beta
    M, b = part_world_transforms(seg, x_test_all)
    rows.append(["true rest mesh, DQS (same parts; LBS = the rigid mode)",
                 *(f"{v:.2f}" for v in err_stats(dqs(rest_true, beta, M, b), true_mesh)),
                 "", "", ""])
    t = time.perf_counter()
    tps = np.concatenate([global_rbf(seg.reference, x_test_all[a : a + 100], rest_true)
                          for a in range(0, x_test_all.shape[0], 100)])  # fmt: skip
    rows.append(["true rest mesh, global thin-plate RBF",
                 *(f"{v:.2f}" for v in err_stats(tps, true_mesh)), "", "",
                 f"{time.perf_counter() - t:.1f}"])  # fmt: skip
    del tps
    # a scan-like template in the reference pose: 6 % wider, with smooth 4 mm bumps, shifted
    tmpl = rest_true.copy()
    c = tmpl.mean(0)
    tmpl[:, [0, 2]] = c[[0, 2]] + (tmpl[:, [0, 2]] - c[[0, 2]]) * 1.06
    tmpl += 0.004 * np.sin(tmpl * 9.0) + [0.01, 0.005, -0.01]
    ctxf = Context()
    t = time.perf_counter()
    fitted = fit_mesh(Mesh(tmpl, faces), seg, marker_offset=0.007, ctx=ctxf)
    t_fit = time.perf_counter() - t
    rep = fitted["report"]
    rest_err = np.linalg.norm(fitted["mesh"].vertices - rest_true, axis=1) * 1000
    out = deform(mk_test, seg, fitted["mesh"], ctx=Context())
    rows.append(["fitted template (reference pose only)", f"{rest_err.mean():.2f}",
                 f"{np.percentile(rest_err, 95):.2f}", "", "", f"{t_fit:.1f}"])  # fmt: skip
    rows.append(["fitted template, quadratic_residual",
                 *(f"{v:.2f}" for v in err_stats(out["mesh"].vertices, true_mesh)), "", "", ""])
    rows.append(["(template before fitting, reference pose)",
                 *(f"{v:.2f}" for v in err_stats(tmpl, rest_true)), "", "", ""])
    print_table(
        f"Detailed mesh ({len(rest_true)} vertices) vs the simulator's true mesh, per vertex "
        f"over {true_mesh.shape[0]} frames (fit_mesh: markers-to-surface RMS "
        f"{rep['aligned']['rms_mm']:.1f} mm aligned -> {rep['fitted']['rms_mm']:.1f} mm fitted)",
        ["mesh / mode", "mean mm", "p95 mm", "stretched > 3x", "flipped vs rigid", "s"], rows)


def mesh_artifacts(faces, rest, rigid, verts):
    """Triangles of ``verts (F, V, 3)`` stretched > 3x against ``rest`` and flipped against
    the ``rigid`` mode in some frame (:mod:`mocapflow.stages.metrics.mesh`, the check of
    ``tests/stages/skin/test_artifacts.py``), as two strings."""
    return (str(int(stretched_triangles(verts, rest, faces).sum())),
            str(int(flipped_triangles(verts, rigid, faces).sum())))


def throughput_table(sim, seg, mk_test, *, frames):
    """Table 4: frames per second deforming a ~13k-vertex mesh, in process, with 2 worker
    processes and with 2 threads (``threads=2``), against a NumPy linear-blend skinning of
    the same mesh.

    BLAS runs at one thread, as the engine runs every stage (``single_threaded_blas``):
    with a threaded BLAS on a loaded 2-core machine each small product can cost ~20 ms
    of thread hand-off, whatever the code."""
    n_markers = mk_test.n_markers
    big = procedural_body(sim["body"].skeleton, n_vertices=13000)
    rom0 = sim["rom_motion"]
    R0, p0 = skinning_transforms(big, rom0.replace(root_position=rom0.root_position[:1],
                                                   rotations=rom0.rotations[:1]))  # fmt: skip
    big_rest = skin(big, R0, p0)[0]  # the reference (first ROM) frame, like the markers
    mesh13 = Mesh(big_rest, big.faces)
    mk = Markers(mk_test.positions[:frames], mk_test.labels, RATE)
    rows = []

    def timed(fn):
        """Frames per second and per CPU-second: best of 3 calls, and the first call's
        frames per CPU-second (fresh pages for the output and the work arrays: what a
        stage pays once per task)."""
        best_t = best_c = np.inf
        first_c = None
        for _ in range(3):
            t, c = time.perf_counter(), time.process_time()
            fn()
            best_t = min(best_t, time.perf_counter() - t)
            best_c = min(best_c, time.process_time() - c)
            first_c = first_c or time.process_time() - c
        return frames / best_t, frames / best_c, frames / first_c

    with ProcessPoolExecutor(2) as pool, single_threaded_blas():
        procs = lambda fn, items: list(pool.map(fn, items))  # noqa: E731
        list(pool.map(abs, [1, 2]))  # start the workers
        setups = [  # (label, processes, mapper, chunk_frames, threads)
            ("in-process", 1, None, frames, 1),
            ("in-process on 2 threads (threads=2)", 1, None, frames, 2),
            ("part fits on workers, one evaluation pass", 2, procs, frames, 1),
            ("part fits on workers, one evaluation pass on 2 threads", 2, procs, frames, 2),
            ("part fits + 4 frame chunks on workers", 2, procs, -(-frames // 4), 1),
        ]  # fmt: skip
        for mode in ("quadratic_residual", "rigid"):
            for label, n_proc, mp, chunk, n_threads in setups:
                fps, cps, first = timed(partial(deform, mk, seg, mesh13, mode=mode,
                                                chunk_frames=chunk, threads=n_threads,
                                                ctx=Context(mapper=mp)))  # fmt: skip
                rows.append([f"ours, {mode}, {label}", n_proc, f"{fps:.0f}",
                             f"{cps:.0f}" if n_proc == 1 else "",
                             f"{first:.0f}" if n_proc == 1 else ""])  # fmt: skip
            fps, cps, first = timed(partial(deform, mk, seg, mesh13, mode=mode,
                                            max_blend_stretch=None, ctx=Context()))
            rows.append([f"ours, {mode}, in-process, no blend widening (max_blend_stretch None)",
                         1, f"{fps:.0f}", f"{cps:.0f}", f"{first:.0f}"])  # fmt: skip
        beta = bind_mesh(big_rest, seg).beta

        def numpy_lbs():
            M, b = part_world_transforms(seg, mk.positions)
            out = np.empty((frames, len(big.vertices), 3))
            for a in range(0, frames, 16):
                out[a : a + 16] = lbs(big_rest, beta, M[a : a + 16], b[a : a + 16])

        fps, cps, first = timed(numpy_lbs)
    rows.append(["NumPy LBS baseline (dense weights)", 1, f"{fps:.0f}", f"{cps:.0f}",
                 f"{first:.0f}"])
    print_table(
        f"Throughput: {len(big_rest)}-vertex mesh from {n_markers} markers, {frames} frames "
        "(best of 3 and the first of them, whole stage incl. binding; BLAS at one thread as in "
        "the engine; 2 = two "
        "worker processes behind ctx.map; the stage's default blend widening unless said; "
        "target >= 1500 frames/s; frames per CPU-second of "
        "this process shows the cost independently of other load on the machine)",
        ["method", "processes", "frames/s", "frames/CPU-s", "first call, frames/CPU-s"], rows)


# --------------------------------------------------------------------------- graph path


MAKEHUMAN = "/work/shared/data/mesh/makehuman_base.obj"
GRAPH_NODES = ("clean", "rom_clean", "segment", "template", "fit", "match", "deform")


def graph_params() -> dict[str, dict]:
    """The skin graph's own stage params (configs/skin.yaml, defaults filled), per node."""
    cfg = load_config("skin", parts=[__file__])
    return {n: dict(cfg.nodes[n].params) for n in GRAPH_NODES}


def simulate_graph_captures(seed, *, subject, rom_frames, test_frames, body_vertices):
    """A range-of-motion and a dynamic capture (stage ``simulate_capture``: occlusion,
    fragments, ghosts, noise) of one subject whose shape is drawn from ``seed``
    (``fit_mesh.shaped_body``: height, bone lengths, girths; procedural or MakeHuman).

    The simulator builds its body with ``capture.capture_body``; it is swapped for the
    shaped body here, everything else is the stage as the demo runs it."""
    from fit_mesh import shaped_body  # noqa: PLC0415 (the subject of benchmarks/fit_mesh.py)

    body = shaped_body(seed, kind=subject, n_vertices=body_vertices)
    out = {}
    with mock.patch.object(sim_capture, "capture_body", lambda *a, **k: body):
        for name, motion, n in (("rom", "range_of_motion", rom_frames),
                                ("test", "dynamic", test_frames)):
            ctx = Context(part=f"seed={seed}", seed=seed)
            out[name] = simulate_capture(n_markers=350, n_frames=n, motion=motion, seed=seed,
                                         ctx=ctx)  # fmt: skip
    return body, out


def graph_landmarks(body, rom, seg, template, ref_frame):
    """The automatic anatomical landmarks (``{marker label: template vertex}``): markers on
    the simulated body's bones (its dominant joint, ``truth["part"]``) matched to template
    vertices at the same place on the same bone (``registration.anatomical_landmarks``)."""
    truth = rom["truth"]
    index = {lb: i for i, lb in enumerate(truth["labels"])}
    names = truth["part_names"]
    marker_joint = [names[truth["part"][index[lb]]] for lb in seg.labels]
    R, p = skinning_transforms(body, rom["motion"])
    bones = skeleton_bones(body, R[ref_frame], p[ref_frame])
    tn = template.attrs["joint_names"]
    vj = [tn[j] for j in template.attrs["vertex_part"]]
    lm = anatomical_landmarks(seg.reference, marker_joint, bones, template.vertices, vj,
                              template.attrs["bones"])  # fmt: skip
    return {seg.labels[m]: v for m, v in lm.items()}


def surface_errors_mm(verts, faces, true_verts, true_faces):
    """Per frame: mean distance (mm) of ``verts``' vertices to the true surface and of the
    true vertices to ``verts``' surface, pooled as two flat arrays."""
    fwd = [closest_points_on_triangles(v, t, true_faces, k=24)[2] for v, t in
           zip(verts, true_verts)]  # fmt: skip
    back = [closest_points_on_triangles(t, v, faces, k=24)[2] for v, t in
            zip(verts, true_verts)]  # fmt: skip
    return np.concatenate(fwd) * 1000, np.concatenate(back) * 1000


def graph_path_run(seed, template_name, *, quick, stride):
    """One seed and template through the skin graph's own path, against the true body."""
    P = graph_params()
    t0 = time.perf_counter()
    body, cap = simulate_graph_captures(seed, subject=template_name,
                                        rom_frames=240 if quick else 600,
                                        test_frames=240 if quick else 480,
                                        body_vertices=3000 if quick else 6000)  # fmt: skip
    rom_c = clean(cap["rom"]["markers"], **P["rom_clean"], ctx=Context())
    test_c = clean(cap["test"]["markers"], **P["clean"], ctx=Context())
    seg = segment(rom_c["markers"], rom_c["surface"], **P["segment"], ctx=Context())
    seg = seg["segmentation"]
    tkw = {**P["template"], "body_mesh": MAKEHUMAN if template_name == "makehuman" else None}
    if quick:
        tkw["n_vertices"] = 5000  # the quick demo's
    template = template_mesh(**tkw, ctx=Context())["mesh"]
    ref_frame = rom_c["report"]["reference_frame"]
    lm = graph_landmarks(body, cap["rom"], seg, template, ref_frame)
    try:
        fit = fit_mesh(template, seg, **{**P["fit"], "landmarks": lm}, ctx=Context())["mesh"]
    except DeformError as e:  # the stage refuses the template: a row says so
        print(f"  seed {seed} {template_name}: fit_mesh fails", flush=True)
        return [[str(seed), template_name, f"fit_mesh fails: {str(e)[:70]}…", "", "", "",
                 ""]], {}  # fmt: skip
    mk = match_markers(test_c["markers"], seg, **P["match"], ctx=Context())["markers"]
    true_mesh = cap["test"]["mesh"]
    true_faces = true_mesh.faces
    n_cal = cap["test"]["motion"].attrs.get("calibration_frames", 0)
    frames = np.arange(n_cal, true_mesh.vertices.shape[0], stride)  # the motion, not the T-pose
    true_v = true_mesh.vertices[frames]
    true_rest = cap["rom"]["mesh"].vertices[ref_frame]
    rows = []

    def row(what, verts, faces):
        f, b = surface_errors_mm(verts, faces, true_v, true_faces)
        rows.append([str(seed), template_name, what, f"{f.mean():.2f}",
                     f"{np.percentile(f, 95):.2f}", f"{b.mean():.2f}",
                     f"{np.percentile(b, 95):.2f}"])  # fmt: skip
        return f.mean()

    f, b = (closest_points_on_triangles(fit.vertices, true_rest, true_faces, k=24)[2] * 1000,
            closest_points_on_triangles(true_rest, fit.vertices, fit.faces, k=24)[2] * 1000)
    rows.append([str(seed), template_name, f"fitted rest mesh vs true rest ({len(lm)} landmarks)",
                 f"{f.mean():.2f}", f"{np.percentile(f, 95):.2f}", f"{b.mean():.2f}",
                 f"{np.percentile(b, 95):.2f}"])  # fmt: skip
    dkw = dict(P["deform"])
    means = {}
    for mode in MODES:
        out = deform(mk, seg, fit, **{**dkw, "mode": mode}, ctx=Context())["mesh"].vertices
        means[mode] = row(f"fitted, {mode}", out[frames], fit.faces)
    # the same deformation of the true rest body: what registration costs
    out = deform(mk, seg, Mesh(true_rest, true_faces), **dkw, ctx=Context())["mesh"].vertices
    row(f"true rest mesh, {dkw['mode']}", out[frames], true_faces)
    # the same with the true marker positions (no cleaning error)
    mk_true = Markers(cap["test"]["truth"]["positions"], cap["test"]["truth"]["labels"],
                      mk.rate)
    mk_true = match_markers(mk_true, seg, **P["match"], ctx=Context())["markers"]
    out = deform(mk_true, seg, fit, **dkw, ctx=Context())["mesh"].vertices
    row(f"fitted, {dkw['mode']}, true marker positions", out[frames], fit.faces)
    print(f"  seed {seed} {template_name}: {time.perf_counter() - t0:.0f} s", flush=True)
    return rows, means


def graph_path_table(*, seeds, templates, quick):
    """Table 5: the animated detailed mesh against the true body through the graph's path."""
    stride = 8 if quick else 4
    rows, summary = [], {}
    for seed in seeds:
        for name in templates:
            r, means = graph_path_run(seed, name, quick=quick, stride=stride)
            rows += r
            for mode, v in means.items():
                summary.setdefault((name, mode), []).append(v)
    print_table(
        f"Animated detailed mesh vs the simulator's true body through the skin graph's path "
        f"(simulate_capture -> clean -> segment (ROM) -> template_mesh -> fit_mesh allen + "
        f"automatic landmarks -> match_markers -> deform, params of configs/skin.yaml; "
        f"seeds {seeds}; motion frames after the T-pose calibration, every {stride}th; "
        f"distances vertex to surface, mm)",
        ["seed", "template", "mesh / mode", "fitted->true mean", "p95", "true->fitted mean",
         "p95"], rows)  # fmt: skip
    print_table("Mean over seeds (fitted->true mean mm; target <= 5; seeds whose fit_mesh "
                "failed are left out)", ["template", "mode", "mean mm", "seeds"],
                [[t, m, f"{np.mean(v):.2f}", len(v)] for (t, m), v in summary.items()])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small run")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--throughput", action="store_true",
                    help="only table 4 (throughput), on the full run's 900 test frames")
    ap.add_argument("--graph-path", action="store_true",
                    help="only table 5 (the animated mesh vs truth through the graph's path)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[3, 4, 5],
                    help="--graph-path: simulated subjects (held out; 0-2 for tuning)")
    ap.add_argument("--templates", nargs="+", default=["procedural", "makehuman"],
                    choices=["procedural", "makehuman"], help="--graph-path: templates")
    args = ap.parse_args()
    q = args.quick
    if args.graph_path:
        t0 = time.perf_counter()
        graph_path_table(seeds=args.seeds, templates=args.templates, quick=q)
        print(f"\ntotal {time.perf_counter() - t0:.0f} s")
        return
    n_markers = 350
    t0 = time.perf_counter()
    n_test = 240 if q and not args.throughput else 900
    sim = simulate(n_markers=n_markers, body_vertices=3000 if q else 6000,
                   rom_frames=600 if q else 1200, test_frames=n_test, seed=args.seed)  # fmt: skip
    print(f"# Skin deformation benchmark ({'quick' if q else 'full'}, seed {args.seed})")
    print(f"simulated: {n_markers} markers, body {sim['body'].n_vertices} vertices, ROM "
          f"{sim['rom']['true'].shape[0]} frames, test (run) {sim['test']['true'].shape[0]} "
          f"frames at {RATE:g} Hz, noise 0.3 mm; {time.perf_counter() - t0:.0f} s")  # fmt: skip
    rom_obs = sim["rom"]["observed"]
    full_faces = build_marker_surface(rom_obs[0], positions=rom_obs).faces
    mk_test = Markers(sim["test"]["observed"], labels_of(np.arange(n_markers)), RATE)
    if args.throughput:
        seg = segment_markers(rom_obs, np.arange(n_markers), full_faces)[0]
    else:
        seg = segmentation_table(sim, rom_obs, full_faces)
        held_out_table(sim, rom_obs, full_faces, folds=1 if q else 3, seed=args.seed)
        true_mesh_table(sim, seg, mk_test)
    throughput_table(sim, seg, mk_test, frames=n_test)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
