"""Fixtures shared across the test tree: the one full demo run the end-to-end tests share."""

from __future__ import annotations

import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest


@dataclass(frozen=True)
class DemoRun:
    """``mocapflow demo --out OUT -q`` run once (the README's command, local executor).

    Attributes
    ----------
    out : Path
        The demo folder; its store is ``out / "store"``.
    cmd : list of str
    proc : subprocess.CompletedProcess
    seconds : float
    """

    out: Path
    cmd: list[str]
    proc: subprocess.CompletedProcess
    seconds: float


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory) -> DemoRun:
    """The demo, run once per session (``tests/test_demo.py`` and the lock/frozen tests)."""
    out = tmp_path_factory.mktemp("demo") / "demo"
    cmd = [sys.executable, "-m", "mocapflow", "demo", "--out", str(out), "-q"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1200)
    return DemoRun(out=out, cmd=cmd, proc=proc, seconds=time.perf_counter() - t0)
