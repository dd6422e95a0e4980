"""C3D marker files: read into :class:`~mocapflow.stages.motion.datatypes.Markers`, write back.

Reading and writing go through ``ezc3d``.  Before ezc3d sees a file,
:func:`~mocapflow.stages.motion.formats.c3d_check.check_file` walks its header and
parameter section in pure Python with ezc3d's own rules and checks the data block
it will read against the file size: ezc3d silently returns fewer frames for a
truncated data block, and can hang, allocate without bound or crash the process
on a corrupt parameter section, so a bad file must be rejected before it reaches
it.  What ezc3d returns is checked too: labels must be UTF-8 text; coordinates
finite and within :data:`~mocapflow.stages.motion.formats.MAX_DISTANCE_M` of the
origin; residuals finite.  Every failure is one :class:`C3DError` naming the file
and the field.

What :func:`read_c3d` makes of the points of a file
---------------------------------------------------
* **missing**: a sample is missing when a coordinate is NaN or its residual is
  negative, or (markers and fragments) when it is exactly ``(0, 0, 0)``, which
  Vicon and others write for gaps; its position and residual become NaN.
* **units**: ``POINT:UNITS`` (``mm``, ``cm``, ``m`` …) is converted to metres;
  the source unit stays in ``attrs["source_unit"]``.  Residuals are converted too.
  A unit word or a cut of one that names one unit only (``mete``, ``millimeters``)
  is read as that unit.
* **labels**: ``POINT:LABELS``, ``LABELS2``, ``LABELS3`` … are joined, so files
  with more than 255 points keep every label.  Markers (and fragments) sharing a
  label are joined into one trajectory when never visible in the same frame
  (pieces of one marker), else the later ones are renamed ``LABEL_2``,
  ``LABEL_3`` … (different markers whose names were cut).
* **parameters of an undefined group** (a group id no group entry defines; ezc3d
  files them under ``""``) are left out of ``attrs["c3d_parameters"]``.
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
* **frames with analog words ezc3d does not count** (the parameters leave
  ``ANALOG:RATE`` out or declare no channel, the header and the data block hold them):
  ezc3d would read every frame after the first from the wrong place, so the points
  are read with the header's frame size instead (c3d.org sample28, BTKData's
  ``561xxa01_anonym.C3D``); no analog data then.
* **notes**: each departure from the file above (zeros read as missing, a unit
  word read, labels joined or renamed, parameters left out) is one line of
  ``attrs["read_notes"]`` (absent when there is none), for the ingest to warn with.
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
    "RESIDUAL_ENCODING",
    "classify_points",
    "parameter_tree",
    "publish",
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


def _ezc3d_points(path: str) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray, int, float]:
    """Parameters, points ``(4, P, F)``, residuals ``(1, P, F)``, analogs ``(1, C, S)``,
    first frame, header rate.

    Uses ezc3d's SWIG object directly, which skips the camera masks and rotations
    that ``ezc3d.c3d(path)`` also converts; falls back to that wrapper if the SWIG
    layer is laid out differently.
    """
    try:
        sw = ezc3d.ezc3d.c3d(path)
        params = ezc3d.c3d.Parameters(sw.parameters())
        pts, res = sw.get_points(), sw.get_point_residuals()
        analogs = sw.get_analogs()
        first, rate = sw.header().firstFrame(), sw.header().frameRate()
    except AttributeError:  # pragma: no cover - other ezc3d versions
        c = ezc3d.c3d(path)
        params, pts = c["parameters"], c["data"]["points"]
        res = c["data"]["meta_points"]["residuals"]
        analogs = c["data"]["analogs"]
        first, rate = c["header"]["points"]["first_frame"], c["header"]["points"]["frame_rate"]
    pts = np.asarray(pts, dtype=np.float64)
    res = np.asarray(res, dtype=np.float64)
    return params, pts, res, np.asarray(analogs, dtype=np.float64), int(first), float(rate)


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
        "missing"}``, ``missing`` = missing frames), ``fragment_missing``,
        ``c3d_parameters`` (every group, see :func:`parameter_tree`), ``read_notes``
        (list of one-line strings, only when the reader departed from the file, see
        the module docstring); ``analogs
        (S, C)`` as ezc3d gives them (``(raw - ANALOG:OFFSET) x SCALE x GEN_SCALE``),
        ``None`` without analog channels.

    Raises
    ------
    C3DError
        Empty, truncated, corrupt or unsupported file; unknown POINT:UNITS.
    """
    path = Path(path)
    notes: list[str] = []
    params, pts, res, analogs, first_frame, header_rate = _read_points(path, notes)
    n_points = pts.shape[1]
    rate = _point_rate(params, header_rate, path)
    unit, unit_assumed = _point_unit(params, path, notes)
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
    _origin_is_missing(labels, idx["marker"] + idx["fragment"], xyz, r, missing, notes)
    labels, joined = _shared_labels(
        labels, descriptions, idx["marker"] + idx["fragment"], xyz, r, missing, notes
    )
    mk, fr = ([i for i in idx[kd] if i not in joined] for kd in ("marker", "fragment"))
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
    tree = parameter_tree(params)
    if "" in tree:  # ezc3d's group for parameters of a group id the file never defines
        orphans = ", ".join(tree.pop("")["parameters"])
        if orphans:  # (an unnamed group with no parameter is dropped silently)
            notes.append(f"parameters of an undefined group skipped: {orphans}")
    attrs["c3d_parameters"] = tree
    if notes:
        attrs["read_notes"] = notes
    return Markers(
        positions=_columns(xyz, mk),
        labels=[labels[i] for i in mk],
        rate=rate,
        first_frame=first_frame,
        residuals=_columns(r, mk),
        fragments=_columns(xyz, fr),
        fragment_labels=[labels[i] for i in fr],
        attrs=attrs,
        analogs=_analog_samples(path, analogs, pts.shape[2]),
    )


