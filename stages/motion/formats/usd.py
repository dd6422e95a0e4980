"""Meshes and animated meshes as USD, for pipelines built on OpenUSD (written with usd-core).

:func:`write_usd` writes one layer (``.usdc``: the binary crate format; ``.usda``:
text) holding an ``Xform`` (the default prim) with one ``UsdGeom.Mesh`` child:

* ``faceVertexCounts`` (all 3) and ``faceVertexIndices``, ``subdivisionScheme =
  "none"`` (the triangles are the surface, renderers must not subdivide them);
* ``points`` (float32) and ``extent``: time-independent for a static mesh; for an
  animated one a time sample per frame at time code ``i`` = frame ``i``, with
  ``timeCodesPerSecond = framesPerSecond`` = the mesh's rate and start/end time
  codes ``0`` and ``F - 1`` (the default value is frame 0, the rest pose);
* the stage's ``metersPerUnit = 1`` (mocapflow meshes are in metres) and
  ``upAxis`` (``Y`` or ``Z``);
* per-vertex data as primvars with ``vertex`` interpolation (``int[]`` or
  ``float[]``, ``elementSize`` = columns of a ``(V, k)`` array); a primvar's
  ``customData["names"]`` names its integer values where given (e.g. part names).

:func:`read_usd` reads such a file back (tests, tools).  ``pxr`` is imported
inside the functions: importing this module is cheap and works without
usd-core; using it without usd-core raises :class:`UsdUnavailableError`.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.stages.motion.axes import axis_vector

__all__ = ["UsdError", "UsdMeshFile", "UsdUnavailableError", "read_usd", "require_usd",
           "usd_available", "write_usd"]


class UsdError(ValueError):
    """Bad input to :func:`write_usd`, or a file :func:`read_usd` cannot read as a mesh."""


class UsdUnavailableError(ImportError):
    """usd-core (the ``pxr`` package) is not installed; the message says how to get it."""


def _pxr():
    """The ``pxr`` modules used here, or :class:`UsdUnavailableError` (one line)."""
    try:
        from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt  # noqa: PLC0415 (heavy, optional)
    except ImportError as e:
        raise UsdUnavailableError(
            f"USD needs usd-core (the pxr package), which cannot be imported ({e}); "
            "install it with `pip install usd-core`"
        ) from None
    return Gf, Sdf, Tf, Usd, UsdGeom, Vt


def require_usd() -> None:
    """Raise :class:`UsdUnavailableError` (one line) unless usd-core can be imported."""
    _pxr()


def usd_available() -> bool:
    """Whether usd-core can be imported."""
    try:
        _pxr()
    except UsdUnavailableError:
        return False
    return True


@dataclass(eq=False)
class UsdMeshFile:
    """A mesh read back by :func:`read_usd`.

    Attributes
    ----------
    vertices : (V, 3) or (F, V, 3) float32 ndarray
        The static points, or one pose per time sample (in time-code order).
    faces : (T, 3) int64 ndarray
    times : (F,) float ndarray
        The time codes of the samples (empty for a static mesh).
    time_codes_per_second, frames_per_second, start_time_code, end_time_code : float
    meters_per_unit : float
    up_axis : str
        ``"Y"`` or ``"Z"``.
    primvars : dict
        ``name -> (V,) or (V, k) ndarray`` (vertex-interpolated primvars; ``(F, V)`` or
        ``(F, V, k)`` for time-sampled ones).
    names : dict
        ``primvar name -> list of str`` from the primvars' ``customData["names"]``.
    path : str
        Prim path of the mesh.
    """

    vertices: np.ndarray
    faces: np.ndarray
    times: np.ndarray
    time_codes_per_second: float
    frames_per_second: float
    start_time_code: float
    end_time_code: float
    meters_per_unit: float
    up_axis: str
    primvars: dict[str, np.ndarray] = field(default_factory=dict)
    names: dict[str, list[str]] = field(default_factory=dict)
    path: str = ""


def _rotation_to_z(axis: str) -> np.ndarray:
    """A proper rotation ``(3, 3)`` taking the signed axis (``"-Y"``, ``"+X"`` ...) to +Z."""
    u = axis_vector(axis)
    z = np.array([0.0, 0.0, 1.0])
    if u @ z < -0.5:  # -Z: half a turn about X
        return np.diag([1.0, -1.0, -1.0])
    k = np.cross(u, z)  # a quarter turn (or none) about u x z
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + K + K @ K / (1.0 + u @ z)


def _check(vertices, faces, rate, up, primvars, names):
    """Validated ``(vertices, faces, rate, up, primvars)``; :class:`UsdError` on bad input."""
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim not in (2, 3) or v.shape[-1] != 3 or v.shape[-2] == 0:
        raise UsdError(f"write_usd: vertices must be (V, 3) or (F, V, 3), got shape {v.shape}")
    if not np.isfinite(v).all():
        raise UsdError("write_usd: vertices must be finite")
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise UsdError(f"write_usd: faces must be an integer (T, 3) array, got {f.dtype} "
                       f"{f.shape}")
    V = v.shape[-2]
    if f.size and (f.min() < 0 or f.max() >= V):
        raise UsdError(f"write_usd: faces index vertices outside [0, {V})")
    if v.ndim == 3 and not (rate is not None and np.isfinite(rate) and rate > 0):
        raise UsdError(f"write_usd: an animated mesh needs a positive rate, got {rate}")
    m = re.fullmatch(r"\s*([+-]?)\s*([xyzXYZ])\s*", str(up))
    if m is None:
        raise UsdError(f"write_usd: up must be x, y or z with an optional sign, got {up!r}")
    axis = f"{m.group(1) or '+'}{m.group(2).upper()}"
    pv = {}
    for name, a in (primvars or {}).items():
        a = np.asarray(a)
        if a.ndim not in (1, 2) or a.shape[0] != V or a.dtype.kind not in "biuf":
            raise UsdError(f"write_usd: primvar {name!r} must be a numeric (V,) or (V, k) "
                           f"array with V = {V}, got {a.dtype} {a.shape}")
        pv[name] = a
    for name in names or {}:
        if name not in pv:
            raise UsdError(f"write_usd: names given for {name!r}, which is not a primvar")
    return v, f.astype(np.int64), axis, pv


def write_usd(
    vertices: np.ndarray,
    faces: np.ndarray,
    path: str | os.PathLike,
    *,
    rate: float | None = None,
    up: str = "y",
    primvars: dict[str, np.ndarray] | None = None,
    names: dict[str, list[str]] | None = None,
    prim_name: str = "mesh",
    frame_primvars: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write a (possibly animated) triangle mesh as one USD layer.

    Parameters
    ----------
    vertices : (V, 3) or (F, V, 3) float ndarray
        Positions in metres (written as float32); ``(F, V, 3)``: one pose per frame,
        time-sampled at time codes ``0 … F - 1``.
    faces : (T, 3) int ndarray
    path : str or path-like
        ``.usdc`` (binary crate), ``.usda`` (text) or ``.usd`` (crate).
    rate : float, optional
        Frames per second; required for an animated mesh (``timeCodesPerSecond``
        and ``framesPerSecond``).
    up : str
        The data's up axis, ``x``, ``y`` or ``z`` with an optional sign: ``+y`` /
        ``+z`` become the stage's ``upAxis``; any other (USD has only Y and Z) is
        stood up on ``upAxis`` Z by a rotation on the root ``Xform`` (the points
        stay in the data's axes).
    primvars : dict, optional
        ``name -> (V,) or (V, k)`` numeric array, written as vertex primvars
        (integers as ``int[]``, others as ``float[]``).
    names : dict, optional
        ``primvar name -> list of str`` naming its integer values (``customData``).
    prim_name : str
        Name of the root ``Xform`` (made a valid identifier); the mesh is its
        child ``mesh``.
    frame_primvars : dict, optional
        ``name -> (F, V) or (F, V, k)`` float array of an animated mesh: vertex
        primvars time-sampled per frame, like the points.

    Returns
    -------
    Path

    Raises
    ------
    UsdError
        Bad shapes, non-finite vertices, a missing rate, an unknown up axis.
    UsdUnavailableError
        usd-core is not installed.
    """
    v, f, axis, pv = _check(vertices, faces, rate, up, primvars, names)
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = _pxr()
    path = Path(path)
    if path.suffix.lower() not in (".usd", ".usdc", ".usda"):
        raise UsdError(f"write_usd: {path.name}: the suffix must be .usdc, .usda or .usd")
    path.unlink(missing_ok=True)  # CreateNew refuses an existing layer
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.LinearUnits.meters)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if axis == "+Y" else UsdGeom.Tokens.z)
    root = UsdGeom.Xform.Define(stage, Sdf.Path("/" + Tf.MakeValidIdentifier(prim_name)))
    if axis not in ("+Y", "+Z"):  # USD says only Y or Z: the root stands the data up on +Z
        R = _rotation_to_z(axis)
        M = np.eye(4)
        M[:3, :3] = R.T  # USD matrices act on row vectors
        root.AddTransformOp().Set(Gf.Matrix4d(M.tolist()))
    stage.SetDefaultPrim(root.GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, root.GetPath().AppendChild("mesh"))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(f), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(f.astype(np.int32).ravel()))
    v32 = np.ascontiguousarray(v, dtype=np.float32)
    ext = np.stack([v32.min(axis=-2), v32.max(axis=-2)], axis=-2)  # (2, 3) or (F, 2, 3)
    points, extent = mesh.CreatePointsAttr(), mesh.CreateExtentAttr()
    points.Set(Vt.Vec3fArray.FromNumpy(v32 if v32.ndim == 2 else v32[0]))  # default: rest
    extent.Set(Vt.Vec3fArray.FromNumpy(ext if ext.ndim == 2 else ext[0]))
    if v32.ndim == 3:
        n = v32.shape[0]
        stage.SetTimeCodesPerSecond(float(rate))
        stage.SetFramesPerSecond(float(rate))
        stage.SetStartTimeCode(0.0)
        stage.SetEndTimeCode(float(n - 1))
        for i in range(n):
            t = Usd.TimeCode(float(i))
            points.Set(Vt.Vec3fArray.FromNumpy(v32[i]), t)
            extent.Set(Vt.Vec3fArray.FromNumpy(ext[i]), t)
    api = UsdGeom.PrimvarsAPI(mesh)
    for name, a in (frame_primvars or {}).items():
        a = np.asarray(a, dtype=np.float32)
        if v32.ndim != 3 or a.shape[:2] != v32.shape[:2] or a.ndim not in (2, 3):
            raise UsdError(f"write_usd: frame primvar {name!r} must be (F, V) or (F, V, k) "
                           f"with (F, V) = {v32.shape[:2]}, got {a.shape}")
        var = api.CreatePrimvar(name, Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex,
                                1 if a.ndim == 2 else a.shape[2])
        for i in range(a.shape[0]):
            var.Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(a[i].ravel())),
                    Usd.TimeCode(float(i)))
    for name, a in pv.items():
        integer = a.dtype.kind in "biu"
        type_ = Sdf.ValueTypeNames.IntArray if integer else Sdf.ValueTypeNames.FloatArray
        k = 1 if a.ndim == 1 else a.shape[1]
        var = api.CreatePrimvar(name, type_, UsdGeom.Tokens.vertex, k)
        flat = np.ascontiguousarray(a.ravel(), dtype=np.int32 if integer else np.float32)
        var.Set(Vt.IntArray.FromNumpy(flat) if integer else Vt.FloatArray.FromNumpy(flat))
        if names and name in names:
            var.GetAttr().SetCustomDataByKey("names", Vt.StringArray([str(s) for s in
                                                                      names[name]]))
    stage.GetRootLayer().Save()
    return path


