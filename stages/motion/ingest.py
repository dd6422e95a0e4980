"""Ingest stages: one source file (a part) in, a stored data type out.

* ``ingest_c3d``   C3D → ``markers`` (+ ``report``: counts, missing fractions, gaps,
  excluded model-output points, fragments).
* ``ingest_bvh``   BVH → ``motion`` (optionally resampled).
* ``ingest_amc``   ASF/AMC → ``motion`` (the ASF defaults to ``<subject>.asf`` beside the AMC).
* ``ingest_strokes``      UCI CSV / Omniglot / mocapflow strokes CSV → one ``strokes``.
* ``ingest_strokes_set``  the same files → ``examples``: a :class:`StrokesSet` of
  every selected example (e.g. the 5 examples of UCI letter ``a``), for stages
  that learn from several examples of one file.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.pipeline import Context, FilePath, stage
from mocapflow.stages.motion.axes import (
    AxisError,
    axis_vector,
    data_axes,
    detect_forward,
    detect_up,
    frame_basis,
    parse_axis,
)
from mocapflow.stages.motion.datatypes import Markers, Motion, StrokesSet
from mocapflow.stages.motion.formats.asf import read_amc, read_asf
from mocapflow.stages.motion.formats.bvh import read_bvh, rest_extent
from mocapflow.stages.motion.formats.c3d import read_c3d
from mocapflow.stages.motion.formats.strokes import StrokesFileError, read_strokes_file
from mocapflow.stages.motion.kinematics import (
    end_site_positions,
    forward_kinematics,
    resample_motion,
)
from mocapflow.stages.motion.rotations import quat_multiply, quat_rotate

__all__ = [
    "MAX_RESAMPLED_SAMPLES",
    "MAX_UPSAMPLE",
    "IngestError",
    "amc_skeleton_path",
    "bvh_axes",
    "gap_statistics",
    "ingest_amc",
    "ingest_bvh",
    "ingest_c3d",
    "ingest_strokes",
    "ingest_strokes_set",
    "markers_axes",
    "markers_report",
]


# --------------------------------------------------------------------------- markers


def gap_statistics(visible: np.ndarray) -> dict[str, Any]:
    """Interior gaps of marker trajectories (runs of missing frames not touching either end).

    Parameters
    ----------
    visible : (F, M) bool ndarray

    Returns
    -------
    dict
        ``count``, ``median`` and ``max`` length in frames (``None`` without gaps),
        ``markers`` (how many markers have one), ``edge_gap_markers``.
    """
    F, M = visible.shape
    pad = np.zeros((1, M), np.int8)
    d = np.diff(np.vstack([pad, (~visible).astype(np.int8), pad]), axis=0)
    s_m, s_f = np.nonzero(d.T == 1)  # gap starts, sorted by marker then frame
    e_m, e_f = np.nonzero(d.T == -1)  # gap ends (exclusive), same order
    interior = (s_f > 0) & (e_f < F)
    lengths = (e_f - s_f)[interior]
    return {
        "count": int(lengths.size),
        "median": float(np.median(lengths)) if lengths.size else None,
        "max": int(lengths.max()) if lengths.size else None,
        "markers": int(np.unique(s_m[interior]).size),
        "edge_gap_markers": int(np.unique(s_m[~interior]).size),
    }


def markers_report(markers: Markers) -> dict[str, Any]:
    """Summary of a C3D read: counts, missing fractions, gaps, exclusions, analogs.

    Missing fractions are shares of samples (frame × point): ``missing_fraction``
    over the labelled markers, ``missing_fraction_with_fragments`` over markers and
    unlabelled fragments, ``missing_fraction_non_model`` over every point that is
    not a model output (markers, fragments and Plug-in-Gait virtual segment
    points: the PROVENANCE.md convention).
    """
    F, M = markers.positions.shape[:2]
    U = markers.fragments.shape[1]
    vis = markers.visible
    miss_m = int((~vis).sum())
    miss_f = int((~np.isfinite(markers.fragments).all(axis=-1)).sum())
    excluded = markers.attrs.get("excluded_points", [])
    virtual = [e for e in excluded if e.get("kind") == "virtual_segment"]
    miss_v = sum(int(e.get("missing", 0)) for e in virtual)

    def frac(num: int, n_points: int) -> float | None:
        return num / (F * n_points) if F * n_points else None

    kinds: dict[str, int] = {}
    for e in excluded:
        kinds[e.get("kind", "?")] = kinds.get(e.get("kind", "?"), 0) + 1
    return {
        "source": markers.attrs.get("source"),
        "frames": F,
        "rate": markers.rate,
        "first_frame": markers.first_frame,
        "source_unit": markers.attrs.get("source_unit"),
        "points_in_file": markers.attrs.get("n_points", M + U + len(excluded)),
        "markers": M,
        "fragments": U,
        "excluded": kinds,
        "excluded_points": [
            {"label": e["label"], "kind": e.get("kind"), "reason": e.get("reason")}
            for e in excluded
        ],
        "missing_fraction": frac(miss_m, M),
        "missing_fraction_with_fragments": frac(miss_m + miss_f, M + U),
        "missing_fraction_non_model": frac(miss_m + miss_f + miss_v, M + U + len(virtual)),
        "never_seen": [lb for lb, v in zip(markers.labels, vis.any(axis=0)) if not v],
        "interior_gaps": gap_statistics(vis),
        "fragment_lengths": (
            [int(x) for x in np.isfinite(markers.fragments).all(axis=-1).sum(axis=0)] if U else []
        ),
        "analog_channels": 0 if markers.analogs is None else int(markers.analogs.shape[1]),
        "analog_rate": markers.rate * markers.analog_subframes or None,
        "parameter_groups": list(markers.attrs.get("c3d_parameters", {})),
    }


#: Markers a ``Name:`` label prefix needs to count as a subject in :func:`markers_axes`.
SUBJECT_MARKERS = 10


def _largest_subject(labels: list[str]) -> np.ndarray | None:
    """Columns of the largest subject when ``Name:`` prefixes name two or more subjects
    of at least :data:`SUBJECT_MARKERS` markers each (Vicon / Motive multi-subject
    takes), else None."""
    prefix = np.array([lb.split(":", 1)[0] if ":" in lb else "" for lb in labels])
    names, counts = np.unique(prefix[prefix != ""], return_counts=True)
    if (counts >= SUBJECT_MARKERS).sum() < 2:
        return None
    return np.flatnonzero(prefix == names[np.argmax(counts)])


def markers_axes(markers: Markers, *, up: str = "auto", forward: str = "auto"
                 ) -> tuple[Markers, dict[str, Any]]:
    """Markers with their up axis and facing direction in ``attrs`` (``up``, ``forward``,
    ``axes_source``), detected (:mod:`~mocapflow.stages.motion.axes`) unless given.

    Parameters
    ----------
    markers : Markers
    up, forward : str
        ``"auto"`` or a signed axis (``z``, ``+z``, ``-y`` ...).

    Returns
    -------
    markers : Markers
    evidence : dict
        What decided: ``up`` and ``forward`` evidence (see :func:`detect_up`).  With
        two or more subjects named by ``Name:`` label prefixes, the largest one's
        markers decide (``up["subject"]``): subjects standing metres apart made their
        spread the long axis (kineticstoolkit's two-player tennis serve, Z up, read +y).
    """
    tree = markers.attrs.get("c3d_parameters") or {}
    screen = tree.get("POINT", {}).get("parameters", {}).get("Y_SCREEN", {}).get("value")
    one = _largest_subject(markers.labels)
    if one is not None:  # several subjects apart: their spread is not a body's extent
        both, labels = markers.positions[:, one], [markers.labels[i] for i in one]
    else:
        both, labels = markers.positions, markers.labels
        if markers.fragments.shape[1]:
            both = np.concatenate([markers.positions, markers.fragments], axis=1)
    up_axis, up_ev = detect_up(both, y_screen=str(screen[0]) if screen else None, up=up)
    fwd, fwd_ev = detect_forward(both[:, :len(labels)], labels, up=up_axis, forward=forward)
    if one is not None:
        up_ev["subject"] = labels[0].split(":", 1)[0]
    source = {"up": up_ev["source"], "up_confidence": up_ev["confidence"],
              "forward": fwd_ev["source"]}
    if up_ev.get("note"):
        source["note"] = up_ev["note"]
    attrs = {**markers.attrs, "up": up_axis, "forward": fwd, "axes_source": source}
    return markers.replace(attrs=attrs), {"up": up_ev, "forward": fwd_ev}


@stage("ingest_c3d", outputs=("markers", "report"))
def ingest_c3d(path: FilePath, *, up: str = "auto", forward: str = "auto", ctx: Context) -> dict:
    """Read a C3D file into markers (metres) and a report of what was read.

    Parameters
    ----------
    path : FilePath
        The ``.c3d`` part.
    up : str
        The vertical axis of the capture: ``"auto"`` (``POINT:Y_SCREEN`` where the
        file says, its sign checked against the floor; else the body's long axis
        over the trial, signed by the floor), or ``x``, ``y``, ``z`` with an
        optional sign (``+z``, ``-y``).  Stored in ``markers.attrs["up"]``; every
        stage reads it from there (the data are never rotated).
    forward : str
        The horizontal axis the subject faces: ``"auto"`` (front/back landmark
        pairs such as ``ASI``/``PSI``, else the direction of travel, else the
        body's thin horizontal axis) or a signed axis.  ``markers.attrs["forward"]``.

    Returns
    -------
    dict
        ``markers``: :class:`Markers` (``positions (F, M, 3)``, fragments, residuals,
        ``analogs (S, C)`` in the source's units, and the whole parameter section
        in ``attrs["c3d_parameters"]``: what ``export`` writes back);
        ``report``: JSON summary (see :func:`markers_report`) with ``up``,
        ``forward`` and ``axes`` (what decided them).
    """
    try:
        markers, evidence = markers_axes(read_c3d(path), up=up, forward=forward)
    except AxisError as e:
        raise IngestError(f"{path}: {e}") from None
    report = markers_report(markers)
    report.update(up=markers.attrs["up"], forward=markers.attrs["forward"],
                  axes=markers.attrs["axes_source"])
    for note in markers.attrs.get("read_notes", []):  # what the reader repaired or skipped
        ctx.warn(f"{Path(path).name}: {note}")
    if report["never_seen"]:
        ctx.warn(f"{Path(path).name}: markers never seen: {', '.join(report['never_seen'])}")
    src = markers.attrs["axes_source"]
    if src.get("note"):
        ctx.warn(f"{Path(path).name}: up axis: {src['note']}")
    if src["up_confidence"] == "low" and markers.n_markers + markers.fragments.shape[1]:
        ctx.warn(f"{Path(path).name}: up axis {markers.attrs['up']} guessed from the data "
                 "with little evidence; set ingest.up (x, y, z, +z, -y ...; in the skin graph "
                 "params.up, which its range-of-motion trial reads too) if it is wrong")
    return {"markers": markers, "report": report}


# --------------------------------------------------------------------------- motion


#: Most frames a resample may make per source frame (e.g. 30 Hz -> 480 Hz).
MAX_UPSAMPLE = 16
#: Most frames x joints a resample may make (rotations of 1 GiB).
MAX_RESAMPLED_SAMPLES = 1 << 25


class IngestError(ValueError):
    """An ingest param does not fit the file read (the message names the file and the param)."""


def _resampled(motion: Motion, rate: float | None, path: str) -> Motion:
    """``motion`` at ``rate`` (unchanged when ``None`` or equal), refusing huge targets.

    The target frame count ``floor((F - 1) * rate / motion.rate) + 1`` is checked
    before anything is allocated: at most :data:`MAX_UPSAMPLE` per source frame and
    :data:`MAX_RESAMPLED_SAMPLES` frames x joints.
    """
    if rate is None or abs(rate - motion.rate) <= 1e-9 * motion.rate:
        return motion
    if not (rate > 0 and math.isfinite(rate)):
        raise IngestError(f"{path}: rate: must be a finite number > 0, got {rate}")
    F, J = motion.n_frames, motion.skeleton.n_joints
    n_new = math.floor((F - 1) / motion.rate * rate + 1e-9) + 1
    if n_new > MAX_UPSAMPLE * F or n_new * J > MAX_RESAMPLED_SAMPLES:
        raise IngestError(
            f"{path}: rate: resampling {F} frames at {motion.rate:.6g} Hz (the file's frame "
            f"time) to {rate:.6g} Hz would make {n_new} frames of {J} joints; at most "
            f"{MAX_UPSAMPLE} per source frame and {MAX_RESAMPLED_SAMPLES} frames x joints"
        )
    return resample_motion(motion, rate)


#: Joint names that mark the head and the feet (case-insensitive), for the up axis.
_HEAD_NAME = re.compile(r"head", re.IGNORECASE)
_FOOT_NAME = re.compile(r"foot|toe|ankle", re.IGNORECASE)
#: Left -> right joint name spellings (``LeftUpLeg``, ``LHipJoint``, ``thigh_l``), for facing.
_LEFT_RIGHT = ((r"left", "right"), (r"Left", "Right"), (r"LEFT", "RIGHT"),
               (r"^L(?=[A-Z_])", "R"), (r"_l$", "_r"), (r"_L$", "_R"))
#: Most frames the up-axis evidence is computed on (evenly spread over the take).
_AXES_FRAMES = 240


def _static_root_dropped(motion: Motion) -> tuple[Motion, str | None]:
    """``motion`` without a static root joint whose only child carries the travel.

    When the root's position is constant and its rotation the identity over the
    take (to 1e-9), it has one child joint, no End Site, and that child has
    position channels that move (Bandai-Namco: ``joint_Root`` never moves, ``Hips``
    walks), the child becomes the root: its root position is the old root's plus the
    child's translation (rotated by the old root's, folded in exactly), its offset
    the old root's position plus its own.  Joint world positions are unchanged.

    Parameters
    ----------
    motion : Motion
        ``F`` frames of ``J`` joints, as :func:`read_bvh` gives them.

    Returns
    -------
    motion : Motion
        The re-rooted motion (``attrs["dropped_root"]``: the old root's name;
        ``attrs["dropped_root_joint"]``, also in the skeleton's ``attrs``: its name,
        offset, channels and constant position, metres, from which
        :func:`~mocapflow.stages.motion.formats.bvh.write_bvh` writes it back, so a file
        keeps its hierarchy through the graphs), or ``motion`` itself.
    message : str or None
        One line naming both joints when the root was dropped.
    """
    sk, F = motion.skeleton, motion.n_frames
    children = np.flatnonzero(sk.parents == 0)
    q0 = motion.rotations[:, 0]
    if (F < 2 or motion.translations is None or len(children) != 1 or (sk.end_parents == 0).any()
            or np.ptp(motion.root_position, axis=0).max() > 1e-9
            or (1.0 - np.abs(q0[:, 0])).max() > 1e-9):
        return motion, None
    c = int(children[0])  # 1: joints are in depth-first order
    moving = [j for j in range(1, sk.n_joints)
              if any(ch.endswith("position") for ch in sk.channels[j])
              and np.ptp(motion.translations[:, j], axis=0).max() > 1e-9]
    if moving != [c]:
        return motion, None
    keep = np.arange(1, sk.n_joints)
    root_position = motion.root_position + quat_rotate(q0, motion.translations[:, c])
    rotations = motion.rotations[:, keep].copy()
    rotations[:, 0] = quat_multiply(q0, rotations[:, 0])
    translations = motion.translations[:, keep].copy()
    translations[:, 0] = root_position
    offsets = sk.offsets[keep].copy()
    offsets[0] += motion.root_position[0]
    # what write_bvh needs to put the static root back around the new one (on the
    # skeleton too: stages that make new motions on it keep it, as the source unit)
    joint = {"name": sk.names[0], "offset": [float(v) for v in sk.offsets[0]],
             "channels": list(sk.channels[0]),
             "position": [float(v) for v in motion.root_position[0]]}  # fmt: skip
    skeleton = dataclasses.replace(
        sk, names=sk.names[1:], parents=np.maximum(sk.parents[keep] - 1, -1),
        offsets=offsets, channels=sk.channels[1:], end_parents=sk.end_parents - 1,
        attrs={**sk.attrs, "dropped_root_joint": joint})
    has_pos = [any(ch.endswith("position") for ch in chans) for chans in skeleton.channels]
    out = motion.replace(skeleton=skeleton, root_position=root_position, rotations=rotations,
                         translations=translations if any(has_pos[1:]) else None,
                         attrs={**motion.attrs, "dropped_root": sk.names[0],
                                "dropped_root_joint": joint})  # fmt: skip
    return out, (f"root joint {sk.names[0]!r} never moves and its child {sk.names[c]!r} carries "
                 f"the travel: {sk.names[c]!r} is the root, {sk.names[0]!r} is dropped")


def bvh_axes(motion: Motion, *, up: str = "auto", forward: str = "auto"
             ) -> tuple[str, str, dict[str, Any]]:
    """The up axis and facing of a BVH motion: BVH's Y up unless the motion clearly says Z.

    Evidence, from the world positions of the joints and End Sites over the take (at most
    :data:`_AXES_FRAMES` frames): the head-over-feet vector (joints named ``head`` minus
    those named ``foot`` / ``toe`` / ``ankle``, median over frames; clear when its largest
    axis is >= 2x the others), and the body's long axis signed by the floor
    (:func:`~mocapflow.stages.motion.axes.data_axes`; clear when it is >= 1.3x the
    next and the floor, coordinate 0, bounds the body along it).  The clear ones must
    agree; ``+z`` / ``-z`` is taken then, anything else keeps ``+y``.  The facing of
    a Z-up motion: ``left x up`` with ``left`` the median left-minus-right joint
    vector (``Left``/``Right``, ``L``/``R`` prefix, ``_l``/``_r`` suffix pairs), else
    ``-y`` for ``+z`` (Blender's front) and ``+y`` for ``-z``; Y up faces ``+z``.

    Parameters
    ----------
    motion : Motion
    up, forward : str
        ``"auto"`` or a signed axis used as given.

    Returns
    -------
    up, forward : str
        Signed axis names (:data:`~mocapflow.stages.motion.axes.AXES`).
    source : dict
        ``up`` (``"param"``, ``"names+data"``, ``"names"``, ``"data"``, ``"convention"``),
        ``up_confidence`` (``"high"``, or ``"low"`` with a ``note`` saying why),
        ``forward`` (``"param"``, ``"names"``, ``"convention"``).

    Raises
    ------
    AxisError
        A bad axis name, or ``forward`` along ``up``.
    """
    sk = motion.skeleton
    pos = pts = None
    if up == "auto" or forward == "auto":
        idx = np.unique(np.linspace(0, motion.n_frames - 1, _AXES_FRAMES).astype(int))
        tr = None if motion.translations is None else motion.translations[idx]
        pos, grot = forward_kinematics(sk, motion.rotations[idx], motion.root_position[idx],
                                       translations=tr)
        pts = np.concatenate([pos, end_site_positions(sk, pos, grot)], axis=1)
    if up != "auto":
        up, source = parse_axis(up, name="ingest_bvh.up"), {"up": "param", "up_confidence": "high"}
    else:
        up, source = _bvh_up(sk.names, pos, pts)
    if forward != "auto":
        forward, source["forward"] = parse_axis(forward, name="ingest_bvh.forward"), "param"
    elif up[1] == "y":
        forward, source["forward"] = ("+z" if up == "+y" else "-z"), "convention"
    else:
        forward, source["forward"] = _facing(sk.names, pos, up)
    frame_basis(up, forward)
    return up, forward, source


def _bvh_up(names: list[str], pos: np.ndarray, pts: np.ndarray) -> tuple[str, dict[str, Any]]:
    """The up axis of :func:`bvh_axes` from joint positions ``pos (F, J, 3)`` and joint and
    End Site positions ``pts (F, N, 3)``; with its ``source`` dict."""
    votes: dict[str, str] = {}
    head = [j for j, n in enumerate(names) if _HEAD_NAME.search(n)]
    feet = [j for j, n in enumerate(names) if _FOOT_NAME.search(n)]
    if head and feet:
        v = np.median(pos[:, head].mean(1) - pos[:, feet].mean(1), axis=0)
        a = np.sort(np.abs(v))
        k = int(np.argmax(np.abs(v)))
        if a[2] >= 2.0 * a[1] and a[2] > 0:
            votes["names"] = f"{'+' if v[k] > 0 else '-'}{'xyz'[k]}"
    d = data_axes(pts)
    if d["long_axis"] is not None:
        k = d["long_axis"]
        if d["long_ratio"] >= 1.3 and d["floor_sign"][k]:
            votes["data"] = f"{'+' if d['floor_sign'][k] > 0 else '-'}{'xyz'[k]}"
    said = set(votes.values())
    if len(said) == 1 and (found := next(iter(said))) in ("+y", "+z", "-z"):
        return found, {"up": "+".join(votes), "up_confidence": "high"}
    if len(said) > 1:
        why = "the head-over-feet axis ({names}) and the body's long axis ({data}) disagree"
    elif said:
        why = f"the motion says {next(iter(said))} up (only +y, +z or -z are taken)"
    else:
        why = ("no head and foot joint names, and the body's long axis over the take is "
               "not clear (or not bounded by a floor at 0)")
    return "+y", {"up": "convention", "up_confidence": "low", "note": why.format(**votes)}


def _facing(names: list[str], pos: np.ndarray, up: str) -> tuple[str, str]:
    """The facing of :func:`bvh_axes` for an up axis other than Y, with its source."""
    index = {n: j for j, n in enumerate(names)}
    pairs = []
    for n, j in index.items():
        for pattern, right in _LEFT_RIGHT:
            other = re.sub(pattern, right, n, count=1)
            if other != n and other in index:
                pairs.append((j, index[other]))
                break
    upv = axis_vector(up)
    if pairs:
        left_idx, right_idx = np.array(pairs).T
        left = np.median((pos[:, left_idx] - pos[:, right_idx]).mean(1), axis=0)
        f = np.cross(left, upv)
        if np.linalg.norm(f) > 1e-9:
            k = int(np.argmax(np.abs(f)))
            return f"{'+' if f[k] > 0 else '-'}{'xyz'[k]}", "names"
    return ("-" if upv.sum() > 0 else "+") + "xy"[int(up[1] == "x")], "convention"


#: A BVH skeleton with fewer joints is no whole body: ``unit="auto"`` (a 1.7 m body) then
#: warns (a 1-joint camera track read as metres sat 2.5 km away; pybvh's 2- and 4-joint
#: test files as decimetres and CMU units; every body in the shared and scouted files
#: has 22-60 joints).
BODY_JOINTS = 5


@stage("ingest_bvh", outputs=("motion",))
def ingest_bvh(
    path: FilePath, *, rate: float | None = None, unit: str = "auto", up: str = "auto",
    forward: str = "auto", ctx: Context
) -> dict:
    """Read a BVH file into a motion (metres), optionally resampled to ``rate``.

    Parameters
    ----------
    path : FilePath
        The ``.bvh`` part.
    rate : float, optional
        Target frames per second (``None`` keeps the file's Frame Time).
    unit : str
        Length unit of the file (``"auto"`` guesses it from the skeleton size).
    up, forward : str
        The file's vertical axis and the direction its character faces, stored in
        ``motion.attrs["up"]`` / ``["forward"]`` (``["axes_source"]``: what decided,
        see :func:`bvh_axes`).  ``"auto"``: BVH's convention, Y up facing +Z, unless
        the motion clearly says Z up (then facing by the left/right joints, else
        ``-y``); one warning when the evidence is weak.  Or a signed axis, e.g.
        ``up: +z, forward: -y`` for a file exported Z-up.

    Returns
    -------
    dict
        ``motion``: :class:`Motion` with ``root_position (F, 3)``, ``rotations (F, J, 4)``.
        A static root joint whose one child carries the travel is dropped (that
        child becomes the root, one warning; see :func:`_static_root_dropped`).
    """
    name = Path(path).name
    motion, dropped = _static_root_dropped(read_bvh(path, unit=unit))
    if dropped:
        ctx.warn(f"{name}: {dropped}")
    if unit == "auto" and motion.skeleton.n_joints < BODY_JOINTS:
        ctx.warn(f"{name}: unit {motion.attrs['source_unit']!r} guessed from a skeleton of "
                 f"{motion.skeleton.n_joints} joint(s), which says little about size "
                 f"(rest pose {rest_extent(motion.skeleton):.3g} m across in that unit); "
                 "set ingest.unit (m, cm, mm, in ...) if it is wrong")
    try:
        up_axis, fwd, source = bvh_axes(motion, up=up, forward=forward)
    except AxisError as e:
        raise IngestError(f"{path}: {e}") from None
    if source.get("note"):
        ctx.warn(f"{name}: up axis +y (BVH's convention) kept, the evidence is weak: "
                 f"{source['note']}; set ingest.up (+z, -y ...) if it is wrong")
    motion = motion.replace(attrs={**motion.attrs, "up": up_axis, "forward": fwd,
                                   "axes_source": source})
    return {"motion": _resampled(motion, rate, path)}


def amc_skeleton_path(amc: str | Path) -> Path:
    """The ASF that belongs to an AMC by CMU naming: ``cmu_01_01.amc`` → ``cmu_01.asf``.

    The subject is the AMC stem without its last ``_<trial>`` (``01_01`` → ``01``);
    the ASF is looked for beside the AMC.
    """
    amc = Path(amc)
    stem = amc.stem
    subject = stem.rsplit("_", 1)[0] if "_" in stem else stem
    return amc.with_name(f"{subject}.asf")


@stage("ingest_amc", outputs=("motion",), sidecars={"asf": lambda amc: str(amc_skeleton_path(amc))})
def ingest_amc(
    path: FilePath,
    *,
    asf: FilePath | None = None,
    rate: float | None = None,
    ctx: Context,
) -> dict:
    """Read an Acclaim AMC motion with its ASF skeleton into a motion (metres).

    Parameters
    ----------
    path : FilePath
        The ``.amc`` part.
    asf : FilePath, optional
        The skeleton file; default ``<subject>.asf`` beside the AMC
        (``cmu_01_01.amc`` → ``cmu_01.asf``, ``01_01.amc`` → ``01.asf``).  Pass it
        explicitly to have its content in the task key.
    rate : float, optional
        Target frames per second (``None`` keeps the AMC rate, 120 Hz for CMU).

    Returns
    -------
    dict
        ``motion``: :class:`Motion`.
    """
    asf_path = Path(asf) if asf is not None else amc_skeleton_path(path)
    if not asf_path.is_file():
        raise FileNotFoundError(
            f"{path}: no ASF skeleton {asf_path} beside it; pass the 'asf' param"
        )
    motion = read_amc(path, read_asf(asf_path))
    return {"motion": _resampled(motion, rate, path)}


# --------------------------------------------------------------------------- strokes


def _select(path: str, items: list, letter: str | None, example: int | None) -> list:
    if example is not None:
        chosen = [s for s in items if s.attrs.get("example") == example]
        if not chosen and 0 <= example < len(items) and "example" not in items[0].attrs:
            chosen = [items[example]]
        if not chosen:
            have = sorted({s.attrs.get("example") for s in items}, key=str)
            raise StrokesFileError(
                f"{path}: no example {example}"
                + (f" of letter {letter!r}" if letter else "")
                + f" (examples: {have})"
            )
        return chosen
    return items


@stage("ingest_strokes", outputs=("strokes",))
def ingest_strokes(
    path: FilePath,
    *,
    letter: str | None = None,
    example: int | None = None,
    ctx: Context,
) -> dict:
    """Read one written example: a UCI character, an Omniglot drawing or a strokes CSV row set.

    Parameters
    ----------
    path : FilePath
        UCI CSV, Omniglot ``.txt`` or mocapflow strokes CSV (detected by content).
    letter : str, optional
        UCI / mocapflow CSV: the letter to take.
    example : int, optional
        The example number (UCI ``example`` column, 1-based; mocapflow CSV:
        attrs ``example`` or else the 0-based position).  Required when the
        selection holds more than one example.

    Returns
    -------
    dict
        ``strokes``: :class:`Strokes` (``points (N, 2)``, ``stroke_starts (S,)``).
        Use ``ingest_strokes_set`` to get every example of a letter at once.
    """
    items = _select(path, read_strokes_file(path, letter=letter), letter, example)
    if len(items) != 1:
        have = [s.attrs.get("example", i) for i, s in enumerate(items)]
        raise StrokesFileError(
            f"{path}: {len(items)} examples match"
            + (f" letter {letter!r}" if letter else "")
            + f" (examples {have}); set 'example' (or 'letter'), or use ingest_strokes_set"
        )
    return {"strokes": items[0]}


@stage("ingest_strokes_set", outputs=("examples",))
def ingest_strokes_set(path: FilePath, *, letter: str | None = None, ctx: Context) -> dict:
    """Read every example of a stroke file (optionally of one letter) as one set.

    Parameters
    ----------
    path : FilePath
        UCI CSV, Omniglot ``.txt`` or mocapflow strokes CSV.
    letter : str, optional
        Keep only this letter.

    Returns
    -------
    dict
        ``examples``: :class:`StrokesSet` (a list of :class:`Strokes`, file order).
    """
    return {"examples": StrokesSet(read_strokes_file(path, letter=letter))}
