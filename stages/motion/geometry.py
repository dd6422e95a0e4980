"""Mesh geometry shared by the simulator and the skin graph."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["mesh_laplacian", "triangle_normals", "vertex_normals"]


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


def mesh_laplacian(n_vertices: int, faces: np.ndarray) -> sp.csr_matrix:
    """Uniform graph Laplacian ``L = I - D⁻¹A`` of a triangle mesh.

    Parameters
    ----------
    n_vertices : int
    faces : (T, 3) int ndarray

    Returns
    -------
    (V, V) scipy.sparse.csr_matrix
        Isolated vertices get a zero row.
    """
    i = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    j = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    A = sp.coo_matrix((np.ones(i.size), (i, j)), shape=(n_vertices, n_vertices)).tocsr()
    A = ((A + A.T) > 0).astype(np.float64)
    deg = np.asarray(A.sum(1)).ravel()
    inv = np.where(deg > 0, 1.0 / np.maximum(deg, 1), 0.0)
    return (sp.diags((deg > 0).astype(float)) - sp.diags(inv) @ A).tocsr()
