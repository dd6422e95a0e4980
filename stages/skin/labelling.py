"""Labels for unlabelled takes and subjects of one take (Park & Hodgins 2006, §4.1).

A raw dense capture is a set of unlabelled trajectory fragments.  In the paper the
labels are the vertices of the marker surface built in the reference pose: every
trajectory visible in the reference frame becomes a marker, every other
fragment is joined to one of them by merging (§4.2).  Helpers of the
``clean`` stage:

* :func:`reference_labelling` — no labels at all: the frame where the most
  lasting trajectories are visible is the reference frame, and those trajectories
  become the markers ``L001 …`` (short ones, ghosts, stay fragments);
* :func:`template_labelling` with :func:`read_label_template` — a label layout
  from an earlier session of the same marker set (a labelled C3D, or JSON
  ``{"labels": [...], "positions": [[x, y, z], ...], "unit": "m"}``): the new
  take's reference-frame trajectories are matched to it by
  :func:`match_template` (rigid search over headings + scaled ICP, then non-rigid
  ICP: a thin-plate-spline warp of the template and a one-to-one assignment);
* :func:`template_proposals` (with :func:`fragment_frames`) — mid-take: a marker
  proposed for each fragment that no prediction reaches (a limb that lost its
  labels at once), by matching the layout of the missing markers' estimates to the
  fragments seen in a frame; ``clean`` judges them again (``template_merge_rounds``);
* :func:`subject_groups` / :func:`fragment_subjects` — several subjects in one
  take (C3D ``SUBJECTS:LABEL_PREFIXES``, ``Name:`` label prefixes, or groups of
  markers apart in space): ``clean`` cleans each subject on its own, so no
  neighbourhood, surface triangle or fill predictor spans two subjects.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import scipy.sparse as sp
from scipy.interpolate import RBFInterpolator
from scipy.optimize import linear_sum_assignment
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.distance import pdist
from scipy.spatial.transform import Rotation

from mocapflow.stages.motion.axes import axis_vector
from mocapflow.stages.motion.datatypes import Markers
from mocapflow.stages.motion.formats.c3d import read_c3d
from mocapflow.stages.skin.predict import choose_reference_frame, reference_pose

#: Trajectories shorter than this (seconds) are not made markers by
#: :func:`reference_labelling` (the simulator's ghosts last 1-15 frames).
MIN_LABEL_DURATION = 0.25

#: A subject needs at least this many markers; smaller groups (a few markers on a
#: prop) stay with the nearest subject (the segment stage keeps objects apart).
MIN_SUBJECT_MARKERS = 10
#: A group of markers apart in space is a subject only if its two farthest markers are
#: this many metres apart: a standing body spans more (a child's too).  The legs of
#: btk's PiG calibration (12 markers) lie more than 0.3 m from its pelvis markers but
#: span 0.71 m: one subject, not two (the upper body spans 1.53 m).
MIN_SUBJECT_SPAN = 1.0


class LabellingError(ValueError):
    """An unlabelled take cannot be labelled (no trajectories, bad template...)."""


def _runs_length(visible: np.ndarray) -> np.ndarray:
    """``(F, U)`` -> ``(F, U)`` length of the visible run each sample is in (0 off)."""
    F, U = visible.shape
    out = np.zeros((F, U), dtype=np.int64)
    for u in range(U):
        v = visible[:, u]
        if not v.any():
            continue
        edges = np.flatnonzero(np.diff(np.r_[0, v.astype(np.int8), 0]))
        for a, b in zip(edges[::2], edges[1::2]):
            out[a:b, u] = b - a
    return out


def _promote(markers: Markers, chosen: np.ndarray, labels: list[str],
             positions: np.ndarray | None = None) -> Markers:
    """Fragments ``chosen`` (U_c,) become the labelled markers ``labels``."""
    keep = np.ones(markers.fragments.shape[1], dtype=bool)
    keep[chosen] = False
    P = markers.fragments[:, chosen] if positions is None else positions
    out = markers.replace(
        positions=P, labels=labels, residuals=None, status=None,
        fragments=markers.fragments[:, keep],
        fragment_labels=[lb for lb, k in zip(markers.fragment_labels, keep) if k])
    return out


def reference_labelling(
    markers: Markers, *, reference_frame: int | None = None,
    min_duration: float = MIN_LABEL_DURATION,
) -> tuple[Markers, dict[str, Any]]:
    """Label an unlabelled take by its reference frame (§4.1).

    Parameters
    ----------
    markers : Markers
        ``fragments (F, U, 3)``; any labelled markers are kept as they are and the
        fragments are not relabelled when there are some.
    reference_frame : int, optional
        Frame whose trajectories become the markers; default: the frame where the
        most trajectories lasting ``min_duration`` are visible.
    min_duration : float
        Seconds a trajectory must last to become a marker.

    Returns
    -------
    markers : Markers
        ``positions (F, M, 3)`` the promoted trajectories, labels ``L001 …`` in
        fragment order; ``attrs["labelled_from"]`` maps label -> fragment name.
    info : dict
        ``reference_frame``, ``labelled``, ``short_skipped``.
    """
    frags = markers.fragments
    if markers.positions.shape[1]:
        return markers, {}
    if frags.shape[1] == 0 or frags.shape[0] == 0:
        source = markers.attrs.get("source", "the capture")
        if markers.positions.shape[0] == 0:
            raise LabellingError(f"clean: {source} has no labelled markers or no frames")
        points = markers.attrs.get("n_points")
        why = ("" if points is None else
               " (the file holds no points: analog or rotation data only)" if points == 0 else
               f" ({points} points in the file, none a marker: model outputs only?)")
        raise LabellingError(f"clean: {source} has no marker trajectories to clean{why}")
    vis = np.isfinite(frags).all(-1)
    lasting = _runs_length(vis) >= max(1, int(round(min_duration * markers.rate)))
    if reference_frame is None:
        frame = int(np.argmax(lasting.sum(1)))
    else:
        frame = _frame_index(reference_frame, frags.shape[0])
    chosen = np.flatnonzero(lasting[frame])
    if len(chosen) < 4:
        raise LabellingError(f"clean: only {len(chosen)} lasting trajectories in reference "
                             f"frame {frame}; cannot label the take")
    labels = [f"L{i + 1:03d}" for i in range(len(chosen))]
    out = _promote(markers, chosen, labels)
    out.attrs["labelled_from"] = {lb: markers.fragment_labels[int(u)]
                                  for lb, u in zip(labels, chosen)}
    # the promoted fragments' samples outside their reference-frame run stay
    # measured: they are those fragments' own samples, nothing else is moved
    return out, {"reference_frame": frame, "labelled": len(chosen),
                 "short_skipped": int((vis[frame] & ~lasting[frame]).sum())}


def _frame_index(frame: int, F: int) -> int:
    if not -F <= frame < F:
        raise LabellingError(f"clean: reference_frame {frame} out of range ({F} frames)")
    return int(frame) % F


# --------------------------------------------------------------------------- templates


@dataclass
class LabelTemplate:
    """A label layout: ``positions (L, 3)`` metres in the reference pose, ``labels``,
    and the ``up`` axis of its coordinates (``"+y"``, ``"+z"``... or None: unknown)."""

    labels: list[str]
    positions: np.ndarray
    up: str | None = None


def read_label_template(path: str | Path) -> LabelTemplate:
    """Read a label template: a labelled C3D (its reference pose: the frame with the
    most visible markers, carried over) or JSON ``{"labels", "positions", "unit"
    (m, mm, cm; default m), "up"}``.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    LabelTemplate
    """
    p = Path(path)
    if not p.is_file():
        raise LabellingError(f"clean: label template {p} not found")
    if p.suffix.lower() == ".c3d":
        m = read_c3d(p)
        if m.positions.shape[1] < 4:
            raise LabellingError(f"clean: label template {p.name} has fewer than 4 labelled "
                                 "markers")
        ref, _, never = reference_pose(m.positions, choose_reference_frame(m.positions))
        ok = np.isfinite(ref).all(1)
        return LabelTemplate([lb for lb, k in zip(m.labels, ok) if k], ref[ok],
                             m.attrs.get("up"))
    try:
        d = json.loads(p.read_text())
        labels = [str(x) for x in d["labels"]]
        pos = np.asarray(d["positions"], dtype=np.float64).reshape(-1, 3)
    except (ValueError, KeyError, TypeError) as e:
        raise LabellingError(f"clean: label template {p.name} is not a C3D or a JSON with "
                             f"'labels' and 'positions': {e}") from None
    if len(labels) != len(pos) or len(labels) < 4:
        raise LabellingError(f"clean: label template {p.name}: {len(labels)} labels for "
                             f"{len(pos)} positions (need >= 4, equal)")
    scale = {"m": 1.0, "cm": 0.01, "mm": 0.001}.get(str(d.get("unit", "m")).lower())
    if scale is None:
        raise LabellingError(f"clean: label template {p.name}: unit must be m, cm or mm")
    return LabelTemplate(labels, pos * scale, d.get("up"))


def _similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares ``s, R, t`` with ``dst ≈ s R src + t`` (Umeyama)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.diag([1.0, 1.0, d])
    R = U @ D @ Vt
    s = float((S * np.diag(D)).sum() / max((a ** 2).sum(), 1e-12))
    return s, R, md - s * R @ ms


def _icp(src: np.ndarray, dst_tree: cKDTree, dst: np.ndarray, iterations: int = 30,
         trim: float = 0.85) -> tuple[np.ndarray, float]:
    """Scaled ICP of ``src`` onto ``dst`` (trimmed); returns moved src and its score
    (mean of the kept nearest distances)."""
    x = src
    score = np.inf
    for _ in range(iterations):
        d, j = dst_tree.query(x)
        keep = d <= np.quantile(d, trim)
        s, R, t = _similarity(src[keep], dst[j[keep]])
        x = s * src @ R.T + t
        new = float(d[keep].mean())
        if abs(score - new) < 1e-7:
            break
        score = new
    d, _ = dst_tree.query(x)
    return x, float(np.sort(d)[: max(1, int(trim * len(d)))].mean())


def match_template(
    points: np.ndarray, template: np.ndarray, *, up: np.ndarray | None = None,
    headings: int = 24, warp_rounds: int = 4, max_distance: float | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Match a take's reference-pose points to a label template (rigid + non-rigid ICP).

    The template is moved onto the points: for ``headings`` turns about ``up``
    a scaled ICP (trimmed), the best kept; then ``warp_rounds`` rounds of a
    one-to-one assignment (``linear_sum_assignment``) and a smoothed thin-plate
    spline warp of the template onto its assigned points.

    Parameters
    ----------
    points : (N, 3) float ndarray
        The take's trajectories in the reference frame.
    template : (L, 3) float ndarray
        The template's reference pose (same unit).
    up : (3,) float ndarray, optional
        The common up axis (both in the same lab axes); default: the template's
        axis of largest extent.
    headings : int
        Turns about ``up`` tried as starts.
    warp_rounds : int
        Non-rigid rounds.
    max_distance : float, optional
        A point farther than this from its template marker after the warp stays
        unlabelled; default: half the template's median nearest-marker spacing.

    Returns
    -------
    assignment : (N,) int ndarray
        Template index per point, -1 where unmatched.
    info : dict
        ``rigid_mm`` (score of the best start), ``residual_mm`` (mean distance of
        the matched points after the warp), ``matched``, ``heading_deg``.
    """
    P = np.asarray(points, dtype=np.float64)
    T = np.asarray(template, dtype=np.float64)
    if len(P) < 4 or len(T) < 4:
        raise LabellingError("clean: template matching needs >= 4 points on both sides")
    if up is None:
        ext = T.max(0) - T.min(0)
        up = np.eye(3)[int(np.argmax(ext))]
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    tree = cKDTree(P)
    spacing = float(np.median(cKDTree(T).query(T, k=2)[0][:, 1]))
    cap = 0.5 * spacing if max_distance is None else float(max_distance)
    c = T.mean(0)
    best = (np.inf, None, 0.0)
    for k in range(headings):
        ang = 2 * np.pi * k / headings
        R = Rotation.from_rotvec(ang * up).as_matrix()
        start = (T - c) @ R.T + P.mean(0)
        moved, score = _icp(start, tree, P)
        if score < best[0]:
            best = (score, moved, np.degrees(ang))
    rigid, X = best[0], best[1]
    assign = np.full(len(P), -1, dtype=np.int64)
    for r in range(warp_rounds + 1):
        D = np.linalg.norm(P[:, None] - X[None], axis=-1)
        rows, cols = linear_sum_assignment(np.minimum(D, 10 * cap))
        good = D[rows, cols] <= (cap if r == warp_rounds else 3 * cap)
        rows, cols = rows[good], cols[good]
        if r == warp_rounds or len(rows) < 8:
            break
        warp = RBFInterpolator(T[cols], P[rows] - T[cols], kernel="thin_plate_spline",
                               smoothing=len(rows) * (spacing ** 2) * 1e-1)
        X = T + warp(T)
    assign[rows] = cols
    res = float(np.linalg.norm(P[rows] - X[cols], axis=1).mean()) if len(rows) else np.nan
    return assign, {"rigid_mm": round(rigid * 1e3, 2), "residual_mm": round(res * 1e3, 2),
                    "matched": int(len(rows)), "heading_deg": round(float(best[2]), 1)}


