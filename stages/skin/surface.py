"""The marker surface of Park & Hodgins (2006, §4.1): a triangle mesh over the markers.

The paper built this mesh by hand in the reference pose.  Here it is built
automatically from surface neighbourhoods, and a manual override file is accepted:

1. **candidates**: each marker's ``candidates`` nearest markers in the reference
   pose, dropping those farther than ``max_edge`` times the marker's local spacing
   (mean distance to its 3 nearest) and — when the whole capture is given — pairs
   whose distance varies over the capture by more than ``max_stretch`` (relative
   standard deviation): markers on different limbs that happen to be close in the
   reference pose are not surface neighbours;
2. **umbrellas**: the candidates are projected onto the marker's tangent plane
   and triangulated (Delaunay); the triangles incident to the marker form its
   umbrella.  With ``close_holes`` the tangent plane is normal to
   :func:`marker_normals` (local principal axis, or the direction away from the
   wider neighbourhood's centre where that is not flat: radial on a thin limb),
   and candidates facing the other way or lying far below the plane (the far
   side of a limb) are dropped; otherwise the normal is the least principal
   axis of the candidates;
3. **selection** — ``close_holes=True``: a 2-manifold is grown
   greedily from the umbrella triangles, most votes (corners whose umbrella
   holds the triangle) and shortest perimeter first, taking a triangle only if
   no edge gets a third triangle, it does not fold onto a neighbour, it faces
   the corners' normals and its wedge overlaps no other at any corner
   (:func:`manifold_triangles`); triangles with a stretching edge are never
   candidates.  It is then wound consistently and outward
   (:func:`orient_faces`), tiny detached pieces are dropped, boundary loops are
   closed by minimum-area triangulation without stretching, over-long or
   folding edges (:func:`fill_surface_holes`; the gaps at the armpits and the crotch,
   whose bridges stretch over the capture, stay open), markers left on no
   triangle split their nearest triangle (:func:`insert_markers`) and edges
   are flipped towards Delaunay (:func:`flip_edges`).
   ``close_holes=False`` (default for now: the ``clean`` stage's tests were
   tuned on it): the plain vote — a triangle is
   kept when it is in the umbrellas of at least two of its three corners (a
   marker left with fewer than 3 neighbours keeps its own umbrella, and
   once-voted triangles that join separate pieces are kept) — which leaves
   holes and edges on three or more triangles;
4. **one-ring** neighbours are the markers sharing an edge with the marker;
   **local frames** ``(t, b, n)``: ``n`` the area-weighted mean normal of the
   incident triangles (wound consistently, outward), ``t`` the direction to
   the nearest neighbour projected onto the tangent plane, ``b = n × t``.

:func:`surface_topology` counts what makes a surface a closed oriented
2-manifold (boundary / non-manifold / misoriented edges, pinched markers,
boundary loops, Euler characteristic).

Manual override file (``surface`` param of the ``clean`` stage): either JSON
``{"faces": [[a, b, c], ...]}`` or a text file with one triangle per line
(``a b c`` or ``a,b,c``; ``#`` starts a comment), where corners are marker labels
(or 0-based integer indices).
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from mocapflow.stages.motion.datatypes import Mesh

__all__ = [
    "MarkerSurface",
    "SurfaceFileError",
    "SurfaceInputError",
    "build_marker_surface",
    "edge_stretch",
    "fill_surface_holes",
    "flip_edges",
    "insert_markers",
    "local_frames",
    "manifold_triangles",
    "marker_normals",
    "marker_surface_from_faces",
    "one_ring",
    "orient_faces",
    "pinched_markers",
    "read_surface_file",
    "rigidity_weights",
    "supplement_rigid",
    "surface_topology",
    "triangulate_markers",
]


class SurfaceFileError(ValueError):
    """A manual marker-surface file is unreadable or names unknown markers."""


class SurfaceInputError(ValueError):
    """Reference pose or capture of the wrong shape for a marker surface."""


@dataclass(eq=False)
class MarkerSurface:
    """Triangle mesh over the markers with one-ring neighbours and local frames.

    Parameters
    ----------
    reference : (M, 3) float ndarray
        Marker positions in the reference pose (metres); NaN for markers that
        are not on the surface (never visible).
    faces : (T, 3) int ndarray
        Triangles as marker indices.
    neighbours : (M, K) int ndarray
        One-ring neighbours of each marker, ``-1`` padded, nearest first.
    frames : (M, 3, 3) float ndarray
        Local reference frame of each marker in the reference pose: rows
        ``t, b, n`` (tangent, bitangent, normal); NaN where undefined.
    labels : list of str
        ``M`` marker labels.
    source : str
        ``"automatic"`` or the override file's name.
    rigidity : (M, K) float ndarray, optional
        Weight of each neighbour in the rigid fits, from how much its distance
        to the marker varies over the capture (see :func:`rigidity_weights`);
        1 where unknown, 0 for padding.
    n_ring : (M,) int ndarray, optional
        How many of ``neighbours`` (the first ones) form the one-ring; the rest
        are rigid two-ring supplements (see :func:`supplement_rigid`).
    reference_frame : int, optional
        Capture frame the reference pose was taken from (when known).
    """

    reference: np.ndarray
    faces: np.ndarray
    neighbours: np.ndarray
    frames: np.ndarray
    labels: list[str] = field(default_factory=list)
    source: str = "automatic"
    rigidity: np.ndarray | None = None
    n_ring: np.ndarray | None = None
    reference_frame: int | None = None

    def __post_init__(self) -> None:
        if self.rigidity is None:
            self.rigidity = np.where(self.neighbours >= 0, 1.0, 0.0)
        if self.n_ring is None:
            self.n_ring = (self.neighbours >= 0).sum(1)

    @property
    def n_markers(self) -> int:
        """Number of markers ``M``."""
        return self.reference.shape[0]

    @property
    def n_neighbours(self) -> np.ndarray:
        """``(M,)`` int: one-ring size of every marker."""
        return (self.neighbours >= 0).sum(axis=1)

    @property
    def mean_distance(self) -> np.ndarray:
        """``(M,)`` mean reference-pose distance to the one-ring (NaN without one)."""
        nb = self.neighbours
        d = np.linalg.norm(self.reference[np.maximum(nb, 0)] - self.reference[:, None], axis=-1)
        ring = np.arange(nb.shape[1])[None, :] < self.n_ring[:, None]
        d = np.where((nb >= 0) & ring, d, np.nan)
        with _quiet():
            return np.nanmean(d, axis=1)

    def to_mesh(self) -> Mesh:
        """The surface as a :class:`~mocapflow.stages.motion.datatypes.Mesh` (vertices = markers).

        ``attrs`` carry ``labels``, ``neighbours`` (lists of labels' indices) and
        the local frames, so downstream stages (segment, deform) can use it, and
        ``reference_frame`` (the capture frame of the reference pose) when known.
        """
        extra = {} if self.reference_frame is None else {
            "reference_frame": int(self.reference_frame)}
        return Mesh(
            vertices=np.where(np.isfinite(self.reference), self.reference, np.nan),
            faces=self.faces,
            attrs={
                "labels": list(self.labels),
                "kind": "marker_surface",
                "source": self.source,
                "neighbours": [[int(j) for j in row if j >= 0] for row in self.neighbours],
                "frames": self.frames.tolist(),
                "rigidity": [[round(float(w), 4) for w, j in zip(wr, row) if j >= 0]
                             for wr, row in zip(self.rigidity, self.neighbours)],
                **extra,
            },
        )


@contextmanager
def _quiet() -> Iterator[None]:
    """Silence numpy's 'mean of empty slice' RuntimeWarning."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


# --------------------------------------------------------------------------- neighbourhoods


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
    pos = positions[::step]
    d = np.linalg.norm(pos[:, pairs[:, 0]] - pos[:, pairs[:, 1]], axis=-1)  # (F', P)
    n = np.isfinite(d).sum(0)
    ok = n >= min_frames
    with _quiet():
        sd = np.nanstd(d[:, ok], axis=0)
    out[ok] = sd / np.maximum(_nanmedian_columns(d[:, ok]), 1e-12)
    return out


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


def _candidates(
    reference: np.ndarray,
    valid: np.ndarray,
    positions: np.ndarray | None,
    k: int,
    max_edge: float,
    max_stretch: float,
) -> list[np.ndarray]:
    idx = np.flatnonzero(valid)
    cand: list[np.ndarray] = [np.zeros(0, dtype=np.int64) for _ in range(len(reference))]
    if len(idx) < 2:
        return cand
    tree = cKDTree(reference[idx])
    kq = min(k + 1, len(idx))
    dist, nn = tree.query(reference[idx], k=kq)
    dist, nn = dist[:, 1:], idx[nn[:, 1:]]
    scale = dist[:, : min(3, dist.shape[1])].mean(1)
    keep = dist <= max_edge * scale[:, None]
    if positions is not None and max_stretch > 0:
        pairs = np.stack([np.repeat(idx, nn.shape[1]), nn.ravel()], 1)
        s = edge_stretch(positions, pairs).reshape(nn.shape)
        keep &= ~(s > max_stretch)  # unknown (NaN) stretch is kept
    for row, i in enumerate(idx):
        cand[i] = nn[row][keep[row]]
    return cand


def _umbrella(reference: np.ndarray, i: int, cand: np.ndarray, max_angle: float,
              normal: np.ndarray | None = None) -> list[tuple]:
    """Triangles incident to marker ``i`` in the tangent-plane Delaunay of its candidates.

    The tangent plane is normal to ``normal`` when given, else to the least
    principal axis of the candidates.
    """
    if len(cand) < 2:
        return []
    pts = reference[np.concatenate([[i], cand])] - reference[i]
    if normal is None:
        _, _, vt = np.linalg.svd(pts - pts.mean(0), full_matrices=False)
        plane = vt[:2]
    else:
        u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        plane = np.stack([u, np.cross(normal, u)])
    uv = pts @ plane.T
    if len(cand) == 2:
        simplices = np.array([[0, 1, 2]])
    else:
        try:
            simplices = Delaunay(uv).simplices
        except (QhullError, ValueError):
            return []
    out = []
    cos_max = np.cos(max_angle)
    for s in simplices:
        if 0 not in s:
            continue
        a, b = (int(v) for v in s if v != 0)
        ea, eb = uv[a], uv[b]
        c = ea @ eb / max(np.linalg.norm(ea) * np.linalg.norm(eb), 1e-15)
        if c < cos_max:  # sliver fan across a hull edge
            continue
        out.append(tuple(sorted((i, int(cand[a - 1]), int(cand[b - 1])))))
    return out


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


def _rigid_triangles(positions: np.ndarray, votes: dict[tuple, int],
                     max_stretch: float) -> dict[tuple, int]:
    """The candidate triangles none of whose edges stretches more than ``max_stretch``."""
    tris = np.array(list(votes), dtype=np.int64)
    e = np.unique(np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [0, 2]]]),
                          axis=1), axis=0)
    bad = e[edge_stretch(positions, e) > max_stretch]
    if len(bad) == 0:
        return votes
    badset = {(int(a), int(b)) for a, b in bad}
    return {t: v for t, v in votes.items()
            if not ({(t[0], t[1]), (t[1], t[2]), (t[0], t[2])} & badset)}


