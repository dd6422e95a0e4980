"""Learning the dynamic Bayesian network of motion variation (Lau, Bar-Joseph & Kuffner 2009, §5).

The model of ``D`` DOFs has two parts.

Prior network
    A Bayesian network over the ``2D`` nodes ``X[0]`` (nodes ``0..D-1``) and
    ``X[1]`` (nodes ``D..2D-1``).  Its training instances are the pairs
    ``(x[t], x[t+1])`` of the first ``w`` frames of every clip (``w`` grows
    when the clips are few: ``prior_window``).
Transition network
    ``X[t], X[t+1] → X[t+2]``, second-order Markov.  Node ``i`` of ``X[t+2]``
    always has the self parents ``X_i[t]`` and ``X_i[t+1]``; further parents
    are searched among the ``2D`` nodes of frames ``t`` and ``t+1``.  The
    regression target is the delta ``X_i[t+2] − X_i[t+1]``; the self parents
    enter the distance as position ``X_i[t+1]`` and velocity
    ``X_i[t+1] − X_i[t]`` (scaled by ``velocity_weight``).

Where each step lives
    :mod:`~mocapflow.stages.variation.training`: standardisation and the
    training instances of both networks.
    :mod:`~mocapflow.stages.variation.kernel`: the conditional densities
    (Lau Eq. 5–6, non-parametric kernel regression on the ``k`` nearest
    instances) and the per-node bandwidth ``h = kernel_width · m`` (``m`` the median
    distance to the k-th neighbour; with ``kernel_width=None``, the default, the
    factor is chosen per node and parent set by held-out likelihood, which keeps
    the predictive variance calibrated: a fixed width makes the scores reward
    irrelevant parents that merely widen the kernel).
    :mod:`~mocapflow.stages.variation.scores`: the cross-validated (leave one
    clip out) log-likelihood of a node given a parent set, one-step or
    propagated.
    :mod:`~mocapflow.stages.variation.search`: the greedy structure searches
    (prior: add / delete / reverse with restarts; transition: add / delete per
    node, in parallel through ``ctx.map``).
    :mod:`~mocapflow.stages.variation.model`: :class:`VariationModel` and its codec.
    This module: the ``learn`` stage, which composes them.

Additions to the paper (each can be switched off)
    ``half_life`` (default 0.5 s): the transition mean keeps only a fraction
    ``λ`` per frame of the state's offset from its neighbours
    (:func:`~mocapflow.stages.variation.training.retention_of`); pure delta
    regression (``None``) lets a state that has left the data run away under
    sampling noise.  ``calibrate_retention`` (default on; off: the ``half_life``
    retention for every DOF): each DOF's retention
    is lowered from that of ``half_life`` to the one at which the offset the
    sampling noise accumulates has the held-out clips' spread about their
    neighbours (:func:`~mocapflow.stages.variation.scores.transition_node_retention`),
    computed once the structure is found (the search scores with the
    ``half_life`` retention): near-identical examples (the demo's procedural
    walk, 6 cycles of 5 % variation) otherwise give variants whose knee runs
    1.2 rad past the inputs' range, once noise carries it past a sharp turn and
    neighbours of other phases with the same velocity keep it going.
    ``phase`` (default for non-cyclic clips): a normalised-time DOF
    (:func:`~mocapflow.stages.variation.training.with_phase`) that
    disambiguates look-alike states and ends variants.
    ``time_warp`` (default on, cyclic clips): the cycles' time warps onto a
    reference cycle (:func:`~mocapflow.stages.variation.warp.time_warps`),
    from which the ``sample`` stage draws one warp per variant.
    ``kernel_width=None``: per-node bandwidth by held-out likelihood.
    ``horizon`` (default ``None``, the paper's unbounded propagation): the
    propagated transition score re-anchors to the held-out clip's true
    frames every ``horizon`` seconds, so a few runaway re-synthesised frames
    cannot dominate the score (:mod:`~mocapflow.stages.variation.scores`).
    ``candidates``: sparse candidate parents (Friedman et al. 1999).

Similar-input selection (Lau §9) scores clips with the transition network:
:mod:`~mocapflow.stages.variation.similar`.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context, stage
from mocapflow.stages.variation.clips import ClipError, Clips, flatten_clips
from mocapflow.stages.variation.model import VariationModel
from mocapflow.stages.variation.scores import transition_node_retention
from mocapflow.stages.variation.search import search_prior, search_transition
from mocapflow.stages.variation.training import (
    CYCLE_PHASE,
    LearnError,
    PriorData,
    TransitionData,
    prior_data,
    prior_window_of,
    retention_of,
    standardization,
    transition_data,
    with_phase,
)
from mocapflow.stages.variation.warp import time_warps

__all__ = ["LearnError", "learn"]


@stage("learn", outputs=("model", "report"))
def learn(
    clips: Any,
    *,
    k: int = 15,
    kernel_width: float | None = None,
    min_std: float = 0.01,
    velocity_weight: float = 1.0,
    max_parents: int = 8,
    candidates: int | None = 20,
    restarts: int = 2,
    prior_window: int | None = None,
    score: Literal["propagated", "one_step"] = "propagated",
    half_life: float | None = 0.5,
    calibrate_retention: bool = True,
    horizon: float | None = None,
    phase: bool | None = None,
    time_warp: bool = True,
    cyclic: bool | None = None,
    seed: int = 0,
    ctx: Context,
) -> dict:
    """Learn the prior and transition networks of motion variation (Lau §5).

    Parameters
    ----------
    clips : Clips or list of Clips
        Training clips (a gather input is a list; it is merged).
    k : int
        Nearest instances of the kernel regression (paper: 15–60).
    kernel_width : float or None
        Bandwidth as a multiple of the median k-th neighbour distance
        (``None``: chosen per node by held-out likelihood).
    min_std : float
        Standard-deviation floor, standardised units.
    velocity_weight : float
        Weight of the self velocity in the transition distance.
    max_parents : int
        Parents per node at most (paper: 2–15).
    candidates : int or None
        Candidate parents per node (sparse candidate search); ``None``: all.
    restarts : int
        Random restarts of the prior-network search.
    prior_window : int, optional
        Prior training frames per clip (default: enough for ``2(k+1)`` held-out
        neighbours, :func:`~mocapflow.stages.variation.training.prior_window`).
    score : {"propagated", "one_step"}
        Transition network score (:mod:`~mocapflow.stages.variation.scores`).
    half_life : float or None
        Seconds; offset retention of the transition mean
        (:func:`~mocapflow.stages.variation.training.retention_of`; ``None``: pure
        delta regression, which can run away from the data under noise).
    calibrate_retention : bool
        Lower each DOF's retention to the one calibrated on the held-out clips
        (:func:`~mocapflow.stages.variation.scores.transition_node_retention`;
        at most that of ``half_life``), stored as ``params["retention_dof"]``
        (default); ``False``: the ``half_life`` retention for every DOF.
    horizon : float or None
        Seconds; ``score="propagated"`` only: the re-synthesised state is
        re-anchored to the held-out clip's true frames every ``horizon``
        seconds (rounded to whole frames, at least one; one frame is the
        one-step score), which bounds how much a run that drifts away from
        the data can weigh in a node's score.  Default ``None``: never
        re-anchored, the paper's form.
    phase : bool, optional
        Add the phase DOFs (default: yes;
        :func:`~mocapflow.stages.variation.training.with_phase`): normalised
        time ``_phase`` for non-cyclic clips, a parent candidate like any DOF;
        the cycle phase ``(cos φ, sin φ)`` for cyclic clips, a parent of every
        transition node (without it the mean dynamics of a walk can come to
        rest: streams stall).
    time_warp : bool
        Cyclic clips: learn the inputs' time warps onto a reference cycle
        (:func:`~mocapflow.stages.variation.warp.time_warps`), stored as
        ``params["time_warp"]``, from which the ``sample`` stage draws one warp
        per variant (the paper's temporal variation: whole-cycle variants of
        the figure-8 walk have 0.64 x the inputs' warp-slope std without it,
        0.70-0.92 with it; cmu_131_02's ~0.5 either way); ``False``: none.
    cyclic : bool, optional
        Override ``clips.cyclic``.
    seed : int
        Seed of the random restarts.
    ctx : Context
        Parallel map (per node) and warnings.

    Returns
    -------
    dict
        ``model`` (:class:`VariationModel`) and ``report`` (JSON: sizes, k used,
        edge counts, parents per node, scores, evaluations; the times of the steps
        ``training_data``, ``transition``, ``prior`` and ``retention`` go to
        ``ctx.timer``).
    """
    try:
        data = flatten_clips(clips)
    except ClipError as e:
        raise LearnError(str(e)) from None
    _check_params(data, k=k, kernel_width=kernel_width, ctx=ctx)
    horizon_frames = _horizon_frames(horizon, data.rate)
    cyclic = data.cyclic if cyclic is None else bool(cyclic)
    phase = True if phase is None else bool(phase)
    train = _training_clips(data.replace(cyclic=cyclic), phase=phase, ctx=ctx)
    with ctx.timer("training_data"):
        tdata, pdata = _training_data(
            train, cyclic=cyclic, k=k, kernel_width=kernel_width, min_std=min_std,
            velocity_weight=velocity_weight, half_life=half_life, prior_window=prior_window,
            ctx=ctx,
        )
    with ctx.timer("transition"):
        transition = search_transition(
            tdata, candidates=candidates, max_parents=max_parents, score=score, ctx=ctx,
            required=_phase_parents(train, cyclic=cyclic),
            horizon=horizon_frames,
        )
    with ctx.timer("prior"):
        prior = search_prior(
            pdata, candidates=candidates, max_parents=max_parents, restarts=restarts,
            seed=seed, ctx=ctx,
        )
    retention = retention_of(half_life, train.rate)
    warps = None
    if time_warp and cyclic:
        with ctx.timer("time_warp"):
            w = time_warps(data.trajectories, rate=float(data.rate))
        warps = None if w is None else w.round(6).tolist()
    retention_dof = [retention] * train.n_dofs
    if calibrate_retention:
        with ctx.timer("retention"):
            retention_dof = [
                transition_node_retention(tdata, i, ps, h * h, cap=retention)
                for i, (ps, h) in enumerate(zip(transition.parents, transition.bandwidth))
            ]
    model = VariationModel(
        clips=train.replace(cyclic=cyclic),
        prior_parents=prior.parents,
        transition_parents=transition.parents,
        params={
            "k": int(k),
            "k_prior": int(pdata.k),
            "k_transition": int(tdata.k),
            "kernel_width": None if kernel_width is None else float(kernel_width),
            "min_std": float(min_std),
            "velocity_weight": float(velocity_weight),
            "prior_window": int(prior_window_of(train, k, prior_window)),
            "score": score,
            "cyclic": cyclic,
            "half_life": half_life,
            "horizon": None if horizon is None else float(horizon),
            "retention": retention,
            "retention_dof": [float(x) for x in retention_dof],
            "calibrate_retention": bool(calibrate_retention),
            "phase": bool(phase),
            "time_warp": warps,
        },
        prior_scores=prior.scores,
        transition_scores=transition.scores,
        prior_bandwidth=prior.bandwidth,
        transition_bandwidth=transition.bandwidth,
        attrs={
            "evaluations": {"transition": transition.evaluations, "prior": prior.evaluations},
        },
    )
    return {"model": model, "report": _report(data, model)}


def _horizon_frames(horizon: float | None, rate: float) -> int | None:
    """``horizon`` seconds as whole frames (at least one), ``None`` kept."""
    if horizon is None:
        return None
    if (isinstance(horizon, bool) or not isinstance(horizon, (int, float))
            or not np.isfinite(horizon) or horizon <= 0):
        raise LearnError(f"horizon must be a positive number of seconds or None, got {horizon!r}")
    return max(1, int(round(float(horizon) * rate)))


def _phase_parents(train: Clips, *, cyclic: bool) -> tuple[int, ...]:
    """Parents of every transition node: the cycle phase at ``t+1`` of cyclic clips."""
    names = train.labels
    if not cyclic or not all(n in names for n in CYCLE_PHASE):
        return ()
    return tuple(train.n_dofs + names.index(n) for n in CYCLE_PHASE)


def _check_params(clips: Clips, *, k: int, kernel_width: float | None, ctx: Context) -> None:
    """Raise :class:`LearnError` for clips or kernel params the networks cannot use."""
    if clips.n_dofs == 0:
        raise LearnError(
            "no varying DOF: every DOF is constant over all clips "
            f"({len(clips.dof_names)} constant DOFs)"
        )
    if k < 2:
        raise LearnError(f"k must be at least 2, got {k}")
    if not 15 <= k <= 60:
        ctx.warn(f"k = {k} is outside the paper's range 15–60")
    if kernel_width is not None and not kernel_width > 0:
        raise LearnError(f"kernel_width must be > 0 or null, got {kernel_width}")


def _training_clips(data: Clips, *, phase: bool, ctx: Context) -> Clips:
    """The clips the networks train on: with the ``_phase`` DOF if ``phase`` (warns on one clip)."""
    train = with_phase(data) if phase else data
    if train.n_clips == 1:
        ctx.warn(
            "only one input clip: held-out scores leave out nearby frames instead of whole "
            "clips, and variants stay close to the input"
        )
    return train


def _training_data(
    clips: Clips,
    *,
    cyclic: bool,
    k: int,
    kernel_width: float | None,
    min_std: float,
    velocity_weight: float,
    half_life: float | None,
    prior_window: int | None,
    ctx: Context,
) -> tuple[TransitionData, PriorData]:
    """Transition and prior instances of the clips, one standardisation (warns when k shrinks)."""
    trajs = clips.trajectories
    stats = standardization(trajs)
    tdata = transition_data(
        trajs,
        stats,
        cyclic=cyclic,
        k=k,
        kernel_width=kernel_width,
        min_std=min_std,
        velocity_weight=velocity_weight,
        retention=retention_of(half_life, clips.rate),
    )
    pdata = prior_data(
        trajs, stats, k=k, kernel_width=kernel_width, min_std=min_std, window=prior_window
    )
    for name, dk in (("transition", tdata.k), ("prior", pdata.k)):
        if dk < k:
            ctx.warn(f"{name} network: k reduced from {k} to {dk} (too few held-out instances)")
    return tdata, pdata


def _report(data: Clips, model: VariationModel) -> dict[str, Any]:
    """JSON report: sizes, k used, edge counts, parents per node, scores, evaluations."""
    tp = [len(p) for p in model.transition_parents]
    pp = [len(p) for p in model.prior_parents]
    return {
        "n_clips": data.n_clips,
        "n_dofs": data.n_dofs,
        "frames": int(data.lengths.sum()),
        "k_prior": model.params["k_prior"],
        "k_transition": model.params["k_transition"],
        "edges": model.edges(),
        "transition_parents_mean": float(np.mean(tp) + 2),
        "prior_parents_max": int(max(pp)),
        "prior_score": float(model.prior_scores.sum()),
        "transition_score": float(model.transition_scores.sum()),
        "evaluations": model.attrs["evaluations"],
    }
