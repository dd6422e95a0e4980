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
    P, R, V = view.P, view.R, view.V
    dv = (P[o[:, 1:]] - P[o[:, :-1]]) - V[np.minimum(i[:, :-1], n - 2)]
    d = np.sqrt(np.einsum("...k,...k->...", dv, dv)) / view.spacing
    ra = R[o[:, :-1]] - R[i[:, :-1]]
    rb = R[o[:, 1:]] - R[i[:, 1:]]
    ra = np.sqrt(np.einsum("...k,...k->...", ra, ra))
    rb = np.sqrt(np.einsum("...k,...k->...", rb, rb))
    dist = slot_distance(np.concatenate([d, ra, rb], axis=-1))
    w = pair_weights[None, :] * valid
    return np.sum(w * dist, axis=1), np.sum(w, axis=1), reject


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
