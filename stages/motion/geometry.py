"""Mesh geometry shared by the simulator and the skin graph."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["triangle_normals", "vertex_normals"]


def triangle_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unnormalised normals of every triangle, ``(b - a) × (c - a)``.

    Parameters
    ----------
    vertices : (..., V, 3) float ndarray
    faces : (T, 3) int ndarray

    Returns
    -------
    (..., T, 3) float ndarray
    """
    X = np.asarray(vertices)
    a = X[..., faces[:, 0], :]
    return np.cross(X[..., faces[:, 1], :] - a, X[..., faces[:, 2], :] - a)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals.

    Parameters
    ----------
    vertices : (..., V, 3) float ndarray
    faces : (T, 3) int ndarray

    Returns
    -------
    (..., V, 3) float ndarray
    """
    v = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    V, T = v.shape[-2], len(faces)
    fn = triangle_normals(v, faces)  # (..., T, 3)
    S = sp.csr_matrix((np.ones(3 * T), (faces.ravel(), np.repeat(np.arange(T), 3))),
                      shape=(V, T))
    moved = np.moveaxis(fn, -2, 0).reshape(T, -1)
    n = np.moveaxis(np.asarray(S @ moved).reshape((V,) + fn.shape[:-2] + (3,)), 0, -2)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    return n / np.where(norm > 0, norm, 1.0)
