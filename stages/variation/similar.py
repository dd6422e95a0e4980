"""Selection of similar inputs by held-out likelihood (Lau, Bar-Joseph & Kuffner 2009, §9).

The method needs a few *similar* examples.  A clip is scored by its per-frame
log-likelihood (median over frames of the mean over DOFs of the one-step log
density) under the transition network trained on other clips
(:func:`heldout_log_likelihood`).  As in the paper, the network's structure is
learned on each training set (``structure="learned"``: the transition parents
searched by :func:`~mocapflow.stages.variation.search.search_transition` with
the one-step score); ``structure="self"`` keeps self parents only (faster).

* :func:`likelihood_threshold`: the 10th percentile of the held-out scores of
  random train-on-6 / test-on-2 splits of a trusted set, the structure learned
  on each split's 6 training clips;
* :func:`select_similar`: removes the least likely clip (scored against the
  other remaining clips, the structure learned on them) while it is below the
  threshold.

Departures from the paper: the score is the median over frames of the
per-frame log density (robust to the few frames a small training set cannot
predict), the structure search is sparse (``candidates`` most correlated
parents, ``max_parents`` at most; small defaults to keep it fast) and the
prior network is not used (a clip's first two frames are not scored).

The ``clips`` stage runs :func:`select_similar` when ``similar_threshold`` is set.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context
from mocapflow.stages.variation.clips import ClipError, Clips
from mocapflow.stages.variation.kernel import gauss_log_density, nearest_kernel_regression
from mocapflow.stages.variation.scores import transition_node_fit
from mocapflow.stages.variation.search import search_transition
from mocapflow.stages.variation.training import standardization, transition_data

__all__ = ["heldout_log_likelihood", "likelihood_threshold", "select_similar"]


def heldout_log_likelihood(
    train: list[np.ndarray],
    test: list[np.ndarray],
    *,
    cyclic: bool = False,
    transition_parents: list[list[int]] | None = None,
    k: int = 15,
    kernel_width: float | None = None,
    min_std: float = 0.01,
    velocity_weight: float = 1.0,
    statistic: Literal["mean", "median"] = "median",
    structure: Literal["learned", "self"] = "learned",
    max_parents: int = 2,
    candidates: int | None = 4,
) -> np.ndarray:
    """Per-frame log-likelihood of test clips under a transition network.

    Parameters
    ----------
    train : list of (T_c, D) float ndarray
        Training clips (kernel regression data; standardisation).
    test : list of (T_c, D) float ndarray
        Clips to score.
    cyclic : bool
    transition_parents : list of list of int, optional
        Extra parents per DOF over ``0..2D-1`` (``X[t]`` then ``X[t+1]``);
        given, no structure is searched.
    k, kernel_width, min_std, velocity_weight
        Kernel regression parameters.
    statistic : {"median", "mean"}
        Summary over frames of the per-frame log density (mean over DOFs);
        the median is robust to the few frames a small training set cannot
        predict.
    structure : {"learned", "self"}
        Without ``transition_parents``: search the transition structure on
        ``train`` (the paper) or use self parents only.
    max_parents : int
        Extra parents per node of the learned structure (default 2; the
        ``learn`` stage's is 8).
    candidates : int or None
        Candidate parents per node of the search (default 4; ``None``: all).

    Returns
    -------
    (len(test),) float ndarray
        Per-frame one-step log density (standardised delta units).
    """
    stats = standardization(train)
    common = dict(kernel_width=kernel_width, min_std=min_std, velocity_weight=velocity_weight)
    tr = transition_data(train, stats, cyclic=cyclic, k=k, **common)
    D = tr.n_dofs
    if transition_parents is None and structure == "learned":
        found = search_transition(
            tr, candidates=candidates, max_parents=max_parents, score="one_step",
            ctx=Context(),
        )
        transition_parents = [list(p) for p in found.parents]
    elif structure not in ("learned", "self"):
        raise ValueError(f"structure must be 'learned' or 'self', got {structure!r}")
    parents = transition_parents or [[] for _ in range(D)]
    kk = min(k, tr.F.shape[0])
    h2s = [transition_node_fit(tr, i, parents[i], score="one_step")[1] for i in range(D)]
    out = []
    for t in test:
        te = transition_data([t], stats, cyclic=cyclic, k=2, exclusion=0, **common)
        ll = np.zeros(te.F.shape[0])
        for i in range(D):
            d2 = np.zeros((te.F.shape[0], tr.F.shape[0]))
            for c in [D + i, *parents[i]]:
                d2 += (te.F[:, c][:, None] - tr.F[:, c][None, :]) ** 2
            d2 += (te.V[:, i][:, None] - tr.V[:, i][None, :]) ** 2
            mu, var = nearest_kernel_regression(d2, tr.Y[:, i], kk, h2s[i], min_std)
            ll += gauss_log_density(te.Y[:, i], mu, var)
        per_frame = ll / D
        out.append(float(np.median(per_frame) if statistic == "median" else per_frame.mean()))
    return np.asarray(out)


def likelihood_threshold(
    trusted: Clips,
    *,
    n_train: int = 6,
    n_test: int = 2,
    splits: int = 20,
    percentile: float = 10.0,
    seed: int = 0,
    k: int = 15,
    kernel_width: float | None = None,
    structure: Literal["learned", "self"] = "learned",
    max_parents: int = 2,
    candidates: int | None = 4,
) -> float:
    """Log-likelihood threshold for similar inputs from a trusted set (Lau §9).

    Random train-on-``n_train`` / test-on-``n_test`` splits of the trusted
    clips; each test clip's per-frame log-likelihood (median over frames) under
    the transition network trained on the split's training clips (its
    structure learned on them, with ``structure="learned"``); the threshold
    is the ``percentile`` of those values.

    Parameters
    ----------
    trusted : Clips
        At least 3 clips known to be similar (8 for the paper's 6/2 splits;
        with fewer, ``n_train = C - n_test``).
    n_train, n_test, splits : int
    percentile : float
    seed : int
    k, kernel_width
        Kernel regression parameters (as in the ``learn`` stage).
    structure, max_parents, candidates
        Structure of each split's network (:func:`heldout_log_likelihood`).

    Returns
    -------
    float
        Per-frame log-likelihood threshold.
    """
    C = trusted.n_clips
    if C < 3:
        raise ClipError(f"likelihood_threshold: need at least 3 trusted clips, got {C}")
    n_test = min(n_test, C - 2)
    n_train = min(n_train, C - n_test)
    rng = np.random.default_rng(seed)
    values: list[float] = []
    for _ in range(splits):
        perm = rng.permutation(C)
        train = [trusted.trajectories[i] for i in perm[:n_train]]
        test = [trusted.trajectories[i] for i in perm[n_train : n_train + n_test]]
        values += list(
            heldout_log_likelihood(
                train, test, cyclic=trusted.cyclic, k=k, kernel_width=kernel_width,
                structure=structure, max_parents=max_parents, candidates=candidates,
            )
        )
    return float(np.percentile(values, percentile))


def select_similar(
    clips: Clips,
    threshold: float,
    *,
    min_clips: int = 2,
    k: int = 15,
    kernel_width: float | None = None,
    structure: Literal["learned", "self"] = "learned",
    max_parents: int = 2,
    candidates: int | None = 4,
) -> tuple[Clips, list[dict[str, Any]]]:
    """Iteratively remove the least likely clip while it falls below ``threshold`` (Lau §9).

    Each clip is scored by its per-frame log-likelihood (median over frames)
    under the transition network trained on the other remaining clips (its
    structure learned on them, with ``structure="learned"``).

    Parameters
    ----------
    clips : Clips
    threshold : float
        From :func:`likelihood_threshold`.
    min_clips : int
        Never go below this many clips.
    k, kernel_width
        Kernel regression parameters.
    structure, max_parents, candidates
        Structure of each network (:func:`heldout_log_likelihood`).

    Returns
    -------
    kept : Clips
    removed : list of dict
        ``name`` and ``log_likelihood`` of each removed clip, in removal order.
    """
    idx = list(range(clips.n_clips))
    removed: list[dict[str, Any]] = []
    while len(idx) > min_clips:
        scores = []
        for i in idx:
            train = [clips.trajectories[j] for j in idx if j != i]
            scores.append(
                heldout_log_likelihood(
                    train,
                    [clips.trajectories[i]],
                    cyclic=clips.cyclic,
                    k=k,
                    kernel_width=kernel_width,
                    structure=structure,
                    max_parents=max_parents,
                    candidates=candidates,
                )[0]
            )
        worst = int(np.argmin(scores))
        if scores[worst] >= threshold:
            break
        removed.append({"name": clips.names[idx[worst]], "log_likelihood": float(scores[worst])})
        idx.pop(worst)
    return clips.subset(idx), removed
