"""How rigidly markers move together over a capture (the rigidity weights of the marker surface).

The marker surface is automatic, so a one-ring may straddle a joint or the
armpit (a departure from Park & Hodgins 2006, whose surface was built by hand):
every neighbour carries a weight from how constant its distance to the marker
stays over the capture (:func:`rigidity_weights`, from :func:`edge_stretch`),
used in every rigid fit of the clean stage, and a marker with fewer than 3
rigid neighbours borrows rigid ones from its two-ring (:func:`supplement_rigid`).
The same stretch rejects candidate neighbours and edges of the triangulation
(:mod:`mocapflow.stages.skin.triangulate`, :mod:`mocapflow.stages.skin.manifold`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

__all__ = ["edge_stretch", "rigidity_weights", "supplement_rigid"]


@contextmanager
def _quiet() -> Iterator[None]:
    """Silence numpy's 'mean of empty slice' RuntimeWarning."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def edge_stretch(positions: np.ndarray, pairs: np.ndarray, *, min_frames: int = 10) -> np.ndarray:
    """Relative variation of the distance between marker pairs over a capture.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        Marker trajectories, NaN where missing.
    pairs : (P, 2) int ndarray
        Marker index pairs.
    min_frames : int
        Pairs seen together in fewer frames get NaN (unknown).

    Returns
    -------
    (P,) float ndarray
        Standard deviation of the pair distance divided by its median.
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    out = np.full(len(pairs), np.nan)
    if len(pairs) == 0:
        return out
    F = positions.shape[0]
    step = max(1, F // 400)  # 400 frames are plenty for a spread estimate
    d = _pair_distances(positions[::step], pairs)  # (F', P)
    n = np.isfinite(d).sum(0)
    ok = n >= min_frames
    with _quiet():
        sd = np.nanstd(d[:, ok], axis=0)
    out[ok] = sd / np.maximum(_nanmedian_columns(d[:, ok]), 1e-12)
    return out


def _pair_distances(positions: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(positions[:, pairs[:, 0]] - positions[:, pairs[:, 1]], axis=-1)``,
    the same bits, about 2.5x faster: gathered per coordinate (planes of ``(F, P)``)
    and summed in the norm's order, ``(x² + y²) + z²``.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
    pairs : (P, 2) int ndarray

    Returns
    -------
    (F, P) float ndarray
    """
    planes = np.ascontiguousarray(positions.transpose(2, 0, 1))  # (3, F, M)
    s = np.take(planes, pairs[:, 0], axis=2) - np.take(planes, pairs[:, 1], axis=2)
    s *= s
    return np.sqrt((s[0] + s[1]) + s[2])


def _nanmedian_columns(d: np.ndarray) -> np.ndarray:
    """``np.nanmedian(d, axis=0)`` of a ``(F, P)`` array with a value in every
    column, by one sort (NaN sorts last); numpy's is ~10x slower on many columns."""
    s = np.sort(d, axis=0)
    n = np.isfinite(d).sum(0)
    lo, hi = (n - 1) // 2, n // 2
    cols = np.arange(d.shape[1])
    return 0.5 * (s[lo, cols] + s[hi, cols])


def rigidity_weights(
    positions: np.ndarray | None, neighbours: np.ndarray, *, scale: float = 0.05
) -> np.ndarray:
    """Weights of one-ring neighbours from how rigidly they move with the marker.

    ``w = 1 / (1 + (s / scale)²)`` where ``s`` is the relative standard
    deviation of the marker–neighbour distance over the capture
    (:func:`edge_stretch`): ~1 on one skin patch, small across a joint or the
    armpit.  Unknown stretch (too few frames together) gives 1.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray or None
        The capture (``None``: all weights 1).
    neighbours : (M, K) int ndarray
    scale : float

    Returns
    -------
    (M, K) float ndarray
        0 for padding.
    """
    valid = neighbours >= 0
    w = valid.astype(float)
    if positions is None or not valid.any():
        return w
    i, k = np.nonzero(valid)
    s = edge_stretch(positions, np.stack([i, neighbours[i, k]], 1))
    w[i, k] = np.where(np.isfinite(s), 1.0 / (1.0 + (s / scale) ** 2), 1.0)
    return w


def supplement_rigid(
    positions: np.ndarray,
    reference: np.ndarray,
    neighbours: np.ndarray,
    rigidity: np.ndarray,
    *,
    min_rigid: int = 3,
    threshold: float = 0.5,
    max_extra: int = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """Add rigid two-ring markers to neighbourhoods with fewer than 3 rigid members.

    A rigid fit needs 3 points that move with the marker; where the one-ring
    straddles a joint or the armpit, the two-ring markers with the highest
    rigidity weight (then the nearest) are appended until ``min_rigid`` members
    weigh more than ``threshold`` (at most ``max_extra``).

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
    reference : (M, 3) float ndarray
    neighbours : (M, K) int ndarray
        One-ring, nearest first.
    rigidity : (M, K) float ndarray

    Returns
    -------
    neighbours, rigidity : (M, K') ndarrays
        One-ring first, supplements after.
    """
    M = len(neighbours)
    rows = [list(r[r >= 0]) for r in neighbours]
    wts = [list(w[r >= 0]) for w, r in zip(rigidity, neighbours)]
    need = [i for i in range(M) if sum(w > threshold for w in wts[i]) < min_rigid and rows[i]]
    cands: dict[int, list[int]] = {}
    pairs = []
    for i in need:
        ring = set(rows[i])
        two = sorted({k for j in rows[i] for k in rows[j]} - ring - {i})
        cands[i] = two
        pairs += [(i, k) for k in two]
    if pairs:
        pa = np.array(pairs)
        st = edge_stretch(positions, pa)
        w = np.where(np.isfinite(st), 1.0 / (1.0 + (st / 0.05) ** 2), 0.0)
        look = {(int(a), int(b)): float(x) for (a, b), x in zip(pa, w)}
        for i in need:
            have = sum(x > threshold for x in wts[i])
            order = sorted(cands[i], key=lambda k: (-look[(i, k)],
                                                    float(np.linalg.norm(reference[k]
                                                                         - reference[i]))))
            for k in order[:max_extra]:
                if have >= min_rigid or look[(i, k)] <= threshold:
                    break
                rows[i].append(k)
                wts[i].append(look[(i, k)])
                have += 1
    K = max((len(r) for r in rows), default=0)
    nb = np.full((M, K), -1, dtype=np.int64)
    wt = np.zeros((M, K))
    for i in range(M):
        nb[i, : len(rows[i])] = rows[i]
        wt[i, : len(wts[i])] = wts[i]
    return nb, wt


def _pair_stretch(pos: np.ndarray, a: int, b: int, min_frames: int = 10) -> float:
    """:func:`edge_stretch` of one pair on already subsampled ``pos`` (F', M, 3)."""
    d = np.sqrt(((pos[:, a] - pos[:, b]) ** 2).sum(-1))
    d = d[np.isfinite(d)]
    if len(d) < min_frames:
        return math.nan
    return float(d.std() / max(float(np.median(d)), 1e-12))
