"""Surface artifacts of a deformed triangle mesh (skin deformation, issue 15 item 4).

Registers nothing; :func:`triangle_normals` is :mod:`mocapflow.stages.motion.geometry`'s.
"""

from __future__ import annotations

import numpy as np

from mocapflow.stages.motion.geometry import triangle_normals

__all__ = ["flipped_triangles", "stretched_triangles", "triangle_edge_lengths",
           "triangle_normals"]


def triangle_edge_lengths(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Edge lengths of every triangle.

    Parameters
    ----------
    vertices : (..., V, 3) float ndarray
    faces : (T, 3) int ndarray

    Returns
    -------
    (..., T, 3) float ndarray
        Edge ``k`` joins corners ``k`` and ``k + 1``.
    """
    X = np.asarray(vertices)
    return np.stack([np.linalg.norm(X[..., faces[:, (k + 1) % 3], :] - X[..., faces[:, k], :],
                                    axis=-1) for k in range(3)], -1)  # fmt: skip


def stretched_triangles(vertices: np.ndarray, rest: np.ndarray, faces: np.ndarray, *,
                        factor: float = 3.0) -> np.ndarray:
    """Triangles with an edge longer than ``factor`` × its rest length in some frame.

    Parameters
    ----------
    vertices : (F, V, 3) float ndarray
    rest : (V, 3) float ndarray
    faces : (T, 3) int ndarray
    factor : float

    Returns
    -------
    (T,) bool ndarray
    """
    ratio = triangle_edge_lengths(vertices, faces) / triangle_edge_lengths(rest, faces)[None]
    return (ratio.max(-1) > factor).any(0)


def flipped_triangles(vertices: np.ndarray, reference: np.ndarray,
                      faces: np.ndarray) -> np.ndarray:
    """Triangles whose normal opposes the reference's (e.g. the rigid mode's) in some frame.

    Parameters
    ----------
    vertices, reference : (F, V, 3) float ndarray
    faces : (T, 3) int ndarray

    Returns
    -------
    (T,) bool ndarray
    """
    dot = np.sum(triangle_normals(vertices, faces) * triangle_normals(reference, faces), -1)
    return (dot < 0).any(0)
