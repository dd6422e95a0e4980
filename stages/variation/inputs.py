"""The ``clips`` stage: ingested parts → the similar training clips (Lau et al. 2009, §4, §9).

Each take of a cyclic motion is cut into cycles
(:mod:`~mocapflow.stages.variation.cycles`), the cycles of several takes are
separate examples named by take (``cut: none``: each part one example);
each pen-stroke example is one clip (:mod:`~mocapflow.stages.variation.clips`).
Optionally only the ``max_clips`` most typical clips are kept (smallest RMS
distance to the elementwise median clip, all resampled to 32 frames; taken in
turn from each take so that every take contributes) and clips
unlikely under the others are removed (Lau §9,
:mod:`~mocapflow.stages.variation.similar`).
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context, stage
from mocapflow.stages.motion.datatypes import Motion, Strokes
from mocapflow.stages.variation.clips import (
    ClipError,
    Clips,
    clips_from_motions,
    clips_from_strokes,
    merge_clips,
    source_name,
)
from mocapflow.stages.variation.cycles import cut_cycles
from mocapflow.stages.variation.similar import select_similar

__all__ = ["clips"]


def _motion_up(motions: list[Motion]) -> str:
    """The shared up axis (``"y"`` / ``"z"``) of the motions' ``attrs["up"]`` (default y)."""
    ups = {str(m.attrs.get("up", "+y")).lstrip("+") for m in motions}
    if len(ups) > 1 or not ups <= {"y", "z"}:
        raise ClipError(f"clips: the motions' up axes {sorted(ups)} are not one of y, z; "
                        "set ingest.up / clips.up")
    return ups.pop()


@stage("clips", outputs=("clips", "report"))
def clips(
    sources: Any,
    *,
    cut: Literal["auto", "feet", "period", "none"] = "auto",
    cyclic: bool | None = None,
    root: Literal["heading", "absolute"] = "heading",
    up: Literal["auto", "y", "z"] = "auto",
    outlier: float = 2.5,
    min_cycles: int = 2,
    letter: str | None = None,
    max_clips: int | None = None,
    similar_threshold: float | None = None,
    similar_structure: Literal["learned", "self"] = "learned",
    ctx: Context,
) -> dict:
    """Make the DOF clips the ``learn`` stage trains on, from ingested parts.

    With ``cut`` not ``"none"`` every motion part (a take) is cut into cycles
    (:func:`~mocapflow.stages.variation.cycles.cut_cycles`); the cycles of all
    takes are the examples, named ``<take file>[a:b]``.  A single take with
    fewer than ``min_cycles`` cycles is used whole; one of several takes is
    then skipped (warned).  With ``cut: none`` each part is one example.  Each
    pen-stroke example is one clip.

    Parameters
    ----------
    sources : Motion, Strokes, Clips or list of them
        The ingested parts (a gather input is a list ordered by part).
    cut : {"auto", "feet", "period", "none"}
        Cycle cutting of every take (``auto``: heel strikes, else period;
        ``none``: each part whole).
    cyclic : bool, optional
        Mark the clips as cycles (default: true exactly when a take was cut).
    root : {"heading", "absolute"}
        Root DOFs (see :mod:`~mocapflow.stages.variation.dofs`).
    up : {"auto", "y", "z"}
        World up axis; ``auto``: the motions' ``attrs["up"]`` (set by ``ingest_bvh``,
        whose default is BVH's Y up), else y.
    outlier : float
        Shape-outlier factor for dropping cycles.
    min_cycles : int
        Fewer cycles than this: the take is used whole, with a warning.
    letter : str, optional
        Keep only strokes whose ``attrs["letter"]`` equals it.
    max_clips : int, optional
        Keep at most this many clips, the most typical ones (smallest
        distance to the median clip, all resampled to 32 frames), in order;
        with several takes chosen in turn per take (balanced: counts per take
        differ by at most one).
    similar_threshold : float, optional
        Run :func:`~mocapflow.stages.variation.similar.select_similar` (Lau §9)
        with this per-frame log-likelihood threshold (from
        :func:`~mocapflow.stages.variation.similar.likelihood_threshold` on a
        trusted set).  Default ``None``: no selection.
    similar_structure : {"learned", "self"}
        Transition structure of the selection's networks: searched on each
        training set (default, the paper) or self parents only (faster).
    ctx : Context

    Returns
    -------
    dict
        ``clips`` (:class:`Clips`) and ``report`` (JSON: clip names and
        lengths, cut method and frames, dropped constant DOFs, removed clips).
    """
    items = _flatten_sources(sources, [])
    if not items:
        raise ClipError("clips: no input part")
    report: dict[str, Any] = {}
    if all(isinstance(x, Clips) for x in items):
        out = merge_clips(items)
        groups = np.arange(out.n_clips)
    elif all(isinstance(x, Strokes) for x in items):
        out = _stroke_clips(items, letter=letter, cyclic=cyclic, ctx=ctx)
        groups = np.arange(out.n_clips)
    elif all(isinstance(x, Motion) for x in items):
        up = _motion_up(items) if up == "auto" else up
        if cut != "none":
            out, groups, report["cut"] = _takes_cycles(
                items, cut=cut, cyclic=cyclic, root=root, up=up, outlier=outlier,
                min_cycles=min_cycles, ctx=ctx,
            )
        else:
            out = clips_from_motions(items, root=root, up=up, cyclic=bool(cyclic))
            groups = np.arange(out.n_clips)
    else:
        kinds = {type(x).__name__ for x in items}
        raise ClipError(f"clips: mixed or unsupported inputs {sorted(kinds)}")
    if max_clips is not None and out.n_clips > max_clips:
        out, report["dropped_atypical"] = _most_typical(out, max_clips, groups)
    if similar_threshold is not None:
        out, report["removed"] = _similar_only(out, similar_threshold, similar_structure, ctx)
    return {"clips": out, "report": _summary(out, report, ctx)}


