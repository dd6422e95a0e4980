"""Merging unlabelled fragments into missing markers (Park & Hodgins 2006, §4.2).

:func:`merge_fragments` runs rounds (:func:`_merge_rounds`): the rigid predictions
of the missing samples in the frames that need them (:func:`_predict_round`, by
:func:`mocapflow.stages.skin.predict.predict_missing`), every unmerged fragment
judged against them (:func:`_judge_round`, :func:`_judge_fragment`: the entry test
against ``ε₁ = α₁·d̄``, the tube ``ε₂ = α₂·d̄`` over the fragment, the mean
distance and the ambiguity tests; :func:`_tolerances`; beyond the paper, an
unmerged fragment in the same frames as close to the prediction makes the merge
ambiguous: :func:`_rival_fragment`, and so does a missing marker without a prediction
close enough to the chosen one: :func:`_blind_rival`, or a missing marker close enough
with the chosen one seen as another unmerged fragment where the swap puts it:
:func:`_swap_rival`), and the claims merged, closest first (:func:`_merge_claims`).
Before and after the rounds, fragments that continue a marker's trajectory across a
break or a gap of at most :func:`bridge_frames` (8 frames, 67 ms above 120 Hz) are
merged by continuity (:func:`continue_breaks`, beyond the paper).  The fragments the
rounds leave are judged again against the filled trajectories, jointly, in
:mod:`mocapflow.stages.skin.assign` (beyond the paper).  See
:mod:`mocapflow.stages.skin.clean` for the whole procedure and where it goes beyond
the paper.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from mocapflow.pipeline import Context
from mocapflow.stages.motion.absolute_orientation import absolute_orientation_batch
from mocapflow.stages.skin.predict import (
    MIN_NEIGHBOURS,
    RIGID_ANCHOR,
    _neighbour_fit,
    _predict_parallel,
    finite_rows,
    gather_samples,
    local_targets,
)
from mocapflow.stages.skin.surface import MarkerSurface

#: A fragment is merged only if every other missing marker's prediction is at
#: least this many times farther from it (on average over its frames).
AMBIGUITY_RATIO = 3.0

#: Judging against hole-filled (PCA) estimates instead of rigid predictions: a
#: fragment's mean distance must stay below this fraction of ε₁ ...
PCA_MEAN_TOLERANCE = 0.6
#: ... and every other missing marker within :data:`NEAR_RADIUS` mean neighbour
#: distances of the chosen one (in the reference pose) must have its estimate at
#: least this many times farther from the fragment.  The estimate of such a close
#: marker may be far off (few members, long unobserved) while the chosen marker's
#: lies on the fragment, so the plain :data:`AMBIGUITY_RATIO` is not enough.
#: On simulated 350-marker captures (seed 0) the wrong merges against hole-filled
#: estimates had mean distances of 0.71–0.86 ε₁ (correct ones: 99 % below
#: 0.67 ε₁) or a close marker's estimate only 4.0–5.9 times farther.
PCA_NEAR_RATIO = 6.5
NEAR_RADIUS = 1.0
#: Fragments shorter than :data:`ASSIGN_MIN_FRAMES` frames (one or two samples: no
#: tube to check) must lie within this fraction of ε₁ of the prediction on average.
#: On the simulated range-of-motion capture (seed 0) a single-frame fragment merged
#: 0.77 ε₁ from the rigid prediction of the wrong marker.
SHORT_MEAN_TOLERANCE = 0.5
#: Fragments shorter than this (frames) merge against the filling
#: (:func:`~mocapflow.stages.skin.assign.assign_fragments`) only by continuing an
#: exact gap: the two wrong merges of the joint assignment on the simulated
#: range-of-motion capture (seed 0, 1 of 173) were single-frame fragments 6.6 and
#: 11.2 mm from the wrong marker's estimate (fill error there: 55 mm mean).
ASSIGN_MIN_FRAMES = 3


# --------------------------------------------------------------------------- merging (§4.2)


def nearest_marker_distance(reference: np.ndarray) -> np.ndarray:
    """``(M,)`` distance from each marker to the nearest other one in the reference pose.

    NaN for markers without reference position.
    """
    out = np.full(len(reference), np.nan)
    ok = np.flatnonzero(np.isfinite(reference).all(1))
    if len(ok) >= 2:
        d, _ = cKDTree(reference[ok]).query(reference[ok], k=2)
        out[ok] = d[:, 1]
    return out



class PredictionIndex:
    """Per-round look-up tables over the ``(F, M)`` sample grid for contiguous fragments.

    Parameters
    ----------
    available : (F, M) bool ndarray
        Samples with data (a marker is a candidate only if missing in all frames).
    predicted : (F, M) bool ndarray
        Samples with a (trusted) prediction.
    like : PredictionIndex, optional
        An index of the same ``available`` (its counts are shared, not counted again).
    """

    def __init__(self, available: np.ndarray, predicted: np.ndarray,
                 like: PredictionIndex | None = None) -> None:
        zero = np.zeros((1, predicted.shape[1]), dtype=np.int32)
        self.n_available = (like.n_available if like is not None else
                            np.concatenate([zero, np.cumsum(available, 0, dtype=np.int32)]))
        self.n_predicted = np.concatenate([zero, np.cumsum(predicted, 0, dtype=np.int32)])
        self._predicted = predicted

    @functools.cached_property
    def next_predicted(self) -> np.ndarray:
        """``(F, M)`` int: the first frame at or after each with a prediction (``F``: none)."""
        F = len(self._predicted)
        nxt = np.where(self._predicted, np.arange(F)[:, None], F)
        return np.minimum.accumulate(nxt[::-1], axis=0)[::-1]

    def free(self, first: int, last: int) -> np.ndarray:
        """``(M,)`` bool: markers without data in frames ``first..last``."""
        return self.n_available[last + 1] == self.n_available[first]


def _is_run(T: np.ndarray) -> bool:
    return len(T) > 0 and int(T[-1]) - int(T[0]) + 1 == len(T)


@functools.lru_cache(maxsize=4096)
def _spread(n: int) -> np.ndarray:
    """Up to 16 indices spread evenly over ``0..n-1`` (read-only ``(k,)`` int array): the
    frames of a fragment the quick rival and screening tests look at."""
    sub = np.unique(np.linspace(0, n - 1, min(n, 16)).round().astype(int))
    sub.flags.writeable = False
    return sub


def _nonzero(a: np.ndarray) -> np.ndarray:
    """``np.flatnonzero`` of a 1-D array, without its wrappers (the hot loops call it)."""
    return a.nonzero()[0]


def _norm(x: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(x, axis=-1)`` of a real array (the same operations, so the same
    bits) without its checks: the hot loops call it on small arrays."""
    return np.sqrt(np.add.reduce(x * x, axis=-1))


def _distances(frag: np.ndarray, T: np.ndarray, m: np.ndarray, E: np.ndarray):
    """Distances ``(|T|, len(m))`` of the fragment to predictions (NaN where none)."""
    return _norm(frag[:, None] - E[T[:, None], m[None]])


def _nan_mean(d: np.ndarray) -> np.ndarray:
    """``np.nanmean(d, axis=0)`` (the same operations, so the same bits), quietly: NaN
    for all-NaN columns."""
    nan = np.isnan(d)
    n = (~nan).sum(0, dtype=np.intp)
    return np.divide(np.where(nan, 0.0, d).sum(0), n, out=np.full(n.shape, np.nan), where=n > 0)


