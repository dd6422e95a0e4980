"""Fixtures shared by the stage tests."""

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.motion.simulate.capture import capture_body, simulate_capture


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``<repo>/../shared/data`` (the public sample data); skips the test if absent."""
    path = (Path(__file__).resolve().parents[2] / ".." / "shared" / "data").resolve()
    if not path.is_dir():
        pytest.skip(f"shared sample data not found at {path}")
    return path


def simulated_capture(*, rng: int = 0, **params):
    """The ``simulate_capture`` stage on the generator ``default_rng(rng)``, plus its body.

    The tests were tuned on these streams; the returned namespace has the stage's
    outputs (``markers``, ``truth``, ``mesh``, ``motion``) and the simulated ``body``.
    """
    out = simulate_capture(**params, ctx=Context(rng=np.random.default_rng(rng)))
    body = capture_body(out["motion"], body_mesh=params.get("body_mesh"),
                        body_vertices=params.get("body_vertices", 3000))
    return SimpleNamespace(**out, body=body)


#: Measurement noise of the shared walk capture (metres, per axis).
WALK_CAPTURE_NOISE = 0.0003


@pytest.fixture(scope="session")
def sim():
    """A simulated 120-marker, 200-frame walk capture (noise ``WALK_CAPTURE_NOISE``)."""
    return simulated_capture(n_markers=120, n_frames=200, motion="walk", rng=0,
                             body_vertices=1500, noise=WALK_CAPTURE_NOISE)
