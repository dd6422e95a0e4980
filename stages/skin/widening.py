"""Blend widening: the weights ``β`` of P&H Eq. 9 diffused where a blend tears the mesh.

Beyond Park & Hodgins 2006 (§5.3), used by the stage
:func:`mocapflow.stages.skin.deform.deform` (``max_blend_stretch``,
``blend_widening_reach``; ``max_blend_stretch=None``: the paper) after its evaluation
pass (:mod:`mocapflow.stages.skin.blend`): :func:`_widen_blends` checks the triangles
whose corners blend differently (:func:`_blending_edges`; their edges' largest lengths
over the frames, :func:`_longest_edges`), diffuses ``β`` where one stretches an edge
beyond ``max_blend_stretch`` and moves those vertices again with every part they now
follow; :func:`widening_steps` turns ``blend_widening_reach`` into a number of diffusion
steps; :class:`_Rows` is the vertex-major store of the predictions and positions it
combines.  The stage's docstring lists the other departures from the paper; this one,
with its measurements:

**Blends widened where they tear** (``max_blend_stretch`` 2.5; ``None`` = the
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
970 frames per CPU-second against about 1,650 without widening in the same
run, ``rigid`` (2,709 vertices, 92 steps) at about 1,090 against 3,250
(table 4 has both rows; before the widening took frame ranges and the non-rigid
terms single precision, issue 15: 772 / 1,237 and 1,030 / 2,962 in a run the same
day; before the widening took the operator's rows with
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
pass: 350 and 270; before the checks were made incremental: 200).  On one thread
(about 1.0 CPU-s) what is left is the evaluation pass (about 0.35 CPU-s: its two sparse
products per chunk, the non-rigid one in single precision, about 0.17
(:mod:`mocapflow.stages.skin.blend`; per part the rows would be dense blocks of 1,058,699
entries against 438,209 terms, mostly kernel values that are zero, and a fixed-order
NumPy sum over them costs 11x the CSR kernel, BLAS 0.8x without the
bit-reproducibility), its clamp test about 0.05, the transposition into the output and
the blending edges' lengths about 0.1), the widening (about 0.31: its predictions over
all frames about 0.1, the positions and lengths it measures about 0.13, its rounds'
bookkeeping about 0.07) and the set-up (binding, part fits, operator, report: about
0.25).  On 2 threads (the stage's ``threads``, issue 15; the same bits) the same body
runs at 1,340-1,390 frames/s (three calls in one process, idle 2-core machine; 619-679
on one thread and 932-976 on two before the widening took frame ranges, the binding ran
beside the part fits and the non-rigid terms went to single precision): the binding,
operator and mesh topology (about 0.14 s) run beside the part fits and report (about
0.16 s), the evaluation pass takes about 0.21 s and the widening about 0.28 s; the
passes over memory scale by only 1.2-1.8 (the two cores share about 30 GB/s) and the
widening's bookkeeping (about 0.07 s) stays on one thread.  Since, the second thread
makes the report (and the first-pass gap) after the binding while the first starts the
evaluation pass, whose chunks of frames the two share, and the binding's closest points
are found in chunks of points: paired whole-process runs on 2 threads against the code
before, 0.88-0.96 of its wall time on a noisy day (no change on one thread).
Held-out markers (``benchmarks/deform.py`` table 2) are points without
triangles, so they are not affected; table 3 (the simulator's true mesh)
measures it.  Not fixed by this: triangles that turn over against the rigid
mode (see ``tests/stages/skin/test_artifacts.py``; the stage's ``unflip``,
:func:`~mocapflow.stages.skin.deform.unflip_triangles`, pulls them back).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from mocapflow.stages.motion.datatypes import Mesh
from mocapflow.stages.skin.binding import blend_smoothing_operator, mesh_edges
from mocapflow.stages.skin.blend import (
    _NONRIGID,
    _XYZ,
    Threads,
    VertexOperator,
    _clamp_weighted,
    _CSRRows,
    _pair_rows,
    _sparse_product,
    csr_matvecs,
    frame_coefficients,
    vertex_operator,
)
from mocapflow.stages.skin.parts import PartFit, PartModel

__all__ = ["widening_steps"]


def _blending(beta: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Whether the corners of triangles ``faces (T, 3)`` blend differently (``β (V, P)``)."""
    b = beta[faces]  # (T, 3, P)
    return ((b[:, 0] != b[:, 1]) | (b[:, 0] != b[:, 2])).any(1)


