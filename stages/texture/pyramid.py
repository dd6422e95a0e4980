"""Gaussian multi-resolution tree of a motion (Moradoff 2002, §3.4).

Every level halves the frame count: node ``k`` of level ``l + 1`` is the
weighted average of the ``filter_size`` nodes ``2k - filter_size/2 + 1 …
2k + filter_size/2`` of level ``l`` (binomial weights, edges clamped), so its
children are ``2k`` and ``2k + 1`` and it stands for the fine frames
``[k 2^(l+1), (k+1) 2^(l+1))``.

Per level the tree keeps the joint-angle representation the synthesis copies
and the 3-D representation it compares:

* ``rotations`` — local joint rotations; the root keeps its rotation with the
  heading (the twist about the up axis ``y``) removed.  Filtering is
  quaternion-aware (signs aligned to the centre tap, weighted sum, normalised).
* ``yaw_rate`` — heading change per fine frame (radians), ``velocity`` — root
  horizontal displacement per fine frame in the heading frame ``(x, z)``,
  ``height`` — root height: the root as a translation velocity.
* ``positions`` — forward kinematics of the heading-free pose with the root at
  ``(0, height, 0)``: the 3-D pose representation of the level.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from math import comb
from typing import Any

import numpy as np

from mocapflow.pipeline import Context, stage
from mocapflow.pipeline.codecs import Encoded, codec, component_coords
from mocapflow.stages.motion.datatypes import Motion, Skeleton
from mocapflow.stages.motion.kinematics import forward_kinematics, reorient_motion
from mocapflow.stages.motion.rotations import (
    heading_split,
    quat_continuity,
    quat_rotate,
    yaw_quaternion,
)
from mocapflow.stages.texture.smoothing import _row_sum

__all__ = [
    "LEVELS_AT_30",
    "MIN_COARSE_NODES",
    "Pyramid",
    "PyramidError",
    "PyramidLevel",
    "binomial_filter",
    "build_pyramid",
    "downsample",
    "downsample_quaternions",
    "level_positions",
    "levels_for_rate",
    "pyramid",
    "root_features",
]

#: The coarsest level must keep at least this many nodes (room for ±3 slots).
MIN_COARSE_NODES = 8

#: Levels of the default pyramid at 30 fps (the thesis used 3–5); one more per doubling.
LEVELS_AT_30 = 4


class PyramidError(ValueError):
    """The motion cannot be turned into the requested pyramid."""


# --------------------------------------------------------------------------- data type


@dataclass(eq=False)
class PyramidLevel:
    """One level of the multi-resolution tree.

    Parameters
    ----------
    rotations : (n, J, 4) float ndarray
        Local joint rotations, root heading removed.
    yaw_rate : (n,) float ndarray
        Heading change per fine frame, radians.
    velocity : (n, 2) float ndarray
        Root horizontal displacement per fine frame in the heading frame ``(x, z)``, metres.
    height : (n,) float ndarray
        Root height, metres.
    positions : (n, J, 3) float ndarray
        Forward kinematics of the heading-free pose, root at ``(0, height, 0)``.
    translations : (n, J, 3) float ndarray, optional
        Filtered per-frame joint translations when the motion has them.
    """

    rotations: np.ndarray
    yaw_rate: np.ndarray
    velocity: np.ndarray
    height: np.ndarray
    positions: np.ndarray
    translations: np.ndarray | None = None

    @property
    def n_nodes(self) -> int:
        """Number of nodes ``n`` of the level."""
        return self.rotations.shape[0]


@dataclass(eq=False)
class Pyramid:
    """Gaussian multi-resolution tree of one motion (level 0 = the input frames).

    Parameters
    ----------
    levels : list of PyramidLevel
        Finest first.
    filter_size : int
        Taps of the binomial filter between levels.
    rate : float
        Frames per second of level 0.
    attrs : dict
        ``n_frames``, source.
    """

    levels: list[PyramidLevel]
    filter_size: int
    rate: float
    attrs: dict[str, Any] = field(default_factory=dict)

    @property
    def n_levels(self) -> int:
        """Number of levels."""
        return len(self.levels)

    def __repr__(self) -> str:
        """One line: levels and their node counts, joints, rate, filter taps."""
        nodes = [lev.n_nodes for lev in self.levels]
        shown = "/".join(map(str, nodes[:6])) + ("/…" if len(nodes) > 6 else "")
        J = self.levels[0].rotations.shape[1] if self.levels else 0
        return (f"Pyramid({len(nodes)} levels of {shown} nodes × {J} joints "
                f"@ {float(self.rate):.4g} Hz, {self.filter_size}-tap filter)")

    @property
    def n_frames(self) -> int:
        """Frames of level 0."""
        return self.levels[0].n_nodes


_LEVEL_FIELDS = {
    "rotations": ("joint", "wxyz"),
    "yaw_rate": (),
    "velocity": ("xz",),
    "height": (),
    "positions": ("joint", "xyz"),
    "translations": ("joint", "xyz"),
}


def _encode_pyramid(p: Pyramid) -> Encoded:
    arrays = {}
    for l, lev in enumerate(p.levels):
        for name, tail in _LEVEL_FIELDS.items():
            a = getattr(lev, name)
            if a is not None:
                arrays[f"l{l}_{name}"] = (a, (f"node_l{l}",) + tail)
    return Encoded(
        "pyramid",
        arrays,
        {"n_levels": p.n_levels, "filter_size": p.filter_size, "rate": p.rate, "attrs": p.attrs},
        component_coords("xyz", "wxyz", "xz"),
    )


def _decode_pyramid(e: Encoded) -> Pyramid:
    a = e.attrs
    levels = []
    for l in range(int(a["n_levels"])):
        kw = {
            name: e.arrays[f"l{l}_{name}"][0]
            for name in _LEVEL_FIELDS
            if f"l{l}_{name}" in e.arrays
        }
        levels.append(PyramidLevel(**kw))
    return Pyramid(levels, int(a["filter_size"]), float(a["rate"]), a.get("attrs", {}))


codec("pyramid", encode=_encode_pyramid, decode=_decode_pyramid)(Pyramid)


# --------------------------------------------------------------------------- filtering


def binomial_filter(filter_size: int) -> np.ndarray:
    """Binomial (discrete Gaussian) weights.

    Parameters
    ----------
    filter_size : int
        Number of taps, even and ``>= 2`` (4: ``[1, 3, 3, 1] / 8``).

    Returns
    -------
    (filter_size,) float ndarray
        Sums to 1.
    """
    if filter_size < 2 or filter_size % 2:
        raise PyramidError(f"filter_size must be even and >= 2, got {filter_size}")
    w = np.array([comb(filter_size - 1, k) for k in range(filter_size)], dtype=np.float64)
    return w / w.sum()


def _taps(n: int, filter_size: int) -> np.ndarray:
    """``(ceil(n/2), filter_size)`` source indices of each coarse node (edges clamped)."""
    k = np.arange((n + 1) // 2)
    off = np.arange(filter_size) - (filter_size // 2 - 1)
    return np.clip(2 * k[:, None] + off[None, :], 0, n - 1)


def downsample(x: np.ndarray, filter_size: int = 4) -> np.ndarray:
    """One level of the Gaussian pyramid for a linear signal.

    Parameters
    ----------
    x : (n, ...) float ndarray
    filter_size : int

    Returns
    -------
    (ceil(n / 2), ...) float ndarray
    """
    x = np.asarray(x, dtype=np.float64)
    w = binomial_filter(filter_size)
    return np.einsum("kf...,f->k...", x[_taps(x.shape[0], filter_size)], w)


def downsample_quaternions(q: np.ndarray, filter_size: int = 4) -> np.ndarray:
    """One pyramid level for unit quaternions.

    Each tap is sign-aligned with the centre-left tap (``2k``), the weighted sum
    is normalised (the chordal mean, within 1e-3 rad of the geodesic mean for
    neighbouring frames).

    Parameters
    ----------
    q : (n, ..., 4) float ndarray
    filter_size : int

    Returns
    -------
    (ceil(n / 2), ..., 4) float ndarray
    """
    q = np.asarray(q, dtype=np.float64)
    w = binomial_filter(filter_size)
    taps = q[_taps(q.shape[0], filter_size)]  # (k, f, ..., 4)
    ref = taps[:, filter_size // 2 - 1 : filter_size // 2]
    sign = np.where(_row_sum(taps * ref) < 0, -1.0, 1.0)  # (np.sum's values)
    s = np.einsum("kf...,f->k...", taps * sign, w)
    return s / np.sqrt(_row_sum(s * s))  # (np.linalg.norm's values)


# --------------------------------------------------------------------------- root


def root_features(
    root_position: np.ndarray, heading: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Root trajectory as velocities in the heading frame.

    Parameters
    ----------
    root_position : (F, 3) float ndarray
    heading : (F,) float ndarray
        Unwrapped heading, radians.

    Returns
    -------
    yaw_rate : (F,) float ndarray
        ``heading[t+1] - heading[t]`` (last frame repeats the previous value).
    velocity : (F, 2) float ndarray
        ``(x, z)`` of ``R_y(-heading[t]) (p[t+1] - p[t])``.
    height : (F,) float ndarray
    """
    p = np.asarray(root_position, dtype=np.float64)
    F = p.shape[0]
    if F < 2:
        return np.zeros(F), np.zeros((F, 2)), p[:, 1].copy()
    dp = np.diff(p, axis=0)
    dp[:, 1] = 0.0
    local = quat_rotate(yaw_quaternion(-heading[:-1]), dp)
    yaw = np.diff(heading)
    vel = local[:, [0, 2]]
    return np.append(yaw, yaw[-1]), np.vstack([vel, vel[-1:]]), p[:, 1].copy()


