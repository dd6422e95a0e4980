"""What ``deform`` builds once and reuses gives the bits of building it again (issue 15).

The operator keeps its rows with ``β = 1`` (``VertexOperator.unit``): its own rows are
them times ``β``, and the blend widening takes them for the vertex-part pairs the
operator holds instead of building those rows again (:func:`_pair_rows`); the frame
coefficients are one C-contiguous array, so their ``(K, 3F)`` rows are a view; the
widening's neighbourhoods (:func:`_columns`) are those of indexing the sparse rows.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import mocapflow.stages.skin.blend as blend_module
import mocapflow.stages.skin.widening as widening_module
from mocapflow.stages.skin.blend import _frame_major, _pair_rows, frame_coefficients
from mocapflow.stages.skin.widening import _blending_edges, _columns, _widen_blends
from tests.stages.skin.conftest import limb_deform_setup


@pytest.fixture(scope="module")
def limb():
    return limb_deform_setup(n_frames=40)


def _same(A, B):
    """Two CSR matrices with the same shape, terms, places and order, bit for bit."""
    return A.shape == B.shape and all(np.asarray(getattr(A, k)).tobytes()
                                      == np.asarray(getattr(B, k)).tobytes()
                                      for k in ("data", "indices", "indptr"))  # fmt: skip


def _pairs(op):
    """Each operator pair's vertex, in the operator's order."""
    v = np.zeros(op.rigid.shape[0], np.int64)
    for lv, first in op.layers:
        v[first : first + len(lv)] = lv
    return v


def test_unit_rows_times_beta_are_the_operator_rows(limb):
    """The operator's rows are its β = 1 rows times β, the same bits as rows built with β;
    the β = 1 rows equal those built again for any subset of the pairs, in any order."""
    L = limb
    op, mesh = L["op"], L["mesh"]
    v, p = _pairs(op), op.pair_part
    R1, N1 = op.unit
    assert R1.shape == op.rigid.shape and N1.nnz == op.nonrigid.nnz > 0
    with_beta = _pair_rows(L["models"], op.offsets, mesh.vertices, v, p, op.pair_beta,
                           residual=True)  # fmt: skip
    assert _same(with_beta[0], op.rigid) and _same(with_beta[1], op.nonrigid)
    assert not _same(R1, op.rigid)  # β differs from 1 somewhere: the rows are the unit ones
    pick = np.random.default_rng(0).permutation(len(v))[: len(v) // 3]
    again = _pair_rows(L["models"], op.offsets, mesh.vertices, v[pick], p[pick], residual=True)
    assert _same(again[0], R1[pick]) and _same(again[1], N1[pick])


@pytest.mark.parametrize("stretch", [1.3, 2.0])
def test_widening_with_the_operators_rows_equals_building_them(limb, stretch, monkeypatch):
    """The widening given the operator (its β = 1 rows reused for the pairs it holds, new
    pairs built) gives the same β, positions, steps and counts as building every row."""
    L = limb
    mesh, V = L["mesh"], len(L["mesh"].vertices)
    watch, ends = _blending_edges(mesh, L["beta"])
    verts, most = _frame_major(L["models"], L["fits"], V, L["op"], residual=True, edges=ends)
    built = []  # pairs whose rows _pair_rows built
    rows = widening_module._pair_rows  # where the widening looks it up
    monkeypatch.setattr(widening_module, "_pair_rows",
                        lambda *a, **k: built.append(len(a[3])) or rows(*a, **k))  # fmt: skip
    kw = {"max_stretch": stretch, "steps": 100, "residual": True, "measured": (watch, most)}
    want_verts = verts.copy()
    want = _widen_blends(L["models"], L["fits"], mesh, L["beta"], want_verts, **kw)
    n_want, built[:] = sum(built), []
    got_verts = verts.copy()
    got = _widen_blends(L["models"], L["fits"], mesh, L["beta"], got_verts, operator=L["op"],
                        **kw)  # fmt: skip
    assert got[1:] == want[1:]
    assert got[0].tobytes() == want[0].tobytes()
    assert got_verts.tobytes() == want_verts.tobytes()
    assert want[2] > 10  # it reweighted vertices, predicting their parts
    # fewer rows built: the operator's were taken; the blends spread to parts the
    # operator's pairs lack, whose rows were built
    assert 0 < sum(built) < n_want


def test_frame_coefficients_are_one_c_contiguous_array(limb):
    """The coefficients come C-contiguous (their (K, 3F) rows a view, not a copy) with the
    values of stacking the blocks."""
    L = limb
    C = frame_coefficients(L["models"], L["fits"], residual=True)
    K, F, _ = C.shape
    assert C.flags.c_contiguous and np.shares_memory(C, C.reshape(K, 3 * F))
    f, m = L["fits"][0], L["models"][0]
    n = len(m.members)
    assert K == L["op"].offsets[-1] and 14 + n == L["op"].offsets[1]
    assert C[:3].tobytes() == np.ascontiguousarray(f.R.transpose(2, 0, 1)).tobytes()
    kernel = blend_module._products(f.W, f.R.transpose(0, 2, 1)).transpose(1, 0, 2)
    assert C[14 : 14 + n].tobytes() == np.ascontiguousarray(kernel).tobytes()
    np.testing.assert_allclose(C[14 : 14 + n], np.einsum("fnk,fjk->nfj", f.W, f.R),
                               rtol=0, atol=1e-15)  # fmt: skip


def test_columns_of_rows_are_those_of_the_indexed_rows():
    """``_columns(A, rows)`` is ``np.unique(A[rows].indices)``: any rows, repeated, in any
    order, empty rows among them, and no rows at all."""
    rng = np.random.default_rng(3)
    A = sp.random(300, 500, density=0.01, format="csr", random_state=4)
    A = A + sp.csr_matrix((np.ones(3), ([7, 7, 9], [499, 0, 250])), shape=A.shape)
    empty = np.flatnonzero(np.diff(A.indptr) == 0)
    assert len(empty) > 0
    for rows in (rng.integers(0, 300, 40), np.array([7, 9, 7, *empty[:3]]), np.arange(300),
                 np.zeros(0, np.int64)):  # fmt: skip
        got = _columns(A, rows)
        assert got.tobytes() == np.unique(A[rows].indices).astype(got.dtype).tobytes()
    assert _columns(A, np.array([7])).tolist() == sorted(A[7].indices.tolist())
    assert {0, 250, 499} <= set(_columns(A, np.array([7, 9])).tolist())