def read_usd(path: str | os.PathLike) -> UsdMeshFile:
    """Read the first ``UsdGeom.Mesh`` of a USD file (triangles only).

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    UsdMeshFile

    Raises
    ------
    UsdError
        The file does not open as USD, has no mesh, or a face is not a triangle.
    UsdUnavailableError
        usd-core is not installed.
    """
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = _pxr()
    path = Path(path)
    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as e:
        raise UsdError(f"{path}: not a USD file ({str(e).strip().splitlines()[-1]})") from None
    if stage is None:
        raise UsdError(f"{path}: not a USD file")
    prim = next((p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)), None)
    if prim is None:
        raise UsdError(f"{path}: no UsdGeom.Mesh in the stage")
    mesh = UsdGeom.Mesh(prim)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(), dtype=np.int64)
    if counts.size and not (counts == 3).all():
        raise UsdError(f"{path}: {prim.GetPath()} has faces that are not triangles")
    faces = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
    points = mesh.GetPointsAttr()
    times = np.asarray(points.GetTimeSamples(), dtype=np.float64)
    if times.size:
        verts = np.stack([np.asarray(points.Get(Usd.TimeCode(t)), dtype=np.float32)
                          for t in times])
    else:
        verts = np.asarray(points.Get(), dtype=np.float32)
    primvars: dict[str, np.ndarray] = {}
    names: dict[str, list[str]] = {}
    for var in UsdGeom.PrimvarsAPI(mesh).GetPrimvars():
        if var.GetInterpolation() != UsdGeom.Tokens.vertex or not var.HasValue():
            continue
        name = var.GetPrimvarName()
        k = var.GetElementSize()
        samples = var.GetAttr().GetTimeSamples()
        if samples:  # per frame: (F, V) or (F, V, k)
            a = np.stack([np.asarray(var.Get(Usd.TimeCode(t))) for t in samples])
            primvars[name] = a.reshape(len(samples), -1, k) if k > 1 else a
            continue
        a = np.asarray(var.Get())
        primvars[name] = a.reshape(-1, k) if k > 1 else a
        custom: Any = var.GetAttr().GetCustomDataByKey("names")
        if custom is not None:
            names[name] = [str(s) for s in custom]
    return UsdMeshFile(
        vertices=verts, faces=faces, times=times,
        time_codes_per_second=float(stage.GetTimeCodesPerSecond()),
        frames_per_second=float(stage.GetFramesPerSecond()),
        start_time_code=float(stage.GetStartTimeCode()),
        end_time_code=float(stage.GetEndTimeCode()),
        meters_per_unit=float(UsdGeom.GetStageMetersPerUnit(stage)),
        up_axis=str(UsdGeom.GetStageUpAxis(stage)),
        primvars=primvars, names=names, path=str(prim.GetPath()),
    )
