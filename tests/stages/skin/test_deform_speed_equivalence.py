"""The fast paths of the skin deformation equal straightforward computations (issue 15).

``deform``'s speed-ups must not change a bit: the stretch of the blending edges measured
while the frames are evaluated (``_frame_major(edges=...)``) against the plain lengths
of the result; any number of frames per sparse product; the widening fed those lengths,
with its length bounds (edges whose bound stays below ``max_blend_stretch`` are not
measured again, positions computed only when measured) against the widening measuring
every blending edge on every frame; and the whole stage in-process against frame chunks
on an executor (which measures the lengths afterwards).
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

import mocapflow.stages.skin.blend as blend_module
import mocapflow.stages.skin.deform as deform_module
import mocapflow.stages.skin.widening as widening_module
from mocapflow.pipeline import Context
from mocapflow.stages.skin.binding import mesh_edges
from mocapflow.stages.skin.blend import _frame_major, _part_local, deform_positions, vertex_operator
from mocapflow.stages.skin.deform import deform
from mocapflow.stages.skin.parts import fit_part, prepare_part, soft_clamp
from mocapflow.stages.skin.widening import _blending_edges, _longest_edges, _Rows, _widen_blends
from tests.stages.skin.conftest import limb_deform_setup


@pytest.fixture(scope="module")
def limb_fits():
    return limb_deform_setup(n_frames=60)


def _plain_longest(verts, ends):
    """Largest squared length over the frames of edges ``ends (E, 2)``, one edge at a time."""
    return np.array([max(float(np.dot(d, d)) for d in verts[:, b] - verts[:, a])
                     for a, b in ends])  # fmt: skip


def test_edges_measured_while_evaluating_equal_the_plain_lengths(limb_fits, monkeypatch):
    """The blending edges' largest squared lengths, taken chunk by chunk while the frames are
    evaluated, are the plain lengths of the returned vertices; the vertices are the same
    bytes for 1 frame, 7 frames or all frames per sparse product."""
    L = limb_fits
    mesh, V = L["mesh"], len(L["mesh"].vertices)
    watch, ends = _blending_edges(mesh, L["beta"])
    assert 20 < len(watch) < len(mesh_edges(np.asarray(mesh.faces), V)[0])  # some, not all
    runs = []
    for values in (1, 7 * 3 * L["op"].rigid.shape[0], 10**9):  # 1, 7 and all frames
        monkeypatch.setattr(blend_module, "_VALUES_PER_PRODUCT", values)
        runs.append(_frame_major(L["models"], L["fits"], V, L["op"], residual=True, edges=ends))
    verts, most = runs[0]
    assert verts.shape == (60, V, 3)
    assert verts.tobytes() == deform_positions(L["models"], L["fits"], V, L["op"],
                                               residual=True).tobytes()  # fmt: skip
    want = _plain_longest(verts, ends)
    np.testing.assert_allclose(most, want, rtol=1e-15, atol=0)
    assert _longest_edges(verts, ends).tobytes() == most.tobytes()
    for v, m in runs[1:]:
        assert v.tobytes() == verts.tobytes() and m.tobytes() == most.tobytes()


def _widen_every_edge(models, fits, mesh, beta, verts, **kw):
    """The widening with every blending edge measured on every frame after every round:
    ``_widen_blends`` with a length bound that never holds (no edge is skipped)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(widening_module, "_MOVE_ROUND_OFF", np.inf)
        return _widen_blends(models, fits, mesh, beta, verts, **kw)


