"""Skin deformation of a detailed mesh from dense markers (Park & Hodgins 2006, §5.3).

This module holds the stage :func:`deform` (binding, the per-part fits through
``ctx.map``, the evaluation in process or in frame chunks on workers, the report, the
fallbacks' warnings) and :func:`unflip_triangles`; the blended vertices of all parts
(P&H Eq. 8–9) are :mod:`mocapflow.stages.skin.blend`, the blend widening
:mod:`mocapflow.stages.skin.widening`.

Per frame and per near-rigid part ``p`` (see :mod:`mocapflow.stages.skin.segment`):

1. **rigid**: Horn's absolute orientation of the part's reference marker positions
   ``p̄_i`` (in the part's local frame) onto the observed ``x_i``: ``x ≈ R p̄ + d``
   (:func:`mocapflow.stages.skin.parts.fit_part`);
2. **quadratic** (P&H Eq. 6): the markers brought back into the local frame,
   ``p̂_i = R^T (x_i - d)``, are fitted by a 3×9 quadratic transform
   ``p̂ ≈ A q(p̄)``, ``q = [x y z x² y² z² xy yz zx]``
   (:func:`mocapflow.stages.skin.kernels.quadratic_basis`), by the pseudo-inverse
   (:mod:`mocapflow.stages.skin.parts`);
3. **residual** (P&H Eq. 7): what is left, ``p̂_i - A q(p̄_i)``, is interpolated by
   radial basis functions with a compactly supported cubic B-spline kernel
   whose dilation is twice the part's largest nearest-neighbour marker
   distance (a sparse system solved once per visibility pattern; a thin-plate
   spline is an option, see below; kernels and solves in
   :mod:`mocapflow.stages.skin.kernels`);
4. **vertices** (P&H Eq. 8–9): every vertex ``v̄`` of the detailed mesh is moved by
   the same model of every part it belongs to and the results are blended with
   its weights ``β`` (barycentric interpolation of the markers' ``α`` from the
   nearest marker-surface triangle, sharpened by default, see below;
   :func:`mocapflow.stages.skin.binding.bind_mesh`), all parts and frames as one
   linear map (:mod:`mocapflow.stages.skin.blend`:
   :func:`~mocapflow.stages.skin.blend.vertex_operator`,
   :func:`~mocapflow.stages.skin.blend.deform_positions`).

Modes: ``rigid`` (1 + blend: linear blend skinning with the part transforms),
``quadratic`` (1–2), ``rigid_residual`` (1 + 3), ``quadratic_residual`` (1–3).

Departures from the paper, chosen by measurement (``benchmarks/deform.py``:
markers held out of the whole pipeline and predicted as mesh vertices on a
dynamic trial, and the simulator's true mesh).  The paper's exact method is
``beta_sharpness=1, quadratic_damping=0, residual_kernel="cubic_bspline",
support_margin=None, clamp_margin=None, max_blend_stretch=None``:

* **sharpened weights** ``β ∝ β_bary^4`` (``beta_sharpness``; weights < 10⁻³
  dropped).  What dominated the held-out error was the blend, not the
  per-part models: markers binding to two or more parts had 9.9 mm mean
  error against 4.5 mm for markers inside one part (paper settings), and the
  best single part predicted them better than the blend (6.2 mm).  The segmentation's
  ``α`` are mostly 0/1, and barycentric interpolation over the coarse marker
  triangles (4–7 cm, larger around holes) spreads each part boundary over a
  whole triangle, blending two parts' extrapolations there.  Sharpening
  narrows that zone (a vertex midway between two hard parts stays 50/50):
  held-out error 7.3 → 5.9 mm with everything else at the paper's settings,
  6.5 → 5.1 mm with the thin-plate residual.  4 was chosen over 8 (better on
  seed 0, worse on seeds 1–5 and on the true mesh).  It costs the ``rigid``
  mode (plain skinning wants wide blends: ~1 mm more on the true mesh) and a
  little on a limb whose ``α`` are genuinely soft, so it is a parameter;
* an optional **thin-plate residual** (``residual_kernel="thin_plate"``; the
  default stays the paper's B-spline): ``φ(r) = r² log r``
  (``r`` in units of the part's RMS radius) with a linear polynomial, per part,
  dense.  The compact B-spline interpolates with dips between centres and made
  markers inside a part *worse* than no residual at all (held-out markers sit
  between centres); the thin plate lowered held-out error by a further 9–15 %
  on 6 simulated seeds and the true-mesh error by ~10 %.  Its polynomial is
  folded into ``A`` and ``d`` (so ``rigid_residual`` becomes affine + thin
  plate, which is why it is within a few hundredths of a millimetre of
  ``quadratic_residual`` with this kernel); the polynomial spans only the
  directions the markers extend in, so a flat part or a 3-marker frame does
  not extrapolate off its plane.  Held-out markers, 900-frame run (seed 0):
  quadratic + residual 5.56 mm mean with the B-spline, 5.13 with the thin
  plate; but with the thin plate ``rigid_residual`` ties it (5.14), i.e. the
  quadratic term no longer matters, while with the B-spline it is 0.10 mm
  better than ``rigid_residual`` (5.66) and both beat the global thin-plate
  RBF (6.06).  The default keeps the paper's kernel and its sparse solve;
* ``quadratic_damping`` (default 0.3; 0 = the paper's pseudo-inverse) adds a
  ridge toward the rigid transform on the 9 quadratic coefficients: parts
  with 10–15 markers otherwise extrapolate their quadratic by centimetres
  (held-out error 5.5 → 5.1 mm, true-mesh error 5.2 → 3.4 mm on 300 frames);
  0.03–1 measure the same within 0.1 mm;
* **no extrapolation artifacts** (``support_margin`` 0.5, ``clamp_margin`` 0.1;
  ``None, None`` = the paper): the quadratic monomials of a vertex outside the
  bounding box of its part's markers (part frame, grown by ``support_margin`` ×
  the largest nearest-neighbour marker distance) are those of the nearest point
  of the box, so the quadratic's displacement is held at its edge instead of
  growing where no marker constrains it; and each vertex's non-rigid
  displacement per part (quadratic + residual minus the rigid fit) is softly
  clamped at the largest deviation of the part's visible markers from their
  rigid prediction in that frame (unchanged up to it, at most
  ``1 + clamp_margin`` times it, continuous slope;
  :func:`~mocapflow.stages.skin.parts.soft_clamp`).  Markers and every vertex
  inside the box and within the bound move exactly as in the paper.  The
  demo's quadratic panels showed a flat fin at the left arm: a forearm part
  that also held a shoulder marker fitted the elbow's bend with its quadratic
  and threw the unmarked hand 26 cm off its rigid prediction, 69 mm farther
  than any of the part's markers (192 mm); with the rule: 98 mm, never beyond
  the markers (``tests/stages/skin/test_artifacts.py``).  Held-out error
  (``benchmarks/deform.py --quick``) is unchanged within a few hundredths of a
  millimetre.
* **blends widened where they tear** (``max_blend_stretch`` 2.5; ``None`` = the
  paper), ``blend_widening_reach`` 0.45 m: where two parts' models disagree and a
  sharpened ``β`` moves from one to the other within a mesh edge or two, the ``β``
  of the torn triangles' corners and their neighbours are diffused over the mesh
  until no blending triangle stretches an edge beyond ``max_blend_stretch``, and
  kept as bound where that does not leave fewer torn triangles.  Why, what it
  measured (the demo, the shared captures, the simulator's true mesh) and what it
  costs: :mod:`mocapflow.stages.skin.widening`, which implements it
  (:func:`~mocapflow.stages.skin.widening._widen_blends`);
* ``unflip`` (off in the stage, on in the skin graph's config): the vertices of
  triangles that turn over against the rigid mode are pulled towards their rigid
  positions, the pull eased over 4 rings of the mesh (:func:`unflip_triangles`).
  On the demo's body (5,001 vertices, 120 frames, ``quadratic_residual``) 344
  triangles flipped at some frame -> 0, none stretched beyond 3x before or after,
  the vertices moved 4.7 mm on average where moved (at most 100 mm, 87 frames
  touched); the stage costs 3.3x as much there (0.67 -> 2.19 CPU-s: the rigid
  mode's own pass, then the pulls).  Against the simulator's true surface the
  rigid mode itself faces the wrong way on 806 triangles of that body (the
  xfail this replaced), so this is about what a viewer sees, not accuracy;

Implementation notes (none changes the method):

* the quadratic monomials are centred on their weighted mean over the part's
  markers and scaled by the part's RMS radius; this is a change of basis of the
  paper's 3×9 ``A`` that makes Horn's translation absorb the constant, so a known
  quadratic deformation is recovered exactly;
* ``A`` is solved as a deviation from the identity (``p̂ - p̄ ≈ ΔA q``) so that
  directions the markers do not constrain (a flat part's normal) stay rigid
  instead of collapsing to the minimum-norm zero of a plain pseudo-inverse;
* the B-spline kernel is ``φ(r) = 1.5·B₃(2r/σ)``: it vanishes for ``r ≥ σ``, the
  dilation.  (With support ``2σ`` the kernel matrices of body-like marker
  layouts are indefinite; with support ``σ`` they are positive definite with
  condition numbers ~20–50.)  When one isolated marker makes the paper's
  ``σ = 2 × max nearest-neighbour distance`` so wide that the system is
  indefinite or ill-conditioned (condition > 100), ``σ`` is reduced in 15 %
  steps until it is not, with a warning naming the part: otherwise the
  residual oscillates by centimetres between markers (B-spline kernel only);
* the evaluation of all parts and frames as one linear map, and why it is
  bit-reproducible: :mod:`mocapflow.stages.skin.blend`.

Fallbacks, each with a warning naming the part: a part with fewer than
``min_quadratic_markers`` markers (quadratic under-determined) uses the rigid
transform (+ residual in residual modes); a frame in which a part has fewer than
3 visible markers (or a degenerate set) gets the part's model interpolated in
time from the nearest frames where it could be fitted (held at the ends); a
frame with 3 to ``min_quadratic_markers - 1`` visible markers keeps its own
rigid fit and residual but interpolates the quadratic terms.  A part never
fitted in any frame, and a mesh that does not overlap the marker surface, are
errors naming the problem.
"""

