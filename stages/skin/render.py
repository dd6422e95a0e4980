"""Off-screen rendering of animated meshes and markers (pyvista / VTK) to videos.

Rendering needs no display: VTK >= 9.4 wheels create an EGL (or OSMesa) context
when no X server is there; this module asks VTK for the EGL window directly
(``VTK_DEFAULT_OPENGL_WINDOW``) unless the environment says otherwise, which
avoids a failed X connection first.  pyvista and imageio are imported inside
the functions, so importing this module stays cheap.

Stages
------
render
    A deformed mesh with the markers overlaid.
render_modes
    Figure-7-style side by side of the deformation modes (rigid, quadratic,
    rigid + residual, quadratic + residual) on the same frames.
render_error
    Per-vertex distance to a ground-truth mesh as a heat map, with statistics.

Outputs are :class:`Video` objects (frames stored losslessly as uint8); the
``video`` exporter writes an MP4 (H.264 through imageio-ffmpeg's bundled
ffmpeg) and one PNG per frame.  Meshes are exported by
:mod:`mocapflow.stages.motion.mesh_export`.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context, FilePath, ParamError, stage
from mocapflow.pipeline.codecs import Encoded, codec, component_coords, exporter, frame_coords
from mocapflow.pipeline.context import split_hint
from mocapflow.stages.motion.axes import AxisError, frame_basis
from mocapflow.stages.motion.datatypes import Markers, Mesh
from mocapflow.stages.skin.binding import closest_points_on_triangles
from mocapflow.stages.skin.deform import align_markers, deform
from mocapflow.stages.skin.parts import MODES
from mocapflow.stages.skin.segmentation import Segmentation

__all__ = [
    "RenderError",
    "Video",
    "export_video",
    "offscreen_available",
    "read_truth",
    "render",
    "render_error",
    "render_frames",
    "render_modes",
    "write_mp4",
]

View = Literal["front", "back", "side", "iso"]
_VIEW_DIRS = {
    "front": (0.0, 0.15, 1.0),
    "back": (0.0, 0.15, -1.0),
    "side": (1.0, 0.15, 0.0),
    "iso": (0.75, 0.35, 0.75),
}


class RenderError(RuntimeError):
    """Off-screen rendering is impossible here, or the inputs cannot be drawn."""


# --------------------------------------------------------------------------- data type


@dataclass(eq=False)
class Video:
    """Rendered frames.

    Parameters
    ----------
    frames : (F, H, W, 3) uint8 ndarray
        RGB images.
    rate : float
        Frames per second for playback.
    attrs : dict
        What was rendered (titles, source frames, colour range).
    """

    frames: np.ndarray
    rate: float
    attrs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.frames = np.asarray(self.frames)
        if self.frames.dtype != np.uint8 or self.frames.ndim != 4 or self.frames.shape[-1] != 3:
            raise ValueError(f"Video frames must be (F, H, W, 3) uint8, got "
                             f"{self.frames.shape} {self.frames.dtype}")  # fmt: skip
        self.rate = float(self.rate)

    @property
    def n_frames(self) -> int:
        """Number of frames ``F``."""
        return self.frames.shape[0]

    def __repr__(self) -> str:
        """One line: frames, image size, rate (never the pixels)."""
        F, H, W = self.frames.shape[:3]
        return f"Video({F} frames of {W}×{H} px @ {self.rate:.4g} Hz)"


def _encode_video(v: Video) -> Encoded:
    arrays = {"frames": (v.frames, ("frame", "y", "x", "rgb"))}
    coords = {**frame_coords(v.frames.shape[0], v.rate), **component_coords("rgb")}
    return Encoded("video", arrays, {"rate": v.rate, "attrs": v.attrs}, coords)


def _decode_video(e: Encoded) -> Video:
    return Video(frames=e.arrays["frames"][0], rate=e.attrs["rate"], attrs=e.attrs.get("attrs", {}))


codec("video", encode=_encode_video, decode=_decode_video)(Video)


# --------------------------------------------------------------------------- writers


def write_mp4(frames: np.ndarray, path: str | Path, *, rate: float = 30.0) -> Path:
    """Write RGB frames as an H.264 MP4 (yuv420p, plays everywhere).

    Parameters
    ----------
    frames : (F, H, W, 3) uint8 ndarray
        ``H`` and ``W`` are padded to even sizes if needed.
    path : str or Path
    rate : float

    Returns
    -------
    Path
    """
    import imageio.v2 as imageio  # noqa: PLC0415 (heavy)

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    F, H, W, _ = frames.shape
    ph, pw = (-H) % 2, (-W) % 2
    writer = imageio.get_writer(
        path, fps=float(rate), codec="libx264", quality=8, macro_block_size=1,
        pixelformat="yuv420p", ffmpeg_log_level="error",
    )  # fmt: skip
    try:
        for f in frames:
            if ph or pw:
                f = np.pad(f, ((0, ph), (0, pw), (0, 0)), mode="edge")
            writer.append_data(f)
    finally:
        writer.close()
    return path


@exporter("video")
def export_video(video: Video, directory: Path, stem: str, **options: Any) -> list[Path]:
    """Write ``<stem>.mp4`` and ``<stem>_frames/<stem>_NNNNN.png`` (one PNG per frame).

    Parameters
    ----------
    video : Video
    directory : Path
    stem : str
    options
        ``png``: write the PNG frames (default True).

    Returns
    -------
    list of Path
    """
    import imageio.v2 as imageio  # noqa: PLC0415 (heavy)

    directory = Path(directory)
    written = [write_mp4(video.frames, directory / f"{stem}.mp4", rate=video.rate)]
    if options.get("png", True):
        sub = directory / f"{stem}_frames"
        sub.mkdir(parents=True, exist_ok=True)
        for i, f in enumerate(video.frames):
            p = sub / f"{stem}_{i:05d}.png"
            imageio.imwrite(p, f)
            written.append(p)
    return written


# --------------------------------------------------------------------------- rendering core


def _pyvista():
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv  # noqa: PLC0415 (heavy)

    pv.OFF_SCREEN = True
    return pv


_PROBE = (
    "import os; os.environ.setdefault('VTK_DEFAULT_OPENGL_WINDOW', 'vtkEGLRenderWindow');"
    "import pyvista as pv; pv.OFF_SCREEN = True;"
    "p = pv.Plotter(off_screen=True, window_size=(32, 32)); p.add_mesh(pv.Sphere());"
    "img = p.screenshot(return_img=True); p.close(); assert img.std() > 0; print('ok')"
)


@lru_cache(maxsize=1)
def offscreen_available() -> tuple[bool, str]:
    """Whether off-screen rendering works here (probed once in a subprocess).

    Returns
    -------
    ok : bool
    detail : str
        The probe's error output when it failed.
    """
    try:
        r = subprocess.run(
            [sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120
        )
    except (OSError, subprocess.TimeoutExpired) as e:
        return False, str(e)
    ok = r.returncode == 0 and "ok" in r.stdout
    return ok, "" if ok else (r.stderr.strip().splitlines() or ["unknown failure"])[-1]


def _cells(faces: np.ndarray) -> np.ndarray:
    return np.hstack([np.full((len(faces), 1), 3), faces]).astype(np.int64).ravel()


def _camera_track(seqs: list[np.ndarray], *, follow: bool, smooth: int = 15):
    """Focal points ``(F, 3)`` (smoothed bounding-box centres, or one fixed point)."""
    allpts = [s[:, np.isfinite(s).all((0, 2))] for s in seqs]
    lo = np.min([p.min(1) for p in allpts], axis=0)  # (F, 3)
    hi = np.max([p.max(1) for p in allpts], axis=0)
    centre = (lo + hi) / 2
    if follow:
        k = max(1, min(smooth, len(centre)))
        pad = np.pad(centre, ((k // 2, k - 1 - k // 2), (0, 0)), mode="edge")
        kernel = np.ones(k) / k
        return np.stack([np.convolve(pad[:, i], kernel, mode="valid") for i in range(3)], -1)
    return np.repeat(((lo.min(0) + hi.max(0)) / 2)[None], len(centre), axis=0)


def _frame_body(seq: np.ndarray, focal: np.ndarray, d: np.ndarray, up: np.ndarray,
                width: int, height: int, *, top: float = 0.0,
                bottom: float = 0.0) -> tuple[np.ndarray, float]:
    """Focal points ``(F, 3)`` and distance that frame the body's bounding box tightly.

    The points of every shown frame, relative to the (smoothed) track ``focal``,
    are put in the camera's axes; the focal track is shifted so that their
    extent is centred in the picture, and the distance is the smallest at
    which every point lies inside the 30-degree view (perspective: a point
    nearer the camera needs more room) with ``top`` / ``bottom`` fractions of
    the picture's height left free for a title and a colour bar.

    Parameters
    ----------
    seq : (F, V, 3) float ndarray
        Vertices of the shown frames (NaN ignored).
    focal : (F, 3) float ndarray
    d : (3,) float ndarray
        Unit direction from the focal point to the camera.
    up : (3,) float ndarray
    width, height : int
    top, bottom : float
        Fractions of the height kept free above and below the body.

    Returns
    -------
    focal : (F, 3) float ndarray
    distance : float
    """
    right = np.cross(up, d)
    right /= np.linalg.norm(right)
    true_up = np.cross(d, right)
    rel = seq - focal[:, None, :]
    ok = np.isfinite(rel).all(-1)
    x, y, z = (np.where(ok, rel @ a, np.nan) for a in (right, true_up, d))
    # centre the extent on the screen's axes (z: towards the camera)
    cx = (np.nanmin(x) + np.nanmax(x)) / 2
    cy = (np.nanmin(y) + np.nanmax(y)) / 2
    x, y = x - cx, y - cy
    t = np.tan(np.radians(15.0))  # half of the 30-degree vertical view angle
    usable = max(0.2, 1.0 - top - bottom)  # picture height left for the body
    shift = bottom - top  # half-heights the body's centre sits above the picture's
    # |y| / (D - z) <= usable·t and |x| / (D - z) <= t·W/H
    ty = usable * t
    tx = t * width / height
    need = np.nanmax(np.maximum(np.abs(y) / ty, np.abs(x) / tx) + z)
    dist = float(need) * 1.04  # a small border
    # moving the focal point down by shift·t·dist puts the body's centre that far up
    centre = cx * right + cy * true_up - shift * t * dist * true_up
    return focal + centre, dist


def render_frames(
    panels: list[dict[str, Any]],
    *,
    width: int = 640,
    height: int = 480,
    view: str = "front",
    up: str = "+y",
    forward: str = "+z",
    follow: bool = True,
    background: str = "white",
    marker_size: float | None = None,
    progress: Callable[[int, int, str], Any] | None = None,
) -> np.ndarray:
    """Render one or more synchronised panels of animated meshes, side by side.

    Parameters
    ----------
    panels : list of dict
        Each: ``vertices`` ``(F, V, 3)``, ``faces`` ``(T, 3)``; optional
        ``markers`` ``(F, M, 3)`` (NaN = hidden), ``scalars`` ``(F, V)`` with
        ``clim`` ``(lo, hi)``, ``cmap`` and ``scalar_title``, ``title`` str,
        ``color`` of the mesh.
    width, height : int
        Size of one panel in pixels.
    view : {"front", "back", "side", "iso"}
        Camera direction relative to the body: ``front`` looks at its face.
    up, forward : str
        The data's vertical axis and the direction the body faces (signed axes,
        e.g. ``+z`` and ``-y`` for a Vicon lab; ``attrs["up"]`` / ``["forward"]`` of
        the markers): the image's vertical is ``up``.
    follow : bool
        Camera follows the body (smoothed bounding-box centre).  Each panel is
        framed on its own body: the bounding box of its vertices over the shown
        frames, seen from the camera, fills the picture (less room for a title
        and a colour bar).
    background : str
    marker_size : float, optional
        Marker sphere size in pixels (default ``height / 70``).
    progress : callable, optional
        ``progress(done, total, "frames")`` after each frame (``ctx.progress``).

    Returns
    -------
    (F, H, W * len(panels), 3) uint8 ndarray

    Raises
    ------
    RenderError
        When no off-screen OpenGL context can be created.
    """
    pv = _pyvista()
    F = panels[0]["vertices"].shape[0]
    if any(p["vertices"].shape[0] != F for p in panels):
        raise RenderError("render: panels have different frame counts")
    focal, dist, d, upv = _camera(panels, view=view, up=up, forward=forward, follow=follow,
                                  width=width, height=height)
    try:
        pl = pv.Plotter(
            off_screen=True, shape=(1, len(panels)), window_size=(width * len(panels), height),
            border=False,
        )  # fmt: skip
    except Exception as e:  # pragma: no cover - depends on the machine
        raise RenderError(f"render: no off-screen OpenGL context ({e})") from e
    pl.set_background(background)
    meshes, marker_polys = _add_panels(pv, pl, panels, marker_size or max(3.0, height / 70))
    out = np.empty((F, height, width * len(panels), 3), np.uint8)
    for f in range(F):
        for k, p in enumerate(panels):
            pl.subplot(0, k)
            _update_panel(pv, p, f, meshes[k], marker_polys[k], focal[k, f])
            cam = pl.camera
            cam.focal_point = focal[k, f]
            cam.position = focal[k, f] + dist[k] * d
            cam.up = upv
            cam.view_angle = 30.0
            pl.renderer.ResetCameraClippingRange()
        pl.render()
        img = pl.screenshot(return_img=True)
        out[f] = img[:height, : width * len(panels), :3]
        if progress is not None:
            progress(f + 1, F, "frames")
    pl.close()
    return out


def _camera(panels: list[dict[str, Any]], *, view: str, up: str, forward: str, follow: bool,
            width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Camera of every panel and frame, each panel framed on its own body: focal points
    ``(P, F, 3)``, distances ``(P,)``, direction from the focal point ``(3,)`` and up
    vector ``(3,)`` (room left for a title and a colour bar)."""
    try:
        basis = frame_basis(up, forward)  # the Y-up, +Z-facing view directions -> data axes
    except AxisError as e:
        raise RenderError(f"render: {e}") from None
    d = basis @ np.asarray(_VIEW_DIRS[view], dtype=float)
    upv = basis[:, 1]
    d /= np.linalg.norm(d)
    focals, dists = [], []
    for p in panels:
        seq = np.asarray(p["vertices"], dtype=np.float64)
        if not np.isfinite(seq).all(-1).any():
            raise RenderError("render: a panel has no finite vertex to frame")
        track = _camera_track([seq], follow=follow)
        top = 0.07 if p.get("title") else 0.0
        bottom = 0.12 if p.get("scalars") is not None else 0.0
        f, dist = _frame_body(seq, track, d, upv, width, height, top=top, bottom=bottom)
        focals.append(f)
        dists.append(dist)
    return np.stack(focals), np.asarray(dists), d, upv