def template_labelling(
    markers: Markers, template: LabelTemplate, *, reference_frame: int | None = None,
    min_duration: float = MIN_LABEL_DURATION,
) -> tuple[Markers, dict[str, Any]]:
    """Label an unlabelled take with a template's labels (§4.1, a new session).

    The take's lasting reference-frame trajectories (:func:`reference_labelling`)
    are matched to the template (:func:`match_template`); matched ones get the
    template's labels, in the template's order (a template marker nobody matched
    is a marker with no samples yet: merging may still fill it); the rest stay
    fragments.

    Parameters
    ----------
    markers : Markers
    template : LabelTemplate
    reference_frame : int, optional
    min_duration : float

    Returns
    -------
    markers : Markers
    info : dict
        ``reference_frame``, ``matched``, ``unmatched_template``, ``residual_mm``...
    """
    first, info = reference_labelling(markers, reference_frame=reference_frame,
                                      min_duration=min_duration)
    if not info:
        return markers, {}
    frame = info["reference_frame"]
    names = first.attrs["labelled_from"]
    frag_index = {lb: u for u, lb in enumerate(markers.fragment_labels)}
    chosen = np.array([frag_index[names[lb]] for lb in first.labels])
    pts = markers.fragments[frame, chosen]
    up = None
    if template.up and markers.attrs.get("up") == template.up:
        up = axis_vector(template.up)
    assign, minfo = match_template(pts, template.positions, up=up)
    F = markers.n_frames
    L = len(template.labels)
    P = np.full((F, L, 3), np.nan)
    src = np.full(L, -1, dtype=np.int64)
    ok = assign >= 0
    P[:, assign[ok]] = markers.fragments[:, chosen[ok]]
    src[assign[ok]] = chosen[ok]
    out = _promote(markers, chosen[ok], list(template.labels), positions=P)
    out.attrs["labelled_from"] = {template.labels[int(t)]: markers.fragment_labels[int(u)]
                                  for t, u in enumerate(src) if u >= 0}
    unmatched = [template.labels[t] for t in range(L) if src[t] < 0]
    return out, {"reference_frame": frame, **minfo, "unmatched_template": unmatched,
                 "unmatched_points": int((~ok).sum())}