from __future__ import annotations

from dataclasses import replace
from functools import partial
from typing import Any

import numpy as np

from mocapflow.pipeline import Context, stage
from mocapflow.stages.motion.datatypes import Markers, Mesh
from mocapflow.stages.motion.geometry import triangle_normals
from mocapflow.stages.skin.binding import DeformError, bind_mesh, mesh_edges
from mocapflow.stages.skin.blend import (
    Threads,
    VertexOperator,
    _frame_major,
    deform_positions,
    frame_coefficients,
    vertex_operator,
)
from mocapflow.stages.skin.limb_pose import limb_binding
from mocapflow.stages.skin.parts import (
    Mode,
    PartFit,
    PartModel,
    ResidualKernel,
    evaluate_part,
    fit_part,
    prepare_part,
)
from mocapflow.stages.skin.segmentation import Segmentation
from mocapflow.stages.skin.widening import (
    _blending_edges,
    _first_pass_gap,
    _longest_edges,
    _mesh_topology,
    _widen_blends,
    widening_steps,
)

__all__ = [
    "align_markers",
    "deform",
    "unflip_triangles",
]


def _slice_fit(fit: PartFit, sl: slice) -> PartFit:
    return PartFit(
        fit.R[sl], fit.d[sl], fit.A[sl], fit.W[sl], fit.rigid_frames[sl],
        fit.quadratic_frames[sl], [],
        None if fit.rigid_d is None else fit.rigid_d[sl],
        None if fit.marker_deviation is None else fit.marker_deviation[sl],
    )  # fmt: skip


