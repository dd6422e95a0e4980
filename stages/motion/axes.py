"""The up axis and the facing direction of a capture: parsed, detected, turned into bases.

Capture labs record Z-up (Vicon, Qualisys: the floor is the XY plane), animation
tools Y-up (BVH, Blender's importers, Maya).  Nothing downstream assumes either:
ingest stores the axes of the data in ``attrs["up"]`` and ``attrs["forward"]``
(signed axis names such as ``"+z"``, with ``attrs["axes_source"]`` saying where
they came from), and the stages that need them (the renderer's camera, the
template fit) read them from there.

* :func:`parse_axis`: ``"z"``, ``"+Z"``, ``"-y"`` ... -> ``"+z"`` / ``"-y"``;
* :func:`axis_vector`: the unit vector of a signed axis;
* :func:`detect_up`: from C3D ``POINT:Y_SCREEN`` (the axis pointing up on the
  screen) checked against the data, else from the data alone: the axis along
  which the body is tallest frame by frame (its long axis over the trial), signed
  by the floor (the lowest markers sit near the lab's ground plane at 0);
* :func:`detect_forward`: the horizontal direction the body faces, from
  front/back landmark pairs (Plug-in-Gait ``ASI``/``PSI``, ``FHD``/``BHD``), else
  from the direction of travel, else the body's thin horizontal axis;
* :func:`frame_basis`: the rotation from the Y-up, +Z-facing convention (BVH,
  CMU, our simulators and templates) to given axes.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = [
    "AXES",
    "AxisError",
    "axis_vector",
    "data_axes",
    "detect_forward",
    "detect_up",
    "frame_basis",
    "parse_axis",
]

#: The signed axis names stored in ``attrs["up"]`` / ``attrs["forward"]``.
AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
_AXIS_RE = re.compile(r"^\s*([+-]?)\s*([xyz])\s*$", re.IGNORECASE)
#: Front / back landmark name pairs (Plug-in-Gait and common full-body sets).
_FRONT_BACK = (("ASI", "PSI"), ("FHD", "BHD"), ("STRN", "T10"), ("CLAV", "C7"))


class AxisError(ValueError):
    """An axis value that is not one of ``x, y, z`` with an optional sign."""


def parse_axis(value: Any, *, name: str = "axis") -> str:
    """A signed axis name: ``"z"`` / ``"+Z"`` -> ``"+z"``, ``"-y"`` -> ``"-y"``.

    Parameters
    ----------
    value : str
    name : str
        What the value is, for the error message.

    Returns
    -------
    str
        One of :data:`AXES`.

    Raises
    ------
    AxisError
        Anything else.
    """
    m = _AXIS_RE.match(str(value)) if isinstance(value, str) else None
    if m is None:
        raise AxisError(f"{name}: expected x, y or z with an optional sign (e.g. +z, -y), "
                        f"got {value!r}")
    return f"{m.group(1) or '+'}{m.group(2).lower()}"


def axis_vector(axis: str) -> np.ndarray:
    """Unit vector ``(3,)`` of a signed axis name (see :func:`parse_axis`)."""
    a = parse_axis(axis)
    v = np.zeros(3)
    v["xyz".index(a[1])] = 1.0 if a[0] == "+" else -1.0
    return v


def _per_frame_bounds(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median over frames of the 2nd / 98th percentile of the visible markers, per axis."""
    P = positions.reshape(positions.shape[0], -1, 3)
    ok = np.isfinite(P).all(-1).sum(1) >= 3
    if not ok.any():
        return np.full(3, np.nan), np.full(3, np.nan)
    P = P[ok]
    with np.errstate(all="ignore"):
        lo = np.nanpercentile(P, 2, axis=1)
        hi = np.nanpercentile(P, 98, axis=1)
    return np.median(lo, axis=0), np.median(hi, axis=0)