def label_markers(
    markers: Markers, *, template: str | Path | None = None, reference_frame: int | None = None,
) -> tuple[Markers, dict[str, Any]]:
    """Labels for a take without any (the ``clean`` stage's first step): by the
    ``template`` when given, else by the reference frame; a labelled take is
    returned unchanged with ``{}``."""
    if markers.positions.shape[1]:
        return markers, {}
    if template is not None:
        out, info = template_labelling(markers, read_label_template(template),
                                       reference_frame=reference_frame)
        return out, {"method": "template", "template": Path(template).name, **info}
    out, info = reference_labelling(markers, reference_frame=reference_frame)
    return out, {"method": "reference_frame", **info}



# --------------------------------------------------------------------------- mid-take labels

#: Frames :func:`fragment_frames` picks at most per round of proposals.
TEMPLATE_FRAMES = 12
#: A missing marker is in a frame's template only within this many metres of a fragment
#: seen there (the template is local: a limb's markers, not the whole body).
TEMPLATE_RADIUS = 0.3


def fragment_frames(visible: np.ndarray, *, min_frames: int = 3,
                    frames: int = TEMPLATE_FRAMES) -> np.ndarray:
    """Frames that together see the fragments: greedily, the frame seeing the most
    fragments of at least ``min_frames`` frames that no frame picked before sees (at
    least 4).

    Parameters
    ----------
    visible : (F, U) bool ndarray
        Where each fragment has a sample.
    min_frames : int
    frames : int
        Most frames picked.

    Returns
    -------
    (k,) int ndarray
        Frames, in the order picked.
    """
    long = visible.sum(0) >= min_frames
    seen = np.zeros(visible.shape[1], dtype=bool)
    out: list[int] = []
    for _ in range(frames):
        count = (visible & (long & ~seen)[None]).sum(1)
        f = int(np.argmax(count))
        if count[f] < 4:
            break
        seen |= visible[f] & long
        out.append(f)
    return np.array(out, dtype=np.int64)


