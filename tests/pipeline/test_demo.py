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


def test_demo_full_applies_each_steps_full_overrides_and_says_where_to_look(cli, tmp_path):
    (tmp_path / "cfg").mkdir()
    write_config(tmp_path / "cfg" / "first.yaml", """\
        nodes:
          src: {stage: toy_source, seeds: {count: 3}, params: {n: 4, noise: 0.0}}
        """)
    spec = write_config(tmp_path / "cfg" / "demo.yaml", """\
        steps:
          - config: first.yaml
            export_to: first
            set: {src.value: 2.0, src.seeds: 1}
            show: ["src/*/values.npy", "src/none/*"]
            full:
              set: {src.seeds: 3, src.n: 6}
        """)
    quick, full = tmp_path / "quick", tmp_path / "full"
    code, text, err = cli("demo", "--out", quick, "--spec", spec, *SYNC, "-q")
    assert code == 0, err
    values = sorted((quick / "first" / "src").glob("*/values.npy"))
    assert [p.parent.name for p in values] == ["seed0"] and np.load(values[0]).shape == (4,)
    lines = text.splitlines()
    # one line per step: its folder, then the one file the first glob matched (the
    # second glob matches nothing: left out)
    assert lines[lines.index("where to look:") + 1] == (
        f"  first: {quick / 'first'}/  src/seed0/values.npy")

    code, text, err = cli("demo", "--out", full, "--spec", spec, "--full", *SYNC, "-q")
    assert code == 0, err
    values = sorted((full / "first" / "src").glob("*/values.npy"))
    assert [p.parent.name for p in values] == ["seed0", "seed1", "seed2"]
    # full: merged over set: (n from full:, value 2.0 kept from set:)
    np.testing.assert_allclose(np.load(values[0]), 2.0 * np.arange(6))
    assert f"  first: {full / 'first'}/  src/*/values.npy (3)" in text.splitlines()


def test_demo_step_full_rejects_unknown_keys(cli, tmp_path):
    spec = write_config(tmp_path / "demo.yaml", """\
        steps:
          - config: first.yaml
            full: {targets: [src]}
        """)
    code, _, err = cli("demo", "--out", tmp_path / "o", "--spec", spec, *SYNC, "-q")
    assert code != 0 and "steps[0].full: unknown key 'targets'" in err
