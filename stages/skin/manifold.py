"""2-manifold marker surfaces: greedy growth, orientation, hole filling, edge flips, topology.

The ``close_holes=True`` path of the automatic marker surface
(:func:`mocapflow.stages.skin.triangulate.triangulate_markers`) after the umbrella vote:

* :func:`manifold_triangles` — a greedy 2-manifold subset of the voted triangles
  (most votes, then shortest perimeter first; no edge on a third triangle, no
  fold onto a neighbour, facing the corners' normals, wedges that do not overlap);
* :func:`orient_faces` — consistent winding across shared edges, outward per piece
  (also used by :func:`mocapflow.stages.skin.surface.local_frames`);
* :func:`fill_surface_holes` — boundary loops closed by minimum-area triangulation
  (Liepa 2003) without stretching, over-long or folding edges;
* :func:`insert_markers` — markers left on no triangle split their nearest one;
* :func:`flip_edges` — edge flips towards Delaunay, without folds or stretching edges;
* :func:`surface_topology`, :func:`pinched_markers` — what makes a mesh a closed,
  oriented 2-manifold.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components
from scipy.spatial import cKDTree

from mocapflow.stages.skin.rigidity import _pair_stretch, edge_stretch

__all__ = [
    "fill_surface_holes",
    "flip_edges",
    "insert_markers",
    "manifold_triangles",
    "orient_faces",
    "pinched_markers",
    "surface_topology",
]


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
        Unit marker normals (:func:`~mocapflow.stages.skin.triangulate.marker_normals`).
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
