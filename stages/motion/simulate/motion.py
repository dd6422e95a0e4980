"""Procedural motion stages: ``simulate_walk`` and ``simulate_range_of_motion``.

Both draw everything random from ``ctx.rng``:

* ``simulate_walk`` — :func:`~mocapflow.stages.motion.simulate.gait.procedural_walk`
  (walk / run cycles with cycle-to-cycle variation);
* ``simulate_range_of_motion`` —
  :func:`~mocapflow.stages.motion.simulate.range_of_motion.procedural_range_of_motion`
  (joint groups flexed in turn);

both on :func:`~mocapflow.stages.motion.simulate.skeleton.procedural_skeleton`.
"""

from __future__ import annotations

from typing import Literal

from mocapflow.pipeline import Context, stage
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.motion.simulate.range_of_motion import procedural_range_of_motion

__all__ = ["simulate_range_of_motion", "simulate_walk"]


@stage("simulate_walk", outputs=("motion",))
def simulate_walk(
    *,
    n_frames: int = 600,
    rate: float = 120.0,
    gait: Literal["walk", "run"] = "walk",
    speed: float | None = None,
    variation: float = 0.05,
    seed: int = 0,
    ctx: Context,
) -> dict:
    """Procedural walk or run with cycle-to-cycle variation (see :func:`procedural_walk`).

    Parameters
    ----------
    n_frames : int
        Frames to generate.
    rate : float
        Frames per second (Hz).
    gait : {"walk", "run"}
        Walking or running.
    speed : float, optional
        Mean forward speed in m/s (default 1.3 walking, 3.2 running).
    variation : float
        Relative standard deviation of the per-cycle period and speed (0: exactly
        periodic).
    seed : int
        Seeds ``ctx.rng``, the only source of randomness.
    ctx : Context

    Returns
    -------
    dict
        ``{"motion": Motion}``.
    """
    motion = procedural_walk(
        n_frames, rate=rate, gait=gait, speed=speed, seed=ctx.rng, variation=variation
    )
    motion.attrs["seed"] = int(seed)
    return {"motion": motion}


@stage("simulate_range_of_motion", outputs=("motion",))
def simulate_range_of_motion(
    *, n_frames: int = 1200, rate: float = 120.0, seed: int = 0, ctx: Context
) -> dict:
    """Joint groups flexed through their range in turn (see :func:`procedural_range_of_motion`).

    Parameters
    ----------
    n_frames : int
        Frames to generate.
    rate : float
        Frames per second (Hz).
    seed : int
        Seeds ``ctx.rng``.
    ctx : Context

    Returns
    -------
    dict
        ``{"motion": Motion}``.
    """
    motion = procedural_range_of_motion(n_frames, rate=rate, seed=ctx.rng)
    motion.attrs["seed"] = int(seed)
    return {"motion": motion}
