"""Marker surface (Park & Hodgins 2006 §4.1): triangulation, one-ring, local frames, overrides."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mocapflow.stages.skin.manifold import (
    fill_surface_holes,
    insert_markers,
    orient_faces,
    pinched_markers,
    surface_topology,
)
from mocapflow.stages.skin.rigidity import edge_stretch, rigidity_weights, supplement_rigid
from mocapflow.stages.skin.surface import (
    SurfaceFileError,
    SurfaceInputError,
    build_marker_surface,
    local_frames,
    marker_surface_from_faces,
    one_ring,
    read_surface_file,
)
from mocapflow.stages.skin.triangulate import triangulate_markers


def cylinder_markers(n_around: int = 12, n_along: int = 8, radius: float = 0.1,
                     spacing: float = 0.05) -> np.ndarray:
    """Markers on a cylinder about the y axis, staggered rows (a limb-like patch)."""
    pts = []
    for k in range(n_along):
        for a in range(n_around):
            th = 2 * np.pi * (a + 0.5 * (k % 2)) / n_around
            pts.append([radius * np.cos(th), k * spacing, radius * np.sin(th)])
    return np.array(pts)


@pytest.mark.parametrize("close_holes", [False, True])
def test_cylinder_surface_has_outward_frames_and_symmetric_rings(close_holes):
    ref = cylinder_markers()
    surf = build_marker_surface(ref, close_holes=close_holes)
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


@pytest.mark.parametrize("close_holes", [False, True])
def test_stretch_filter_keeps_separate_limbs_apart(close_holes):
    # two parallel patches 4 cm apart (closer than their spacing) that slide
    # relative to each other over the capture: no surface edge may join them
    ref_a = cylinder_markers(8, 6, radius=0.06)
    ref_b = ref_a + [0.16, 0.0, 0.0]
    ref = np.concatenate([ref_a, ref_b])
    F = 60
    t = np.linspace(0, 2 * np.pi, F)
    pos = np.repeat(ref[None], F, axis=0)
    pos[:, len(ref_a):, 1] += 0.15 * np.sin(t)[:, None]  # patch b slides along y
    surf = build_marker_surface(ref, positions=pos, close_holes=close_holes)
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


# --------------------------------------------------------------------------- closed surfaces


def fibonacci_sphere(n: int, radius: float) -> np.ndarray:
    """``n`` nearly evenly spaced markers on a sphere about the origin."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = np.pi * (1 + 5**0.5) * i
    return radius * np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], 1)


def capsule_markers(n: int, radius: float, length: float, rng: np.random.Generator,
                    centre=(0.0, 0.0, 0.0)) -> np.ndarray:
    """``n`` evenly spread markers on a capsule along y (farthest-point sampling)."""
    N = 40 * n
    k = int(N * length / (length + 2 * radius))  # cylinder share of the area
    th = rng.uniform(0, 2 * np.pi, k)
    cyl = np.stack([radius * np.cos(th), rng.uniform(-length / 2, length / 2, k),
                    radius * np.sin(th)], 1)
    v = rng.normal(size=(N - k, 3))
    sph = radius * v / np.linalg.norm(v, axis=1, keepdims=True)
    sph[:, 1] += np.sign(sph[:, 1]) * length / 2
    pts = np.concatenate([cyl, sph])
    chosen, d = [0], np.linalg.norm(pts - pts[0], axis=1)
    for _ in range(n - 1):
        chosen.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(pts - pts[chosen[-1]], axis=1))
    return pts[chosen] + np.asarray(centre)


def outward_fraction(ref: np.ndarray, faces: np.ndarray, axis_mask=(1, 1, 1)) -> float:
    a, b, c = (ref[faces[:, k]] for k in range(3))
    radial = ((a + b + c) / 3 - ref.mean(0)) * axis_mask
    return float(np.mean(np.einsum("ij,ij->i", np.cross(b - a, c - a), radial) > 0))


CLOSED = {"boundary_edges": 0, "nonmanifold_edges": 0, "nonmanifold_vertices": 0,
          "misoriented_edges": 0, "boundary_loops": 0}


