"""Fixtures of the motion tests: the fuzz benchmark's mutators and runner as a module."""

import importlib.util
import sys
from pathlib import Path

import pytest

FUZZ = Path(__file__).resolve().parents[3] / "benchmarks" / "fuzz.py"


@pytest.fixture(scope="session")
def fuzz():
    """``benchmarks/fuzz.py`` imported (its C3D entry walker, sources and classifier)."""
    spec = importlib.util.spec_from_file_location("mocapflow_fuzz", FUZZ)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod
