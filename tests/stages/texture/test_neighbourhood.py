"""Slot-pair distances of the search: per-coordinate gathers and the pair tables give
the values of the formula on (…, K, 3) vectors, to the last bit (the search's choices
and so ``source_index`` depend on exact ties)."""

from __future__ import annotations

import numpy as np
import pytest

from mocapflow.stages.texture.neighbourhood import (
    LevelView,
    pair_distance,
    pair_tables,
    slot_distance,
    window_cost,
)


@pytest.fixture(scope="module")
def view() -> LevelView:
    rng = np.random.default_rng(7)
    n, K, E = 23, 5, 2
    P = np.cumsum(rng.normal(scale=0.05, size=(n, K, 3)), axis=0)
    return LevelView(P, rng.normal(scale=0.1, size=(n, E, 3)), spacing=2.0)


def _reference(view: LevelView, o0, o1, i0, i1) -> np.ndarray:
    """The distance written out on interleaved xyz vectors (the definition)."""
    def norms(x):
        return np.sqrt((x[..., 0] ** 2 + x[..., 2] ** 2) + x[..., 1] ** 2)

    dv = (view.P[o1] - view.P[o0]) - view.V[np.minimum(i0, view.n - 2)]
    d = norms(dv) / view.spacing
    ra, rb = norms(view.R[o0] - view.R[i0]), norms(view.R[o1] - view.R[i1])
    return slot_distance(np.concatenate([d, ra, rb], axis=-1))


def test_pair_distance_is_the_definition_to_the_last_bit(view):
    rng = np.random.default_rng(0)
    o0, o1, i0 = (rng.integers(0, view.n, 200) for _ in range(3))
    i0 = np.minimum(i0, view.n - 2)
    got = pair_distance(view, o0, o1, i0, i0 + 1)
    np.testing.assert_array_equal(got, _reference(view, o0, o1, i0, i0 + 1))
    # known answers: an input pair against itself is 0; a jump (0 → 2) moving one of 2
    # joints by (6, 8, 0) cm more than the input's step, over spacing 2, is 5 cm on that
    # joint: ‖d‖∞ + ‖d‖₀.₅ = 0.05 + (√0.05 / 4)² over 2 joints + 2 rate errors of 0
    assert pair_distance(view, 4, 5, 4, 5) == 0.0
    P = np.zeros((3, 2, 3))
    P[2, 0] = [0.06, 0.08, 0.0]
    small = LevelView(P, np.zeros((3, 1, 3)), spacing=2.0)
    assert pair_distance(small, 0, 2, 0, 1) == pytest.approx(0.05 + 0.05 / 16, abs=1e-15)


def test_tables_hold_pair_distance_and_window_cost_is_the_same_with_them(view):
    n = view.n
    T = pair_tables(view)
    x, y = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    np.testing.assert_array_equal(T.verbatim, pair_distance(view, x, x + 1, y, y + 1))
    x, y = np.meshgrid(np.arange(n), np.arange(1, n), indexing="ij")
    np.testing.assert_array_equal(T.into[:, 1:], pair_distance(view, x, y, y - 1, y))
    x, y = np.meshgrid(np.arange(n - 1), np.arange(n), indexing="ij")
    np.testing.assert_array_equal(T.out_of[: n - 1], pair_distance(view, x, y, x, x + 1))
    # windows of a search: verbatim runs, jumps, empty slots, candidates past the ends
    rng = np.random.default_rng(1)
    W, m = 7, 300
    ov = rng.integers(0, n, (m, W))
    ov[:, 1:] = np.where(rng.random((m, W - 1)) < 0.6, np.minimum(ov[:, :-1] + 1, n - 1),
                         ov[:, 1:])
    ov[rng.random((m, W)) < 0.15] = -1
    iv = rng.integers(-2, n + 2, m)[:, None] + np.arange(-3, 4)[None, :]
    block = np.arange(-3, 4) == 0
    pw = np.exp(-0.5 * ((np.arange(W - 1) - 2.5) / 3) ** 2)
    plain, tabled = window_cost(view, ov, iv, block, pw), window_cost(view, ov, iv, block, pw, T)
    for a, b in zip(plain, tabled):
        np.testing.assert_array_equal(a, b)
    num, den, reject = plain
    assert np.isfinite(num).all() and (den >= 0).all()
    # a filled pair at the candidate whose input slot is missing rejects the row
    out = np.array([[3, 4, 5, 6, 7, 8, 9]])
    assert window_cost(view, out, np.array([[-3, -2, -1, 0, 1, 2, 3]]), block, pw)[2][0]
    assert not window_cost(view, out, out, block, pw)[2][0]
    assert window_cost(view, out, out, block, pw)[0][0] == 0.0


def test_rate_feature_table_gives_the_computed_norms(view, monkeypatch):
    # known answer: rate features 3 and 4 apart on two axes are 5 apart
    R = np.zeros((4, 1, 3))
    R[2, 0] = [3.0, 0.0, 4.0]
    small = LevelView(np.zeros((4, 1, 3)), R, spacing=1.0)
    assert small.rate_norms()[2, 0, 0] == 5.0 and small.rate_norms()[0, 2, 0] == 5.0
    rng = np.random.default_rng(0)
    o0, o1, i0 = (rng.integers(0, view.n, 300) for _ in range(3))
    i0 = np.minimum(i0, view.n - 2)
    tabled = pair_distance(view, o0, o1, i0, i0 + 1)
    monkeypatch.setattr(LevelView, "RATE_TABLE_NODES", 0)  # the computed path
    plain = LevelView(view.P, view.R, view.spacing)
    assert plain.rate_norms() is None
    np.testing.assert_array_equal(tabled, pair_distance(plain, o0, o1, i0, i0 + 1))


def test_children_tables_hold_exactly_what_a_coarser_search_reads(view):
    n = view.n
    T = pair_tables(view, out_of=False, children=True)
    assert T.partial and T.out_of is None
    full = pair_tables(view)
    x, y = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    same = (x - y) % 2 == 0
    np.testing.assert_array_equal(T.verbatim[same], full.verbatim[same])
    assert np.isnan(T.verbatim[~same]).all()
    x, y = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    odd_even = (x % 2 == 1) & (y % 2 == 0)
    np.testing.assert_array_equal(T.into[odd_even], full.into[odd_even])
    assert np.isnan(T.into[~odd_even]).all()
    # windows of children (a coarser level's finer windows) and arbitrary ones: the
    # entries not tabulated are computed, the sums are those without tables
    rng = np.random.default_rng(3)
    W, m = 8, 400
    par = rng.integers(0, n // 2, (m, W // 2))
    par[:, 1:] = np.where(rng.random((m, W // 2 - 1)) < 0.5, par[:, :-1] + 1, par[:, 1:])
    ov = (2 * par[:, :, None] + np.arange(2)[None, None, :]).reshape(m, W)
    ov[rng.random((m, W)) < 0.1] = -1
    ov[ov >= n] = -1
    odd = rng.random(m) < 0.3  # some rows not made of children
    ov[odd] = rng.integers(-1, n, (int(odd.sum()), W))
    iv = 2 * rng.integers(-1, n // 2 + 1, m)[:, None] + np.arange(-3, 5)[None, :]
    block = (np.arange(-3, 5) == 0) | (np.arange(-3, 5) == 1)
    pw = np.exp(-0.5 * ((np.arange(W - 1) - 3.0) / 3) ** 2)
    for a, b in zip(window_cost(view, ov, iv, block, pw),
                    window_cost(view, ov, iv, block, pw, T)):
        np.testing.assert_array_equal(a, b)