def _deform_chunk(item: tuple) -> np.ndarray:
    models, fits, n_vertices, operator, residual = item
    return deform_positions(models, fits, n_vertices, operator, residual=residual)


def _without_vertices(m: PartModel) -> PartModel:
    """A copy of the model without its per-vertex arrays (cheap to ship to workers)."""
    return PartModel(
        name=m.name, members=m.members, alpha=m.alpha, local=m.local, origin=m.origin,
        axes=m.axes, scale=m.scale, q_mean=m.q_mean, sigma=m.sigma, kernel=m.kernel,
        quadratic=m.quadratic, residual_kernel=m.residual_kernel,
        support=m.support, clamp_margin=m.clamp_margin,
    )  # fmt: skip


def _fit_part_item(item: tuple[PartModel, np.ndarray], *, mode: str, min_quadratic_markers: int,
                   damping: float):  # fmt: skip
    model, x = item
    return fit_part(model, x, mode=mode, min_quadratic_markers=min_quadratic_markers,
                    damping=damping)  # fmt: skip


def align_markers(markers: Markers, segmentation: Segmentation) -> np.ndarray:
    """Positions ``(F, M, 3)`` of ``markers`` in the segmentation's marker order.

    Raises
    ------
    DeformError
        Naming the markers of the segmentation missing from the capture.
    """
    index = {m: i for i, m in enumerate(markers.labels)}
    missing = [m for m in segmentation.labels if m not in index]
    if missing:
        raise DeformError(
            f"capture lacks {len(missing)} markers of the segmentation: {missing[:10]}"
        )
    return markers.positions[:, [index[m] for m in segmentation.labels]]


