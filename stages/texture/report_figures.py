"""Figures of the texture stages on the ``mocapflow report`` page.

* ``synth``: the root's path seen from above (seams marked), the source frame and
  the joint angles against time with the seams marked, a stick-figure strip
  (seam frames in red) and the synthesis report as a table;
* ``stickfigure``: the strip it rendered.

Figures are plain :class:`matplotlib.figure.Figure` objects (no pyplot state),
made only when a report is written; matplotlib is imported inside the functions.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mocapflow.pipeline.registry import report_figures
from mocapflow.pipeline.report import ReportEntry, html_table
from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.texture.stickfigure import render_strip

__all__ = ["joint_angles", "seam_output_frames", "stickfigure_figures", "synth_figures"]

#: Joints whose angle is drawn (those that move most).
ANGLE_JOINTS = 4
#: Poses in the strip.
STRIP_PANELS = 8


def _figure(width: float, height: float):
    from matplotlib.figure import Figure  # noqa: PLC0415 (heavy)

    return Figure(figsize=(width, height), layout="constrained")


def joint_angles(motion: Motion) -> np.ndarray:
    """Rotation angle of every joint from its rest orientation, degrees, ``(F, J)``."""
    w = np.clip(np.abs(motion.rotations[..., 0]), 0.0, 1.0)
    return np.degrees(2.0 * np.arccos(w))


def seam_output_frames(report: dict[str, Any], n_frames: int) -> np.ndarray:
    """The seams of a synthesis report (synthesis frames) as frames of its output motion."""
    seams = np.asarray(report.get("seams") or [], dtype=np.float64)
    scale = float(report.get("output_rate") or 1.0) / float(report.get("rate") or 1.0)
    return np.unique(np.clip(np.round(seams * scale), 0, max(n_frames - 1, 0)).astype(int))


def _path(motion: Motion, seams: np.ndarray):
    up = "xyz".index(str(motion.attrs.get("up", "+y"))[-1])
    h = [a for a in range(3) if a != up]
    p = motion.root_position[:, h]
    fig = _figure(4.8, 4.4)
    ax = fig.subplots()
    ax.plot(p[:, 0], p[:, 1], color="#1f77b4", lw=1.2, label="root")
    ax.plot(*p[0], "o", color="#2ca02c", label="start")
    ax.plot(*p[-1], "s", color="#111111", label="end")
    if seams.size:
        ax.plot(p[seams, 0], p[seams, 1], "x", color="#d62728", ms=5, label="seams")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"{'xyz'[h[0]]} (m)")
    ax.set_ylabel(f"{'xyz'[h[1]]} (m)")
    ax.legend(fontsize=7)
    return fig


def _angles(motion: Motion, source_index: np.ndarray, report: dict[str, Any],
            seams: np.ndarray):
    ang = joint_angles(motion)
    sk = motion.skeleton
    inner = [j for j in range(1, sk.n_joints) if sk.children(j)] or list(range(sk.n_joints))
    spread = ang[:, inner].std(axis=0)  # limb joints (fingers and toes jitter)
    order = [inner[i] for i in np.argsort(-spread, kind="stable")[:ANGLE_JOINTS]]
    t = np.arange(motion.n_frames) / motion.rate
    fig = _figure(9.0, 5.2)
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=[1, 2])
    rate = float(report.get("rate") or motion.rate)
    top.plot(np.arange(len(source_index)) / rate, source_index, color="#555555", lw=1.0)
    top.set_ylabel("input frame", fontsize=8)
    top.set_title("source frame copied (jumps are seams)", fontsize=9, loc="left")
    for j in order:
        bottom.plot(t, ang[:, j], lw=1.0, label=motion.skeleton.names[j])
    for k, s in enumerate(seams):
        for ax in (top, bottom):
            ax.axvline(s / motion.rate, color="#d62728", lw=0.6, alpha=0.6,
                       label="seam" if (k == 0 and ax is bottom) else None)
    bottom.set_ylabel("joint angle (deg)", fontsize=8)
    bottom.set_xlabel("time (s)")
    bottom.legend(fontsize=7, ncol=3, loc="upper right")
    return fig


@report_figures("synth")
def synth_figures(outputs: dict[str, Any], entry: ReportEntry) -> list[tuple[str, Any]]:
    """Root path, seam plot, strip and report table of a synthesis.

    Parameters
    ----------
    outputs : dict
        ``motion`` (:class:`Motion`), ``source_index``, ``report``.
    entry : ReportEntry

    Returns
    -------
    list of (str, Figure, image or str)
    """
    motion, report = outputs["motion"], outputs["report"]
    source_index = np.asarray(outputs["source_index"])
    seams = seam_output_frames(report, motion.n_frames)
    strip, frames = render_strip(motion, n_panels=STRIP_PANELS, view="side",
                                 highlight=[int(s) for s in seams])
    smoothing = report.get("smoothing") or {}
    rows = [["output frames", report.get("output_frames")],
            ["output rate (fps)", report.get("output_rate")],
            ["input frames", report.get("input_frames")],
            ["levels", report.get("levels")], ["method", report.get("method")],
            ["seams", report.get("n_seams")],
            ["constraints", len(report.get("constraints") or [])],
            ["constraint max angle (deg)", report.get("constraint_max_angle_deg")],
            ["jerk p99 (m/s³)", report.get("jerk_p99")],
            ["foot IK max (m)", report.get("foot_ik_max_m")]]
    rows += [[f"smoothing: {k}", v] for k, v in smoothing.items()
             if isinstance(v, (int, float, str, bool))]
    return [
        ("Root path from above (seams: red crosses)", _path(motion, seams)),
        ("Source frame and joint angles; seams marked", _angles(motion, source_index, report,
                                                                seams)),
        (f"Stick figures at frames {', '.join(map(str, frames))}"
         + (" (seam frames red)" if set(frames) & set(seams.tolist()) else ""), strip),
        ("Synthesis", html_table(["", "value"], rows, caption="Synthesis report")),
    ]


@report_figures("stickfigure")
def stickfigure_figures(outputs: dict[str, Any], entry: ReportEntry) -> list[tuple[str, Any]]:
    """The strip a ``stickfigure`` task rendered.

    Parameters
    ----------
    outputs : dict
        ``strip`` (:class:`~mocapflow.stages.texture.stickfigure.StickStrip`).
    entry : ReportEntry

    Returns
    -------
    list of (str, image)
    """
    strip = outputs["strip"]
    shown = ", ".join(map(str, strip.frames)) if strip.frames else "?"
    return [(f"Stick-figure strip (frames {shown})", strip.image)]