@pytest.mark.parametrize("stretch", [1.05, 1.3, 2.0])
def test_widening_with_bounds_equals_measuring_everything(limb_fits, stretch, monkeypatch):
    """Fed the lengths measured while evaluating, and skipping the edges its bounds clear,
    the widening gives the same β, positions, steps, reweighted vertices and torn
    triangles as measuring every blending edge on every frame each round."""
    L = limb_fits
    mesh, V = L["mesh"], len(L["mesh"].vertices)
    watch, ends = _blending_edges(mesh, L["beta"])
    verts, most = _frame_major(L["models"], L["fits"], V, L["op"], residual=True, edges=ends)
    kw = {"max_stretch": stretch, "steps": 100, "residual": True}
    measured = []  # edge-frames (and prediction-frames) whose length was computed
    lengths = widening_module._squared_lengths
    monkeypatch.setattr(widening_module, "_squared_lengths",
                        lambda d: measured.append(d[..., 0].size) or lengths(d))  # fmt: skip
    want_verts = verts.copy()
    want = _widen_every_edge(L["models"], L["fits"], mesh, L["beta"], want_verts, **kw)
    n_want, measured[:] = sum(measured), []
    got_verts = verts.copy()
    got = _widen_blends(L["models"], L["fits"], mesh, L["beta"], got_verts,
                        measured=(watch, most), **kw)  # fmt: skip
    assert sum(measured) < n_want  # the bounds and the given lengths spared measurements
    assert got[1:] == want[1:]
    assert got[0].tobytes() == want[0].tobytes()
    assert got_verts.tobytes() == want_verts.tobytes()
    if stretch == 1.3:  # a case that widens: steps taken, vertices reweighted and moved
        assert got[1] > 2 and got[2] > 10 and got[4] < got[3]
        assert np.abs(got_verts - verts).max() > 1e-4


def test_stage_in_process_equals_frame_chunks_on_an_executor(limb_fits):
    """deform in-process (the blending edges measured during the one evaluation pass)
    gives the same bytes and widening report as frame chunks on an executor (lengths
    measured on the assembled vertices afterwards)."""
    d, seg, mesh = limb_fits["d"], limb_fits["seg"], limb_fits["mesh"]
    runs = [deform(d["markers"], seg, mesh, max_blend_stretch=1.3, chunk_frames=chunk,
                   ctx=Context(mapper=mapper))  # fmt: skip
            for chunk, mapper in ((1024, None), (7, lambda fn, items: list(map(fn, items))))]
    report = runs[0]["report"]["blend_widening"]
    assert report["vertices"] > 10 and report["torn_after"] < report["torn_before"]
    assert runs[1]["report"]["blend_widening"] == report
    assert runs[1]["mesh"].vertices.tobytes() == runs[0]["mesh"].vertices.tobytes()


def test_stage_on_threads_equals_one_thread(limb_fits, monkeypatch):
    """deform on 3 threads (the evaluation pass's chunks of frames shared by the threads,
    frame ranges of the widening, the binding beside the per-part fits, the report after
    it) gives the same bytes and report as on one, and the kernels and the evaluation
    pass's chunks did run on more than one thread; ``threads=0`` is refused in one line."""
    d, seg, mesh = limb_fits["d"], limb_fits["seg"], limb_fits["mesh"]
    # 5 rows per product on one thread (15 on 3: 20 frames each), and stores of blocks of
    # 4, 8, 16, ... rows, so that the widening's products and sums cross blocks; one frame
    # per chunk of the evaluation pass (60 chunks to share)
    monkeypatch.setattr(widening_module, "_EDGE_FRAMES_PER_SLICE", 60 * 5)
    monkeypatch.setattr(widening_module, "_FIRST_BLOCK_ROWS", 4)
    monkeypatch.setattr(widening_module, "_FIRST_BLOCK_BYTES", 0)
    monkeypatch.setattr(blend_module, "_VALUES_PER_PRODUCT", 1)
    ran, chunked = set(), []
    kernel, chunks = blend_module.csr_matvecs, blend_module._blended_chunks

    def spy(*a):
        ran.add(threading.get_ident())
        return kernel(*a)

    def chunk_spy(*a, **k):
        for item in chunks(*a, **k):
            chunked.append((threading.get_ident(), item[0], item[1]))
            yield item

    monkeypatch.setattr(blend_module, "csr_matvecs", spy)
    monkeypatch.setattr(widening_module, "csr_matvecs", spy)
    monkeypatch.setattr(blend_module, "_blended_chunks", chunk_spy)
    runs = []
    for n in (1, 3):
        ran.clear()
        chunked.clear()
        runs.append(deform(d["markers"], seg, mesh, max_blend_stretch=1.3, threads=n,
                           ctx=Context()))  # fmt: skip
        assert len(ran) == n
        # every frame evaluated once, in 60 one-frame chunks, by more than one thread on 3
        assert sorted((a, b) for _, a, b in chunked) == [(f, f + 1) for f in range(60)]
        takers = {t for t, _, _ in chunked}
        assert len(takers) == 1 if n == 1 else len(takers) >= 2
    report = runs[0]["report"]["blend_widening"]
    assert report["vertices"] > 10 and report["torn_after"] < report["torn_before"]
    assert runs[1]["report"] == runs[0]["report"]
    assert runs[1]["mesh"].vertices.tobytes() == runs[0]["mesh"].vertices.tobytes()
    with pytest.raises(deform_module.DeformError, match="threads must be >= 1"):
        deform(d["markers"], seg, mesh, threads=0, ctx=Context())


