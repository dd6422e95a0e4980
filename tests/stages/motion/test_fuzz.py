"""The quick subset of ``benchmarks/fuzz.py``: mutated and hostile files through ``mocapflow run``.

Every case runs in a child of a fresh ``benchmarks/fuzz.py --quick`` process (it forks,
so it must not be this multi-threaded pytest process) under a 1 GiB address-space limit
and a 10 s timeout; the whole suite is ``python benchmarks/fuzz.py``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from .conftest import FUZZ


@pytest.fixture(scope="module")
def quick(shared_data, tmp_path_factory):
    out = tmp_path_factory.mktemp("fuzz") / "outcomes.json"
    proc = subprocess.run(
        [sys.executable, str(FUZZ), "--quick", "--json", str(out)],
        capture_output=True, text=True, timeout=600,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"},
    )
    assert out.is_file(), proc.stderr[-2000:]
    return proc, {o["name"].split(" ")[0]: o for o in json.loads(out.read_text())}


def test_quick_fuzz_every_case_is_read_sanely_or_refused_in_one_typed_line(quick):
    proc, outcomes = quick
    bad = {k: (o["outcome"], o["message"]) for k, o in outcomes.items()
           if o["outcome"] not in ("accepted", "rejected")}
    assert not bad, bad
    assert proc.returncode == 0, proc.stdout[-2000:]
    kinds = [o["kind"] for o in outcomes.values()]
    assert kinds.count("c3d") >= 15 and kinds.count("bvh") >= 12
    assert max(o["seconds"] for o in outcomes.values()) < 10
    assert max(o["rss_mib"] for o in outcomes.values()) < 1024
    assert "| total |" in proc.stdout


@pytest.mark.parametrize(("case", "outcome", "text"), [
    # the issue's files: each was a MemoryError, a RecursionError, an unencodable label
    # in store.commit, an ezc3d crash or exception, or was accepted
    ("bvh-built-nine_lines", "rejected", "'Frames: 2000000000' but only 0 lines"),
    ("bvh-built-nine_lines_channels", "rejected", "'Frames: 2000000000'"),
    ("bvh-built-frames_zero", "rejected", "Frames: 0: a BVH motion needs at least one frame"),
    ("bvh-built-frame_time_1e6_resampled", "rejected", "IngestError: take.bvh: rate: resampling"),
    ("bvh-built-rate_huge", "rejected", "IngestError"),
    ("bvh-built-deep_5000", "rejected", "the hierarchy nests deeper than 256 joints"),
    ("bvh-built-deep_20000", "rejected", "nests deeper than 256"),
    ("bvh-built-deep_256", "accepted", "read ok"),
    ("bvh-built-wide_5000", "accepted", "read ok"),
    ("bvh-built-unit_huge", "rejected", "OFFSET values too large"),
    ("c3d-built-label_not_utf8", "rejected", r"POINT:LABELS entry 2 is not UTF-8: b'\xff\xe4BB'"),
    ("c3d-built-label_duplicate", "accepted", "read ok"),
    ("c3d-built-char_param_no_dims", "rejected", "POINT:USED: character data without dim"),
    ("c3d-built-description_length_200", "rejected", "description length 200"),
    ("c3d-built-frames_float", "rejected", "POINT:FRAMES is stored as float data"),
    ("c3d-built-frames_65535", "rejected", "65535 frames of 5 points"),
    ("c3d-built-analog_rate_1e30", "rejected", "ANALOG:RATE 1e+30 / POINT:RATE 120"),
    ("c3d-built-coordinate_inf", "rejected", "POINT data: point 'M000' is inf m"),
    ("c3d-built-processor_mips", "rejected", "processor type 86"),
])
def test_quick_fuzz_issue_cases(quick, case, outcome, text):
    o = quick[1][case]
    assert (o["outcome"], text in o["message"]) == (outcome, True), o["message"]


def test_classifier_flags_what_is_not_a_clean_rejection(fuzz, tmp_path):
    """Untyped errors, missing fields, several lines, tracebacks, signals, MemoryError."""
    case = fuzz.Case(name="x", kind="bvh", part="take.bvh")
    path = f"{tmp_path}/take.bvh"
    head = "mocapflow: error: 1 task(s) failed: ingest/take.bvh: "
    lines = {
        f"{head}BVHError: {path}:3: OFFSET of joint 'A' is not finite": ("rejected", 1 << 8),
        f"{head}ValueError: {path}:3: OFFSET of joint 'A' is not finite": ("unclear", 1 << 8),
        f"{head}BVHError: {path}:3: something is wrong": ("unclear", 1 << 8),
        f"{head}BVHError: elsewhere.bvh:3: OFFSET is bad": ("unclear", 1 << 8),
        f"warning: a\nRuntimeWarning: overflow\n{head}BVHError: {path}: Frames: 0": ("unclear",
                                                                                   1 << 8),
        "Traceback (most recent call last):\n  x\nRecursionError: deep": ("traceback", 1 << 8),
        f"{head}MemoryError: Unable to allocate 44.7 GiB": ("over-memory", 1 << 8),
        "": ("crash", 11),  # SIGSEGV
        "mocapflow: error: odd": ("crash", 70 << 8),
    }
    for text, (want, status) in lines.items():
        (tmp_path / "stderr").write_text(text + "\n")
        got, _ = fuzz._classify(case, tmp_path, status, 1024, 100.0)
        assert got == want, text
    (tmp_path / "stderr").write_text("")
    (tmp_path / "sanity.json").write_text('["motion: non-finite values"]')
    assert fuzz._classify(case, tmp_path, 0, 1024, 100.0)[0] == "insane"
    assert fuzz._classify(case, tmp_path, 0, 1024, 2000.0)[0] == "over-memory"