def _floor_sign(lo: float, hi: float) -> int:
    """+1 / -1 when the ground plane (coordinate 0) bounds the body from below / above
    along this axis (within a fifth of its extent), 0 when the data does not say."""
    ext = hi - lo
    if not ext > 0:
        return 0
    if abs(lo) <= 0.2 * ext and hi > 0:
        return 1
    if abs(hi) <= 0.2 * ext and lo < 0:
        return -1
    return 0


def data_axes(positions: np.ndarray) -> dict[str, Any]:
    """What the data says of the up axis.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        Marker positions (NaN where missing), any unit.

    Returns
    -------
    dict
        ``extent`` (median per-frame extent per axis), ``long_axis`` (index of
        the largest), ``long_ratio`` (largest / second largest), ``floor_sign``
        per axis (+1, -1 or 0: see :func:`_floor_sign`).
    """
    lo, hi = _per_frame_bounds(positions)
    ext = hi - lo
    if not np.isfinite(ext).all():
        return {"extent": None, "long_axis": None, "long_ratio": None, "floor_sign": [0, 0, 0]}
    order = np.argsort(ext)[::-1]
    return {
        "extent": [float(e) for e in ext],
        "long_axis": int(order[0]),
        "long_ratio": float(ext[order[0]] / max(ext[order[1]], 1e-12)),
        "floor_sign": [_floor_sign(float(a), float(b)) for a, b in zip(lo, hi)],
    }


def detect_up(
    positions: np.ndarray, *, y_screen: str | None = None, up: str = "auto"
) -> tuple[str, dict[str, Any]]:
    """The up axis of a capture.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        Marker positions (NaN where missing).
    y_screen : str, optional
        C3D ``POINT:Y_SCREEN`` (e.g. ``"+Z"``): the axis the file says points up.
    up : str
        ``"auto"``, or an axis (``x``, ``+z``, ``-y`` ...) that is used as given.

    Returns
    -------
    up : str
        One of :data:`AXES`.
    evidence : dict
        ``source`` (``"param"``, ``"parameters"``, ``"parameters+floor"`` when the
        floor overrode the file's sign, ``"data"``, ``"default"``), ``confidence``
        (``"high"`` / ``"low"``), ``y_screen``, what the data says
        (:func:`data_axes`) and a ``note`` when the file and the data disagree.
    """
    if up != "auto":
        return parse_axis(up, name="up"), {"source": "param", "confidence": "high"}
    d = data_axes(positions)
    ev: dict[str, Any] = {"y_screen": y_screen, "data": d}
    screen = None
    if y_screen:
        try:
            screen = parse_axis(y_screen)
        except AxisError:
            ev["note"] = f"POINT:Y_SCREEN {y_screen!r} is not an axis; ignored"
    if screen is not None:
        k = "xyz".index(screen[1])
        floor = d["floor_sign"][k]
        sign = screen[0]
        source = "parameters"
        if floor and (floor > 0) != (sign == "+"):
            sign = "+" if floor > 0 else "-"
            source = "parameters+floor"
            ev["note"] = (f"POINT:Y_SCREEN says {y_screen}, but the floor (coordinate 0) is "
                          f"below the body along {sign}{screen[1]}: using {sign}{screen[1]}")
        if d["long_axis"] is not None and d["long_axis"] != k and d["long_ratio"] > 1.5:
            ev["note"] = (ev.get("note", "") + "; " if ev.get("note") else "") + (
                f"the body is tallest along {'xyz'[d['long_axis']]}, not {screen[1]}")
        ev.update(source=source, confidence="high")
        return f"{sign}{screen[1]}", ev
    if d["long_axis"] is None:
        ev.update(source="default", confidence="low")
        return "+y", ev
    k = d["long_axis"]
    floor = d["floor_sign"][k]
    sign = "-" if floor < 0 else "+"
    confident = d["long_ratio"] > 1.3 and floor != 0
    ev.update(source="data", confidence="high" if confident else "low")
    return f"{sign}{'xyz'[k]}", ev