def template_proposals(
    positions: np.ndarray, fragments: np.ndarray, estimates: np.ndarray, frames: np.ndarray,
    *, min_frames: int = 3, radius: float = TEMPLATE_RADIUS,
) -> np.ndarray:
    """Propose a marker for fragments that no prediction reaches, by the markers' layout.

    Beyond §4.2 (the paper merged what was left by hand).  When a whole limb loses its
    labels at once (on the simulated range of motion most of an arm's markers
    reappear as new fragments after an occlusion, for the rest of the take), every
    prediction of its markers comes from the trunk, 10–20 cm off, and no fragment
    passes the entry test.  The layout of the missing markers still matches the
    fragments' up to the limb's motion: in each of ``frames``, the estimates of the
    markers missing there and within ``radius`` of a fragment are matched to the
    fragments seen there (:func:`match_template`: scaled ICP from the estimates'
    place, then a thin-plate warp and a one-to-one assignment).  A proposal is not
    a merge: :func:`mocapflow.stages.skin.clean` judges the fragments again against
    rigid predictions made with the proposals in place (``template_merge_rounds``).

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        Labelled and merged trajectories (NaN where missing).
    fragments : (F, U, 3) float ndarray
        Unmerged fragments.
    estimates : (F, M, 3) float ndarray
        Estimates of the missing samples in ``frames`` (e.g. the hole filling).
    frames : (k,) int ndarray
        Frames to match in (:func:`fragment_frames`).
    min_frames : int
        Shorter fragments get no proposal.
    radius : float
        Metres (:data:`TEMPLATE_RADIUS`).

    Returns
    -------
    (U,) int ndarray
        Proposed marker per fragment (the first frame that proposes one decides), -1
        where none.  A marker is only proposed for a fragment if it is missing in all
        the fragment's frames.
    """
    visible = np.isfinite(fragments).all(-1)
    avail = np.isfinite(positions).all(-1)
    long = visible.sum(0) >= min_frames
    out = np.full(fragments.shape[1], -1, dtype=np.int64)
    for f in frames:
        us = np.flatnonzero(visible[f] & long)
        miss = np.flatnonzero(~avail[f] & np.isfinite(estimates[f]).all(-1))
        if len(us) < 4 or len(miss) < 4:
            continue
        pts = fragments[f, us]
        miss = miss[cKDTree(pts).query(estimates[f, miss])[0] < radius]
        if len(miss) < 4:
            continue
        match, _ = match_template(pts, estimates[f, miss], headings=1)
        for i in np.flatnonzero((match >= 0) & (out[us] < 0)):
            u, m = us[i], miss[match[i]]
            if not avail[visible[:, u], m].any():
                out[u] = m
    return out


