"""Fixtures shared by the texture tests (Moradoff 2002)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.texture.synth import synth


def seeded_context(seed: int) -> Context:
    """A context whose ``rng`` is ``np.random.default_rng(seed)``.

    The engine's context derives its stream from the seed and the part id; the
    texture tests were written against the plain ``default_rng(seed)`` stream.
    """
    ctx = Context(seed=seed)
    ctx.rng = np.random.default_rng(seed)
    return ctx


@pytest.fixture
def run_synth():
    """``run_synth(pyramid, motion, seed=0, **params)``: the ``synth`` stage's outputs."""

    def run(pyramid, motion, seed: int = 0, **params):
        return synth(pyramid, motion, seed=seed, ctx=seeded_context(seed), **params)

    return run


# --------------------------------------------------------------------------- BVH export checks
# (shared with tests/stages/variation: native frame rate and units, issue 14)


def bvh_frame_time_text(path) -> str:
    """The text after ``Frame Time:`` in a BVH file, as written."""
    for line in Path(path).read_text().splitlines():
        if line.strip().startswith("Frame Time:"):
            return line.split(":", 1)[1].strip()
    raise AssertionError(f"{path}: no Frame Time line")


def bvh_frame_count(path) -> int:
    """The ``Frames:`` count of a BVH file."""
    for line in Path(path).read_text().splitlines():
        if line.strip().startswith("Frames:"):
            return int(line.split(":", 1)[1])
    raise AssertionError(f"{path}: no Frames line")


def bvh_skeleton_size(path) -> float:
    """Summed lengths of every ``OFFSET`` (joints and End Sites) of a BVH, in file units."""
    text = Path(path).read_text().split("MOTION", 1)[0]
    rows = [line.split()[1:4] for line in text.splitlines() if line.strip().startswith("OFFSET")]
    return float(np.linalg.norm(np.array(rows, dtype=np.float64), axis=1).sum())
