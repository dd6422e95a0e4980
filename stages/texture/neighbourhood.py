"""Neighbourhood distance of the synthesis (Moradoff §3.5–3.7).

What the search compares at one level of the input pyramid
(:class:`LevelView`, built by :func:`level_view`) and how an output window is
compared with an input window (:func:`window_cost`).  A slot pair ``(s, s+1)``
is compared on the *velocities* between the two nodes: the joint-position
velocities of the 3-D pose representation (so a jump of pose shows as a wrong
velocity) and the root's rate features (horizontal velocity, yaw rate ×
``YAW_LEVER``).  The per-slot distance of the vector ``d`` of per-joint velocity
errors is ``‖d‖∞ + ‖d‖₀.₅`` with ``‖d‖₀.₅ = (mean_j √d_j)²`` (the normalised
0.5-norm, :func:`slot_distance`).  Slot pairs are weighted by a Gaussian of
their distance from the centre (:func:`slot_pair_weights`); empty slots (not yet
synthesised, or outside the input) have weight 0 and the weights are
renormalised by the caller.  A level's cost unit (``LevelView.unit``) is the
median distance between consecutive input velocities.

How the three levels of the tree are combined and which candidates are
rejected is :meth:`mocapflow.stages.texture.search.LevelSearch.cost_rows`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "YAW_LEVER",
    "LevelView",
    "level_view",
    "slot_pair_weights",
    "slot_distance",
    "PairTables",
    "pair_tables",
    "window_cost",
]

#: Length (metres) turning a yaw rate (rad per frame) into a velocity.
YAW_LEVER = 1.0


@dataclass
class LevelView:
    """What the search compares at one level of the input pyramid.

    Attributes
    ----------
    P : (n, K, 3) float ndarray
        Joint positions of the heading-free pose.
    R : (n, E, 3) float ndarray
        Rate features per fine frame (root velocity, yaw rate × 1 m).
    spacing : float
        Fine frames between consecutive nodes (``2**l``).
    unit : float
        Cost unit: median per-slot distance between consecutive velocities.
    V : (n - 1, K, 3) float ndarray
        Input joint velocities ``P[i+1] - P[i]`` (derived).
    """

    P: np.ndarray
    R: np.ndarray
    spacing: float
    unit: float = 1.0

    def __post_init__(self) -> None:
        self.V = np.diff(self.P, axis=0) if self.P.shape[0] > 1 else np.zeros_like(self.P)

    @property
    def n(self) -> int:
        """Number of input nodes."""
        return self.P.shape[0]


def slot_distance(d: np.ndarray) -> np.ndarray:
    """``‖d‖∞ + ‖d‖₀.₅`` over the last axis (``‖d‖₀.₅ = (mean √d)²``).

    Parameters
    ----------
    d : (..., K) float ndarray
        Non-negative per-joint errors.

    Returns
    -------
    (...) float ndarray
    """
    return d.max(axis=-1) + np.square(np.sqrt(d).mean(axis=-1))


def level_view(level, spacing: float) -> LevelView:
    """Comparison features of one pyramid level.

    Parameters
    ----------
    level : PyramidLevel
    spacing : float
        ``2**l``.

    Returns
    -------
    LevelView
    """
    n = level.n_nodes
    R = np.zeros((n, 2, 3))
    R[:, 0, 0] = level.velocity[:, 0]
    R[:, 0, 2] = level.velocity[:, 1]
    R[:, 1, 0] = level.yaw_rate * YAW_LEVER
    view = LevelView(np.asarray(level.positions, dtype=np.float64), R, float(spacing))
    if n >= 3:
        v = np.diff(view.P, axis=0) / spacing
        dv = np.linalg.norm(np.diff(v, axis=0), axis=-1)
        dr = np.linalg.norm(np.diff(R, axis=0), axis=-1)[1:]
        unit = float(np.median(slot_distance(np.concatenate([dv, dr, dr], axis=-1))))
        view.unit = unit if unit > 0 else 1.0
    return view


def window_cost(
    view: LevelView,
    ov: np.ndarray,
    iv: np.ndarray,
    block: np.ndarray,
    pair_weights: np.ndarray,
    tables: PairTables | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted velocity distance between output windows and input windows.

    Parameters
    ----------
    view : LevelView
    ov : (m, W) int ndarray
        Input node copied at each output slot (-1: empty).
    iv : (m, W) int ndarray
        Input node at each slot of the candidate's input window (may fall
        outside ``[0, n)``: then empty).
    block : (W,) bool ndarray
        Slots holding the candidate itself.
    pair_weights : (W - 1,) float ndarray
        Weight of each slot pair.
    tables : PairTables, optional
        :func:`pair_tables` of ``view``: pairs that play the input forwards, or jump
        into or out of the input pair, are looked up instead of computed (same
        values; worth it where a level is searched over all its nodes).

    Returns
    -------
    num : (m,) float ndarray
        Weighted sum of per-pair distances over valid pairs.
    den : (m,) float ndarray
        Sum of the weights of valid pairs.
    reject : (m,) bool ndarray
        A pair touching the candidate is filled in the output but missing in the input.
    """
    n = view.n
    out_ok = ov >= 0
    in_ok = (iv >= 0) & (iv < n)
    o = np.clip(ov, 0, n - 1)
    i = np.clip(iv, 0, n - 1)
    both_out = out_ok[:, 1:] & out_ok[:, :-1]
    valid = both_out & in_ok[:, 1:] & in_ok[:, :-1]
    touch = block[1:] | block[:-1]
    reject = np.any(both_out & ~valid & touch[None, :], axis=1)
    o0, o1, i0, i1 = o[:, :-1], o[:, 1:], i[:, :-1], i[:, 1:]
    # computed only where it counts: valid pairs that are not the input pair itself
    # (distance exactly 0); with tables, the pairs they hold are looked up
    dist = np.zeros(o0.shape)
    need = valid & ((o0 != i0) | (o1 != i1))
    if tables is not None:  # valid pairs have i1 = i0 + 1, both inside the input
        for sel, T, x, y in (
            (o1 == o0 + 1, tables.verbatim, o0, i0),
            (o1 == i1, tables.into, o0, i1),
            (o0 == i0, tables.out_of, o0, o1),
        ):
            sel = need & sel
            dist[sel] = T[x[sel], y[sel]]
            need &= ~sel
    if need.any():
        dist[need] = pair_distance(view, o0[need], o1[need], i0[need], i1[need])
    w = pair_weights[None, :] * valid
    return np.sum(w * dist, axis=1), np.sum(w, axis=1), reject


