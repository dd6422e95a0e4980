"""Fixtures shared by the texture tests (Moradoff 2002)."""

from __future__ import annotations

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
