"""Automatic triangulation of the markers: tangent-plane umbrellas and their vote.

Steps 1–3 of the automatic marker surface (see :mod:`mocapflow.stages.skin.surface`):
candidate neighbours (:func:`_candidates`: nearest markers, not too far, not
stretching over the capture), per-marker umbrellas (:func:`_umbrella`: Delaunay of
the candidates in the tangent plane; with ``close_holes`` the plane is normal to
:func:`marker_normals`), and the selection (:func:`triangulate_markers`): the
plain vote (triangles in the umbrellas of two corners, islands' own umbrellas,
once-voted bridges, :func:`_bridges`) or, with ``close_holes``, the 2-manifold
path of :mod:`mocapflow.stages.skin.manifold`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from mocapflow.stages.skin.manifold import (
    _drop_misoriented,
    _drop_small_pieces,
    _outward,
    fill_surface_holes,
    flip_edges,
    insert_markers,
    manifold_triangles,
    orient_faces,
)
from mocapflow.stages.skin.rigidity import edge_stretch

__all__ = ["NORMAL_K", "marker_normals", "triangulate_markers"]


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


#: Nearest markers of the local plane fit of :func:`marker_normals` (``close_holes``).
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
