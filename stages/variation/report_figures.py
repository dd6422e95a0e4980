"""Figures of the variation stages on the ``mocapflow report`` page.

* ``sample``: Fig. 6-style overlays of the variants on the training clips (the
  model's, read from the ``learn`` entry the task was wired to): the DOFs that
  vary most against time, and the first two principal components of the inputs'
  standardised DOFs (PC1 against PC2), each with a legend;
* ``ik``: the clean-up per variant as a table (constrained frames, errors, misses);
* ``variation_plots``: the figures the stage drew.

Figures are plain :class:`matplotlib.figure.Figure` objects (no pyplot state),
made only when a report is written; matplotlib is imported inside the functions.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mocapflow.pipeline.registry import report_figures
from mocapflow.pipeline.report import ReportEntry, html_table
from mocapflow.stages.variation.clips import Clips

__all__ = ["common_dofs", "ik_figures", "plots_figures", "sample_figures"]

#: DOFs drawn against time.
TIME_DOFS = 3


def _figure(width: float, height: float):
    from matplotlib.figure import Figure  # noqa: PLC0415 (heavy)

    return Figure(figsize=(width, height), layout="constrained")


def common_dofs(inputs: Clips, variants: Clips) -> tuple[list[str], list[np.ndarray],
                                                         list[np.ndarray]]:
    """The varying DOFs both clip sets have, and their trajectories in that order.

    Returns
    -------
    names : list of str
    xin, xout : list of (T, D) float ndarray
        Inputs' and variants' trajectories restricted to ``names``.
    """
    names = [n for n in inputs.labels if n in set(variants.labels)]
    ci = [inputs.labels.index(n) for n in names]
    co = [variants.labels.index(n) for n in names]
    return (names, [t[:, ci] for t in inputs.trajectories],
            [t[:, co] for t in variants.trajectories])


def _colors(n: int) -> list[Any]:
    import matplotlib  # noqa: PLC0415 (heavy)

    cmap = matplotlib.colormaps["viridis"]
    return [cmap(x) for x in np.linspace(0.0, 0.9, max(n, 1))]


def _overlay(ax: Any, xin: list[np.ndarray], xout: list[np.ndarray], f_in, f_out) -> None:
    """Inputs in grey, variants in colour, one legend entry each kind."""
    for k, x in enumerate(xin):
        ax.plot(*f_in(x), color="0.6", lw=1.6, label=f"inputs ({len(xin)})" if k == 0 else None)
    for k, (x, c) in enumerate(zip(xout, _colors(len(xout)))):
        ax.plot(*f_out(x), color=c, lw=0.9,
                label=f"variants ({len(xout)})" if k == 0 else None)


def _dof_time(inputs: Clips, variants: Clips, names: list[str], xin, xout):
    spread = np.concatenate(xin, axis=0).std(axis=0)
    rot = [i for i in np.argsort(-spread, kind="stable") if names[i].endswith("rotation")]
    rest = [i for i in np.argsort(-spread, kind="stable") if i not in rot]
    pick = (rot + rest)[:TIME_DOFS]
    fig = _figure(9.0, 2.1 * len(pick) + 0.4)
    axes = fig.subplots(len(pick), 1, squeeze=False, sharex=True)[:, 0]
    for ax, d in zip(axes, pick):
        _overlay(ax, xin, xout, lambda x, d=d: (np.arange(len(x)) / inputs.rate, x[:, d]),
                 lambda x, d=d: (np.arange(len(x)) / variants.rate, x[:, d]))
        ax.set_ylabel(names[d], fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].legend(fontsize=7, loc="upper right")
    axes[-1].set_xlabel("time (s)")
    return fig


def _pca(xin, xout):
    X = np.concatenate(xin, axis=0)
    mean, std = X.mean(axis=0), X.std(axis=0)
    std = np.where(std > 0, std, 1.0)
    _, sv, vt = np.linalg.svd((X - mean) / std, full_matrices=False)
    P = vt[:2].T

    def proj(x: np.ndarray) -> np.ndarray:
        return ((x - mean) / std) @ P

    fig = _figure(5.2, 4.6)
    ax = fig.subplots()
    _overlay(ax, xin, xout, lambda x: proj(x).T, lambda x: proj(x).T)
    energy = sv[:2] ** 2 / max(float(np.sum(sv**2)), 1e-300)
    ax.set_xlabel(f"PC1 ({100 * energy[0]:.0f} %)")
    ax.set_ylabel(f"PC2 ({100 * energy[1]:.0f} %)" if len(energy) > 1 else "PC2")
    ax.legend(fontsize=7)
    return fig


@report_figures("sample", "sample_noise")
def sample_figures(outputs: dict[str, Any], entry: ReportEntry) -> list[tuple[str, Any]]:
    """Fig. 6-style overlays of the variants on the model's training clips.

    Parameters
    ----------
    outputs : dict
        ``variants`` (:class:`Clips`).
    entry : ReportEntry
        Its ``model`` input (the ``learn`` entry) gives the training clips.

    Returns
    -------
    list of (str, Figure)
    """
    variants = outputs["variants"]
    inputs = entry.upstream("model")["model"].clips
    names, xin, xout = common_dofs(inputs, variants)
    if not names:
        raise ValueError("the variants share no DOF with the model's clips")
    out: list[tuple[str, Any]] = [
        ("DOFs against time: inputs grey, variants in colour (Lau et al. Fig. 6)",
         _dof_time(inputs, variants, names, xin, xout))]
    if len(names) >= 2:
        out.append(("First principal components of the inputs' standardised DOFs",
                    _pca(xin, xout)))
    return out


@report_figures("ik")
def ik_figures(outputs: dict[str, Any], entry: ReportEntry) -> list[tuple[str, Any]]:
    """The foot clean-up per variant as a table.

    Parameters
    ----------
    outputs : dict
        ``variants``, ``report``.
    entry : ReportEntry

    Returns
    -------
    list of (str, str)
    """
    rep = outputs["report"]
    if "skipped" in rep:
        return [("IK", html_table(["skipped"], [[rep["skipped"]]]))]
    rows = []
    for c in rep.get("clips") or []:
        reached = [v for v in (c.get("max_error_reached") or {}).values()]
        rows.append([c.get("name"), c.get("output_frames"),
                     sum((c.get("constrained_frames") or {}).values()),
                     1000.0 * max(reached) if reached else None,
                     len(c.get("unreachable") or [])])
    jerk = rep.get("jerk_p99") or {}
    return [("IK clean-up", html_table(
        ["variant", "frames", "constrained frames", "max error reached (mm)", "unreached"],
        rows, caption=f"Foot clean-up (jerk p99 sampled {jerk.get('sampled', 0):.3g}, "
                      f"cleaned {jerk.get('cleaned', 0):.3g} m/s³)"))]


@report_figures("variation_plots")
def plots_figures(outputs: dict[str, Any], entry: ReportEntry) -> list[tuple[str, Any]]:
    """The images the ``variation_plots`` task drew.

    Parameters
    ----------
    outputs : dict
        ``figures`` (:class:`~mocapflow.stages.variation.plots.Figures`).
    entry : ReportEntry

    Returns
    -------
    list of (str, image)
    """
    return [(name, img) for name, img in outputs["figures"].images.items()]
