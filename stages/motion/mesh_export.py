"""The ``mesh`` exporter of ``mocapflow export``: a mesh or an animated mesh as files
ParaView, Blender, Maya, Houdini and USD pipelines open.

* :func:`export_mesh`: the exporter (formats chosen with ``formats``);
* :func:`write_ply`: one binary PLY;
* :func:`write_vtp`: one VTK PolyData file, with point data.

pyvista is imported inside the functions, so importing this module stays cheap.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.pipeline.codecs import ExportFormatError, exporter
from mocapflow.stages.motion.datatypes import Mesh
from mocapflow.stages.motion.formats.meshcache import write_obj, write_pc2

__all__ = ["export_mesh", "write_ply", "write_vtp"]


def write_ply(vertices: np.ndarray, faces: np.ndarray, path: str | Path) -> Path:
    """Write a triangle mesh as binary little-endian PLY (Blender, ParaView, MeshLab).

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (T, 3) int ndarray
    path : str or Path

    Returns
    -------
    Path
    """
    path = Path(path)
    v = np.ascontiguousarray(vertices, dtype="<f4")
    f = np.empty(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    f["n"] = 3
    f["idx"] = faces
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment mocapflow\n"
        f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(v.tobytes())
        fh.write(f.tobytes())
    return path


def write_vtp(vertices: np.ndarray, faces: np.ndarray, path: Path, scalars=None) -> Path:
    """Write a triangle mesh as binary VTK PolyData (``.vtp``).

    Parameters
    ----------
    vertices : (V, 3) float ndarray
    faces : (T, 3) int ndarray
    path : Path
    scalars : dict, optional
        ``name -> (V,) or (V, k) array``, written as point data.

    Returns
    -------
    Path
    """
    import pyvista as pv  # noqa: PLC0415 (heavy)

    cells = np.hstack([np.full((len(faces), 1), 3), faces]).astype(np.int64).ravel()
    poly = pv.PolyData(np.asarray(vertices, dtype=np.float64), cells)
    if scalars is not None:
        for k, v in scalars.items():
            poly.point_data[k] = v
    poly.save(str(path), binary=True)
    return path


@exporter("mesh")
def export_mesh(mesh: Mesh, directory: Path, stem: str, **options: Any) -> list[Path]:
    """Write a mesh (or mesh sequence) for ParaView, Blender, Maya and Houdini.

    A static mesh becomes ``<stem>.vtp`` and ``<stem>.ply``.  An animated mesh
    becomes one animation: ``<stem>.obj`` (the rest pose, frame 0) with the point
    cache ``<stem>.pc2`` (every frame; Blender's built-in Mesh Cache modifier,
    Maya and Houdini read it, see :mod:`~mocapflow.stages.motion.formats.meshcache`),
    and ``<stem>.pvd``, a ParaView time series over ``<stem>/<stem>_NNNNN.vtp``
    (which keeps vertex data such as part labels as point data).  One PLY per
    frame (``<stem>/<stem>_NNNNN.ply``) is opt-in.

    Parameters
    ----------
    mesh : Mesh
    directory : Path
    stem : str
    options
        ``formats``: subset of ``("vtp", "ply", "pc2")``; default ``("vtp", "ply")``
        for a static mesh (``pc2`` adds its OBJ), ``("vtp", "pc2")`` for an animated one.

    Returns
    -------
    list of Path
        Every file written.
    """
    default = ("vtp", "pc2") if mesh.animated else ("vtp", "ply")
    formats = tuple(options.get("formats", default))
    unknown = sorted(set(formats) - {"vtp", "ply", "pc2"})
    if unknown:
        raise ExportFormatError(f"unknown mesh format(s) {unknown}; it writes vtp, ply, pc2")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    rest = mesh.vertices[0] if mesh.animated else mesh.vertices
    if "pc2" in formats:
        rate = f", {mesh.rate:g} frames per second in {stem}.pc2" if mesh.animated else ""
        written.append(write_obj(rest, mesh.faces, directory / f"{stem}.obj",
                                 comment=f"rest pose (frame 0), metres{rate}"))
        if mesh.animated:
            written.append(write_pc2(mesh.vertices, directory / f"{stem}.pc2"))
    if not mesh.animated:
        if "vtp" in formats:
            written.append(write_vtp(mesh.vertices, mesh.faces, directory / f"{stem}.vtp"))
        if "ply" in formats:
            written.append(write_ply(mesh.vertices, mesh.faces, directory / f"{stem}.ply"))
        return written
    if "vtp" in formats or "ply" in formats:
        (directory / stem).mkdir(exist_ok=True)
    written += _write_frames(mesh, directory, stem, formats)
    return written


def _write_frames(mesh: Mesh, directory: Path, stem: str, formats: tuple[str, ...]
                  ) -> list[Path]:
    """The per-frame files of an animated mesh: the VTP series with its ``.pvd``, PLYs."""
    sub = directory / stem
    rate = mesh.rate or 1.0
    written: list[Path] = []
    entries = []
    for i, verts in enumerate(mesh.vertices):
        name = f"{stem}_{i:05d}"
        if "vtp" in formats:
            written.append(write_vtp(verts, mesh.faces, sub / f"{name}.vtp"))
            entries.append(
                f'    <DataSet timestep="{i / rate!r}" group="" part="0" '
                f'file="{stem}/{name}.vtp"/>'
            )
        if "ply" in formats:
            written.append(write_ply(verts, mesh.faces, sub / f"{name}.ply"))
    if "vtp" in formats:
        pvd = directory / f"{stem}.pvd"
        pvd.write_text(
            '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n'
            + "\n".join(entries)
            + "\n  </Collection>\n</VTKFile>\n"
        )
        written.insert(0, pvd)
    return written