NORMAL_K = 6


def marker_normals(reference: np.ndarray, *, k: int = 6, flatness: float = 0.2) -> np.ndarray:
    """Outward unit normal of every marker from its neighbourhood.

    The least principal axis of the marker and its ``k`` nearest markers, signed
    away from the centre of its wider (30-marker) neighbourhood; where the
    small neighbourhood is too flat to tell (a thin limb seen by few markers)
    the outward direction itself.

    Parameters
    ----------
    reference : (M, 3) float ndarray
    k : int

    Returns
    -------
    (M, 3) float ndarray
        NaN for markers without a position.
    """
    valid = np.isfinite(reference).all(1)
    out = np.full(reference.shape, np.nan)
    idx = np.flatnonzero(valid)
    if len(idx) < 3:
        return out
    away = _outward(reference, valid)[idx]
    away /= np.maximum(np.linalg.norm(away, axis=1, keepdims=True), 1e-15)
    _, nn = cKDTree(reference[idx]).query(reference[idx], k=min(k + 1, len(idx)))
    pts = reference[idx][nn]
    pts = pts - pts.mean(1, keepdims=True)
    _, s, vt = np.linalg.svd(pts)
    n = vt[:, -1]
    n *= np.where(np.einsum("ij,ij->i", n, away) < 0, -1.0, 1.0)[:, None]
    flat = s[:, 2] < flatness * s[:, 1]
    out[idx] = np.where(flat[:, None], n, away)
    return out


def _vote(
    reference: np.ndarray,
    positions: np.ndarray | None,
    candidates: int,
    max_edge: float,
    max_stretch: float,
    max_angle: float,
    oriented: bool = False,
    min_normal_cos: float = 0.0,
    max_below: float = 0.87,
) -> tuple[dict[tuple, int], list[list[tuple]], np.ndarray, np.ndarray | None]:
    """Umbrella triangles of every marker and how many corners voted for each.

    With ``oriented``, each marker's normal is the direction away from the
    centre of its wider neighbourhood (:func:`_outward`; radial on a limb); a
    candidate whose normal is more than 90° from the marker's
    (``min_normal_cos``) or that lies more than ~60° below the tangent plane
    (``max_below``: the far side of a thin limb) is dropped, and the umbrella
    is triangulated in that tangent plane.  Returns ``votes, umbrellas, valid,
    normals`` (``normals`` ``None`` unless ``oriented``).
    """
    valid = np.isfinite(reference).all(1)
    cand = _candidates(reference, valid, positions, candidates, max_edge, max_stretch)
    nrm = None
    if oriented:
        nrm = marker_normals(reference, k=NORMAL_K)
        for i in np.flatnonzero(valid):
            c = cand[i]
            if len(c) == 0:
                continue
            e = reference[c] - reference[i]
            below = -(e @ nrm[i]) / np.maximum(np.linalg.norm(e, axis=1), 1e-15)
            cand[i] = c[(nrm[c] @ nrm[i] > min_normal_cos) & (below < max_below)]
    votes: dict[tuple, int] = {}
    umbrellas: list[list[tuple]] = [[] for _ in range(len(reference))]
    for i in np.flatnonzero(valid):
        umbrellas[i] = _umbrella(reference, int(i), cand[i], max_angle,
                                 None if nrm is None else nrm[i])
        for tri in umbrellas[i]:
            votes[tri] = votes.get(tri, 0) + 1
    return votes, umbrellas, valid, nrm