def _add_panels(pv, pl, panels: list[dict[str, Any]], marker_size: float) -> tuple[list, list]:
    """Add each panel's mesh (coloured, or scalars with a colour bar), marker points and
    title to its subplot; returns the meshes and the marker point sets (None without)."""
    meshes, marker_polys = [], []
    for k, p in enumerate(panels):
        pl.subplot(0, k)
        poly = pv.PolyData(np.array(p["vertices"][0], dtype=np.float64), _cells(p["faces"]))
        kw: dict[str, Any] = dict(smooth_shading=True, specular=0.2)
        if p.get("scalars") is not None:
            poly.point_data["scalars"] = np.asarray(p["scalars"][0], dtype=np.float64)
            kw.update(
                scalars="scalars", cmap=p.get("cmap", "inferno"), clim=p.get("clim"),
                scalar_bar_args={"title": p.get("scalar_title", ""), "color": "black",
                                 "vertical": False, "position_x": 0.25, "position_y": 0.02,
                                 "width": 0.5, "height": 0.06, "title_font_size": 12,
                                 "label_font_size": 10, "n_labels": 3},
            )  # fmt: skip
        else:
            kw["color"] = p.get("color", "#d9b38c")
        pl.add_mesh(poly, **kw)
        meshes.append(poly)
        mpoly = None
        if p.get("markers") is not None:
            mpoly = pv.PolyData(np.zeros((1, 3)))
            pl.add_mesh(
                mpoly, color=p.get("marker_color", "#1f4fff"), point_size=marker_size,
                render_points_as_spheres=True,
            )  # fmt: skip
        marker_polys.append(mpoly)
        if p.get("title"):
            pl.add_text(p["title"], position="upper_edge", font_size=9, color="black")
    return meshes, marker_polys