def test_widening_on_frame_ranges_of_unequal_length(monkeypatch):
    """An odd number of frames on 2 threads (the widening's ranges of 30 and 29 frames) gives
    the bytes of one thread.  The stores' first blocks were sized per range (at least
    ``_FIRST_BLOCK_BYTES``): with 7,200 bytes, 10 rows for 30 frames and 11 for 29, so the
    new rows were cut at the first range's block edges and the second's products failed
    with "_Rows.view: rows across blocks" (ezc3d's ``BTS.c3d``, 675 frames, on 2 threads)."""
    L = limb_deform_setup(n_frames=59)
    d, seg, mesh = L["d"], L["seg"], L["mesh"]
    with blend_module.Threads(2) as two:
        assert widening_module._frame_ranges(59, two) == [(0, 30), (30, 59)]
    monkeypatch.setattr(widening_module, "_FIRST_BLOCK_ROWS", 1)
    monkeypatch.setattr(widening_module, "_FIRST_BLOCK_BYTES", 7200)
    runs = [deform(d["markers"], seg, mesh, max_blend_stretch=1.3, threads=n, ctx=Context())
            for n in (1, 2)]  # fmt: skip
    report = runs[0]["report"]["blend_widening"]
    assert report["vertices"] > 10 and report["torn_after"] < report["torn_before"]
    assert runs[1]["report"] == runs[0]["report"]
    assert runs[1]["mesh"].vertices.tobytes() == runs[0]["mesh"].vertices.tobytes()


def test_rows_store_takes_vertex_major_rows():
    """_Rows.append of vertex-major rows ``(k, F, 3)`` stores them as they are, across
    blocks, next to frame-major appends."""
    rng = np.random.default_rng(7)
    store, kept = _Rows(5, first_block=2), []
    for k, frame_major in ((3, True), (4, False), (1, False), (6, True)):
        rows = rng.standard_normal((5, k, 3) if frame_major else (k, 5, 3))
        store.append(rows, frame_major=frame_major)
        kept.append(rows.transpose(1, 0, 2) if frame_major else rows)
    kept = np.concatenate(kept)
    assert store.take(np.arange(len(kept))).tobytes() == kept.tobytes()


def test_csr_rows_cut_as_scipy_cuts_them():
    """blend._CSRRows takes, slices, stacks and rounds rows to the arrays scipy's own
    ``A[rows]``, ``A[a:b]``, ``vstack`` and single precision give, in the same order, so a
    product with them has the same bits."""
    import scipy.sparse as sp

    from mocapflow.stages.skin.blend import _sparse_product

    rng = np.random.default_rng(3)
    A = sp.random(40, 30, density=0.2, format="csr", random_state=rng)
    B = sp.random(7, 30, density=0.3, format="csr", random_state=rng)
    rows = rng.integers(0, 40, 25)  # unsorted, with repeats
    R = blend_module._CSRRows.of(A)
    X = rng.standard_normal((30, 6))
    cases = [(R.take(rows), A[rows]), (R.between(5, 17), A[5:17]),
             (R.take(rows).above(blend_module._CSRRows.of(B)), sp.vstack([A[rows], B]).tocsr()),
             (R.between(3, 3), A[3:3])]  # fmt: skip
    for got, want in cases:
        assert got.shape == want.shape and got.nnz == want.nnz
        for name in ("indptr", "indices", "data"):
            assert np.array_equal(getattr(got, name), getattr(want, name))
        out = np.empty((got.shape[0], 6))
        _sparse_product(got, X, out)
        assert out.tobytes() == (want @ X).tobytes()
    single = R.between(0, 40).single()
    assert single.dtype == np.float32 and np.array_equal(single.data, A.data.astype(np.float32))


# ----------------------------------------------------------------- sparse products (issue 15)


