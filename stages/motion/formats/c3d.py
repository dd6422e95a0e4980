"""C3D marker files: read into :class:`~mocapflow.stages.motion.datatypes.Markers`, write back.

Reading and writing go through ``ezc3d``.  Before ezc3d sees a file,
:func:`~mocapflow.stages.motion.formats.c3d_check.check_file` walks its header and
parameter section in pure Python with ezc3d's own rules and checks the data block
it will read against the file size: ezc3d silently returns fewer frames for a
truncated data block, and can hang, allocate without bound or crash the process
on a corrupt parameter section, so a bad file must be rejected before it reaches
it.  What ezc3d returns is checked too: labels must be UTF-8 text and, among the
markers and fragments, unique; coordinates finite and within
:data:`~mocapflow.stages.motion.formats.MAX_DISTANCE_M` of the origin; residuals
finite.  Every failure is one :class:`C3DError` naming the file and the field.

What :func:`read_c3d` makes of the points of a file
---------------------------------------------------
* **missing**: a sample is missing when a coordinate is NaN or its residual is
  negative; its position and residual become NaN.
* **units**: ``POINT:UNITS`` (``mm``, ``cm``, ``m`` …) is converted to metres;
  the source unit stays in ``attrs["source_unit"]``.  Residuals are converted too.
* **labels**: ``POINT:LABELS``, ``LABELS2``, ``LABELS3`` … are joined, so files
  with more than 255 points keep every label.
* **model outputs** are not markers: points listed in ``POINT:ANGLES``,
  ``FORCES``, ``MOMENTS``, ``POWERS``, ``SCALARS``, ``REACTIONS`` (and in any
  parameter named by ``POINT:TYPE_GROUPS``), points whose ``POINT:DESCRIPTIONS``
  entry is one of those types, Plug-in-Gait output names (``…Angles``,
  ``…Force``, ``…Moment``, ``…Power``, ``CentreOfMass``) and Plug-in-Gait virtual
  segment points (``PELO``, ``LFEA`` …: a segment code such as ``PEL`` or ``LFE``
  followed by ``O``/``A``/``L``/``P``, kept out only when at least three of the
  four axes points of that segment are present).  They are listed in
  ``attrs["excluded_points"]`` with the reason and their missing-frame count.
* **unlabelled trajectories** (``*12`` style labels) go to ``fragments`` /
  ``fragment_labels``; they are not dropped.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from pathlib import Path
from typing import Any

import ezc3d
import numpy as np

from mocapflow.stages.motion.datatypes import UNIT_SCALE, Markers
from mocapflow.stages.motion.formats import MAX_DISTANCE_M
from mocapflow.stages.motion.formats.c3d_check import C3DError, check_file

__all__ = [
    "MODEL_OUTPUT_TYPES",
    "PIG_SEGMENTS",
    "C3DError",
    "classify_points",
    "read_c3d",
    "write_c3d",
]


#: ``POINT`` parameters that list model-output points, with the point type they hold.
MODEL_OUTPUT_TYPES: dict[str, str] = {
    "ANGLES": "angle",
    "FORCES": "force",
    "MOMENTS": "moment",
    "POWERS": "power",
    "SCALARS": "scalar",
    "REACTIONS": "reaction",
}

#: Plug-in-Gait segment codes whose ``<code>O/A/L/P`` points are virtual (model output).
PIG_SEGMENTS: frozenset[str] = frozenset(
    "PEL HED TRX LCL RCL LHU RHU LRA RRA LHN RHN LFE RFE LTI RTI LFO RFO LTO RTO".split()
)

_FRAGMENT_RE = re.compile(r"^\*\d+$")
_PIG_OUTPUT_RE = re.compile(
    r"^[A-Z][A-Za-z0-9]*(Angles?|Forces?|Moments?|Powers?)$|^Cent(re|er)OfMass(Floor)?$"
)
_DESCRIPTION_TYPES = {
    "angle",
    "angles",
    "force",
    "forces",
    "moment",
    "moments",
    "power",
    "powers",
    "scalar",
    "scalars",
    "reaction",
    "reactions",
}
_MAX_LABELS_PER_PARAM = 255


# --------------------------------------------------------------------------- reading


def _param(params: dict, group: str, name: str, default: Any = None) -> Any:
    g = params.get(group)
    if g is None or name not in g:
        return default
    return g[name]["value"]


def _joined(params: dict, group: str, name: str) -> list[str]:
    """``GROUP:NAME`` joined with ``NAME2``, ``NAME3`` … (C3D's > 255 entries rule)."""
    out: list[str] = []
    first = _param(params, group, name)
    if first is None:
        return out
    out.extend(str(s).strip() for s in first)
    k = 2
    while True:
        more = _param(params, group, f"{name}{k}")
        if more is None:
            return out
        out.extend(str(s).strip() for s in more)
        k += 1


def _strip_prefix(label: str) -> str:
    return label.rsplit(":", 1)[-1]


def classify_points(
    labels: list[str], descriptions: list[str], listed: dict[str, str]
) -> list[tuple[str, str]]:
    """Decide, per C3D point, whether it is a marker, a fragment or a model output.

    Parameters
    ----------
    labels : list of str
        ``P`` point labels (``POINT:LABELS`` joined).
    descriptions : list of str
        ``POINT:DESCRIPTIONS`` joined (may be shorter than ``labels``).
    listed : dict
        ``label -> "POINT:ANGLES"`` etc. for points named by a model-output parameter.

    Returns
    -------
    list of (kind, reason)
        ``kind`` is ``"marker"``, ``"fragment"``, ``"model_output"`` or
        ``"virtual_segment"``; ``reason`` says why (empty for markers).
    """
    bare = [_strip_prefix(lb) for lb in labels]
    axes_present: dict[str, int] = {}
    for b in bare:
        if len(b) == 4 and b[:3] in PIG_SEGMENTS and b[3] in "OALP":
            axes_present[b[:3]] = axes_present.get(b[:3], 0) + 1
    out: list[tuple[str, str]] = []
    for i, (lb, b) in enumerate(zip(labels, bare)):
        desc = descriptions[i].strip().lower() if i < len(descriptions) else ""
        if lb in listed or b in listed:
            out.append(("model_output", f"listed in {listed.get(lb) or listed[b]}"))
        elif desc in _DESCRIPTION_TYPES:
            out.append(("model_output", f"POINT:DESCRIPTIONS says {desc!r}"))
        elif _PIG_OUTPUT_RE.match(b):
            out.append(("model_output", "Plug-in-Gait model output name"))
        elif len(b) == 4 and b[:3] in PIG_SEGMENTS and b[3] in "OALP" and axes_present[b[:3]] >= 3:
            out.append(
                ("virtual_segment", f"Plug-in-Gait virtual point of segment {b[:3]} (axis {b[3]})")
            )
        elif _FRAGMENT_RE.match(b):
            out.append(("fragment", "unlabelled trajectory"))
        else:
            out.append(("marker", ""))
    return out


def _model_output_lists(params: dict) -> dict[str, str]:
    names = set(MODEL_OUTPUT_TYPES)
    tg = _param(params, "POINT", "TYPE_GROUPS")
    if tg:
        names.update(str(s).strip().upper() for s in tg if str(s).strip())
    listed: dict[str, str] = {}
    for n in sorted(names):
        if n in {"LABELS", "DESCRIPTIONS", "UNITS", "USED"}:
            continue
        for lb in _joined(params, "POINT", n):
            if lb:
                listed.setdefault(lb, f"POINT:{n}")
    return listed


def _ezc3d_points(path: str) -> tuple[dict, np.ndarray, np.ndarray, int, float]:
    """Parameters, points ``(4, P, F)``, residuals ``(1, P, F)``, first frame, header rate.

    Uses ezc3d's SWIG object directly, which skips the camera masks, analogs and
    rotations that ``ezc3d.c3d(path)`` also converts; falls back to that wrapper if
    the SWIG layer is laid out differently.
    """
    try:
        sw = ezc3d.ezc3d.c3d(path)
        params = ezc3d.c3d.Parameters(sw.parameters())
        pts, res = sw.get_points(), sw.get_point_residuals()
        first, rate = sw.header().firstFrame(), sw.header().frameRate()
    except AttributeError:  # pragma: no cover - other ezc3d versions
        c = ezc3d.c3d(path)
        params, pts = c["parameters"], c["data"]["points"]
        res = c["data"]["meta_points"]["residuals"]
        first, rate = c["header"]["points"]["first_frame"], c["header"]["points"]["frame_rate"]
    pts = np.asarray(pts, dtype=np.float64)
    return params, pts, np.asarray(res, dtype=np.float64), int(first), float(rate)


def _columns(a: np.ndarray, idx: list[int]) -> np.ndarray:
    """``a[:, idx]``, as a view when ``idx`` is one contiguous run (the usual case)."""
    if idx and idx == list(range(idx[0], idx[-1] + 1)):
        return a[:, idx[0] : idx[-1] + 1]
    return a[:, idx]


def read_c3d(path: str | os.PathLike) -> Markers:
    """Read the labelled markers, unlabelled fragments and residuals of a C3D file.

    Parameters
    ----------
    path : str or path-like
        The ``.c3d`` file.

    Returns
    -------
    Markers
        ``positions (F, M, 3)`` in metres (NaN where missing), ``labels``,
        ``rate`` (POINT:RATE, kept non-integer), ``first_frame`` (ezc3d's 0-based
        header first frame), ``residuals (F, M)`` in metres (NaN where missing),
        ``fragments (F, U, 3)`` / ``fragment_labels`` for ``*N`` points, and
        ``attrs``: ``source``, ``source_unit``, ``n_points`` (points in the file),
        ``excluded_points`` (list of ``{"label", "index", "kind", "reason",
        "missing"}``, ``missing`` = missing frames), ``fragment_missing``.

    Raises
    ------
    C3DError
        Empty, truncated, corrupt or unsupported file; unknown POINT:UNITS.
    """
    path = Path(path)
    params, pts, res, first_frame, header_rate = _read_points(path)
    n_points = pts.shape[1]
    rate = _point_rate(params, header_rate, path)
    unit, unit_assumed = _point_unit(params, path)
    k = UNIT_SCALE[unit]
    labels = _point_labels(params, n_points)
    _check_text(path, "POINT:LABELS", labels)
    descriptions = _joined(params, "POINT", "DESCRIPTIONS")
    listed = _model_output_lists(params)
    _check_text(path, "POINT:TYPE_GROUPS", list(listed.values()))
    kinds = classify_points(labels, descriptions, listed)
    with np.errstate(over="ignore", invalid="ignore"):
        xyz, r, missing = _metre_samples(pts, res, k)

    idx = {
        kind: [i for i, (kd, _) in enumerate(kinds) if kd == kind]
        for kind in ("marker", "fragment")
    }
    mk, fr = idx["marker"], idx["fragment"]
    _check_kept(path, labels, mk + fr, xyz, r)
    attrs = {
        "source": path.name,
        "source_unit": unit,
        "n_points": n_points,
        "excluded_points": _excluded_points(labels, kinds, missing),
        "fragment_missing": int(missing[:, fr].sum()),
    }
    if unit_assumed:
        attrs["unit_assumed"] = True
    return Markers(
        positions=_columns(xyz, mk),
        labels=[labels[i] for i in mk],
        rate=rate,
        first_frame=first_frame,
        residuals=_columns(r, mk),
        fragments=_columns(xyz, fr),
        fragment_labels=[labels[i] for i in fr],
        attrs=attrs,
    )


def _read_points(path: Path) -> tuple[dict, np.ndarray, np.ndarray, int, float]:
    """:func:`check_file`, then :func:`_ezc3d_points`, checked against the header's sizes."""
    layout = check_file(path)
    try:
        params, pts, res, first_frame, header_rate = _ezc3d_points(str(path))
    except Exception as e:  # ezc3d raises RuntimeError/OSError/IndexError …
        raise _fail(path, f"corrupt C3D file: ezc3d could not read it ({e})") from None
    if pts.ndim != 3 or pts.shape[1] != layout.n_points or pts.shape[2] != layout.n_frames:
        raise _fail(
            path,
            f"truncated or corrupt C3D data: read {pts.shape[2] if pts.ndim == 3 else 0} frames"
            f" of {pts.shape[1] if pts.ndim == 3 else 0} points, the header says "
            f"{layout.n_frames} frames of {layout.n_points} points",
        )
    return params, pts, res, first_frame, header_rate


def _fail(path: Path, msg: str) -> C3DError:
    return C3DError(f"{path}: {msg}")


def _point_rate(params: dict, header_rate: float, path: Path) -> float:
    """``POINT:RATE`` (kept non-integer), else the header's rate; must be finite and positive."""
    rate_v = _param(params, "POINT", "RATE")
    rate = float(np.ravel(rate_v)[0]) if rate_v is not None and np.size(rate_v) else 0.0
    if not rate > 0:
        rate = header_rate
    if not rate > 0:
        raise _fail(path, "no positive POINT:RATE")
    if not math.isfinite(rate):
        raise _fail(path, f"POINT:RATE (or the header frame rate) is not finite: {rate}")
    return rate


def _check_text(path: Path, field: str, values: list[str]) -> None:
    """Labels that are not UTF-8 (ezc3d hands their bytes over as surrogates) are an error."""
    for i, v in enumerate(values):
        try:
            v.encode("utf-8")
        except UnicodeEncodeError:
            raw = v.encode("utf-8", "surrogateescape")
            raise _fail(path, f"{field} entry {i + 1} is not UTF-8: {raw!r}") from None


def _check_kept(
    path: Path, labels: list[str], kept: list[int], xyz: np.ndarray, r: np.ndarray
) -> None:
    """The markers and fragments read: unique labels, finite coordinates within
    :data:`MAX_DISTANCE_M`, finite residuals (``xyz (F, P, 3)`` metres, ``r (F, P)``)."""
    seen: dict[str, int] = {}
    for i in kept:
        if labels[i] in seen:
            raise _fail(
                path, f"POINT:LABELS: {labels[i]!r} names points {seen[labels[i]] + 1} and {i + 1}"
            )
        seen[labels[i]] = i
    if not kept:
        return
    sel = xyz[:, kept] if len(kept) < xyz.shape[1] else xyz
    far = np.abs(np.nan_to_num(sel, nan=0.0, posinf=np.inf, neginf=np.inf)).max(axis=-1)
    if (far > MAX_DISTANCE_M).any():
        f, j = (int(a[0]) for a in np.nonzero(far > MAX_DISTANCE_M))
        raise _fail(
            path,
            f"POINT data: point {labels[kept[j]]!r} is {far[f, j]:.3g} m from the origin in "
            f"frame {f} (a wrong POINT:SCALE or POINT:UNITS?)",
        )
    res = r[:, kept] if len(kept) < r.shape[1] else r
    if np.isinf(res).any():
        f, j = (int(a[0]) for a in np.nonzero(np.isinf(res)))
        raise _fail(
            path, f"POINT data: residual of point {labels[kept[j]]!r} in frame {f} is not finite"
        )


def _point_unit(params: dict, path: Path) -> tuple[str, bool]:
    """``POINT:UNITS`` lower-cased (a key of ``UNIT_SCALE``), and whether ``mm`` was assumed."""
    units = _param(params, "POINT", "UNITS") or [""]
    unit = str(units[0]).strip().lower() if len(units) else ""
    unit_assumed = unit == ""
    if unit_assumed:
        unit = "mm"
    if unit not in UNIT_SCALE:
        raise _fail(path, f"unsupported POINT:UNITS {unit!r} (known: {sorted(UNIT_SCALE)})")
    return unit, unit_assumed


def _point_labels(params: dict, n_points: int) -> list[str]:
    """``P`` labels: ``POINT:LABELS`` joined, ``POINT<i>`` where missing or empty."""
    labels = _joined(params, "POINT", "LABELS")[:n_points]
    labels += [f"POINT{i + 1}" for i in range(len(labels), n_points)]
    return [lb if lb else f"POINT{i + 1}" for i, lb in enumerate(labels)]


def _metre_samples(
    pts: np.ndarray, res: np.ndarray, k: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions ``(F, P, 3)`` and residuals ``(F, P)`` in metres, NaN where missing.

    ``k`` is metres per file unit; a sample is missing when a coordinate is NaN
    or its residual is negative.  Returns the missing mask ``(F, P)`` too.
    """
    n_points, n_frames = pts.shape[1], pts.shape[2]
    xyz = np.ascontiguousarray(pts[:3].transpose(2, 1, 0))  # (F, P, 3), the one copy
    r = np.ascontiguousarray(res[0].T) if res.size else np.zeros((n_frames, n_points))
    missing = np.isnan(xyz).any(axis=-1)
    missing |= ~(r >= 0)
    if k != 1.0:
        xyz *= k
        r *= k
    xyz[missing] = np.nan
    r[missing] = np.nan
    return xyz, r, missing


def _excluded_points(
    labels: list[str], kinds: list[tuple[str, str]], missing: np.ndarray
) -> list[dict[str, Any]]:
    """``attrs["excluded_points"]``: the model outputs and virtual segment points."""
    return [
        {
            "label": labels[i],
            "index": i,
            "kind": kd,
            "reason": why,
            "missing": int(missing[:, i].sum()),
        }
        for i, (kd, why) in enumerate(kinds)
        if kd in ("model_output", "virtual_segment")
    ]


# --------------------------------------------------------------------------- writing


def write_c3d(markers: Markers, path: str | os.PathLike, *, unit: str = "mm") -> Path:
    """Write markers (and their unlabelled fragments) to a float C3D file with ezc3d.

    Parameters
    ----------
    markers : Markers
        ``positions (F, M, 3)`` metres, NaN where missing; ``fragments (F, U, 3)``
        are written after the markers as extra points labelled with
        ``fragment_labels``.
    path : str or path-like
        Output file (``.c3d`` is appended by ezc3d when missing, so pass it).
    unit : str
        POINT:UNITS of the file (a key of ``UNIT_SCALE``: ``"mm"``, ``"m"`` …).

    Returns
    -------
    Path
        The file written.  Labels beyond 255 go to ``POINT:LABELS2``, ``LABELS3`` …
        (ezc3d splits them); ``POINT:USED`` is ``M + U``; missing samples get
        residual -1; ``first_frame`` and the (possibly non-integer) rate are kept.
        Residuals are stored with ``POINT:SCALE = -max_residual / 255`` (C3D keeps
        them in one byte), so they read back to within ``max_residual / 510``.
    """
    if unit not in UNIT_SCALE:
        raise ValueError(f"write_c3d: unknown unit {unit!r} (known: {sorted(UNIT_SCALE)})")
    path = Path(path)
    k = UNIT_SCALE[unit]
    labels = list(markers.labels) + list(markers.fragment_labels)
    F = markers.n_frames
    xyz = np.concatenate([markers.positions, markers.fragments], axis=1) / k  # (F, P, 3)
    P = xyz.shape[1]
    missing = ~np.isfinite(xyz).all(axis=-1)
    resid = np.zeros((F, P))
    if markers.residuals is not None:
        resid[:, : markers.n_markers] = np.nan_to_num(markers.residuals / k, nan=0.0)
    resid = np.clip(resid, 0.0, None)
    top = float(resid.max()) if resid.size else 0.0
    scale = -(top / 255.0) * (1 + 1e-6) if top > 0 else -1.0
    resid += 0.5 * abs(scale) if top > 0 else 0.0  # ezc3d truncates residual / |scale|
    resid[missing] = -1.0
    pts = np.ones((4, P, F))
    pts[:3] = np.where(missing[..., None], np.nan, xyz).transpose(2, 1, 0)

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = np.array([float(markers.rate)])
    c["parameters"]["POINT"]["LABELS"]["value"] = labels
    c["parameters"]["POINT"]["UNITS"]["value"] = [unit]
    c["parameters"]["POINT"]["SCALE"]["value"] = np.array([scale])
    c["header"]["points"]["first_frame"] = int(markers.first_frame)
    c["data"]["points"] = pts
    c["data"]["meta_points"] = {"residuals": resid.T[None].copy()}
    c.add_parameter("MANUFACTURER", "SOFTWARE", "mocapflow")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".c3d", prefix=f".{path.stem}-", dir=path.parent)
    os.close(fd)
    try:
        c.write(tmp)
        os.replace(tmp, path)
    except Exception:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
