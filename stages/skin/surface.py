"""The marker surface of Park & Hodgins (2006, §4.1): a triangle mesh over the markers.

This module holds the :class:`MarkerSurface` type (reference pose, triangles,
one-ring neighbours, local frames, rigidity weights), its assembly from
triangles (:func:`marker_surface_from_faces`, :func:`build_marker_surface`) and
the manual override file (:func:`read_surface_file`).  The paper built the mesh
by hand in the reference pose.  Here it is built automatically from surface
neighbourhoods, and a manual override file is accepted:

1. **candidates** (:mod:`mocapflow.stages.skin.triangulate`): each marker's
   ``candidates`` nearest markers in the reference pose, dropping those farther
   than ``max_edge`` times the marker's local spacing (mean distance to its 3
   nearest) and — when the whole capture is given — pairs whose distance varies
   over the capture by more than ``max_stretch`` (relative standard deviation,
   :func:`mocapflow.stages.skin.rigidity.edge_stretch`): markers on different
   limbs that happen to be close in the reference pose are not surface neighbours;
2. **umbrellas** (:mod:`mocapflow.stages.skin.triangulate`): the candidates are
   projected onto the marker's tangent plane and triangulated (Delaunay); the
   triangles incident to the marker form its umbrella.  With ``close_holes`` the
   tangent plane is normal to :func:`~mocapflow.stages.skin.triangulate.marker_normals`
   (local principal axis, or the direction away from the wider neighbourhood's
   centre where that is not flat: radial on a thin limb), and candidates facing
   the other way or lying far below the plane (the far side of a limb) are
   dropped; otherwise the normal is the least principal axis of the candidates;
3. **selection** (:func:`mocapflow.stages.skin.triangulate.triangulate_markers`) —
   ``close_holes=True`` (:mod:`mocapflow.stages.skin.manifold`): a 2-manifold is
   grown greedily from the umbrella triangles, most votes (corners whose umbrella
   holds the triangle) and shortest perimeter first, taking a triangle only if
   no edge gets a third triangle, it does not fold onto a neighbour, it faces
   the corners' normals and its wedge overlaps no other at any corner
   (``manifold_triangles``); triangles with a stretching edge are never
   candidates.  It is then wound consistently and outward (``orient_faces``),
   tiny detached pieces are dropped, boundary loops are closed by minimum-area
   triangulation without stretching, over-long or folding edges
   (``fill_surface_holes``; the gaps at the armpits and the crotch, whose
   bridges stretch over the capture, stay open), markers left on no triangle
   split their nearest triangle (``insert_markers``) and edges are flipped
   towards Delaunay (``flip_edges``).
   ``close_holes=False`` (default for now: the ``clean`` stage's tests were
   tuned on it): the plain vote — a triangle is
   kept when it is in the umbrellas of at least two of its three corners (a
   marker left with fewer than 3 neighbours keeps its own umbrella, and
   once-voted triangles that join separate pieces are kept) — which leaves
   holes and edges on three or more triangles;
4. **one-ring** neighbours (:func:`one_ring`) are the markers sharing an edge
   with the marker; **local frames** ``(t, b, n)`` (:func:`local_frames`): ``n``
   the area-weighted mean normal of the incident triangles (wound consistently,
   outward), ``t`` the direction to the nearest neighbour projected onto the
   tangent plane, ``b = n × t``;
5. **rigidity** (:mod:`mocapflow.stages.skin.rigidity`, beyond the paper): each
   neighbour's weight in the rigid fits, and rigid two-ring supplements for
   markers with fewer than 3 rigid neighbours.

:func:`mocapflow.stages.skin.manifold.surface_topology` counts what makes a
surface a closed oriented 2-manifold (boundary / non-manifold / misoriented
edges, pinched markers, boundary loops, Euler characteristic).

Manual override file (``surface`` param of the ``clean`` stage): either JSON
``{"faces": [[a, b, c], ...]}`` or a text file with one triangle per line
(``a b c`` or ``a,b,c``; ``#`` starts a comment), where corners are marker labels
(or 0-based integer indices).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.stages.motion.datatypes import Mesh
from mocapflow.stages.skin.manifold import (
    _face_normals,
    _outward,
    orient_faces,
    surface_topology,
)
from mocapflow.stages.skin.rigidity import (
    _quiet,
    rigidity_weights,
    supplement_rigid,
)
from mocapflow.stages.skin.triangulate import triangulate_markers

__all__ = [
    "MarkerSurface",
    "SurfaceFileError",
    "SurfaceInputError",
    "build_marker_surface",
    "local_frames",
    "marker_surface_from_faces",
    "one_ring",
    "read_surface_file",
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

    @classmethod
    def from_mesh(cls, mesh: Mesh) -> MarkerSurface:
        """The surface back from :meth:`to_mesh` (e.g. the ``surface`` output of ``clean``).

        Reference pose, triangles, neighbours, frames, labels, source and reference
        frame are those of the surface; the rigidity weights come back rounded to 4
        decimals (as :meth:`to_mesh` stores them); ``n_ring`` is recounted from the
        triangles (each row of ``neighbours`` holds the one-ring first, then the
        rigid supplements), so :attr:`mean_distance` is the surface's.

        Parameters
        ----------
        mesh : Mesh
            ``vertices (M, 3)``, ``faces (T, 3)`` and the ``attrs`` of :meth:`to_mesh`.

        Returns
        -------
        MarkerSurface
        """
        attrs = mesh.attrs
        reference = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
        rows, weights = attrs["neighbours"], attrs["rigidity"]
        M = len(reference)
        neighbours = np.full((M, max((len(r) for r in rows), default=0)), -1, dtype=np.int64)
        rigidity = np.zeros(neighbours.shape)
        for i, (r, w) in enumerate(zip(rows, weights)):
            neighbours[i, : len(r)] = r
            rigidity[i, : len(w)] = w
        n_ring = (one_ring(faces, reference) >= 0).sum(1)
        frames = np.asarray(attrs["frames"], dtype=np.float64).reshape(M, 3, 3)
        return cls(reference, faces, neighbours, frames, list(attrs["labels"]),
                   attrs.get("source", "automatic"), rigidity, n_ring,
                   attrs.get("reference_frame"))

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


# --------------------------------------------------------------------------- one-ring, frames


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