def test_main_pass_makes_two_sparse_products_per_chunk_with_the_bits_of_scipy(limb_fits,
                                                                             monkeypatch):
    """The evaluation pass calls scipy's CSR kernel twice per chunk of frames (the non-rigid
    rows in single precision, the rigid ones in double added onto them, each into a reused
    array) and gives the bytes of the plain computation per frame: the non-rigid product
    (``A @ X`` of scipy), clamped (the clamp's rule in double precision, the clamped
    displacement stored back in single), then each rigid term added to it in its row's
    order, layer by layer."""
    L = limb_fits
    op, V = L["op"], len(L["mesh"].vertices)
    calls = []
    kernel = blend_module.csr_matvecs
    monkeypatch.setattr(blend_module, "csr_matvecs",
                        lambda *a: calls.append((a[0], a[5].dtype)) or kernel(*a))  # fmt: skip
    monkeypatch.setattr(blend_module, "_VALUES_PER_PRODUCT", 7 * 3 * op.rigid.shape[0])
    got = deform_positions(L["models"], L["fits"], V, op, residual=True)
    N = op.rigid.shape[0]
    assert calls == [(N, np.float32), (N, np.float64)] * 9  # 60 frames, 7 a chunk: 9 chunks
    C = blend_module.frame_coefficients(L["models"], L["fits"], residual=True)
    single = op.nonrigid.astype(np.float32)
    R = op.rigid
    n_terms = np.diff(R.indptr)
    want = np.empty_like(got)
    pair_beta = op.pair_beta
    for f in range(C.shape[1]):  # one frame at a time
        U = single @ C[:, f].astype(np.float32)
        assert U.dtype == np.float32
        bound = np.array([L["fits"][p].marker_deviation[f] for p in op.pair_part])
        r = np.sqrt(np.sum(np.square(U.astype(np.float64)), 1) / np.square(pair_beta))
        over = np.flatnonzero(np.square(r) > np.square(bound))
        if len(over):
            U[over] = soft_clamp(U[over].astype(np.float64), pair_beta[over] * bound[over], 0.1)
        Y = U.astype(np.float64)
        for t in range(n_terms.max()):  # the rigid terms, the t-th of every row in turn
            rows = np.flatnonzero(n_terms > t)
            at = R.indptr[rows] + t
            Y[rows] += R.data[at, None] * C[R.indices[at], f]
        X = Y[:V].copy()
        for v, first in op.layers[1:]:
            X[v] += Y[first : first + len(v)]
        want[f] = X
    assert got.tobytes() == want.tobytes()


def test_operator_rows_built_from_arrays_equal_the_sparse_stacking(limb_fits):
    """vertex_operator from rest vertices and β (rows built from arrays, in layer order)
    equals the one from the models' own vertex arrays given the same local coordinates
    (scipy's sparse stacking, as the rest path was built before): the same rows, entries,
    pairs and layers, bit for bit."""
    L = limb_fits
    mesh, beta, seg = L["mesh"], L["beta"], L["seg"]
    V = len(mesh.vertices)
    bound = [prepare_part(seg, p, vertices=mesh.vertices, beta=beta) for p in range(seg.n_parts)]
    for m in bound:  # local coordinates as the rest path computes them (no BLAS product)
        m.vertex_local = _part_local(m, mesh.vertices[m.vertices])
        m.vertex_basis, m.vertex_kernel = m.basis(m.vertex_local), m.kernel_rows(m.vertex_local)
    for residual in (True, False):
        want = vertex_operator(bound, V, residual=residual)
        got = vertex_operator(L["models"], V, residual=residual, rest=mesh.vertices, beta=beta)
        for a, b in ((got.rigid, want.rigid), (got.nonrigid, want.nonrigid)):
            assert a.shape == b.shape and a.nnz == b.nnz > 0
            assert np.array_equal(a.indptr, b.indptr) and np.array_equal(a.indices, b.indices)
            assert a.data.tobytes() == b.data.tobytes()
        assert np.array_equal(got.pair_part, want.pair_part)
        assert got.pair_beta.tobytes() == want.pair_beta.tobytes()
        assert len(got.layers) == len(want.layers) == 2  # some vertices follow two parts
        for (v, first), (w, start) in zip(got.layers, want.layers):
            assert first == start and np.array_equal(v, w)
        for a, b in zip(got.vertices + got.beta, want.vertices + want.beta):
            assert a.tobytes() == b.tobytes()