def _fit_parts(models: list[PartModel], x: np.ndarray, *, mode: str,
               min_quadratic_markers: int, damping: float, ctx: Context,
               threads: Threads | None = None) -> list[PartFit]:  # fmt: skip
    """Every part's fit over all frames (:func:`~mocapflow.stages.skin.parts.fit_part`),
    one task per part through ``ctx.map`` (on ``threads`` when the context has no
    executor); the models' and fits' messages are warned."""
    fit = partial(_fit_part_item, mode=mode, min_quadratic_markers=min_quadratic_markers,
                  damping=damping)  # fmt: skip
    items = [(_without_vertices(m), x[:, m.members]) for m in models]
    if ctx.mapper is None and threads is not None and threads.n > 1:
        fits = threads.run(lambda item, _: fit(item), items)
    else:
        fits = ctx.map(fit, items)
    for m, f in zip(models, fits):
        notes = m.messages if mode.endswith("residual") else []  # the kernel's notes
        for msg in notes + f.messages:
            ctx.warn(msg, hint=_fallback_hint(msg))
    return fits


def _fallback_hint(message: str) -> str | None:
    """What to do about a part model's or fit's fallback message (``None``: no advice)."""
    if "under-determined" in message or "using rigid for this part" in message:
        return ("harmless where the part moves rigidly; for a part that bends, give it more "
                "markers (segment.override) or lower deform.min_quadratic_markers")
    if "interpolated" in message:
        return ("the part's markers are hidden in those frames; if the mesh looks wrong "
                "there, check clean's report (markers_with_holes_left) and its fill")
    return None


