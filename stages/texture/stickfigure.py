"""Previews of a (synthesized) motion: a PNG strip of poses, an MP4, a joint-angle plot.

``stickfigure`` (stage) returns a :class:`StickStrip`; its exporter writes
``<stem>.png``, ``<stem>.mp4`` when it holds video frames and ``<stem>_angles.png``
when it holds the angle plot.  Given the ``synth`` report (or its source track) the
seams and the constraints, lettered A, B, … (:func:`preview_marks`), are marked on all three:

* the strip (:func:`render_strip`): poses at different stride phases plus the
  constrained frames, a side view in the root's heading frame and a top view scaled by
  the poses' horizontal extent with the root trace and the path, the whole trace from
  above, and a timeline of the output frames under the panels;
* the video (:func:`render_video`): the input and the output side by side on a floor
  grid, each camera following its root, frame counters and timelines;
* Moradoff Fig. 4.2-style plot (:func:`render_angles`): hip and knee flexion of the
  output against its frames, seams as thin lines, constraints lettered, and the
  input's curves with the same letters at the constrained input frames.

Bones are lines from forward kinematics, ``y`` up (a motion in other axes is turned
to them, as ``synth`` does).  matplotlib (Agg canvas, no pyplot) and
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
from mocapflow.stages.metrics.quality import seams_from_source
from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.motion.kinematics import motion_positions, reorient_motion
from mocapflow.stages.motion.rotations import heading_split

__all__ = ["COLOURS", "StickStrip", "cycle_period", "leg_angles", "panel_frames",
           "preview_marks", "render_angles", "render_strip", "render_video", "stickfigure"]


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
    angles : (h, w, 3) uint8 ndarray, optional
        Joint-angle plot (:func:`render_angles`).
    """

    image: np.ndarray
    video: np.ndarray | None = None
    rate: float = 30.0
    frames: list[int] = field(default_factory=list)
    attrs: dict[str, Any] = field(default_factory=dict)
    angles: np.ndarray | None = None

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
    if s.angles is not None:
        arrays["angles"] = (s.angles, ("angles_y", "angles_x", "rgb"))
    attrs = {"rate": s.rate, "frames": s.frames, "attrs": s.attrs}
    return Encoded("stickstrip", arrays, attrs, coords)


