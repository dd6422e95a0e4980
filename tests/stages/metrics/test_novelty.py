"""Novelty metrics: DTW against a reference implementation, copied runs, report."""

import numpy as np
import pytest

from mocapflow.stages.metrics.novelty import (
    aligned_distance,
    dtw,
    longest_copied_run,
    nearest_pose_distance,
    novelty_report,
    warp_slope_std,
)


def _dtw_reference(a, b):
    n, m = len(a), len(b)
    D = np.full((n + 1, m + 1), np.inf)
    D[0, 0] = 0.0
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            c = np.linalg.norm(a[i - 1] - b[j - 1])
            D[i, j] = c + min(D[i - 1, j - 1], D[i - 1, j], D[i, j - 1])
    return D[n, m]


@pytest.mark.parametrize("n,m", [(1, 1), (7, 12), (15, 9), (20, 20)])
def test_dtw_matches_reference_and_path_is_valid(n, m):
    rng = np.random.default_rng(n * 100 + m)
    a, b = rng.normal(size=(n, 3)), rng.normal(size=(m, 3))
    cost, path = dtw(a, b)
    assert cost == pytest.approx(_dtw_reference(a, b), rel=1e-12, abs=1e-12)
    assert tuple(path[0]) == (0, 0) and tuple(path[-1]) == (n - 1, m - 1)
    steps = np.diff(path, axis=0)
    assert np.all((steps >= 0) & (steps <= 1)) and np.all(steps.sum(axis=1) >= 1)
    assert sum(np.linalg.norm(a[i] - b[j]) for i, j in path) == pytest.approx(cost, rel=1e-12)


def test_identical_and_time_warped_sequences():
    t = np.linspace(0, 4 * np.pi, 120)
    a = np.stack([np.sin(t), np.cos(2 * t)], axis=1)
    cost, path = dtw(a, a)
    assert cost == 0.0 and np.all(path[:, 0] == path[:, 1])
    assert warp_slope_std(path) < 1e-12
    # output at alternating speeds 0.5 / 1.5 of the input (30-frame blocks): slope std 0.5
    speed = np.tile(np.repeat([0.5, 1.5], 30), 4)
    s = np.concatenate([[0.0], np.cumsum(speed[:-1])])
    u = np.linspace(0, 4 * np.pi, int(s[-1]) + 1)
    inp = np.stack([np.sin(u), np.cos(2 * u)], axis=1)
    out = np.stack([np.interp(s, np.arange(len(u)), inp[:, d]) for d in range(2)], axis=1)
    c2, p2 = dtw(out, inp)
    assert c2 / len(p2) < 0.05
    assert 0.35 <= warp_slope_std(p2) <= 0.55
    assert aligned_distance(out, inp) == pytest.approx(c2 / len(p2))
    with pytest.raises(ValueError, match="empty"):
        dtw(np.zeros((0, 2)), a)


def test_longest_copied_run_and_nearest_pose():
    rng = np.random.default_rng(0)
    x = np.cumsum(rng.normal(size=(50, 2)), axis=0)
    out = rng.normal(size=(30, 2)) * 100 + 1000
    out[10:17] = x[20:27]  # a verbatim 7-frame copy
    assert longest_copied_run(out, [x], 1e-9) == 7
    ok = np.ones(50, bool)
    ok[23] = False  # a frame that may not count (at rest) splits the run
    assert longest_copied_run(out, [x], 1e-9, eligible=[ok]) == 3
    wrap = np.concatenate([x[-3:], x[:4]])  # crosses the end of a cyclic input
    assert longest_copied_run(wrap, [x], 1e-9) == 4
    assert longest_copied_run(wrap, [x], 1e-9, cyclic=True) == 7
    assert longest_copied_run(out[:5], [x], 1e-9) == 0
    brute = np.min(np.linalg.norm(out[:, None] - x[None], axis=-1))
    assert nearest_pose_distance(out, [x]) == pytest.approx(brute, rel=1e-12)


def test_report_flags_copies_and_gives_input_references():
    rng = np.random.default_rng(1)
    t = np.linspace(0, 2 * np.pi, 60)
    ins = [np.stack([np.sin(t + p), np.cos(t + p)], 1) * (1 + 0.1 * rng.standard_normal())
           for p in rng.uniform(0, 0.3, 4)]
    rep = novelty_report(ins[:2], ins)  # the outputs are inputs: copies
    assert rep["equal_poses"] == 120 and rep["copied_run"] == [60, 60]
    assert rep["nearest_pose"] == [0.0, 0.0] and rep["aligned_distance"] == [0.0, 0.0]
    assert len(rep["input_distances"]) == 6 and rep["input_distance_p95"] > 0
    assert rep["input_copied_run"] < 60
    noisy = [i + 0.05 * rng.standard_normal(i.shape) for i in ins[:2]]
    rep2 = novelty_report(noisy, ins)
    assert rep2["equal_poses"] == 0 and max(rep2["copied_run"]) < 5
    assert all(0 < d < rep2["input_distance_p95"] for d in rep2["aligned_distance"])
    with pytest.raises(ValueError, match="no input"):
        novelty_report(noisy, [])