# --------------------------------------------------------------------------- subjects


def _prefix(label: str) -> str | None:
    return label.split(":", 1)[0] + ":" if ":" in label else None


def _c3d_prefixes(markers: Markers) -> list[str]:
    try:
        v = markers.attrs["c3d_parameters"]["SUBJECTS"]["parameters"]["LABEL_PREFIXES"]["value"]
    except (KeyError, TypeError):
        return []
    return [str(x).strip() for x in (v if isinstance(v, list) else [v]) if str(x).strip()]


def subject_groups(
    markers: Markers, reference: np.ndarray, *,
    mode: Literal["auto", "none"] = "auto", gap: float = 0.3,
    min_markers: int = MIN_SUBJECT_MARKERS, min_span: float = MIN_SUBJECT_SPAN,
) -> list[tuple[str, np.ndarray]]:
    """The subjects of a take: ``[(name, marker indices)]`` (one group: one subject).

    ``auto``: the C3D's ``SUBJECTS:LABEL_PREFIXES`` (two or more), else label
    prefixes ``Name:`` (two or more), else groups of the reference pose whose
    markers are all more than ``gap`` from every other group's (single linkage)
    and that span a body (``min_span``).  Groups smaller than ``min_markers``, and
    groups in space that span less than ``min_span``, join the subject nearest to them.

    Parameters
    ----------
    markers : Markers
    reference : (M, 3) float ndarray
        Reference pose (NaN: unknown; such markers join the first subject).
    mode : {"auto", "none"}
    gap : float
        Metres between subjects standing apart.
    min_markers : int
    min_span : float
        Metres a group found in space must span (its two farthest markers) to be a
        subject of its own: a body part set apart by a sparse marker set is not one
        (:data:`MIN_SUBJECT_SPAN`).

    Returns
    -------
    list of (str, (K,) int ndarray)
    """
    M = len(markers.labels)
    everyone = [("all", np.arange(M))]
    if mode == "none" or M < 2 * min_markers:
        return everyone
    if mode != "auto":
        raise ValueError(f"clean: subjects must be 'auto' or 'none', got {mode!r}")
    group = np.full(M, -1, dtype=np.int64)
    names: list[str] = []
    prefixes = _c3d_prefixes(markers)
    if len(prefixes) < 2:
        found = sorted({p for p in map(_prefix, markers.labels) if p})
        prefixes = found if len(found) >= 2 else []
    if prefixes:
        for i, lb in enumerate(markers.labels):
            for k, p in enumerate(prefixes):
                if lb.startswith(p):
                    group[i] = k
                    break
        names = [p.rstrip(":") for p in prefixes]
    else:
        ok = np.flatnonzero(np.isfinite(reference).all(1))
        if len(ok) < 2:
            return everyone
        pairs = cKDTree(reference[ok]).query_pairs(gap, output_type="ndarray")
        adj = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                            shape=(len(ok), len(ok)))
        n, lab = connected_components(adj, directed=False)
        group[ok] = lab
        names = [f"subject{k + 1}" for k in range(n)]
    sizes = np.bincount(group[group >= 0], minlength=len(names))
    big = np.flatnonzero(sizes >= min_markers)
    if len(big) < 2:
        return everyone
    group = _join_nearest(reference, group, big)
    if not prefixes:  # groups found in space: a subject spans a body
        span = np.array([pdist(reference[(group == g) & np.isfinite(reference).all(1)])
                         .max(initial=0.0) for g in big])
        big = big[span >= min_span]
        if len(big) < 2:
            return everyone
        group = _join_nearest(reference, group, big)
    return [(names[g], np.flatnonzero(group == g)) for g in big]


