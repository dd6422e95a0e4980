"""Skin deformation of a detailed mesh from dense markers (Park & Hodgins 2006, §5.3).

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
   linear map (:func:`vertex_operator`, :func:`deform_positions`, this module).

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
  paper), ``blend_widening_reach`` 0.45 m: two parts' models
  disagree at a vertex between them (a part's rigid transform is a compromise
  away from its markers; on the demo's segmentation the rigid predictions of
  neighbouring parts differ by 48 mm at the median blend vertex and by up to
  23 cm at the right shoulder, where one part holds the whole arm), and a
  sharpened ``β`` moves from one to the other within a mesh edge or two: the
  demo's quick body (5,001 vertices, 120 frames) had 238 triangles with an
  edge stretched more than 3× in ``rigid`` mode and 40 in
  ``quadratic_residual``, every one where parts blend.  After the per-part
  fits, every triangle whose corners blend differently is checked in every
  frame; while one stretches an edge beyond ``max_blend_stretch``, the ``β``
  of its corners and of their neighbours take a diffusion step over the mesh
  (half their own, half their neighbours' in proportion to ``1 / edge
  length``, so slivers' short edges are pulled together;
  :func:`~mocapflow.stages.skin.binding.blend_smoothing_operator`; more steps
  and rings at once while the torn triangles do not get fewer) and those
  vertices are moved again with every part they now follow
  (:func:`_widen_blends`).  Only the blends that tear are widened; elsewhere
  the sharpened ``β`` stay.  Where widening does not leave fewer torn triangles
  than it found, the paper's ``β`` are kept (a one-line warning): rigid
  skinning of the sparse real captures, whose parts disagree by decimetres,
  tore more after it (graph to ``deform`` on the shared C3Ds, triangles stretched
  beyond 3×, widening against the paper: Qualisys 543 / 661, racing 530 / 1,138,
  pyomeca 2,560 / 854 before this rule, 854 / 854 with it).  On the demo:
  ``quadratic_residual`` reweights 630 of 5,001 vertices in 87 steps and no
  edge stretches beyond 2.50×;
  ``rigid`` 888 vertices in 31 steps (2.49×).  The widening's reach is a distance
  over the surface (``blend_widening_reach``), not a step count: a step spreads a
  blend about one edge, so the steps needed grow with the square of the mesh's
  resolution (two parts sliding 15 cm apart: 7, 23, 55, 95 steps on 22, 11, 7.3,
  5.5 mm edges).  With the former fixed 100 steps the graph's default 13,000-vertex
  body on the shared captures stopped with triangles still stretched beyond 3×
  (Qualisys 39, racing 503, pyomeca 314; 0 at 2,000 vertices); with a 0.45 m reach
  (963 / 894 / 1,227 steps): 6 / 0 / 0, the 2,000-vertex runs unchanged (a 0.6 m
  reach: 4 / 0 / 0).  The last ones were slivers of the decimated template (rest
  edges of 4-7 mm beside 12-98 mm ones, at the hips); with the template's triangles
  evened out (``template_mesh(relax=5)``) 0 / 0 / 0, in 216 / 303 / 207 steps, and
  none left torn beyond ``max_blend_stretch`` (592 / 1,281 / 637 found).  On the
  simulator's true mesh (table 3, quick; seeds 0 / 1) no triangle stretches beyond 3× (before:
  47 / 46 in quadratic + residual, 153 / 168 in rigid); the mean vertex error
  drops in rigid (7.10 → 6.70 / 7.11 → 6.85 mm) and quadratic (5.38 → 5.16 /
  5.48 → 5.34) and changes by −0.02 / +0.07 mm in quadratic + residual
  (3.68 → 3.66 / 3.65 → 3.72).  Cost: on the throughput body of
  ``benchmarks/deform.py --throughput`` (13,000 vertices, 900 frames)
  ``quadratic_residual`` reweights 2,619 vertices in 60 steps and runs at about
  670 frames per CPU-second against about 1,100 without widening in the same
  (loaded) run, ``rigid`` (2,709 vertices, 92 steps) at about 820 against 2,900
  (table 4 has both rows; before the widening took the operator's rows with
  ``β = 1`` instead of building them again, the frame coefficients were made one
  C-contiguous array and the operator's rows ordered by one stable sort, issue 15:
  about 5 % more CPU time in paired runs, the row without widening unchanged;
  before the frame coefficients were shared by the two
  passes, the widening's predictions written straight into their store, its final
  positions straight into the output and the clamp tested only near its bound,
  issue 15: 620 and 670 in the same session, the rows without widening unchanged;
  before the products were made one CSR kernel call per chunk and the widening's
  predictions and positions sparse products over its stores: 430 / 920 and
  560 / 2,500 in the same runs; before the edges' length bounds, the positions
  computed only where measured and the first check made during the evaluation
  pass: 350 and 270; before the checks were made incremental: 200).  What is left
  is mostly the evaluation pass's one sparse product per chunk (about 0.25 CPU-s
  of the 1.3 here, the rows' terms added in order for the bit-reproducibility
  below; per part the rows would be dense blocks of 1,058,699 entries against
  438,209 terms, mostly kernel values that are zero, and a fixed-order NumPy sum
  over them costs 11x the CSR kernel, BLAS 0.8x without the bit-reproducibility),
  its clamp test and the transposition into the output (about 0.1 each), the
  widening's predictions over all frames (about 0.2) and its measurements (about
  0.15), and the set-up (binding, part fits, operator, report: about 0.3).
  Held-out markers (``benchmarks/deform.py`` table 2) are points without
  triangles, so they are not affected; table 3 (the simulator's true mesh)
  measures it.  Not fixed by this: triangles that turn over against the rigid
  mode (see ``tests/stages/skin/test_artifacts.py``);
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
* all parts and frames are evaluated as one linear map
  ``vertices(f) = H · C(f)`` (``H``: β-weighted local coordinates, monomials
  and kernel values of the vertex-part pairs, built once; ``C``: per-frame part
  coefficients), done as one sparse product per chunk of frames (the non-rigid
  rows, clamped, stacked above the rigid ones; 16 frames of a 13,000-vertex mesh:
  the work arrays stay a few MB, and the chunking changes no bit) by scipy's CSR
  kernel called directly into reused work arrays (``A @ X`` would allocate and
  copy its result and pay scipy's checks on every call); ``β`` is folded into ``H``
  because the clamp commutes with a positive scale, and only the few entries
  beyond their bound are clamped.  ``H``'s rows are built from arrays (no sparse
  stacking), the blending edges' lengths are taken during that pass by one more
  sparse product (end minus start), and the widening's predictions, positions
  and edge vectors are sparse products over its stores of rows (all frames at
  once; :meth:`_Rows.combine`), each adding its terms in the order the plain sums
  did: the same bits as before (issue 15).  The frame coefficients are computed once
  for both passes, as one C-contiguous array (their ``(K, 3F)`` rows a view), and the
  clamp's test ``|u|² / β² > bound²`` is made only on the
  entries whose ``|u|²`` comes within 10⁻⁹ of ``β² bound²`` (the same entries).  The
  operator keeps its rows with ``β = 1`` (:attr:`VertexOperator.unit`; its own rows are
  them times ``β``, the same products as before): the widening takes the rows of the
  pairs it predicts from them where the operator holds the pair, and builds only the
  pairs the diffused ``β`` adds (on the throughput body 1,332 of 4,967);
* **bit-reproducible**: every vertex's result is computed by operations whose
  rounding does not depend on which other vertices, frames or parts are computed
  in the same call, nor on BLAS or its thread count: ``H``'s rows come from their
  own vertex alone (local coordinates as products summed in a fixed order, not a
  BLAS product), a sparse row times the coefficients adds its terms in column
  order one row at a time (scipy's CSR kernel), ``C`` is built by products summed
  in a fixed order, and each vertex's parts are summed in a fixed order.  A BLAS
  product does not have this property: the same row of ``H @ C`` rounds
  differently (last bit) depending on how many rows are multiplied with it, which
  made the widened vertices (evaluated apart from the rest) differ by 1.7e-18 m
  between the demo's run and its frozen replay.  Worker frame chunks,
  ``max_blend_stretch`` re-evaluations, vertex subsets and thread counts give the
  same bytes (``tests/stages/skin/test_deform.py``); results equal the former
  dense BLAS evaluation within 1e-15 m.

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

from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
import scipy.sparse as sp

from mocapflow.pipeline import Context, stage
from mocapflow.stages.motion.datatypes import Markers, Mesh
from mocapflow.stages.motion.geometry import triangle_normals
from mocapflow.stages.skin.binding import (
    DeformError,
    MeshBinding,
    bind_mesh,
    blend_smoothing_operator,
    mesh_edges,
)
from mocapflow.stages.skin.parts import (
    Mode,
    PartFit,
    PartModel,
    ResidualKernel,
    evaluate_part,
    fit_part,
    prepare_part,
    soft_clamp,
)
from mocapflow.stages.skin.segmentation import Segmentation

try:  # scipy's CSR kernel, the one ``A @ X`` calls: y += A x, row by row, terms in stored order
    from scipy.sparse._sparsetools import csr_matvecs
except ImportError:  # pragma: no cover - a private module; the same bits through ``A @ X``

    def csr_matvecs(n_row, n_col, n_vecs, indptr, indices, data, x, y):  # noqa: D103
        # each call here adds at most one term to a row that is not zero (_Rows.combine),
        # so adding the product afterwards rounds as adding inside the kernel
        A = sp.csr_matrix((data, indices, indptr), shape=(n_row, n_col))
        y += (A @ x.reshape(n_col, n_vecs)).ravel()

__all__ = [
    "VertexOperator",
    "align_markers",
    "deform",
    "deform_positions",
    "unflip_triangles",
    "frame_coefficients",
    "operator_matrix",
    "vertex_operator",
]


# ------------------------------------------------------------------------- all parts (P&H Eq. 8–9)


@dataclass
class VertexOperator:
    """Sparse rows with ``vertices(f) = Σ_pairs (R_pair + N_pair) @ C(f)`` (P&H Eq. 8–9).

    Built once per mesh, segmentation and ``β``; every chunk of frames is then one
    sparse product (the non-rigid rows stacked above the rigid ones).  One row per
    vertex-part pair, ordered by layer (layer ``k``: each vertex's ``k``-th part,
    vertices ascending; layer 0 holds every vertex with a part), so the pairs are
    summed into the vertices layer by layer.  Every entry of a
    row depends only on its vertex and part, and a sparse row times a dense matrix
    adds its terms in column order, one row at a time: a vertex's result never
    depends on which other vertices are evaluated with it, on BLAS, or on its thread
    count (:func:`deform_positions`).

    Attributes
    ----------
    vertices : list of (Vp,) int ndarray
        Mesh vertices of each part (``β > 0``).
    beta : list of (Vp,) float ndarray
        The vertices' ``β`` per part.
    rigid : (N, K) scipy.sparse.csr_matrix
        ``β [v̄, 1]`` of each pair at its part's first four columns (local position,
        constant of the rigid transform).
    nonrigid : (N, K) scipy.sparse.csr_matrix
        ``β [q(v̄), 1, φ(v̄)]`` of each pair at its part's remaining columns (centred
        scaled monomials, constant, residual kernel values at the part's markers).
    pair_part : (N,) int ndarray
    pair_beta : (N,) float ndarray
    offsets : (P + 1,) int ndarray
        Columns of each part in :func:`frame_coefficients`.
    n_vertices : int
    clamp_margins : list of float or None
        Each part's :func:`~mocapflow.stages.skin.parts.soft_clamp` margin (None: no clamp).
    layers : list of ((n,) int ndarray, int)
        ``(vertices, first pair)`` of each layer; its pairs are consecutive.
    unit : (rigid, nonrigid) scipy.sparse.csr_matrix pair, or None
        The same rows with ``β = 1`` (built from rest vertices only; ``rigid`` and
        ``nonrigid`` are them times ``β``, bit for bit): :func:`_widen_blends` reuses
        them for the pairs it evaluates again with other weights.  Not shipped to
        workers.
    """

    vertices: list[np.ndarray]
    beta: list[np.ndarray]
    rigid: sp.csr_matrix
    nonrigid: sp.csr_matrix
    pair_part: np.ndarray
    pair_beta: np.ndarray
    offsets: np.ndarray
    n_vertices: int
    clamp_margins: list[float | None]
    layers: list[tuple[np.ndarray, int]]
    unit: tuple[sp.csr_matrix, sp.csr_matrix] | None = None


def _part_local(m: PartModel, points: np.ndarray) -> np.ndarray:
    """``(points - origin) @ axes`` as three products and two sums per coordinate, in a fixed
    order: a point's local coordinates never depend on the other points (BLAS blocking)."""
    d = points - m.origin
    return d[:, :1] * m.axes[0] + d[:, 1:2] * m.axes[1] + d[:, 2:3] * m.axes[2]