@pytest.mark.parametrize("shape", ["sphere", "capsule", "thin capsule"])
def test_closed_shapes_give_closed_oriented_2_manifolds(shape):
    rng = np.random.default_rng(0)
    ref = {"sphere": lambda: fibonacci_sphere(160, 0.12),
           "capsule": lambda: capsule_markers(120, 0.05, 0.3, rng),
           # a limb: 6-7 markers around, like forearms and shins on the body
           "thin capsule": lambda: capsule_markers(60, 0.035, 0.35, rng)}[shape]()
    surf = build_marker_surface(ref, close_holes=True)
    top = surface_topology(surf.faces)
    assert {k: top[k] for k in CLOSED} == CLOSED
    # a sphere: V - E + F = 2, one piece, every marker on it; closed => E = 3F/2
    assert top["euler"] == 2 and top["components"] == 1 and top["vertices"] == len(ref)
    assert 2 * top["edges"] == 3 * top["faces"]
    assert surf.n_ring.min() >= 4 and 5.5 < surf.n_ring.mean() < 6.0  # mean 6 - 12/V
    mask = (1, 1, 1) if shape == "sphere" else (1, 0, 1)
    assert outward_fraction(ref, surf.faces, mask) == 1.0
    # the plain vote (the default) leaves edges on 3+ triangles on this shape
    old = surface_topology(build_marker_surface(ref).faces)
    assert old["nonmanifold_edges"] > 0


def test_two_touching_capsules_stay_apart_when_they_slide():
    rng = np.random.default_rng(1)
    a = capsule_markers(100, 0.05, 0.3, rng)
    b = capsule_markers(100, 0.05, 0.3, rng, centre=(0.12, 0.0, 0.0))  # 2 cm gap, 3 cm spacing
    ref = np.concatenate([a, b])
    F = 60
    pos = np.repeat(ref[None], F, axis=0)
    pos[:, 100:, 1] += 0.15 * np.sin(np.linspace(0, 2 * np.pi, F))[:, None]
    surf = build_marker_surface(ref, positions=pos, close_holes=True)
    top = surface_topology(surf.faces)
    assert {k: top[k] for k in CLOSED} == CLOSED
    assert top["components"] == 2 and top["euler"] == 4  # two spheres
    edges = np.concatenate([surf.faces[:, [0, 1]], surf.faces[:, [1, 2]], surf.faces[:, [2, 0]]])
    assert not np.any((edges[:, 0] < 100) != (edges[:, 1] < 100))  # no bridge
    # from the geometry alone the gap is bridged: the capture is what separates them
    still = build_marker_surface(ref, close_holes=True)
    e2 = np.concatenate([still.faces[:, [0, 1]], still.faces[:, [1, 2]]])
    assert np.any((e2[:, 0] < 100) != (e2[:, 1] < 100))


def test_open_patch_and_tube_ends_stay_open():
    # a 7 x 7 curved patch: its rim is not a hole to close (the lid would fold onto it)
    u, v = np.meshgrid(np.linspace(-0.15, 0.15, 7), np.linspace(-0.15, 0.15, 7))
    ref = np.stack([u.ravel(), v.ravel(), 0.5 * (u.ravel() ** 2 + v.ravel() ** 2)], 1)
    top = surface_topology(build_marker_surface(ref, close_holes=True).faces)
    assert top["boundary_loops"] == 1 and top["euler"] == 1 and top["nonmanifold_edges"] == 0
    assert 18 <= top["boundary_edges"] <= 24
    # a tube 4 spacings wide (12 around): closing its ends needs edges > 3 x the spacing
    ref = cylinder_markers()
    faces = build_marker_surface(ref, close_holes=True).faces
    top = surface_topology(faces)
    assert top["boundary_loops"] == 2 and top["euler"] == 0 and top["nonmanifold_edges"] == 0