def triangulate_markers(
    reference: np.ndarray,
    *,
    positions: np.ndarray | None = None,
    candidates: int = 10,
    max_edge: float = 2.0,
    max_stretch: float = 0.2,
    max_angle: float = np.deg2rad(150.0),
    close_holes: bool = False,
    max_hole: int = 40,
    min_piece: int = 12,
) -> np.ndarray:
    """Triangle mesh over markers from tangent-plane umbrellas with voting.

    Parameters
    ----------
    reference : (M, 3) float ndarray
        Reference pose; rows with NaN are left out of the mesh.
    positions : (F, M, 3) float ndarray, optional
        The whole capture, used to drop candidate pairs whose distance varies
        by more than ``max_stretch`` (not on one skin patch).
    candidates : int
        Nearest markers considered per marker.
    max_edge : float
        Candidates farther than this many times the marker's local spacing are dropped.
    max_stretch : float
        Largest relative standard deviation of a neighbour distance.
    max_angle : float
        Umbrella triangles with an angle above this at the marker are dropped (radians).
    close_holes : bool
        ``True``: a 2-manifold — the umbrella triangles are added greedily (most
        votes, then shortest perimeter first) only where they keep every edge
        on at most two triangles and do not fold over a neighbour
        (:func:`manifold_triangles`), the result is wound consistently and the
        remaining holes of at most ``max_hole`` edges are closed by minimum-area
        triangulation without stretching edges (:func:`fill_surface_holes`).
        ``False``: the plain vote (triangles in the umbrellas of two corners, plus
        islands' own umbrellas and once-voted bridges), which may leave holes and
        edges on three or more triangles.
    max_hole : int
        Longest boundary loop (edges) that is closed.
    min_piece : int
        With ``close_holes``, pieces of fewer triangles are dropped before the
        holes are closed, and their markers are then inserted into the surface
        (:func:`insert_markers`).

    Returns
    -------
    (T, 3) int ndarray
        Triangles as marker indices: sorted corners (unoriented) when
        ``close_holes`` is ``False``, wound consistently otherwise.
    """
    reference = np.asarray(reference, dtype=np.float64)
    votes, umbrellas, valid, normals = _vote(reference, positions, candidates, max_edge,
                                             max_stretch, max_angle, oriented=close_holes)
    if close_holes:
        if positions is not None and max_stretch > 0 and votes:
            votes = _rigid_triangles(positions, votes, max_stretch)
        faces = manifold_triangles(reference, votes, normals=normals)
        faces = _drop_misoriented(orient_faces(reference, faces))
        faces = _drop_small_pieces(faces, min_piece)
        faces = fill_surface_holes(reference, faces, positions=positions, max_stretch=max_stretch,
                           max_hole=max_hole)
        faces = insert_markers(reference, faces)
        faces = flip_edges(reference, faces, positions=positions, max_stretch=max_stretch)
        if len(faces):
            return faces
        # a handful of markers: no normals to speak of; fall back on the plain vote
        votes, umbrellas, valid, _ = _vote(reference, positions, candidates, max_edge,
                                           max_stretch, max_angle)
    kept = {t for t, v in votes.items() if v >= 2}
    # markers left with < 3 neighbours keep their own umbrella
    nb_count = _ring_sizes(kept, len(reference))
    for i in np.flatnonzero(valid & (nb_count < 3)):
        kept.update(umbrellas[i])
    kept |= _bridges(kept, [t for t, v in votes.items() if v == 1], reference)
    if not kept:
        return np.zeros((0, 3), dtype=np.int64)
    return np.array(sorted(kept), dtype=np.int64)


# --------------------------------------------------------------------------- 2-manifold


def _edge_key(a: int, b: int) -> tuple[int, int]:
    return (a, b) if a < b else (b, a)


def _fold_angle(p: np.ndarray, a: int, b: int, c: int, d: int) -> float:
    """Interior angle (radians) between triangles ``abc`` and ``abd`` about edge ``ab``."""
    e = p[b] - p[a]
    e = e / max(np.linalg.norm(e), 1e-15)
    u = p[c] - p[a]
    w = p[d] - p[a]
    u = u - (u @ e) * e
    w = w - (w @ e) * e
    cos = u @ w / max(np.linalg.norm(u) * np.linalg.norm(w), 1e-15)
    return float(np.arccos(np.clip(cos, -1.0, 1.0)))


def manifold_triangles(
    reference: np.ndarray,
    votes: dict[tuple, int],
    *,
    min_fold: float = np.deg2rad(60.0),
    normals: np.ndarray | None = None,
    max_tilt: float = np.deg2rad(70.0),
    wedge_tol: float = np.deg2rad(5.0),
) -> np.ndarray:
    """Greedy 2-manifold subset of candidate triangles.

    Triangles are taken most votes first, then shortest perimeter first; one is
    added only when each of its edges is on at most one triangle so far, the
    interior angle with each such neighbour is at least ``min_fold`` (no folded
    fins) and no corner's umbrella is already closed.  With ``normals``, a
    triangle must also face within ``max_tilt`` of each corner's normal, and its
    angular wedge at each corner (in the corner's tangent plane) may overlap the
    wedges already there by at most ``wedge_tol``: umbrellas do not wrap twice,
    so no tunnels or doubled layers form.

    Parameters
    ----------
    reference : (M, 3) float ndarray
    votes : dict
        Candidate triangle (sorted corner tuple) → number of votes.
    min_fold : float
        Smallest interior angle between adjacent triangles (radians; π = flat).
    normals : (M, 3) float ndarray, optional
        Unit marker normals (:func:`marker_normals`).
    max_tilt, wedge_tol : float
        Radians.

    Returns
    -------
    (T, 3) int ndarray
        Unoriented triangles; every edge on at most two.
    """
    if not votes:
        return np.zeros((0, 3), dtype=np.int64)
    tris = np.array(list(votes), dtype=np.int64)
    v = np.array(list(votes.values()))
    p = reference
    per = sum(np.linalg.norm(p[tris[:, k]] - p[tris[:, (k + 1) % 3]], axis=1) for k in range(3))
    order = np.lexsort((per, -v))
    wedges: list[list[tuple[float, float]]] = [[] for _ in range(len(p))]
    if normals is not None:
        fn = np.cross(p[tris[:, 1]] - p[tris[:, 0]], p[tris[:, 2]] - p[tris[:, 0]])
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-15)
        cos = np.einsum("tj,tkj->tk", fn, normals[tris])  # (T, 3)
        cos *= np.sign(cos.sum(1, keepdims=True))
        upright = (cos > np.cos(max_tilt)).all(1)
        order = order[upright[order]]
        arcs = _wedge_arcs(p, normals, tris)
    edge_third: dict[tuple[int, int], list[int]] = {}
    open_edges = np.zeros(len(p), dtype=np.int64)  # edges on one triangle, per marker
    n_faces = np.zeros(len(p), dtype=np.int64)
    out = []
    for t in order:
        a, b, c = (int(x) for x in tris[t])
        corners = ((a, b, c), (b, c, a), (c, a, b))
        if any(n_faces[x] and not open_edges[x] for x in (a, b, c)):
            continue  # a closed umbrella cannot take another triangle
        ok = True
        for x, y, z in corners:
            other = edge_third.get(_edge_key(x, y), [])
            if len(other) >= 2 or (other and _fold_angle(p, x, y, z, other[0]) < min_fold):
                ok = False
                break
        if not ok:
            continue
        if normals is not None:
            if any(_overlaps(wedges[x], arcs[t, k], wedge_tol) for k, x in enumerate(tris[t])):
                continue
            for k, x in enumerate(tris[t]):
                wedges[x].append(tuple(arcs[t, k]))
        for x, y, z in corners:
            key = _edge_key(x, y)
            other = edge_third.setdefault(key, [])
            other.append(z)
            delta = 1 if len(other) == 1 else -1
            open_edges[x] += delta
            open_edges[y] += delta
        n_faces[[a, b, c]] += 1
        out.append((a, b, c))
    return np.array(out, dtype=np.int64).reshape(-1, 3)


