"""Marker surface (Park & Hodgins 2006 §4.1): triangulation, one-ring, local frames, overrides."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mocapflow.stages.surface import (
    SurfaceFileError,
    build_marker_surface,
    edge_stretch,
    local_frames,
    marker_surface_from_faces,
    one_ring,
    read_surface_file,
    rigidity_weights,
    supplement_rigid,
    triangulate_markers,
)


def cylinder_markers(n_around: int = 12, n_along: int = 8, radius: float = 0.1,
                     spacing: float = 0.05) -> np.ndarray:
    """Markers on a cylinder about the y axis, staggered rows (a limb-like patch)."""
    pts = []
    for k in range(n_along):
        for a in range(n_around):
            th = 2 * np.pi * (a + 0.5 * (k % 2)) / n_around
            pts.append([radius * np.cos(th), k * spacing, radius * np.sin(th)])
    return np.array(pts)


def test_cylinder_surface_has_outward_frames_and_symmetric_rings():
    ref = cylinder_markers()
    surf = build_marker_surface(ref)
    M = len(ref)
    # every marker gets a ring; interior markers the 6 of a staggered grid
    assert (surf.n_ring >= 3).all()
    interior = (ref[:, 1] > 0.01) & (ref[:, 1] < ref[:, 1].max() - 0.01)
    assert np.median(surf.n_ring[interior]) == 6
    # rings are symmetric
    for i in range(M):
        for j in surf.neighbours[i, : surf.n_ring[i]]:
            assert i in surf.neighbours[j, : surf.n_ring[j]]
    # one-ring neighbours are near: none farther than 2 x the spacing (~0.05)
    assert np.nanmax(surf.mean_distance) < 0.1
    # frames: orthonormal, right-handed, n radial and outward
    F = surf.frames
    assert np.allclose(np.einsum("mij,mkj->mik", F, F), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(F), 1.0)
    radial = ref * [1, 0, 1] / 0.1
    cosn = np.einsum("mi,mi->m", F[:, 2], radial)
    assert np.median(cosn[interior]) > 0.95
    # t points to the nearest neighbour (projected): positive component
    first = ref[surf.neighbours[:, 0]] - ref
    assert (np.einsum("mi,mi->m", F[:, 0], first) > 0).all()
    # faces wound outward
    a, b, c = (ref[surf.faces[:, k]] for k in range(3))
    fn = np.cross(b - a, c - a)
    centre = (a + b + c) / 3 * [1, 0, 1]
    side = np.abs(fn[:, 1]) < 0.5 * np.linalg.norm(fn, axis=1)  # not across an open end
    assert np.mean(np.einsum("ij,ij->i", fn, centre)[side] > 0) > 0.95


def test_stretch_filter_keeps_separate_limbs_apart():
    # two parallel patches 4 cm apart (closer than their spacing) that slide
    # relative to each other over the capture: no surface edge may join them
    ref_a = cylinder_markers(8, 6, radius=0.06)
    ref_b = ref_a + [0.16, 0.0, 0.0]
    ref = np.concatenate([ref_a, ref_b])
    F = 60
    t = np.linspace(0, 2 * np.pi, F)
    pos = np.repeat(ref[None], F, axis=0)
    pos[:, len(ref_a):, 1] += 0.15 * np.sin(t)[:, None]  # patch b slides along y
    surf = build_marker_surface(ref, positions=pos)
    na = len(ref_a)
    for i in range(len(ref)):
        ring = surf.neighbours[i, : surf.n_ring[i]]
        assert ((ring < na) == (i < na)).all(), f"marker {i} joined to the other patch"
    # without the capture the geometry alone may join them
    faces = triangulate_markers(ref, max_stretch=0)
    assert len(faces)


def test_rigidity_weights_and_two_ring_supplement():
    ref = cylinder_markers(10, 6)
    F = 40
    pos = np.repeat(ref[None], F, axis=0)
    # marker 0's one-ring stretches (its neighbours breathe), the two-ring does not
    surf0 = build_marker_surface(ref)
    ring0 = surf0.neighbours[0, : surf0.n_ring[0]]
    wave = 1 + 0.25 * np.sin(np.linspace(0, 6, F))
    pos[:, ring0] = ref[0] + (ref[ring0] - ref[0]) * wave[:, None, None]
    w = rigidity_weights(pos, surf0.neighbours)
    assert (w[0, : len(ring0)] < 0.2).all()
    moving = set(ring0.tolist()) | {0}
    still = [w[i, k] for i in range(len(ref)) for k, j in enumerate(surf0.neighbours[i])
             if j >= 0 and i not in moving and j not in moving]
    assert len(still) > 50 and np.min(still) > 0.95
    nb, wt = supplement_rigid(pos, ref, surf0.neighbours, w)
    extra = nb[0][(nb[0] >= 0)][len(ring0):]
    assert len(extra) == 3 and (wt[0, len(ring0): len(ring0) + 3] > 0.5).all()
    assert not np.isin(extra, ring0).any()


def test_edge_stretch_exact():
    pos = np.zeros((5, 2, 3))
    pos[:, 1, 0] = [1.0, 1.0, 1.2, 0.8, 1.0]
    s = edge_stretch(pos, np.array([[0, 1]]), min_frames=3)
    assert s[0] == pytest.approx(np.std([1, 1, 1.2, 0.8, 1]) / 1.0)
    assert np.isnan(edge_stretch(pos[:2], np.array([[0, 1]]), min_frames=3))[0]


def test_one_ring_and_frames_from_manual_faces():
    ref = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.5, 0.5, 1.0]], float)
    faces = np.array([[0, 1, 4], [1, 3, 4], [3, 2, 4], [2, 0, 4]])
    nb = one_ring(faces, ref)
    assert sorted(nb[4][nb[4] >= 0]) == [0, 1, 2, 3]
    assert sorted(nb[0][nb[0] >= 0]) == [1, 2, 4]
    frames, wound = local_frames(ref, faces, nb)
    assert np.allclose(np.linalg.det(frames), 1.0)
    assert frames[4, 2, 2] > 0.99  # apex normal points up (away from the base)


def test_isolated_triangle_leaves_markers_with_two_neighbours():
    ref = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [1, 1, 1]], float)
    surf = marker_surface_from_faces(ref, np.array([[0, 1, 2]]), source="test",
                                     positions=np.repeat(ref[None], 20, axis=0))
    assert list(surf.n_neighbours) == [2, 2, 2, 0]
    assert np.isnan(surf.frames[3]).all()


def test_surface_file_formats_and_errors(tmp_path):
    labels = ["A", "B", "C", "D"]
    txt = tmp_path / "surf.txt"
    txt.write_text("# manual surface\nA B C\nB,C,D  # second\n")
    assert read_surface_file(txt, labels).tolist() == [[0, 1, 2], [1, 2, 3]]
    js = tmp_path / "surf.json"
    js.write_text(json.dumps({"faces": [["A", "B", "D"], [0, 2, 3]]}))
    assert read_surface_file(js, labels).tolist() == [[0, 1, 3], [0, 2, 3]]
    bad = tmp_path / "bad.txt"
    bad.write_text("A B C\nA B ZZ\n")
    with pytest.raises(SurfaceFileError, match=r"bad\.txt:2.*unknown marker label 'ZZ'"):
        read_surface_file(bad, labels)
    two = tmp_path / "two.txt"
    two.write_text("A B\n")
    with pytest.raises(SurfaceFileError, match="exactly 3 corners"):
        read_surface_file(two, labels)
    dup = tmp_path / "dup.json"
    dup.write_text(json.dumps({"faces": [["A", "A", "B"]]}))
    with pytest.raises(SurfaceFileError, match=r"faces\[0\].*distinct"):
        read_surface_file(dup, labels)
    with pytest.raises(SurfaceFileError, match="cannot read"):
        read_surface_file(tmp_path / "missing.txt", labels)
    rng_idx = tmp_path / "range.txt"
    rng_idx.write_text("0 1 9\n")
    with pytest.raises(SurfaceFileError, match="out of range"):
        read_surface_file(rng_idx, labels)


def test_to_mesh_carries_labels_and_rings():
    ref = cylinder_markers(8, 4)
    surf = build_marker_surface(ref, labels=[f"m{i}" for i in range(len(ref))])
    mesh = surf.to_mesh()
    assert mesh.vertices.shape == ref.shape and mesh.faces.shape[1] == 3
    assert mesh.attrs["labels"][3] == "m3"
    assert sorted(mesh.attrs["neighbours"][5]) == sorted(
        surf.neighbours[5][surf.neighbours[5] >= 0].tolist())