def _update_panel(pv, panel: dict[str, Any], f: int, mesh, marker_poly,
                  focal: np.ndarray) -> None:
    """Move a panel's mesh, scalars and visible markers to frame ``f`` (a panel without
    visible markers shows one point at the focal point, hidden in the mesh)."""
    mesh.points = np.asarray(panel["vertices"][f], dtype=np.float64)
    if panel.get("scalars") is not None:
        mesh.point_data["scalars"][:] = panel["scalars"][f]
    if marker_poly is not None:
        m = panel["markers"][f]
        m = m[np.isfinite(m).all(1)]
        marker_poly.copy_from(pv.PolyData(m if len(m) else focal[None]))


def _axes(data: Any) -> dict[str, str]:
    """``up`` / ``forward`` of the data (``attrs``, set at ingest; default Y up, facing +Z)."""
    attrs = getattr(data, "attrs", {}) or {}
    return {"up": str(attrs.get("up", "+y")), "forward": str(attrs.get("forward", "+z"))}


def _frame_indices(n: int, stride: int, max_frames: int) -> np.ndarray:
    idx = np.arange(0, n, max(1, stride))
    if max_frames and len(idx) > max_frames:
        idx = idx[:max_frames]
    return idx


# --------------------------------------------------------------------------- stages


@stage("render", outputs=("video",))
def render(
    mesh: Mesh,
    markers: Markers,
    *,
    width: int = 640,
    height: int = 480,
    stride: int = 2,
    max_frames: int = 600,
    view: View = "front",
    follow: bool = True,
    show_markers: bool = True,
    truth: FilePath | None = None,
    clim_mm: float = 20.0,
    ctx: Context,
) -> dict[str, Any]:
    """Render an animated mesh with the markers overlaid, off-screen.

    Where the capture's true body is known (a simulated capture), ``truth`` colours
    the mesh by each vertex's distance to it, a heat map like :func:`render_error`'s.

    Parameters
    ----------
    mesh : Mesh
        Animated mesh ``(F, V, 3)`` (stage ``deform``).
    markers : Markers
        The capture it was deformed from (same ``F`` frames).
    width, height : int
        Image size in pixels.
    stride : int
        Render every ``stride``-th frame (the video plays at ``rate / stride``).
    max_frames : int
        At most this many rendered frames (0: no limit).
    view : {"front", "back", "side", "iso"}
        Camera direction relative to the body (as in :func:`render_frames`).
    follow : bool
        Camera follows the body.
    show_markers : bool
        Draw the markers as spheres over the mesh.
    truth : FilePath, optional
        The capture's true body as a PC2 point cache ``(F, V', 3)`` in the
        capture's coordinates, its faces in the OBJ of the same name beside it
        (what ``simulate_capture``'s ``mesh`` export writes; the demo passes it).
        The mesh is then coloured by each vertex's distance to the true surface
        in the same frame (mm, ``0``-``clim_mm``), and the mean / p95 over the
        rendered frames go to the run summary.  ``None``: plain skin colour.
    clim_mm : float
        Upper end of the heat map's colour scale (mm), with ``truth``.

    Returns
    -------
    dict
        ``video``: :class:`Video`.
    """
    verts = mesh.vertices if mesh.animated else mesh.vertices[None]
    if show_markers and markers.n_frames != verts.shape[0]:
        raise RenderError(
            f"render: mesh has {verts.shape[0]} frames but the markers have {markers.n_frames}"
        )
    idx = _frame_indices(verts.shape[0], stride, max_frames)
    panel = {"vertices": verts[idx], "faces": mesh.faces,
             "title": f"{mesh.attrs.get('mode', '')}".replace("_", " + ")}  # fmt: skip
    if show_markers:
        panel["markers"] = markers.positions[idx]
    attrs: dict[str, Any] = {"source_frames": idx.tolist(), "kind": "mesh"}
    if truth is not None:
        true_v, true_f = read_truth(truth)
        if true_v.shape[0] != verts.shape[0]:
            raise RenderError(f"render: truth {truth} has {true_v.shape[0]} frames but the mesh "
                              f"has {verts.shape[0]}")  # fmt: skip
        err = vertex_errors(verts[idx], true_v[idx], true_f) * 1000
        panel.update(scalars=err, clim=(0.0, clim_mm), cmap="inferno",
                     scalar_title="distance to the true body (mm)",
                     title=f"{panel['title']}: mean {err.mean():.1f} mm")  # fmt: skip
        attrs.update(kind="error", clim_mm=clim_mm, mean_mm=float(err.mean()),
                     p95_mm=float(np.percentile(err, 95)))  # fmt: skip
        ctx.figure("error mean mm", round(attrs["mean_mm"], 2))
        ctx.figure("error p95 mm", round(attrs["p95_mm"], 2))
    frames = render_frames([panel], width=width, height=height, view=view, follow=follow,
                           **_axes(markers), progress=ctx.progress)
    rate = (mesh.rate or markers.rate) / max(1, stride)
    return {"video": Video(frames, rate, attrs)}


