"""Export: layout DIR/<node>/<part label>/<output>.<ext>, arrays, JSON values, records."""

from __future__ import annotations

import json

import numpy as np

from mocapflow.pipeline.testing import write_config

SYNC = ("--executor", "sync")


def test_export_layout_and_content(cli, toy_config, tmp_path):
    out_dir = tmp_path / "out"
    code, out, err = cli("export", toy_config, "--to", out_dir, "--store", tmp_path / "s",
                         *SYNC, "--target", "scale", "--target", "total")
    assert code == 0
    total = np.load(out_dir / "total" / "all" / "total.npy")
    np.testing.assert_array_equal(total, [2 * (5 * i + 15) for i in range(5)])
    assert json.loads((out_dir / "total" / "all" / "report.json").read_text()) == {
        "parts": 5, "grand_total": float(total.sum())}
    np.testing.assert_array_equal(np.load(out_dir / "scale" / "trial002" / "values.npy"),
                                  2 * (np.arange(5.0) + 3))
    assert len(out.splitlines()) == 7
    # a record output: attrs as JSON, arrays as .npy
    cfg = write_config(tmp_path / "r.yaml", """\
        nodes:
          src: {stage: toy_source, params: {n: 8}}
          stats: {stage: toy_stats, inputs: {values: src.values}}
        targets: [stats]
        """)
    code, out, err = cli("export", cfg, "--to", out_dir, "--store", tmp_path / "s", *SYNC)
    rec = json.loads((out_dir / "stats" / "all" / "stats.json").read_text())
    assert rec["mean"] == 3.5 and rec["_arrays"]["hist"] == "stats.hist.npy"
    np.testing.assert_array_equal(np.load(out_dir / "stats" / "all" / "stats.hist.npy"),
                                  [2, 2, 2, 2])