def vertex_operator(models: list[PartModel], n_vertices: int, *, residual: bool,
                    rest: np.ndarray | None = None,
                    beta: np.ndarray | None = None) -> VertexOperator:  # fmt: skip
    """Operator with ``vertices(f) = H @ C(f)`` for every frame (P&H Eq. 8–9).

    For part ``p`` and vertex ``v`` the row is ``β [v̄, 1, q(v̄), 1, φ(v̄)]`` (local
    position and constant of the rigid transform; centred scaled monomials,
    constant and kernel values at the part's markers of the non-rigid terms);
    :func:`frame_coefficients` gives the matching ``C``.  The non-rigid product is
    clamped (:func:`~mocapflow.stages.skin.parts.soft_clamp`, which commutes with
    the positive scale ``β``) in :func:`deform_positions`.

    Parameters
    ----------
    models : list of PartModel
    n_vertices : int
    residual : bool
        Include the RBF kernel columns.
    rest : (n_vertices, 3) float ndarray, optional
        Rest vertices, with ``beta``: the pairs are ``β > 0`` and every row is computed
        here from its own vertex alone (:func:`_pair_rows`).  Omitted: the models' own vertex arrays
        (:func:`~mocapflow.stages.skin.parts.prepare_part` with ``vertices``).
    beta : (n_vertices, P) float ndarray, optional
        Vertex weights, with ``rest``.

    Returns
    -------
    VertexOperator
    """
    if (rest is None) != (beta is None):
        raise ValueError("vertex_operator: give rest and beta together")
    sizes = [14 + (len(m.members) if residual else 0) for m in models]
    offsets = np.cumsum([0, *sizes])
    if rest is not None:  # every row from its own vertex, straight in (layer, vertex) order
        pair_vertex, pair_part = np.nonzero(beta[:, : len(models)] > 0)  # by vertex, then part
        rank = np.arange(len(pair_vertex)) - np.searchsorted(pair_vertex, pair_vertex)
        order = np.lexsort((pair_vertex, rank))  # by layer, then vertex
        pair_vertex, pair_part, rank = pair_vertex[order], pair_part[order], rank[order]
        pair_beta = beta[pair_vertex, pair_part]
        unit = _pair_rows(models, offsets, rest, pair_vertex, pair_part, residual=residual)
        R, N = (_scaled_rows(M, pair_beta) for M in unit)  # β times each row's terms
        by_part = np.argsort(pair_part, kind="stable")  # each part's vertices ascending
        cut = np.searchsorted(pair_part[by_part], np.arange(len(models) + 1))
        verts = [np.sort(pair_vertex[by_part[a:b]]) for a, b in zip(cut, cut[1:])]
        betas = [beta[v, q] for q, v in enumerate(verts)]
        counts = np.bincount(rank, minlength=1) if len(rank) else np.zeros(0, np.int64)
        starts = np.cumsum([0, *counts])
        layers = [(pair_vertex[a:b], int(a)) for a, b in zip(starts, starts[1:])]
        return VertexOperator(verts, betas, R, N, pair_part, pair_beta, offsets, n_vertices,
                              [m.clamp_margin for m in models], layers, unit)  # fmt: skip
    verts, betas, rigid, nonrigid = [], [], [], []
    for p, m in enumerate(models):  # the models' own vertex arrays
        v, b, local = m.vertices, m.beta, m.vertex_local
        basis, kernel = m.vertex_basis, m.vertex_kernel if residual else None
        one = np.ones((len(v), 1))
        dense = sp.csr_matrix(np.concatenate([basis, one], axis=1) * b[:, None])
        if kernel is not None and kernel.shape[1]:
            kernel = sp.csr_matrix(kernel)
            kernel = sp.csr_matrix((kernel.data * np.repeat(b, np.diff(kernel.indptr)),
                                    kernel.indices, kernel.indptr), shape=kernel.shape)  # fmt: skip
            dense = sp.hstack([dense, kernel], format="csr")
        pad = sp.csr_matrix((len(v), int(offsets[-1] - offsets[p + 1])))
        lead = sp.csr_matrix((len(v), int(offsets[p])))
        rigid.append(sp.hstack([lead, sp.csr_matrix(np.concatenate([local, one], 1) * b[:, None]),
                                sp.csr_matrix((len(v), sizes[p] - 4)), pad], format="csr"))
        nonrigid.append(sp.hstack([lead, sp.csr_matrix((len(v), 4)), dense, pad], format="csr"))
        verts.append(np.asarray(v, dtype=np.int64))
        betas.append(np.asarray(b, dtype=np.float64))
    K = int(offsets[-1])
    stack = (lambda blocks: sp.vstack(blocks, format="csr")) if models else (
        lambda blocks: sp.csr_matrix((0, K)))  # fmt: skip
    R, N = stack(rigid), stack(nonrigid)
    for M in (R, N):
        M.sort_indices()  # each row's terms are added in column order
    pair_vertex = np.concatenate(verts) if verts else np.zeros(0, np.int64)
    pair_part = np.repeat(np.arange(len(models)), [len(v) for v in verts])
    order = np.argsort(pair_vertex, kind="stable")  # by vertex, then part
    rank = np.empty(len(order), np.int64)  # k-th part of its vertex
    rank[order] = np.arange(len(order)) - np.searchsorted(pair_vertex[order], pair_vertex[order])
    order = np.lexsort((pair_vertex, rank))  # by layer, then vertex
    counts = np.bincount(rank, minlength=1) if len(rank) else np.zeros(0, np.int64)
    starts = np.cumsum([0, *counts])
    layers = [(pair_vertex[order[a:b]], int(a)) for a, b in zip(starts, starts[1:])]
    return VertexOperator(verts, betas, R[order], N[order], pair_part[order],
                          np.concatenate(betas)[order] if betas else np.zeros(0), offsets,
                          n_vertices, [m.clamp_margin for m in models], layers)  # fmt: skip


