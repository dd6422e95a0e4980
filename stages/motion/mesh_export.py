"""The ``mesh`` exporter of ``mocapflow export``: a mesh or an animated mesh as files
ParaView, Blender, Maya, Houdini and USD pipelines open.

* :func:`export_mesh`: the exporter (formats chosen with ``formats``);
* :func:`vertex_data`: the per-vertex data of a mesh that the VTP and USD files carry;
* :func:`write_ply`: one binary PLY;
* :func:`write_vtp`: one VTK PolyData file, with point data.

USD is written by :mod:`~mocapflow.stages.motion.formats.usd` (usd-core).  pyvista
and pxr are imported inside the functions, so importing this module stays cheap.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.pipeline.codecs import ExportFormatError, exporter
from mocapflow.stages.motion.axes import AxisError, parse_axis
from mocapflow.stages.motion.datatypes import Mesh
from mocapflow.stages.motion.formats.meshcache import write_obj, write_pc2
from mocapflow.stages.motion.formats.usd import UsdUnavailableError, require_usd, write_usd

__all__ = ["MESH_FORMATS", "export_mesh", "vertex_data", "write_ply", "write_vtp"]

#: Every format :func:`export_mesh` writes.
MESH_FORMATS = ("vtp", "ply", "pc2", "usd")

#: Attrs keys naming the integer values of a vertex attr when ``<x>_names`` is absent.
_NAME_FALLBACK = {"vertex_part": "joint_names"}


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


def vertex_data(mesh: Mesh) -> tuple[dict[str, np.ndarray], dict[str, list[str]]]:
    """The per-vertex data in a mesh's ``attrs``, as the VTP and USD files carry it.

    A per-vertex attr is a key ``vertex_<x>`` holding ``V`` numbers (or ``V`` rows of
    ``k``), e.g. ``vertex_part`` (the dominant part of each vertex: stage ``deform``,
    with ``part_names``; the simulator's true mesh, with ``joint_names``).  Its integer
    values are named by the list of strings ``attrs["<x>_names"]`` (``vertex_part``:
    else ``joint_names``).  Other attrs (``marker_face``: per marker) are not vertex data.

    Parameters
    ----------
    mesh : Mesh

    Returns
    -------
    data : dict
        ``name -> (V,) or (V, k) ndarray``: int32 for integer values, else float32.
    names : dict
        ``name -> list of str`` for the integer attrs that have names.
    """
    V = mesh.vertices.shape[-2]
    data: dict[str, np.ndarray] = {}
    names: dict[str, list[str]] = {}
    for key, value in mesh.attrs.items():
        if not key.startswith("vertex_") or isinstance(value, (str, bytes)):
            continue
        try:
            a = np.asarray(value)
        except ValueError:  # ragged lists
            continue
        if a.ndim not in (1, 2) or a.shape[0] != V or a.dtype.kind not in "biuf":
            continue
        integer = a.dtype.kind in "biu"
        data[key] = a.astype(np.int32 if integer else np.float32)
        label = mesh.attrs.get(f"{key[len('vertex_'):]}_names",
                               mesh.attrs.get(_NAME_FALLBACK.get(key, "")))
        if integer and isinstance(label, list) and all(isinstance(n, str) for n in label):
            names[key] = label
    for key, a in mesh.point_data.items():  # numeric point data (Mesh.point_data)
        if not mesh.frame_varying(a):
            data[key] = a.astype(np.int32 if a.dtype.kind in "biu" else np.float32)
    return data, names


def frame_data(mesh: Mesh) -> dict[str, np.ndarray]:
    """The point data of an animated mesh that changes per frame (e.g. ``error_mm``).

    Returns
    -------
    dict
        ``name -> (F, V) or (F, V, k) float32 ndarray`` (:meth:`Mesh.frame_varying`).
    """
    return {k: a.astype(np.float32) for k, a in mesh.point_data.items()
            if mesh.frame_varying(a)}


def _up_axis(mesh: Mesh) -> str:
    """``attrs["up"]`` as a signed axis (``"+y"`` default; ``"y"``, ``"Z"``, ``"-x"`` ...,
    or an axis index 0/1/2 accepted); ExportFormatError for any other value."""
    up = mesh.attrs.get("up", "+y")
    if isinstance(up, int) and not isinstance(up, bool) and up in (0, 1, 2):
        up = "xyz"[up]
    try:
        return parse_axis(up, name="up")
    except AxisError:
        raise ExportFormatError(f"mesh attrs up={mesh.attrs.get('up')!r}: expected x, y or "
                                "z with an optional sign") from None


@exporter("mesh")
def export_mesh(mesh: Mesh, directory: Path, stem: str, **options: Any) -> list[Path]:
    """Write a mesh (or mesh sequence) for ParaView, Blender, Maya, Houdini and USD.

    A static mesh becomes ``<stem>.vtp`` and ``<stem>.ply``.  An animated mesh
    becomes one animation: ``<stem>.obj`` (the rest pose, frame 0) with the point
    cache ``<stem>.pc2`` (every frame; Blender's built-in Mesh Cache modifier,
    Maya and Houdini read it, see :mod:`~mocapflow.stages.motion.formats.meshcache`),
    ``<stem>.usdc``, one USD layer whose ``UsdGeom.Mesh`` points are time-sampled
    per frame at the mesh's rate (metres, up axis from ``attrs["up"]``, default y;
    see :mod:`~mocapflow.stages.motion.formats.usd`), and ``<stem>.pvd``, a ParaView
    time series over ``<stem>/<stem>_NNNNN.vtp``.  One PLY per frame
    (``<stem>/<stem>_NNNNN.ply``) is opt-in; so is USD for a static mesh (one
    time-independent mesh).  The VTP files (every frame's) carry the mesh's
    per-vertex data (:func:`vertex_data`, e.g. ``vertex_part``, ``part_weights``;
    each frame's own values of :func:`frame_data`, e.g. ``error_mm``) as point data,
    the USD file as vertex primvars (time-sampled where they change per frame;
    value names in the primvar's ``customData["names"]``); OBJ, PC2 and PLY carry
    positions only.

    Parameters
    ----------
    mesh : Mesh
    directory : Path
    stem : str
    options
        ``formats``: subset of ``("vtp", "ply", "pc2", "usd")``; default ``("vtp",
        "ply")`` for a static mesh (``pc2`` adds its OBJ), ``("vtp", "pc2", "usd")``
        for an animated one.

    Returns
    -------
    list of Path
        Every file written.

    Raises
    ------
    ExportFormatError
        An unknown format; ``usd`` without usd-core installed (checked before any
        file is written); with ``usd``, an ``attrs["up"]`` that is not a signed axis.
    """
    default = ("vtp", "pc2", "usd") if mesh.animated else ("vtp", "ply")
    formats = tuple(options.get("formats", default))
    unknown = sorted(set(formats) - set(MESH_FORMATS))
    if unknown:
        raise ExportFormatError(f"unknown mesh format(s) {unknown}; it writes "
                                + ", ".join(MESH_FORMATS))
    if "usd" in formats:
        try:
            require_usd()
        except UsdUnavailableError as e:
            raise ExportFormatError(f"{e} (or leave usd out, e.g. --format mesh=vtp,pc2)"
                                    ) from None
        up = _up_axis(mesh)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    data, names = vertex_data(mesh)
    per_frame = frame_data(mesh)
    written: list[Path] = []
    rest = mesh.vertices[0] if mesh.animated else mesh.vertices
    if "pc2" in formats:
        rate = f", {mesh.rate:g} frames per second in {stem}.pc2" if mesh.animated else ""
        written.append(write_obj(rest, mesh.faces, directory / f"{stem}.obj",
                                 comment=f"rest pose (frame 0), metres{rate}"))
        if mesh.animated:
            written.append(write_pc2(mesh.vertices, directory / f"{stem}.pc2"))
    if "usd" in formats:
        written.append(write_usd(mesh.vertices, mesh.faces, directory / f"{stem}.usdc",
                                 rate=(mesh.rate or 1.0) if mesh.animated else None, up=up,
                                 primvars=data, names=names, prim_name=stem,
                                 frame_primvars=per_frame))
    if not mesh.animated:
        if "vtp" in formats:
            written.append(write_vtp(mesh.vertices, mesh.faces, directory / f"{stem}.vtp",
                                     scalars=data))
        if "ply" in formats:
            written.append(write_ply(mesh.vertices, mesh.faces, directory / f"{stem}.ply"))
        return written
    if "vtp" in formats or "ply" in formats:
        (directory / stem).mkdir(exist_ok=True)
    written += _write_frames(mesh, directory, stem, formats, data, per_frame)
    return written


def _write_frames(mesh: Mesh, directory: Path, stem: str, formats: tuple[str, ...],
                  data: dict[str, np.ndarray], per_frame: dict[str, np.ndarray]
                  ) -> list[Path]:
    """The per-frame files of an animated mesh: the VTP series with its ``.pvd``, PLYs."""
    sub = directory / stem
    rate = mesh.rate or 1.0
    written: list[Path] = []
    entries = []
    for i, verts in enumerate(mesh.vertices):
        name = f"{stem}_{i:05d}"
        if "vtp" in formats:
            scalars = {**data, **{k: a[i] for k, a in per_frame.items()}}
            written.append(write_vtp(verts, mesh.faces, sub / f"{name}.vtp", scalars=scalars))
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