def _decode(e: Encoded) -> StickStrip:
    return StickStrip(
        image=e.arrays["image"][0],
        video=e.arrays["video"][0] if "video" in e.arrays else None,
        rate=e.attrs["rate"],
        frames=list(e.attrs.get("frames", [])),
        attrs=e.attrs.get("attrs", {}),
        angles=e.arrays["angles"][0] if "angles" in e.arrays else None,
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
    if obj.angles is not None:
        out.append(directory / f"{stem}_angles.png")
        iio.imwrite(out[-1], obj.angles)
    return out


def _write_mp4(frames: np.ndarray, path: Path, rate: float) -> None:
    import imageio.v2 as imageio  # noqa: PLC0415 (heavy)

    with imageio.get_writer(path, fps=rate, codec="libx264", macro_block_size=1) as w:
        for f in frames:
            w.append_data(f)


def _figure(width: float, height: float, dpi: int, **kw: Any):
    """A matplotlib Figure on an Agg canvas (no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415 (heavy)
    from matplotlib.figure import Figure  # noqa: PLC0415 (heavy)

    fig = Figure(figsize=(width, height), dpi=dpi, **kw)
    FigureCanvasAgg(fig)
    fig.patch.set_facecolor("white")
    return fig


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


#: Colours of the previews (the tests look for them): bones, constrained frames and
#: their letters, seams, the root trace, the path (top views), the floor grid (video).
COLOURS = {"bone": "#111111", "constraint": "#d62728", "seam": "#9467bd",
           "root": "#1f77b4", "path": "#2ca02c", "grid": "#c8c8c8"}


#: Frames per second the video is drawn at by default (``video_step``).
VIDEO_RATE = 30.0


def _letter(k: int) -> str:
    """``A`` … ``Z``, then ``A2`` … for the 27th constraint on."""
    return chr(65 + k % 26) + (str(k // 26 + 1) if k >= 26 else "")


def preview_marks(
    motion: Motion,
    report: dict[str, Any] | None = None,
    source_index: np.ndarray | None = None,
    source: Motion | None = None,
) -> dict[str, Any]:
    """Seams and lettered constraints of a synthesized motion, as frames of its motion.

    Parameters
    ----------
    motion : Motion
        The synthesized motion (``F`` frames at its rate).
    report : dict, optional
        The ``synth`` report: ``seams`` (synthesis frames), ``rate`` (synthesis),
        ``constraints_synthesis`` (``[input, output]`` at the synthesis rate),
        ``constraint_output_frames``.
    source_index : (L,) int ndarray, optional
        Input frame per synthesis frame; its jumps are the seams when there is no report.
    source : Motion, optional
        The input motion: constrained input frames are counted at its rate.

    Returns
    -------
    dict
        ``seams`` (sorted output frames, list of int) and ``constraints`` (list of
        ``{"letter", "output_frame", "input_frame"}``, by output frame; ``input_frame``
        at ``source``'s rate, else the synthesis rate).
    """
    F = motion.n_frames
    report = report or {}
    rate = float(report.get("rate") or motion.rate)
    seams = np.asarray(report.get("seams") or [], dtype=np.float64) * (motion.rate / rate)
    if not report and source_index is not None:
        src = np.asarray(source_index)
        seams = seams_from_source(src) * (F / max(src.size, 1))
    seams = np.unique(np.clip(np.round(seams), 0, max(F - 1, 0)).astype(int))
    syn = report.get("constraints_synthesis") or []
    in_scale = (source.rate if source is not None else rate) / rate
    out = [int(round(j * motion.rate / rate)) for _, j in syn]
    cons = sorted(zip(out, [int(round(i * in_scale)) for i, _ in syn]))
    return {
        "seams": [int(s) for s in seams],
        "constraints": [{"letter": _letter(k), "output_frame": min(max(j, 0), F - 1),
                         "input_frame": i} for k, (j, i) in enumerate(cons)],
    }


def _ground(motion: Motion) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Y-up, +Z-facing joint positions ``(F, J, 3)``, root heading ``(F,)`` (rad), floor
    height and figure height (``(F, J, 3)`` positions relative to the floor's 1st percentile)."""
    m = reorient_motion(motion)
    pos = motion_positions(m)
    heading, _ = heading_split(m.rotations[:, 0])
    low = pos[..., 1].min(axis=1)
    floor = float(np.percentile(low, 1)) if low.size else 0.0
    height = float(np.percentile(pos[..., 1].max(axis=1) - floor, 99)) if low.size else 1.0
    return pos, heading, floor, max(height, 1e-3)


def _heading_frame(pos: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """``(F, J, 3)`` positions about each frame's root, turned so the root faces +Z."""
    rel = pos - pos[:, :1] * np.array([1.0, 0.0, 1.0])
    c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
    x, z = rel[..., 0], rel[..., 2]
    return np.stack([c * x - s * z, rel[..., 1], s * x + c * z], axis=-1)


def _bones(p: np.ndarray, parents, h: int, v: int) -> np.ndarray:
    """``(B, 2, 2)`` bone segments of one pose ``p`` ``(J, 3)`` on axes ``h``, ``v``."""
    j = np.arange(1, len(parents))
    par = np.asarray(parents)[j]
    return np.stack([p[par][:, [h, v]], p[j][:, [h, v]]], axis=1)


def _head(skeleton, pos: np.ndarray) -> int:
    """The joint named like a head, else the highest on average."""
    names = [n.lower() for n in skeleton.names]
    named = [j for j, n in enumerate(names) if "head" in n and "end" not in n]
    return named[0] if named else int(np.argmax(pos[..., 1].mean(axis=0)))


def _path_points(path: list[list[float]] | None, path_mode: str) -> np.ndarray | None:
    if path is None:
        return None
    from mocapflow.stages.texture.root import PathCurve  # noqa: PLC0415 (scipy)

    return PathCurve.from_points(path, mode=path_mode).samples


def _pixel_box(ax, height: int) -> list[int]:
    """``[x0, y0, x1, y1]`` image pixels (rows from the top) of an axes."""
    b = ax.get_window_extent()
    return [int(round(b.x0)), int(round(height - b.y1)), int(round(b.x1)),
            int(round(height - b.y0))]


def render_strip(
    motion: Motion,
    *,
    n_panels: int = 8,
    view: str | list[str] | tuple[str, ...] = ("side", "top"),
    panel_size: float = 1.6,
    dpi: int = 100,
    highlight: list[int] | None = None,
    marks: dict[str, Any] | None = None,
    path: np.ndarray | None = None,
    return_boxes: bool = False,
) -> tuple[np.ndarray, list[int]] | tuple[np.ndarray, list[int], dict[str, list[list[int]]]]:
    """Poses spread over the motion side by side, at different phases (:func:`panel_frames`).

    One row of panels per view: ``side`` / ``front`` in the root's heading frame
    (the figure faces right / the camera, the floor as a line), scaled by the
    figure's height; ``top`` seen from above in world axes, each centred on its pose,
    all at one scale from the horizontal extent of the poses shown (the largest fills
    86 % of its panel), with the root trace and ``path``.  With a ``top`` row, the whole
    root trace from above (path, seams, constraints, panel frames) on the right.
    Under the panels a timeline of the output frames: seams, lettered constraints and
    the panel frames, each panel joined to its frame.  Constrained frames are panels too.

    Parameters
    ----------
    motion : Motion
    n_panels : int
        Panels at different stride phases (constrained frames come on top).
    view : str or sequence of {"side", "front", "top"}
        The rows.
    panel_size : float
        Inches per panel (width).
    dpi : int
    highlight : list of int, optional
        Frames drawn in red (e.g. constrained frames) when shown.
    marks : dict, optional
        :func:`preview_marks` (seams and lettered constraints).
    path : (M, 2) float ndarray, optional
        Ground path ``(x, z)`` (Y up), drawn in the top views.

    return_boxes : bool
        Also return the pixel boxes of the panels.

    Returns
    -------
    image : (H, W, 3) uint8 ndarray
    frames : list of int
    boxes : dict of str to list of [x0, y0, x1, y1]
        Only with ``return_boxes``: the panels' pixel boxes per view, and ``"timeline"``.
    """
    from matplotlib.collections import LineCollection  # noqa: PLC0415 (heavy)
    from matplotlib.lines import Line2D  # noqa: PLC0415 (heavy)

    views = ([view] if isinstance(view, str) else list(view)) or ["side"]
    marks = marks or {"seams": [], "constraints": []}
    pos, heading, floor, H = _ground(motion)
    F = pos.shape[0]
    letters = {c["output_frame"]: c["letter"] for c in marks["constraints"]}
    frames = sorted(set(panel_frames(pos, n_panels)) | set(letters))
    red = set(highlight or []) | set(letters)
    local = _heading_frame(pos, heading)
    head = _head(motion.skeleton, pos)
    # top views: centred on each pose's box from above, one scale from the largest box shown
    lo_xz, hi_xz = pos[..., [0, 2]].min(axis=1), pos[..., [0, 2]].max(axis=1)
    mid = 0.5 * (lo_xz + hi_xz)
    half_top = 0.58 * max(float((hi_xz - lo_xz)[frames].max()), 0.1 * H)
    root = pos[:, 0][:, [0, 2]]
    top_in = "top" in views
    # layout (inches): rows of panels, the whole path from above on the right, a timeline
    cw, m, title = panel_size, 0.08, 0.22
    rows = [1.25 * cw if v != "top" else cw for v in views]
    ow = 2.2 * cw if top_in else 0.0
    tl = 0.42
    W = 2 * m + len(frames) * cw + (0.3 + ow if top_in else 0.0)
    Ht = m + title + sum(rows) + 0.04 * (len(rows) - 1) + 0.35 + tl + 0.3
    fig = _figure(W, Ht, dpi)
    par = motion.skeleton.parents
    boxes: dict[str, list[list[int]]] = {}
    axes_rows = []
    y = Ht - m - title
    for v, rh in zip(views, rows):
        y -= rh
        row = []
        for c, f in enumerate(frames):
            ax = fig.add_axes(((m + c * cw + 0.03) / W, y / Ht, (cw - 0.06) / W, rh / Ht))
            ax.set_xticks([])
            ax.set_yticks([])
            colour = COLOURS["constraint"] if f in red else COLOURS["bone"]
            if v == "top":
                p = pos[f]
                ax.plot(root[:, 0], root[:, 1], "-", color=COLOURS["root"], lw=1.0, zorder=1)
                if path is not None:
                    ax.plot(path[:, 0], path[:, 1], "-", color=COLOURS["path"], lw=2.0,
                            zorder=0)
                ax.add_collection(LineCollection(_bones(p, par, 0, 2), colors=colour, lw=1.6,
                                                 zorder=3))
                ax.plot(p[head, 0], p[head, 2], "o", color=colour, ms=4, zorder=4)
                ax.set_xlim(mid[f, 0] + half_top, mid[f, 0] - half_top)  # seen from above
                if not row:  # a scale bar
                    bar = _nice(half_top)
                    x0, z0 = mid[f, 0] + 0.92 * half_top, mid[f, 1] - 0.9 * half_top
                    ax.plot([x0, x0 - bar], [z0, z0], "-", color="#777777", lw=1.5)
                    ax.text(x0 - 0.5 * bar, z0 + 0.04 * half_top, f"{bar:g} m", fontsize=6,
                            ha="center", va="bottom", color="#777777")
                ax.set_ylim(mid[f, 1] - half_top, mid[f, 1] + half_top)
            else:
                h = 2 if v == "side" else 0
                p = local[f]
                ax.axhline(floor, color=COLOURS["grid"], lw=1.0, zorder=0)
                ax.add_collection(LineCollection(_bones(p, par, h, 1), colors=colour, lw=1.6))
                ax.plot(p[head, h], p[head, 1], "o", color=colour, ms=4)
                span = 1.18 * H * (cw - 0.06) / rh
                ax.set_xlim(-0.5 * span, 0.5 * span)
                ax.set_ylim(floor - 0.06 * H, floor + 1.12 * H)
            ax.set_aspect("equal", adjustable="box")
            row.append(ax)
        axes_rows.append(row)
        y -= 0.04
    for ax, f in zip(axes_rows[0], frames):
        lab = f"{f}" + (f"  {letters[f]}" if f in letters else "")
        ax.set_title(lab, fontsize=8, pad=2, fontweight="bold" if f in letters else "normal",
                     color=COLOURS["constraint"] if f in letters else "black")
    if top_in:  # the whole motion from above
        x0 = m + len(frames) * cw + 0.3
        ax = fig.add_axes((x0 / W, y / Ht + 0.04 / Ht, ow / W, (sum(rows)) / Ht))
        if path is not None:
            ax.plot(path[:, 0], path[:, 1], "-", color=COLOURS["path"], lw=2.0, label="path")
        ax.plot(root[:, 0], root[:, 1], "-", color=COLOURS["root"], lw=1.0, label="root")
        ax.plot(*root[0], "o", color=COLOURS["root"], ms=4)
        s = np.asarray(marks["seams"], dtype=int)
        if s.size:
            ax.plot(root[s, 0], root[s, 1], "x", color=COLOURS["seam"], ms=4, label="seams")
        ax.plot(root[frames, 0], root[frames, 1], ".", color=COLOURS["bone"], ms=3,
                label="panels")
        for c in marks["constraints"]:
            j = c["output_frame"]
            ax.plot(*root[j], "o", color=COLOURS["constraint"], ms=4)
            ax.annotate(c["letter"], root[j], xytext=(3, 3), textcoords="offset points",
                        color=COLOURS["constraint"], fontsize=9, fontweight="bold")
        ax.set_aspect("equal", adjustable="datalim")
        ax.invert_xaxis()
        ax.tick_params(labelsize=6)
        ax.set_title("from above (m)", fontsize=8, pad=2)
        ax.legend(fontsize=6, loc="best", frameon=False)
    # timeline: output frames, seams, constraints, panels
    tw = len(frames) * cw
    tax = fig.add_axes((m / W, (0.3 + 0.05) / Ht, tw / W, tl / Ht))
    tax.set_xlim(-0.5, F - 0.5)
    tax.set_ylim(0, 1)
    tax.set_yticks([])
    tax.tick_params(labelsize=6, length=2, pad=1)
    tax.axhline(0.35, color="#888888", lw=0.8)
    for s in marks["seams"]:
        tax.axvline(s, ymin=0.1, ymax=0.6, color=COLOURS["seam"], lw=0.8)
    for f in frames:
        tax.plot([f, f], [0.25, 0.45], "-", color=COLOURS["bone"], lw=1.2)
    for c in marks["constraints"]:
        tax.plot(c["output_frame"], 0.35, "v", color=COLOURS["constraint"], ms=5)
        tax.text(c["output_frame"], 0.62, c["letter"], ha="center", va="bottom", fontsize=8,
                 color=COLOURS["constraint"], fontweight="bold")
    for sp in ("top", "left", "right"):
        tax.spines[sp].set_visible(False)
    bottom = y + 0.04  # lowest panel row
    for c, f in enumerate(frames):  # each panel to its frame on the timeline
        fig.add_artist(Line2D([(m + (c + 0.5) * cw) / W, (m + tw * (f + 0.5) / F) / W],
                              [bottom / Ht, (0.35 + tl) / Ht], color="#bbbbbb", lw=0.6))
    fig.text(m / W, 0.06 / Ht,
             f"output frames 0–{F - 1}   |  panels: black ticks   |  "
             f"seams ({len(marks['seams'])}): purple lines   |  constrained frames: "
             "red letters" + ("   |  top views: root trace blue, path green" if top_in else ""),
             fontsize=7, color="#333333")
    fig.canvas.draw()
    img = _canvas(fig)
    for v, row in zip(views, axes_rows):
        boxes.setdefault(v, [_pixel_box(ax, img.shape[0]) for ax in row])
    boxes["timeline"] = [_pixel_box(tax, img.shape[0])]  # x: output frames -0.5 … F - 0.5
    if return_boxes:
        return img, [int(f) for f in frames], boxes
    return img, [int(f) for f in frames]


def _nice(x: float) -> float:
    """The 1-2-5 number nearest below ``x``."""
    e = 10.0 ** np.floor(np.log10(x))
    return float(e * max(k for k in (1, 2, 5) if k * e <= x))


class _Camera:
    """Orthographic camera seen from the side, turned by ``azimuth`` and raised by
    ``elevation`` (radians) about a centre on the floor."""

    def __init__(self, azimuth: float, elevation: float) -> None:
        self.right = np.array([np.sin(azimuth), 0.0, np.cos(azimuth)])
        self.away = np.array([-np.cos(azimuth), 0.0, np.sin(azimuth)])
        self.ce, self.se = np.cos(elevation), np.sin(elevation)

    def project(self, p: np.ndarray, centre: np.ndarray) -> np.ndarray:
        """``(..., 3)`` points → ``(..., 2)`` screen ``(u, v)`` (``v`` up)."""
        q = p - centre
        return np.stack([q @ self.right, q[..., 1] * self.ce + (q @ self.away) * self.se], -1)


def _grid(centre: np.ndarray, reach: float, step: float, floor: float) -> np.ndarray:
    """``(G, 2, 3)`` floor grid lines (spacing ``step``) within ``reach`` of ``centre``."""
    lo, hi = centre[[0, 2]] - reach, centre[[0, 2]] + reach
    out = []
    for a in (0, 1):  # lines of constant x, then of constant z
        k = np.arange(np.ceil(lo[a] / step), np.floor(hi[a] / step) + 1) * step
        ends = np.full((k.size, 2, 3), floor, dtype=np.float64)
        ends[:, :, 2 * a] = k[:, None]
        ends[:, :, 2 - 2 * a] = [lo[1 - a], hi[1 - a]]
        out.append(ends)
    return np.concatenate(out)


def render_video(
    motion: Motion,
    *,
    source: Motion | None = None,
    marks: dict[str, Any] | None = None,
    height: int = 480,
    step: int = 1,
    max_frames: int = 300,
    azimuth: float = 25.0,
    elevation: float = 15.0,
) -> tuple[np.ndarray, list[int]]:
    """Frames of a stick-figure animation on a floor grid, the camera following the root.

    With ``source`` the input plays beside the output (looped at its own rate); each
    panel has its frame counter and a timeline (cursor, and on the output's seams and
    lettered constraints); a constrained frame draws its figure red and shows its letter
    for 0.3 s around it (the input at its constrained frames too).

    Parameters
    ----------
    motion : Motion
        The output motion (``F`` frames).
    source : Motion, optional
        The input motion, drawn on the left.
    marks : dict, optional
        :func:`preview_marks`.
    height : int
        Pixels (the width is ``0.8 height`` per panel, even).
    step : int
        Draw every ``step``-th frame (the video plays at ``rate / step``).
    max_frames : int
        At most this many video frames (the first ones).
    azimuth, elevation : float
        Camera turn from the side view about the vertical, and its elevation (degrees).

    Returns
    -------
    frames : (N, height, w, 3) uint8 ndarray
    shown : list of int
        Output frame of each video frame.
    """
    from matplotlib.collections import LineCollection  # noqa: PLC0415 (heavy)

    marks = marks or {"seams": [], "constraints": []}
    cam = _Camera(np.radians(azimuth), np.radians(elevation))
    shown = list(range(0, motion.n_frames, max(1, int(step))))[:max(1, int(max_frames))]
    panels = [("output", motion, {c["output_frame"]: c["letter"] for c in marks["constraints"]})]
    if source is not None:
        panels.insert(0, ("input", source,
                          {c["input_frame"]: c["letter"] for c in marks["constraints"]}))
    hold = max(1, int(round(0.15 * motion.rate)))
    height = 2 * (int(height) // 2)
    pw = 2 * int(round(0.4 * height))
    step = max(1, int(step))
    dpi = 100
    fig = _figure(pw * len(panels) / dpi, height / dpi, dpi)
    H = _ground(motion)[3]
    spacing = _nice(H / 2.5)  # one floor grid for both panels
    span_v = 1.45 * H
    span_u = span_v * pw / (0.8 * height)
    state, dynamic = [], []
    for k, (name, mot, lettered) in enumerate(panels):
        pos, _, floor, _ = _ground(mot)
        ax = fig.add_axes((k / len(panels), 0.12, 1 / len(panels), 0.8))
        ax.set_axis_off()
        ax.set_xlim(-0.5 * span_u, 0.5 * span_u)
        ax.set_ylim(-0.25 * H, -0.25 * H + span_v)
        grid = LineCollection([], colors=COLOURS["grid"], lw=0.8, zorder=0, animated=True)
        bones = LineCollection([], colors=COLOURS["bone"], lw=2.2, zorder=2, animated=True)
        ax.add_collection(grid)
        ax.add_collection(bones)
        head = ax.plot([], [], "o", ms=7, color=COLOURS["bone"], animated=True)[0]
        fig.text((k + 0.5) / len(panels), 0.985, name, ha="center", va="top", fontsize=12)
        counter = ax.text(0.02, 0.99, "", transform=ax.transAxes, fontsize=10, va="top",
                          family="monospace", animated=True)
        flag = ax.text(0.98, 0.99, "", transform=ax.transAxes, fontsize=20, va="top",
                       ha="right", color=COLOURS["constraint"], fontweight="bold", animated=True)
        tax = fig.add_axes((k / len(panels) + 0.06 / len(panels), 0.04, 0.88 / len(panels),
                            0.05))
        tax.set_xlim(-0.5, mot.n_frames - 0.5)
        tax.set_ylim(0, 1)
        tax.set_axis_off()
        tax.axhline(0.5, color="#888888", lw=1.0)
        if name == "output":
            for s in marks["seams"]:
                tax.axvline(s, ymin=0.2, ymax=0.8, color=COLOURS["seam"], lw=0.8)
        for f, letter in lettered.items():
            tax.text(f, 0.5, letter, ha="center", va="center", fontsize=8,
                     color=COLOURS["constraint"], fontweight="bold")
        cursor = tax.axvline(0, color=COLOURS["bone"], lw=2.0, animated=True)
        state.append({"motion": mot, "lettered": lettered, "pos": pos, "floor": floor,
                      "head": _head(mot.skeleton, pos), "artists": (grid, bones, head),
                      "texts": (counter, flag, cursor)})
        dynamic += [grid, bones, head, counter, flag, cursor]
    fig.canvas.draw()  # the static parts once; then only the moving artists per frame
    background = fig.canvas.copy_from_bbox(fig.bbox)
    reach = 1.2 * max(span_u, span_v)
    out = np.empty((len(shown), *np.asarray(fig.canvas.buffer_rgba()).shape[:2], 3), np.uint8)
    for i, t in enumerate(shown):
        fig.canvas.restore_region(background)
        for st in state:
            mot, pos, lettered = st["motion"], st["pos"], st["lettered"]
            grid, bones, head = st["artists"]
            counter, flag, cursor = st["texts"]
            f = t if mot is motion else int(round(t * mot.rate / motion.rate)) % mot.n_frames
            centre = np.array([pos[f, 0, 0], st["floor"], pos[f, 0, 2]])
            grid.set_segments(cam.project(_grid(centre, reach, spacing, st["floor"]), centre))
            p = np.c_[cam.project(pos[f], centre), np.zeros(pos.shape[1])]
            bones.set_segments(_bones(p, mot.skeleton.parents, 0, 1))
            head.set_data([p[st["head"], 0]], [p[st["head"], 1]])
            tol = int(step * mot.rate / motion.rate) // 2  # a skipped constrained frame
            colour = (COLOURS["constraint"] if any(abs(g - f) <= tol for g in lettered)
                      else COLOURS["bone"])
            bones.set_color(colour)
            head.set_color(colour)
            flag.set_text(" ".join(lt for g, lt in lettered.items() if abs(g - f) <= hold))
            counter.set_text(f"frame {f:>{len(str(mot.n_frames))}}/{mot.n_frames}")
            cursor.set_xdata([f, f])
        for a in dynamic:
            fig.draw_artist(a)
        out[i] = np.asarray(fig.canvas.buffer_rgba())[..., :3]
    return out, shown


def leg_angles(motion: Motion) -> tuple[list[str], np.ndarray]:
    """Hip and knee flexion of each leg (degrees), or the most moving joints' angles.

    Hip flexion: the thigh's angle from straight down in the sagittal plane of the
    root's heading (positive forward); knee flexion: 180° minus the hip-knee-ankle
    angle.  Legs are the two-bone chains above the toes
    (:func:`~mocapflow.stages.texture.root.leg_chains`); a skeleton without them gets
    the rotation angle of its four most moving inner joints.

    Parameters
    ----------
    motion : Motion

    Returns
    -------
    names : list of str
    angles : (F, K) float ndarray
        Degrees.
    """
    from mocapflow.stages.motion.contacts import toe_indices  # noqa: PLC0415
    from mocapflow.stages.texture.root import leg_chains  # noqa: PLC0415

    sk = motion.skeleton
    try:
        chains = leg_chains(sk, toe_indices(sk))
    except ValueError:
        chains = []
    if not chains:
        w = np.clip(np.abs(motion.rotations[..., 0]), 0.0, 1.0)
        ang = np.degrees(2.0 * np.arccos(w))
        inner = [j for j in range(1, sk.n_joints) if sk.children(j)] or list(range(sk.n_joints))
        order = [inner[i] for i in np.argsort(-ang[:, inner].std(axis=0), kind="stable")[:4]]
        return [f"{sk.names[j]} angle" for j in order], ang[:, order]
    pos, heading, _, _ = _ground(motion)
    hip, knee, ankle = (np.array(c) for c in zip(*chains))
    thigh, shank = pos[:, knee] - pos[:, hip], pos[:, ankle] - pos[:, knee]
    fwd = np.stack([np.sin(heading), np.cos(heading)], axis=-1)[:, None]  # (F, 1, 2)
    hip_flex = np.degrees(np.arctan2((thigh[..., [0, 2]] * fwd).sum(-1), -thigh[..., 1]))
    cos = (-thigh * shank).sum(-1) / np.maximum(
        np.linalg.norm(thigh, axis=-1) * np.linalg.norm(shank, axis=-1), 1e-12)
    knee_flex = 180.0 - np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    names = [f"{sk.names[j]} flexion" for j in hip] + [f"{sk.names[j]} flexion" for j in knee]
    return names, np.concatenate([hip_flex, knee_flex], axis=1)


def render_angles(
    motion: Motion,
    *,
    source: Motion | None = None,
    marks: dict[str, Any] | None = None,
    dpi: int = 100,
) -> np.ndarray:
    """Joint angles over time with the constraints lettered (Moradoff Fig. 4.2 style).

    The output's hip and knee flexion (:func:`leg_angles`) against its frames, the
    seams as thin lines and each constraint lettered (A, B, …) at its output frame;
    below, the input's curves with the same letters at the constrained input frames.

    Parameters
    ----------
    motion : Motion
        The output.
    source : Motion, optional
        The input (a second plot).
    marks : dict, optional
        :func:`preview_marks`.
    dpi : int

    Returns
    -------
    (H, W, 3) uint8 ndarray
    """

    marks = marks or {"seams": [], "constraints": []}
    rows = [("output", motion, "output_frame")]
    if source is not None:
        rows.append(("input", source, "input_frame"))
    fig = _figure(11.5, 2.9 * len(rows) + 0.4, dpi, layout="constrained")
    axs = np.atleast_1d(fig.subplots(len(rows), 1))
    for ax, (name, mot, key) in zip(axs, rows):
        names, ang = leg_angles(mot)
        frames = np.arange(mot.n_frames)
        for k, (n, a) in enumerate(zip(names, ang.T)):
            ax.plot(frames, a, lw=1.2, color=f"C{k}", label=n)
        if name == "output":
            for k, s in enumerate(marks["seams"]):
                ax.axvline(s, color=COLOURS["seam"], lw=0.6, alpha=0.7,
                           label="seams" if k == 0 else None)
        top = float(ang.max()) if ang.size else 1.0
        for c in marks["constraints"]:
            f = c[key]
            if not 0 <= f < mot.n_frames:
                continue
            ax.axvline(f, color=COLOURS["constraint"], lw=0.8, ls=":")
            ax.plot(np.full(ang.shape[1], f), ang[f], "o", color=COLOURS["constraint"], ms=4)
            ax.annotate(c["letter"], (f, top), xytext=(0, 4), textcoords="offset points",
                        ha="center", va="bottom", fontsize=12, fontweight="bold",
                        color=COLOURS["constraint"], annotation_clip=False)
        ax.set_xlim(0, mot.n_frames - 1)
        ax.set_ylabel("degrees", fontsize=8)
        ax.set_xlabel(f"{name} frame ({mot.rate:g} fps)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_title(f"{name}: joint angles" + (", constraints lettered" if marks["constraints"]
                                                 else ""), fontsize=9, loc="left", pad=16)
        ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.005, 0.5), frameon=False)
    return _canvas(fig)


@stage("stickfigure", outputs=("strip",))
def stickfigure(
    motion: Motion,
    report: dict[str, Any] | None = None,
    source_index: np.ndarray | None = None,
    source: Motion | None = None,
    *,
    n_panels: int = 8,
    views: tuple[Literal["side", "front", "top"], ...] = ("side", "top"),
    path: list[list[float]] | None = None,
    path_mode: Literal["polyline", "spline"] = "polyline",
    video: bool = False,
    video_step: int | None = None,
    video_max_frames: int = 300,
    video_height: int = 480,
    angles: bool = True,
    highlight: list[int] | None = None,
    ctx: Context,
) -> dict[str, StickStrip]:
    """Stick-figure previews of a (synthesized) motion: PNG strip, optional MP4, angle plot.

    Parameters
    ----------
    motion : Motion
        The motion shown (``synth.motion``).
    report : dict, optional
        The ``synth`` report: seams and lettered constraints are marked
        (:func:`preview_marks`).
    source_index : (L,) int ndarray, optional
        The ``synth`` source track: its jumps are the seams when there is no report.
    source : Motion, optional
        The input motion: drawn beside the output in the video, and its curves in the
        angle plot with the constrained input frames lettered.
    n_panels : int
        Poses in the strip, at different stride phases; constrained frames are added.
    views : sequence of {"side", "front", "top"}
        Rows of the strip: side / front in the root's heading frame, top from above
        (root trace and path; then the whole trace from above on the right).
    path : list of [x, z], optional
        The ``synth`` path (Y-up ground plane), drawn in the top views.
    path_mode : {"polyline", "spline"}
        How its points are joined (as in ``synth``).
    video : bool
        Also render a video (exported as MP4): input and output side by side on a
        floor grid, the camera following each root (:func:`render_video`).
    video_step : int, optional
        Draw every n-th frame in the video (it plays at ``rate / video_step``); default
        the step nearest to 30 fps (:data:`VIDEO_RATE`; every frame below 45 fps).
    video_max_frames : int
        At most this many video frames (the first ones).
    video_height : int
        Video height in pixels (even; each figure's panel is ``0.8`` of it wide).
    angles : bool
        With a ``report``, also the Fig. 4.2-style joint-angle plot
        (:func:`render_angles`, exported as ``<stem>_angles.png``).
    highlight : list of int, optional
        Frames to draw in red.
    ctx : Context

    Returns
    -------
    dict
        ``strip``: :class:`StickStrip` (``attrs``: ``views``, ``panels`` (pixel boxes
        ``[x0, y0, x1, y1]`` per view and of the ``timeline``), ``seams`` and lettered
        ``constraints`` as output frames).
    """
    marks = preview_marks(motion, report, source_index, source)
    img, frames, boxes = render_strip(motion, n_panels=n_panels, view=list(views),
                                      highlight=highlight, marks=marks,
                                      path=_path_points(path, path_mode), return_boxes=True)
    step = max(1, int(video_step or round(motion.rate / VIDEO_RATE)))
    vid = None
    if video:
        vid, _ = render_video(motion, source=source, marks=marks, height=video_height,
                              step=step, max_frames=video_max_frames)
    plot = render_angles(motion, source=source, marks=marks) if angles and report else None
    rate = motion.rate / step
    attrs = {"views": list(views), "panels": boxes, **marks}
    return {"strip": StickStrip(img, vid, rate, frames, attrs, angles=plot)}
