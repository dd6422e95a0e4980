"""Figures of the skin stages on the ``mocapflow report`` page.

* ``clean``: trajectories of the markers with the most filled samples (filled and
  merged samples highlighted), the histogram of gap lengths, the paper's Table 1
  (trajectories, merges, holes) and the unmerged fragments by reason;
* ``render``, ``render_modes``, ``render_error``: a few stills of the video (and the
  error report of ``render_error``).

Figures are plain :class:`matplotlib.figure.Figure` objects (no pyplot state),
made only when a report is written; matplotlib is imported inside the functions.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mocapflow.pipeline.registry import report_figures
from mocapflow.pipeline.report import ReportEntry, html_table
from mocapflow.stages.motion.contacts import true_runs

__all__ = ["clean_figures", "gap_lengths", "render_figures", "still_indices"]

#: Markers whose trajectories are drawn.
TRAJECTORY_MARKERS = 3
#: Stills taken from a rendered video.
STILLS = 3
#: Status codes of the clean report (as :data:`mocapflow.stages.skin.clean.STATUS`).
MISSING, OBSERVED, MERGED, FILLED = -1, 0, 1, 2


def _figure(width: float, height: float):
    from matplotlib.figure import Figure  # noqa: PLC0415 (heavy)

    return Figure(figsize=(width, height), layout="constrained")


def gap_lengths(status: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lengths of the gaps of every marker and whether each was closed.

    Parameters
    ----------
    status : (F, M) int ndarray
        Clean status codes (-1 missing, 0 observed, 1 merged, 2 filled).

    Returns
    -------
    lengths : (G,) int ndarray
        Frames of each run of samples not observed in the capture.
    closed : (G,) bool ndarray
        The gap holds no sample left missing after cleaning.
    """
    lengths, closed = [], []
    for m in range(status.shape[1]):
        col = status[:, m]
        for a, b in true_runs(col != OBSERVED):
            lengths.append(b - a)
            closed.append(bool((col[a:b] != MISSING).all()))
    return np.asarray(lengths, dtype=np.int64), np.asarray(closed, dtype=bool)