@dataclass
class _Topology:
    """What :func:`_widen_blends` needs of the rest mesh alone (:func:`_mesh_topology`):
    ``faces (T, 3)``, the rest lengths ``(T, 3)`` of each triangle's edges (from corner
    ``k`` to ``k + 1``, at least 1e-12), the unique edges
    (:func:`~mocapflow.stages.skin.binding.mesh_edges`: ``ends``, ``face_edge``,
    ``first``), the vertex-triangle and vertex-edge incidences ``(V, T)`` and ``(V, E)``,
    the diffusion step (:func:`~mocapflow.stages.skin.binding.blend_smoothing_operator`)
    and its pattern ``ring``."""

    faces: np.ndarray
    rest_edges: np.ndarray
    ends: np.ndarray
    face_edge: np.ndarray
    first: np.ndarray
    incidence: sp.csr_matrix
    vertex_edges: sp.csr_matrix
    smooth: sp.csr_matrix
    ring: sp.csr_matrix


def _mesh_topology(mesh: Mesh) -> _Topology:
    """:class:`_Topology` of ``mesh`` (its rest vertices and faces)."""
    faces = np.asarray(mesh.faces, dtype=np.int64)
    rest = mesh.vertices
    V, T = len(rest), len(faces)
    rest_edges = np.stack([np.linalg.norm(rest[faces[:, (k + 1) % 3]] - rest[faces[:, k]], axis=1)
                           for k in range(3)], 1)  # fmt: skip
    ends, face_edge, first = mesh_edges(faces, V)
    E = len(ends)
    smooth = blend_smoothing_operator(rest, faces)
    return _Topology(
        faces, np.maximum(rest_edges, 1e-12), ends, face_edge, first,
        sp.csr_matrix((np.ones(3 * T), (faces.ravel(), np.repeat(np.arange(T), 3))),
                      shape=(V, T)),
        sp.csr_matrix((np.ones(2 * E), (ends.ravel(), np.repeat(np.arange(E), 2))),
                      shape=(V, E)),
        smooth, (smooth != 0).astype(np.int8).tocsr(),
    )  # fmt: skip


