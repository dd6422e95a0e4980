"""Similar-input selection (Lau §9): the threshold from a trusted set, the outlier removed first."""

import numpy as np
import pytest

from mocapflow.stages.variation.clips import make_clips
from mocapflow.stages.variation.similar import likelihood_threshold, select_similar


def _cycle(T, D, gain, warp, rng):
    u = np.arange(T) / T
    s = u + warp * np.sin(2 * np.pi * u + rng.uniform(0, 6)) / (2 * np.pi)
    ph = np.linspace(0, np.pi, D, endpoint=False)
    return gain * np.sin(2 * np.pi * s[:, None] + ph)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_similar_input_selection_removes_the_outlier_first(seed):
    rng = np.random.default_rng(seed)
    D = 3
    names = [f"d{i}" for i in range(D)]

    def good():
        return (_cycle(40, D, 1 + 0.05 * rng.standard_normal(D), 0.1, rng)
                + 0.02 * rng.standard_normal((40, D)))

    trusted = make_clips([good() for _ in range(8)], names, rate=40.0, cyclic=True)
    thr = likelihood_threshold(trusted, splits=6, k=8)
    assert np.isfinite(thr)
    assert likelihood_threshold(trusted, splits=6, k=8, percentile=50.0) > thr
    odd = 0.5 * _cycle(40, D, 1.0, 0.0, rng)[:, ::-1] + 0.8  # other shape and level
    labels = [f"g{i}" for i in range(7)] + ["odd"]
    cand = make_clips([good() for _ in range(7)] + [odd], names, rate=40.0, cyclic=True,
                      names=labels)
    kept, removed = select_similar(cand, thr, k=8)
    assert removed and removed[0]["name"] == "odd" and removed[0]["log_likelihood"] < thr
    assert "odd" not in kept.names and len(kept.names) >= 4
    if seed == 1:  # this set: only the outlier goes
        assert kept.names == labels[:7]