def read_truth(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A true body animation: a PC2 point cache and the faces of the OBJ beside it.

    Parameters
    ----------
    path : str or Path
        ``<stem>.pc2``; the faces come from ``<stem>.obj``.

    Returns
    -------
    vertices : (F, V, 3) float ndarray
    faces : (T, 3) int ndarray

    Raises
    ------
    RenderError
        No OBJ beside the PC2, no triangles in it, or a vertex count that differs.
    """
    from mocapflow.stages.motion.formats.meshcache import MeshCacheError, read_pc2  # noqa: PLC0415

    path = Path(path)
    obj = path.with_suffix(".obj")
    try:
        verts = read_pc2(path)[0].astype(np.float64)
        lines = obj.read_text().splitlines()
    except (OSError, MeshCacheError) as e:
        raise RenderError(f"render: truth {path}: {e}") from None
    tris = [[int(w.split("/")[0]) - 1 for w in ln.split()[1:4]]
            for ln in lines if ln.startswith("f ")]  # fmt: skip
    faces = np.array(tris, dtype=np.int64).reshape(-1, 3)
    n_v = sum(ln.startswith("v ") for ln in lines)
    if not len(faces) or n_v != verts.shape[1]:
        raise RenderError(f"render: truth {path}: {obj.name} has {len(faces)} triangles and "
                          f"{n_v} vertices, the point cache {verts.shape[1]} vertices")  # fmt: skip
    return verts, faces


@stage("render_modes", outputs=("video", "report"))
def render_modes(
    markers: Markers,
    segmentation: Segmentation,
    mesh: Mesh,
    *,
    modes: list[str] | None = None,
    width: int = 400,
    height: int = 480,
    stride: int = 4,
    max_frames: int = 300,
    view: View = "front",
    follow: bool = True,
    deform_params: dict[str, Any] | None = None,
    ctx: Context,
) -> dict[str, Any]:
    """Figure 7 of the paper: the deformation modes side by side on the same frames.

    Every panel is the ``deform`` stage itself on the rendered frames, with
    ``mode`` set per panel and everything else from ``deform_params``.

    Parameters
    ----------
    markers : Markers
        Cleaned capture.
    segmentation : Segmentation
    mesh : Mesh
        Fitted detailed rest mesh (stage ``fit_mesh``).
    modes : list of str, optional
        Default: rigid, quadratic, rigid_residual, quadratic_residual.
    width, height : int
        Size of one panel.
    stride, max_frames : int
        Frame subsampling of the rendering.
    view : {"front", "back", "side", "iso"}
        Camera direction relative to the body (as in :func:`render_frames`).
    follow : bool
        Camera follows the body.
    deform_params : dict, optional
        Params of :func:`mocapflow.stages.skin.deform.deform` other than ``mode``
        (e.g. ``quadratic_damping``); default: the stage's defaults.

    Returns
    -------
    dict
        ``video`` (:class:`Video`, one panel per mode) and ``report`` (fallbacks).
    """
    modes = list(modes or MODES)
    bad = [m for m in modes if m not in MODES]
    if bad:
        raise RenderError(f"render_modes: unknown modes {bad}; choose from {list(MODES)}")
    params = dict(deform_params or {})
    if "mode" in params:
        raise RenderError("render_modes: deform_params must not set 'mode' (one panel per mode)")
    x = align_markers(markers, segmentation)
    idx = _frame_indices(x.shape[0], stride, max_frames)
    shown = markers.take_frames(idx)
    panels, messages = [], []
    for i, mode in enumerate(modes):
        ctx.progress(i, len(modes), "deform modes")
        sub = Context(part=ctx.part, mapper=ctx.mapper, workers=ctx.workers)
        try:
            out = deform(shown, segmentation, mesh, mode=mode, **params, ctx=sub)
        except (TypeError, ParamError) as e:
            raise RenderError(f"render_modes: bad deform_params: {e}") from None
        messages += sub.warnings  # fallbacks (with their hints), reported once below
        panels.append({
            "vertices": out["mesh"].vertices,
            "faces": mesh.faces, "markers": shown.positions,
            "title": mode.replace("_", " + "),
        })  # fmt: skip
    for msg in sorted(set(messages)):
        ctx.warn(msg)
    frames = render_frames(panels, width=width, height=height, view=view, follow=follow,
                           **_axes(markers), progress=ctx.progress)
    video = Video(frames, markers.rate / max(1, stride),
                  {"source_frames": idx.tolist(), "kind": "modes", "modes": modes})  # fmt: skip
    return {"video": video, "report": {"modes": modes, "frames": len(idx),
                                       "fallbacks": sorted({split_hint(m)[0]
                                                            for m in messages})}}  # fmt: skip


def vertex_errors(mesh: np.ndarray, truth: np.ndarray, truth_faces: np.ndarray) -> np.ndarray:
    """Per-vertex distance ``(F, V)`` of a mesh sequence to a ground-truth sequence.

    Vertex to vertex when both have the same vertex count (same topology),
    otherwise from each vertex to the closest point of the truth surface.
    """
    if mesh.shape == truth.shape:
        return np.linalg.norm(mesh - truth, axis=-1)
    out = np.empty(mesh.shape[:2])
    for f in range(mesh.shape[0]):
        out[f] = closest_points_on_triangles(mesh[f], truth[f], truth_faces)[2]
    return out


@stage("render_error", outputs=("video", "report", "mesh"))
def render_error(
    mesh: Mesh,
    truth: Mesh,
    *,
    clim_mm: float = 20.0,
    width: int = 640,
    height: int = 480,
    stride: int = 2,
    max_frames: int = 600,
    view: View = "front",
    follow: bool = True,
    ctx: Context,
) -> dict[str, Any]:
    """Heat map of the per-vertex distance (mm) between a deformed mesh and ground truth.

    Parameters
    ----------
    mesh : Mesh
        Animated mesh ``(F, V, 3)`` (stage ``deform``).
    truth : Mesh
        Ground-truth animated mesh ``(F, V', 3)`` (e.g. the simulator's); vertex
        to vertex when ``V' == V``, else to the closest truth surface point.
    clim_mm : float
        Upper end of the colour scale in mm.
    width, height, stride, max_frames, view, follow
        As in :func:`render`.

    Returns
    -------
    dict
        ``video`` (:class:`Video`), ``report`` with the per-vertex error
        mean / p95 / max in mm over all frames (not only the rendered ones), and
        ``mesh``: the evaluated frames of ``mesh`` with the error as per-frame point
        data ``error_mm (F, V)`` (the ``mesh`` exporter writes it into the VTP
        series and the USD primvars).
    """
    if not (mesh.animated and truth.animated):
        raise RenderError("render_error: both meshes must be animated (F, V, 3)")
    if mesh.vertices.shape[0] != truth.vertices.shape[0]:
        raise RenderError(
            f"render_error: mesh has {mesh.vertices.shape[0]} frames, truth "
            f"{truth.vertices.shape[0]}"
        )
    idx = _frame_indices(mesh.vertices.shape[0], stride, max_frames)
    same = mesh.vertices.shape == truth.vertices.shape
    err_all = (
        vertex_errors(mesh.vertices, truth.vertices, truth.faces) if same
        else vertex_errors(mesh.vertices[idx], truth.vertices[idx], truth.faces)
    ) * 1000  # fmt: skip
    err_r = err_all[idx] if same else err_all
    panel = {"vertices": mesh.vertices[idx], "faces": mesh.faces, "scalars": err_r,
             "clim": (0.0, clim_mm), "cmap": "inferno", "scalar_title": "error (mm)",
             "title": "distance to ground truth"}  # fmt: skip
    frames = render_frames([panel], width=width, height=height, view=view, follow=follow,
                           **_axes(mesh), progress=ctx.progress)
    report = {
        "mean_mm": float(np.mean(err_all)),
        "p95_mm": float(np.percentile(err_all, 95)),
        "max_mm": float(np.max(err_all)),
        "frames_evaluated": "all" if same else len(idx),
        "vertex_to_vertex": bool(same),
    }
    for name in ("mean", "p95", "max"):
        ctx.figure(f"error {name} mm", round(report[f"{name}_mm"], 2))
    video = Video(frames, (mesh.rate or 30.0) / max(1, stride),
                  {"source_frames": idx.tolist(), "kind": "error", "clim_mm": clim_mm})  # fmt: skip
    shown = mesh.vertices if same else mesh.vertices[idx]
    rate = mesh.rate if same or not mesh.rate else mesh.rate / max(1, stride)
    static = {k: a for k, a in mesh.point_data.items() if not mesh.frame_varying(a)}
    err_mesh = Mesh(shown, mesh.faces, rate=rate, attrs=mesh.attrs,
                    point_data={**static, "error_mm": err_all.astype(np.float32)})
    return {"video": video, "report": report, "mesh": err_mesh}