def _blending_edges(mesh: Mesh, beta: np.ndarray, topology: _Topology | None = None,
                    ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The edges (:func:`~mocapflow.stages.skin.binding.mesh_edges`, ascending) of the
    triangles of ``mesh`` whose corners blend differently with weights ``β (V, P)``:
    their indices ``(E,)`` and ends ``(E, 2)`` (``topology``: the mesh's
    :func:`_mesh_topology` when already made)."""
    if topology is None:
        faces = np.asarray(mesh.faces, dtype=np.int64)
        ends, face_edge, _ = mesh_edges(faces, len(mesh.vertices))
    else:
        faces, ends, face_edge = topology.faces, topology.ends, topology.face_edge
    watch = np.unique(face_edge[_blending(beta, faces)])
    return watch, ends[watch]


#: Most diffusion steps of :func:`_widen_blends` between two checks of the stretch: one
#: while the torn triangles get fewer, twice as many each time they do not.
_MOST_STEPS_PER_CHECK = 8


#: Edge-frames (stretch checks) or vertex-frames (moved vertices) per slice of
#: :func:`_widen_blends`: work arrays of a few MB.
_EDGE_FRAMES_PER_SLICE = 100_000


#: Rows of the first block of :func:`_widen_blends`' stores (:class:`_Rows`; each next block
#: twice the one before), at least :data:`_FIRST_BLOCK_BYTES`.
_FIRST_BLOCK_ROWS = 256


#: Bytes of the first block of :func:`_widen_blends`' stores at least: NumPy asks for huge
#: pages for arrays of 4 MiB or more, and the stores are filled once each (on the
#: throughput body of ``benchmarks/deform.py``, 2.8 MB blocks took 7,400-8,900 page faults
#: of 4 kB per deform, 0.05-0.18 s of system time).
_FIRST_BLOCK_BYTES = 4 << 20


#: Relative margin of :func:`_widen_blends`' length bounds over the round-off of the lengths
#: they bound (~1e-16): a bound within it of ``max_blend_stretch`` is measured instead.
_BOUND_MARGIN = 1e-9


#: Absolute slack (m) of :func:`_widen_blends`' bound on how far a vertex moved, over the
#: round-off of positions (~1e-16 m at a few metres from the origin).
_MOVE_ROUND_OFF = 1e-12


def _squared_lengths(d: np.ndarray) -> np.ndarray:
    """``|d|²`` of vectors ``d (..., 3)``, its three terms added in a fixed order (``x² + y²``,
    then ``+ z²``); ``d`` is squared in place (one pass over it, no temporaries)."""
    np.square(d, out=d)
    out = d[..., 0] + d[..., 1]
    out += d[..., 2]
    return out


def _longest_edges(verts: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The largest squared length over the frames of ``edges (E, 2)`` of ``verts (F, V, 3)``."""
    most = np.zeros(len(edges))
    n = max(1, _EDGE_FRAMES_PER_SLICE // max(1, len(edges)))  # frames per slice
    for f0 in range(0, verts.shape[0], n):
        d = verts[f0 : f0 + n, edges[:, 1]] - verts[f0 : f0 + n, edges[:, 0]]
        np.maximum(most, _squared_lengths(d).max(0), out=most)
    return most


def _frame_ranges(n_frames: int, threads: Threads | None) -> list[tuple[int, int]]:
    """The frames ``0..n_frames-1`` as one consecutive range ``(start, stop)`` per thread of
    ``threads`` (one range without; never an empty one but for no frame at all), as the
    widening splits them (each range then keeps its own stores)."""
    n = 1 if threads is None else min(threads.n, max(1, n_frames))
    cuts = np.linspace(0, n_frames, n + 1).round().astype(int).tolist()
    return list(zip(cuts[:-1], cuts[1:]))


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
                  operator: VertexOperator | None = None, threads: Threads | None = None,
                  topology: _Topology | None = None, gap: np.ndarray | None = None,
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
    prediction_first|``, the weights summing to 1; on its first move, plus how far its
    first-pass position can lie from ``Σ_p β_p prediction_p``, :func:`_first_pass_gap`:
    the two round the single-precision non-rigid terms differently).  An edge is measured
    again (on every frame) only where a triangle starts to blend or a moved end's edge has
    bounds on both sides of ``max_stretch`` (within ``_BOUND_MARGIN``): the same decisions as
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
    ``verts``' frames, when already measured
    (:func:`~mocapflow.stages.skin.deform._deform_frames`); ``coefficients``: the models'
    :func:`~mocapflow.stages.skin.blend.frame_coefficients` when already computed;
    ``operator``: the :func:`~mocapflow.stages.skin.blend.vertex_operator` of ``beta``
    (from the rest vertices), whose rows with ``β = 1`` are reused for the pairs it holds
    (the same rows as built again); ``topology``: the mesh's :func:`_mesh_topology` when
    already made; ``gap``: :func:`_first_pass_gap` of ``operator`` and ``coefficients`` when
    already computed.
    """
    threads = Threads() if threads is None else threads
    top = _mesh_topology(mesh) if topology is None else topology
    faces, ends, face_edge, first = top.faces, top.ends, top.face_edge, top.first
    incidence, vertex_edges, smooth, ring = top.incidence, top.vertex_edges, top.smooth, top.ring
    rest = mesh.vertices
    beta = beta.copy()
    V, T, P = len(rest), len(faces), beta.shape[1]
    F = verts.shape[0]
    E = len(ends)
    limit = (max_stretch * top.rest_edges.ravel()[first]) ** 2  # (E,) longest squared length
    # vertex-major stores, filled on first use: positions of the vertices whose edges are
    # measured, and each vertex-part prediction with how far it lies from the vertex's
    # first prediction (largest over the frames); a row's index is the same in every
    # frame range's stores (below)
    row = np.full(V, -1, np.int64)
    slot = np.full((V, P), -1, np.int64)
    spread = np.zeros(0)
    first = np.full(V, -1, np.int64)  # slot of each vertex's first prediction
    stale = np.zeros(V, bool)  # weights changed since its row of pos was last computed

    # every part's frame_coefficients (K, F, 3), whether its model has non-rigid terms
    # (deform_positions adds them then) and its clamp (bound per frame, margin)
    C = frame_coefficients(models, fits, residual=residual) if coefficients is None \
        else coefficients  # fmt: skip
    C = C.reshape(len(C), F, 3)
    offsets = np.cumsum([0, *[14 + (len(m.members) if residual else 0) for m in models]])
    nonrigid = np.array([bool(C[o + 4 : z].any()) for o, z in zip(offsets, offsets[1:])], bool)
    clamped = np.array([m.clamp_margin is not None for m in models], bool)
    margins = np.array([m.clamp_margin or 0.0 for m in models])
    deviation = np.stack([f.marker_deviation if c else np.zeros(F)
                          for f, c in zip(fits, clamped)]) if P else np.zeros((0, F))  # fmt: skip
    # the frames in one consecutive range per thread (as the evaluation pass): every
    # product, sum and measurement below is made range by range, each range on its own
    # thread with its own stores and work arrays; a value is computed as over all frames
    # at once, and the largest over the frames is the largest of the ranges' largest
    ranges = _frame_ranges(F, threads)
    longest = max(b - a for a, b in ranges)
    n_rows = max(1, _EDGE_FRAMES_PER_SLICE // max(1, longest))
    # every range's stores in the same blocks (sized for the longest range): the products
    # below cut the new rows at the first range's block edges for all of them (with blocks
    # sized per range, 675 frames in ranges of 337 and 338 cut them apart: the BTS capture
    # of ezc3d's test files on 2 threads failed with "_Rows.view: rows across blocks")
    first_block = max(_FIRST_BLOCK_ROWS, -(-_FIRST_BLOCK_BYTES // (24 * max(1, longest))))
    spans = threads.run(lambda r, _: _FrameRange(*r, C, deviation, n_rows, first_block),
                        ranges)  # fmt: skip

    def in_ranges(fn) -> list:
        """``fn(span)`` for every frame range, one thread each (they write disjoint frames:
        the same bits on any thread); the results in range order."""
        return threads.run(lambda s, _: fn(s), spans)

    def reserve(store: str, k: int) -> np.ndarray:
        """``k`` new rows of every range's ``store`` (``"pos"`` or ``"pred"``): their indices,
        the same in every range (the stores grow alike)."""
        return [getattr(s, store).append(None, n_rows=k) for s in spans][0]

    def with_rows(v: np.ndarray) -> None:
        """Give vertices ``v`` (any order, repeats) a row of ``pos``; a stale vertex's
        position is then computed from its predictions."""
        new = np.zeros(V, bool)
        new[v[row[v] < 0]] = True
        fresh = np.flatnonzero(new & ~stale)  # still at their first-pass positions
        if len(fresh):
            row[fresh] = reserve("pos", len(fresh))

            def copy(s: _FrameRange) -> None:  # (f, k) -> (k, f), 32 frames a time
                frames = verts[s.start : s.stop]
                for lo, hi, into in s.pos.segments(row[fresh]):
                    into = into.reshape(hi - lo, s.n, 3).view(_XYZ)[..., 0]
                    for f in range(0, s.n, 32):
                        into[:, f : f + 32] = frames[f : f + 32].view(_XYZ)[:, fresh[lo:hi], 0].T

            in_ranges(copy)
        new = np.flatnonzero(new & stale)  # placed below, straight into their new rows
        if len(new):
            row[new] = reserve("pos", len(new))
            place(new)
        place(np.flatnonzero(np.isin(np.arange(V), v) & stale) if len(v) else v)

    # the first pass's rows with β = 1 (an operator pair per vertex and part, -1: none)
    unit = None if operator is None or operator.unit is None else \
        tuple(map(_CSRRows.of, operator.unit))  # fmt: skip
    if unit is not None:
        pair_at = np.full((V, P), -1, np.int64)
        for lv, at in operator.layers:
            pair_at[lv, operator.pair_part[at : at + len(lv)]] = np.arange(at, at + len(lv))

    # how far a vertex's first-pass position (``verts``) can lie from Σ_p β_p prediction_p:
    # added to the bound of its first move (:func:`_first_pass_gap`)
    if gap is None:
        gap = _first_pass_gap(operator if unit is not None else vertex_operator(
            models, V, residual=residual, rest=rest, beta=beta), C)  # fmt: skip

    def pair_rows(v: np.ndarray, p: np.ndarray) -> tuple[_CSRRows, _CSRRows]:
        """:func:`~mocapflow.stages.skin.blend._pair_rows` of pairs ``(v, p)`` with ``β = 1``,
        the operator's where it has them."""
        if unit is None:
            return tuple(map(_CSRRows.of, _pair_rows(models, offsets, rest, v, p,
                                                     residual=residual)))  # fmt: skip
        at = pair_at[v, p]
        have = np.flatnonzero(at >= 0)
        if len(have) == len(v):
            return unit[0].take(at), unit[1].take(at)
        new = np.flatnonzero(at < 0)
        built = _pair_rows(models, offsets, rest, v[new], p[new], residual=residual)
        back = np.argsort(np.concatenate([have, new]))  # each pair's row, in (v, p) order
        return tuple(M.take(at[have]).above(_CSRRows.of(B)).take(back)
                     for M, B in zip(unit, built))  # fmt: skip

    def predict(v: np.ndarray, p: np.ndarray) -> None:
        """Give pairs ``(v, p)`` a row of ``pred``: part ``p``'s model alone at vertex ``v``
        (β = 1), by the row-by-row products of
        :func:`~mocapflow.stages.skin.blend.deform_positions` (the rigid rows straight into
        the store, the clamped non-rigid ones added)."""
        nonlocal spread
        # part by part (a part's coefficient rows stay in cache from one pair to the next),
        # vertices ascending
        key = np.unique(p[slot[v, p] < 0] * V + v[slot[v, p] < 0])
        v, p = key % V, key // V
        if not len(key):
            return
        new = reserve("pred", len(key))
        slot[v, p] = new
        u, at = np.unique(v, return_index=True)  # a vertex's first new pair: its lowest part
        first[u[first[u] < 0]] = new[at[first[u] < 0]]
        rigid_rows, nonrigid_rows = pair_rows(v, p)  # every new pair's rows, built once
        # rows c..z of the new ones per product, with the pairs whose part has non-rigid
        # terms and, of those, the clamped ones
        chunks = []
        for lo, hi, _ in spans[0].pred.segments(new):  # (the stores' blocks are alike)
            for c in range(lo, hi, n_rows):
                chunks.append((c, min(hi, c + n_rows)))
        for n, (c, z) in enumerate(chunks):
            bent = np.flatnonzero(nonrigid[p[c:z]])
            cl = np.flatnonzero(clamped[p[c + bent]])
            N = (nonrigid_rows.between(c, z) if len(bent) == z - c else
                 nonrigid_rows.take(c + bent)).single()  # fmt: skip
            other = np.flatnonzero(first[v[c:z]] != new[c:z])
            chunks[n] = (c, z, rigid_rows.between(c, z), bent, N, cl, other)

        def products(s: _FrameRange) -> np.ndarray:
            work = s.work
            far = np.zeros(len(key))
            for c, z, rigid, bent, N, cl, other in chunks:
                rows = s.pred.view(new[c:z])  # straight into the store
                if len(bent):  # the clamped non-rigid displacement, then the rigid terms
                    U = s.single[1][: len(bent)]
                    _sparse_product(N, s.C_single, U)
                    if len(cl):
                        Uc = U if len(cl) == len(bent) else U[cl]
                        one = np.ones(len(cl))
                        _clamp_weighted(Uc, one, p[c + bent[cl]], s.deviation,
                                        margins[p[c + bent[cl]]], beta_squared=one,
                                        deviation_squared=s.deviation_squared,
                                        work=s.single[0][: len(cl)])  # fmt: skip
                        if len(cl) < len(bent):
                            U[cl] = Uc
                    if len(bent) == z - c:
                        rows[...] = U
                    else:
                        rows.fill(0.0)
                        rows[bent] = U
                _sparse_product(rigid, s.C, rows, add=bool(len(bent)))
                # how far each prediction lies from its vertex's first (0 for the first
                # itself), while the chunk's rows are in cache: a vertex's first new pair
                # is its lowest part's, in this chunk or an earlier one
                if len(other):
                    d = _row_differences(first[v[c + other]], new[c + other], s.pred, work[0])
                    far[c + other] = np.sqrt(_squared_lengths(d).max(1))
            return far

        spread = np.concatenate([spread, np.maximum.reduce(in_ranges(products))])

    def place(R: np.ndarray, *, final: bool = False) -> None:
        """Rows of ``pos`` for vertices ``R`` (ascending, with rows): ``Σ_p β_p prediction_p``,
        parts in ascending order (:meth:`_Rows.combine`); ``final``: into ``verts`` instead
        (``R`` need no rows)."""
        b = beta[R]
        chunks = []  # vertices R[c : c + n_rows]: each one's predictions and weights
        for c in range(0, len(R), n_rows):
            i, p = np.nonzero(b[c : c + n_rows] > 0)  # each vertex's parts, ascending
            layer = np.arange(len(i)) - np.searchsorted(i, i)  # k-th part of its vertex
            index = np.full((min(n_rows, len(R) - c), P), -1, np.int64)
            weights = np.zeros(index.shape)
            index[i, layer], weights[i, layer] = slot[R[c + i], p], b[c + i, p]
            L = int(layer.max(initial=-1)) + 1
            rows = None if final else row[R[c : c + n_rows]]
            chunks.append((c, index[:, :L], weights[:, :L], rows))

        def combined(s: _FrameRange) -> None:
            for c, index, weights, rows in chunks:
                if final:  # (k, f) -> (f, k), moving whole xyz triplets (24 bytes) at a time
                    moved = s.work[0][: len(index)]
                    s.pred.combine(index, weights, moved)
                    verts[s.start : s.stop].view(_XYZ)[:, R[c : c + n_rows], 0] = \
                        moved.view(_XYZ).T  # fmt: skip
                elif np.all(np.diff(rows) == 1):  # consecutive rows: straight into the store
                    for lo, hi, into in s.pos.segments(rows):
                        s.pred.combine(index[lo:hi], weights[lo:hi], into)
                else:
                    moved = s.work[0][: len(index)]
                    s.pred.combine(index, weights, moved)
                    s.pos.put(rows, moved)

        in_ranges(combined)  # disjoint frames
        stale[R] = False

    def blending(t: np.ndarray) -> np.ndarray:
        """Whether the corners of triangles ``t`` blend differently."""
        return _blending(beta, faces[t])

    def longest(e: np.ndarray) -> np.ndarray:
        """The largest squared length of edges ``e`` over the frames (current positions)."""
        with_rows(ends[e].ravel())
        a, b = row[ends[e].T]

        def lengths(s: _FrameRange) -> np.ndarray:
            out = np.empty(len(e))
            for i in range(0, len(e), n_rows):
                d = _row_differences(a[i : i + n_rows], b[i : i + n_rows], s.pos, s.work[0])
                out[i : i + n_rows] = _squared_lengths(d).max(1)
            return out

        return np.maximum.reduce(in_ranges(lengths)) if len(e) else np.zeros(0)

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
        was = changed[S]
        redo = ~was | (b != prior).any(1)
        changed[S] = True
        R, b, prior, was = S[redo], b[redo], prior[redo], was[redo]
        i, p = np.nonzero((b > 0) | (prior > 0))  # the parts it follows and followed
        predict(R[i], p)
        stale[R] = True  # placed when one of its edges is measured, or at the end
        # how far each vertex can have moved: Σ_p |Δβ_p| |prediction_p - first prediction|
        # (the weights sum to 1 before and after, so Σ_p Δβ_p c = 0 for any c; round-off
        # of the sums well inside _MOVE_ROUND_OFF), and on its first move how far its
        # first-pass position can lie from Σ_p β_p prediction_p (gap)
        moves = np.zeros(V)
        moves[R] = np.bincount(i, np.abs(b[i, p] - prior[i, p]) * spread[slot[R[i], p]],
                               minlength=len(R)) + _MOVE_ROUND_OFF  # fmt: skip
        moves[R[~was]] += gap[R[~was]]
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

    def copy_kept(s: _FrameRange) -> None:  # (k, f) -> (f, k), whole xyz triplets at a time
        for c in range(0, len(kept), n_rows):
            k = len(kept[c : c + n_rows])
            rows = s.pos.take(row[kept[c : c + n_rows]], s.work[0][:k].reshape(k, s.n, 3))
            verts[s.start : s.stop].view(_XYZ)[:, kept[c : c + n_rows], 0] = \
                rows.view(_XYZ)[..., 0].T  # fmt: skip

    in_ranges(copy_kept)
    place(done[(row[done] < 0) | stale[done]], final=True)  # the others, straight into verts
    return beta, taken, len(done), torn_before, len(bad)


def _first_pass_gap(operator: VertexOperator, C: np.ndarray) -> np.ndarray:
    """How far each vertex's first-pass position can lie from ``Σ_p β_p prediction_p``
    (``(V,)``, metres): the evaluation pass multiplies the non-rigid rows with ``β`` folded
    in, the widening those with ``β = 1`` (``operator.unit``), both in the single precision
    of :data:`~mocapflow.stages.skin.blend._NONRIGID`, so the two round differently.  A row
    of ``n`` terms ``a_k`` times coefficients ``c_k`` (``C (K, F, 3)``) rounds by at most
    ``(n + 6) ε Σ_k |a_k| max_f |c_k|`` (its products and sums, ``a_k`` and ``c_k`` rounded
    to single precision, a clamped displacement stored back; the clamp, a radial
    contraction, moves no two values apart), per coordinate (``√3 < 2`` in length); twice
    that (the two passes), summed over the vertex's pairs with their ``β``.  0 where no part
    has non-rigid terms (the rigid mode)."""
    rows = operator.unit[1]
    V = operator.n_vertices
    if not rows.nnz:
        return np.zeros(V)
    top = np.abs(C.reshape(len(C), -1)).max(1)  # (K,): the largest |c_k| over the frames
    terms = abs(rows) @ top  # (N,): Σ_k |a_k| max |c_k| of each pair
    n = int(np.diff(rows.indptr).max())
    pair_vertex = np.zeros(rows.shape[0], np.int64)
    for v, at in operator.layers:
        pair_vertex[at : at + len(v)] = v
    eps = float(np.finfo(_NONRIGID).eps)
    return 4.0 * (n + 6) * eps * np.bincount(pair_vertex, operator.pair_beta * terms,
                                               minlength=V)  # fmt: skip


def _columns(A: sp.csr_matrix, rows: np.ndarray) -> np.ndarray:
    """The columns (ascending, each once) with an entry in any of ``rows (k,)`` of ``A``
    (``np.unique(A[rows].indices)`` without building ``A[rows]``)."""
    lo, n = A.indptr[rows], np.diff(A.indptr)[rows]
    at = np.arange(int(n.sum())) + np.repeat(lo - (np.cumsum(n) - n), n)
    hit = np.zeros(A.shape[1], bool)
    hit[A.indices[at]] = True
    return np.flatnonzero(hit)


def _row_differences(a: np.ndarray, b: np.ndarray, store: _Rows,
                     work: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """``store`` rows ``b`` minus rows ``a`` (``(k,)`` each) as ``(k, F, 3)``, by
    :meth:`_Rows.combine` (``0 - a + b``: the bits of the subtraction); in the first
    ``k`` rows of ``work (n >= k, 3 F)`` when given."""
    out = np.empty((len(a), 3 * store.shape[0])) if work is None else work[: len(a)]
    store.combine(np.stack([a, b], 1), np.tile([-1.0, 1.0], (len(a), 1)), out)
    return out.reshape(len(a), *store.shape)


class _FrameRange:
    """Consecutive frames ``start..stop-1`` of :func:`_widen_blends`, worked on by one
    thread: their frame coefficients ``C (K, 3 n)`` (from ``(K, F, 3)``) and ``C_single``, them
    in the precision of the non-rigid products (:data:`~mocapflow.stages.skin.blend._NONRIGID`),
    the parts' marker deviations ``(P, n)`` and their squares, the stores ``pos`` and
    ``pred`` of ``(n, 3)`` rows (first blocks of ``first_block`` rows, the same in every
    range) and the work arrays ``work`` and ``single`` (that precision),
    ``(2, n_rows, 3 n)`` each."""

    def __init__(self, start: int, stop: int, C: np.ndarray, deviation: np.ndarray,
                 n_rows: int, first_block: int):  # fmt: skip
        self.start, self.stop, self.n = start, stop, stop - start
        self.C = np.ascontiguousarray(C[:, start:stop]).reshape(len(C), 3 * self.n)
        self.deviation = deviation[:, start:stop]
        self.deviation_squared = np.square(self.deviation)
        self.pos, self.pred = _Rows(self.n, first_block), _Rows(self.n, first_block)
        self.work = np.empty((2, n_rows, 3 * self.n))
        self.C_single = self.C.astype(_NONRIGID)
        self.single = np.empty((2, n_rows, 3 * self.n), _NONRIGID)


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
        """Store ``rows (F, k, 3)`` (frame-major, as
        :func:`~mocapflow.stages.skin.blend.deform_positions` returns them)
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

    def take(self, index: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Rows ``index (n,)`` as an ``(n, F, 3)`` array (``out`` when given)."""
        block = np.searchsorted(self.starts, index, side="right") - 1
        out = np.empty((len(index), *self.shape)) if out is None else out
        if len(index) and block.min() == block.max():  # one block (the usual case): one copy
            np.take(self.blocks[block[0]], index - self.starts[block[0]], axis=0, out=out)
            return out
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

    def view(self, index: np.ndarray) -> np.ndarray:
        """The ``(k, 3 F)`` view of the consecutive rows ``index (k,)``, within one block."""
        (a, b, rows), *more = self.segments(index)
        if more or b - a != len(index):
            raise ValueError("_Rows.view: rows across blocks")
        return rows

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