def level_positions(
    skeleton: Skeleton,
    rotations: np.ndarray,
    height: np.ndarray,
    translations: np.ndarray | None = None,
) -> np.ndarray:
    """FK of heading-free poses with the root at ``(0, height, 0)``.

    Parameters
    ----------
    skeleton : Skeleton
    rotations : (n, J, 4) float ndarray
    height : (n,) float ndarray
    translations : (n, J, 3) float ndarray, optional

    Returns
    -------
    (n, J, 3) float ndarray
    """
    root = np.zeros((rotations.shape[0], 3))
    root[:, 1] = height
    pos, _ = forward_kinematics(skeleton, rotations, root, translations=translations)
    return pos


# --------------------------------------------------------------------------- building


def levels_for_rate(rate: float, n_frames: int | None = None) -> int:
    """Pyramid levels by frame rate: the coarsest node spans the same time at any rate.

    :data:`LEVELS_AT_30` at 30 fps and one more per doubling of the rate (rounded:
    6 at 120 fps, 3 at 15 fps; at least 2), so a 120 fps take is synthesized with
    the 30 fps take's coarse plan instead of four times as many coarsest nodes.

    Parameters
    ----------
    rate : float
        Frames per second of the motion (> 0).
    n_frames : int, optional
        Frames of the motion: the levels are capped so the coarsest level keeps
        :data:`MIN_COARSE_NODES` nodes (at least 1 level).

    Returns
    -------
    int
    """
    if not (np.isfinite(rate) and rate > 0):
        raise PyramidError(f"rate must be a positive number of frames per second, got {rate}")
    levels = max(2, LEVELS_AT_30 + int(round(np.log2(rate / 30.0))))
    if n_frames is not None:
        while levels > 1 and -(-n_frames // 2 ** (levels - 1)) < MIN_COARSE_NODES:
            levels -= 1
    return levels


def build_pyramid(
    motion: Motion, *, levels: int | None = None, filter_size: int = 4
) -> Pyramid:
    """Gaussian multi-resolution tree of a motion.

    Parameters
    ----------
    motion : Motion
        ``F`` frames; ``y`` is up.
    levels : int, optional
        Number of levels including the input (the thesis used 3–5).  ``None``
        (default): by the motion's rate, :func:`levels_for_rate` (4 at 30 fps, 6 at
        120 fps; fewer when the motion is too short for them).
    filter_size : int
        Binomial filter taps (4).

    Returns
    -------
    Pyramid

    Raises
    ------
    PyramidError
        Fewer than 1 level, a bad filter size, or a coarsest level with fewer
        than :data:`MIN_COARSE_NODES` nodes.
    """
    F = motion.n_frames
    if levels is None:
        levels = levels_for_rate(motion.rate, F)
    if levels < 1:
        raise PyramidError(f"levels must be >= 1, got {levels}")
    binomial_filter(filter_size)
    coarse = -(-F // 2 ** (levels - 1))
    if coarse < MIN_COARSE_NODES:
        if F < MIN_COARSE_NODES:
            raise PyramidError(
                f"motion of {F} frames is too short to synthesize from: it needs at least "
                f"{MIN_COARSE_NODES} frames at the synthesis rate ({motion.rate:g} fps: "
                f"{MIN_COARSE_NODES / motion.rate:.2f} s)"
            )
        usable = levels - 1
        while usable > 1 and -(-F // 2 ** (usable - 1)) < MIN_COARSE_NODES:
            usable -= 1
        raise PyramidError(
            f"motion of {F} frames is too short for {levels} levels: the coarsest level "
            f"would have {coarse} nodes (need >= {MIN_COARSE_NODES}); use at most "
            f"{usable} level{'s' if usable > 1 else ''}"
        )
    rot = np.array(motion.rotations, dtype=np.float64)
    heading, rot[:, 0] = heading_split(rot[:, 0])
    rot = quat_continuity(rot, axis=0)
    yaw, vel, height = root_features(motion.root_position, heading)
    trans = motion.translations
    tree = []
    for l in range(levels):
        if l:
            rot = downsample_quaternions(rot, filter_size)
            yaw, vel, height = (downsample(a, filter_size) for a in (yaw, vel, height))
            trans = None if trans is None else downsample(trans, filter_size)
        tree.append((rot, yaw, vel, height, trans))
    # the poses of every level in one forward kinematics (frame by frame, so the same
    # positions as one call per level), cut back into levels
    pos = level_positions(motion.skeleton, np.concatenate([t[0] for t in tree]),
                          np.concatenate([t[3] for t in tree]),
                          None if trans is None else np.concatenate([t[4] for t in tree]))
    cuts = np.cumsum([t[0].shape[0] for t in tree])[:-1]
    out = [PyramidLevel(r, y, v, h, p.copy(), tr)
           for (r, y, v, h, tr), p in zip(tree, np.split(pos, cuts))]
    attrs = {"n_frames": F, "source": motion.attrs.get("source", motion.attrs.get("path"))}
    return Pyramid(out, filter_size, motion.rate, attrs)


@stage("pyramid", outputs=("pyramid",))
def pyramid(
    motion: Motion, *, levels: int | None = None, filter_size: int = 4, ctx: Context
) -> dict[str, Pyramid]:
    """Gaussian multi-resolution tree over the joint angles (Moradoff §3.4).

    Parameters
    ----------
    motion : Motion
        Input textural motion (``F`` frames); one in other axes (``attrs["up"]``,
        ``["forward"]``) is first turned to Y up, facing +Z
        (:func:`~mocapflow.stages.motion.kinematics.reorient_motion`), the axes
        the synthesis works in.
    levels : int, optional
        Levels including the input (the thesis used 3–5).  ``None`` (default): by
        the motion's rate — 4 at 30 fps, one more per doubling (6 at 120 fps), fewer
        when the motion is too short (:func:`levels_for_rate`); the synthesis then
        plans at the same time scale at any rate.
    filter_size : int
        Binomial filter taps between levels (4).
    ctx : Context

    Returns
    -------
    dict
        ``pyramid``: :class:`Pyramid`.
    """
    return {"pyramid": build_pyramid(reorient_motion(motion), levels=levels,
                                     filter_size=filter_size)}
