"""Mesh artifact measures (stages/metrics/mesh.py) on triangles with known answers."""

import numpy as np

from mocapflow.stages.metrics.mesh import (
    flipped_triangles,
    stretched_triangles,
    triangle_edge_lengths,
    triangle_normals,
)

REST = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
FACES = np.array([[0, 1, 2], [1, 3, 2]])


def test_edges_and_normals_of_a_unit_square():
    e = triangle_edge_lengths(REST, FACES)
    assert np.allclose(e, [[1, np.sqrt(2), 1], [1, 1, np.sqrt(2)]])
    assert np.allclose(triangle_normals(REST, FACES), [[0, 0, 1], [0, 0, 1]])


def test_stretched_and_flipped_in_some_frame():
    frames = np.repeat(REST[None], 3, 0)
    frames[1, 3] = [2.5, 1, 0]  # frame 1: triangle 1 stretched 2.5x at most (edge 3-2)
    frames[2, 3] = [1, 4.5, 0]  # frame 2: edge 1-3 becomes 4.5 (> 3x), triangle 0 unchanged
    assert stretched_triangles(frames, REST, FACES).tolist() == [False, True]
    assert stretched_triangles(frames[:2], REST, FACES).tolist() == [False, False]
    mirrored = frames.copy()
    mirrored[1, 0] = [0, 2, 0]  # frame 1: triangle 0 turned over (normal -z); 1 lacks vertex 0
    assert flipped_triangles(mirrored, frames, FACES).tolist() == [True, False]
    assert not flipped_triangles(frames, frames, FACES).any()