def _flatten_sources(value: Any, out: list) -> list:
    """Append the parts in ``value`` (nested lists, ``{"strokes": ...}`` sets) to ``out``."""
    if isinstance(value, (list, tuple)):
        for v in value:
            _flatten_sources(v, out)
    elif isinstance(value, dict) and "strokes" in value:
        _flatten_sources(value["strokes"], out)
    elif value is not None:
        out.append(value)
    return out


def _stroke_clips(
    strokes: list[Strokes], *, letter: str | None, cyclic: bool | None, ctx: Context
) -> Clips:
    """One clip per pen-stroke example (of ``letter`` only, when given)."""
    if letter is not None:
        strokes = [s for s in strokes if s.attrs.get("letter") == letter]
        if not strokes:
            raise ClipError(f"clips: no strokes of letter {letter!r}")
    out = clips_from_strokes(strokes)
    if cyclic:
        out = out.replace(cyclic=True)
    if out.attrs.get("pen_up_joined"):
        ctx.warn(f"pen-up breaks joined in {out.attrs['pen_up_joined']}")
    return out


def _take_cycles(
    take: Motion,
    *,
    cut: Literal["auto", "feet", "period"],
    cyclic: bool | None,
    root: Literal["heading", "absolute"],
    up: str,
    outlier: float,
    min_cycles: int,
    ctx: Context,
    allow_whole: bool = True,
) -> tuple[Clips | None, dict[str, Any]]:
    """The kept cycles of one take as clips, or the whole take when too few are found.

    With ``allow_whole`` false (several takes) a take with too few cycles is
    skipped (``None``) instead, so that every clip is one cycle.

    Returns
    -------
    clips : Clips
    cut_report : dict
        From :func:`~mocapflow.stages.variation.cycles.cut_cycles`.
    """
    cycles, rep = cut_cycles(take, method=cut, up=up, outlier=outlier)
    if len(cycles) < min_cycles:
        if not allow_whole:
            ctx.warn(f"{source_name(take, 'take')}: found {len(cycles)} cycle(s) "
                     f"(< {min_cycles}); take skipped")
            return None, rep
        ctx.warn(
            f"{source_name(take, 'take')}: found {len(cycles)} cycle(s) (< {min_cycles}); "
            "using the whole take as one clip"
        )
        return clips_from_motions([take], root=root, up=up, cyclic=bool(cyclic)), rep
    bounds = sorted({x for c in cycles for x in c})
    out = clips_from_motions(
        [take],
        cuts=[np.array(bounds)],
        root=root,
        up=up,
        cyclic=True if cyclic is None else cyclic,
    )
    keep = [i for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])) if (a, b) in set(cycles)]
    return out.subset(keep), rep


