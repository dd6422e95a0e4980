"""Similar-input selection (Lau §9): the threshold from a trusted set, the outlier removed first."""

import json
from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline.cli import main
from mocapflow.stages.variation import similar
from mocapflow.stages.variation.clips import make_clips
from mocapflow.stages.variation.similar import (
    heldout_log_likelihood,
    likelihood_threshold,
    select_similar,
)
from tests.stages.variation.conftest import DATA


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


def _lagged(rng, T=60):
    """Two DOFs: a random walk and its one-frame-late copy (d1[t+2] = d0[t+1])."""
    x = np.cumsum(rng.standard_normal(T + 1)) * 0.1
    return np.stack([x[1:], x[:-1]], 1)


def test_learned_structure_predicts_a_lagged_copy_better_than_self_parents():
    rng = np.random.default_rng(0)
    train, test = [_lagged(rng) for _ in range(6)], [_lagged(rng) for _ in range(2)]
    own = heldout_log_likelihood(train, test, k=8, structure="self")
    learned = heldout_log_likelihood(train, test, k=8, structure="learned")
    # self parents cannot predict a random walk's step (≈ -1.4, -1.1); the copy's can
    assert np.all(learned > own + 0.15), (own, learned)
    np.testing.assert_allclose(
        heldout_log_likelihood(train, test, k=8, transition_parents=[[], []]), own)
    with pytest.raises(ValueError, match="structure"):
        heldout_log_likelihood(train, test, k=8, structure="none")


def test_threshold_learns_the_structure_on_each_six_two_split(monkeypatch):
    rng = np.random.default_rng(1)
    trusted = make_clips([_lagged(rng, 40) for _ in range(8)], ["a", "b"], rate=40.0)
    seen = []
    real = similar.search_transition

    def spy(data, **kw):
        seen.append(data.Y.shape[0])
        return real(data, **kw)

    monkeypatch.setattr(similar, "search_transition", spy)
    likelihood_threshold(trusted, splits=3, k=6)
    # one search per split, on the 6 training clips' 6 * (40 - 2) instances
    assert seen == [6 * 38] * 3
    seen.clear()
    likelihood_threshold(trusted, splits=3, k=6, structure="self")
    assert seen == []


@pytest.mark.skipif(not (DATA / "strokes").is_dir(), reason="shared data absent")
def test_similar_threshold_reaches_the_selection_from_the_config(tmp_path, capsys):
    cfg = Path(__file__).resolve().parents[3] / "configs" / "variation_strokes.yaml"

    def run(threshold):
        capsys.readouterr()
        code = main(["run", str(cfg), "--store", str(tmp_path / "store"), "--executor", "sync",
                     "--target", "clips", "--set", f"clips.similar_threshold={threshold}",
                     "--set", "clips.similar_structure=self", "--json", "-q"])
        out, err = capsys.readouterr()
        assert code == 0, err[-2000:]
        (task,) = [t for t in json.loads(out)["tasks"] if t["node"] == "clips"]
        return task

    # letter a: 5 clips; no clip scores above +100 per frame, every clip above -100
    high = run(100.0)
    removed = [w for w in high["warnings"] if "removed: log-likelihood" in w]
    assert len(removed) == 3  # down to min_clips = 2
    low = run(-100.0)
    assert not [w for w in low["warnings"] if "removed" in w]
