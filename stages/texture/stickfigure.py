"""Stick-figure renderings of a motion: a PNG strip of poses, or an MP4.

``stickfigure`` (stage) draws frames spread over a motion side by side (bones
as lines from forward kinematics, ``y`` up, seen from the side or from above)
and returns a :class:`StickStrip`; its exporter writes ``<stem>.png``
and, when the strip holds the video frames too, ``<stem>.mp4``.  matplotlib and
imageio(-ffmpeg) are imported inside the functions.

Panels of a cyclic motion (a walk) taken at a fixed stride that happens to be a
multiple of the gait period would all show the same phase; :func:`panel_frames`
detects the period (:func:`cycle_period`) and spaces the panels ``q/n`` of a cycle
apart (``q`` coprime with ``n``), so ``n`` panels show ``n`` different phases.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context, stage
from mocapflow.pipeline.codecs import Encoded, codec, component_coords, exporter, frame_coords
from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.motion.kinematics import motion_positions

__all__ = ["StickStrip", "cycle_period", "panel_frames", "render_strip", "render_video",
           "stickfigure"]


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

    def __repr__(self) -> str:
        """One line: strip size, frames shown, video size and rate (never the pixels)."""
        H, W = self.image.shape[:2]
        if self.video is None:
            video = "no video"
        else:
            N, h, w = self.video.shape[:3]
            video = f"video {N} frames of {w}×{h} px @ {float(self.rate):.4g} Hz"
        return f"StickStrip({W}×{H} px strip of {len(self.frames)} frames, {video})"


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


def cycle_period(pos: np.ndarray, *, min_lag: int = 3, min_peak: float = 0.3
                 ) -> float | None:
    """Period (frames, sub-frame) of a cyclic motion from its joint positions, or ``None``.

    The signal is heading-independent: every joint's height and its horizontal
    distance from the root, standardised; the period is the first peak of their
    summed autocorrelation after it first drops below zero, refined by a parabola
    through the peak and its neighbours.

    Parameters
    ----------
    pos : (F, J, 3) ndarray
        Joint positions, ``y`` up.
    min_lag : int
        Shortest period considered.
    min_peak : float
        The peak's normalised autocorrelation must exceed this (else ``None``:
        not cyclic enough).

    Returns
    -------
    float or None
    """
    F = pos.shape[0]
    if F < 4 * max(min_lag, 1):
        return None
    rel = pos - pos[:, :1]
    X = np.concatenate([pos[..., 1], np.hypot(rel[..., 0], rel[..., 2])], axis=1)
    X = X - X.mean(axis=0)
    std = X.std(axis=0)
    keep = std > 1e-6 * max(float(std.max()), 1e-12)
    if not keep.any():
        return None
    X = X[:, keep] / std[keep]
    n = 1 << int(np.ceil(np.log2(2 * F)))
    spec = np.fft.rfft(X, n, axis=0)
    ac = np.fft.irfft((spec * spec.conj()).real, n, axis=0)[:F].sum(axis=1)
    ac = ac / (F - np.arange(F))  # unbiased: each lag averages over its own overlap
    ac = ac / ac[0]
    half = F // 2
    below = np.flatnonzero(ac[:half] < 0)
    if not below.size:
        return None
    start = max(int(below[0]), min_lag)
    if start >= half - 1:
        return None
    k = start + int(np.argmax(ac[start:half]))
    if ac[k] < min_peak or k in (start, half - 1):
        return None
    a, b, c = ac[k - 1], ac[k], ac[k + 1]
    den = a - 2 * b + c
    return float(k + (0.5 * (a - c) / den if den < 0 else 0.0))


def panel_frames(pos: np.ndarray, n_panels: int) -> list[int]:
    """Frames for ``n_panels`` poses spread over a motion, at different phases if cyclic.

    Evenly spaced frames show one phase ``n`` times when their spacing is a
    multiple of the cycle (a walk's stride).  With a detected period ``P``
    (:func:`cycle_period`) the spacing is ``q P / n`` instead, ``q`` the largest
    integer coprime with ``n`` for which the panels still fit in the motion: panel
    ``i`` is at phase ``i q / n`` (mod 1), so the ``n`` panels show ``n`` different
    phases, ``1/n`` of a cycle apart, spread over the motion (centred).  Without a
    period, or a motion too short for it, evenly spaced frames.

    Parameters
    ----------
    pos : (F, J, 3) ndarray
        Joint positions, ``y`` up.
    n_panels : int

    Returns
    -------
    list of int
        Increasing frame indices.
    """
    F = pos.shape[0]
    n = max(1, min(n_panels, F))
    even = [int(f) for f in np.unique(np.linspace(0, F - 1, n).round().astype(int))]
    period = cycle_period(pos) if n > 1 else None
    if period is None:
        return even
    q = int(np.floor((F - 1) / (n - 1) * n / period))
    while q >= 1 and math.gcd(q, n) != 1:
        q -= 1
    step = q * period / n
    if q < 1 or step < 1:
        return even
    start = 0.5 * ((F - 1) - (n - 1) * step)
    frames = np.unique(np.clip(np.round(start + step * np.arange(n)), 0, F - 1).astype(int))
    return [int(f) for f in frames]


def render_strip(
    motion: Motion,
    *,
    n_panels: int = 8,
    view: Literal["side", "front", "top"] = "side",
    panel_size: float = 1.6,
    dpi: int = 80,
    highlight: list[int] | None = None,
) -> tuple[np.ndarray, list[int]]:
    """Poses spread over the motion side by side, at different phases (:func:`panel_frames`).

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
    frames = np.asarray(panel_frames(pos, n_panels), dtype=int)
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