def _landmark_forward(positions: np.ndarray, labels: Sequence[str], upv: np.ndarray
                      ) -> np.ndarray | None:
    """Mean front-minus-back landmark vector, horizontal (``None`` without pairs)."""
    names = [str(x).split(":")[-1].upper() for x in labels]
    vecs = []
    for front, back in _FRONT_BACK:
        fi = [i for i, n in enumerate(names) if n.endswith(front) and len(n) <= len(front) + 1]
        bi = [i for i, n in enumerate(names) if n.endswith(back) and len(n) <= len(back) + 1]
        if fi and bi:
            with warnings.catch_warnings():  # frames where a landmark is missing: NaN
                warnings.simplefilter("ignore", RuntimeWarning)
                v = np.nanmean(positions[:, fi], axis=1) - np.nanmean(positions[:, bi], axis=1)
            v = v[np.isfinite(v).all(-1)]
            if len(v):
                vecs.append(v.mean(0))
    if not vecs:
        return None
    v = np.mean(vecs, axis=0)
    v = v - (v @ upv) * upv
    return v if np.linalg.norm(v) > 1e-9 else None


def detect_forward(
    positions: np.ndarray, labels: Sequence[str], *, up: str, forward: str = "auto"
) -> tuple[str, dict[str, Any]]:
    """The horizontal axis the body faces.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
    labels : list of str
        ``M`` marker labels (front/back landmark pairs are looked for).
    up : str
        The up axis (:func:`detect_up`).
    forward : str
        ``"auto"`` or an axis used as given (it must be horizontal).

    Returns
    -------
    forward : str
        One of :data:`AXES`, perpendicular to ``up``.
    evidence : dict
        ``source``: ``"param"``, ``"landmarks"``, ``"travel"``, ``"shape"`` or
        ``"default"``.

    Raises
    ------
    AxisError
        A given ``forward`` along the up axis.
    """
    upv = axis_vector(up)
    if forward != "auto":
        f = parse_axis(forward, name="forward")
        if f[1] == parse_axis(up)[1]:
            raise AxisError(f"forward: {f} is along the up axis {up}; give a horizontal axis")
        return f, {"source": "param"}
    P = np.asarray(positions, dtype=float).reshape(len(positions), -1, 3)
    horizontal = [k for k in range(3) if upv[k] == 0]

    def snap(v: np.ndarray) -> str:
        k = max(horizontal, key=lambda a: abs(v[a]))
        return f"{'+' if v[k] > 0 else '-'}{'xyz'[k]}"

    v = _landmark_forward(P, labels, upv) if len(labels) == P.shape[1] else None
    if v is not None:
        return snap(v), {"source": "landmarks"}
    seen = np.isfinite(P).all(-1)
    c = np.where(seen[..., None], P, 0.0).sum(1) / np.maximum(seen.sum(1), 1)[:, None]
    c = c[seen.any(1)]
    lo, hi = _per_frame_bounds(P)
    width = float(np.nanmax((hi - lo)[horizontal])) if np.isfinite(hi - lo).all() else 0.0
    if len(c) >= 2:
        travel = c[-1] - c[0]
        travel = travel - (travel @ upv) * upv
        if width > 0 and np.linalg.norm(travel) > 1.0 * width:
            return snap(travel), {"source": "travel"}
    if width > 0:
        ext = (hi - lo)
        k = min(horizontal, key=lambda a: ext[a])
        return f"+{'xyz'[k]}", {"source": "shape"}
    k = horizontal[-1]
    return f"+{'xyz'[k]}", {"source": "default"}


def frame_basis(up: str, forward: str) -> np.ndarray:
    """Rotation ``(3, 3)`` from the Y-up, +Z-facing convention to these axes.

    Its columns are the images of x (the body's left, ``up x forward``), y (up)
    and z (forward): ``R @ v_yup`` is ``v`` in the given axes.

    Raises
    ------
    AxisError
        ``forward`` along ``up``.
    """
    u, f = axis_vector(up), axis_vector(forward)
    if abs(u @ f) > 0.5:
        raise AxisError(f"forward {forward} is along the up axis {up}")
    return np.stack([np.cross(u, f), u, f], axis=1)