def test_rows_store_combines_rows_across_blocks_as_the_plain_sum():
    """_Rows.combine adds ``w_0 x_0 + w_1 x_1 + ...`` in that order over rows in different
    blocks (-1: no term), the bytes of the plain NumPy sum; _row_differences are the bytes
    of the subtraction, and _edge_vectors' product those of ``x[b] - x[a]`` either way round."""
    combine, differences = widening_module._Rows.combine, widening_module._row_differences
    rng = np.random.default_rng(3)
    store = _Rows(4, first_block=2)
    for k in (3, 5, 9):  # blocks of 2, 4, 8 rows: the rows straddle them
        store.append(rng.standard_normal((4, k, 3)))
    rows = store.take(np.arange(store.n))  # (17, 4, 3)
    index = rng.integers(0, store.n, (6, 3))
    index[1, 2] = index[4, 1:] = -1
    weights = rng.uniform(0.1, 1.0, index.shape)
    got = np.empty((6, 12))
    combine(store, index, weights, got)
    want = weights[:, 0, None, None] * rows[index[:, 0]]
    for j in (1, 2):
        has = index[:, j] >= 0
        want[has] += weights[has, j, None, None] * rows[index[has, j]]
    assert got.tobytes() == want.reshape(6, 12).tobytes()
    assert np.array_equal(got[4], (weights[4, 0] * rows[index[4, 0]]).ravel())
    a, b = np.array([0, 16, 5]), np.array([9, 2, 5])
    assert differences(a, b, store).tobytes() == (rows[b] - rows[a]).tobytes()
    X = rng.standard_normal((7, 6))
    edges = np.array([[0, 3], [5, 1], [6, 2]])
    out = np.empty((3, 6))
    blend_module._sparse_product(blend_module._edge_vectors(edges, 7), X, out)
    assert out.tobytes() == (X[edges[:, 1]] - X[edges[:, 0]]).tobytes()


def test_widening_with_a_rigid_part_among_bending_ones_matches_the_direct_loop(limb_fits):
    """A part without non-rigid terms (too few markers: rigid) next to quadratic ones: the
    widening's predictions (the rigid rows for every pair, the non-rigid rows only for the
    pairs of bending parts, clamped) give the bytes of the plain loop of test_deform."""
    from tests.stages.skin.test_deform import _widen_blends_directly

    L = limb_fits
    mesh, V, x = L["mesh"], len(L["mesh"].vertices), L["d"]["markers"].positions
    models = [prepare_part(L["seg"], p) for p in range(L["seg"].n_parts)]
    models[0].quadratic = False  # rigid: no non-rigid coefficient (quadratic mode)
    fits = [fit_part(m, x[:, m.members], mode="quadratic") for m in models]
    assert not fits[0].A.any() and all(f.A.any() for f in fits[1:])
    op = vertex_operator(models, V, residual=False, rest=mesh.vertices, beta=L["beta"])
    verts = deform_positions(models, fits, V, op, residual=False)
    kw = {"max_stretch": 1.3, "steps": 100, "residual": False}
    want_beta, want_verts, *want = _widen_blends_directly(models, fits, mesh, L["beta"], verts,
                                                          **kw)  # fmt: skip
    got_verts = verts.copy()
    got_beta, *got = _widen_blends(models, fits, mesh, L["beta"], got_verts, **kw)
    assert got == want and want[1] > 10 and want[3] < want[2]  # widened: fewer torn
    assert got_beta.tobytes() == want_beta.tobytes()
    assert got_verts.tobytes() == want_verts.tobytes()


def test_stage_computes_the_frame_coefficients_once(limb_fits, monkeypatch):
    """The evaluation pass and the widening share one frame_coefficients (issue 15: the
    widening computed them again), with the same bytes and report as before."""
    d, seg, mesh = limb_fits["d"], limb_fits["seg"], limb_fits["mesh"]
    want = deform(d["markers"], seg, mesh, max_blend_stretch=1.3, ctx=Context())
    calls = []
    coefficients = blend_module.frame_coefficients
    for module in (deform_module, blend_module, widening_module):  # wherever it is looked up
        monkeypatch.setattr(module, "frame_coefficients",
                            lambda *a, **k: calls.append(1) or coefficients(*a, **k))  # fmt: skip
    got = deform(d["markers"], seg, mesh, max_blend_stretch=1.3, ctx=Context())
    assert got["report"]["blend_widening"]["vertices"] > 10  # the widening ran
    assert len(calls) == 1
    assert got["report"] == want["report"]
    assert got["mesh"].vertices.tobytes() == want["mesh"].vertices.tobytes()