def _nan_stats(dn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(np.nanmax, np.nanmean)`` of ``dn`` over axis 0, quietly (NaN: all-NaN column)."""
    return np.fmax.reduce(dn, axis=0), _nan_mean(dn)


def _candidate_stats_dense(frag: np.ndarray, T: np.ndarray, cands: np.ndarray, E: np.ndarray):
    """Entry, max and mean distance of the fragment to every candidate's predictions.

    Returns ``None`` when no candidate has predictions in at least half of the
    fragment's frames, else ``(m_c, d_entry, d_max, d_mean, column)``: the
    checkable candidates (a subset of ``cands``, in its order), their ``(C,)``
    statistics, and ``column(c)`` the ``(|T|,)`` distances to ``m_c[c]`` (NaN where
    not predicted).
    """
    d = _distances(frag, T, cands, E)  # (|T|, C)
    have = np.isfinite(d)
    checkable = have.sum(0) >= max(1, int(np.ceil(0.5 * len(T))))
    if not checkable.any():
        return None
    cc = _nonzero(checkable)
    dc, hc = d[:, cc], have[:, cc]
    first = np.argmax(hc, axis=0)
    d_entry = dc[first, np.arange(len(cc))]
    dn = np.where(hc, dc, np.nan)
    d_max, d_mean = _nan_stats(dn)
    return cands[cc], d_entry, d_max, d_mean, lambda c: dn[:, c]


def _candidate_stats(frag: np.ndarray, T: np.ndarray, cands: np.ndarray, E: np.ndarray,
                     eps1: np.ndarray, index: PredictionIndex,
                     entry: tuple[np.ndarray, np.ndarray] | None = None):
    """:func:`_candidate_stats_dense` for a fragment over contiguous frames ``T``.

    Counts and entry samples come from ``index`` (or ``entry``: the checkable
    candidates and their entry distances, already found by :func:`_entry_screen`);
    the whole-fragment statistics are computed only for candidates that pass the
    entry test (``d_entry < ε₁``, a condition of every merge and of the later
    rejection reasons), the others get NaN.  Same values as the dense version.
    """
    if not _is_run(T):
        return _candidate_stats_dense(frag, T, cands, E)
    a, b = int(T[0]), int(T[-1])
    if entry is not None:
        m_c, d_entry = entry
    else:
        count = index.n_predicted[b + 1, cands] - index.n_predicted[a, cands]
        checkable = count >= max(1, int(np.ceil(0.5 * len(T))))
        if not checkable.any():
            return None
        m_c = cands[_nonzero(checkable)]
        first = index.next_predicted[a, m_c]
        d_entry = _norm(frag[first - a] - gather_samples(E, first, m_c))
    d_max = np.full(len(m_c), np.nan)
    d_mean = np.full(len(m_c), np.nan)
    near = _nonzero(d_entry < eps1[m_c])
    if len(near):
        d = _norm(frag[:, None] - E[a:b + 1, m_c[near]])
        d_max[near], d_mean[near] = _nan_stats(d)

    def column(c: int) -> np.ndarray:
        return _norm(frag - E[a:b + 1, m_c[c]])

    return m_c, d_entry, d_max, d_mean, column


#: The verdicts :func:`_judge_fragment` and its batched screen :func:`_entry_screen` share.
OVERLAPS_EVERY_MARKER = "overlaps every marker (no marker is missing in all its frames)"
NO_PREDICTION = (f"no prediction: candidate markers have fewer than {MIN_NEIGHBOURS} "
                 "reliable neighbours in its frames")


def _entry_rejection(d_entry: float, eps1: float, label: str) -> dict[str, Any]:
    """The verdict on a fragment whose nearest candidate ``label`` (relative to ε₁) is
    ``d_entry`` (m) from it at its first predicted frame, beyond ``eps1``."""
    mm = 1000.0
    return {"reason": f"entry {d_entry * mm:.1f} mm from the prediction of nearest marker "
                      f"{label} > eps1 {eps1 * mm:.1f} mm",
            "nearest": label, "entry_mm": round(float(d_entry * mm), 2)}


def _entry_screen(fragments: np.ndarray, frames_of: list[np.ndarray], us: list[int],
                  index: PredictionIndex, E: np.ndarray, eps1: np.ndarray, usable: np.ndarray,
                  labels: list[str]) -> tuple[np.ndarray, dict[int, tuple], dict[int, dict]]:
    """:func:`_judge_fragment`'s first tests for many fragments over contiguous frames at once.

    For fragments ``us`` (``(n,)``, each over contiguous frames), the markers missing
    in all their frames (and ``usable``), the candidates predicted (``index``) in at
    least half of them, and the entry distance of each candidate (its first
    predicted sample in ``E`` to the fragment's sample there).  A fragment no
    candidate of which passes the entry test (``< ε₁``) gets its verdict here, the
    one :func:`_judge_fragment` gives it (the same values, from one gather for all).

    Returns
    -------
    free : (n, M) bool ndarray
        The markers missing in all of each fragment's frames, ``usable`` ones only.
    entries : dict
        ``{fragment: (markers, distances)}`` for the fragments with a candidate within
        ``ε₁`` (:func:`_judge_fragment` decides them): their checkable candidates in
        increasing order and the ``(C,)`` entry distances.
    verdicts : dict
        ``{fragment: verdict}`` for the others.
    """
    us_a = np.asarray(us, dtype=np.intp)
    a = np.array([frames_of[u][0] for u in us], dtype=np.intp)
    b = np.array([frames_of[u][-1] for u in us], dtype=np.intp)
    free = (index.n_available[b + 1] == index.n_available[a]) & usable  # (n, M)
    need = np.maximum(1, np.ceil(0.5 * (b - a + 1)).astype(np.intp))
    checkable = free & (index.n_predicted[b + 1] - index.n_predicted[a] >= need[:, None])
    ii, mm_ = np.nonzero(checkable)  # per fragment, markers in increasing order
    first = index.next_predicted[a[ii], mm_]
    d_entry = _norm(gather_samples(fragments, first, us_a[ii]) - gather_samples(E, first, mm_))
    e1 = eps1[mm_]
    entered = np.zeros(len(us), dtype=bool)
    entered[ii[d_entry < e1]] = True
    bounds = np.searchsorted(ii, np.arange(len(us) + 1))
    entries = {us[i]: (mm_[bounds[i]:bounds[i + 1]], d_entry[bounds[i]:bounds[i + 1]])
               for i in _nonzero(entered)}
    verdicts: dict[int, dict[str, Any]] = {}
    # the nearest candidate (relative to ε₁) of each fragment: its first minimum, as
    # np.argmin (the first NaN if any)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = d_entry / e1
    rel = np.where(np.isnan(rel), -np.inf, rel)
    has = _nonzero(bounds[1:] > bounds[:-1])  # fragments with a checkable candidate
    low = np.full(len(us), np.inf)
    low[has] = np.minimum.reduceat(rel, bounds[has]) if len(has) else low[has]
    at_low = _nonzero(rel == low[ii])
    at_low = at_low[np.r_[True, ii[at_low][1:] != ii[at_low][:-1]]] if len(at_low) else at_low
    nearest = dict(zip(ii[at_low].tolist(), at_low.tolist()))
    for i in _nonzero(~entered):
        u = us[i]
        k = nearest.get(int(i))
        if k is not None:
            verdicts[u] = _entry_rejection(d_entry[k], e1[k], labels[int(mm_[k])])
        elif free[i].any():
            verdicts[u] = {"reason": NO_PREDICTION}
        else:
            verdicts[u] = {"reason": OVERLAPS_EVERY_MARKER}
    return free, entries, verdicts


def _judge_fragment(
    frag: np.ndarray,
    T: np.ndarray,
    free: np.ndarray,
    E: np.ndarray,
    E_all: np.ndarray,
    eps1: np.ndarray,
    eps2: np.ndarray,
    labels: list[str],
    index: PredictionIndex | None = None,
    *,
    mean_tolerance: float = 1.0,
    near: np.ndarray | None = None,
    near_ratio: float = AMBIGUITY_RATIO,
    entry: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Decide one fragment against the predictions of the markers missing in all its frames.

    ``index`` (for fragments over contiguous frames) avoids computing distances
    to candidates that cannot pass the entry test.  ``mean_tolerance``: the mean
    distance must be below ``mean_tolerance · ε₁`` (:data:`SHORT_MEAN_TOLERANCE` at most
    for fragments shorter than :data:`ASSIGN_MIN_FRAMES`).  ``near`` (``(M, M)`` bool,
    markers close to each other in the reference pose): other missing markers
    near the chosen one are rivals unless ``near_ratio`` times farther (instead
    of :data:`AMBIGUITY_RATIO`).  ``entry`` (with ``index``): the checkable candidates
    and their ``(C,)`` entry distances when :func:`_entry_screen` has them.

    Returns ``{"marker", "entry", "max", "mean"}`` for a merge, else
    ``{"reason", ...}`` (and ``"conflict"`` for ambiguities).
    """
    mm = 1000.0
    cands = _nonzero(free)
    if len(cands) == 0:
        return {"reason": OVERLAPS_EVERY_MARKER}
    stats = (_candidate_stats(frag, T, cands, E, eps1, index, entry) if index is not None
             else _candidate_stats_dense(frag, T, cands, E))
    if stats is None:
        return {"reason": NO_PREDICTION}
    m_c, d_entry, d_max, d_mean, column = stats
    e1, e2 = eps1[m_c], eps2[m_c]
    if len(T) < ASSIGN_MIN_FRAMES:
        mean_tolerance = min(mean_tolerance, SHORT_MEAN_TOLERANCE)
    ok = (d_entry < e1) & (d_max < e2) & (d_mean < mean_tolerance * e1)
    if not ok.any():
        c = int(np.argmin(d_entry / e1))
        m = int(m_c[c])
        if d_entry[c] >= e1[c]:
            return _entry_rejection(d_entry[c], e1[c], labels[m])
        if d_max[c] < e2[c]:
            why = (f"mean distance {d_mean[c] * mm:.1f} mm to the prediction of {labels[m]} "
                   f"> {mean_tolerance:g} eps1 {mean_tolerance * e1[c] * mm:.1f} mm")
        else:
            bad = int(T[np.nanargmax(column(c))])
            why = (f"leaves the eps2 tube of {labels[m]}: {d_max[c] * mm:.1f} mm > "
                   f"{e2[c] * mm:.1f} mm at frame {bad}")
        return {"reason": why, "nearest": labels[m], "entry_mm": round(float(d_entry[c] * mm), 2)}
    okc = _nonzero(ok)
    okc = okc[np.argsort(d_mean[okc])]
    c0 = okc[0]
    m = int(m_c[c0])
    if len(okc) > 1 and not AMBIGUITY_RATIO * d_mean[c0] < d_mean[okc[1]]:
        return {"reason": "ambiguous between markers "
                + ", ".join(labels[int(m_c[c])] for c in okc[:3]),
                "conflict": {"labels": [labels[int(m_c[c])] for c in okc],
                             "mean_mm": [round(float(d_mean[c] * mm), 2) for c in okc]}}
    # any other missing marker, even one predicted only from estimates, that comes
    # as close to the fragment makes it ambiguous
    others = cands[cands != m]
    if len(others):
        sub = _spread(len(T))
        da = _norm(frag[sub][:, None] - gather_samples(E_all, T[sub][:, None], others[None]))
        da_mean = _nan_mean(da)
        ratio = np.full(len(others), AMBIGUITY_RATIO)
        if near is not None:
            ratio[near[m, others]] = max(near_ratio, AMBIGUITY_RATIO)
        rel = da_mean / ratio
        if np.fmin.reduce(rel) < d_mean[c0]:  # the nearest with an estimate (NaN: none)
            k = int(np.argmin(np.where(np.isnan(rel), np.inf, rel)))
            rival = labels[int(others[k])]
            return {"reason": f"ambiguous: {labels[m]} at {d_mean[c0] * mm:.1f} mm, {rival} at "
                              f"{da_mean[k] * mm:.1f} mm",
                    "conflict": {"labels": [labels[m], rival],
                                 "mean_mm": [round(float(d_mean[c0] * mm), 2),
                                             round(float(da_mean[k] * mm), 2)]}}
    return {"marker": m, "entry": float(d_entry[c0]), "max": float(d_max[c0]),
            "mean": float(d_mean[c0])}


#: Continuity across a short gap (:func:`continue_breaks`): a fragment whose first
#: (last) sample lies within this share of ε₁ of a marker's last (next) sample
#: carried across the gap by the rigid motion of the marker's neighbours continues
#: that marker.  On the simulated 350-marker range-of-motion capture (seed 0) the
#: true continuations lie at 0.05 ε₁ (p95) from the carried sample across a
#: one-frame gap, 0.24 ε₁ across two frames, 0.45 ε₁ across three (p95).
BREAK_JUMP = 0.25
#: ... and every other candidate (another marker carried across its gap, a marker
#: sample or another unmerged fragment in that frame) lies at least this many ε₁
#: from it and at least :data:`AMBIGUITY_RATIO` times farther than the fragment.
BREAK_CLEARANCE = 1.0
#: Longest gap :func:`continue_breaks` bridges: at least :data:`MAX_BRIDGE` frames and
#: at least :data:`MAX_BRIDGE_TIME` seconds (:func:`bridge_frames`), between the
#: marker's gap-end sample and the fragment's end sample.  What the carried sample
#: misses is the marker's motion relative to its neighbours while it is lost; the
#: jump test (:data:`BREAK_JUMP`), not the gap length, is what keeps continuity
#: right (on the shared C3Ds cut into pieces, true continuations across 20-80 ms lie
#: 0.001-0.1 ε₁ from the carried sample).  Measured (shared C3Ds, 2-4 cuts per
#: trajectory, gaps of 0-8 frames; simulated Tables 1/1b, seeds 0-4):
#: a bridge of 67 ms alone (3 frames at 50 Hz) loses right continuations (22 of 45
#: merges at 50 Hz, 8 of 22 at 70 Hz, 50 of 121 at 100 Hz: a missed continuation
#: breaks the chain after it); 160 ms gains on the real files (100 Hz 121 -> 136,
#: none wrong) but at 120 Hz (19 frames) made 2 wrong merges on the simulated range of
#: motion, seed 4; 8 frames at 120 Hz (the simulator) and below, 13 at 200 Hz
#: (Qualisys 141 -> 150 merges, all right) are what measured without a wrong merge.
MAX_BRIDGE_TIME = 8 / 120
#: The bridge's floor in frames (and the bridge when the capture rate is not known).
MAX_BRIDGE = 8


def bridge_frames(rate: float | None, seconds: float | None = None) -> int:
    """Longest gap bridged at ``rate`` Hz, in frames: ``⌊seconds · rate⌋``, at least
    :data:`MAX_BRIDGE`; ``seconds`` default :data:`MAX_BRIDGE_TIME`; ``rate`` None:
    :data:`MAX_BRIDGE`.

    Up to 120 Hz: 8 frames; 200 Hz: 13; 250 Hz: 16.
    """
    if rate is None:
        return MAX_BRIDGE
    seconds = MAX_BRIDGE_TIME if seconds is None else seconds
    if not (np.isfinite(rate) and rate > 0) or not seconds >= 0:
        raise ValueError(f"bridge_frames: need rate > 0 and seconds >= 0, got {rate}, {seconds}")
    return max(MAX_BRIDGE, int(np.floor(seconds * rate + 1e-9)))
#: Markers farther than this (metres) from the fragment's end sample at their own
#: gap end are not candidates (a screen: the carried motion is a few centimetres).
BRIDGE_SCREEN = 0.25


def _carry(X: np.ndarray, avail: np.ndarray, src: np.ndarray, dst: np.ndarray,
           m: np.ndarray, neighbours: np.ndarray, rigidity: np.ndarray) -> np.ndarray:
    """``(n, 3)`` marker ``m[i]``'s sample at frame ``src[i]`` moved to frame ``dst[i]``
    by the rigid motion (Horn, rigidity weights) of its neighbours seen in both frames
    (NaN with fewer than 3 of them)."""
    N = neighbours[m]  # (n, K)
    Nc = np.maximum(N, 0)
    w = np.where((N >= 0) & avail[src[:, None], Nc] & avail[dst[:, None], Nc],
                 rigidity[m], 0.0)
    w = np.where((w > 0).sum(1, keepdims=True) >= 3, w, 0.0)
    R, t = absolute_orientation_batch(X[src[:, None], Nc], X[dst[:, None], Nc], weights=w)
    return np.einsum("nij,nj->ni", R, X[src, m]) + t


def continue_breaks(
    positions: np.ndarray,
    fragments: np.ndarray,
    eps1: np.ndarray,
    assigned: np.ndarray,
    neighbours: np.ndarray,
    *,
    rigidity: np.ndarray | None = None,
    jump: float = BREAK_JUMP,
    clearance: float = BREAK_CLEARANCE,
    max_gap: int = MAX_BRIDGE,
    visible: np.ndarray | None = None,
) -> list[tuple[int, int, float]]:
    """Merge fragments that continue a marker across a break or short gap (beyond §4.2).

    A capture system breaks a trajectory where a marker is lost for a few frames
    (or for none).  Fragment ``u`` continues marker ``m`` when ``m`` is missing in
    all of ``u``'s (contiguous) frames, ``m``'s last sample before ``u`` starts
    (first after it ends) is at most ``max_gap`` frames away, and ``u``'s first
    (last) sample lies within ``jump · ε₁`` of ``m``'s sample carried across the
    gap by the rigid motion of ``m``'s neighbours (:func:`_carry`), while every
    other candidate marker carried likewise, every marker sample and every other
    unmerged fragment sample of that frame lies at least ``clearance · ε₁`` and
    :data:`AMBIGUITY_RATIO` times farther, and ``u``'s two ends do not continue
    different markers.  Repeated until nothing merges (each merge gives the next
    fragment a marker end to continue); a repeat looks again only at the fragments
    within ``max_gap`` frames of a merge of the pass before (all a verdict reads
    lies there, so the others' stays the same).  The gap ends are measurements a few
    frames away, so this holds where predictions from far-off data (the rigid
    rounds' local targets, the hole filling) are off.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        Labelled trajectories, NaN where missing; the merges are written in place.
    fragments : (F, U, 3) float ndarray
        Unlabelled fragments, NaN outside each.
    eps1 : (M,) float ndarray
        Entry tolerance per marker (NaN: the marker takes no fragment).
    assigned : (U,) int ndarray
        Marker of each fragment, ``-1`` if none; updated in place.
    neighbours : (M, K) int ndarray
        Surface neighbours of each marker, ``-1`` padded.
    rigidity : (M, K) float ndarray, optional
        Neighbour weights of the rigid fits (default 1).
    jump, clearance : float
        :data:`BREAK_JUMP`, :data:`BREAK_CLEARANCE`.
    max_gap : int
        Longest gap bridged, frames between the two end samples (:data:`MAX_BRIDGE`,
        :func:`bridge_frames` of the capture rate; 1: breaks without a lost frame
        only).
    visible : (F, U) bool ndarray, optional
        ``np.isfinite(fragments).all(-1)``, when the caller has it.

    Returns
    -------
    list of (fragment, marker, jump in metres)
        The merges, in order.
    """
    if jump < 0 or clearance < 0 or max_gap < 1:
        raise ValueError(f"continue_breaks: need jump >= 0, clearance >= 0, max_gap >= 1, "
                         f"got {jump}, {clearance}, {max_gap}")
    X = positions
    F, U = fragments.shape[:2]
    M = X.shape[1]
    rigidity = np.where(neighbours >= 0, 1.0, 0.0) if rigidity is None else rigidity
    fvis = finite_rows(fragments) if visible is None else visible
    n_vis = fvis.sum(0)
    first = np.argmax(fvis, 0)
    last = F - 1 - np.argmax(fvis[::-1], 0)
    run = (n_vis > 0) & (last - first + 1 == n_vis)
    usable = np.isfinite(eps1)
    steps = np.arange(1, max_gap + 1)
    avail = finite_rows(X)  # kept up to date with the merges below
    done: list[tuple[int, int, float]] = []
    merged_at = None  # (F,) frames the last pass merged into (None: the first pass)
    # cumulative counts of avail over frames, kept up to date with the merges below
    n_avail = np.concatenate([np.zeros((1, M), np.int32), np.cumsum(avail, 0, dtype=np.int32)])
    while True:
        todo = _nonzero(run & (assigned < 0))
        if merged_at is not None:
            # a fragment's verdict reads its frames and max_gap frames on either side
            n_merged = np.concatenate([[0], np.cumsum(merged_at)])
            near_merge = (n_merged[np.minimum(last[todo] + max_gap, F - 1) + 1]
                          > n_merged[np.maximum(first[todo] - max_gap, 0)])
            todo = todo[near_merge]
        if not len(todo):
            return done
        a, b = first[todo], last[todo]
        free = (n_avail[b + 1] == n_avail[a]) & usable  # (n, M)
        pick = np.full(len(todo), -1)
        dist = np.full(len(todo), np.nan)
        for at, sign in ((a, -1), (b, 1)):
            inside = (at + sign >= 0) & (at + sign < F)
            # markers with a sample at most max_gap frames beyond the fragment's end
            lo, hi = ((np.maximum(at - max_gap, 0), at) if sign < 0
                      else (at + 1, np.minimum(at + max_gap + 1, F)))
            ii, mm_ = np.nonzero(free & inside[:, None] & (n_avail[hi] > n_avail[lo]))
            # the marker's gap end: its nearest sample beyond the fragment's end
            f = at[ii, None] + sign * steps  # (k, max_gap)
            seen = (f >= 0) & (f < F)
            seen[seen] = avail[f[seen], np.broadcast_to(mm_[:, None], f.shape)[seen]]
            end = at[ii] + sign * (1 + np.argmax(seen, 1))
            frag = gather_samples(fragments, at, todo)  # (n, 3)
            screen = _norm(X[end, mm_] - frag[ii]) < BRIDGE_SCREEN
            ii, mm_, end = ii[screen], mm_[screen], end[screen]
            if not len(ii):
                continue
            pred = _carry(X, avail, end, at[ii], mm_, neighbours, rigidity)
            d = _norm(pred - frag[ii])  # NaN: no fit
            d = np.where(np.isfinite(d), d, np.inf)
            # per fragment end: the closest candidate, and the next one
            order = np.lexsort((d, ii))
            ii, mm_, d, pred = ii[order], mm_[order], d[order], pred[order]
            head = _nonzero(np.r_[True, ii[1:] != ii[:-1]])
            second = np.full(len(head), np.inf)
            has2 = (head + 1 < len(ii)) & (np.r_[head[1:], len(ii)] > head + 1)
            second[has2] = d[head[has2] + 1]
            i_h, m_h, d_h, p_h = ii[head], mm_[head], d[head], pred[head]
            e1 = eps1[m_h]
            ok = (d_h < jump * e1) & (second >= np.maximum(clearance * e1, AMBIGUITY_RATIO * d_h))
            i_h, m_h, d_h, p_h, e1 = i_h[ok], m_h[ok], d_h[ok], p_h[ok], e1[ok]
            if not len(i_h):
                continue
            # rivals seen in that frame: marker samples and other unmerged fragments
            t_h = at[i_h]
            r = np.arange(len(i_h))
            with np.errstate(invalid="ignore"):
                dm = _norm(X[t_h] - p_h[:, None])  # (r, M)
                dm[r, m_h] = np.inf
                seen_u = fvis[t_h] & (assigned < 0)[None]  # (r, U)
                seen_u[r, todo[i_h]] = False
                rr, uu = np.nonzero(seen_u)
                df = _norm(fragments[t_h[rr], uu] - p_h[rr])
            rival = np.where(np.isfinite(dm), dm, np.inf).min(1)
            np.minimum.at(rival, rr, np.where(np.isfinite(df), df, np.inf))
            ok = (rival >= clearance * e1) & (rival >= AMBIGUITY_RATIO * d_h)
            for i, mi, di in zip(i_h[ok], m_h[ok], d_h[ok]):
                if pick[i] == -2 or (pick[i] >= 0 and pick[i] != mi):
                    pick[i] = -2  # the two ends continue different markers
                else:
                    pick[i] = mi
                    dist[i] = di if np.isnan(dist[i]) else max(dist[i], di)
        n_before = len(done)
        merged_at = np.zeros(F, dtype=bool)
        for i in _nonzero(pick >= 0):
            u, mi = int(todo[i]), int(pick[i])
            T = slice(int(a[i]), int(b[i]) + 1)
            if np.isfinite(X[T, mi]).any():
                continue  # another fragment of this pass took the marker there
            X[T, mi] = fragments[T, u]
            avail[T, mi] = True  # u is seen in all of T
            merged_at[T] = True
            n_avail[T.start + 1:T.stop + 1, mi] += np.arange(1, T.stop - T.start + 1,
                                                             dtype=np.int32)
            n_avail[T.stop + 1:, mi] += T.stop - T.start
            assigned[u] = mi
            done.append((u, mi, float(dist[i])))
        if len(done) == n_before:
            return done


@dataclass
class _MergeRun:
    """What one :func:`merge_fragments` call carries from round to round.

    ``X`` the positions with the merges written in, ``dbar``, ``eps1``, ``eps2``
    the markers' tolerances (:func:`_tolerances`), ``assigned`` the marker of
    each fragment (-1), ``verdict`` the last rejection of each unmerged fragment,
    ``merges`` / ``conflicts`` the report lists, ``dirty`` the frames whose data
    or predictions changed since the fragments there were judged, ``stale`` the
    frames to predict again, ``visible`` ``(F, U)`` where each fragment has a sample,
    ``reference``, ``neighbours``, ``rigidity`` the surface's (:func:`_swap_rival`).
    """

    X: np.ndarray
    fragments: np.ndarray
    frames_of: list[np.ndarray]
    flabels: list[str]
    labels: list[str]
    dbar: np.ndarray
    eps1: np.ndarray
    eps2: np.ndarray
    assigned: np.ndarray
    dirty: np.ndarray
    stale: np.ndarray
    reference: np.ndarray
    visible: np.ndarray
    neighbours: np.ndarray
    rigidity: np.ndarray | None
    verdict: dict[int, dict[str, Any]] = field(default_factory=dict)
    merges: list[dict[str, Any]] = field(default_factory=list)
    conflicts: list[dict[str, Any]] = field(default_factory=list)


def _tolerances(surface: MarkerSurface, alpha1: float,
                alpha2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(d̄, ε₁ = α₁ d̄, ε₂ = α₂ d̄)`` per marker, ``(M,)`` each (P&H §4.2), ``d̄`` the
    mean neighbour distance capped by the distance to the nearest marker."""
    dbar = np.fmin(surface.mean_distance, nearest_marker_distance(surface.reference))
    return dbar, alpha1 * dbar, alpha2 * dbar


def _near_markers(surface: MarkerSurface) -> np.ndarray:
    """``(M, M)`` bool: markers within :data:`NEAR_RADIUS` mean neighbour distances of
    each other in the reference pose."""
    ref = surface.reference
    gap = _norm(ref[:, None] - ref[None])
    with np.errstate(invalid="ignore"):
        return gap < NEAR_RADIUS * surface.mean_distance[:, None]


def _predict_round(run: _MergeRun, surface: MarkerSurface, fvis: np.ndarray, todo: list[int],
                   Y: np.ndarray, E: np.ndarray, E_all: np.ndarray, depth: int,
                   min_support: float, ctx: Context) -> np.ndarray:
    """Rigid predictions of the round in the frames that need them (P&H §4.2).

    The markers' local targets are recomputed; frames that are stale or whose
    targets changed, and hold an unmerged fragment, are predicted again (trusted
    ones into ``E``, all into ``E_all``, in place); frames whose predictions
    changed become dirty.  Returns the new targets ``Y (F, M, 3)``.
    """
    Y_new = local_targets(run.X, surface.reference, surface.neighbours,
                          rigidity=surface.rigidity)
    changed = ~((Y_new == Y) | (np.isnan(Y_new) & np.isnan(Y))).all((1, 2))
    frames = np.union1d(run.stale, _nonzero(changed))
    # predictions are only read in the frames of fragments still unmerged
    frames = frames[fvis[frames][:, todo].any(1)]
    if len(frames):
        e, ea = _predict_parallel(run.X, surface, Y_new, frames, ctx, depth, min_support)
        diff = ~(((e == E[frames]) | (np.isnan(e) & np.isnan(E[frames])))
                 & ((ea == E_all[frames]) | (np.isnan(ea) & np.isnan(E_all[frames])))
                 ).all((1, 2))
        run.dirty[frames[diff]] = True
        E[frames], E_all[frames] = e, ea
    return Y_new


def _rival_fragment(fragments: np.ndarray, unmerged: np.ndarray, u: int, T: np.ndarray,
                    v: dict[str, Any], E_all: np.ndarray, eps1: np.ndarray,
                    labels: list[str], flabels: list[str],
                    n_unmerged: np.ndarray | None = None) -> dict[str, Any]:
    """Refuse fragment ``u``'s merge verdict ``v`` when another unmerged fragment seen
    in its frames ``T`` could be the chosen marker as well (beyond §4.2).

    The paper's tests compare one fragment with every missing marker; two fragments
    of two close markers, both missing, in the same frames are judged one at a time,
    and where the markers' predictions are off the wrong one can pass alone.  A rival
    is an unmerged fragment ``r`` (``unmerged``, ``(F, U)`` bool) seen with a
    prediction (``E_all``, ``(F, M, 3)``) in at least half of ``u``'s frames, whose
    mean distance to the marker's prediction over those frames is below ``ε₁`` and
    below :data:`AMBIGUITY_RATIO` times ``u``'s mean distance there.  ``n_unmerged``,
    optional ``(F + 1, U)``: cumulative counts of ``unmerged`` over frames (finds the
    fragments seen in contiguous ``T``, and in how many of its frames, without
    scanning them).  Returns ``v`` or an ambiguous rejection.

    On the simulated 350-marker captures with labels stripped (``benchmarks/clean.py``
    table 1b, seed 1) the wrong merges this refuses were a 4-frame fragment
    (range of motion, 10.1 mm from the prediction, its neighbour's own fragment at
    18.5 mm) and a 3-frame one (dynamic, 9.3 / 21.9 mm).  A rival seen in only a
    few frames of a long fragment is none: long fragments of one marker, each
    crossed for 3–5 frames by short fragments of a neighbour, were refused
    (0.4 points of the real samples on the dynamic capture).
    """
    m = int(v["marker"])
    run_T = _is_run(T)
    seen = unmerged[T[0]:T[-1] + 1] if run_T else unmerged[T]  # (|T|, U)
    if run_T and n_unmerged is not None:
        rivals = _nonzero(n_unmerged[T[-1] + 1] != n_unmerged[T[0]])
    else:
        rivals = _nonzero(seen.any(0))
    rivals = rivals[rivals != u]
    if not len(rivals):
        return v
    p = E_all[T, m]  # (|T|, 3)
    d_u = _norm(fragments[T, u] - p)  # NaN: not predicted
    have = np.isfinite(d_u)
    if run_T and n_unmerged is not None and have.all():
        n = (n_unmerged[T[-1] + 1] - n_unmerged[T[0]])[rivals]  # frames both are seen
    else:
        n = (seen[:, rivals] & have[:, None]).sum(0)
    cols = _nonzero(n >= max(1, int(np.ceil(0.5 * len(T)))))  # seen in enough frames
    if not len(cols):
        return v
    # their distances where both are seen (0 elsewhere), summed over frames as numpy sums
    # the columns of a table of all rivals: one by one (a single column is summed
    # pairwise, so a lone column of several rivals is doubled)
    if len(cols) == 1 and len(rivals) > 1:
        cols = np.r_[cols, cols]
    both = seen[:, rivals[cols]] & have[:, None]  # (|T|, C)
    g = (fragments[T[0]:T[-1] + 1, rivals[cols]] if run_T
         else fragments[T[:, None], rivals[cols][None]])  # (|T|, C, 3)
    d_r = np.where(both, _norm(g - p[:, None]), 0.0)
    mean_r = d_r.sum(0) / n[cols]  # n >= 1 there
    mean_u = np.where(both, d_u[:, None], 0.0).sum(0) / n[cols]
    close = (mean_r < eps1[m]) & (mean_r < AMBIGUITY_RATIO * mean_u)
    if not close.any():
        return v
    k = int(np.argmin(np.where(close, mean_r, np.inf)))
    r = int(rivals[cols[k]])
    mm = 1000.0
    return {"reason": f"ambiguous: fragment {flabels[r]} in the same frames at "
                      f"{mean_r[k] * mm:.1f} mm of the prediction of {labels[m]}, this one at "
                      f"{mean_u[k] * mm:.1f} mm",
            "conflict": {"labels": [labels[m]], "fragments": [flabels[r]],
                         "mean_mm": [round(float(mean_u[k] * mm), 2),
                                     round(float(mean_r[k] * mm), 2)]}}


def _blind_rival(frag: np.ndarray, T: np.ndarray, v: dict[str, Any], free: np.ndarray,
                 E_all: np.ndarray, reference: np.ndarray, labels: list[str],
                 index_all: PredictionIndex | None = None) -> dict[str, Any]:
    """Refuse the merge verdict ``v`` of fragment ``frag`` (frames ``T``) when a marker
    missing in all its frames, but not predicted there, could be it (beyond §4.2).

    The ambiguity test compares the fragment with the predictions of the other
    missing markers; a marker without one (fewer than 3 neighbours with data, in at
    least half of the fragment's frames) escapes it however close it is.  Such a
    marker ``r`` is bounded instead through the chosen marker ``m``: under the local
    rigidity the predictions assume, ``r`` lies ``D`` (their distance in the
    reference pose) from ``m``, so if the fragment, at mean distance ``δ`` from
    ``m``'s prediction, were ``r``, that prediction would be off by at least
    ``|D − δ|``.  The merge is clear only if this is :data:`AMBIGUITY_RATIO` times
    ``δ``, i.e. ``D ≥ (1 + AMBIGUITY_RATIO) δ``.  With ``ε₁ = d̄ / 2`` (``d̄`` the
    mean neighbour distance), a merge within ``ε₁ / 2`` is refused only for a blind
    marker nearer than ``d̄`` to the chosen one.  Continuity merges
    (:func:`continue_breaks`) have their own rival test and are not judged here.

    ``free`` ``(M,)`` bool: the markers missing in all of ``T`` (and usable);
    ``E_all`` ``(F, M, 3)``: every prediction; ``reference`` ``(M, 3)``: the
    reference pose; ``index_all``, optional: a :class:`PredictionIndex` of ``E_all``
    (counts for fragments over contiguous frames).  Returns ``v`` or an ambiguous
    rejection.

    On the real PiG calibration cut into pieces (``btkdata_PiG_Calibration-
    FlatFoot-Hole.c3d``, head markers 123 mm apart, ``ε₁`` 62 mm) the fragment of
    RFHD over frames 274–299 went to RBHD 46 mm from its prediction (made from the
    torso while the head turned), RFHD free there but with no prediction.
    """
    m = int(v["marker"])
    others = _nonzero(free)
    others = others[others != m]
    if not len(others):
        return v
    if index_all is not None and _is_run(T):
        seen = index_all.n_predicted[T[-1] + 1, others] - index_all.n_predicted[T[0], others]
    else:
        seen = finite_rows(E_all[T[:, None], others[None]]).sum(0)
    blind = others[seen < max(1, int(np.ceil(0.5 * len(T))))]
    with np.errstate(invalid="ignore"):
        D = _norm(reference[blind] - reference[m])
        close = D < (1.0 + AMBIGUITY_RATIO) * v["mean"]
    if not close.any():
        return v
    k = int(np.argmin(np.where(close, D, np.inf)))
    r = int(blind[k])
    mm = 1000.0
    return {"reason": f"ambiguous: {labels[m]} at {v['mean'] * mm:.1f} mm, {labels[r]} "
                      f"({D[k] * mm:.1f} mm from it in the reference pose) missing with no "
                      "prediction",
            "conflict": {"labels": [labels[m], labels[r]],
                         "mean_mm": [round(float(v["mean"] * mm), 2)],
                         "reference_mm": round(float(D[k] * mm), 2)}}


def _swap_rival(fragments: np.ndarray, unmerged: np.ndarray, u: int, T: np.ndarray,
                v: dict[str, Any], free: np.ndarray, X: np.ndarray, E_all: np.ndarray,
                reference: np.ndarray, neighbours: np.ndarray, rigidity: np.ndarray | None,
                eps1: np.ndarray, labels: list[str], flabels: list[str],
                n_unmerged: np.ndarray | None = None) -> dict[str, Any]:
    """Refuse fragment ``u``'s merge verdict ``v`` (marker ``m``) when the fragment may be
    a marker ``r`` near ``m`` with ``m`` itself seen as another unmerged fragment ``g``
    (beyond §4.2).

    Where the neighbourhood of ``m`` bends (a limb at the end of its range of motion),
    ``m``'s prediction may lie near ``r``'s trajectory and ``r``'s own prediction far off:
    the ambiguity test then sees no rival.  The swap is taken as a rival when:

    - ``r`` is missing in all of ``T`` and close to ``m``: ``D = |ref[r] − ref[m]| <
      (1 + AMBIGUITY_RATIO) δ``, ``δ`` the fragment's mean distance to ``m``'s prediction
      (the bound of :func:`_blind_rival`: were the fragment ``r``, the prediction would be
      off by at least ``|D − δ|``, less than :data:`AMBIGUITY_RATIO` times ``δ``);
    - an unmerged fragment ``g``, seen in at least half of ``T``, lies where ``m``
      would be were the fragment ``r``: ``f + R (ref[m] − ref[r])``, ``R`` the rotation
      of the rigid fit (Horn, rigidity weights) of ``m``'s neighbours from the reference
      pose onto the frame (measured, else predicted: ``X`` with ``E_all``), within ``ε₁``
      on average over the frames of :func:`_spread` where both fragments are seen (the
      rotation is surer than the prediction's translation where the neighbourhood
      bends);
    - and the chosen labelling cannot place ``g``: for every marker ``s`` missing in all
      of ``T`` (``free``, ``(M,)`` bool; ``s ≠ m``), ``g`` lies at least
      :data:`AMBIGUITY_RATIO` times farther from ``f + R (ref[s] − ref[m])``.  (On a
      regular layout ``g`` is often ``m``'s neighbour on the far side from ``r``, as
      far from the fragment as ``r`` is: the chosen labelling places it too.)

    ``f`` is the fragment's sample in a frame; ``fragments`` ``(F, U, 3)``, ``T`` its
    frames; ``X`` ``(F, M, 3)`` the positions, ``E_all`` every prediction;
    ``reference`` ``(M, 3)``, ``neighbours`` / ``rigidity`` ``(M, K)`` the surface's;
    ``unmerged`` and ``n_unmerged`` as in :func:`_rival_fragment`.  Returns ``v`` or an
    ambiguous rejection (``conflict`` with ``swap_mm``: the distance of ``g``).

    On the simulated 350-marker range-of-motion capture with labels stripped
    (``benchmarks/clean.py`` table 1b, seed 4) the fragment of L155 over frames 782–899
    went to L298 in the first rigid round, 19.5 mm (0.69 ε₁) from L298's prediction
    (itself 57.9 mm off), L155 56.6 mm from L298 in the reference pose and its own
    prediction 113 mm off; L298 was the unmerged fragment 11.8 mm (0.42 ε₁) from where
    the swap puts it, more than 3 times farther from where the chosen labelling puts any
    free marker.  Refused, the later rounds merged the fragment into L155 and L298's
    into L298 (2 wrong merges -> 0, with the continuation of the wrong one; kept share
    98.48 -> 98.84 %); the 17 other Tables 1 / 1b runs (seeds 2-4) did not change.
    """
    m = int(v["marker"])
    delta = float(v["mean"])
    others = _nonzero(free)
    others = others[others != m]
    with np.errstate(invalid="ignore"):
        D = _norm(reference[others] - reference[m])
        near = others[D < (1.0 + AMBIGUITY_RATIO) * delta]
    if not len(near):
        return v
    if _is_run(T) and n_unmerged is not None:
        rivals = _nonzero(n_unmerged[T[-1] + 1] - n_unmerged[T[0]]
                                >= max(1, int(np.ceil(0.5 * len(T)))))
    else:
        rivals = _nonzero(unmerged[T].sum(0) >= max(1, int(np.ceil(0.5 * len(T)))))
    rivals = rivals[rivals != u]
    if not len(rivals):
        return v
    Ts = T[_spread(len(T))]
    Xs = np.where(finite_rows(X[Ts])[..., None], X[Ts], E_all[Ts])  # (k, M, 3)
    R, _ = _neighbour_fit(Xs, reference, neighbours, rigidity, np.arange(len(Ts)),
                          np.full(len(Ts), m))  # (k, 3, 3)
    rel = gather_samples(fragments, Ts[:, None], rivals[None]) - fragments[Ts, u][:, None]

    def misfit(g: np.ndarray, markers: np.ndarray, sign: float) -> np.ndarray:
        """``(len(g), len(markers))`` mean distance of ``rel[:, g]`` to ``sign·R (ref[markers]
        − ref[m])`` over the spread frames (NaN: never both seen with a fit)."""
        w = sign * np.einsum("kij,nj->kni", R, reference[markers] - reference[m])
        d = _norm(rel[:, g, None] - w[:, None])  # (k, len(g), len(markers))
        return _nan_mean(d.reshape(len(Ts), -1)).reshape(len(g), len(markers))

    swap = misfit(np.arange(len(rivals)), near, -1.0)  # g is m, the fragment r
    with np.errstate(invalid="ignore"):
        gi, ri = np.nonzero(swap < eps1[m])
    if not len(gi):
        return v
    hit = np.unique(gi)
    placed = dict(zip(hit.tolist(), np.fmin.reduce(misfit(hit, others, 1.0), axis=1)))
    for i, j in sorted(zip(gi.tolist(), ri.tolist()), key=lambda c: swap[c]):
        if not placed[i] < AMBIGUITY_RATIO * swap[i, j]:
            mm = 1000.0
            g, r = int(rivals[i]), int(near[j])
            return {"reason": f"ambiguous: {labels[m]} at {delta * mm:.1f} mm, or {labels[r]} "
                              f"with {labels[m]} the fragment {flabels[g]} "
                              f"({swap[i, j] * mm:.1f} mm from the place of the swap)",
                    "conflict": {"labels": [labels[m], labels[r]], "fragments": [flabels[g]],
                                 "mean_mm": [round(delta * mm, 2)],
                                 "swap_mm": round(float(swap[i, j] * mm), 2)}}
    return v


def _judge_round(run: _MergeRun, todo: list[int], E: np.ndarray, E_all: np.ndarray, *,
                 mean_tolerance: float, near: np.ndarray | None,
                 near_ratio: float) -> dict[int, list[tuple[float, int, dict]]]:
    """Judge every unmerged fragment whose frames changed (:func:`_judge_fragment`).

    Fragments over contiguous frames pass the entry test together first
    (:func:`_entry_screen`: those with no candidate within ``ε₁`` are decided there).
    Rejections go to ``run.verdict`` (a new ambiguity also to ``run.conflicts``);
    returns the claims ``{marker: [(mean distance, fragment, verdict), ...]}``.
    """
    avail = finite_rows(run.X)
    index = PredictionIndex(avail, finite_rows(E))
    index_all = index if E_all is E else None  # built when a verdict first needs it
    unmerged = run.visible & (run.assigned < 0)[None]  # (F, U)
    n_unmerged = None  # its cumulative counts, built when a verdict first needs them
    usable = np.isfinite(run.dbar)
    # nothing changed in the frames of a fragment judged before: its verdict stands
    todo = [u for u in todo if u not in run.verdict or run.dirty[run.frames_of[u]].any()]
    runs = [u for u in todo if _is_run(run.frames_of[u])]
    free_of, entries, screened = _entry_screen(run.fragments, run.frames_of, runs, index, E,
                                               run.eps1, usable, run.labels)
    row = {u: i for i, u in enumerate(runs)}
    claims: dict[int, list[tuple[float, int, dict]]] = {}
    for u in todo:
        T = run.frames_of[u]
        if u in screened:
            v = screened[u]
        else:
            if u in row:  # contiguous frames: a view of the samples
                free, frag = free_of[row[u]], run.fragments[T[0]:T[-1] + 1, u]
            else:
                free, frag = ~avail[T].any(0) & usable, run.fragments[T, u]
            v = _judge_fragment(frag, T, free, E, E_all, run.eps1, run.eps2, run.labels, index,
                                mean_tolerance=mean_tolerance, near=near, near_ratio=near_ratio,
                                entry=entries.get(u))
        if "marker" in v:
            if index_all is None:
                index_all = PredictionIndex(avail, finite_rows(E_all), like=index)
            v = _blind_rival(frag, T, v, free, E_all, run.reference, run.labels, index_all)
        if "marker" in v:
            if n_unmerged is None:
                n_unmerged = np.concatenate([np.zeros((1, unmerged.shape[1]), np.int32),
                                             np.cumsum(unmerged, 0, dtype=np.int32)])
            v = _rival_fragment(run.fragments, unmerged, u, T, v, E_all, run.eps1,
                                run.labels, run.flabels, n_unmerged)
        if "marker" in v:
            v = _swap_rival(run.fragments, unmerged, u, T, v, free, run.X, E_all,
                            run.reference, run.neighbours, run.rigidity, run.eps1, run.labels,
                            run.flabels, n_unmerged)
        if "marker" in v:
            claims.setdefault(v["marker"], []).append((v["mean"], u, v))
            run.verdict.pop(u, None)
        else:
            if "conflict" in v and run.verdict.get(u, {}).get("reason") != v["reason"]:
                run.conflicts.append({"fragment": run.flabels[u], **v["conflict"],
                                      "resolution": "ambiguous: not merged"})
            run.verdict[u] = {k: x for k, x in v.items() if k != "conflict"}
    return claims


def _merge_claims(run: _MergeRun, claims: dict[int, list[tuple[float, int, dict]]], *,
                  rnd: int, predictor: str, depth: Any) -> int:
    """Merge the claimed fragments, per marker closest first; a fragment overlapping
    one merged before it is a conflict.  Returns the number of merges."""
    mm = 1000.0
    labels, flabels, frames_of = run.labels, run.flabels, run.frames_of
    n_new = 0
    new_frames = [run.stale]
    for m, cl in claims.items():
        cl.sort(key=lambda c: c[0])
        taken = np.zeros(len(run.X), dtype=bool)
        winner: dict[int, str] = {}
        for _, u, v in cl:
            T = frames_of[u]
            if taken[T].any():
                w = next(flabels[w_] for w_, _ in winner.items() if taken[frames_of[w_]].any())
                run.conflicts.append({
                    "fragment": flabels[u], "labels": [labels[m]],
                    "resolution": f"overlaps fragment {w} merged into {labels[m]} (closer): "
                                  "not merged"})
                run.verdict[u] = {"reason": f"conflict with {w} for {labels[m]}"}
                continue
            taken[T] = True
            winner[u] = flabels[u]
            run.X[T, m] = run.fragments[T, u]
            run.dirty[T] = True
            new_frames.append(T)
            run.assigned[u] = m
            n_new += 1
            run.merges.append({
                "fragment": flabels[u], "label": labels[m],
                "first_frame": int(T[0]), "last_frame": int(T[-1]), "n_frames": len(T),
                "entry_mm": round(v["entry"] * mm, 2), "mean_mm": round(v["mean"] * mm, 2),
                "max_mm": round(v["max"] * mm, 2),
                "eps1_mm": round(float(run.eps1[m] * mm), 2),
                "eps2_mm": round(float(run.eps2[m] * mm), 2), "round": rnd,
                "predictor": predictor,
                "depth": depth,
            })
    run.stale = np.unique(np.concatenate(new_frames))
    return n_new


def _merge_breaks(run: _MergeRun, surface: MarkerSurface, max_break: float, *,
                  rnd: Any, max_gap: int = MAX_BRIDGE) -> int:
    """:func:`continue_breaks` on the run (``max_break`` its ``jump``; 0: nothing; gaps up
    to ``max_gap`` frames), the merges reported; returns their number."""
    if max_break <= 0:
        return 0
    mm = 1000.0
    done = continue_breaks(run.X, run.fragments,
                           np.where(np.isfinite(run.dbar), run.eps1, np.nan), run.assigned,
                           surface.neighbours, rigidity=surface.rigidity, jump=max_break,
                           max_gap=max_gap, visible=run.visible)
    for u, m, d in done:
        T = run.frames_of[u]
        run.verdict.pop(u, None)
        run.dirty[T] = True
        run.merges.append({
            "fragment": run.flabels[u], "label": run.labels[m], "first_frame": int(T[0]),
            "last_frame": int(T[-1]), "n_frames": len(T), "entry_mm": round(d * mm, 2),
            "mean_mm": round(d * mm, 2), "max_mm": round(d * mm, 2),
            "eps1_mm": round(float(run.eps1[m] * mm), 2),
            "eps2_mm": round(float(run.eps2[m] * mm), 2), "round": rnd,
            "jump_mm": round(d * mm, 2), "predictor": "continuity", "depth": "break"})
    if done:
        run.stale = np.unique(np.concatenate([run.stale] + [run.frames_of[u] for u, _, _ in done]))
    return len(done)


def _rejections(run: _MergeRun) -> list[dict[str, Any]]:
    """One entry per unmerged fragment: frames and the reason of its last verdict."""
    return [
        {"fragment": run.flabels[u], "n_frames": len(run.frames_of[u]),
         "first_frame": int(run.frames_of[u][0]) if len(run.frames_of[u]) else None,
         **run.verdict.get(u, {"reason": "not examined"})}
        for u in range(len(run.assigned)) if run.assigned[u] < 0
    ]


def _merge_rounds(
    run: _MergeRun, surface: MarkerSurface, fvis: np.ndarray, levels: list[Any], *,
    rounds_per_level: int, predictions: np.ndarray | None, competitors: np.ndarray | None,
    min_support: float, mean_tolerance: float, near: np.ndarray | None, near_ratio: float,
    ctx: Context,
) -> dict[str, int]:
    """The rounds of :func:`merge_fragments`: predict, judge, merge, until nothing merges.

    ``levels``: the prediction depths trusted in turn (``["given"]`` with
    ``predictions``: one round).  Returns the merges per level.
    """
    F = len(run.X)
    order = sorted((u for u in range(len(run.assigned)) if len(run.frames_of[u])),
                   key=lambda u: -len(run.frames_of[u]))
    n_by_depth: dict[str, int] = {}
    E = np.full_like(run.X, np.nan)
    E_all = np.full_like(run.X, np.nan)
    Y = np.full_like(run.X, np.nan)
    level, rounds_here = 0, 0
    for rnd in range(len(levels) * rounds_per_level):
        todo = [u for u in order if run.assigned[u] < 0]
        if not todo:
            break
        key = levels[level]
        if predictions is not None:
            E = np.where(np.isfinite(run.X), np.nan, predictions)
            E_all = E if competitors is None else np.where(np.isfinite(run.X), np.nan,
                                                           competitors)
        else:
            with ctx.timer("merge_predict"):
                Y = _predict_round(run, surface, fvis, todo, Y, E, E_all, key, min_support, ctx)
        run.stale = np.zeros(0, dtype=np.int64)
        with ctx.timer("merge_judge"):
            claims = _judge_round(run, todo, E, E_all, mean_tolerance=mean_tolerance,
                                  near=near, near_ratio=near_ratio)
        run.dirty[:] = False
        n_new = _merge_claims(run, claims, rnd=rnd,
                              predictor="rigid" if predictions is None else "given", depth=key)
        n_by_depth[str(key)] = n_by_depth.get(str(key), 0) + n_new
        rounds_here += 1
        if n_new == 0 or rounds_here >= rounds_per_level or predictions is not None:
            if level + 1 >= len(levels) or predictions is not None:
                break
            level, rounds_here = level + 1, 0
            run.stale = np.arange(F)  # trust changes: every frame is predicted again
            run.dirty[:] = True
    return n_by_depth


def merge_fragments(
    positions: np.ndarray,
    fragments: np.ndarray,
    surface: MarkerSurface,
    *,
    alpha1: float = 0.5,
    alpha2: float = 0.6,
    fragment_labels: list[str] | None = None,
    predictions: np.ndarray | None = None,
    competitors: np.ndarray | None = None,
    depths: tuple[int, ...] = (1, 2, 3),
    rounds_per_level: int = 4,
    min_support: float = RIGID_ANCHOR,
    mean_tolerance: float | None = None,
    near_ratio: float | None = None,
    max_break: float = BREAK_JUMP,
    rate: float | None = None,
    ctx: Context | None = None,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Merge unlabelled fragments into labelled markers (Park & Hodgins §4.2).

    Rounds: predict the missing samples
    (:func:`~mocapflow.stages.skin.predict.predict_missing` with the markers' local
    targets), judge every unmerged fragment (the ε₁ entry test,
    the ε₂ tube over its length, ambiguity tests), merge, repeat with the merged
    data.  Fragments whose frames saw no change since they were last judged are
    not judged again, and predictions are only made in frames that hold an
    unmerged fragment (frames are predicted independently of each other).

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        Labelled trajectories, NaN where missing.
    fragments : (F, U, 3) float ndarray
        Unlabelled trajectories, NaN outside each fragment.
    surface : MarkerSurface
    alpha1, alpha2 : float
        ``ε₁ = α₁ d̄``: entry tolerance; ``ε₂ = α₂ d̄``: tolerance over the whole
        fragment (``d̄``: the marker's mean neighbour distance, capped by its
        distance to the nearest marker so that a closer marker — across the
        armpit or the crotch — never falls inside the tolerance).
    fragment_labels : list of str, optional
        ``U`` names for the report.
    predictions : (F, M, 3) float ndarray, optional
        Judge against these predictions of the missing samples instead (e.g.
        the PCA hole filling of the merged data); one round.
    competitors : (F, M, 3) float ndarray, optional
        With ``predictions``: the predictions used in the ambiguity test
        (default the same).
    depths : tuple of int
        How far predictions may be from observed data (estimates of estimates)
        to judge a fragment, tried in turn: rounds first trust only predictions
        made from observed (or merged) neighbours (depth 1), and go one step
        further when a level stops merging.  Every prediction, trusted or not,
        takes part in the ambiguity test.
    rounds_per_level : int
        Rounds at most per depth level.
    min_support : float
        Predictions whose third most rigid neighbour weighs less are not
        trusted either.
    mean_tolerance : float, optional
        A fragment's mean distance to the prediction must be below
        ``mean_tolerance · ε₁``.  Default 1 (the paper) for rigid predictions,
        :data:`PCA_MEAN_TOLERANCE` with ``predictions`` (hole-filled estimates
        are less sure).
    near_ratio : float, optional
        Other missing markers within :data:`NEAR_RADIUS` mean neighbour
        distances of the chosen marker in the reference pose make a merge
        ambiguous unless their predictions are ``near_ratio`` times farther
        from the fragment.  Default :data:`AMBIGUITY_RATIO` (like all other
        markers) for rigid predictions, :data:`PCA_NEAR_RATIO` with
        ``predictions``: a close marker's estimate may be far off (few
        members, long unobserved) while the chosen one's lies on the fragment.
    max_break : float
        Before and after the rounds, fragments that continue a marker across a
        break or a gap of at most :func:`bridge_frames` (8 frames, 67 ms above
        120 Hz), within
        ``max_break · ε₁`` of its gap-end sample carried across by its
        neighbours' rigid motion, are merged (:func:`continue_breaks`,
        :data:`BREAK_JUMP`; 0: off, the paper).
    rate : float, optional
        Capture rate (Hz): the bridge in frames (:func:`bridge_frames`); default
        :data:`MAX_BRIDGE` frames.
    ctx : Context, optional
        For the parallel prediction (frame chunks through ``ctx.map``), and its
        timers: ``merge_continuity``, ``merge_predict``, ``merge_judge`` (seconds in
        :func:`continue_breaks`, the rigid predictions, the judging).

    Returns
    -------
    positions : (F, M, 3) float ndarray
        With the merged fragments written in.
    assigned : (U,) int ndarray
        Marker each fragment was merged into, ``-1`` if none.
    report : dict
        ``merges``, ``rejections``, ``conflicts`` (lists of dicts naming fragment,
        label and reason), ``merged_by_depth`` (``"break"``: by
        :func:`continue_breaks`).
    """
    ctx = ctx or Context()
    max_gap = bridge_frames(rate)
    F = positions.shape[0]
    U = fragments.shape[1]
    fvis = finite_rows(fragments)
    dbar, eps1, eps2 = _tolerances(surface, alpha1, alpha2)
    run = _MergeRun(
        X=positions.copy(), fragments=fragments,
        frames_of=[np.flatnonzero(fvis[:, u]) for u in range(U)],
        flabels=list(fragment_labels or [f"*{u + 1}" for u in range(U)]),
        labels=surface.labels, dbar=dbar, eps1=eps1, eps2=eps2,
        assigned=np.full(U, -1, dtype=np.int64),
        dirty=np.ones(F, dtype=bool),  # frames whose predictions / data changed
        stale=np.arange(F), reference=surface.reference, visible=fvis,
        neighbours=surface.neighbours, rigidity=surface.rigidity,
    )
    run.verdict = {u: {"reason": "empty fragment"} for u in range(U) if not len(run.frames_of[u])}
    given = predictions is not None
    if mean_tolerance is None:
        mean_tolerance = PCA_MEAN_TOLERANCE if given else 1.0
    if near_ratio is None:
        near_ratio = PCA_NEAR_RATIO if given else AMBIGUITY_RATIO
    near = _near_markers(surface) if near_ratio > AMBIGUITY_RATIO else None
    with ctx.timer("merge_continuity"):
        n_breaks = _merge_breaks(run, surface, max_break, rnd="break", max_gap=max_gap)
    n_by_depth = _merge_rounds(run, surface, fvis, ["given"] if given else list(depths),
                               rounds_per_level=rounds_per_level, predictions=predictions,
                               competitors=competitors, min_support=min_support,
                               mean_tolerance=mean_tolerance, near=near, near_ratio=near_ratio,
                               ctx=ctx)
    with ctx.timer("merge_continuity"):
        n_by_depth["break"] = n_breaks + _merge_breaks(run, surface, max_break, rnd="break",
                                                       max_gap=max_gap)
    return run.X, run.assigned, {"merges": run.merges, "rejections": _rejections(run),
                                 "conflicts": run.conflicts, "merged_by_depth": n_by_depth}