def _deform_frames(models: list[PartModel], fits: list[PartFit], n_frames: int,
                   operator: VertexOperator, *, residual: bool, chunk_frames: int,
                   ctx: Context, edges: np.ndarray | None = None,
                   coefficients: np.ndarray | None = None, threads: Threads | None = None,
                   ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The blended vertices ``(F, V, 3)`` of ``operator``
    (:func:`~mocapflow.stages.skin.blend.vertex_operator` of the rest vertices and their
    weights; P&H Eq. 8–9): in one in-process pass, or in frame chunks of ``chunk_frames``
    on the executor's workers (the same bits either way); and the largest squared length
    over the frames of ``edges (E, 2)`` (:func:`~mocapflow.stages.skin.widening._longest_edges`;
    empty without).  ``coefficients``: the models'
    :func:`~mocapflow.stages.skin.blend.frame_coefficients` when already computed
    (in-process pass)."""
    F, V = n_frames, operator.n_vertices
    edges = np.zeros((0, 2), np.int64) if edges is None else edges
    bounds = list(range(0, F, max(1, chunk_frames))) + [F]
    if ctx.mapper is None or len(bounds) <= 2:  # in-process: one pass, no copies
        return _frame_major(models, fits, V, operator, residual=residual, edges=edges,
                            coefficients=coefficients, threads=threads)  # fmt: skip
    light = [_without_vertices(m) for m in models]
    operator = replace(operator, unit=None)  # the rows with β = 1 stay here
    chunks = [
        (light, [_slice_fit(f, slice(a, b)) for f in fits], V, operator, residual)
        for a, b in zip(bounds, bounds[1:])
    ]
    verts = np.empty((F, V, 3))
    for (a, b), part in zip(zip(bounds, bounds[1:]), ctx.map(_deform_chunk, chunks)):
        verts[a:b] = part
    return verts, _longest_edges(verts, edges)


def _deform_report(models: list[PartModel], fits: list[PartFit], x: np.ndarray,
                   n_vertices: int, *, mode: str) -> dict[str, Any]:
    """The deform report: per part its markers, vertices, fallback frames, dilation and
    how well the model reproduces the observed markers (RMS mm; 0 up to round-off with
    the residual); ``max_vertex_distance_to_markers_mm`` left None for the binding."""
    marker_rms = {}
    for m, f in zip(models, fits):
        pred = evaluate_part(m, f, m.local, m.basis(m.local), m.kernel.tocsr())
        err = np.linalg.norm(pred - x[:, m.members], axis=-1)
        ok = np.isfinite(err)
        marker_rms[m.name] = float(np.sqrt(np.mean(err[ok] ** 2)) * 1000) if ok.any() else None
    return {
        "mode": mode,
        "frames": x.shape[0],
        "vertices": n_vertices,
        "parts": {
            m.name: {
                "markers": int(len(m.members)),
                "vertices": int(len(m.vertices)),
                "quadratic": bool(m.quadratic and mode.startswith("quadratic")),
                "interpolated_frames": int((~f.rigid_frames).sum()),
                "rigid_only_frames": int((f.rigid_frames & ~f.quadratic_frames).sum())
                if mode.startswith("quadratic") and m.quadratic
                else 0,
                "marker_rms_mm": marker_rms[m.name],
                "dilation_mm": m.sigma * 1000 if m.residual_kernel == "cubic_bspline" else None,
            }
            for m, f in zip(models, fits)
        },
        "max_vertex_distance_to_markers_mm": None,
    }


#: :func:`unflip_triangles`: rings a pull spreads over, its decay per ring, and the
#: rounds (the last three move the vertices of a still-flipped triangle all the way).
UNFLIP_RINGS = 4


UNFLIP_DECAY = 0.7


UNFLIP_ROUNDS = 12


def unflip_triangles(vertices: np.ndarray, reference: np.ndarray, faces: np.ndarray, *,
                     rings: int = UNFLIP_RINGS, decay: float = UNFLIP_DECAY,
                     rounds: int = UNFLIP_ROUNDS) -> tuple[np.ndarray, dict[str, int]]:  # fmt: skip
    """Pull the vertices of triangles turned over against ``reference`` towards it.

    In every frame where a triangle's normal opposes the reference's (the rest pose
    moved by the rigid mode), the vertices of the flipped triangles move towards their
    reference positions: a round halves what is left of their pull (the last three
    rounds pull them all the way), and the pull spreads over ``rings`` rings of the mesh
    with ``decay`` per ring (taking the largest), so the region eases back instead of
    creasing; rounds repeat until no triangle of the frame is flipped.  Frames with no
    flipped triangle are untouched (beyond the paper: issue 15 item 4).

    Parameters
    ----------
    vertices, reference : (F, V, 3) float ndarray
        The deformed mesh and the reference (rigid mode) one.
    faces : (T, 3) int ndarray
    rings, decay, rounds : see :data:`UNFLIP_RINGS`, :data:`UNFLIP_DECAY`,
        :data:`UNFLIP_ROUNDS`.

    Returns
    -------
    vertices : (F, V, 3) float ndarray
        A copy, pulled where needed.
    report : dict
        ``flipped_before`` / ``flipped_after`` (triangles flipped in some frame),
        ``frames`` (frames changed), ``vertex_frames`` (vertex-frames moved).
    """
    if vertices.shape != reference.shape:
        raise ValueError(f"unflip_triangles: {vertices.shape} vs reference {reference.shape}")
    if rings < 0 or not 0.0 <= decay < 1.0 or rounds < 1:
        raise ValueError(f"unflip_triangles: need rings >= 0, 0 <= decay < 1, rounds >= 1, "
                         f"got {rings}, {decay}, {rounds}")
    out = np.array(vertices, dtype=np.float64, copy=True)
    F, V, _ = out.shape
    faces = np.asarray(faces)
    # each vertex's ring neighbours, padded with itself: (V, largest degree)
    edges = mesh_edges(faces, V)[0]
    head = np.concatenate([edges[:, 0], edges[:, 1], np.arange(V)])
    tail = np.concatenate([edges[:, 1], edges[:, 0], np.arange(V)])
    order = np.argsort(head, kind="stable")
    head, tail = head[order], tail[order]
    slot = np.arange(len(head)) - np.searchsorted(head, head)
    ring = np.repeat(np.arange(V)[:, None], slot.max(initial=0) + 1, axis=1)
    ring[head, slot] = tail
    before = np.zeros(len(faces), bool)
    after = np.zeros(len(faces), bool)
    n_frames = n_moved = 0
    for a in range(0, F, 32):
        ref = reference[a : a + 32]
        n_ref = triangle_normals(ref, faces)
        flipped = np.einsum("ftk,ftk->ft", triangle_normals(out[a : a + 32], faces), n_ref) < 0
        rows = np.flatnonzero(flipped.any(1))
        if not len(rows):
            continue
        before |= flipped.any(0)
        start, pull_to, n_ref = out[a + rows], ref[rows], n_ref[rows]
        core = np.zeros((len(rows), V))
        pull = core
        moved = start
        left = flipped[rows]
        for k in range(rounds):
            fr, tr = np.nonzero(left)
            mark = np.zeros(core.shape, bool)
            mark[fr[:, None], faces[tr]] = True
            core[mark] = 1.0 if k >= rounds - 3 else 1.0 - 0.5 * (1.0 - core[mark])
            pull = core  # spread ring by ring, the largest pull kept
            for _ in range(rings):
                pull = np.maximum(pull, decay * pull[:, ring].max(-1))
            moved = start - pull[..., None] * (start - pull_to)
            left = np.einsum("ftk,ftk->ft", triangle_normals(moved, faces), n_ref) < 0
            if not left.any():
                break
        after |= left.any(0)
        out[a + rows] = moved
        n_frames += len(rows)
        n_moved += int((pull > 0).sum())
    return out, {"flipped_before": int(before.sum()), "flipped_after": int(after.sum()),
                 "frames": n_frames, "vertex_frames": n_moved}


@stage("deform", outputs=("mesh", "report"))
def deform(
    markers: Markers,
    segmentation: Segmentation,
    mesh: Mesh,
    *,
    mode: Mode = "quadratic_residual",
    min_quadratic_markers: int = 10,
    quadratic_damping: float = 0.3,
    dilation_factor: float = 2.0,
    beta_sharpness: float = 4.0,
    residual_kernel: ResidualKernel = "cubic_bspline",
    chunk_frames: int = 1024,
    support_margin: float | None = 0.5,
    clamp_margin: float | None = 0.1,
    max_blend_stretch: float | None = 2.5,
    blend_widening_reach: float = 0.45,
    unflip: bool = False,
    threads: int | None = None,
    ctx: Context,
) -> dict[str, Any]:
    """Animate a detailed mesh from markers: rigid + quadratic + RBF residual per part.

    Parameters
    ----------
    markers : Markers
        Cleaned capture ``(F, M, 3)``; must contain every segmented marker.
    segmentation : Segmentation
        Near-rigid parts with soft weights (stage ``segment``).
    mesh : Mesh
        Detailed mesh in the reference pose, overlapping the marker surface
        (stage ``fit_mesh``); ``vertices (V, 3)``.
    mode : {"rigid", "quadratic", "rigid_residual", "quadratic_residual"}
        Model per part (Figure 7 of the paper compares the four).
    min_quadratic_markers : int
        Parts (or frames) with fewer markers use the rigid transform (paper: 10).
    quadratic_damping : float
        Ridge toward rigid on the quadratic coefficients (0 = P&H Eq. 6);
        helps parts with few markers, whose quadratic extrapolates wildly.
    dilation_factor : float
        B-spline support = this × the part's largest nearest-neighbour distance.
    beta_sharpness : float
        ``β ∝ β_bary^γ`` (1 = the paper's barycentric weights); narrows the
        blend between parts, see the module docstring.
    residual_kernel : {"cubic_bspline", "thin_plate"}
        Kernel of the residual (``"cubic_bspline"`` = P&H Eq. 7, the
        default; ``"thin_plate"``: see the module docstring).
    chunk_frames : int
        Frames per parallel evaluation task (``ctx.map``); a capture of at most
        this many frames is evaluated in one in-process pass.  Shipping the
        vertices back from worker processes costs more than the evaluation
        on a 2-core machine (see ``benchmarks/deform.py``), so the default only
        splits long captures.  The per-part fits always go through ``ctx.map``.
    support_margin : float or None
        The quadratic is evaluated as fitted inside the bounding box of the
        part's markers (rest pose, the part's frame) grown by this × the part's
        largest nearest-neighbour marker distance, and continued to first order
        (tangentially) beyond it; ``None``: the quadratic everywhere (the paper).
        See the module docstring (departures).
    clamp_margin : float or None
        A vertex's non-rigid displacement (quadratic + residual minus rigid, per
        part) is softly clamped at the largest distance of the part's markers
        from their rigid prediction in that frame: unchanged up to it, never more
        than ``1 + clamp_margin`` times it; ``None``: no clamp (the paper).
    max_blend_stretch : float or None
        Where the blend between parts stretches a mesh edge beyond this factor of
        its rest length in some frame, the weights ``β`` there are diffused over the
        mesh (widening the blend) until it does not, or the blend reached
        ``blend_widening_reach`` (see :mod:`mocapflow.stages.skin.widening`); ``None``:
        ``β`` as bound (the paper).  The default 2.5 removes the demo's torn triangles (40 -> 0 in
        ``quadratic_residual``).
    blend_widening_reach : float
        How far over the surface (metres) the widening may spread a blend: it takes
        at most ``ceil((reach / e)**2)`` diffusion steps, ``e`` the mean rest edge
        length (a step spreads a blend about one edge, so a mesh twice as fine needs
        4x the steps for the same width): 110 steps on a 2,000-vertex body (43 mm
        edges), 367 on 5,000 (23 mm), 986 on 13,000 (14 mm).
    unflip : bool
        In the non-rigid modes, pull the vertices of triangles turned over against the
        rigid mode (the same call with ``mode="rigid"``) towards it
        (:func:`unflip_triangles`; ``report["unflip"]``).  It deforms the mesh a second
        time, rigidly, and pulls (the demo's body: 3.3x the cost).  Off by default; the
        skin graph's config turns it on (the demo: 344 flipped triangles -> 0).
    threads : int or None
        Threads of this process evaluating the frames (chunks of frames shared by the
        threads) and widening the blends (each thread its own range of frames), the
        binding and then the report running on a second one beside the per-part fits (the
        fits on all of them without a second thread or an executor);
        ``None``: ``ctx.workers`` (the engine's worker
        count; 1 for a plain Python call).  The result is the same bits on any number
        (every vertex, frame and part is computed apart from the others: see
        :mod:`mocapflow.stages.skin.blend`).

    Returns
    -------
    dict
        ``mesh``: animated :class:`Mesh` ``(F, V, 3)`` at the capture's rate
        (``attrs``: ``vertex_part``, ``V`` ints indexing ``part_names``);
        ``report``: per-part markers, mode used, fallback frames, and the RMS
        distance (mm) between the observed markers and the model's prediction.
        A segmentation below Park & Hodgins' density (``attrs["density"]["suited"]``
        false, :mod:`~mocapflow.stages.skin.density`) is skinned rigidly whatever
        ``mode`` says, every vertex bound to its nearest marker triangle (no
        overlap error).
    """
    if mesh.animated:
        raise DeformError("deform: the detailed mesh must be a single rest pose (V, 3)")
    if max_blend_stretch is not None and not max_blend_stretch > 1.0:
        raise DeformError(
            f"deform: max_blend_stretch must be > 1 (or null), got {max_blend_stretch}")
    if not blend_widening_reach >= 0:
        raise DeformError(
            f"deform: blend_widening_reach must be >= 0 (metres), got {blend_widening_reach}")
    n_threads = ctx.workers if threads is None else threads
    if not n_threads >= 1:
        raise DeformError(f"deform: threads must be >= 1 (or null), got {threads}")
    x = align_markers(markers, segmentation)
    sparse = (segmentation.attrs.get("density") or {}).get("suited") is False
    if sparse:  # below Park & Hodgins' density (segment warned once): rigid skinning
        mode = "rigid"
    # frame-independent set-up in-process (cheap; per-vertex arrays stay here), the
    # per-part fits over all frames on the executor (small inputs and outputs)
    models = [
        prepare_part(segmentation, p, min_quadratic_markers=min_quadratic_markers,
                     dilation_factor=dilation_factor, residual_kernel=residual_kernel,
                     support_margin=support_margin, clamp_margin=clamp_margin)
        for p in range(segmentation.n_parts)
    ]  # fmt: skip
    V = mesh.vertices.shape[0]
    widen = max_blend_stretch is not None and len(mesh.faces) > 0
    residual = mode.endswith("residual")

    def mesh_setup() -> tuple:
        """The mesh's binding, the edges of its triangles that blend (measured while the
        frames are evaluated), the vertex operator and, to widen the blends, the mesh's
        topology: NumPy over the rest vertices."""
        allowed = None  # a limb's skin held to its limb's and the body's parts
        if {"joint_names", "vertex_part"} <= set(mesh.attrs):
            allowed = limb_binding(segmentation.labels, segmentation.reference,
                                   segmentation.weights, mesh.vertices,
                                   list(mesh.attrs["joint_names"]),
                                   np.asarray(mesh.attrs["vertex_part"]))  # fmt: skip
        binding = bind_mesh(mesh.vertices, segmentation, sharpness=beta_sharpness,
                            name="detailed mesh", min_overlap=0.0 if sparse else 0.9,
                            allowed=allowed)
        topology = _mesh_topology(mesh) if widen else None
        watch, ends = _blending_edges(mesh, binding.beta, topology) if widen else (None, None)
        operator = vertex_operator(models, V, residual=residual, rest=mesh.vertices,
                                   beta=binding.beta)  # fmt: skip
        return binding, watch, ends, operator, topology

    with Threads(n_threads) as pool:  # the evaluation's threads (the same bits on any number)
        # with a second thread the binding runs there while this one fits the parts (mostly
        # Python): neither needs the other; on one thread it runs before the fits, as ever
        pending = pool.submit(mesh_setup)
        try:
            fits = _fit_parts(models, x, mode=mode, min_quadratic_markers=min_quadratic_markers,
                              damping=quadratic_damping, ctx=ctx,
                              threads=pool if pool.pool is None else None)
            # with a second thread the report is made there after the binding, while this
            # one starts the evaluation pass (whose chunks of frames it joins when done)
            reporting = pool.submit(_deform_report, models, fits, x, V, mode=mode)
            # computed once for both passes when the blend widens; else the evaluation pass
            # computes them where it runs (in process, or per chunk on the workers)
            C = frame_coefficients(models, fits, residual=residual) if widen else None
        except Exception:
            pending.result()  # the binding's error first, as on one thread
            raise
        binding, watch, ends, operator, topology = pending.result()
        # and there, after the report, the widening's bound of how far the evaluation
        # pass's positions can lie from its own (needs the operator and the coefficients)
        gapping = pool.submit(_first_pass_gap, operator, C) if widen and \
            operator.unit is not None else None  # fmt: skip
        verts, longest = _deform_frames(
            models, fits, x.shape[0], operator, residual=residual,
            chunk_frames=chunk_frames, ctx=ctx, edges=ends, coefficients=C, threads=pool)
        report = reporting.result()
        report["max_vertex_distance_to_markers_mm"] = float(binding.distance.max() * 1000)
        beta, widened = binding.beta, {"steps": 0, "vertices": 0}
        if widen:
            beta, n_steps, n_changed, torn0, torn1 = _widen_blends(
                models, fits, mesh, binding.beta, verts, max_stretch=max_blend_stretch,
                steps=widening_steps(mesh, blend_widening_reach), residual=residual,
                measured=(watch, longest), coefficients=C, operator=operator,
                threads=pool, topology=topology,
                gap=None if gapping is None else gapping.result())
            widened = {"steps": n_steps, "vertices": n_changed, "torn_before": torn0,
                       "torn_after": torn1 if n_changed else torn0}
            if torn0 and not n_changed:
                ctx.warn(f"deform: widening the blends did not tear fewer triangles ({torn0} "
                         f"-> {torn1} beyond {max_blend_stretch:g}x), so the paper's blend is kept")
    if unflip and mode != "rigid" and len(mesh.faces):
        reference = deform(markers, segmentation, mesh, mode="rigid",
                           min_quadratic_markers=min_quadratic_markers,
                           quadratic_damping=quadratic_damping, dilation_factor=dilation_factor,
                           beta_sharpness=beta_sharpness, residual_kernel=residual_kernel,
                           chunk_frames=chunk_frames, support_margin=support_margin,
                           clamp_margin=clamp_margin, max_blend_stretch=max_blend_stretch,
                           blend_widening_reach=blend_widening_reach, threads=n_threads,
                           ctx=Context(part=ctx.part, mapper=ctx.mapper, workers=ctx.workers))
        verts, report["unflip"] = unflip_triangles(verts, reference["mesh"].vertices, mesh.faces)
    for p, part in enumerate(report["parts"].values()):
        part["vertices"] = int(np.count_nonzero(beta[:, p]))
    report["blend_widening"] = widened
    report["density"] = segmentation.attrs.get("density")
    rms = [p["marker_rms_mm"] for p in report["parts"].values() if p["marker_rms_mm"] is not None]
    ctx.figure("parts", len(report["parts"]))
    if rms:
        ctx.figure("marker RMS mm", round(float(np.mean(rms)), 3))
    ctx.figure("rigid-only frames", sum(p["rigid_only_frames"] for p in report["parts"].values()))
    out = Mesh(
        vertices=verts,
        faces=mesh.faces,
        rate=markers.rate,
        attrs={"mode": mode, "source": "deform", **{k: v for k, v in mesh.attrs.items()
                                                    if isinstance(v, (str, int, float))},
               # dominant part of each vertex (largest β), a V-int list the exporters
               # write as vertex data; the (V, P) float β goes as point data below
               "vertex_part": np.argmax(beta, axis=1).tolist(),
               "part_names": list(segmentation.part_names)},
        # the vertex weights β (V, P) of §5.3, columns in part_names order
        point_data={"part_weights": beta.astype(np.float32)},
    )
    return {"mesh": out, "report": report}
