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
   (normal = least principal axis of the neighbourhood) and triangulated
   (Delaunay); the triangles incident to the marker form its umbrella;
3. **voting**: a triangle is kept when it is in the umbrellas of at least two of
   its three corners (a marker left with fewer than 3 neighbours keeps its own
   umbrella, and once-voted triangles that join separate pieces are kept, so an
   abrupt change of spacing does not leave islands);
4. **one-ring** neighbours are the markers sharing an edge with the marker;
   **local frames** ``(t, b, n)``: ``n`` the area-weighted mean normal of the
   incident triangles (oriented away from the local body centre), ``t`` the
   direction to the nearest neighbour projected onto the tangent plane,
   ``b = n × t``.

Manual override file (``surface`` param of the ``clean`` stage): either JSON
``{"faces": [[a, b, c], ...]}`` or a text file with one triangle per line
(``a b c`` or ``a,b,c``; ``#`` starts a comment), where corners are marker labels
(or 0-based integer indices).
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from mocapflow.stages.data import Mesh

__all__ = [
    "MarkerSurface",
    "SurfaceFileError",
    "build_marker_surface",
    "edge_stretch",
    "local_frames",
    "marker_surface_from_faces",
    "one_ring",
    "read_surface_file",
    "rigidity_weights",
    "supplement_rigid",
    "triangulate_markers",
]


class SurfaceFileError(ValueError):
    """A manual marker-surface file is unreadable or names unknown markers."""


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
    """

    reference: np.ndarray
    faces: np.ndarray
    neighbours: np.ndarray
    frames: np.ndarray
    labels: list[str] = field(default_factory=list)
    source: str = "automatic"
    rigidity: np.ndarray | None = None
    n_ring: np.ndarray | None = None

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
        """The surface as a :class:`~mocapflow.stages.data.Mesh` (vertices = markers).

        ``attrs`` carry ``labels``, ``neighbours`` (lists of labels' indices) and
        the local frames, so downstream stages (segment, deform) can use it.
        """
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
        med = np.nanmedian(d[:, ok], axis=0)
        sd = np.nanstd(d[:, ok], axis=0)
    out[ok] = sd / np.maximum(med, 1e-12)
    return out


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


def _umbrella(reference: np.ndarray, i: int, cand: np.ndarray, max_angle: float) -> list[tuple]:
    """Triangles incident to marker ``i`` in the tangent-plane Delaunay of its candidates."""
    if len(cand) < 2:
        return []
    pts = reference[np.concatenate([[i], cand])] - reference[i]
    _, _, vt = np.linalg.svd(pts - pts.mean(0), full_matrices=False)
    uv = pts @ vt[:2].T
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


def triangulate_markers(
    reference: np.ndarray,
    *,
    positions: np.ndarray | None = None,
    candidates: int = 10,
    max_edge: float = 2.0,
    max_stretch: float = 0.2,
    max_angle: float = np.deg2rad(150.0),
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

    Returns
    -------
    (T, 3) int ndarray
        Triangles as sorted marker indices (unoriented).
    """
    reference = np.asarray(reference, dtype=np.float64)
    valid = np.isfinite(reference).all(1)
    cand = _candidates(reference, valid, positions, candidates, max_edge, max_stretch)
    votes: dict[tuple, int] = {}
    umbrellas: list[list[tuple]] = [[] for _ in range(len(reference))]
    for i in np.flatnonzero(valid):
        umbrellas[i] = _umbrella(reference, int(i), cand[i], max_angle)
        for tri in umbrellas[i]:
            votes[tri] = votes.get(tri, 0) + 1
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
        The faces wound so their normals point outward (same sense as ``n``).
    """
    M = len(reference)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    valid = np.isfinite(reference).all(1)
    outward = _outward(reference, valid)
    fn = _face_normals(reference, faces) if len(faces) else np.zeros((0, 3))
    # orient faces by the outward direction of their corners
    if len(faces):
        o = outward[faces].sum(1)
        flip = np.einsum("ij,ij->i", fn, o) < 0
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
) -> MarkerSurface:
    """Build the marker surface automatically from the reference pose.

    Parameters
    ----------
    reference : (M, 3) float ndarray
        Reference pose (NaN rows are left off the surface).
    positions : (F, M, 3) float ndarray, optional
        The capture, to reject neighbours whose distance is not skin-like stable.
    labels : list of str, optional
    candidates, max_edge, max_stretch
        See :func:`triangulate_markers`.

    Returns
    -------
    MarkerSurface
    """
    faces = triangulate_markers(
        reference,
        positions=positions,
        candidates=candidates,
        max_edge=max_edge,
        max_stretch=max_stretch,
    )
    return marker_surface_from_faces(reference, faces, labels=labels, source="automatic",
                                     positions=positions)


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