def pair_distance(view: LevelView, o0, o1, i0, i1) -> np.ndarray:
    """Per-slot distance of output pairs ``(o0, o1)`` to input pairs ``(i0, i1)``.

    Parameters
    ----------
    view : LevelView
    o0, o1, i0, i1 : int ndarrays
        Input nodes in ``[0, n)``, broadcastable to one shape.

    Returns
    -------
    float ndarray
        :func:`slot_distance` of the joint velocity errors ``‖(P[o1] - P[o0]) -
        V[i0]‖ / spacing`` and the rate-feature errors at both nodes.
    """
    P, R, V = view.P, view.R, view.V
    dv = (P[o1] - P[o0]) - V[np.minimum(i0, view.n - 2)]
    d = np.sqrt(np.einsum("...k,...k->...", dv, dv)) / view.spacing
    ra = R[o0] - R[i0]
    rb = R[o1] - R[i1]
    ra = np.sqrt(np.einsum("...k,...k->...", ra, ra))
    rb = np.sqrt(np.einsum("...k,...k->...", rb, rb))
    return slot_distance(np.concatenate([d, ra, rb], axis=-1))


@dataclass
class PairTables:
    """:func:`pair_distance` tabulated for the pairs a search mostly compares.

    Attributes
    ----------
    verbatim : (n - 1, n - 1) float ndarray
        Output pair ``(x, x + 1)`` against input pair ``(y, y + 1)``.
    into : (n, n) float ndarray
        Output pair ``(x, y)`` against input pair ``(y - 1, y)`` (a jump into ``y``;
        column 0 unused).
    out_of : (n, n) float ndarray
        Output pair ``(x, y)`` against input pair ``(x, x + 1)`` (a jump out of ``x``;
        row ``n - 1`` unused).
    """

    verbatim: np.ndarray
    into: np.ndarray
    out_of: np.ndarray


def _tabulate(f, n: int) -> np.ndarray:
    """``T[x, y] = f(x[:, None], y[None, :])`` for ``x, y < n``, in row blocks."""
    T = np.empty((n, n))
    x = np.arange(n)
    rows = max(1, 1_000 // max(n, 1))  # small blocks: (rows, n, J, 3) temporaries stay in cache
    for a in range(0, n, rows):
        xs, ys = np.broadcast_arrays(x[a : a + rows, None], x[None, :])
        T[a : a + rows] = f(xs, ys)
    return T


def pair_tables(view: LevelView) -> PairTables:
    """The :class:`PairTables` of a level (``3 n²`` distances), for :func:`window_cost`.

    Parameters
    ----------
    view : LevelView

    Returns
    -------
    PairTables
    """
    n = view.n
    top = n - 1  # clamp: entries of pairs outside the input are never read
    return PairTables(
        verbatim=_tabulate(lambda x, y: pair_distance(view, x, x + 1, y, y + 1), n - 1),
        into=_tabulate(lambda x, y: pair_distance(view, x, y, np.maximum(y - 1, 0), y), n),
        out_of=_tabulate(
            lambda x, y: pair_distance(view, x, y, x, np.minimum(x + 1, top)), n),
    )


def slot_pair_weights(offsets: np.ndarray, centre: float, sigma: float) -> np.ndarray:
    """Gaussian weight of each slot pair of a window.

    Parameters
    ----------
    offsets : (W,) int ndarray
        Slot offsets of the window.
    centre : float
        Offset the weights peak at (0: a node; 0.5: a pair of children).
    sigma : float

    Returns
    -------
    (W - 1,) float ndarray
    """
    mid = 0.5 * (offsets[1:] + offsets[:-1]) - centre
    return np.exp(-0.5 * (mid / sigma) ** 2)
