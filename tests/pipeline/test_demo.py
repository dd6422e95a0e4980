"""The demo runner: steps chain through each other's exports ({out})."""

from __future__ import annotations

import numpy as np

from mocapflow.pipeline.store import Store
from mocapflow.pipeline.testing import write_config

SYNC = ("--executor", "sync")


def test_demo_steps_chain_through_exports(cli, tmp_path):
    (tmp_path / "cfg").mkdir()
    write_config(tmp_path / "cfg" / "first.yaml", """\
        nodes:
          src: {stage: toy_source, seeds: {count: 2}, params: {n: 4, noise: 1.0}}
        """)
    write_config(tmp_path / "cfg" / "second.yaml", """\
        parts: [none.npy]
        nodes:
          read: {stage: toy_read_file, inputs: {path: part}}
          total: {stage: toy_sum, inputs: {values: read.values}, gather: true}
        targets: [total]
        """)
    spec = write_config(tmp_path / "cfg" / "demo.yaml", """\
        steps:
          - config: first.yaml
            export_to: first
            set: {src.value: 2.0}
          - config: second.yaml
            name: sums
            parts: ["{out}/first/src/*/values.npy"]
            export_to: second
        """)
    out = tmp_path / "demo"
    code, text, err = cli("demo", "--out", out, "--spec", spec, *SYNC, "-q")
    assert code == 0, err
    assert text.splitlines()[0] == f"demo results in {out}"
    firsts = sorted((out / "first" / "src").glob("*/values.npy"))
    assert [p.parent.name for p in firsts] == ["seed0", "seed1"]
    want = [np.load(p).sum() for p in firsts]
    np.testing.assert_allclose(np.load(out / "second" / "total" / "all" / "total.npy"), want)
    assert Store(out / "store").verify() == []
