"""Shared helpers of the variation tests (Lau et al. 2009).

The sampling tests were tuned on generators ``numpy.random.default_rng(n)``: the
helpers run the ``sample`` and ``sample_noise`` stages on such a generator.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.motion.kinematics import forward_kinematics
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.variation.sample import sample, sample_noise

#: ``<repo>/../shared/data`` (the public sample data; tests using it skip when absent).
DATA = Path(__file__).resolve().parents[3] / ".." / "shared" / "data"

#: ``<repo>/configs``.
CONFIGS = Path(__file__).resolve().parents[3] / "configs"


def variants(model, rng: int, **params):
    """The ``sample`` stage's ``variants`` of ``model``, drawn from ``default_rng(rng)``."""
    return sample(model, **params, ctx=Context(rng=np.random.default_rng(rng)))["variants"]


def noise_variants(clips, rng: int, **params):
    """The ``sample_noise`` stage's ``variants`` of ``clips``, drawn from ``default_rng(rng)``."""
    return sample_noise(clips, **params, ctx=Context(rng=np.random.default_rng(rng)))["variants"]


def positions(m):
    """Joint positions ``(F, J, 3)`` of a motion (forward kinematics, no joint translations)."""
    return forward_kinematics(m.skeleton, m.rotations, m.root_position)[0]


@pytest.fixture(scope="module")
def walk():
    """A procedural walk of 8 s with natural cycle-to-cycle variation (gait events known)."""
    return procedural_walk(480, rate=60.0, seed=3, variation=0.05)