def test_clamp_tests_only_near_entries_and_clamps_the_same_ones():
    """_clamp_weighted tests ``|u|² / β² > deviation²`` only where ``|u|²`` comes near
    ``β² deviation²``: with entries at the bound and one ulp beyond it, the result is
    ``β soft_clamp(u / β, bound)`` entry by entry (the plain rule), bit for bit."""
    rng = np.random.default_rng(11)
    N, f, P = 40, 6, 3
    part = rng.integers(0, P, N)
    beta = rng.uniform(0.05, 1.0, N)
    deviation = rng.uniform(0.01, 0.05, (P, f))
    direction = rng.standard_normal((N, f, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    length = deviation[part] * rng.uniform(0.5, 1.5, (N, f))
    length[::4, 0] = deviation[part[::4], 0]  # at the bound
    length[1::4, 1] = np.nextafter(deviation[part[1::4], 1], 1.0)  # just beyond it
    u = (beta[:, None, None] * length[..., None] * direction).reshape(N, 3 * f)
    margin = np.full(N, 0.1)
    want = u.reshape(N, f, 3).copy()
    r2 = (np.square(want[..., 0]) + np.square(want[..., 1])) + np.square(want[..., 2])
    over = r2 / np.square(beta)[:, None] > np.square(deviation)[part]
    i, j = np.nonzero(over)
    want[i, j] = soft_clamp(want[i, j], beta[i] * deviation[part[i], j], margin[i])
    got = u.copy()
    blend_module._clamp_weighted(got, beta, part, deviation, margin)
    assert 0 < over.sum() < over.size
    assert got.tobytes() == want.reshape(N, 3 * f).tobytes()


def test_clamp_of_single_precision_displacements_clamps_the_same_ones():
    """_clamp_weighted on single-precision ``u`` (the evaluation's non-rigid products) gives
    the plain rule in double precision on those values, entry by entry, bit for bit: with
    lengths within a few single-precision roundings of the bound (columns 0-2), far from it
    (3-4), and bounds far below single precision's normal range (deviation 1e-20 m, column
    5, lengths within 3e-7 of it)."""
    rng = np.random.default_rng(12)
    N, f, P = 400, 6, 3
    part = rng.integers(0, P, N)
    beta = rng.uniform(0.05, 1.0, N)
    deviation = rng.uniform(0.01, 0.05, (P, f))
    deviation[:, 5] = 1e-20  # tiny bounds: every entry tested
    direction = rng.standard_normal((N, f, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    factor = 1.0 + rng.uniform(-3e-7, 3e-7, (N, f))  # at the bound, within roundings
    factor[:, 3:5] = rng.uniform(0.1, 10.0, (N, 2))
    length = deviation[part] * factor
    u = (beta[:, None, None] * length[..., None] * direction).astype(np.float32)
    u = u.reshape(N, 3 * f)
    margin = np.full(N, 1e-9)  # a clamped entry lands at its bound: a miss shows
    want = u.reshape(N, f, 3).copy()
    w = want.astype(np.float64)
    r2 = (np.square(w[..., 0]) + np.square(w[..., 1])) + np.square(w[..., 2])
    over = r2 / np.square(beta)[:, None] > np.square(deviation)[part]
    i, j = np.nonzero(over)
    want[i, j] = soft_clamp(w[i, j], beta[i] * deviation[part[i], j], margin[i])
    got = u.copy()
    blend_module._clamp_weighted(got, beta, part, deviation, margin,
                                 work=np.empty_like(got))  # fmt: skip
    assert 0 < over.sum() < over.size and over[:, 5].any() and not over[:, 5].all()
    assert got.dtype == np.float32
    assert got.tobytes() == want.reshape(N, 3 * f).tobytes()


def test_first_pass_gap_bounds_the_two_single_precision_evaluations(limb_fits):
    """widening._first_pass_gap bounds, per vertex, how far its evaluation-pass position
    (β folded into the single-precision non-rigid rows) lies from Σ_p β_p prediction_p (the
    rows with β = 1), over every frame; the two do differ (else no bound is needed); and it
    is 0 in the rigid mode, where they are equal."""
    L = limb_fits
    mesh, V, beta = L["mesh"], len(L["mesh"].vertices), L["beta"]
    for mode in ("quadratic_residual", "rigid"):
        residual = mode.endswith("residual")
        fits = L["fits"] if residual else [fit_part(m, L["d"]["markers"].positions[:, m.members],
                                                    mode="rigid") for m in L["models"]]  # fmt: skip
        op = vertex_operator(L["models"], V, residual=residual, rest=mesh.vertices, beta=beta)
        first = deform_positions(L["models"], fits, V, op, residual=residual)
        summed = np.zeros_like(first)
        for p in range(beta.shape[1]):
            sel = np.flatnonzero(beta[:, p] > 0)
            one = vertex_operator([L["models"][p]], len(sel), residual=residual,
                                  rest=mesh.vertices[sel], beta=np.ones((len(sel), 1)))  # fmt: skip
            alone = deform_positions([L["models"][p]], [fits[p]], len(sel), one,
                                     residual=residual)  # fmt: skip
            summed[:, sel] += beta[sel, p][None, :, None] * alone
        apart = np.linalg.norm(first - summed, axis=-1).max(0)  # (V,)
        gap = widening_module._first_pass_gap(
            op, blend_module.frame_coefficients(L["models"], fits, residual=residual))
        if residual:
            assert apart.max() > 0 and np.all(apart <= gap + 1e-12)
        else:
            assert np.all(gap == 0) and apart.max() < 1e-12


def test_binding_error_comes_first_on_threads(limb_fits):
    """With the binding on a second thread beside the part fits, a mesh that does not
    overlap the markers is still the error raised, also when the fits fail too (a part
    never placeable), as on one thread."""
    d, seg, mesh = limb_fits["d"], limb_fits["seg"], limb_fits["mesh"]
    far = deform_module.Mesh(mesh.vertices + [1.0, 0.0, 0.0], mesh.faces)
    x = d["markers"].positions.copy()
    labels = d["markers"].labels
    x[:, [labels.index(seg.labels[i]) for i in seg.members(0)]] = np.nan  # never placeable
    hidden = deform_module.Markers(x, d["markers"].labels, d["markers"].rate)
    for n in (1, 2):
        with pytest.raises(deform_module.DeformError, match="does not overlap"):
            deform(d["markers"], seg, far, threads=n, ctx=Context())
        with pytest.raises(deform_module.DeformError, match="does not overlap"):
            deform(hidden, seg, far, threads=n, ctx=Context())
        with pytest.raises(deform_module.DeformError, match="cannot be placed"):
            deform(hidden, seg, mesh, threads=n, ctx=Context())


def test_rbf_matrix_without_trees_is_the_same_matrix():
    """``rbf_matrix`` from every distance (small inputs) equals the k-d trees' matrix: the
    same pairs, values and bytes, one dilation or one per centre; a point on a centre
    takes the trees' path."""
    from mocapflow.stages.skin import kernels

    rng = np.random.default_rng(11)
    n_dense = 0
    for t in range(60):
        points = rng.normal(size=(int(rng.integers(1, 300)), 3)) * rng.uniform(0.01, 2.0)
        centres = rng.normal(size=(int(rng.integers(1, 50)), 3)) * rng.uniform(0.01, 2.0)
        if t % 4 == 0:
            points[0] = centres[0]  # coincident
        sigma = rng.uniform(0.05, 3.0, len(centres)) if t % 2 else rng.uniform(0.05, 3.0)
        got = kernels.rbf_matrix(points, centres, sigma)
        dense = kernels._dense_rbf_matrix(points, centres, np.broadcast_to(sigma, len(centres)))
        n_dense += dense is not None
        assert (dense is None) == (t % 4 == 0)
        old = kernels._MOST_DENSE_PAIRS
        try:
            kernels._MOST_DENSE_PAIRS = -1  # the trees
            want = kernels.rbf_matrix(points, centres, sigma)
        finally:
            kernels._MOST_DENSE_PAIRS = old
        assert got.shape == want.shape and got.nnz == want.nnz
        for a in ("indptr", "indices", "data"):
            assert getattr(got, a).tobytes() == getattr(want, a).tobytes(), (t, a)
    assert n_dense == 45