def _trajectories(markers: Any, status: np.ndarray):
    P = markers.positions
    touched = ((status == FILLED) | (status == MERGED)).sum(axis=0)
    order = np.argsort(-touched, kind="stable")
    picks = [int(m) for m in order[:TRAJECTORY_MARKERS] if touched[m] > 0] or [int(order[0])]
    fig = _figure(9.0, 2.0 * len(picks) + 0.4)
    axes = fig.subplots(len(picks), 1, squeeze=False, sharex=True)[:, 0]
    t = (np.arange(P.shape[0]) + getattr(markers, "first_frame", 0)) / markers.rate
    colors = ("#1f77b4", "#2ca02c", "#9467bd")
    for ax, m in zip(axes, picks):
        st = status[:, m]
        Y = P[:, m] * 1000
        with np.errstate(all="ignore"):
            Y = Y - np.nanmean(Y, axis=0) if np.isfinite(Y).any() else Y
        for k, name in enumerate("xyz"):
            ax.plot(t, Y[:, k], color=colors[k], lw=0.9, label=name)
        for code, col, lab in ((FILLED, "#ff7f0e", "filled"), (MERGED, "#d62728", "merged")):
            sel = st == code
            for k in range(3):
                if sel.any():
                    ax.plot(t[sel], Y[sel, k], ".", ms=3, color=col,
                            label=lab if k == 0 else None)
        n_f, n_m = int((st == FILLED).sum()), int((st == MERGED).sum())
        ax.set_title(f"{markers.labels[m]}: {n_f} filled, {n_m} merged samples", fontsize=9,
                     loc="left")
        ax.set_ylabel("mm (about mean)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7, ncol=5, loc="upper right")
    axes[-1].set_xlabel("time (s)")
    return fig


def _histogram(status: np.ndarray, rate: float):
    lengths, closed = gap_lengths(status)
    fig = _figure(6.0, 3.4)
    ax = fig.subplots()
    if not lengths.size:
        ax.text(0.5, 0.5, "no gaps", ha="center", va="center", transform=ax.transAxes)
        return fig
    top = int(lengths.max())
    bins = (np.unique(np.geomspace(1, top + 1, 30).astype(int)) if top > 40
            else np.arange(1, top + 2))
    ax.hist([lengths[closed], lengths[~closed]], bins=bins, stacked=True,
            color=["#2ca02c", "#d62728"],
            label=[f"closed ({int(closed.sum())})", f"samples left ({int((~closed).sum())})"])
    if top > 40:
        ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(f"gap length (frames at {rate:g} fps)")
    ax.set_ylabel("gaps")
    ax.legend(fontsize=8)
    return fig


def _reason(text: str) -> str:
    head = str(text).split(":")[0]
    return head if len(head) <= 60 else head[:59] + "…"


@report_figures("clean")
def clean_figures(outputs: dict[str, Any], entry: ReportEntry) -> list[tuple[str, Any]]:
    """Trajectories, gap-length histogram, Table 1 and rejection reasons of a clean.

    Parameters
    ----------
    outputs : dict
        ``markers`` (:class:`~mocapflow.stages.motion.datatypes.Markers`), ``report``.
    entry : ReportEntry

    Returns
    -------
    list of (str, Figure or str)
    """
    markers, report = outputs["markers"], outputs["report"]
    status = np.asarray(report["status"])
    t1 = report["table1"]
    out: list[tuple[str, Any]] = [
        ("Trajectories of the markers with the most filled samples (filled: orange, "
         "merged: red)", _trajectories(markers, status)),
        ("Gap lengths (runs of samples not observed, per marker)",
         _histogram(status, markers.rate)),
        ("Table 1", html_table(
            ["markers", "trajectories before", "after", "runs before", "merged", "holes",
             "filled", "left unfilled"],
            [[t1["markers"], t1["fragments_before"], t1["fragments_after"], t1["runs_before"],
              t1["merged"], t1["holes"], t1["filled"], t1["left_unfilled"]]],
            caption="Table 1 (Park & Hodgins 2006): trajectories and holes before/after")),
    ]
    reasons: dict[str, int] = {}
    for r in report.get("rejections") or []:
        k = _reason(r.get("reason", "?"))
        reasons[k] = reasons.get(k, 0) + 1
    if reasons:
        rows = sorted(reasons.items(), key=lambda kv: -kv[1])[:8]
        out.append(("Unmerged fragments", html_table(["reason", "fragments"], rows,
                                                     caption="Unmerged fragments by reason")))
    return out


def still_indices(n_frames: int, n: int = STILLS) -> np.ndarray:
    """``n`` evenly spaced frame indices of a video of ``n_frames`` (fewer if shorter)."""
    return np.unique(np.linspace(0, n_frames - 1, min(n, n_frames)).round().astype(int))


@report_figures("render", "render_modes", "render_error")
def render_figures(outputs: dict[str, Any], entry: ReportEntry) -> list[tuple[str, Any]]:
    """Stills of a rendered video (and the error report of ``render_error``).

    Parameters
    ----------
    outputs : dict
        ``video`` (:class:`~mocapflow.stages.skin.render.Video`), maybe ``report``.
    entry : ReportEntry

    Returns
    -------
    list of (str, ndarray or str)
    """
    video = outputs["video"]
    src = video.attrs.get("source_frames") or list(range(video.n_frames))
    idx = still_indices(video.n_frames)
    shown = ", ".join(str(src[i]) for i in idx)
    row = np.concatenate([video.frames[i] for i in idx], axis=1)
    out: list[tuple[str, Any]] = [(f"Render stills (frames {shown})", row)]
    rep = outputs.get("report")
    if entry.stage == "render_error" and isinstance(rep, dict):
        out.append(("Error", html_table(
            ["mean mm", "p95 mm", "max mm", "frames evaluated"],
            [[rep.get("mean_mm"), rep.get("p95_mm"), rep.get("max_mm"),
              rep.get("frames_evaluated")]], caption="Distance to the ground truth")))
    return out