def _read_points(path: Path, notes: list[str]
                 ) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray, int, float]:  # fmt: skip
    """:func:`check_file`, then :func:`_ezc3d_points`, checked against the header's sizes
    (the points of a file whose frames hold analog words ezc3d does not count read by
    :func:`_points_by_header` instead, with a line in ``notes``)."""
    layout = check_file(path)
    try:
        params, pts, res, analogs, first_frame, header_rate = _ezc3d_points(str(path))
    except Exception as e:  # ezc3d raises RuntimeError/OSError/IndexError …
        raise _fail(path, f"corrupt C3D file: ezc3d could not read it ({e})") from None
    words = _misread_analog_words(layout, analogs)
    if words is not None:
        pts, res = _points_by_header(path, layout, words, params)
        notes.append(f"points read with the header's frame size: {words} analog words a frame "
                     "that the ANALOG parameters do not size (no analog data read)")
    if pts.ndim != 3 or pts.shape[1] != layout.n_points or pts.shape[2] != layout.n_frames:
        raise _fail(
            path,
            f"truncated or corrupt C3D data: read {pts.shape[2] if pts.ndim == 3 else 0} frames"
            f" of {pts.shape[1] if pts.ndim == 3 else 0} points, the header says "
            f"{layout.n_frames} frames of {layout.n_points} points",
        )
    return params, pts, res, analogs, first_frame, header_rate