def _join_nearest(reference: np.ndarray, group: np.ndarray, big: np.ndarray) -> np.ndarray:
    """``group`` with every marker outside the ``big`` groups in the big group whose
    median is nearest to it (unknown position: the first big group)."""
    group = group.copy()
    centre = {int(g): np.nanmedian(reference[group == g], axis=0) for g in big}
    for i in np.flatnonzero(~np.isin(group, big)):
        if np.isfinite(reference[i]).all():
            group[i] = min(centre, key=lambda g: np.linalg.norm(reference[i] - centre[g]))
        else:
            group[i] = int(big[0])
    return group


def fragment_subjects(markers: Markers, groups: list[tuple[str, np.ndarray]]) -> np.ndarray:
    """The subject of each fragment: the one whose visible markers are nearest to it
    (median over the fragment's frames of the distance to the subject's nearest
    marker).

    Returns
    -------
    (U,) int ndarray
        Index into ``groups``.
    """
    frags, P = markers.fragments, markers.positions
    U = frags.shape[1]
    out = np.zeros(U, dtype=np.int64)
    if len(groups) < 2 or U == 0:
        return out
    fvis = np.isfinite(frags).all(-1)
    for u in range(U):
        f = np.flatnonzero(fvis[:, u])
        if not len(f):
            continue
        f = f[:: max(1, len(f) // 20)]
        best = []
        for _, idx in groups:
            q = P[f][:, idx]  # (n, K, 3)
            d = np.linalg.norm(q - frags[f, u][:, None], axis=-1)
            with np.errstate(all="ignore"):
                dm = np.nanmin(np.where(np.isfinite(d), d, np.inf), axis=1)
            best.append(np.median(dm))
        out[u] = int(np.argmin(best))
    return out
