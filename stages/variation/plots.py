"""Plots of inputs and variants like Lau, Bar-Joseph & Kuffner 2009 (Fig. 1 right, Fig. 6).

* ``strokes``: the input pen strokes and the generated ones (Fig. 1, right);
* ``dof_time``: a few DOFs against time, inputs in grey, variants in colour
  (every DOF / PCA figure has a legend: inputs vs variants, with their counts);
* ``dof_dof``: one DOF against another (phase portrait);
* ``pca``: inputs and variants projected on the first principal components of
  the inputs (standardised DOFs): PC1 and PC2 against time, PC1 against PC2
  (Fig. 6).

Figures are rendered with matplotlib's Agg backend (imported inside the
functions) to RGBA arrays held in a :class:`Figures` output, which
``mocapflow export`` writes as PNG files.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.pipeline import Context, stage
from mocapflow.pipeline.codecs import Encoded, codec, component_coords, exporter
from mocapflow.stages.variation.clips import Clips, flatten_clips

__all__ = [
    "Figures",
    "figure_dof_dof",
    "figure_dof_time",
    "figure_pca",
    "figure_strokes",
    "variation_plots",
]


@dataclass(eq=False)
class Figures:
    """Named RGBA images.

    Parameters
    ----------
    images : dict of str to (H, W, 4) uint8 ndarray
    attrs : dict
    """

    images: dict[str, np.ndarray]
    attrs: dict[str, Any] = field(default_factory=dict)

    def __repr__(self) -> str:
        """One line: image count, the first few names and sizes (never the pixels)."""
        shown = ", ".join(f"{k[:24]!r} {np.shape(v)[1]}×{np.shape(v)[0]}"
                          for k, v in list(self.images.items())[:3])
        more = ", …" if len(self.images) > 3 else ""
        return f"Figures({len(self.images)} images{': ' + shown + more if shown else ''})"


def _encode_figures(f: Figures) -> Encoded:
    # per-figure y / x dims: the figures differ in size
    arrays = {k: (np.asarray(v, dtype=np.uint8), (f"{k}_y", f"{k}_x", "rgba"))
              for k, v in f.images.items()}
    attrs = {"names": list(f.images), "attrs": f.attrs}
    return Encoded("figures", arrays, attrs, component_coords("rgba"))


def _decode_figures(e: Encoded) -> Figures:
    return Figures({k: e.arrays[k][0] for k in e.attrs["names"]}, e.attrs.get("attrs", {}))


codec("figures", encode=_encode_figures, decode=_decode_figures)(Figures)


@exporter("figures")
def export_figures(obj: Figures, directory: Path, stem: str) -> list[Path]:
    """Write each figure as ``<stem>_<name>.png``."""
    import matplotlib.image as mpimg  # noqa: PLC0415 (heavy)

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    out = []
    for name, img in obj.images.items():
        p = directory / f"{stem}_{name}.png"
        mpimg.imsave(p, img)
        out.append(p)
    return out


def _render(fig) -> np.ndarray:
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba()).copy()
    import matplotlib.pyplot as plt  # noqa: PLC0415 (heavy)

    plt.close(fig)
    return img


def _figure(nrows: int, ncols: int, size: tuple[float, float]):
    import matplotlib  # noqa: PLC0415 (heavy)

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt  # noqa: PLC0415 (heavy)

    return plt.subplots(nrows, ncols, figsize=size, dpi=100, squeeze=False)


def _full(clips: Clips, names: list[str]) -> list[np.ndarray]:
    col = [clips.dof_names.index(n) for n in names]
    return [clips.full(c)[:, col] for c in range(clips.n_clips)]


def _colors(n: int):
    import matplotlib  # noqa: PLC0415 (heavy)

    cmap = matplotlib.colormaps["viridis"]
    return [cmap(x) for x in np.linspace(0.0, 0.9, max(n, 1))]


def _legend(a, n_inputs: int, n_variants: int) -> None:
    """Legend on axes ``a``: grey inputs vs coloured variants, with their counts."""
    from matplotlib.lines import Line2D  # noqa: PLC0415 (heavy)

    mid = _colors(3)[1]
    handles = [Line2D([], [], color="0.6", lw=1.5, label=f"inputs ({n_inputs})"),
               Line2D([], [], color=mid, lw=0.9, label=f"variants ({n_variants})")]
    a.legend(handles=handles, loc="best", fontsize=7, framealpha=0.8)


def figure_strokes(inputs: Clips, variants: Clips) -> np.ndarray:
    """Fig. 1 (right): input strokes (left panel) and generated strokes (right panel).

    Parameters
    ----------
    inputs, variants : Clips
        ``kind == "strokes"``.

    Returns
    -------
    (H, W, 4) uint8 ndarray
    """
    fig, ax = _figure(1, 2, (9, 4.5))
    for a, clips, title in ((ax[0, 0], inputs, "inputs"), (ax[0, 1], variants, "variants")):
        cols = _colors(clips.n_clips) if clips is variants else ["k"] * clips.n_clips
        for xy, c in zip(_full(clips, ["x", "y"]), cols):
            a.plot(xy[:, 0], xy[:, 1], color=c, lw=1.2)
        a.set_aspect("equal")
        a.set_title(f"{title} ({clips.n_clips})")
        a.set_xticks([])
        a.set_yticks([])
    return _render(fig)


def _pick_dofs(inputs: Clips, n: int) -> list[str]:
    """The ``n`` varying DOFs with the largest spread (angles first)."""
    X = np.concatenate(inputs.trajectories, axis=0)
    std = X.std(axis=0)
    order = np.argsort(-std)
    labels = inputs.labels
    rot = [labels[i] for i in order if labels[i].endswith("rotation")]
    rest = [labels[i] for i in order if not labels[i].endswith("rotation")]
    return (rot + rest)[:n]


def figure_dof_time(inputs: Clips, variants: Clips, dofs: list[str] | None = None) -> np.ndarray:
    """DOFs against time: inputs grey, variants in colour.

    Parameters
    ----------
    inputs, variants : Clips
    dofs : list of str, optional
        DOF names (default the 3 with the largest spread).

    Returns
    -------
    (H, W, 4) uint8 ndarray
    """
    dofs = dofs or _pick_dofs(inputs, 3)
    fig, ax = _figure(len(dofs), 1, (9, 2.3 * len(dofs)))
    xin, xout = _full(inputs, dofs), _full(variants, dofs)
    cols = _colors(len(xout))
    for d, name in enumerate(dofs):
        a = ax[d, 0]
        for x in xin:
            a.plot(np.arange(len(x)) / inputs.rate, x[:, d], color="0.6", lw=1.5)
        for x, c in zip(xout, cols):
            a.plot(np.arange(len(x)) / variants.rate, x[:, d], color=c, lw=0.9)
        a.set_ylabel(name, fontsize=8)
    _legend(ax[0, 0], len(xin), len(xout))
    ax[-1, 0].set_xlabel("time (s)")
    return _render(fig)


def figure_dof_dof(
    inputs: Clips, variants: Clips, pair: tuple[str, str] | None = None
) -> np.ndarray:
    """One DOF against another (phase portrait), inputs grey, variants in colour.

    Parameters
    ----------
    inputs, variants : Clips
    pair : (str, str), optional
        DOF names (default the two with the largest spread).

    Returns
    -------
    (H, W, 4) uint8 ndarray
    """
    pair = tuple(pair or _pick_dofs(inputs, 2))
    fig, ax = _figure(1, 1, (5.5, 5))
    a = ax[0, 0]
    for x in _full(inputs, list(pair)):
        a.plot(x[:, 0], x[:, 1], color="0.6", lw=1.5)
    for x, c in zip(_full(variants, list(pair)), _colors(variants.n_clips)):
        a.plot(x[:, 0], x[:, 1], color=c, lw=0.9)
    a.set_xlabel(pair[0], fontsize=8)
    a.set_ylabel(pair[1], fontsize=8)
    _legend(a, inputs.n_clips, variants.n_clips)
    return _render(fig)


def figure_pca(inputs: Clips, variants: Clips) -> np.ndarray:
    """Fig. 6: PC1 and PC2 of the inputs' standardised DOFs against time, and PC1 vs PC2.

    Parameters
    ----------
    inputs, variants : Clips
        Same DOF layout.

    Returns
    -------
    (H, W, 4) uint8 ndarray
    """
    labels = inputs.labels
    X = np.concatenate(_full(inputs, labels), axis=0)
    mean, std = X.mean(axis=0), X.std(axis=0)
    std = np.where(std > 0, std, 1.0)
    _, sv, Vt = np.linalg.svd((X - mean) / std, full_matrices=False)
    energy = np.cumsum(sv**2) / np.sum(sv**2)
    P = Vt[:2].T

    def proj(clips: Clips) -> list[np.ndarray]:
        return [((x - mean) / std) @ P for x in _full(clips, labels)]

    pin, pout = proj(inputs), proj(variants)
    cols = _colors(len(pout))
    fig, ax = _figure(1, 3, (14, 4))
    for k in range(2):
        a = ax[0, k]
        for y in pin:
            a.plot(np.arange(len(y)) / inputs.rate, y[:, k], color="0.6", lw=1.5)
        for y, c in zip(pout, cols):
            a.plot(np.arange(len(y)) / variants.rate, y[:, k], color=c, lw=0.9)
        a.set_xlabel("time (s)")
        a.set_ylabel(f"PC{k + 1}")
    a = ax[0, 2]
    for y in pin:
        a.plot(y[:, 0], y[:, 1], color="0.6", lw=1.5)
    for y, c in zip(pout, cols):
        a.plot(y[:, 0], y[:, 1], color=c, lw=0.9)
    a.set_xlabel("PC1")
    a.set_ylabel("PC2")
    _legend(a, len(pin), len(pout))
    k99 = int(np.searchsorted(energy, 0.99) + 1)
    fig.suptitle(f"{len(labels)} DOFs; 99 % energy in {k99} principal components", fontsize=9)
    return _render(fig)


def _concat(value: Any) -> Clips:
    """Variants of several tasks as one Clips (same layout: trajectories concatenated)."""
    if isinstance(value, Clips):
        return value
    items = [_concat(v) for v in value]
    first = items[0]
    return first.replace(
        trajectories=[t for c in items for t in c.trajectories],
        origins=np.concatenate([c.origins for c in items]),
        names=[n for c in items for n in c.names],
    )


@stage("variation_plots", outputs=("figures",))
def variation_plots(
    inputs: Any, variants: Any, *, dofs: list[str] | None = None, ctx: Context
) -> dict:
    """Fig. 1 / Fig. 6-style plots of input clips and generated variants.

    Parameters
    ----------
    inputs : Clips or list of Clips
        Training clips.
    variants : Clips or list of Clips
        Variants (a gather over seeds gives a list; they are concatenated).
    dofs : list of str, optional
        DOF names for the DOF plots.
    ctx : Context

    Returns
    -------
    dict
        ``figures``: :class:`Figures` (exported as PNG): ``strokes`` for pen
        strokes; ``dof_time``, ``dof_dof`` and (with at least 2 DOFs) ``pca``
        for every kind.
    """
    inputs, variants = flatten_clips(inputs), _concat(variants)
    images = {}
    if inputs.kind == "strokes":
        images["strokes"] = figure_strokes(inputs, variants)
    images["dof_time"] = figure_dof_time(inputs, variants, dofs)
    pair = tuple(dofs[:2]) if dofs and len(dofs) >= 2 else None
    images["dof_dof"] = figure_dof_dof(inputs, variants, pair)
    if inputs.n_dofs >= 2:
        images["pca"] = figure_pca(inputs, variants)
    figures = Figures(images, {"inputs": inputs.n_clips, "variants": variants.n_clips})
    return {"figures": figures}