def test_fill_holes_closes_a_hole_unless_it_stretches():
    ref = fibonacci_sphere(120, 0.1)
    faces = build_marker_surface(ref, close_holes=True).faces
    ring0 = np.unique(faces[(faces == 0).any(1)])
    holed = faces[~(faces == 0).any(1)]
    top = surface_topology(holed)
    assert top["boundary_loops"] == 1 and top["boundary_edges"] == len(ring0) - 1
    closed = fill_surface_holes(ref, holed)
    assert len(closed) == len(faces) - 2  # n-gon: n - 2 triangles
    top = surface_topology(closed)
    assert top["boundary_edges"] == 0 and top["euler"] == 2 and top["misoriented_edges"] == 0
    assert outward_fraction(ref, closed) == 1.0
    assert surface_topology(fill_surface_holes(ref, holed, max_hole=3))["boundary_edges"] > 0
    # one rim marker slides against the others: no new edge may end on it
    F = 40
    pos = np.repeat(ref[None], F, axis=0)
    k = int(ring0[ring0 != 0][0])
    pos[:, k] += np.outer(np.sin(np.linspace(0, 6, F)), [0.1, 0.1, 0.0])
    left = fill_surface_holes(ref, holed, positions=pos)
    assert len(left) == len(closed)

    def edges(f):
        return {tuple(e) for e in np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), 1)}

    added = np.array(sorted(edges(left) - edges(holed)))
    assert len(added) == len(ring0) - 4 and not (added == k).any()
    assert (edge_stretch(pos, added) < 0.2).all()
    others = ring0[(ring0 != 0) & (ring0 != k)]
    assert (edge_stretch(pos, np.stack([np.full(len(others), k), others], 1)) > 0.2).all()
    # every rim marker sliding its own way: no rigid diagonal, the hole stays open
    pos = np.repeat(ref[None], F, axis=0)
    phase = np.linspace(0, 2 * np.pi, len(ring0), endpoint=False)
    pos[:, ring0] += 0.04 * np.sin(np.linspace(0, 6, F)[:, None, None] + phase[None, :, None])
    assert len(fill_surface_holes(ref, holed, positions=pos)) == len(holed)
    # ... and with it put back, one split triangle: a closed surface again, marker 0 on it
    back = insert_markers(ref, closed)
    top = surface_topology(back)
    assert top["vertices"] == 120 and top["euler"] == 2 and top["boundary_edges"] == 0
    assert (back == 0).any(1).sum() == 3


def test_topology_counts_and_pinched_markers():
    tet = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [0, 2, 3]])
    top = surface_topology(tet)
    assert (top["euler"], top["edges"], top["boundary_edges"], top["misoriented_edges"]) == (
        2, 6, 0, 0)
    flipped = tet.copy()
    flipped[0] = flipped[0][::-1]
    assert surface_topology(flipped)["misoriented_edges"] == 3
    bowtie = np.array([[0, 1, 2], [0, 3, 4]])
    assert pinched_markers(bowtie).tolist() == [0]
    top = surface_topology(bowtie)
    assert (top["boundary_loops"], top["components"], top["nonmanifold_vertices"]) == (1, 1, 1)
    fin = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]])
    assert surface_topology(fin)["nonmanifold_edges"] == 1
    assert surface_topology(np.zeros((0, 3), int))["faces"] == 0


def test_orient_faces_makes_random_windings_consistent_and_outward():
    ref = fibonacci_sphere(100, 0.1)
    faces = build_marker_surface(ref, close_holes=True).faces
    rng = np.random.default_rng(2)
    scrambled = faces.copy()
    flip = rng.random(len(faces)) < 0.5
    scrambled[flip] = scrambled[flip][:, ::-1]
    assert surface_topology(scrambled)["misoriented_edges"] > 50
    fixed = orient_faces(ref, scrambled)
    assert surface_topology(fixed)["misoriented_edges"] == 0
    assert outward_fraction(ref, fixed) == 1.0
    assert sorted(map(sorted, fixed.tolist())) == sorted(map(sorted, faces.tolist()))


def test_bad_input_shapes_are_named():
    with pytest.raises(SurfaceInputError, match=r"reference.*\(M, 3\).*\(5, 2\)"):
        build_marker_surface(np.zeros((5, 2)))
    with pytest.raises(SurfaceInputError, match=r"positions.*5 markers.*\(10, 4, 3\)"):
        build_marker_surface(np.zeros((5, 3)), positions=np.zeros((10, 4, 3)))


def test_to_mesh_carries_the_reference_frame():
    ref = fibonacci_sphere(60, 0.1)
    mesh = build_marker_surface(ref, reference_frame=17).to_mesh()
    assert mesh.attrs["reference_frame"] == 17
    assert np.array_equal(mesh.vertices, ref)
    assert "reference_frame" not in build_marker_surface(ref, close_holes=True).to_mesh().attrs


def test_a_handful_of_markers_falls_back_on_the_plain_vote():
    ref = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0]], float)
    for close_holes in (False, True):
        faces = build_marker_surface(ref, close_holes=close_holes).faces
        assert sorted(faces[0].tolist()) == [0, 1, 2] and len(faces) == 1