def _wedge_arcs(p: np.ndarray, normals: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Angular interval each triangle covers around each corner, in the corner's tangent plane.

    Returns ``(T, 3, 2)``: start angle and (positive, < π) length of the arc.
    """
    n = normals[tris]  # (T, 3, 3)
    ref = np.where(np.abs(n[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    u = np.cross(n, ref)
    u /= np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-15)
    w = np.cross(n, u)
    out = np.zeros(tris.shape + (2,))
    for k in range(3):
        x = p[tris[:, k]]
        ang = []
        for other in ((k + 1) % 3, (k + 2) % 3):
            e = p[tris[:, other]] - x
            ang.append(np.arctan2(np.einsum("ij,ij->i", e, w[:, k]),
                                  np.einsum("ij,ij->i", e, u[:, k])))
        d = np.mod(ang[1] - ang[0], 2 * np.pi)
        fwd = d <= np.pi
        out[:, k, 0] = np.where(fwd, ang[0], ang[1])
        out[:, k, 1] = np.where(fwd, d, 2 * np.pi - d)
    return out


def _overlaps(arcs: list[tuple[float, float]], arc: np.ndarray, tol: float) -> bool:
    """Whether ``arc`` (start, length) overlaps any of ``arcs`` by more than ``tol``."""
    b0, lb = float(arc[0]), float(arc[1])
    for a0, la in arcs:
        if (np.mod(b0 - a0, 2 * np.pi) < la - tol or np.mod(a0 - b0, 2 * np.pi) < lb - tol):
            return True
    return False


def _edge_faces(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique undirected edges, their face count and an edge index per face corner."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    ue, inv, cnt = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    return ue, cnt, inv.reshape(3, -1).T


def orient_faces(reference: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Wind triangles consistently across shared edges, outward per connected piece.

    Orientation spreads across edges shared by exactly two triangles (breadth
    first); each piece so reached is then flipped as a whole when most of its
    area faces inward (towards the centre of the markers' wider neighbourhood,
    or by signed volume for a closed piece).

    Parameters
    ----------
    reference : (M, 3) float ndarray
    faces : (T, 3) int ndarray

    Returns
    -------
    (T, 3) int ndarray
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3).copy()
    T = len(faces)
    if T == 0:
        return faces
    ue, cnt, fe = _edge_faces(faces)
    fid = np.repeat(np.arange(T)[:, None], 3, 1)
    pair = cnt[fe] == 2
    # the two faces on each manifold edge
    ek, ef = fe[pair], fid[pair]
    srt = np.argsort(ek, kind="stable")
    ek, ef = ek[srt], ef[srt]
    f0, f1 = ef[0::2], ef[1::2]
    g = coo_matrix((np.ones(len(f0)), (f0, f1)), shape=(T, T)).tocsr()
    g = g + g.T
    n_comp, comp = connected_components(g, directed=False)
    # directed edge sets for consistency: face j must traverse the shared edge opposite to i
    def directed(f: np.ndarray) -> set[tuple[int, int]]:
        return {(int(f[0]), int(f[1])), (int(f[1]), int(f[2])), (int(f[2]), int(f[0]))}

    nbrs: dict[int, list[int]] = {}
    for a, b in zip(f0, f1):
        nbrs.setdefault(int(a), []).append(int(b))
        nbrs.setdefault(int(b), []).append(int(a))
    done = np.zeros(T, dtype=bool)
    for c in range(n_comp):
        root = int(np.flatnonzero(comp == c)[0])
        order, pred = breadth_first_order(g, root, directed=False)
        done[root] = True
        for j in order[1:]:
            i = int(pred[j])
            if directed(faces[i]) & directed(faces[j]):
                faces[j] = faces[j][[0, 2, 1]]
            done[j] = True
    # outward per piece
    valid = np.isfinite(reference).all(1)
    outward = _outward(reference, valid)
    fn = _face_normals(reference, faces)
    score = np.einsum("ij,ij->i", fn, np.nan_to_num(outward[faces].sum(1)))
    a = reference[faces[:, 0]]
    vol = np.einsum("ij,ij->i", a, fn)  # 6 x signed volume of the tetra with the origin
    closed = np.zeros(n_comp, dtype=bool)
    edge_comp_open = np.bincount(comp[fid[cnt[fe] == 1]], minlength=n_comp)
    closed = edge_comp_open == 0
    s_out = np.bincount(comp, weights=score, minlength=n_comp)
    s_vol = np.bincount(comp, weights=vol, minlength=n_comp)
    flip_comp = np.where(closed, s_vol < 0, s_out < 0)
    flip = flip_comp[comp]
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return faces


def _drop_misoriented(faces: np.ndarray) -> np.ndarray:
    """Remove the triangles on edges that two triangles traverse the same way."""
    de = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    _, inv, cnt = np.unique(de, axis=0, return_inverse=True, return_counts=True)
    bad = (cnt[inv.reshape(3, -1)] > 1).any(0)
    return faces[~bad]


def _drop_small_pieces(faces: np.ndarray, min_faces: int) -> np.ndarray:
    """Remove edge-connected pieces of fewer than ``min_faces`` triangles (unless all are)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(faces) == 0:
        return faces
    _, _, fe = _edge_faces(faces)
    T = len(faces)
    f = np.repeat(np.arange(T), 3)
    g = coo_matrix((np.ones(3 * T), (f, fe.ravel())), shape=(T, int(fe.max()) + 1)).tocsr()
    _, comp = connected_components(g @ g.T, directed=False)
    size = np.bincount(comp)
    keep = size[comp] >= min(min_faces, size.max())
    return faces[keep]


def _hole_loops(faces: np.ndarray, reference: np.ndarray | None = None) -> list[list[int]]:
    """Boundary loops of consistently wound triangles, as marker sequences.

    Each loop runs against the winding of its triangles (the direction a
    triangle filling the hole traverses it).  Where a loop reaches a marker
    with several ways on (two fans meeting at the marker), it takes the one
    that keeps the same gap between the fans (the smallest turn, about the
    marker's normal, from the way in; needs ``reference``); a loop passing a
    marker twice is split there.
    """
    ue, cnt, fe = _edge_faces(faces)
    one = cnt[fe] == 1  # (T, 3): corner k's edge (k, k+1) is on this triangle only
    hole: dict[int, list[int]] = {}
    for t, k in zip(*np.nonzero(one)):
        a, b = int(faces[t, k]), int(faces[t, (k + 1) % 3])
        hole.setdefault(b, []).append(a)  # hole half-edge b -> a
    vn = None
    if reference is not None:
        vn = np.zeros((len(reference), 3))
        fn = _face_normals(reference, faces)
        for k in range(3):
            np.add.at(vn, faces[:, k], fn)

    def pick(prev: int, v: int) -> int:
        outs = hole[v]
        if len(outs) == 1 or vn is None:
            return outs.pop()
        n = vn[v] / max(np.linalg.norm(vn[v]), 1e-15)
        u = reference[prev] - reference[v]
        u -= (u @ n) * n
        w = np.cross(n, u)
        d = reference[outs] - reference[v]
        ang = np.mod(-np.arctan2(d @ w, d @ u), 2 * np.pi)  # clockwise turn from the way in
        return outs.pop(int(np.argmin(ang)))

    loops = []
    while hole:
        start = next(iter(hole))
        path = [start]
        v = start
        prev = -1
        while True:
            nxt = hole[v].pop() if prev < 0 else pick(prev, v)
            prev = v
            if not hole[v]:
                del hole[v]
            if nxt == start:
                break
            path.append(nxt)
            v = nxt
            if v not in hole:  # open chain (non-manifold input): give up on it
                path = []
                break
        loops.extend(_split_loop(path))
    return loops


def _split_loop(path: list[int]) -> list[list[int]]:
    """Split a closed marker sequence at repeated markers into simple loops."""
    out: list[list[int]] = []
    stack: list[int] = []
    seen: dict[int, int] = {}
    for v in path:
        if v in seen:
            k = seen[v]
            out.append(stack[k:])
            for u in stack[k + 1:]:
                del seen[u]
            stack = stack[: k + 1]
        else:
            seen[v] = len(stack)
            stack.append(v)
    if len(stack) >= 3:
        out.append(stack)
    return [lp for lp in out if len(lp) >= 3]


def _fill_loop(reference: np.ndarray, loop: list[int], allowed: np.ndarray,
               outside: np.ndarray | None = None, min_fold: float = 0.0) -> list[tuple]:
    """Minimum-area triangulation of a boundary loop (Liepa 2003 dynamic programme).

    ``allowed[i, k]``: loop markers ``i`` and ``k`` may be joined by a new edge.
    ``outside[i]``: the third corner of the existing triangle on the loop edge
    ``(i, i + 1)``; a new triangle on that edge must meet it at an interior angle
    of at least ``min_fold`` (no folding back onto the surface).
    Returns the triangles ``(loop[i], loop[m], loop[k])`` with ``i < m < k`` (wound
    like the loop), or ``[]`` when no triangulation uses only allowed edges.
    """
    n = len(loop)
    p = reference[loop]
    W = np.full((n, n), np.inf)
    best = np.full((n, n), -1, dtype=np.int64)
    for i in range(n - 1):
        W[i, i + 1] = 0.0

    def folds(a: int, b: int, x: int) -> bool:  # new triangle on loop edge (a, b), apex x
        c = outside[a] if b == (a + 1) % n else outside[b]
        return outside is not None and c >= 0 and _fold_angle(
            reference, loop[a], loop[b], loop[x], int(c)) < min_fold

    for span in range(2, n):
        for i in range(n - span):
            k = i + span
            if not allowed[i, k]:
                continue
            m = np.arange(i + 1, k)
            area = 0.5 * np.linalg.norm(np.cross(p[m] - p[i], p[k] - p[i]), axis=1)
            w = W[i, m] + W[m, k] + area
            if outside is not None:
                if folds(i, i + 1, k):
                    w[0] = np.inf
                if folds(k - 1, k, i):
                    w[-1] = np.inf
                if i == 0 and k == n - 1:
                    w[[folds(n - 1, 0, int(x)) for x in m]] = np.inf
            j = int(np.argmin(w))
            if np.isfinite(w[j]):
                W[i, k] = w[j]
                best[i, k] = m[j]
    if not np.isfinite(W[0, n - 1]):
        return []
    out = []
    stack = [(0, n - 1)]
    while stack:
        i, k = stack.pop()
        if k - i < 2:
            continue
        m = int(best[i, k])
        out.append((loop[i], loop[m], loop[k]))
        stack += [(i, m), (m, k)]
    return out


def _spacing(reference: np.ndarray) -> np.ndarray:
    """``(M,)`` mean distance of each marker to its 3 nearest (NaN off the surface)."""
    out = np.full(len(reference), np.nan)
    idx = np.flatnonzero(np.isfinite(reference).all(1))
    if len(idx) < 2:
        return out
    k = min(4, len(idx))
    d, _ = cKDTree(reference[idx]).query(reference[idx], k=k)
    out[idx] = d[:, 1:].mean(1)
    return out


def fill_surface_holes(
    reference: np.ndarray,
    faces: np.ndarray,
    *,
    positions: np.ndarray | None = None,
    max_stretch: float = 0.2,
    max_hole: int = 40,
    max_edge: float = 3.0,
    min_fold: float = np.deg2rad(35.0),
) -> np.ndarray:
    """Close the holes of a consistently wound triangle mesh.

    Every boundary loop of at most ``max_hole`` edges is triangulated with the
    least total area (Liepa 2003) using no edge that already exists (which
    would then be on three triangles), no edge longer than ``max_edge`` times
    the larger local marker spacing of its ends (mean distance to the 3 nearest
    markers: the open end of a wide tube stays open) and, when the capture is given,
    no edge whose length varies by more than ``max_stretch``
    (:func:`edge_stretch`): a gap between an arm and the torso, or between the
    legs, stays open.  A new triangle must meet the old one across a loop edge
    at an interior angle of at least ``min_fold`` (no lid folded back onto an
    open patch).  A loop that cannot be closed so is left open.

    Parameters
    ----------
    reference : (M, 3) float ndarray
    faces : (T, 3) int ndarray
        Wound consistently (:func:`orient_faces`).
    positions : (F, M, 3) float ndarray, optional
    max_stretch : float
    max_hole : int
    max_edge : float
    min_fold : float
        Radians.

    Returns
    -------
    (T', 3) int ndarray
        ``faces`` followed by the new triangles (same winding).
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return faces
    ue, _, _ = _edge_faces(faces)
    existing = {(int(a), int(b)) for a, b in ue}
    # half-edge (a, b) of a triangle -> its third corner
    third = {(int(t[k]), int(t[(k + 1) % 3])): int(t[(k + 2) % 3]) for t in faces for k in range(3)}
    spacing = _spacing(reference)
    new: list[tuple] = []
    for loop in _hole_loops(faces, reference):
        n = len(loop)
        if n > max_hole:
            continue
        lp = np.asarray(loop)
        length = np.linalg.norm(reference[lp][:, None] - reference[lp][None], axis=-1)
        allowed = length <= max_edge * np.maximum(spacing[lp][:, None], spacing[lp][None])
        allowed[np.arange(n), (np.arange(n) + 1) % n] = True  # the loop's own edges
        allowed[(np.arange(n) + 1) % n, np.arange(n)] = True
        for i in range(n):
            for k in range(i + 2, n):
                if (i, k) != (0, n - 1) and _edge_key(loop[i], loop[k]) in existing:
                    allowed[i, k] = allowed[k, i] = False
        if positions is not None and max_stretch > 0:
            ii, kk = np.triu_indices(n, 2)
            s = edge_stretch(positions, np.stack([lp[ii], lp[kk]], 1))
            bad = s > max_stretch
            allowed[ii[bad], kk[bad]] = allowed[kk[bad], ii[bad]] = False
            allowed[0, n - 1] = allowed[n - 1, 0] = True  # a loop edge
        outside = np.array([third.get((loop[(i + 1) % n], loop[i]), -1) for i in range(n)])
        tris = _fill_loop(reference, loop, allowed, outside, min_fold)
        for a, b, c in tris:
            for x, y in ((a, b), (b, c), (c, a)):
                existing.add(_edge_key(x, y))
        new += tris
    if not new:
        return faces
    return np.concatenate([faces, np.array(new, dtype=np.int64)])


def insert_markers(reference: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Put the markers that are on no triangle onto the surface.

    Each such marker (with a reference position) splits the triangle whose
    centroid is nearest into three, keeping the winding, so the surface stays
    a 2-manifold and every marker gets a one-ring.

    Parameters
    ----------
    reference : (M, 3) float ndarray
    faces : (T, 3) int ndarray
        Wound consistently.

    Returns
    -------
    (T', 3) int ndarray
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    valid = np.isfinite(reference).all(1)
    missing = np.flatnonzero(valid & ~np.isin(np.arange(len(reference)), faces))
    if len(faces) == 0 or len(missing) == 0:
        return faces
    faces = faces.copy()
    for m in missing:
        cen = reference[faces].mean(1)
        t = int(np.argmin(np.linalg.norm(cen - reference[m], axis=1)))
        a, b, c = (int(x) for x in faces[t])
        faces[t] = (a, b, m)
        faces = np.concatenate([faces, [[b, c, m], [c, a, m]]])
    return faces


def pinched_markers(faces: np.ndarray) -> np.ndarray:
    """Markers whose triangles form more than one fan (joined only at the marker).

    Parameters
    ----------
    faces : (T, 3) int ndarray

    Returns
    -------
    (P,) int ndarray
        Sorted marker indices.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return np.zeros(0, dtype=np.int64)
    T = len(faces)
    _, _, fe = _edge_faces(faces)
    # corner (t, k) touches edges k = (k, k+1) and k-1 = (k-1, k); corners of one
    # marker meeting on an edge are in one fan
    node = np.concatenate([np.arange(T) * 3 + k for k in range(3) for _ in (0, 1)])
    key = np.concatenate([np.stack([faces[:, k], fe[:, e]], 1)
                          for k in range(3) for e in (k, (k + 2) % 3)])
    _, kid = np.unique(key, axis=0, return_inverse=True)
    n = 3 * T + int(kid.max()) + 1
    g = coo_matrix((np.ones(len(node)), (node, 3 * T + kid.ravel())), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    pieces = np.unique(np.stack([faces.ravel(), lab[: 3 * T]], 1), axis=0)
    cnt = np.bincount(pieces[:, 0])
    return np.flatnonzero(cnt > 1)


def _angle(p: np.ndarray, at: int, u: int, v: int) -> float:
    e1, e2 = p[u] - p[at], p[v] - p[at]
    c = float(e1 @ e2) / max(math.sqrt(float(e1 @ e1) * float(e2 @ e2)), 1e-30)
    return math.acos(min(1.0, max(-1.0, c)))


def _pair_stretch(pos: np.ndarray, a: int, b: int, min_frames: int = 10) -> float:
    """:func:`edge_stretch` of one pair on already subsampled ``pos`` (F', M, 3)."""
    d = np.sqrt(((pos[:, a] - pos[:, b]) ** 2).sum(-1))
    d = d[np.isfinite(d)]
    if len(d) < min_frames:
        return math.nan
    return float(d.std() / max(float(np.median(d)), 1e-12))


def flip_edges(
    reference: np.ndarray,
    faces: np.ndarray,
    *,
    positions: np.ndarray | None = None,
    max_stretch: float = 0.2,
    min_fold: float = np.deg2rad(120.0),
    max_passes: int = 10,
) -> np.ndarray:
    """Flip edges towards a Delaunay mesh, without folding or stretching edges.

    An edge ``ab`` between triangles ``abc`` and ``bad`` becomes ``cd`` when the
    angles opposite it sum to more than π, ``cd`` is not an edge yet, ``a`` and
    ``b`` keep at least three neighbours, the two new triangles meet at an
    interior angle of at least ``min_fold`` and face the old triangles' way, and
    (with the capture) ``cd`` stretches by at most ``max_stretch``.  Mends the
    thin triangles of hole filling and marker insertion.

    Parameters
    ----------
    reference : (M, 3) float ndarray
    faces : (T, 3) int ndarray
        A consistently wound 2-manifold.
    positions : (F, M, 3) float ndarray, optional
    max_stretch, min_fold : float
    max_passes : int

    Returns
    -------
    (T, 3) int ndarray
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3).copy()
    if len(faces) < 2 or surface_topology(faces)["nonmanifold_edges"]:
        return faces
    p = reference
    tri = faces.tolist()
    half = {}
    for t, (a, b, c) in enumerate(tri):
        half[(a, b)], half[(b, c)], half[(c, a)] = t, t, t
    valence = np.bincount(_edge_faces(faces)[0].ravel(), minlength=len(p))
    stretch: dict[tuple[int, int], float] = {}
    pos = None
    if positions is not None and max_stretch > 0:
        pos = positions[:: max(1, positions.shape[0] // 400)]  # as edge_stretch
    for _ in range(max_passes):
        flipped = 0
        for (a, b), t1 in list(half.items()):
            if a > b or half.get((a, b)) != t1 or (b, a) not in half:
                continue
            t2 = half[(b, a)]
            c = next(x for x in tri[t1] if x != a and x != b)
            d = next(x for x in tri[t2] if x != a and x != b)
            if c == d or (c, d) in half or (d, c) in half or min(valence[a], valence[b]) <= 3:
                continue
            if _angle(p, c, a, b) + _angle(p, d, a, b) <= np.pi + 1e-9:
                continue
            n_old = np.cross(p[b] - p[a], p[c] - p[a]) + np.cross(p[a] - p[b], p[d] - p[b])
            n1 = np.cross(p[a] - p[c], p[d] - p[c])
            n2 = np.cross(p[b] - p[d], p[c] - p[d])
            if n1 @ n_old <= 0 or n2 @ n_old <= 0 or _fold_angle(p, c, d, a, b) < min_fold:
                continue
            if pos is not None:
                key = _edge_key(c, d)
                if key not in stretch:
                    stretch[key] = _pair_stretch(pos, c, d)
                if stretch[key] > max_stretch:
                    continue
            for x, y in ((a, b), (b, c), (c, a), (b, a), (a, d), (d, b)):
                del half[(x, y)]
            tri[t1] = [c, a, d]
            tri[t2] = [d, b, c]
            for x, y, t in ((c, a, t1), (a, d, t1), (d, c, t1), (d, b, t2), (b, c, t2),
                            (c, d, t2)):
                half[(x, y)] = t
            valence[[a, b]] -= 1
            valence[[c, d]] += 1
            flipped += 1
        if not flipped:
            break
    return np.array(tri, dtype=np.int64).reshape(-1, 3)


def surface_topology(faces: np.ndarray) -> dict[str, int]:
    """Counts that say whether a triangle mesh is a closed, oriented 2-manifold.

    Parameters
    ----------
    faces : (T, 3) int ndarray

    Returns
    -------
    dict
        ``vertices``, ``edges``, ``faces``, ``euler`` (V − E + F over the markers
        on a triangle; 2 for a closed sphere-like surface), ``boundary_edges``
        (on one triangle), ``nonmanifold_edges`` (on three or more),
        ``boundary_loops``, ``components``, ``misoriented_edges`` (a directed
        edge used by two triangles: neighbours wound against each other),
        ``nonmanifold_vertices`` (:func:`pinched_markers`).
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return dict.fromkeys(("nonmanifold_vertices", "vertices", "edges", "faces", "euler",
                              "boundary_edges", "nonmanifold_edges", "boundary_loops",
                              "components", "misoriented_edges"), 0)
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ue, cnt, _ = _edge_faces(faces)
    used = np.unique(faces)
    n = int(used.max()) + 1
    bnd = ue[cnt == 1]

    def n_comp(edges: np.ndarray, nodes: np.ndarray) -> int:
        g = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
        _, lab = connected_components(g, directed=False)
        return len(np.unique(lab[nodes]))

    de = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    _, dcnt = np.unique(de, axis=0, return_counts=True)
    return {
        "nonmanifold_vertices": len(pinched_markers(faces)),
        "vertices": len(used),
        "edges": len(ue),
        "faces": len(faces),
        "euler": len(used) - len(ue) + len(faces),
        "boundary_edges": len(bnd),
        "nonmanifold_edges": int((cnt > 2).sum()),
        "boundary_loops": n_comp(bnd, np.unique(bnd)) if len(bnd) else 0,
        "components": n_comp(ue, used),
        "misoriented_edges": int((dcnt > 1).sum()),
    }


def _bridges(kept: set[tuple], single: list[tuple], reference: np.ndarray) -> set[tuple]:
    """Once-voted triangles that join separate pieces of the mesh, shortest first.

    Where the marker spacing changes abruptly (a sparse head over a dense neck)
    the dense side's umbrellas do not reach the sparse side and the vote leaves
    islands; the sparse side's own triangles reconnect them.
    """
    parent = list(range(len(reference)))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b, c in kept:
        parent[find(b)] = find(a)
        parent[find(c)] = find(a)
    per = [float(np.linalg.norm(reference[a] - reference[b]) + np.linalg.norm(reference[b]
           - reference[c]) + np.linalg.norm(reference[c] - reference[a])) for a, b, c in single]
    out = set()
    for k in np.argsort(per):
        a, b, c = single[k]
        roots = {find(a), find(b), find(c)}
        if len(roots) > 1:
            out.add(single[k])
            r0 = roots.pop()
            for r in roots:
                parent[r] = r0
    return out


def _ring_sizes(faces: set[tuple], n: int) -> np.ndarray:
    ring: list[set[int]] = [set() for _ in range(n)]
    for a, b, c in faces:
        ring[a].update((b, c))
        ring[b].update((a, c))
        ring[c].update((a, b))
    return np.array([len(r) for r in ring])


def one_ring(faces: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """One-ring neighbours from a triangle mesh.

    Parameters
    ----------
    faces : (T, 3) int ndarray
    reference : (M, 3) float ndarray
        Reference pose, to sort each ring nearest first.

    Returns
    -------
    (M, K) int ndarray
        Neighbour indices, nearest first, ``-1`` padded (``K`` = largest ring).
    """
    M = len(reference)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.concatenate([edges, edges[:, ::-1]])
    edges = np.unique(edges, axis=0) if len(edges) else edges
    edges = edges[edges[:, 0] != edges[:, 1]]
    if len(edges) == 0:
        return np.full((M, 0), -1, dtype=np.int64)
    d = np.linalg.norm(reference[edges[:, 0]] - reference[edges[:, 1]], axis=1)
    d = np.where(np.isfinite(d), d, np.inf)
    order = np.lexsort((d, edges[:, 0]))
    edges = edges[order]
    counts = np.bincount(edges[:, 0], minlength=M)
    K = int(counts.max())
    out = np.full((M, K), -1, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(edges)) - starts[edges[:, 0]]
    out[edges[:, 0], slot] = edges[:, 1]
    return out


def _face_normals(reference: np.ndarray, faces: np.ndarray) -> np.ndarray:
    a, b, c = (reference[faces[:, k]] for k in range(3))
    return np.cross(b - a, c - a)  # length = 2 * area


def _outward(reference: np.ndarray, valid: np.ndarray, k: int = 30) -> np.ndarray:
    """Per marker, a direction away from the centre of its wider neighbourhood."""
    out = np.full(reference.shape, np.nan)
    idx = np.flatnonzero(valid)
    if len(idx) == 0:
        return out
    tree = cKDTree(reference[idx])
    _, nn = tree.query(reference[idx], k=min(k, len(idx)))
    nn = np.atleast_2d(nn)
    out[idx] = reference[idx] - reference[idx][nn].mean(1)
    return out


def local_frames(reference: np.ndarray, faces: np.ndarray, neighbours: np.ndarray) -> tuple[
    np.ndarray, np.ndarray
]:
    """Local reference frames ``(t, b, n)`` of the markers, and consistently wound faces.

    Parameters
    ----------
    reference : (M, 3) float ndarray
    faces : (T, 3) int ndarray
    neighbours : (M, K) int ndarray
        One-ring, nearest first (``t`` points to the first).

    Returns
    -------
    frames : (M, 3, 3) float ndarray
        Rows ``t, b, n``; NaN for markers on no triangle.
    faces : (T, 3) int ndarray
        The faces wound outward (same sense as ``n``): consistently
        (:func:`orient_faces`) on a mesh without edges on 3+ triangles, else
        each triangle on its own.
    """
    M = len(reference)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    valid = np.isfinite(reference).all(1)
    if len(faces) and surface_topology(faces)["nonmanifold_edges"] == 0:
        faces = orient_faces(reference, faces)
        fn = _face_normals(reference, faces)
    else:  # no consistent winding exists: each triangle faces away from its corners' centre
        outward = _outward(reference, valid)
        fn = _face_normals(reference, faces) if len(faces) else np.zeros((0, 3))
        if len(faces):
            flip = np.einsum("ij,ij->i", fn, outward[faces].sum(1)) < 0
            faces = faces.copy()
            faces[flip] = faces[flip][:, [0, 2, 1]]
            fn[flip] *= -1
    n = np.zeros((M, 3))
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    nn = np.linalg.norm(n, axis=1)
    frames = np.full((M, 3, 3), np.nan)
    ok = valid & (nn > 0) & (neighbours.shape[1] > 0)
    if neighbours.shape[1] > 0:
        ok &= neighbours[:, 0] >= 0
    if not ok.any():
        return frames, faces
    n_ = n[ok] / nn[ok, None]
    first = reference[neighbours[ok, 0]] - reference[ok]
    t = first - np.einsum("ij,ij->i", first, n_)[:, None] * n_
    tn = np.linalg.norm(t, axis=1)
    # a first neighbour along the normal (degenerate): use any axis not parallel to n
    bad = tn < 1e-9
    if bad.any():
        alt = np.where(np.abs(n_[bad, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        t[bad] = alt - np.einsum("ij,ij->i", alt, n_[bad])[:, None] * n_[bad]
        tn[bad] = np.linalg.norm(t[bad], axis=1)
    t /= tn[:, None]
    b = np.cross(n_, t)
    frames[ok] = np.stack([t, b, n_], axis=1)
    return frames, faces


def marker_surface_from_faces(
    reference: np.ndarray,
    faces: np.ndarray,
    *,
    labels: list[str] | None = None,
    source: str,
    positions: np.ndarray | None = None,
) -> MarkerSurface:
    """Assemble a :class:`MarkerSurface` (one-ring, frames) from given triangles.

    Parameters
    ----------
    reference : (M, 3) float ndarray
    faces : (T, 3) int ndarray
        Triangles; those touching a marker without reference position are dropped.
    labels : list of str, optional
    source : str
        Where the triangles came from (``"automatic"`` or a file name).
    positions : (F, M, 3) float ndarray, optional
        The capture, for the neighbours' rigidity weights.

    Returns
    -------
    MarkerSurface
    """
    reference = np.asarray(reference, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    valid = np.isfinite(reference).all(1)
    faces = faces[valid[faces].all(1)] if len(faces) else faces
    neighbours = one_ring(faces, reference)
    frames, faces = local_frames(reference, faces, neighbours)
    labels = list(labels) if labels is not None else [f"M{i:03d}" for i in range(len(reference))]
    n_ring = (neighbours >= 0).sum(1)
    rigidity = rigidity_weights(positions, neighbours)
    if positions is not None:
        neighbours, rigidity = supplement_rigid(positions, reference, neighbours, rigidity)
    return MarkerSurface(reference, faces, neighbours, frames, labels, source, rigidity, n_ring)


def build_marker_surface(
    reference: np.ndarray,
    *,
    positions: np.ndarray | None = None,
    labels: list[str] | None = None,
    candidates: int = 10,
    max_edge: float = 2.0,
    max_stretch: float = 0.2,
    close_holes: bool = False,
    max_hole: int = 40,
    reference_frame: int | None = None,
) -> MarkerSurface:
    """Build the marker surface automatically from the reference pose.

    Parameters
    ----------
    reference : (M, 3) float ndarray
        Reference pose (NaN rows are left off the surface).
    positions : (F, M, 3) float ndarray, optional
        The capture, to reject neighbours whose distance is not skin-like stable.
    labels : list of str, optional
    candidates, max_edge, max_stretch, close_holes, max_hole
        See :func:`triangulate_markers`.  ``close_holes=True``: a consistently
        wound 2-manifold, holes closed except where closing them needs a
        stretching, over-long or folding edge (armpits, crotch, wide open
        ends); ``False`` (default): the plain umbrella vote, which may leave
        holes and edges on three or more triangles.
    reference_frame : int, optional
        Capture frame of the reference pose, kept on the surface and in
        :meth:`MarkerSurface.to_mesh` ``attrs``.

    Returns
    -------
    MarkerSurface

    Raises
    ------
    SurfaceInputError
        ``reference`` not ``(M, 3)`` or ``positions`` not ``(F, M, 3)``.
    """
    reference = np.asarray(reference, dtype=np.float64)
    if reference.ndim != 2 or reference.shape[1] != 3:
        raise SurfaceInputError(
            f"marker surface: reference must be (M, 3) marker positions, got shape "
            f"{reference.shape}")
    if positions is not None:
        positions = np.asarray(positions, dtype=np.float64)
        if positions.ndim != 3 or positions.shape[1:] != reference.shape:
            raise SurfaceInputError(
                f"marker surface: positions must be (F, M, 3) with the reference's "
                f"{len(reference)} markers, got shape {positions.shape}")
    faces = triangulate_markers(
        reference,
        positions=positions,
        candidates=candidates,
        max_edge=max_edge,
        max_stretch=max_stretch,
        close_holes=close_holes,
        max_hole=max_hole,
    )
    surf = marker_surface_from_faces(reference, faces, labels=labels, source="automatic",
                                     positions=positions)
    surf.reference_frame = reference_frame
    return surf


# --------------------------------------------------------------------------- override file


def _corner(tok: Any, index: dict[str, int], n: int, where: str) -> int:
    if isinstance(tok, bool):
        raise SurfaceFileError(f"{where}: {tok!r} is not a marker label or index")
    if isinstance(tok, int):
        if not 0 <= tok < n:
            raise SurfaceFileError(f"{where}: marker index {tok} out of range 0..{n - 1}")
        return tok
    s = str(tok).strip()
    if s in index:
        return index[s]
    if s.lstrip("-").isdigit():
        return _corner(int(s), index, n, where)
    raise SurfaceFileError(f"{where}: unknown marker label {s!r}")


def read_surface_file(path: str | Path, labels: list[str]) -> np.ndarray:
    """Read a manual marker-surface file.

    Parameters
    ----------
    path : str or Path
        JSON ``{"faces": [[a, b, c], ...]}`` or text with one triangle per line
        (``a b c`` / ``a,b,c``; ``#`` comments); corners are labels or 0-based indices.
    labels : list of str
        Marker labels of the capture.

    Returns
    -------
    (T, 3) int ndarray

    Raises
    ------
    SurfaceFileError
        Unreadable file, a row without exactly three distinct corners, an unknown
        label (the message names the file and line / row).
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise SurfaceFileError(f"marker surface file {path}: cannot read ({e})") from None
    index = {lb: i for i, lb in enumerate(labels)}
    n = len(labels)
    rows: list[tuple[str, list[Any]]] = []
    if path.suffix.lower() == ".json":
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as e:
            raise SurfaceFileError(f"marker surface file {path}: invalid JSON ({e})") from None
        faces = doc.get("faces") if isinstance(doc, dict) else doc
        if not isinstance(faces, list):
            raise SurfaceFileError(f"marker surface file {path}: expected a 'faces' list")
        rows = [(f"{path}: faces[{i}]", r) for i, r in enumerate(faces)]
    else:
        for ln, line in enumerate(text.splitlines(), 1):
            line = line.split("#", 1)[0].strip()
            if line:
                rows.append((f"{path}:{ln}", line.replace(",", " ").split()))
    out = []
    for where, row in rows:
        if not isinstance(row, list) or len(row) != 3:
            raise SurfaceFileError(f"{where}: a triangle needs exactly 3 corners, got {row!r}")
        tri = [_corner(tok, index, n, where) for tok in row]
        if len(set(tri)) != 3:
            raise SurfaceFileError(f"{where}: triangle corners must be distinct, got {row!r}")
        out.append(tri)
    if not out:
        raise SurfaceFileError(f"marker surface file {path}: no triangles")
    return np.array(out, dtype=np.int64)
