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

import numpy as np
import pytest

import mocapflow.stages.skin.deform as deform_module
from mocapflow.pipeline import Context
from mocapflow.stages.skin.binding import bind_mesh, mesh_edges
from mocapflow.stages.skin.deform import (
    _blending_edges,
    _frame_major,
    _longest_edges,
    _Rows,
    _widen_blends,
    deform,
    deform_positions,
    vertex_operator,
)
from mocapflow.stages.skin.parts import fit_part, prepare_part
from mocapflow.stages.skin.segment import segment
from tests.stages.skin.conftest import limb_capture


@pytest.fixture(scope="module")
def limb_fits():
    d = limb_capture(n_frames=60, noise=0.0)
    seg = segment(d["markers"], d["surface"], ctx=Context())["segmentation"]
    mesh, x = d["mesh"], d["markers"].positions
    beta = bind_mesh(mesh.vertices, seg, sharpness=4.0).beta
    models = [prepare_part(seg, p) for p in range(seg.n_parts)]
    fits = [fit_part(m, x[:, m.members], mode="quadratic_residual") for m in models]
    op = vertex_operator(models, len(mesh.vertices), residual=True, rest=mesh.vertices, beta=beta)
    return {"d": d, "seg": seg, "mesh": mesh, "beta": beta, "models": models, "fits": fits,
            "op": op}  # fmt: skip


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
        monkeypatch.setattr(deform_module, "_VALUES_PER_PRODUCT", values)
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
        mp.setattr(deform_module, "_MOVE_ROUND_OFF", np.inf)
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
    lengths = deform_module._squared_lengths
    monkeypatch.setattr(deform_module, "_squared_lengths",
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
