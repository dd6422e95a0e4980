"""The learned DBN of motion variation: :class:`VariationModel` and its codec (Lau et al. 2009, §5).

Kernel regression is non-parametric, so the model is its structure (prior and
transition parent lists), the kernel parameters, the per-node bandwidths and
scores, and the training clips themselves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mocapflow.pipeline.codecs import Encoded, codec, decode, encode
from mocapflow.stages.variation.clips import Clips
from mocapflow.stages.variation.scores import prior_node_fit, transition_node_fit
from mocapflow.stages.variation.training import (
    LearnError,
    prior_data,
    standardization,
    transition_data,
)

__all__ = ["VariationModel"]


@dataclass(eq=False)
class VariationModel:
    """A learned DBN of motion variation plus its training clips.

    Parameters
    ----------
    clips : Clips
        Training clips (kernel regression is non-parametric: the data is the model).
    prior_parents : list of list of int
        ``2D`` parent lists over nodes ``0..2D-1`` (``X[0]``, then ``X[1]``).
    transition_parents : list of list of int
        ``D`` parent lists over ``0..2D-1`` (``X[t]``, then ``X[t+1]``), self
        parents implicit.
    params : dict
        Kernel regression parameters used (``k``, ``kernel_width``,
        ``min_std``, ``velocity_weight``, ``prior_window``, ``cyclic``, ...).
    prior_scores : (2D,) float ndarray
    transition_scores : (D,) float ndarray
        Cross-validated log-likelihood of each node.
    prior_bandwidth : (2D,) float ndarray, optional
    transition_bandwidth : (D,) float ndarray, optional
        Kernel bandwidth of each node (standardised units); computed from the
        training data when not given.
    attrs : dict
        Timings, evaluation counts.
    """

    clips: Clips
    prior_parents: list[list[int]]
    transition_parents: list[list[int]]
    params: dict[str, Any]
    prior_scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    transition_scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    prior_bandwidth: np.ndarray | None = None
    transition_bandwidth: np.ndarray | None = None
    attrs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        D = self.clips.n_dofs
        self.prior_parents = [[int(u) for u in p] for p in self.prior_parents]
        self.transition_parents = [[int(u) for u in p] for p in self.transition_parents]
        if len(self.prior_parents) != 2 * D or len(self.transition_parents) != D:
            raise LearnError(
                f"model: {len(self.prior_parents)} prior / {len(self.transition_parents)} "
                f"transition parent lists for {D} DOFs"
            )
        self.prior_scores = np.asarray(self.prior_scores, dtype=np.float64)
        self.transition_scores = np.asarray(self.transition_scores, dtype=np.float64)
        if self.prior_bandwidth is None or self.transition_bandwidth is None:
            self.prior_bandwidth, self.transition_bandwidth = _bandwidths(self)
        self.prior_bandwidth = np.asarray(self.prior_bandwidth, dtype=np.float64).reshape(2 * D)
        self.transition_bandwidth = np.asarray(
            self.transition_bandwidth, dtype=np.float64
        ).reshape(D)

    @property
    def n_dofs(self) -> int:
        """``D``."""
        return self.clips.n_dofs

    def __repr__(self) -> str:
        """One line: DOFs, edge counts and the training clips' one-line repr."""
        e = self.edges()
        return (f"VariationModel({self.n_dofs} DOFs, {e['prior']} prior + {e['transition']} "
                f"transition edges, trained on {self.clips!r})")

    def edges(self) -> dict[str, int]:
        """Edge counts (prior; transition extra parents, self edges excluded)."""
        return {
            "prior": sum(len(p) for p in self.prior_parents),
            "transition": sum(len(p) for p in self.transition_parents),
        }


def _bandwidths(m: VariationModel) -> tuple[np.ndarray, np.ndarray]:
    """Per-node bandwidths of a model's structure from its training data (one-step)."""
    p = m.params
    trajs = m.clips.trajectories
    stats = standardization(trajs)
    kw = dict(k=p["k"], kernel_width=p["kernel_width"], min_std=p["min_std"])
    td = transition_data(
        trajs, stats, cyclic=bool(p["cyclic"]), velocity_weight=p["velocity_weight"],
        retention=float(p.get("retention", 1.0)), **kw,
    )
    pd = prior_data(trajs, stats, window=p["prior_window"], **kw)
    hp = [math.sqrt(prior_node_fit(pd, v, ps)[1]) for v, ps in enumerate(m.prior_parents)]
    ht = [
        math.sqrt(transition_node_fit(td, i, ps, score="one_step")[1])
        for i, ps in enumerate(m.transition_parents)
    ]
    return np.array(hp), np.array(ht)


def _encode_model(m: VariationModel) -> Encoded:
    e = encode(m.clips)
    arrays = {f"clips_{k}": v for k, v in e.arrays.items()}
    arrays["prior_scores"] = (m.prior_scores, ("prior_node",))
    arrays["transition_scores"] = (m.transition_scores, ("dof",))
    arrays["prior_bandwidth"] = (m.prior_bandwidth, ("prior_node",))
    arrays["transition_bandwidth"] = (m.transition_bandwidth, ("dof",))
    return Encoded(
        "variation_model",
        arrays,
        {
            "clips": e.attrs,
            "prior_parents": m.prior_parents,
            "transition_parents": m.transition_parents,
            "params": m.params,
            "attrs": m.attrs,
        },
        dict(e.coords),  # the clips' labels (joint, dof, clip, ...)
    )


def _decode_model(e: Encoded) -> VariationModel:
    arrs = {k[len("clips_") :]: v for k, v in e.arrays.items() if k.startswith("clips_")}
    clips = decode(Encoded("clips", arrs, e.attrs["clips"]))
    return VariationModel(
        clips=clips,
        prior_parents=e.attrs["prior_parents"],
        transition_parents=e.attrs["transition_parents"],
        params=e.attrs["params"],
        prior_scores=e.arrays["prior_scores"][0],
        transition_scores=e.arrays["transition_scores"][0],
        prior_bandwidth=e.arrays["prior_bandwidth"][0],
        transition_bandwidth=e.arrays["transition_bandwidth"][0],
        attrs=e.attrs.get("attrs", {}),
    )


codec("variation_model", encode=_encode_model, decode=_decode_model)(VariationModel)