def _takes_cycles(
    takes: list[Motion], *, cyclic: bool | None, ctx: Context, **kw: Any
) -> tuple[Clips, np.ndarray, dict[str, Any]]:
    """The cycles of every take (:func:`_take_cycles`), merged, with each clip's take index.

    Returns
    -------
    clips : Clips
        Named ``<take file>[a:b]`` (frames of that take).
    groups : (C,) int ndarray
        Index of the take each clip was cut from.
    cut_report : dict
        One take: :func:`~mocapflow.stages.variation.cycles.cut_cycles`'s
        report; several: ``{"takes": [{"take", "n_cycles", **report}, ...]}``.
    """
    if len(takes) == 1:
        out, rep = _take_cycles(takes[0], cyclic=cyclic, ctx=ctx, **kw)
        return out, np.zeros(out.n_clips, dtype=int), rep
    parts, groups, reps = [], [], []
    for g, take in enumerate(takes):
        out, rep = _take_cycles(take, cyclic=cyclic, ctx=ctx, allow_whole=False, **kw)
        n = 0 if out is None else out.n_clips
        reps.append({"take": source_name(take, f"take{g}"), "n_cycles": n, **rep})
        if out is not None:
            parts.append(out)
            groups += [g] * n
    if not parts:
        raise ClipError(f"clips: no take has {kw['min_cycles']} cycles; use cut: none "
                        "to keep each part whole")
    return merge_clips(parts), np.asarray(groups), {"takes": reps}


def _typicality(trajs: list[np.ndarray], samples: int = 32) -> np.ndarray:
    """RMS distance of each clip (standardised, resampled) to the elementwise median clip."""
    X = np.concatenate(trajs, axis=0)
    mean, std = X.mean(axis=0), X.std(axis=0)
    std = np.where(std > 0, std, 1.0)
    grid = np.linspace(0.0, 1.0, samples)
    shapes = []
    for t in trajs:
        z = (t - mean) / std
        tt = np.linspace(0.0, 1.0, len(z))
        shapes.append(np.stack([np.interp(grid, tt, z[:, d]) for d in range(z.shape[1])], 1))
    shapes = np.stack(shapes)
    med = np.median(shapes, axis=0)
    return np.sqrt(((shapes - med) ** 2).mean(axis=(1, 2)))


def _most_typical(
    clips: Clips, max_clips: int, groups: np.ndarray | None = None
) -> tuple[Clips, list[str]]:
    """The ``max_clips`` most typical clips, balanced over takes, in order, and the dropped names.

    Typicality is :func:`_typicality` against the median of all clips.  The
    takes (``groups``, one index per clip; default: every clip its own)
    contribute in turn, each its most typical remaining clip, the take with
    the most typical clip first, so the kept counts of two takes differ by at
    most one (unless a take runs out of clips).
    """
    if max_clips < 1:
        raise ClipError(f"clips.max_clips must be at least 1, got {max_clips}")
    dist = _typicality(clips.trajectories)
    groups = np.arange(clips.n_clips) if groups is None else np.asarray(groups)
    queues = [list(np.flatnonzero(groups == g)[np.argsort(dist[groups == g], kind="stable")])
              for g in np.unique(groups)]
    # round r takes the r-th most typical clip of every take, most typical first
    ranked = sorted(((r, dist[i], i) for q in queues for r, i in enumerate(q)))
    keep = np.sort([i for _, _, i in ranked[:max_clips]])
    dropped = [clips.names[i] for i in range(clips.n_clips) if i not in keep]
    return clips.subset(keep), dropped


def _similar_only(
    clips: Clips, threshold: float, structure: Literal["learned", "self"], ctx: Context
) -> tuple[Clips, list[dict[str, Any]]]:
    """Lau §9 selection (:func:`~mocapflow.stages.variation.similar.select_similar`), warned."""
    out, removed = select_similar(clips, float(threshold), structure=structure)
    for r in removed:
        ctx.warn(f"clip {r['name']} removed: log-likelihood {r['log_likelihood']:.3g} "
                 f"< threshold {threshold:.3g}")
    return out, removed


def _summary(clips: Clips, report: dict[str, Any], ctx: Context) -> dict[str, Any]:
    """``report`` completed with the clips' sizes (warns on very uneven lengths)."""
    lengths = clips.lengths
    if clips.n_clips > 1 and lengths.max() > 2 * lengths.min():
        ctx.warn(
            f"clip lengths differ a lot ({lengths.min()}–{lengths.max()} frames); "
            "the prior network draws more start frames from the long ones"
        )
    if clips.attrs.get("constant_dofs"):
        report["constant_dofs"] = clips.attrs["constant_dofs"]
    report.update(
        {
            "n_clips": clips.n_clips,
            "names": clips.names,
            "lengths": lengths.tolist(),
            "n_dofs": clips.n_dofs,
            "cyclic": clips.cyclic,
            "kind": clips.kind,
        }
    )
    return report
