"""Foot contacts and runs of frames, shared by every graph that plants feet.

* :func:`true_runs` — the runs of ``True`` in a boolean track (contacts,
  visible spans of a marker, holes);
* :func:`toe_indices`, :func:`foot_joint` — which joints are toes and feet;
* :func:`contact_thresholds`, :func:`foot_contacts` — contact frames of the
  toes (near the floor and slow), as used by texture synthesis, IK clean-up
  and the foot-skate metric.
"""

from __future__ import annotations

import re
from typing import Literal

import numpy as np

from mocapflow.stages.motion.datatypes import Skeleton

__all__ = [
    "contact_thresholds",
    "foot_contacts",
    "foot_joint",
    "horizontal_speed",
    "toe_indices",
    "true_runs",
]


def true_runs(mask: np.ndarray, *, min_length: int = 1) -> list[tuple[int, int]]:
    """Half-open ``(start, stop)`` runs of ``True`` in a boolean track.

    Parameters
    ----------
    mask : (F,) bool ndarray
    min_length : int
        Shorter runs are left out.

    Returns
    -------
    list of (int, int)
        ``mask[start:stop]`` is all ``True`` and maximal; Python ints, in order.
    """
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    starts, stops = np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()
    return [(a, b) for a, b in zip(starts, stops) if b - a >= min_length]


def toe_indices(skeleton) -> list[int]:
    """Indices of the toe joints (names containing ``toe``; else the feet).

    Parameters
    ----------
    skeleton : Skeleton

    Returns
    -------
    list of int
        Joint indices; ``ValueError`` when the skeleton has neither toes nor feet.
    """
    names = [n.lower() for n in skeleton.names]
    toes = [i for i, n in enumerate(names) if "toe" in n and "end" not in n]
    if not toes:
        toes = [i for i, n in enumerate(names) if "foot" in n or "ankle" in n]
    if not toes:
        raise ValueError(
            f"skeleton has no joint named like a toe or foot (joints: {skeleton.names})"
        )
    return toes


def contact_thresholds(
    positions: np.ndarray,
    toe_indices: list[int] | np.ndarray,
    rate: float,
    *,
    up_axis: int = 1,
) -> tuple[float, float]:
    """Default contact thresholds estimated from a reference motion.

    Parameters
    ----------
    positions : (F, J, 3) float ndarray
        Global joint positions, metres.
    toe_indices : sequence of int
    rate : float
    up_axis : int

    Returns
    -------
    height_threshold : float
        Floor (5th percentile of toe height) + 5 cm.
    speed_threshold : float
        The larger of 0.5 m/s and the median horizontal toe speed.
    """
    toes = np.asarray(positions, dtype=np.float64)[:, list(toe_indices)]
    h = toes[..., up_axis]
    height = float(np.percentile(h, 5.0)) + 0.05
    speed = horizontal_speed(toes, rate, up_axis)
    return height, max(0.5, float(np.nanmedian(speed)))


def horizontal_speed(toes: np.ndarray, rate: float, up_axis: int) -> np.ndarray:
    """``(F, T)`` horizontal speed (central differences, one-sided at the ends)."""
    horiz = [a for a in range(3) if a != up_axis]
    xy = toes[..., horiz]
    if xy.shape[0] < 2:
        return np.zeros(xy.shape[:2])
    v = np.gradient(xy, axis=0) * rate
    return np.linalg.norm(v, axis=-1)


def foot_contacts(
    positions: np.ndarray,
    toe_indices: list[int] | np.ndarray,
    rate: float,
    *,
    height_threshold: float | None = None,
    speed_threshold: float | None = None,
    up_axis: int = 1,
) -> np.ndarray:
    """Contact frames of each toe: near the floor and slow.

    Parameters
    ----------
    positions : (F, J, 3) float ndarray
        Global joint positions, metres.
    toe_indices : sequence of int
        ``T`` toe joints.
    rate : float
    height_threshold : float, optional
        Toe height (along ``up_axis``) below which the toe may be in contact;
        default from :func:`contact_thresholds`.
    speed_threshold : float, optional
        Horizontal speed (m/s) below which it may be in contact.
    up_axis : int

    Returns
    -------
    (F, T) bool ndarray
    """
    positions = np.asarray(positions, dtype=np.float64)
    dh, ds = contact_thresholds(positions, toe_indices, rate, up_axis=up_axis)
    h_thr = dh if height_threshold is None else float(height_threshold)
    s_thr = ds if speed_threshold is None else float(speed_threshold)
    toes = positions[:, list(toe_indices)]
    speed = horizontal_speed(toes, rate, up_axis)
    return (toes[..., up_axis] < h_thr) & (speed < s_thr)


_FOOT_NAMES = ("foot", "ankle")
#: A side before the name (``LeftFoot``, ``l_ankle``, ``lfoot``) or after it behind a
#: separator (Bandai-Namco's ``Foot_L``, Blender's ``foot.L``, ``Foot Left``), the
#: namespace of a rig (``mixamorig:``) dropped.
_SIDE_FIRST = re.compile(r"(?P<side>left|right|l|r)[_.\- ]?(?P<stem>.+)")
_SIDE_LAST = re.compile(r"(?P<stem>.+?)(?:[_.\- ](?P<s1>l|r)|[_.\- ]?(?P<s2>left|right))")


def _sided_names(name: str) -> list[tuple[str, str]]:
    """``(side, stem)`` readings of a joint name (side ``"left"``/``"right"``), of the
    whole name and of each tail after a separator (3ds Max's ``Bip01 L Foot``,
    ``Character1_LeftFoot``)."""
    low = name.lower().rsplit(":", 1)[-1]
    tails = [low] + [low[m.end():] for m in re.finditer(r"[_.\- ]", low) if m.end() < len(low)]
    out = []
    for tail in tails:
        if m := _SIDE_FIRST.fullmatch(tail):
            out.append((m["side"], m["stem"]))
        if m := _SIDE_LAST.fullmatch(tail):
            out.append((m["s1"] or m["s2"], m["stem"]))
    return [("left" if side[0] == "l" else "right", stem) for side, stem in out]


def foot_joint(skeleton: Skeleton, side: Literal["left", "right"] = "left") -> int:
    """Index of the ankle/foot joint of one side.

    Parameters
    ----------
    skeleton : Skeleton
    side : {"left", "right"}

    Returns
    -------
    int
        ``-1`` when no joint is named like a foot or ankle of that side
        (``LeftFoot``, ``LeftAnkle``, ``lfoot``, ``l_ankle``, ``Foot_L``, ``foot.L``,
        ``mixamorig:LeftFoot``, ``Bip01 L Foot``...; not a toe or an end joint).
    """
    for j, n in enumerate(skeleton.names):
        low = n.lower()
        if "toe" in low or "end" in low:
            continue
        for s, stem in _sided_names(n):
            if s == side and stem.startswith(_FOOT_NAMES):
                return j
    return -1
