"""Stick-figure renderings of a motion: a PNG strip of poses, or an MP4.

``stickfigure`` (stage) draws evenly spaced frames of a motion side by side
(bones as lines from forward kinematics, ``y`` up, seen from the side or from
above) and returns a :class:`StickStrip`; its exporter writes ``<stem>.png``
and, when the strip holds the video frames too, ``<stem>.mp4``.  matplotlib and
imageio(-ffmpeg) are imported inside the functions.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context, stage
from mocapflow.pipeline.codecs import Encoded, codec, component_coords, exporter, frame_coords
from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.motion.kinematics import motion_positions

__all__ = ["StickStrip", "render_strip", "render_video", "stickfigure"]


@dataclass(eq=False)
class StickStrip:
    """A rendered strip (and optionally a video) of a motion.

    Parameters
    ----------
    image : (H, W, 3) uint8 ndarray
        The strip.
    video : (N, h, w, 3) uint8 ndarray, optional
        Video frames.
    rate : float
        Frames per second of the video.
    frames : list of int
        Motion frames shown in the strip.
    attrs : dict
    """

    image: np.ndarray
    video: np.ndarray | None = None
    rate: float = 30.0
    frames: list[int] = field(default_factory=list)
    attrs: dict[str, Any] = field(default_factory=dict)


def _encode(s: StickStrip) -> Encoded:
    arrays = {"image": (s.image, ("image_y", "image_x", "rgb"))}  # (strip and video sizes differ)
    coords = component_coords("rgb")
    if s.video is not None:
        arrays["video"] = (s.video, ("frame", "y", "x", "rgb"))
        coords.update(frame_coords(s.video.shape[0], s.rate))
    attrs = {"rate": s.rate, "frames": s.frames, "attrs": s.attrs}
    return Encoded("stickstrip", arrays, attrs, coords)


def _decode(e: Encoded) -> StickStrip:
    return StickStrip(
        image=e.arrays["image"][0],
        video=e.arrays["video"][0] if "video" in e.arrays else None,
        rate=e.attrs["rate"],
        frames=list(e.attrs.get("frames", [])),
        attrs=e.attrs.get("attrs", {}),
    )


codec("stickstrip", encode=_encode, decode=_decode)(StickStrip)


@exporter("stickstrip")
def _export(obj: StickStrip, directory: Path, stem: str, **options: Any) -> list[Path]:
    import imageio.v3 as iio  # noqa: PLC0415 (heavy)

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    out = [directory / f"{stem}.png"]
    iio.imwrite(out[0], obj.image)
    if obj.video is not None:
        out.append(directory / f"{stem}.mp4")
        _write_mp4(obj.video, out[1], obj.rate)
    return out


def _write_mp4(frames: np.ndarray, path: Path, rate: float) -> None:
    import imageio.v2 as imageio  # noqa: PLC0415 (heavy)

    with imageio.get_writer(path, fps=rate, codec="libx264", macro_block_size=1) as w:
        for f in frames:
            w.append_data(f)


def _axes(view: str) -> tuple[int, int]:
    return {"side": (2, 1), "front": (0, 1), "top": (0, 2)}[view]


def _canvas(fig) -> np.ndarray:
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def render_strip(
    motion: Motion,
    *,
    n_panels: int = 8,
    view: Literal["side", "front", "top"] = "side",
    panel_size: float = 1.6,
    dpi: int = 80,
    highlight: list[int] | None = None,
) -> tuple[np.ndarray, list[int]]:
    """Evenly spaced poses side by side.

    Parameters
    ----------
    motion : Motion
    n_panels : int
    view : {"side", "front", "top"}
        Projection (side: z horizontal, y up).
    panel_size : float
        Inches per panel.
    dpi : int
    highlight : list of int, optional
        Frames drawn in red (e.g. constrained frames) when shown.

    Returns
    -------
    image : (H, W, 3) uint8 ndarray
    frames : list of int
    """
    import matplotlib  # noqa: PLC0415 (heavy)

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt  # noqa: PLC0415 (heavy)

    pos = motion_positions(motion)
    F = motion.n_frames
    frames = np.unique(np.linspace(0, F - 1, max(1, min(n_panels, F))).round().astype(int))
    h, v = _axes(view)
    par = motion.skeleton.parents
    fig, axs = plt.subplots(
        1, len(frames), figsize=(panel_size * len(frames), panel_size * 1.4), dpi=dpi
    )
    axs = np.atleast_1d(axs)
    lo, hi = pos[..., v].min(), pos[..., v].max()
    half = 0.6 * max(hi - lo, 1e-3)
    marked = set(highlight or [])
    for ax, f in zip(axs, frames):
        p = pos[f]
        c = p[0, h]
        colour = "tab:red" if int(f) in marked else "k"
        for j in range(1, len(par)):
            ax.plot([p[par[j], h], p[j, h]], [p[par[j], v], p[j, v]], "-", color=colour, lw=1.5)
        ax.set_xlim(c - half, c + half)
        ax.set_ylim(lo - 0.1 * half, lo + 2 * half)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"{f}", fontsize=7)
    fig.tight_layout(pad=0.2)
    img = _canvas(fig)
    plt.close(fig)
    return img, [int(f) for f in frames]


def render_video(
    motion: Motion,
    *,
    view: Literal["side", "front", "top"] = "side",
    size: float = 3.0,
    dpi: int = 64,
    step: int = 1,
) -> np.ndarray:
    """Frames of a stick-figure animation following the root.

    Parameters
    ----------
    motion : Motion
    view : {"side", "front", "top"}
    size : float
        Inches.
    dpi : int
    step : int
        Draw every ``step``-th frame.

    Returns
    -------
    (N, h, w, 3) uint8 ndarray
    """
    import matplotlib  # noqa: PLC0415 (heavy)

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt  # noqa: PLC0415 (heavy)

    pos = motion_positions(motion)
    h, v = _axes(view)
    par = motion.skeleton.parents
    fig, ax = plt.subplots(figsize=(size, size), dpi=dpi)
    lo, hi = pos[..., v].min(), pos[..., v].max()
    half = 0.6 * max(hi - lo, 1e-3)
    lines = [ax.plot([], [], "k-", lw=1.5)[0] for _ in range(1, len(par))]
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    out = []
    for f in range(0, motion.n_frames, max(1, step)):
        p = pos[f]
        for ln, j in zip(lines, range(1, len(par))):
            ln.set_data([p[par[j], h], p[j, h]], [p[par[j], v], p[j, v]])
        ax.set_xlim(p[0, h] - half, p[0, h] + half)
        ax.set_ylim(lo - 0.1 * half, lo + 2 * half)
        out.append(_canvas(fig))
    plt.close(fig)
    return np.stack(out)


@stage("stickfigure", outputs=("strip",))
def stickfigure(
    motion: Motion,
    *,
    n_panels: int = 8,
    view: Literal["side", "front", "top"] = "side",
    video: bool = False,
    video_step: int = 1,
    highlight: list[int] | None = None,
    ctx: Context,
) -> dict[str, StickStrip]:
    """Stick-figure PNG strip (and optional MP4) of a motion.

    Parameters
    ----------
    motion : Motion
    n_panels : int
        Poses in the strip.
    view : {"side", "front", "top"}
        Camera: from the side (sagittal plane), the front, or above.
    video : bool
        Also render a video (exported as MP4).
    video_step : int
        Draw every n-th frame in the video.
    highlight : list of int, optional
        Frames to draw in red.
    ctx : Context

    Returns
    -------
    dict
        ``strip``: :class:`StickStrip`.
    """
    img, frames = render_strip(motion, n_panels=n_panels, view=view, highlight=highlight)
    vid = render_video(motion, view=view, step=video_step) if video else None
    rate = motion.rate / max(1, video_step)
    return {"strip": StickStrip(img, vid, rate, frames, {"view": view})}