def _misread_analog_words(layout, analogs: np.ndarray) -> int | None:
    """The header's analog words per frame where ezc3d read the frames with another count
    and the data block holds exactly the header's frames (not ezc3d's), else None.

    ezc3d sizes a frame from the parameters (``ANALOG:USED`` x ``ANALOG:RATE`` /
    ``POINT:RATE``); files whose parameters leave the analog rate out or declare no
    channel while every frame holds analog words (c3d.org sample28, BTKData's
    ``561xxa01_anonym.C3D``: 6 or 18 words a frame) are then read from the wrong place
    after the first frame."""
    P, F, word = layout.n_points, layout.n_frames, layout.word
    if not (P and F and layout.header_analog_words):
        return None
    read = analogs.shape[1] * (analogs.shape[2] // F) if analogs.ndim == 3 else 0
    if read == layout.header_analog_words:
        return None
    header_frames = F * (4 * P + layout.header_analog_words) * word
    read_frames = F * (4 * P + read) * word
    if 0 <= layout.data_bytes - header_frames < 512 and not (
            0 <= layout.data_bytes - read_frames < 512):  # fmt: skip
        return layout.header_analog_words
    return None


def _points_by_header(path: Path, layout, analog_words: int,
                      params: dict) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Points ``(4, P, F)`` and residuals ``(1, P, F)`` as ezc3d gives them, read from the
    data block with the header's frame size (points, then ``analog_words`` analog words,
    skipped; :func:`_misread_analog_words`): c3d.org sample28 ``standing.C3D`` as ezc3d
    read it had shoulders at 2 cm and every step of every marker over 10 cm.
    Coordinates are floats (DEC's converted) or 16-bit integers times ``POINT:SCALE``; the
    fourth word is a missing sample when negative, else its integer's high byte times
    ``|POINT:SCALE|`` is the residual, as ezc3d reads its own files back.
    """
    P, F = layout.n_points, layout.n_frames
    word = layout.word
    frame = (4 * P + analog_words) * word
    start = (layout.data_start - 1) * 512
    raw = np.fromfile(path, np.uint8, count=F * frame, offset=start).reshape(F, frame)
    raw = np.ascontiguousarray(raw[:, : 4 * P * word]).reshape(F, P, 4, word)
    scale_v = _param(params, "POINT", "SCALE")  # the header's (-1: floats) where absent
    scale = float(np.ravel(scale_v)[0]) if scale_v is not None and np.size(scale_v) else (
        -1.0 if word == 4 else 1.0)  # fmt: skip
    if word == 4:
        if layout.processor == 85:  # DEC F-float: 16-bit words swapped, 4 x the value
            values = raw[..., [2, 3, 0, 1]].view("<f4")[..., 0] / 4.0
        else:
            values = raw.view("<f4")[..., 0]  # (F, P, 4)
        xyz, fourth = values[..., :3], values[..., 3]
    else:
        values = raw.view("<i2")[..., 0].astype(np.float64)  # (F, P, 4)
        xyz, fourth = values[..., :3] * scale, values[..., 3]
    # the fourth word as ezc3d reads it back from its own files: negative, missing; else
    # its integer's high byte times |POINT:SCALE| (the low byte: camera mask)
    code = np.where(np.isfinite(fourth), fourth, -1.0)
    residual = np.where(code < 0, -1.0, ((np.maximum(code, 0).astype(np.int64) >> 8) & 0xFF)
                        * abs(scale))  # fmt: skip
    pts = np.ones((4, P, F))
    pts[:3] = xyz.transpose(2, 1, 0)
    return pts, residual.T[None]


def _analog_samples(path: Path, analogs: np.ndarray, n_frames: int) -> np.ndarray | None:
    """``(S, C)`` analog samples (``None`` without channels); a whole number per frame."""
    if analogs.ndim != 3 or analogs.shape[1] == 0:
        return None
    if n_frames and analogs.shape[2] % n_frames:
        raise _fail(
            path,
            f"ANALOG data: {analogs.shape[2]} samples are not a whole number per frame "
            f"({n_frames} frames)",
        )
    return np.ascontiguousarray(analogs[0].T)


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
    """The markers and fragments read: finite coordinates within :data:`MAX_DISTANCE_M`,
    finite residuals (``xyz (F, P, 3)`` metres, ``r (F, P)``)."""
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


#: Unit words and their ``UNIT_SCALE`` key: a ``POINT:UNITS`` that is one of them, or
#: a cut of 3 or more letters of words of one unit only (``mete``, ``mill``), is read so.
_UNIT_WORDS: dict[str, str] = {
    **{f"{p}{w}{s}": u for p, u in (("", "m"), ("milli", "mm"), ("centi", "cm"), ("deci", "dm"))
       for w in ("meter", "metre") for s in ("", "s")},
    "inch": "in", "inches": "in", "foot": "ft", "feet": "ft",
}


def _point_unit(params: dict, path: Path, notes: list[str]) -> tuple[str, bool]:
    """``POINT:UNITS`` as a key of ``UNIT_SCALE``, and whether ``mm`` was assumed.

    A unit word or an unambiguous cut of one (:data:`_UNIT_WORDS`) is read as its
    key, with a line in ``notes``.
    """
    units = _param(params, "POINT", "UNITS") or [""]
    unit = str(units[0]).strip().lower() if len(units) else ""
    unit_assumed = unit == ""
    if unit_assumed:
        unit = "mm"
    if unit not in UNIT_SCALE:
        keys = {u for w, u in _UNIT_WORDS.items() if w.startswith(unit)} if len(unit) > 2 else ()
        if len(keys) != 1:
            raise _fail(path, f"unsupported POINT:UNITS {unit!r} (known: {sorted(UNIT_SCALE)})")
        (key,) = keys
        notes.append(f"POINT:UNITS {unit!r} read as {key!r}")
        unit = key
    return unit, unit_assumed


def _origin_is_missing(
    labels: list[str], kept: list[int], xyz: np.ndarray, r: np.ndarray, missing: np.ndarray,
    notes: list[str],
) -> None:
    """Samples of the points ``kept`` exactly at ``(0, 0, 0)`` become missing, in place.

    ``xyz (F, P, 3)``, ``r (F, P)``, ``missing (F, P)`` as :func:`_metre_samples`
    returns them; a line in ``notes`` says how many samples and points.
    """
    if not kept:
        return
    v = _columns(xyz, kept)
    zero = v[..., 0] == 0  # (F, K); NaN is never 0
    if not zero.any():
        return
    zero &= (v[..., 1] == 0) & (v[..., 2] == 0)
    if not zero.any():
        return
    f, j = np.nonzero(zero)
    p = np.asarray(kept)[j]
    xyz[f, p] = np.nan
    r[f, p] = np.nan
    missing[f, p] = True
    n_pts = int(zero.any(axis=0).sum())
    always = [labels[kept[i]] for i in np.flatnonzero(zero.all(axis=0))]
    notes.append(
        f"{f.size} samples of {n_pts} points exactly at (0, 0, 0) read as missing"
        + (f"; at (0, 0, 0) in every frame: {', '.join(always)}" if always else "")
    )


def _shared_labels(
    labels: list[str], descriptions: list[str], kept: list[int], xyz: np.ndarray,
    r: np.ndarray, missing: np.ndarray, notes: list[str],
) -> tuple[list[str], set[int]]:
    """Give every point of ``kept`` its own label: join or rename points sharing one.

    In file order, a point whose label an earlier point has is joined to the first
    trajectory of that label it is never visible in the same frame with (pieces of
    one marker): its samples are copied into that point's columns of ``xyz (F, P, 3)``,
    ``r (F, P)`` and ``missing (F, P)`` (in place).  A point that overlaps every
    trajectory of its label starts a new one, labelled ``LABEL_2``, ``LABEL_3`` …
    (the first free name).  One line per shared label goes to ``notes``.

    Returns
    -------
    labels : list of str
        ``P`` labels, renamed ones changed.
    joined : set of int
        Points joined into another (no longer a trajectory of their own).
    """
    points: dict[str, list[int]] = {}
    for i in kept:
        points.setdefault(labels[i], []).append(i)
    shared = {lb: ix for lb, ix in points.items() if len(ix) > 1}
    if not shared:
        return labels, set()
    labels, taken, joined = list(labels), set(labels), set()
    for lb, ix in shared.items():
        heads: dict[int, list[int]] = {}  # first point of a trajectory -> points joined to it
        for i in ix:
            seen = ~missing[:, i]
            h = next((h for h in heads if not (seen & ~missing[:, h]).any()), None)
            if h is None:
                heads[i] = []
                continue
            xyz[seen, h] = xyz[seen, i]
            r[seen, h] = r[seen, i]
            missing[seen, h] = False
            heads[h].append(i)
            joined.add(i)
        what = []
        for n, (h, more) in enumerate(heads.items()):
            if more:
                pts = ", ".join(str(i + 1) for i in [h, *more])
                what.append(f"{pts} joined into one trajectory (never visible in the same frame)")
            if n:
                k = 2
                while f"{lb}_{k}" in taken:
                    k += 1
                labels[h] = f"{lb}_{k}"
                taken.add(labels[h])
                desc = descriptions[h].strip() if h < len(descriptions) else ""
                what.append(f"{h + 1}{f' ({desc!r})' if desc else ''} renamed {labels[h]!r} "
                            f"(seen together with point {next(iter(heads)) + 1})")
        notes.append(f"POINT:LABELS {lb!r} names points {', '.join(str(i + 1) for i in ix)}: "
                     + "; ".join(what))
    return labels, joined


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


# --------------------------------------------------------------------------- parameters

#: C3D parameter type codes (the file's byte: -1 text, 1 byte, 2 int16, 4 float).
_TYPE_NAMES = {-1: "char", 1: "byte", 2: "int", 4: "float"}
_TYPE_CODES = {v: k for k, v in _TYPE_NAMES.items()}


def _text(v: Any) -> str:
    """A parameter string as JSON-able text (bytes that are not UTF-8 read as Latin-1)."""
    v = str(v)
    try:
        v.encode("utf-8")
    except UnicodeEncodeError:
        return v.encode("utf-8", "surrogateescape").decode("latin-1")
    return v


def parameter_tree(params: Any) -> dict[str, Any]:
    """The parameter section of a C3D file as a plain JSON tree.

    Parameters
    ----------
    params : mapping
        ezc3d's ``c["parameters"]``.

    Returns
    -------
    dict
        ``{group: {"description", "is_locked", "parameters": {name: {"type",
        "description", "is_locked", "dimension", "value"}}}}``, file order.
        ``type`` is ``"char"``, ``"byte"``, ``"int"`` or ``"float"``; numbers are
        flattened in C3D (column-major) order with their ``dimension`` (list of
        ints, e.g. ``[3, 4, 2]`` for FORCE_PLATFORM:CORNERS); text is a list of
        strings (``dimension`` ``[n]``).  :func:`write_c3d` writes it back.
    """
    tree: dict[str, Any] = {}
    for g in params:
        group = params[g]
        meta = group.get("__METADATA__", {})
        out: dict[str, Any] = {}
        for name, prm in group.items():
            if name == "__METADATA__":
                continue
            kind = _TYPE_NAMES.get(prm["type"], "float")
            if kind == "char":
                value: list = [_text(x) for x in prm["value"]]
                dimension = [len(value)]
            else:
                arr = np.asarray(prm["value"])
                dimension = [int(d) for d in arr.shape]
                value = arr.ravel(order="F").tolist()
            out[_text(name)] = {
                "type": kind,
                "description": _text(prm.get("description", "")),
                "is_locked": bool(prm.get("is_locked", False)),
                "dimension": dimension,
                "value": value,
            }
        tree[_text(g)] = {
            "description": _text(meta.get("DESCRIPTION", "")),
            "is_locked": bool(meta.get("IS_LOCKED", False)),
            "parameters": out,
        }
    return tree


def _ezc3d_param(prm: dict[str, Any]) -> dict[str, Any]:
    """One :func:`parameter_tree` entry as ezc3d's parameter dict."""
    kind = prm["type"]
    if kind == "char":
        value: Any = [str(x) for x in prm["value"]]
    else:
        dtype = np.float64 if kind == "float" else np.int64
        value = np.asarray(prm["value"], dtype=dtype).reshape(prm["dimension"], order="F")
    return {
        "type": _TYPE_CODES[kind],
        "description": prm.get("description", ""),
        "is_locked": bool(prm.get("is_locked", False)),
        "value": value,
    }


def _numeric(kind: str, value: Any) -> dict[str, Any]:
    arr = np.atleast_1d(np.asarray(value, dtype=np.float64 if kind == "float" else np.int64))
    return {"type": _TYPE_CODES[kind], "description": "", "is_locked": False, "value": arr}


def _chars(values: list[str]) -> dict[str, Any]:
    return {"type": _TYPE_CODES["char"], "description": "", "is_locked": False,
            "value": list(values)}


#: Parameters of the source the writer sets itself (the points and analogs written
#: may differ from the source's: other labels, counts, units, scale).
_REWRITTEN = {
    "POINT": {"LABELS", "DESCRIPTIONS", "UNITS", "SCALE", "RATE", "USED", "FRAMES",
              "DATA_START"},
    "ANALOG": {"LABELS", "USED", "RATE"},
}
_NUMBERED_RE = re.compile(r"^(LABELS|DESCRIPTIONS)\d+$")


# --------------------------------------------------------------------------- writing


#: Samples of each state, as :func:`write_c3d` writes them in the residuals.
RESIDUAL_ENCODING = {
    "measured": "the source residual; once cleaned, at least |POINT:SCALE| (> 0)",
    "merged": "0",
    "filled": "0, and the sample lies in a MOCAPFLOW:FILLED run",
    "missing": "-1 (coordinates NaN)",
}


def _residual_codes(markers: Markers, xyz_missing: np.ndarray, k: float) -> tuple[
    np.ndarray, float
]:
    """Residuals ``(F, P)`` in file units (before ezc3d's quantisation) and POINT:SCALE."""
    F, P = xyz_missing.shape
    M = markers.n_markers
    resid = np.zeros((F, P))
    if markers.residuals is not None:
        resid[:, :M] = np.nan_to_num(markers.residuals / k, nan=0.0)
    resid = np.clip(resid, 0.0, None)
    top = float(resid.max()) if resid.size else 0.0
    if top > 0:
        step = top / 255.0 * (1 + 1e-6)
    else:  # no residuals: -1 as before; cleaned, a small step for the measured code
        step = 1.0 if markers.status is None else 1.0 / 255.0
    scale = -step
    if markers.status is not None:  # cleaned: 0 is kept for merged and filled samples
        measured = np.ones((F, P), bool)
        measured[:, :M] = markers.status == 0
        resid = np.where(measured, np.maximum(resid, step), 0.0)
    resid += 0.5 * step  # ezc3d truncates residual / |scale|
    resid[xyz_missing] = -1.0
    return resid, scale


def _filled_runs(markers: Markers) -> np.ndarray:
    """``(3, N)`` float: point number (1-based), first and last frame of each filled run.

    Frames are absolute, numbered like ``first_frame`` (the first sample is
    ``first_frame``), inclusive.
    """
    if markers.status is None:
        return np.zeros((3, 0))
    filled = (markers.status == 2).astype(np.int8)
    pad = np.zeros((1, filled.shape[1]), np.int8)
    d = np.diff(np.vstack([pad, filled, pad]), axis=0)
    s_m, s_f = np.nonzero(d.T == 1)
    _, e_f = np.nonzero(d.T == -1)
    f0 = markers.first_frame
    return np.vstack([s_m + 1, s_f + f0, e_f - 1 + f0]).astype(np.float64)


def _parameters(
    markers: Markers, labels: list[str], unit: str, scale: float, n_analogs: int
) -> dict[str, dict[str, Any]]:
    """ezc3d's parameter dicts: the source's groups, then what the writer sets."""
    tree = markers.attrs.get("c3d_parameters") or {}
    groups: dict[str, dict[str, Any]] = {}
    for g, group in tree.items():
        if g == "ANALOG" and not n_analogs:
            continue
        out: dict[str, Any] = {
            "__METADATA__": {"DESCRIPTION": group.get("description", ""),
                             "IS_LOCKED": bool(group.get("is_locked", False))}
        }
        for name, prm in group.get("parameters", {}).items():
            if name in _REWRITTEN.get(g, ()) or (g in _REWRITTEN and _NUMBERED_RE.match(name)):
                continue
            out[name] = _ezc3d_param(prm)
        groups[g] = out
    point = groups.setdefault("POINT", {"__METADATA__": {"DESCRIPTION": "", "IS_LOCKED": False}})
    src_desc = dict(zip(_joined_tree(tree, "LABELS"), _joined_tree(tree, "DESCRIPTIONS")))
    point["LABELS"] = _chars(labels)
    if len(labels) <= _MAX_LABELS_PER_PARAM:  # beyond, ezc3d writes empty ones itself
        point["DESCRIPTIONS"] = _chars([src_desc.get(lb, "") for lb in labels])
    point["UNITS"] = _chars([unit])
    point["SCALE"] = _numeric("float", [scale])
    point["RATE"] = _numeric("float", [float(markers.rate)])
    if "Y_SCREEN" not in point and markers.attrs.get("up"):  # the up axis, for other tools
        up = str(markers.attrs["up"]).upper()
        point["Y_SCREEN"] = _chars([up])
        point.setdefault("X_SCREEN", _chars(["+Y" if up[-1] == "X" else "+X"]))
    if n_analogs:
        analog = groups.setdefault("ANALOG", {"__METADATA__": {"DESCRIPTION": "",
                                                               "IS_LOCKED": False}})
        src = _joined_tree(tree, "LABELS", group="ANALOG")
        analog["LABELS"] = _chars(
            src[:n_analogs] + [f"Channel_{i + 1}" for i in range(len(src), n_analogs)]
        )
        analog["RATE"] = _numeric("float", [markers.rate * markers.analog_subframes])
    if "MANUFACTURER" not in groups:
        groups["MANUFACTURER"] = {"__METADATA__": {"DESCRIPTION": "", "IS_LOCKED": False},
                                  "SOFTWARE": _chars(["mocapflow"])}
    groups["MOCAPFLOW"] = _status_group(markers)
    return groups


def _analog_rate_up(path: Path, rate: float, subframes: int) -> None:
    """Make the ANALOG:RATE of a file ezc3d wrote say ``subframes`` samples per frame.

    ezc3d writes ``subframes x POINT:RATE`` rounded to the nearest float32, and
    readers (ezc3d, :func:`check_file`) take the whole part of ANALOG:RATE /
    POINT:RATE, so with a non-integer rate they can read one analog sample per frame
    fewer, and every frame after the first from the wrong bytes.  The value is then
    moved up one float32 step, in place.
    """
    point = np.float32(rate)
    buf = bytearray(path.read_bytes())
    start = (buf[0] - 1) * 512
    group = re.compile(rb"[\x06\xfa]([\x80-\xff])ANALOG", re.S).search(buf, start)
    entry = group and re.compile(
        rb"[\x04\xfc]" + bytes([256 - group[1][0]]) + rb"RATE..\x04([\x00\x01])", re.S
    ).search(buf, start)
    if not entry:  # pragma: no cover - ezc3d always writes ANALOG:RATE with analogs
        return
    at = entry.end() + entry[1][0]
    analog = np.frombuffer(buf, "<f4", 1, at)[0]
    if float(analog) / float(point) >= subframes:
        return
    buf[at : at + 4] = np.nextafter(analog, np.float32(np.inf)).astype("<f4").tobytes()
    path.write_bytes(buf)


def _status_group(markers: Markers) -> dict[str, Any]:
    """The ``MOCAPFLOW`` group: how the residuals encode measured / merged / filled."""
    runs = _filled_runs(markers)
    group: dict[str, Any] = {
        "__METADATA__": {"DESCRIPTION": "mocapflow sample status", "IS_LOCKED": False},
        "SOFTWARE": _chars(["mocapflow"]),
        "CLEANED": _numeric("int", [int(markers.status is not None)]),
        "RESIDUALS": _chars([f"{k}: {v}" for k, v in RESIDUAL_ENCODING.items()]),
    }
    for i in range(0, max(runs.shape[1], 1), _MAX_LABELS_PER_PARAM):
        name = "FILLED" if i == 0 else f"FILLED{i // _MAX_LABELS_PER_PARAM + 1}"
        prm = _numeric("float", runs[:, i : i + _MAX_LABELS_PER_PARAM])
        prm["value"] = prm["value"].reshape(3, -1)
        prm["description"] = "point, first frame, last frame of each filled run"
        group[name] = prm
    return group


def _joined_tree(tree: dict, name: str, *, group: str = "POINT") -> list[str]:
    """``GROUP:NAME``, ``NAME2`` … of a :func:`parameter_tree`, joined."""
    prms = tree.get(group, {}).get("parameters", {})
    out: list[str] = []
    k = 1
    while (prm := prms.get(name if k == 1 else f"{name}{k}")) is not None:
        out.extend(str(x).strip() for x in prm["value"])
        k += 1
    return out


def write_c3d(markers: Markers, path: str | os.PathLike, *, unit: str = "mm") -> Path:
    """Write markers, their fragments, analogs and the source's parameters to a float C3D file.

    Parameters
    ----------
    markers : Markers
        ``positions (F, M, 3)`` metres, NaN where missing; ``fragments (F, U, 3)``
        are written after the markers as extra points labelled with
        ``fragment_labels``; ``analogs (S, C)`` as the ANALOG data; every group of
        ``attrs["c3d_parameters"]`` (FORCE_PLATFORM, EVENT, SUBJECTS, TRIAL,
        MANUFACTURER …) as it was read.
    path : str or path-like
        Output file (``.c3d`` is appended by ezc3d when missing, so pass it).
    unit : str
        POINT:UNITS of the file (a key of ``UNIT_SCALE``: ``"mm"``, ``"m"`` …).

    Returns
    -------
    Path
        The file written, mode ``0666 & ~umask`` (0644 usually).

    Notes
    -----
    What is rewritten: POINT:LABELS (beyond 255 in ``LABELS2`` …, split by ezc3d),
    DESCRIPTIONS (the source's for labels it had, else empty), UNITS, SCALE, RATE,
    USED, FRAMES; ANALOG:LABELS, USED and RATE (the point rate times the analog
    samples per frame, whatever the source said; one float32 step up where readers
    would count one sample per frame fewer); ``first_frame`` and the (possibly
    non-integer) rate are kept.  ANALOG:SCALE and GEN_SCALE are kept and the
    samples read back equal in the source units; ANALOG:OFFSET becomes 0 (ezc3d
    stores float samples with the offset applied).  Model-output points (ANGLES,
    FORCES …) are not written, but their POINT parameters are kept.  Byte
    parameters come back as int16 ones with the same values (ezc3d writes them so).

    Residuals say what each sample is (:data:`RESIDUAL_ENCODING`).  Markers that
    carry the clean stage's ``status`` (``MOCAPFLOW:CLEANED`` = 1): a measured
    sample (and every sample of an unmerged fragment) has the source residual, at
    least ``|POINT:SCALE|``; merged (a fragment joined to the marker by cleaning)
    and filled samples have residual 0, and the filled ones are listed in
    ``MOCAPFLOW:FILLED`` (float ``(3, N)``: point number 1-based, first and last
    frame, absolute like ``first_frame`` and inclusive; ``FILLED2`` … beyond 255
    runs).  Without ``status`` (``CLEANED`` = 0) every valid sample is measured and
    keeps its residual (0 where the source had none).  Missing samples have
    residual -1 and NaN coordinates.  Residuals are stored with
    ``POINT:SCALE = -max_residual / 255`` (C3D keeps them in one byte), so they read
    back to within ``max_residual / 510``.
    """
    if unit not in UNIT_SCALE:
        raise ValueError(f"write_c3d: unknown unit {unit!r} (known: {sorted(UNIT_SCALE)})")
    path = Path(path)
    k = UNIT_SCALE[unit]
    labels = list(markers.labels) + list(markers.fragment_labels)
    F = markers.n_frames
    xyz = np.concatenate([markers.positions, markers.fragments], axis=1) / k  # (F, P, 3)
    missing = ~np.isfinite(xyz).all(axis=-1)
    resid, scale = _residual_codes(markers, missing, k)
    pts = np.ones((4, xyz.shape[1], F))
    pts[:3] = np.where(missing[..., None], np.nan, xyz).transpose(2, 1, 0)
    analogs = markers.analogs if markers.analogs is not None else np.zeros((0, 0))
    groups = _parameters(markers, labels, unit, scale, analogs.shape[1])
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".c3d", prefix=f".{path.stem}-", dir=path.parent)
    os.close(fd)
    try:
        c = ezc3d.c3d()
        for g, group in groups.items():
            c["parameters"][g] = dict(group)
        c["header"]["points"]["first_frame"] = int(markers.first_frame)
        c["data"]["points"] = pts
        c["data"]["meta_points"] = {"residuals": resid.T[None].copy()}
        c["data"]["analogs"] = np.ascontiguousarray(analogs.T[None])
        c.write(tmp)
        if analogs.shape[1] and markers.analog_subframes:
            _analog_rate_up(Path(tmp), markers.rate, markers.analog_subframes)
        try:
            check_file(Path(tmp))  # what is written must pass the reader's own checks
        except C3DError as e:
            why = str(e).removeprefix(f"{tmp}: ")
            raise _fail(path, f"ezc3d wrote a file the reader rejects: {why}") from None
        publish(tmp, path)
    except Exception:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _umask() -> int:
    """The process umask, read without changing it where Linux says it."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:  # pragma: no cover - not Linux
        pass
    mask = os.umask(0o022)  # pragma: no cover
    os.umask(mask)  # pragma: no cover
    return mask  # pragma: no cover


def publish(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Give a finished temporary file the usual mode (``0666 & ~umask``) and move it to ``path``."""
    os.chmod(tmp, 0o666 & ~_umask())
    os.replace(tmp, path)
