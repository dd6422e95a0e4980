"""The gap protocol's same-sample comparison (benchmarks/clean_gaps.py): ours against
each baseline on the samples that baseline filled."""

from __future__ import annotations

import numpy as np
from clean_gaps import result_rows, same_sample_ratios  # (benchmarks/ on sys.path: conftest.py)


def _case(rep: int, ours: np.ndarray, spline: np.ndarray) -> dict:
    """A run_case-like result: errors (m) per deleted sample, NaN where unfilled."""
    def sc(e):
        ok = np.isfinite(e)
        return {"err": e[ok], "norm": e[ok], "unfilled": int((~ok).sum()), "n": len(e),
                "n_3nb": len(e), "unfilled_3nb": int((~ok).sum()), "seconds": 0.0,
                "status": "ok", "filled": ok, "err_all": e}
    return {"dataset": "d", "duration": 1.0, "fraction": 0.1, "clustered": False, "rep": rep,
            "mask": "m", "n_gapped": 1, "methods": {"ours": sc(ours), "cubic spline": sc(spline)}}


def test_ours_is_compared_on_the_samples_the_baseline_filled():
    # the spline skips the two hard samples (an edge gap) where ours errs 10 mm
    ours = np.array([0.001, 0.001, 0.002, 0.010, 0.010])
    spline = np.array([0.001, 0.001, 0.001, np.nan, np.nan])
    rows = [{r["method"]: r for r in result_rows(_case(k, ours, spline))} for k in range(2)]
    assert rows[0]["cubic spline"]["unfilled"] == 2
    assert rows[0]["cubic spline"]["err_um"] == [1000, 1000, 1000, -1, -1]
    got = same_sample_ratios(rows)
    # over its own samples ours' mean is 4.8 mm vs 1 mm; over the spline's, 4/3 mm vs 1 mm
    assert np.isclose(got["cubic spline"], (0.004 / 3) / 0.001, rtol=1e-6)
    assert np.isclose(rows[0]["ours"]["sum_err"] / rows[0]["ours"]["n_err"], 0.0048)
    # ours leaves samples the spline filled 30 and 5 mm off: neither is scored there
    hard = np.array([0.001, 0.001, np.nan, np.nan, 0.002])
    easy = np.array([0.001, 0.001, 0.030, 0.005, 0.001])
    rows2 = [{r["method"]: r for r in result_rows(_case(k, hard, easy))} for k in range(2)]
    assert np.isclose(same_sample_ratios(rows2)["cubic spline"], (0.008 / 6) / (0.006 / 6),
                      rtol=1e-6)
    # a baseline row written before it carried err_um: all the samples it filled
    del rows2[0]["cubic spline"]["err_um"]
    assert np.isclose(same_sample_ratios(rows2)["cubic spline"],
                      (0.008 / 6) / ((0.038 + 0.003) / 8), rtol=1e-6)
    # a baseline that failed on a repetition is left out (the criteria skip it too)
    rows[1]["cubic spline"]["status"] = "failed: no complete frame"
    assert same_sample_ratios(rows) == {}
    # rows written before the fields existed give no same-sample ratio
    del rows[1]["ours"]["err_um"]
    assert same_sample_ratios(rows) == {}
