"""Blended vertices of every part as one sparse linear map (Park & Hodgins 2006, §5.3, Eq. 8–9).

Every vertex ``v̄`` of the detailed mesh is moved by the same model of every part it
belongs to (rigid, quadratic, residual: :mod:`mocapflow.stages.skin.parts`) and the
results are blended with its weights ``β``
(:func:`mocapflow.stages.skin.binding.bind_mesh`), all parts and frames as one linear
map ``vertices(f) = H · C(f)``: :func:`vertex_operator` builds ``H`` once (a
:class:`VertexOperator`), :func:`frame_coefficients` gives ``C``, and
:func:`deform_positions` evaluates them (:func:`operator_matrix`: ``H`` as one sparse
matrix).  The stage is :func:`mocapflow.stages.skin.deform.deform`; the blend widening
(:mod:`mocapflow.stages.skin.widening`) evaluates vertex-part pairs again with the same
rows.

Implementation notes (none changes the method):

* all parts and frames are evaluated as one linear map ``vertices(f) = H · C(f)``
  (``H``: β-weighted local coordinates, monomials and kernel values of the
  vertex-part pairs, built once; ``C``: per-frame part coefficients), done as two
  sparse products per chunk of frames (the non-rigid rows, clamped; the rigid rows'
  terms added onto them; 16 frames of a 13,000-vertex mesh: the work arrays stay a few
  MB, and the chunking changes no bit) by scipy's CSR kernel called directly into
  reused work arrays (``A @ X`` would allocate and copy its result and pay scipy's checks on
  every call); ``β`` is folded into ``H`` because the clamp commutes with a positive
  scale, and only the few entries beyond their bound are clamped.  ``H``'s rows are
  built from arrays (no sparse stacking), the blending edges' lengths are taken
  during that pass by one more sparse product (end minus start), and the widening's
  predictions, positions and edge vectors are sparse products over its stores of rows
  (all frames at once; :meth:`~mocapflow.stages.skin.widening._Rows.combine`), each
  adding its terms in the order the plain sums did: the same bits as before (issue
  15).  The frame coefficients are computed once for both passes, as one C-contiguous
  array (their ``(K, 3F)`` rows a view), and the clamp's test ``|u|² / β² > bound²``
  is made only on the entries whose ``|u|²`` comes within 10⁻⁹ of ``β² bound²`` (the
  same entries).  The operator keeps its rows with ``β = 1``
  (:attr:`VertexOperator.unit`; its own rows are them times ``β``, the same products
  as before): the widening takes the rows of the pairs it predicts from them where
  the operator holds the pair, and builds only the pairs the diffused ``β`` adds (on
  the throughput body 1,332 of 4,967);
* **threads** (the stage's ``threads``, :class:`Threads`): the evaluation pass's chunks of
  frames are shared by the threads (each takes the next when done: the second thread
  makes the binding, then the report, and joins late), the widening splits the frames
  into one consecutive range per thread (it keeps its stores of rows per range), and
  the binding runs beside the part fits; scipy's CSR kernel and NumPy's copies and
  ufuncs release the GIL, every job writes its own frames, and every value is computed
  as on one thread (below): the same bits on any number;
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
  same bytes (``tests/stages/skin/test_deform.py``);
* **the non-rigid terms in single precision** (:data:`_NONRIGID`): the non-rigid rows
  (``β [q(v̄), 1, φ(v̄)]``, 85 % of the terms) and their coefficients are rounded to
  single precision and multiplied out there; the clamp's test and the clamp itself are
  made in double precision on those values (a clamped displacement is stored back
  rounded), and the rigid transform, the sum of the two and the blend over the parts
  stay in double.  The non-rigid displacements are millimetres to centimetres, so this
  rounds the vertices by nanometres: on the throughput body of
  ``benchmarks/deform.py --throughput`` (13,000 vertices, 900 frames, coordinates up
  to 1.7 m) 1.2 nm on average and 94 nm at most from the all-double evaluation, whose
  former dense BLAS form it equalled within 1e-15 m; the rigid mode has no non-rigid
  terms and is unchanged.  The product takes less than half the time (0.30 -> 0.13
  CPU-s over the 900 frames on one thread; issue 15: deform 1,500 frames/s).
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from threading import Lock

import numpy as np
import scipy.sparse as sp

from mocapflow.stages.skin.parts import PartFit, PartModel, soft_clamp

try:  # scipy's CSR kernel, the one ``A @ X`` calls: y += A x, row by row, terms in stored order
    from scipy.sparse._sparsetools import csr_matvecs
except ImportError:  # pragma: no cover - a private module; the same bits through ``A @ X``

    def csr_matvecs(n_row, n_col, n_vecs, indptr, indices, data, x, y):  # noqa: D103
        # each call here adds at most one term to a row that is not zero (widening._Rows.combine),
        # so adding the product afterwards rounds as adding inside the kernel
        A = sp.csr_matrix((data, indices, indptr), shape=(n_row, n_col))
        y += (A @ x.reshape(n_col, n_vecs)).ravel()

__all__ = [
    "Threads",
    "VertexOperator",
    "deform_positions",
    "frame_coefficients",
    "operator_matrix",
    "vertex_operator",
]


# ------------------------------------------------------------------------- all parts (P&H Eq. 8–9)


class Threads:
    """``n`` threads sharing lists of jobs: the calling thread and ``n - 1`` pooled ones (a
    context manager; ``n = 1``: the calling thread alone, no pool).

    For work whose jobs write disjoint results and release the GIL (scipy's CSR kernel,
    NumPy's copies and ufuncs): every job computes the same bits whichever thread runs it.
    """

    def __init__(self, n: int = 1):
        self.n = max(1, int(n))
        self.pool = ThreadPoolExecutor(self.n - 1) if self.n > 1 else None

    def __enter__(self) -> Threads:
        return self

    def __exit__(self, *exc) -> None:
        if self.pool is not None:
            self.pool.shutdown()

    def submit(self, fn, *args, **kwargs) -> Future:
        """``fn(*args, **kwargs)`` on the pooled thread (after the work submitted before it), or
        at once on this one without a pool; its result (or error) from ``.result()``."""
        if self.pool is not None:
            return self.pool.submit(fn, *args, **kwargs)
        done: Future = Future()
        try:
            done.set_result(fn(*args, **kwargs))
        except Exception as error:
            done.set_exception(error)
        return done

    def run(self, fn, jobs: list, works: list | None = None) -> list:
        """``fn(job, work)`` for every job (``work``: thread ``t``'s ``works[t]``, None
        without), thread ``t`` taking jobs ``t, t + n, ...``; returns the results in job
        order."""
        out = [None] * len(jobs)

        def share(t: int) -> None:
            for i in range(t, len(jobs), self.n):
                out[i] = fn(jobs[i], None if works is None else works[t])

        if self.pool is None or len(jobs) < 2:  # n = 1 (every job), or one job
            share(0)
            return out
        done = [self.pool.submit(share, t) for t in range(1, min(self.n, len(jobs)))]
        share(0)
        for d in done:
            d.result()
        return out


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
        ``nonrigid`` are them times ``β``, bit for bit):
        :func:`~mocapflow.stages.skin.widening._widen_blends` reuses them for the pairs it
        evaluates again with other weights.  Not shipped to workers.
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
#: vertices, as :func:`~mocapflow.stages.skin.widening._widen_blends`
#: evaluates them).
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
    :func:`~mocapflow.stages.skin.parts.soft_clamp` (``margin (N,)`` per row), in double
    precision (a clamped single-precision ``u`` is stored back rounded).  An entry is beyond
    it when ``|u|² / β² > deviation²`` (``|u|²`` in double precision, its terms in ``x, y,
    z`` order); that test is made only where ``|u|² > β² deviation² (1 - 10⁻⁹)``, or for a
    single-precision ``u`` where its single-precision ``|u|²`` exceeds ``β² deviation² (1 -
    10⁻⁵)`` (every entry where ``deviation² min β² < 10⁻³⁰``, below single precision's
    normal range): a superset (the two sides differ by a few roundings, 2⁻²⁴ each in single
    precision), the same entries as testing all of them.
    ``beta_squared (N,)``, ``deviation_squared (P, f)``: ``β²`` and ``deviation²`` when
    already computed; ``work``: an ``(N, 3f)`` scratch array of ``u``'s dtype.
    """
    if not len(u):
        return
    b2 = np.square(beta) if beta_squared is None else beta_squared
    d2 = np.square(deviation) if deviation_squared is None else deviation_squared
    single = u.dtype == np.float32
    sq = np.square(u, out=work)
    r2 = sq[:, 0::3] + sq[:, 1::3]
    r2 += sq[:, 2::3]  # (N, f): |β R u|²
    if single:
        near = d2 * (1.0 - 1e-5)
        near[d2 * b2.min() < 1e-30] = -1.0
        near = near.astype(np.float32)[part]
        near *= b2.astype(np.float32)[:, None]
    else:
        near = (d2 * (1.0 - 1e-9))[part]
        near *= b2[:, None]
    near = np.flatnonzero(r2 > near)  # the candidates, flat
    if not len(near):
        return
    i, j = np.divmod(near, r2.shape[1])
    u3 = u.reshape(len(u), -1, 3)
    c = u3[i, j].astype(np.float64)  # the candidates in double precision (a copy)
    if single:
        r2 = c[:, 0] * c[:, 0] + c[:, 1] * c[:, 1]
        r2 += c[:, 2] * c[:, 2]
    else:
        r2 = r2.ravel()[near]
    over = r2 / b2[i] > d2[part[i], j]
    if over.any():
        i, j = i[over], j[over]
        u3[i, j] = soft_clamp(c[over], beta[i] * deviation[part[i], j], margin[i])


def _sparse_product(A: sp.csr_matrix | _CSRRows, X: np.ndarray, out: np.ndarray, *,
                    add: bool = False) -> None:  # fmt: skip
    """``out[:] = A @ X`` for C-contiguous ``X (K, n)`` and ``out (N, n)``, by scipy's CSR
    kernel (the one ``A @ X`` calls, without its fresh result array and copy): it adds
    each row's terms in column order, one row at a time, so a row's value does not
    depend on the other rows; ``add``: onto ``out`` as it is (``out += A @ X``, each term
    added in turn)."""
    if not out.flags.c_contiguous or out.shape != (A.shape[0], X.shape[1]) or (
            A.shape[1] != X.shape[0]) or not (
            A.dtype == X.dtype == out.dtype):  # the kernel writes through raw pointers
        raise ValueError(f"_sparse_product: {A.shape} {A.dtype} @ {X.shape} {X.dtype} into "
                         f"{out.shape} {out.dtype}")
    if not add:
        out.fill(0.0)
    if A.nnz:
        csr_matvecs(A.shape[0], A.shape[1], X.shape[1], A.indptr, A.indices, A.data,
                    X.ravel(), out.ravel())  # fmt: skip


#: The precision of the non-rigid displacements' products (P&H Eq. 6–7 terms): single.
#: Their terms are displacements of millimetres to centimetres from the rigid transform, so
#: single precision's rounding (2⁻²⁴ of the terms) is of nanometres, and the product takes
#: less than half the time of double precision's (twice the values per vector operation,
#: half the memory traffic).  The rigid transforms (positions of metres) stay in double.
_NONRIGID = np.float32


@dataclass(frozen=True)
class _CSRRows:
    """Rows of a CSR matrix as its arrays ``indptr``, ``indices`` and ``data`` (``shape``
    ``(rows, columns)``), cut and stacked with NumPy alone: :func:`_widen_blends` cuts a few
    hundred row sets a call, and a scipy matrix costs tens of microseconds to build each
    time.  Each row keeps its terms in their order, so a product with them
    (:func:`~mocapflow.stages.skin.blend._sparse_product`, which takes either) has the
    bits of the scipy rows'."""

    indptr: np.ndarray
    indices: np.ndarray
    data: np.ndarray
    shape: tuple[int, int]

    @classmethod
    def of(cls, A: sp.csr_matrix) -> _CSRRows:
        """The rows of ``A`` (its own arrays, not copied)."""
        return cls(A.indptr, A.indices, A.data, A.shape)

    @property
    def dtype(self) -> np.dtype:
        return self.data.dtype

    @property
    def nnz(self) -> int:
        return int(self.indptr[-1])

    def take(self, rows: np.ndarray) -> _CSRRows:
        """Rows ``rows (k,)`` in that order (repeats allowed), as ``A[rows]``."""
        lo = self.indptr[rows]
        n = self.indptr[rows + 1] - lo
        indptr = np.zeros(len(rows) + 1, self.indices.dtype)
        np.cumsum(n, out=indptr[1:])
        at = np.arange(indptr[-1]) + np.repeat(lo - indptr[:-1], n)
        return _CSRRows(indptr, self.indices[at], self.data[at], (len(rows), self.shape[1]))

    def between(self, a: int, b: int) -> _CSRRows:
        """Rows ``a..b-1`` (views of the arrays), as ``A[a:b]``."""
        lo, hi = int(self.indptr[a]), int(self.indptr[b])
        return _CSRRows(self.indptr[a : b + 1] - lo, self.indices[lo:hi], self.data[lo:hi],
                        (b - a, self.shape[1]))  # fmt: skip

    def above(self, other: _CSRRows) -> _CSRRows:
        """These rows, then ``other``'s (same columns)."""
        indptr = np.concatenate([self.indptr, other.indptr[1:] + self.indptr[-1]])
        return _CSRRows(indptr.astype(self.indices.dtype, copy=False),
                        np.concatenate([self.indices, other.indices]),
                        np.concatenate([self.data, other.data]),
                        (self.shape[0] + other.shape[0], self.shape[1]))  # fmt: skip

    def single(self) -> _CSRRows:
        """The same rows, their entries rounded to the precision of the non-rigid products
        (:data:`_NONRIGID`)."""
        return replace(self, data=self.data.astype(_NONRIGID))


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
                 threads: Threads | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """:func:`deform_positions` ``(F, V, 3)``, and the largest squared length over the frames
    of ``edges (E, 2)`` (vertex pairs; ``(E,)``, empty without), measured on each chunk of
    frames while it is at hand (the same numbers as
    :func:`~mocapflow.stages.skin.widening._longest_edges` of the result).
    ``coefficients``: the models' :func:`frame_coefficients` when already computed;
    ``threads``: the chunks of frames shared by the threads (:class:`Threads`), each thread
    taking the next chunk when done with its last, so a thread that starts late (busy with
    other work of the stage) takes fewer; the same bits on any number of threads and in
    any order: a frame's result never depends on the others, and the largest of the
    threads' largest lengths is their largest."""
    if residual is None:
        residual = any(np.any(f.W) for f in fits)
    if operator is None:
        operator = vertex_operator(models, n_vertices, residual=residual)
    if coefficients is None:
        coefficients = frame_coefficients(models, fits, residual=residual)
    F = fits[0].R.shape[0] if fits else 0
    out = np.empty((F, n_vertices, 3))
    edges = np.zeros((0, 2), np.int64) if edges is None else edges
    along = _edge_vectors(edges, n_vertices)

    chunks = _SharedChunks(F, _frames_per_product(operator))

    def evaluate() -> np.ndarray:
        most = np.zeros(len(edges))
        work = np.empty(0)
        for a, b, X in _blended_chunks(models, fits, n_vertices, operator,
                                       coefficients=coefficients, frames=chunks):  # fmt: skip
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
        return most

    if threads is None or threads.n == 1:
        return out, evaluate()
    return out, np.maximum.reduce(threads.run(lambda _, __: evaluate(), [None] * threads.n))


class _SharedChunks:
    """The frames ``0..n_frames-1`` in chunks of ``n`` (the last shorter), handed out in
    order to whichever thread asks next (an iterator of ``(a, b)``, safe across threads)."""

    def __init__(self, n_frames: int, n: int):
        self.bounds = [(a, min(n_frames, a + n)) for a in range(0, n_frames, n)]
        self.next = 0
        self.lock = Lock()

    def __iter__(self):
        while True:
            with self.lock:
                k, self.next = self.next, self.next + 1
            if k >= len(self.bounds):
                return
            yield self.bounds[k]


def _frames_per_product(operator: VertexOperator) -> int:
    """Frames per product of :func:`_blended_chunks` (:data:`_VALUES_PER_PRODUCT` values)."""
    return max(1, _VALUES_PER_PRODUCT // (3 * max(1, operator.rigid.shape[0])))


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


def _blended_chunks(models: list[PartModel], fits: list[PartFit], n_vertices: int,
                    operator: VertexOperator, *, coefficients: np.ndarray,
                    frames) -> Iterator[tuple[int, int, np.ndarray]]:  # fmt: skip
    """The blended vertices of the chunks of frames ``(a, b)`` that ``frames`` yields (at
    most :func:`_frames_per_product` frames each), vertex-major: yields ``(a, b, X)`` with
    ``X (V, 3 (b - a))`` the positions in frames ``a..b-1`` (a work array, overwritten by the
    next chunk); see
    :func:`deform_positions` (``coefficients``: the models' :func:`frame_coefficients`,
    ``(K, F, 3)``, as :func:`_frame_major` makes them)."""
    C = coefficients
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
    # per chunk: the rigid rows (β (R v̄ + d), the rigid transforms) times the coefficients,
    # and the non-rigid rows (β R u, the non-rigid displacements) times them in single
    # precision (_NONRIGID), into work arrays reused by every chunk (fresh pages cost more
    # than the products here)
    N = operator.rigid.shape[0]
    bent = _CSRRows.of(operator.nonrigid).single() if nonrigid else None
    n = min(F, _frames_per_product(operator))  # frames per product
    Y_full = np.empty((N, 3 * n))
    U_full = np.empty((N if nonrigid else 0, 3 * n), _NONRIGID)
    work_full = np.empty((len(pairs), 3 * n), _NONRIGID)
    for a, b in frames:
        Cc = np.ascontiguousarray(C[:, a:b]).reshape(K, 3 * (b - a))
        full = b - a == n
        Y = Y_full if full else np.empty((N, 3 * (b - a)))
        if nonrigid:  # the clamped non-rigid displacement, then the rigid terms added to it
            U = U_full if full else np.empty((N, 3 * (b - a)), _NONRIGID)
            _sparse_product(bent, Cc.astype(_NONRIGID), U)
            if len(pairs):
                Up = U if len(pairs) == N else U[pairs]  # every part clamps (the default)
                _clamp_weighted(Up, beta, part, deviation[:, a:b], margin,
                                beta_squared=beta_squared,
                                deviation_squared=deviation_squared[:, a:b],
                                work=work_full if full else None)  # fmt: skip
                if len(pairs) < N:
                    U[pairs] = Up
            Y[...] = U
        _sparse_product(operator.rigid, Cc, Y, add=nonrigid)
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


def _scaled_rows(A: sp.csr_matrix, w: np.ndarray) -> sp.csr_matrix:
    """Row ``i`` of ``A`` times ``w[i]`` (``(n,)``), its terms in their order and places
    (each the product ``a w``, as :func:`_pair_rows` with weights computes it)."""
    return sp.csr_matrix((A.data * np.repeat(w, np.diff(A.indptr)), A.indices, A.indptr),
                         shape=A.shape)  # fmt: skip


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