def operator_matrix(operator: VertexOperator) -> sp.csr_matrix:
    """The operator as one sparse ``(V, K)`` matrix ``H`` (``vertices(f) = H @ C(f)``).

    The linear map without the clamp: exact where no part clamps (``clamp_margin``
    None, or no vertex beyond its part's marker deviation).
    """
    n = operator.rigid.shape[0]
    pair_vertex = np.zeros(n, np.int64)
    for v, first in operator.layers:
        pair_vertex[first : first + len(v)] = v
    to_vertex = sp.csr_matrix((np.ones(n), (pair_vertex, np.arange(n))),
                              shape=(operator.n_vertices, n))  # fmt: skip
    return (to_vertex @ (operator.rigid + operator.nonrigid)).tocsr()


def _products(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` over the last two axes, ``(..., i, j) @ (..., j, k)``, as products summed in
    a fixed order (no BLAS: a frame's result never depends on the other frames)."""
    out = a[..., :, :1] * b[..., :1, :]
    for j in range(1, a.shape[-1]):
        out += a[..., :, j : j + 1] * b[..., j : j + 1, :]
    return out


def frame_coefficients(
    models: list[PartModel], fits: list[PartFit], *, residual: bool
) -> np.ndarray:
    """Per-frame coefficients ``C (K, F, 3)`` matching :func:`vertex_operator`.

    Block of part ``p``: ``[R^T; d_rigid; (R A)^T; d - d_rigid; W R^T]`` so that
    ``[v̄, 1, q, 1, φ] @ block = R (v̄ + A q + W^T φ) + d``, the rigid transform
    ``R v̄ + d_rigid`` coming from the first four rows.
    """
    if len(models) != len(fits):
        raise ValueError("frame_coefficients: one fit per model is needed")
    out = []
    for f in fits:
        rigid_d = f.d if f.rigid_d is None else f.rigid_d
        out.append(f.R.transpose(2, 0, 1))  # (3, F, 3): row k = R[:, :, k]
        out.append(rigid_d[None])  # (1, F, 3)
        out.append(_products(f.R, f.A).transpose(2, 0, 1))  # (9, F, 3): row k = (R A)[:, :, k]
        out.append((f.d - rigid_d)[None])  # (1, F, 3): the quadratic's constant, R c
        if residual:
            out.append(_products(f.W, f.R.transpose(0, 2, 1)).transpose(1, 0, 2))  # (n, F, 3)
    # C-contiguous (the blocks are transposed views), so its (K, 3F) reshape is a view
    C = np.empty((sum(len(b) for b in out), *out[0].shape[1:])) if out else None
    return np.concatenate(out, axis=0, out=C)


#: Pair-coordinates (rows x 3 frames) per product in :func:`deform_positions`: the work
#: arrays stay a few MB (16 frames of a 13,000-vertex mesh; all frames of a few hundred
#: vertices, as :func:`_widen_blends` evaluates them).
_VALUES_PER_PRODUCT = 800_000
_XYZ = np.dtype((np.void, 24))  # one vertex position (3 float64) as one item


def _clamp_weighted(u: np.ndarray, beta: np.ndarray, part: np.ndarray, deviation: np.ndarray,
                    margin: np.ndarray, *, beta_squared: np.ndarray | None = None,
                    deviation_squared: np.ndarray | None = None,
                    work: np.ndarray | None = None) -> None:  # fmt: skip
    """Soft-clamp β-weighted displacements ``u (N, 3f)`` in place at ``β × bound``, the
    bound of row ``i`` in frame ``j`` being ``deviation[part[i], j]`` (``deviation (P, f)``).

    Equal to ``β soft_clamp(u / β, bound)`` (the clamp commutes with a positive
    scale); only the entries beyond the bound (few) go through
    :func:`~mocapflow.stages.skin.parts.soft_clamp` (``margin (N,)`` per row).  An entry
    is beyond it when ``|u|² / β² > deviation²``; that test is made only where
    ``|u|² > β² deviation² (1 - 10⁻⁹)`` (a superset: the two sides differ by a few
    roundings), the same entries as testing all of them.
    ``beta_squared (N,)``, ``deviation_squared (P, f)``: ``β²`` and ``deviation²`` when
    already computed; ``work``: an ``(N, 3f)`` scratch array.
    """
    b2 = np.square(beta) if beta_squared is None else beta_squared
    d2 = np.square(deviation) if deviation_squared is None else deviation_squared
    sq = np.square(u, out=work)
    r2 = sq[:, 0::3] + sq[:, 1::3]
    r2 += sq[:, 2::3]  # (N, f): |β R u|²
    near = (d2 * (1.0 - 1e-9))[part]
    near *= b2[:, None]
    near = np.flatnonzero(r2 > near)  # the candidates, flat
    if not len(near):
        return
    i, j = np.divmod(near, r2.shape[1])
    over = r2.ravel()[near] / b2[i] > d2[part[i], j]
    if over.any():
        i, j = i[over], j[over]
        u3 = u.reshape(len(u), -1, 3)
        u3[i, j] = soft_clamp(u3[i, j], beta[i] * deviation[part[i], j], margin[i])


def _sparse_product(A: sp.csr_matrix, X: np.ndarray, out: np.ndarray) -> None:
    """``out[:] = A @ X`` for C-contiguous ``X (K, n)`` and ``out (N, n)``, by scipy's CSR
    kernel (the one ``A @ X`` calls, without its fresh result array and copy): it adds
    each row's terms in column order, one row at a time, so a row's value does not
    depend on the other rows."""
    if not out.flags.c_contiguous or out.shape != (A.shape[0], X.shape[1]) or (
            A.shape[1] != X.shape[0]):  # the kernel writes through raw pointers
        raise ValueError(f"_sparse_product: {A.shape} @ {X.shape} into {out.shape}")
    out.fill(0.0)
    if A.nnz:
        csr_matvecs(A.shape[0], A.shape[1], X.shape[1], A.indptr, A.indices, A.data,
                    X.ravel(), out.ravel())  # fmt: skip


def _stacked_rows(top: sp.csr_matrix, bottom: sp.csr_matrix) -> sp.csr_matrix:
    """The rows of ``top`` above those of ``bottom`` (same columns), as one CSR matrix built
    from their arrays (each row's terms as they are)."""
    indptr = np.concatenate([top.indptr, bottom.indptr[1:] + top.indptr[-1]])
    return sp.csr_matrix((np.concatenate([top.data, bottom.data]),
                          np.concatenate([top.indices, bottom.indices]), indptr),
                         shape=(top.shape[0] + bottom.shape[0], top.shape[1]))  # fmt: skip


def deform_positions(
    models: list[PartModel], fits: list[PartFit], n_vertices: int,
    operator: VertexOperator | None = None, *, residual: bool | None = None,
) -> np.ndarray:  # fmt: skip
    """Blend every part's moved vertices with their weights ``β`` (P&H Eq. 8–9).

    Per chunk of frames: one sparse product for the non-rigid displacements of all
    vertex-part pairs (clamped per part) and the rigid transforms (their rows stacked);
    then rigid + non-rigid per pair, and each vertex's pairs summed layer by layer
    (:class:`VertexOperator`).  Bit-for-bit the same whichever vertices, frames or parts
    are evaluated together, with any BLAS and thread count.

    Parameters
    ----------
    models : list of PartModel
    fits : list of PartFit
        One per model, same frames.
    n_vertices : int
    operator : VertexOperator, optional
        :func:`vertex_operator` of the models (built when omitted).
    residual : bool, optional
        Whether the fits carry a residual (default: any non-zero ``W``); must
        match ``operator``.

    Returns
    -------
    (F, V, 3) float ndarray
    """
    return _frame_major(models, fits, n_vertices, operator, residual=residual)[0]


def _frame_major(models: list[PartModel], fits: list[PartFit], n_vertices: int,
                 operator: VertexOperator | None = None, *, residual: bool | None = None,
                 edges: np.ndarray | None = None, coefficients: np.ndarray | None = None,
                 ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """:func:`deform_positions` ``(F, V, 3)``, and the largest squared length over the frames
    of ``edges (E, 2)`` (vertex pairs; ``(E,)``, empty without), measured on each chunk of
    frames while it is at hand (the same numbers as :func:`_longest_edges` of the result).
    ``coefficients``: the models' :func:`frame_coefficients` when already computed."""
    F = fits[0].R.shape[0] if fits else 0
    out = np.empty((F, n_vertices, 3))
    edges = np.zeros((0, 2), np.int64) if edges is None else edges
    most = np.zeros(len(edges))
    along = _edge_vectors(edges, n_vertices)
    work = np.empty(0)
    for a, b, X in _blended_chunks(models, fits, n_vertices, operator, residual=residual,
                                   coefficients=coefficients):  # fmt: skip
        # (V, f, 3) -> (f, V, 3), moving whole xyz triplets (24 bytes) at a time
        out[a:b].view(_XYZ)[..., 0] = X.view(_XYZ).T
        if len(edges):
            if work.shape != (len(edges), X.shape[1]):
                work = np.empty((len(edges), X.shape[1]))
            _sparse_product(along, X, work)  # (E, 3f): end minus start
            np.square(work, out=work)
            length = work[:, 0::3] + work[:, 1::3]
            length += work[:, 2::3]  # (E, f): as _squared_lengths
            for j in range(length.shape[1]):  # frame by frame (a max over a short axis is slow)
                np.maximum(most, length[:, j], out=most)
    return out, most


def _edge_vectors(edges: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """``(E, V)`` rows with ``-1`` at each edge's first vertex and ``1`` at its second:
    times positions ``(V, n)`` the edge vectors ``x[second] - x[first]``, the same bits
    as the subtraction (``0 - a + b`` or ``0 + b - a``, whichever vertex comes first)."""
    E = len(edges)
    M = sp.csr_matrix((np.repeat([[-1.0, 1.0]], E, axis=0).ravel(),
                       (np.repeat(np.arange(E), 2), np.asarray(edges).ravel())),
                      shape=(E, n_vertices))  # fmt: skip
    M.sort_indices()
    return M


def _squared_lengths(d: np.ndarray) -> np.ndarray:
    """``|d|²`` of vectors ``d (..., 3)``, its three terms added in a fixed order."""
    out = d[..., 0] * d[..., 0]
    out += d[..., 1] * d[..., 1]
    out += d[..., 2] * d[..., 2]
    return out


def _longest_edges(verts: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The largest squared length over the frames of ``edges (E, 2)`` of ``verts (F, V, 3)``."""
    most = np.zeros(len(edges))
    n = max(1, _EDGE_FRAMES_PER_SLICE // max(1, len(edges)))  # frames per slice
    for f0 in range(0, verts.shape[0], n):
        d = verts[f0 : f0 + n, edges[:, 1]] - verts[f0 : f0 + n, edges[:, 0]]
        np.maximum(most, _squared_lengths(d).max(0), out=most)
    return most


def _blended_chunks(models: list[PartModel], fits: list[PartFit], n_vertices: int,
                    operator: VertexOperator | None = None, *, residual: bool | None = None,
                    coefficients: np.ndarray | None = None):  # fmt: skip
    """The blended vertices chunk by chunk of frames, vertex-major: yields ``(a, b, X)``
    with ``X (V, 3 (b - a))`` the positions in frames ``a..b-1`` (a work array, overwritten
    by the next chunk); see :func:`deform_positions`.  ``coefficients``: the models'
    :func:`frame_coefficients` when already computed."""
    if residual is None:
        residual = any(np.any(f.W) for f in fits)
    if operator is None:
        operator = vertex_operator(models, n_vertices, residual=residual)
    C = frame_coefficients(models, fits, residual=residual) if coefficients is None else (
        coefficients)  # fmt: skip
    K, F, _ = C.shape
    if K != operator.offsets[-1]:
        raise ValueError("deform_positions: operator and fits disagree (residual?)")
    o = operator.offsets
    # without any non-rigid coefficient (rigid mode) that product is exactly zero: skipped
    nonrigid = any(C[o[p] + 4 : o[p + 1]].any() for p in range(len(models)))
    # the clamp: each pair's bound per frame (its part's marker deviation) and margin
    clamped = np.array([m is not None for m in operator.clamp_margins], bool)
    pairs = np.flatnonzero(clamped[operator.pair_part]) if nonrigid else np.zeros(0, np.int64)
    if len(pairs):
        deviation = np.stack([f.marker_deviation if c else np.zeros(F)
                              for f, c in zip(fits, clamped)])  # fmt: skip
        deviation_squared = np.square(deviation)
        part = operator.pair_part[pairs]
        margin = np.array([m or 0.0 for m in operator.clamp_margins])[part]
        beta = operator.pair_beta[pairs]
        beta_squared = np.square(beta)
    layers = operator.layers
    complete = bool(layers) and len(layers[0][0]) == n_vertices  # every vertex has a part
    # one product per chunk: the non-rigid rows (β R u, the non-rigid displacements) stacked
    # above the rigid ones (β (R v̄ + d), the rigid transforms), into work arrays reused by
    # every chunk (fresh pages cost more than the products here)
    N = operator.rigid.shape[0]
    rows = _stacked_rows(operator.nonrigid, operator.rigid) if nonrigid else operator.rigid
    n = max(1, min(F, _VALUES_PER_PRODUCT // (3 * max(1, N))))  # frames per product
    Z_full = np.empty((rows.shape[0], 3 * n))
    work_full = np.empty((len(pairs), 3 * n))
    for a in range(0, F, n):
        b = min(F, a + n)
        Cc = np.ascontiguousarray(C[:, a:b]).reshape(K, 3 * (b - a))
        full = b - a == n
        Z = Z_full if full else np.empty((rows.shape[0], 3 * (b - a)))
        _sparse_product(rows, Cc, Z)
        Y = Z[N:] if nonrigid else Z
        if nonrigid:
            U = Z[:N]
            if len(pairs):
                Up = U if len(pairs) == N else U[pairs]  # every part clamps (the default)
                _clamp_weighted(Up, beta, part, deviation[:, a:b], margin,
                                beta_squared=beta_squared,
                                deviation_squared=deviation_squared[:, a:b],
                                work=work_full if full else None)  # fmt: skip
                if len(pairs) < N:
                    U[pairs] = Up
            Y += U
        # sum each vertex's pairs, layer by layer (layer 0: vertices 0..V-1 when complete)
        if complete:
            X = Y[:n_vertices]
        else:
            X = np.zeros((n_vertices, 3 * (b - a)))
            if layers:
                X[layers[0][0]] = Y[: len(layers[0][0])]
        for v, first in layers[1:]:
            X[v] += Y[first : first + len(v)]
        yield a, b, X


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
               min_quadratic_markers: int, damping: float, ctx: Context) -> list[PartFit]:
    """Every part's fit over all frames (:func:`~mocapflow.stages.skin.parts.fit_part`),
    one task per part through ``ctx.map``; the models' and fits' messages are warned."""
    fits = ctx.map(
        partial(_fit_part_item, mode=mode, min_quadratic_markers=min_quadratic_markers,
                damping=damping),
        [(_without_vertices(m), x[:, m.members]) for m in models],
    )
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
                   coefficients: np.ndarray | None = None,
                   ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The blended vertices ``(F, V, 3)`` of ``operator`` (:func:`vertex_operator` of the
    rest vertices and their weights; P&H Eq. 8–9): in one in-process pass, or in frame
    chunks of ``chunk_frames`` on the executor's workers (the same bits either way); and the
    largest squared length over the frames of ``edges (E, 2)`` (:func:`_longest_edges`; empty
    without).  ``coefficients``: the models' :func:`frame_coefficients` when already
    computed (in-process pass)."""
    F, V = n_frames, operator.n_vertices
    edges = np.zeros((0, 2), np.int64) if edges is None else edges
    bounds = list(range(0, F, max(1, chunk_frames))) + [F]
    if ctx.mapper is None or len(bounds) <= 2:  # in-process: one pass, no copies
        return _frame_major(models, fits, V, operator, residual=residual, edges=edges,
                            coefficients=coefficients)  # fmt: skip
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


def _blending(beta: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Whether the corners of triangles ``faces (T, 3)`` blend differently (``β (V, P)``)."""
    b = beta[faces]  # (T, 3, P)
    return ((b[:, 0] != b[:, 1]) | (b[:, 0] != b[:, 2])).any(1)


def _blending_edges(mesh: Mesh, beta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The edges (:func:`~mocapflow.stages.skin.binding.mesh_edges`, ascending) of the
    triangles of ``mesh`` whose corners blend differently with weights ``β (V, P)``:
    their indices ``(E,)`` and ends ``(E, 2)``."""
    faces = np.asarray(mesh.faces, dtype=np.int64)
    ends, face_edge, _ = mesh_edges(faces, len(mesh.vertices))
    watch = np.unique(face_edge[_blending(beta, faces)])
    return watch, ends[watch]


#: Most diffusion steps of :func:`_widen_blends` between two checks of the stretch: one
#: while the torn triangles get fewer, twice as many each time they do not.
_MOST_STEPS_PER_CHECK = 8
#: Edge-frames (stretch checks) or vertex-frames (moved vertices) per slice of
#: :func:`_widen_blends`: work arrays of a few MB.
_EDGE_FRAMES_PER_SLICE = 100_000
#: Relative margin of :func:`_widen_blends`' length bounds over the round-off of the lengths
#: they bound (~1e-16): a bound within it of ``max_blend_stretch`` is measured instead.
_BOUND_MARGIN = 1e-9
#: Absolute slack (m) of :func:`_widen_blends`' bound on how far a vertex moved, over the
#: round-off of positions (~1e-16 m at a few metres from the origin).
_MOVE_ROUND_OFF = 1e-12


def widening_steps(mesh: Mesh, reach: float) -> int:
    """Most diffusion steps of :func:`_widen_blends` for a blend to spread ``reach`` metres.

    A step of :func:`~mocapflow.stages.skin.binding.blend_smoothing_operator` spreads a
    blend about one edge, a random walk: ``k`` steps reach about ``sqrt(k)`` edges, so
    ``ceil((reach / e)**2)`` with ``e`` the mean rest length of ``mesh``'s triangle edges.
    """
    f = np.asarray(mesh.faces, dtype=np.int64)
    if not len(f) or reach <= 0:
        return 0
    v = mesh.vertices
    e = float(np.mean([np.linalg.norm(v[f[:, (k + 1) % 3]] - v[f[:, k]], axis=1).mean()
                       for k in range(3)]))
    return int(np.ceil((reach / e) ** 2)) if e > 0 else 0


def _widen_blends(models: list[PartModel], fits: list[PartFit], mesh: Mesh, beta: np.ndarray,
                  verts: np.ndarray, *, max_stretch: float, steps: int, residual: bool,
                  measured: tuple[np.ndarray, np.ndarray] | None = None,
                  coefficients: np.ndarray | None = None,
                  operator: VertexOperator | None = None,
                  ) -> tuple[np.ndarray, int, int, int, int]:  # fmt: skip
    """Widen the blend between parts where it tears the surface (P&H Eq. 9's ``β``).

    Where two parts' models disagree at a vertex by ``D`` and ``β`` changes by
    ``Δβ`` along an edge of rest length ``e``, the edge stretches by about
    ``1 + D Δβ / e``.  While a triangle whose corners blend differently stretches
    an edge beyond ``max_stretch`` in some frame, the weights of its corners and of
    the vertices within ``k`` rings take ``k`` diffusion steps over the mesh
    (:func:`~mocapflow.stages.skin.binding.blend_smoothing_operator`; ``k`` is 1,
    doubled up to ``_MOST_STEPS_PER_CHECK`` while the torn triangles do not get fewer)
    and those vertices are moved again with every part they now follow (P&H
    Eq. 8–9; each vertex-part prediction is computed once), up to ``steps`` steps
    in all.  Vertices away from a tear keep their weights.

    The stretch is kept per mesh edge (each checked once for its two triangles), with
    bounds of its largest length over the frames: the length when last measured plus
    (upper) or less (lower) how far each end can have moved since (a vertex whose
    weights change by ``Δβ`` moves by at most ``Σ_p |Δβ_p| max_f |prediction_p -
    prediction_first|``, the weights summing to 1).  An edge is measured again (on every
    frame) only where a triangle starts to blend or a moved end's edge has bounds on
    both sides of ``max_stretch`` (within ``_BOUND_MARGIN``): the same decisions as
    measuring every such edge.  A vertex's position ``Σ_p β_p prediction_p`` is computed
    only when one of its edges is measured, and at the end (the same bits whenever it is
    computed).

    Where the widening does not leave fewer torn triangles than it found (parts
    whose models disagree widely, as rigid skinning of a sparse real capture),
    nothing changes: ``β`` and ``verts`` stay as they were.  Otherwise ``verts
    (F, V, 3)`` is updated in place.  Returns the ``β (V, P)`` kept, the steps
    taken, the number of vertices whose weights were diffused (0 when nothing
    changed), and the torn triangles before and after.  ``measured``: the edges of the
    triangles that blend (:func:`_blending_edges`) and their largest squared lengths over
    ``verts``' frames, when already measured (:func:`_deform_frames`); ``coefficients``:
    the models' :func:`frame_coefficients` when already computed; ``operator``: the
    :func:`vertex_operator` of ``beta`` (from the rest vertices), whose rows with ``β = 1``
    are reused for the pairs it holds (the same rows as built again).
    """
    faces = np.asarray(mesh.faces, dtype=np.int64)
    rest = mesh.vertices
    beta = beta.copy()
    V, T, P = len(rest), len(faces), beta.shape[1]
    F = verts.shape[0]
    rest_edges = np.stack([np.linalg.norm(rest[faces[:, (k + 1) % 3]] - rest[faces[:, k]], axis=1)
                           for k in range(3)], 1)  # fmt: skip
    rest_edges = np.maximum(rest_edges, 1e-12)
    ends, face_edge, first = mesh_edges(faces, V)
    E = len(ends)
    limit = (max_stretch * rest_edges.ravel()[first]) ** 2  # (E,) longest squared length
    incidence = sp.csr_matrix((np.ones(3 * T), (faces.ravel(), np.repeat(np.arange(T), 3))),
                              shape=(V, T))  # fmt: skip
    vertex_edges = sp.csr_matrix((np.ones(2 * E), (ends.ravel(), np.repeat(np.arange(E), 2))),
                                 shape=(V, E))  # fmt: skip
    smooth = blend_smoothing_operator(rest, faces)
    ring = (smooth != 0).astype(np.int8).tocsr()
    # vertex-major stores (rows of F x 3), filled on first use: positions of the vertices
    # whose edges are measured, and each vertex-part prediction with how far it lies from
    # the vertex's first prediction (largest over the frames)
    row = np.full(V, -1, np.int64)
    pos = _Rows(F)
    slot = np.full((V, P), -1, np.int64)
    pred = _Rows(F)
    spread = np.zeros(0)
    first = np.full(V, -1, np.int64)  # slot of each vertex's first prediction
    stale = np.zeros(V, bool)  # weights changed since its row of pos was last computed

    def with_rows(v: np.ndarray) -> None:
        """Give vertices ``v`` (any order, repeats) a row of ``pos``; a stale vertex's
        position is then computed from its predictions."""
        new = np.zeros(V, bool)
        new[v[row[v] < 0]] = True
        fresh = np.flatnonzero(new & ~stale)  # still at their first-pass positions
        if len(fresh):
            row[fresh] = pos.append(None, n_rows=len(fresh))
            for lo, hi, into in pos.segments(row[fresh]):  # (F, k) -> (k, F), 32 frames a time
                into = into.reshape(hi - lo, F, 3).view(_XYZ)[..., 0]
                for f in range(0, F, 32):
                    into[:, f : f + 32] = verts[f : f + 32].view(_XYZ)[:, fresh[lo:hi], 0].T
        new = np.flatnonzero(new & stale)  # placed below, straight into their new rows
        if len(new):
            row[new] = pos.append(None, n_rows=len(new))
            place(new)
        place(np.flatnonzero(np.isin(np.arange(V), v) & stale) if len(v) else v)

    # every part's frame_coefficients (K, 3F), whether its model has non-rigid terms
    # (deform_positions adds them then) and its clamp (bound per frame, margin)
    C = (frame_coefficients(models, fits, residual=residual) if coefficients is None
         else coefficients).reshape(-1, 3 * F)  # fmt: skip
    offsets = np.cumsum([0, *[14 + (len(m.members) if residual else 0) for m in models]])
    nonrigid = np.array([bool(C[o + 4 : z].any()) for o, z in zip(offsets, offsets[1:])], bool)
    clamped = np.array([m.clamp_margin is not None for m in models], bool)
    margins = np.array([m.clamp_margin or 0.0 for m in models])
    deviation = np.stack([f.marker_deviation if c else np.zeros(F)
                          for f, c in zip(fits, clamped)]) if P else np.zeros((0, F))  # fmt: skip
    deviation_squared = np.square(deviation)
    n_rows = max(1, _EDGE_FRAMES_PER_SLICE // max(1, F))  # rows per product: a few MB
    scratch = np.empty((2, n_rows, 3 * F))  # results of those products, reused

    # the first pass's rows with β = 1 (an operator pair per vertex and part, -1: none)
    unit = None if operator is None else operator.unit
    if unit is not None:
        pair_at = np.full((V, P), -1, np.int64)
        for lv, at in operator.layers:
            pair_at[lv, operator.pair_part[at : at + len(lv)]] = np.arange(at, at + len(lv))

    def pair_rows(v: np.ndarray, p: np.ndarray) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """:func:`_pair_rows` of pairs ``(v, p)`` with ``β = 1``, the operator's where it
        has them."""
        if unit is None:
            return _pair_rows(models, offsets, rest, v, p, residual=residual)
        at = pair_at[v, p]
        have = np.flatnonzero(at >= 0)
        if len(have) == len(v):
            return unit[0][at], unit[1][at]
        new = np.flatnonzero(at < 0)
        built = _pair_rows(models, offsets, rest, v[new], p[new], residual=residual)
        back = np.argsort(np.concatenate([have, new]))  # each pair's row, in (v, p) order
        return tuple(_stacked_rows(M[at[have]], B)[back] for M, B in zip(unit, built))

    def predict(v: np.ndarray, p: np.ndarray) -> None:
        """Give pairs ``(v, p)`` a row of ``pred``: part ``p``'s model alone at vertex ``v``
        (β = 1), by the row-by-row products of :func:`deform_positions` (the rigid rows
        straight into the store, the clamped non-rigid ones added)."""
        nonlocal spread
        key = np.unique(v[slot[v, p] < 0] * P + p[slot[v, p] < 0])
        v, p = key // P, key % P
        if not len(key):
            return
        new = pred.append(None, n_rows=len(key))
        slot[v, p] = new
        rigid, nonrigid_rows = pair_rows(v, p)
        u, at = np.unique(v, return_index=True)  # a vertex's first new pair comes first
        first[u[first[u] < 0]] = new[at[first[u] < 0]]
        far = np.empty(len(new))
        for lo, hi, into in pred.segments(new):  # (hi - lo, 3F) views of the store
            for c in range(lo, hi, n_rows):  # rows c..z-1, straight into the store
                z = min(hi, c + n_rows)
                rows = into[c - lo : z - lo]
                _sparse_product(_row_block(rigid, c, z), C, rows)
                bent = np.flatnonzero(nonrigid[p[c:z]])  # pairs whose part has non-rigid terms
                if len(bent):
                    U = scratch[1][: len(bent)]
                    every = len(bent) == z - c
                    _sparse_product(_row_block(nonrigid_rows, c, z) if every else
                                    nonrigid_rows[c + bent], C, U)  # fmt: skip
                    cl = np.flatnonzero(clamped[p[c + bent]])
                    if len(cl):
                        Uc = U if len(cl) == len(bent) else U[cl]
                        one = np.ones(len(cl))
                        _clamp_weighted(Uc, one, p[c + bent[cl]], deviation,
                                        margins[p[c + bent[cl]]], beta_squared=one,
                                        deviation_squared=deviation_squared,
                                        work=scratch[0][: len(cl)])  # fmt: skip
                        if len(cl) < len(bent):
                            U[cl] = Uc
                    if every:
                        rows += U  # rigid + non-rigid
                    else:
                        rows[bent] += U
                # how far each prediction lies from its vertex's first (computed by now;
                # 0 for the first itself)
                other = np.flatnonzero(first[v[c:z]] != new[c:z])
                far[c:z] = 0.0
                if len(other):
                    d = _row_differences(first[v[c + other]], new[c + other], pred, scratch[0])
                    far[c + other] = np.sqrt(_squared_lengths(d).max(1))
        spread = np.concatenate([spread, far])

    def place(R: np.ndarray, *, final: bool = False) -> None:
        """Rows of ``pos`` for vertices ``R`` (ascending, with rows): ``Σ_p β_p prediction_p``,
        parts in ascending order (:meth:`_Rows.combine`); ``final``: into ``verts`` instead
        (``R`` need no rows)."""
        b = beta[R]
        for c in range(0, len(R), n_rows):
            i, p = np.nonzero(b[c : c + n_rows] > 0)  # each vertex's parts, ascending
            layer = np.arange(len(i)) - np.searchsorted(i, i)  # k-th part of its vertex
            index = np.full((min(n_rows, len(R) - c), P), -1, np.int64)
            weights = np.zeros(index.shape)
            index[i, layer], weights[i, layer] = slot[R[c + i], p], b[c + i, p]
            L = int(layer.max(initial=-1)) + 1
            if final:  # (k, F) -> (F, k), moving whole xyz triplets (24 bytes) at a time
                moved = scratch[0][: len(index)]
                pred.combine(index[:, :L], weights[:, :L], moved)
                verts.view(_XYZ)[:, R[c : c + n_rows], 0] = moved.view(_XYZ).T
                continue
            rows = row[R[c : c + n_rows]]
            if np.all(np.diff(rows) == 1):  # consecutive rows: straight into the store
                for lo, hi, into in pos.segments(rows):
                    pred.combine(index[lo:hi, :L], weights[lo:hi, :L], into)
                continue
            moved = scratch[0][: len(index)]
            pred.combine(index[:, :L], weights[:, :L], moved)
            pos.put(rows, moved)
        stale[R] = False

    def blending(t: np.ndarray) -> np.ndarray:
        """Whether the corners of triangles ``t`` blend differently."""
        return _blending(beta, faces[t])

    def longest(e: np.ndarray) -> np.ndarray:
        """The largest squared length of edges ``e`` over the frames (current positions)."""
        with_rows(ends[e].ravel())
        out = np.empty(len(e))
        for i in range(0, len(e), n_rows):
            a, b = row[ends[e[i : i + n_rows]].T]
            d = _row_differences(a, b, pos, scratch[0])
            out[i : i + n_rows] = _squared_lengths(d).max(1)
        return out

    # only triangles whose corners blend differently can tear: start from their edges,
    # checked on the frame-major vertices (a vertex-major row only for those near a tear)
    blended = blending(np.arange(T))
    over = np.zeros(E, bool)  # stretched beyond max_stretch in some frame
    known = np.zeros(E, bool)  # `over` holds for the current positions
    # an upper bound of each edge's longest length over the frames: its length when last
    # measured plus how far each end can have moved since (triangle inequality); an edge
    # whose bound stays below max_stretch cannot be over it, so it is not measured again
    upper = np.full(E, np.inf)
    reach = np.sqrt(limit) / (1.0 + _BOUND_MARGIN)
    # and a lower bound (the length when last measured less how far the ends moved): an
    # edge whose lower bound stays beyond max_stretch is still over it
    lower = np.zeros(E)
    beyond = np.sqrt(limit) * (1.0 + _BOUND_MARGIN)
    check = np.zeros(E, bool)
    check[face_edge[blended]] = True
    check = np.flatnonzero(check)
    if measured is not None and np.array_equal(measured[0], check):
        most = measured[1]
    else:
        most = _longest_edges(verts, ends[check])
    over[check], known[check], upper[check] = most > limit[check], True, np.sqrt(most)
    lower[check] = upper[check]
    sides = [np.ascontiguousarray(face_edge[:, k]) for k in range(3)]

    def torn() -> np.ndarray:
        """The triangles that blend with an edge stretched beyond ``max_stretch``."""
        return np.flatnonzero(blended & (over[sides[0]] | over[sides[1]] | over[sides[2]]))

    bad = torn()
    torn_before = len(bad)
    beta_in = beta.copy()
    changed = np.zeros(V, bool)  # weights diffused; the position is then Σ β_p prediction_p
    taken, k, before = 0, 1, len(bad) + 1
    while len(bad) and taken < steps:
        if len(bad) >= before:  # no progress: diffuse farther before the next check
            k = min(2 * k, _MOST_STEPS_PER_CHECK)
        before = len(bad)
        k = min(k, steps - taken)
        taken += k
        S = np.unique(faces[bad])
        for _ in range(k):  # the torn triangles' corners and k rings around them
            S = _columns(ring, S)
        sub = smooth[S]
        prior = beta[S]
        for _ in range(k):
            beta[S] = np.asarray(sub @ beta)
        b = beta[S]
        b[b < 1e-3] = 0.0
        b /= b.sum(1, keepdims=True)
        beta[S] = b
        # a vertex moved before with the same weights would be moved to the same place
        redo = ~changed[S] | (b != prior).any(1)
        changed[S] = True
        R, b, prior = S[redo], b[redo], prior[redo]
        i, p = np.nonzero((b > 0) | (prior > 0))  # the parts it follows and followed
        predict(R[i], p)
        stale[R] = True  # placed when one of its edges is measured, or at the end
        # how far each vertex can have moved: Σ_p |Δβ_p| |prediction_p - first prediction|
        # (the weights sum to 1 before and after, so Σ_p Δβ_p c = 0 for any c; round-off
        # of the sums and of the first-pass positions well inside _MOVE_ROUND_OFF)
        moves = np.zeros(V)
        moves[R] = np.bincount(i, np.abs(b[i, p] - prior[i, p]) * spread[slot[R[i], p]],
                               minlength=len(R)) + _MOVE_ROUND_OFF  # fmt: skip
        # triangles may start or stop blending where weights changed; the edges of a vertex
        # that moved are checked again when their triangle blends and the bound of their
        # length reaches max_stretch
        t = _columns(incidence, S)
        blended[t] = blending(t)
        e = _columns(vertex_edges, R)
        upper[e] += moves[ends[e, 0]] + moves[ends[e, 1]]
        lower[e] -= moves[ends[e, 0]] + moves[ends[e, 1]]
        under, still = upper[e] < reach[e], lower[e] > beyond[e]
        known[e], over[e] = under | still, still
        check = np.zeros(E, bool)
        check[face_edge[blended]] = True
        check = np.flatnonzero(check & ~known)
        most = longest(check)
        over[check], known[check], upper[check] = most > limit[check], True, np.sqrt(most)
        lower[check] = upper[check]
        bad = torn()
    if len(bad) >= torn_before:  # no better: the weights as they were
        return beta_in, taken, 0, torn_before, len(bad)
    done = np.flatnonzero(changed)
    kept = done[(row[done] >= 0) & ~stale[done]]  # their rows of pos hold their positions
    for c in range(0, len(kept), 256):  # (k, F) -> (F, k), whole xyz triplets at a time
        rows = pos.take(row[kept[c : c + 256]])
        verts.view(_XYZ)[:, kept[c : c + 256], 0] = rows.view(_XYZ)[..., 0].T
    place(done[(row[done] < 0) | stale[done]], final=True)  # the others, straight into verts
    return beta, taken, len(done), torn_before, len(bad)


def _columns(A: sp.csr_matrix, rows: np.ndarray) -> np.ndarray:
    """The columns (ascending, each once) with an entry in any of ``rows (k,)`` of ``A``
    (``np.unique(A[rows].indices)`` without building ``A[rows]``)."""
    lo, n = A.indptr[rows], np.diff(A.indptr)[rows]
    at = np.arange(int(n.sum())) + np.repeat(lo - (np.cumsum(n) - n), n)
    hit = np.zeros(A.shape[1], bool)
    hit[A.indices[at]] = True
    return np.flatnonzero(hit)


def _row_block(A: sp.csr_matrix, a: int, b: int) -> sp.csr_matrix:
    """Rows ``a..b-1`` of ``A`` (its arrays' slices, each row's terms in their order)."""
    lo, hi = A.indptr[a], A.indptr[b]
    return sp.csr_matrix((A.data[lo:hi], A.indices[lo:hi], A.indptr[a : b + 1] - lo),
                         shape=(b - a, A.shape[1]))  # fmt: skip


def _scaled_rows(A: sp.csr_matrix, w: np.ndarray) -> sp.csr_matrix:
    """Row ``i`` of ``A`` times ``w[i]`` (``(n,)``), its terms in their order and places
    (each the product ``a w``, as :func:`_pair_rows` with weights computes it)."""
    return sp.csr_matrix((A.data * np.repeat(w, np.diff(A.indptr)), A.indices, A.indptr),
                         shape=A.shape)  # fmt: skip


def _row_differences(a: np.ndarray, b: np.ndarray, store: _Rows,
                     work: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """``store`` rows ``b`` minus rows ``a`` (``(k,)`` each) as ``(k, F, 3)``, by
    :meth:`_Rows.combine` (``0 - a + b``: the bits of the subtraction); in the first
    ``k`` rows of ``work (n >= k, 3 F)`` when given."""
    out = np.empty((len(a), 3 * store.shape[0])) if work is None else work[: len(a)]
    store.combine(np.stack([a, b], 1), np.tile([-1.0, 1.0], (len(a), 1)), out)
    return out.reshape(len(a), *store.shape)


def _pair_rows(models: list[PartModel], offsets: np.ndarray, rest: np.ndarray, v: np.ndarray,
               p: np.ndarray, beta: np.ndarray | None = None, *,
               residual: bool) -> tuple[sp.csr_matrix, sp.csr_matrix]:  # fmt: skip
    """The rows of :func:`vertex_operator` (rigid, non-rigid) of vertex-part pairs ``(v, p)``
    (``(k,)`` each) with weights ``beta (k,)`` (default 1), at the columns of all parts'
    :func:`frame_coefficients` (``offsets (P + 1,)``): every row from its own vertex alone
    (``β`` times its local position, monomials, 1 and kernel values; the zeros of the
    first three left out), each row's terms in column order, built from arrays (one pass
    per part, no sparse stacking)."""
    k, K = len(v), int(offsets[-1])
    rows, cols, vals = [[], []], [[], []], [[], []]  # rigid, non-rigid
    for q in np.unique(p):
        sel = np.flatnonzero(p == q)
        m, o = models[q], int(offsets[q])
        local = _part_local(m, rest[v[sel]])
        one = np.ones((len(sel), 1))
        for r, dense, at in ((0, np.concatenate([local, one], 1), o),
                             (1, np.concatenate([m.basis(local), one], 1), o + 4)):
            i, j = np.nonzero(dense)  # as a sparse matrix of the dense block keeps them
            rows[r].append(sel[i])
            cols[r].append(at + j)
            vals[r].append(dense[i, j] if beta is None else dense[i, j] * beta[sel[i]])
        if residual:
            kernel = sp.csr_matrix(m.kernel_rows(local))
            kernel.sort_indices()  # each row's markers ascending
            i = np.repeat(np.arange(len(sel)), np.diff(kernel.indptr))
            rows[1].append(sel[i])
            cols[1].append(o + 14 + kernel.indices)
            vals[1].append(kernel.data if beta is None else kernel.data * beta[sel[i]])
    out = []
    for r in range(2):
        i = np.concatenate(rows[r]) if rows[r] else np.zeros(0, np.int64)
        j = np.concatenate(cols[r]) if cols[r] else np.zeros(0, np.int64)
        # each row's terms in column order: a row's terms come from one part, appended in
        # column order (its monomials, 1, then its kernel values), so a stable sort by row
        order = np.argsort(i, kind="stable")
        out.append(sp.csr_matrix(
            (np.concatenate(vals[r])[order] if vals[r] else np.zeros(0), j[order],
             np.searchsorted(i[order], np.arange(k + 1))), shape=(k, K)))  # fmt: skip
    return out[0], out[1]


class _Rows:
    """A growing store of ``(F, 3)`` rows in blocks, each twice the size of the one before
    (nothing is copied when it grows; a block's unused rows are never touched)."""

    def __init__(self, n_frames: int, first_block: int = 256):
        self.blocks: list[np.ndarray] = []
        self.starts = [0]  # first row of each block, then the capacity
        self.shape = (n_frames, 3)
        self.first_block = first_block
        self.n = 0

    def append(self, rows: np.ndarray | None, *, frame_major: bool = True,
               n_rows: int = 0) -> np.ndarray:  # fmt: skip
        """Store ``rows (F, k, 3)`` (frame-major, as :func:`deform_positions` returns them)
        or ``(k, F, 3)`` (``frame_major`` false), or reserve ``n_rows`` rows (``rows``
        None, contents undefined until :meth:`put`); returns their indices ``(k,)``."""
        k = n_rows if rows is None else rows.shape[1 if frame_major else 0]
        while self.n + k > self.starts[-1]:
            size = 2 * len(self.blocks[-1]) if self.blocks else self.first_block
            self.blocks.append(np.empty((size, *self.shape)))
            self.starts.append(self.starts[-1] + size)
        for b, block in enumerate(self.blocks):  # the blocks the new rows fall in
            a, z = max(self.n, self.starts[b]), min(self.n + k, self.starts[b + 1])
            if a >= z or rows is None:
                continue
            if not frame_major:
                block[a - self.starts[b] : z - self.starts[b]] = rows[a - self.n : z - self.n]
            else:  # (F, k) -> (k, F), moving whole xyz triplets (24 bytes) at a time
                into = block[a - self.starts[b] : z - self.starts[b]]
                into.view(_XYZ)[..., 0] = rows[:, a - self.n : z - self.n].view(_XYZ)[..., 0].T
        self.n += k
        return np.arange(self.n - k, self.n)

    def put(self, index: np.ndarray, values: np.ndarray) -> None:
        """Overwrite rows ``index (n,)`` with ``values (n, F, 3)`` (or ``(n, 3 F)``)."""
        values = values.reshape(len(index), *self.shape)
        block = np.searchsorted(self.starts, index, side="right") - 1
        if len(index) and block.min() == block.max():  # one block (the usual case)
            self.blocks[block[0]][index - self.starts[block[0]]] = values
            return
        for b in np.unique(block):
            sel = block == b
            self.blocks[b][index[sel] - self.starts[b]] = values[sel]

    def take(self, index: np.ndarray) -> np.ndarray:
        """Rows ``index (n,)`` as an ``(n, F, 3)`` array."""
        block = np.searchsorted(self.starts, index, side="right") - 1
        if len(index) and block.min() == block.max():  # one block (the usual case): one copy
            return self.blocks[block[0]][index - self.starts[block[0]]]
        out = np.empty((len(index), *self.shape))
        for b in np.unique(block):
            sel = block == b
            out[sel] = self.blocks[b][index[sel] - self.starts[b]]
        return out

    def segments(self, index: np.ndarray):
        """The consecutive rows ``index (k,)`` (as :meth:`append` returns them) block by
        block: yields ``(a, b, rows)``, ``rows`` the ``(b - a, 3 F)`` view of ``index[a:b]``."""
        lo, hi = int(index[0]), int(index[-1]) + 1
        for b, block in enumerate(self.blocks):
            a, z = max(lo, self.starts[b]), min(hi, self.starts[b + 1])
            if a < z:
                view = block[a - self.starts[b] : z - self.starts[b]]
                yield a - lo, z - lo, view.reshape(z - a, -1)

    def combine(self, index: np.ndarray, weights: np.ndarray, out: np.ndarray) -> None:
        """``out (k, 3 F)`` = ``Σ_l weights[:, l] × row index[:, l]`` (``(k, L)`` each; index
        -1: no term), the terms added in ``l`` order: one sparse product per term and block,
        each adding to ``out`` (``0 + w_0 x_0 + w_1 x_1 ...``, the bits of the plain sum)."""
        out.fill(0.0)
        block = np.searchsorted(self.starts, index, side="right") - 1
        for j in range(index.shape[1]):
            for b in np.unique(block[index[:, j] >= 0, j]):
                has = (index[:, j] >= 0) & (block[:, j] == b)
                csr_matvecs(len(out), len(self.blocks[b]), out.shape[1],
                            np.concatenate([[0], np.cumsum(has)]),
                            index[has, j] - self.starts[b], weights[has, j],
                            self.blocks[b].ravel(), out.ravel())  # fmt: skip


def _deform_report(models: list[PartModel], fits: list[PartFit], x: np.ndarray,
                   binding: MeshBinding, n_vertices: int, *, mode: str) -> dict[str, Any]:
    """The deform report: per part its markers, vertices, fallback frames, dilation and
    how well the model reproduces the observed markers (RMS mm; 0 up to round-off with
    the residual)."""
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
        "max_vertex_distance_to_markers_mm": float(binding.distance.max() * 1000),
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
        ``blend_widening_reach`` (see the module docstring); ``None``: ``β`` as bound (the
        paper).  The default 2.5 removes the demo's torn triangles (40 -> 0 in
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
    x = align_markers(markers, segmentation)
    sparse = (segmentation.attrs.get("density") or {}).get("suited") is False
    if sparse:  # below Park & Hodgins' density (segment warned once): rigid skinning
        mode = "rigid"
    binding = bind_mesh(mesh.vertices, segmentation, sharpness=beta_sharpness,
                        name="detailed mesh", min_overlap=0.0 if sparse else 0.9)
    # frame-independent set-up in-process (cheap; per-vertex arrays stay here), the
    # per-part fits over all frames on the executor (small inputs and outputs)
    models = [
        prepare_part(segmentation, p, min_quadratic_markers=min_quadratic_markers,
                     dilation_factor=dilation_factor, residual_kernel=residual_kernel,
                     support_margin=support_margin, clamp_margin=clamp_margin)
        for p in range(segmentation.n_parts)
    ]  # fmt: skip
    fits = _fit_parts(models, x, mode=mode, min_quadratic_markers=min_quadratic_markers,
                      damping=quadratic_damping, ctx=ctx)
    V = mesh.vertices.shape[0]
    widen = max_blend_stretch is not None and len(mesh.faces) > 0
    # the edges of the triangles that blend, measured while the frames are evaluated
    watch, ends = _blending_edges(mesh, binding.beta) if widen else (None, None)
    residual = mode.endswith("residual")
    # computed once for both passes when the blend widens; else the evaluation pass
    # computes them where it runs (in process, or per chunk on the workers)
    C = frame_coefficients(models, fits, residual=residual) if widen else None
    operator = vertex_operator(models, V, residual=residual, rest=mesh.vertices,
                               beta=binding.beta)  # fmt: skip
    verts, longest = _deform_frames(
        models, fits, x.shape[0], operator, residual=residual,
        chunk_frames=chunk_frames, ctx=ctx, edges=ends, coefficients=C)
    beta, widened = binding.beta, {"steps": 0, "vertices": 0}
    if widen:
        beta, n_steps, n_changed, torn0, torn1 = _widen_blends(
            models, fits, mesh, binding.beta, verts, max_stretch=max_blend_stretch,
            steps=widening_steps(mesh, blend_widening_reach), residual=residual,
            measured=(watch, longest), coefficients=C, operator=operator)
        widened = {"steps": n_steps, "vertices": n_changed, "torn_before": torn0,
                   "torn_after": torn1 if n_changed else torn0}
        if torn0 and not n_changed:
            ctx.warn(f"deform: widening the blends did not tear fewer triangles ({torn0} "
                     f"-> {torn1} beyond {max_blend_stretch:g}x), so the paper's blend is kept")
    report = _deform_report(models, fits, x, binding, V, mode=mode)
    if unflip and mode != "rigid" and len(mesh.faces):
        reference = deform(markers, segmentation, mesh, mode="rigid",
                           min_quadratic_markers=min_quadratic_markers,
                           quadratic_damping=quadratic_damping, dilation_factor=dilation_factor,
                           beta_sharpness=beta_sharpness, residual_kernel=residual_kernel,
                           chunk_frames=chunk_frames, support_margin=support_margin,
                           clamp_margin=clamp_margin, max_blend_stretch=max_blend_stretch,
                           blend_widening_reach=blend_widening_reach,
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
