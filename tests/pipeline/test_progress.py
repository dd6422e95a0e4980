"""Run progress: a bar on a terminal, plain lines otherwise."""

from __future__ import annotations

import re

import pytest

from mocapflow.pipeline.testing import write_config, write_number_files


def test_progress_bar_and_plain_lines():
    import io

    from mocapflow.pipeline.progress import Progress

    tty = io.StringIO()
    p = Progress(3, stream=tty, tty=True)
    for status in ("hit", "computed", "failed"):
        p.update({"node": "n", "part": "a.bvh", "status": status, "seconds": 0.5,
                  "error": "ValueError: bad" if status == "failed" else None})
    p.close()
    text = tty.getvalue()
    assert "\r" in text and "] 3/3 hit 1 computed 1 failed 1" in text
    assert "failed   n/a.bvh: ValueError: bad" in text
    assert text.endswith("3 tasks: 1 hit, 1 computed, 1 failed, 0 skipped in 0.0s\n")
    plain = io.StringIO()
    p = Progress(2, stream=plain, tty=False)
    p.update({"node": "n", "part": None, "status": "hit"})
    p.update({"node": "m", "part": "b", "status": "computed", "seconds": 1.25})
    p.close()
    assert plain.getvalue().splitlines() == [
        "[2/2] computed m/b 1.25s", "2 tasks: 1 hit, 1 computed, 0 failed, 0 skipped in 0.0s"]


# --------------------------------------------------------------------------- warnings once

WARN = """\
parts: ["{data}/*.txt"]
nodes:
  read: {{stage: toy_read_file, inputs: {{path: part}}}}
  warn: {{stage: toy_warn, inputs: {{values: read.values}},
         params: {{message: "the same advice", times: 2}}}}
  other: {{stage: toy_warn, inputs: {{values: warn.values}}, params: {{message: "once only"}}}}
"""


def test_warning_lines_once_per_message_with_a_count():
    from mocapflow.pipeline.execute import TaskRecord
    from mocapflow.pipeline.progress import warning_lines

    recs = [TaskRecord(index=i, node="n", part=f"p{i}", stage="s", status="computed",
                       warnings=("same", "same") if i < 5 else ("same",)) for i in range(6)]
    recs.append(TaskRecord(index=6, node="g", part=None, stage="s", status="hit"))
    recs.append({"node": "g", "part": None, "warnings": ["gather only"]})
    assert warning_lines(recs) == [
        "warning: n/p0: same (×11 in 6 tasks: also n/p1, n/p2, n/p3 and 2 more)",
        "warning: g: gather only",
    ]
    assert warning_lines([{"node": "a", "part": "x", "warnings": ["w", "w"]}]) == [
        "warning: a/x: w (×2)"]
    assert warning_lines([]) == []


def test_stage_warning_filter_drops_ctx_warn_only():
    import io
    import logging

    from mocapflow.pipeline.context import Context
    from mocapflow.pipeline.progress import StageWarningFilter

    log = logging.getLogger("mocapflow")
    buf = io.StringIO()
    h = logging.StreamHandler(buf)
    h.addFilter(StageWarningFilter())
    log.addHandler(h)
    try:
        Context(part="p").warn("from a stage")
        log.warning("from the engine")
    finally:
        log.removeHandler(h)
    assert buf.getvalue() == "from the engine\n"


@pytest.mark.parametrize("executor", ["sync", "local"])
def test_stage_warnings_print_once_on_every_executor(cli_proc, tmp_path, executor):
    write_number_files(tmp_path / "data", 3)
    cfg = write_config(tmp_path / "w.yaml", WARN, data=tmp_path / "data")
    p = cli_proc("run", cfg, "--store", tmp_path / "s", "--executor", executor,
                 "--workers", "2")
    out, err = p.communicate(timeout=120)
    assert p.returncode == 0, err
    same = [line for line in err.splitlines() if "the same advice" in line]
    once = [line for line in err.splitlines() if "once only" in line]
    assert len(same) == 1 and len(once) == 1, err  # not per task, not again from a worker
    assert re.fullmatch(r"warning: warn/\S+trial000\.txt: the same advice \(×6 in 3 tasks: "
                        r"also warn/\S+trial001\.txt, warn/\S+trial002\.txt\)", same[0]), same
    assert once[0].endswith("once only (×3 in 3 tasks: also other/"
                            + str(tmp_path / "data" / "trial001.txt") + ", other/"
                            + str(tmp_path / "data" / "trial002.txt") + ")")
    assert "9 tasks: 0 hit, 9 computed, 0 failed, 0 skipped, 9 warning(s) in" in err
    p = cli_proc("run", cfg, "--store", tmp_path / "s", "--executor", executor)
    out, err = p.communicate(timeout=120)
    assert p.returncode == 0 and "warning" not in err  # hits: said when computed
