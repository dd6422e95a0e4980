"""Animated meshes as studios load them: a rest mesh (Wavefront OBJ) and a PC2 point cache.

PC2 ("POINTCACHE2") is the point-cache format Blender's built-in *Mesh Cache*
modifier, Maya and Houdini read: one float32 ``xyz`` per vertex per sample, in
the vertex order of the mesh the cache is applied to.  The layout (all
little-endian)::

    char[12] "POINTCACHE2\\0"   int32 version = 1   int32 n_points
    float32 start_frame         float32 sample_rate  int32 n_samples
    float32[n_samples][n_points][3]

``sample_rate`` is the number of frames between two samples (1: one sample per
frame), not a rate in Hz; the capture rate goes into the OBJ's comment line.
The OBJ holds the rest pose (frame 0) with ``v``/``f`` records only (1-based
indices, no normals or groups), so importers keep its vertex order.  Both are
written in the mesh's own axes and metres: import them without axis
conversion (Blender: forward ``Y``, up ``Z``), or the cache and the rest mesh
disagree; a Y-up mesh (the demo's body) then stands up once the object is
rotated 90° about X (an object transform applies after the Mesh Cache modifier).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["PC2_MAGIC", "MeshCacheError", "read_pc2", "write_obj", "write_pc2"]

#: The 12 bytes a PC2 file starts with.
PC2_MAGIC = b"POINTCACHE2\0"
_HEADER = np.dtype([("magic", "S12"), ("version", "<i4"), ("n_points", "<i4"),
                    ("start_frame", "<f4"), ("sample_rate", "<f4"), ("n_samples", "<i4")])


class MeshCacheError(ValueError):
    """A PC2 file that is not one, or is shorter than its header says (names the file)."""


def write_pc2(vertices: np.ndarray, path: str | os.PathLike, *, start_frame: float = 0.0
              ) -> Path:
    """Write an animated mesh's vertex positions as a PC2 point cache.

    Parameters
    ----------
    vertices : (F, V, 3) float ndarray
        Positions per frame (metres), in the vertex order of the rest mesh.
    path : str or path-like
    start_frame : float
        Frame number of the first sample (Blender's Mesh Cache maps scene frames
        to samples through its own ``frame_start``).

    Returns
    -------
    Path
    """
    v = np.ascontiguousarray(vertices, dtype="<f4")
    if v.ndim != 3 or v.shape[-1] != 3:
        raise ValueError(f"vertices must be (F, V, 3), got shape {v.shape}")
    header = np.array([(PC2_MAGIC, 1, v.shape[1], start_frame, 1.0, v.shape[0])], dtype=_HEADER)
    path = Path(path)
    with open(path, "wb") as f:
        f.write(header.tobytes())
        f.write(v.tobytes())
    return path


def read_pc2(path: str | os.PathLike) -> tuple[np.ndarray, float]:
    """Read a PC2 point cache.

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    vertices : (F, V, 3) float32 ndarray
    start_frame : float

    Raises
    ------
    MeshCacheError
        Not a PC2 file, or fewer bytes than its header declares.
    """
    path = Path(path)
    raw = path.read_bytes()
    if len(raw) < _HEADER.itemsize or raw[:12] != PC2_MAGIC:
        raise MeshCacheError(f"{path}: not a PC2 file (no POINTCACHE2 header)")
    h = np.frombuffer(raw[:_HEADER.itemsize], dtype=_HEADER)[0]
    n_p, n_s = int(h["n_points"]), int(h["n_samples"])
    need = _HEADER.itemsize + 12 * n_p * n_s
    if n_p < 0 or n_s < 0 or len(raw) < need:
        raise MeshCacheError(f"{path}: header declares {n_s} samples of {n_p} points "
                             f"({need} bytes) but the file has {len(raw)}")
    data = np.frombuffer(raw, dtype="<f4", count=3 * n_p * n_s, offset=_HEADER.itemsize)
    return data.reshape(n_s, n_p, 3), float(h["start_frame"])


def write_obj(vertices: np.ndarray, faces: np.ndarray, path: str | os.PathLike, *,
              comment: str = "") -> Path:
    """Write a triangle mesh as Wavefront OBJ (``v`` and ``f`` records only).

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        Metres; written with 9 significant digits (float32 round trip).
    faces : (T, 3) int ndarray
        0-based vertex indices (written 1-based).
    path : str or path-like
    comment : str
        One line written as ``# comment`` after the header line.

    Returns
    -------
    Path
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3) + 1
    lines = ["# mocapflow"] + ([f"# {comment}"] if comment else [])
    body = "\n".join(lines) + "\n"
    body += "".join(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in v.tolist())
    body += "".join(f"f {a} {b} {c}\n" for a, b, c in f.tolist())
    path = Path(path)
    path.write_text(body)
    return path
