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

from mocapflow.stages.motion.rotations import quat_to_6d

__all__ = [
    "YAW_LEVER",
    "LevelView",
    "level_view",
    "slot_pair_weights",
    "slot_distance",
    "PairTables",
    "pair_tables",
    "pose_distance",
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
    rotations : (n, J, 6) float ndarray, optional
        6-D rotations (:func:`~mocapflow.stages.motion.rotations.quat_to_6d`) of the
        joints below the root, the pose :func:`pose_distance` compares (every bone's
        orientation, leaves included: a hand or thumb turned shows on a skinned
        character though no joint position moves); without them it compares ``P``.
    V : (n - 1, K, 3) float ndarray
        Input joint velocities ``P[i+1] - P[i]`` (derived).
    """

    P: np.ndarray
    R: np.ndarray
    spacing: float
    unit: float = 1.0
    rotations: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.V = np.diff(self.P, axis=0) if self.P.shape[0] > 1 else np.zeros_like(self.P)
        pose = self.P if self.rotations is None else self.rotations
        #: (n, D) poses flattened and divided by √(joints), for :func:`pose_distance`
        self.Pf = np.ascontiguousarray(pose.reshape(pose.shape[0], -1)
                                       / np.sqrt(max(pose.shape[1], 1)))
        self._rate_norms: np.ndarray | None = None

    #: Largest level (nodes) whose :meth:`rate_norms` are tabulated (``n² E`` floats): a
    #: synthesis compares some ``100 n`` pairs per level, so the table pays up to ~160.
    RATE_TABLE_NODES = 160

    def rate_norms(self) -> np.ndarray | None:
        """``(n, n, E)`` table of ``‖R[a] - R[b]‖`` per rate feature (built once), or
        ``None`` above :attr:`RATE_TABLE_NODES` nodes."""
        if self._rate_norms is None and self.n <= self.RATE_TABLE_NODES:
            self._rate_norms = _norms(self.R[:, None] - self.R[None, :])
        return self._rate_norms

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
    # the mean as sum / count: what ndarray.mean computes, without its wrapper
    root_mean = np.add.reduce(np.sqrt(d), axis=-1) / d.shape[-1]
    return np.maximum.reduce(d, axis=-1) + root_mean * root_mean


def pose_distance(view: LevelView, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """RMS over joints of the distance between the poses of nodes ``a`` and ``b``: of
    their 6-D rotations (``view.rotations``, as :func:`level_view` sets them), else of
    their positions (metres).

    Parameters
    ----------
    view : LevelView
    a : (m,) int ndarray
        Nodes in ``[0, n)``.
    b : (n_b,) int ndarray
        Nodes in ``[0, n)``.

    Returns
    -------
    (m, n_b) float ndarray
        ``sqrt(mean_j ‖X[a, j] - X[b, j]‖²)`` of every pair (``X`` the rotations or
        ``P``), in Gram form (one matrix product).
    """
    X = view.Pf
    sq = np.einsum("ij,ij->i", X, X)
    d2 = sq[a][:, None] + sq[b][None, :] - 2.0 * (X[a] @ X[b].T)
    return np.sqrt(np.maximum(d2, 0.0))


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
    view = LevelView(np.asarray(level.positions, dtype=np.float64), R, float(spacing),
                     rotations=quat_to_6d(level.rotations[:, 1:]))
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
        values; worth it where a level is searched over all its nodes), those of a
        table it does not hold (``None``) computed.

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
    # few, whole-array NumPy calls: this runs once per searched node and level
    out_ok = ov >= 0
    in_ok = (iv >= 0) & (iv < n)
    both_out = out_ok[:, 1:] & out_ok[:, :-1]
    in_pair = in_ok[:, 1:] & in_ok[:, :-1]
    valid = both_out & in_pair
    touch = block[1:] | block[:-1]
    reject = np.logical_or.reduce(both_out & ~in_pair & touch, axis=1)  # filled, not valid
    # only valid pairs are read below: there iv lies inside the input and ov, a filled
    # slot, holds an input node (capped at the last one, as a guard)
    o = np.minimum(ov, n - 1)
    o0, o1, i0, i1 = o[:, :-1], o[:, 1:], iv[:, :-1], iv[:, 1:]
    # computed only where it counts: valid pairs that are not the input pair itself
    # (distance exactly 0); with tables, the pairs they hold are looked up
    dist = np.zeros(o0.shape)
    need = valid & ((o0 != i0) | (o1 != i1))
    if tables is not None:  # valid pairs have i1 = i0 + 1, both inside the input
        for T, sel, x, y in (
            (tables.verbatim, o1 == o0 + 1, o0, i0),
            (tables.into, o1 == i1, o0, i1),
            (tables.out_of, o0 == i0, o0, o1),
        ):
            if T is None:  # not tabulated: computed below
                continue
            sel &= need
            if sel.any():
                got = T[x[sel], y[sel]]
                if tables.partial:  # entries not tabulated (nan) stay needed
                    sel[sel] = ~np.isnan(got)
                    got = got[~np.isnan(got)]
                dist[sel] = got
                need &= ~sel
    if need.any():
        dist[need] = pair_distance(view, o0[need], o1[need], i0[need], i1[need])
    w = pair_weights * valid
    return np.add.reduce(w * dist, axis=1), np.add.reduce(w, axis=1), reject


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
    dv = (P.take(o1, axis=0) - P.take(o0, axis=0)) - V.take(np.minimum(i0, view.n - 2), axis=0)
    q = dv * dv  # _norms3's sum of squares, in its order
    d = np.sqrt((q[..., 0] + q[..., 2]) + q[..., 1]) / view.spacing
    RN = view.rate_norms()
    if RN is None:
        r0, r1 = _norms(R[o0] - R[i0]), _norms(R[o1] - R[i1])
    else:  # the same norms, looked up
        r0, r1 = RN[o0, i0], RN[o1, i1]
    return slot_distance(np.concatenate([d, r0, r1], axis=-1))


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
    out_of : (n, n) float ndarray or None
        Output pair ``(x, y)`` against input pair ``(x, x + 1)`` (a jump out of ``x``;
        row ``n - 1`` unused); ``None`` when not tabulated (:func:`window_cost` then
        computes those pairs).
    """

    verbatim: np.ndarray
    into: np.ndarray
    out_of: np.ndarray | None
    #: Entries not tabulated are ``nan`` (:func:`window_cost` computes those pairs).
    partial: bool = False


def _norms3(x0: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Euclidean norms of 3-vectors given as component arrays.

    One summation order, ``(x0² + x2²) + x1²``, for every distance of the search (the
    tables and :func:`pair_distance` agree to the last bit); it is the order in which
    ``np.einsum("...k,...k->...")`` summed a last axis of 3 on the machine this was
    measured on (NumPy 2.4, x86-64), so the costs are those the search had with einsum,
    about three times faster on contiguous component arrays.
    """
    return np.sqrt((x0 * x0 + x2 * x2) + x1 * x1)


def _norms(x: np.ndarray) -> np.ndarray:
    """:func:`_norms3` over the last axis of ``(..., 3)`` vectors."""
    return _norms3(x[..., 0], x[..., 1], x[..., 2])


def pair_tables(view: LevelView, out_of: bool = True, children: bool = False) -> PairTables:
    """The :class:`PairTables` of a level (up to ``3 n²`` distances), for :func:`window_cost`.

    The same values as :func:`pair_distance` of each pair, computed by table: the
    output velocity of a verbatim pair is the input's ``V[x]``, a jump's ``P[y] -
    P[x]`` is shared by ``into`` and ``out_of``, the joint velocity errors are taken
    per coordinate on contiguous arrays, and the rate-feature errors are one ``(n, n,
    E)`` table of ``‖R[a] - R[b]‖`` (a pair's own node gives 0).

    Parameters
    ----------
    view : LevelView
    out_of : bool
        Tabulate ``out_of`` too (False: ``None``; the coarsest search reads about one
        in 500 of its entries, so it computes those pairs instead).
    children : bool
        Only the entries the next coarser level's search reads (its finer windows hold
        the children ``2 p``, ``2 p + 1`` of its nodes, and so do the candidates'
        windows ``2 c + k``): ``verbatim`` where ``x`` and ``y`` have one parity,
        ``into`` at odd ``x`` and even ``y``, the rest ``nan`` (``partial``; no
        ``out_of``).

    Returns
    -------
    PairTables
    """
    n = view.n
    R, s = view.R, view.spacing
    Pc = np.ascontiguousarray(np.moveaxis(view.P, -1, 0))  # (3, n, K): one array per axis
    Vc = np.ascontiguousarray(np.moveaxis(view.V, -1, 0))
    top = n - 1  # clamp: entries of pairs outside the input are never read
    y = np.arange(n)
    RN = view.rate_norms()  # (n, n, E): RN[a, b] = ‖R[a] - R[b]‖ per feature
    if RN is None:
        RN = _norms(R[:, None] - R[None, :])
    zero = np.zeros(RN.shape[2:])  # (E,)
    V_into = Vc[:, np.minimum(np.maximum(y - 1, 0), n - 2)]  # input pair (y - 1, y)
    if children:  # entries not written stay nan
        verbatim, into = np.full((n - 1, n - 1), np.nan), np.full((n, n), np.nan)
    else:
        verbatim, into = np.empty((n - 1, n - 1)), np.empty((n, n))
    jumps_out = np.empty((n, n)) if out_of and not children else None
    # (rows, verbatim columns, into / out_of columns) of each class of entries
    if children:
        classes = [(y[0::2], y[0 : n - 1 : 2], y[:0]), (y[1::2], y[1 : n - 1 : 2], y[0::2])]
    else:
        classes = [(y, y[: n - 1], y)]
    # row blocks: (rows, n, K) temporaries of about 60,000 values (cache-sized; measured)
    rows = max(1, 60_000 // max(n * view.P.shape[1], 1))
    for xs, cv, ci in classes:
        for a in range(0, xs.size, rows):
            x = xs[a : a + rows]
            xv = x[x < n - 1]
            if xv.size and cv.size:  # output pair (x, x + 1) = V[x] against (y, y + 1)
                d = _norms3(*(Vc[c, xv][:, None] - Vc[c, cv][None, :] for c in range(3))) / s
                verbatim[np.ix_(xv, cv)] = slot_distance(np.concatenate(
                    [d, RN[xv][:, cv], RN[xv + 1][:, cv + 1]], axis=-1))
            if not ci.size:
                continue
            D = [Pc[c, ci][None, :] - Pc[c, x][:, None] for c in range(3)]  # output pair (x, y)
            z = np.broadcast_to(zero, (x.size, ci.size) + zero.shape)
            d = _norms3(*(D[c] - V_into[c, ci][None, :] for c in range(3))) / s
            into[np.ix_(x, ci)] = slot_distance(np.concatenate(
                [d, RN[x][:, np.maximum(ci - 1, 0)], z], axis=-1))
            if jumps_out is None:
                continue
            xn = np.minimum(x, n - 2)
            d = _norms3(*(D[c] - Vc[c, xn][:, None] for c in range(3))) / s
            rb = RN[ci[None, :], np.minimum(x + 1, top)[:, None]]  # ‖R[y] - R[x + 1]‖
            jumps_out[np.ix_(x, ci)] = slot_distance(np.concatenate([d, z, rb], axis=-1))
    return PairTables(verbatim=verbatim, into=into, out_of=jumps_out, partial=children)


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
