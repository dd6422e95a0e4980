"""Fixtures for engine tests: toy stages, temp number files and configs, stores, CLI runners."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import mocapflow.pipeline.testing  # noqa: F401  (registers the toy stages)
from mocapflow.pipeline.config import STAGE_MODULES_ENV, load_config
from mocapflow.pipeline.graph import build_graph
from mocapflow.pipeline.store import Store
from mocapflow.pipeline.testing import TOY_CONFIG, write_config, write_number_files


@pytest.fixture
def data_dir(tmp_path: Path) -> Path:
    """Five number files ``trial000.txt`` … ``trial004.txt`` (``i, i+1, …, i+4``)."""
    d = tmp_path / "data"
    write_number_files(d, 5)
    return d


@pytest.fixture
def toy_config(tmp_path: Path, data_dir: Path) -> Path:
    """The toy graph read → add → scale → total over ``data_dir/*.txt``."""
    return write_config(tmp_path / "toy.yaml", TOY_CONFIG, parts=f"{data_dir}/*.txt")


@pytest.fixture
def store(tmp_path: Path) -> Store:
    return Store(tmp_path / "store")


@pytest.fixture
def graph_of():
    """``graph_of(path, **load_config kwargs, targets=None)`` → Graph."""

    def make(path, targets=None, **kw):
        return build_graph(load_config(path, **kw), targets)

    return make


@pytest.fixture
def cli_env(monkeypatch) -> dict:
    """Environment in which the ``mocapflow`` command sees the toy stages."""
    monkeypatch.setenv(STAGE_MODULES_ENV, "mocapflow.pipeline.testing")
    env = dict(os.environ)
    env[STAGE_MODULES_ENV] = "mocapflow.pipeline.testing"
    return env


@pytest.fixture
def cli(cli_env, capsys):
    """Run ``mocapflow ARGS`` in-process: ``cli(*args) -> (exit code, stdout, stderr)``."""
    from mocapflow.pipeline.cli import main

    def call(*args):
        capsys.readouterr()
        code = main([str(a) for a in args])
        out, err = capsys.readouterr()
        return code, out, err

    return call


def mocapflow_cmd() -> list[str]:
    """The command line of the installed ``mocapflow`` script (same interpreter)."""
    return [sys.executable, "-m", "mocapflow"]


@pytest.fixture
def cli_proc(cli_env):
    """Run ``mocapflow ARGS`` as a subprocess (``subprocess.Popen`` kwargs pass through)."""

    def start(*args, **kw):
        return subprocess.Popen([*mocapflow_cmd(), *map(str, args)], env=cli_env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)

    return start
