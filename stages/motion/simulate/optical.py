"""The optical capture system: cameras, what they see, and how trajectories fragment.

* **cameras** — :func:`camera_ring`: ``n_cameras`` on a ring around the capture
  volume; :func:`calibration_cameras`: the ring around the calibration pose
  (for the marker layout);
* **occlusion** — :func:`marker_visibility`: a marker is seen by a camera when
  its normal faces it (within ``max_view_angle``) and the ray to the camera
  misses every body capsule (a coarse occluder slightly inside the skin;
  ray-capsule tests vectorised over frames, markers, cameras and capsules);
  :func:`crowded`: markers closer than ``min_separation`` to another (skin
  folds) merge in the images and are lost;
* **fragmentation** — :func:`fragment_capture`, the way Vicon output comes:
  every visible run of a marker is its own trajectory, runs break at random
  (``break_rate`` per marker per second), and short ghost trajectories appear
  off the skin (``ghost_rate`` per second).  The runs crossing the *label
  frame* (the frame with the most visible markers, the reference frame the
  ``clean`` stage picks by default) carry the marker labels; every other run
  is an unlabelled fragment ``*N``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from mocapflow.pipeline import Context
from mocapflow.stages.motion.simulate.body import Body

__all__ = [
    "calibration_cameras",
    "camera_ring",
    "crowded",
    "fragment_capture",
    "marker_visibility",
    "segment_distance",
]


# --------------------------------------------------------------------------- cameras


def camera_ring(
    root_path: np.ndarray, *, n_cameras: int = 12, radius: float | None = None,
    heights: tuple[float, float] = (2.6, 1.3),
) -> np.ndarray:
    """Camera positions on a ring around the capture volume.

    Parameters
    ----------
    root_path : (F, 3) float ndarray
        Root positions (the volume is centred on their mean, horizontally).
    n_cameras : int
    radius : float, optional
        Ring radius; default 3.5 m or 2 m beyond the farthest root position.
    heights : (float, float)
        Camera heights, alternating.

    Returns
    -------
    (n_cameras, 3) float ndarray
    """
    c = root_path.mean(0)
    ext = float(np.max(np.linalg.norm((root_path - c)[:, [0, 2]], axis=1))) if len(root_path) \
        else 0.0
    r = radius if radius is not None else max(3.5, ext + 2.0)
    az = 2 * np.pi * (np.arange(n_cameras) + 0.5) / n_cameras
    h = np.array([heights[k % 2] for k in range(n_cameras)])
    return np.stack([c[0] + r * np.cos(az), h, c[2] + r * np.sin(az)], axis=1)


def calibration_cameras(
    vertices: np.ndarray, root: np.ndarray, *, n_cameras: int = 12
) -> np.ndarray:
    """Cameras for the marker layout: a ring around the calibration pose itself.

    The ring is centred under the calibration root, on the floor the pose stands
    on, so the layout does not depend on where the rest of the motion goes.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        Skin in the calibration pose.
    root : (3,) float ndarray
        Root position of the calibration pose.
    n_cameras : int

    Returns
    -------
    (n_cameras, 3) float ndarray
    """
    offset = np.array([root[0], np.min(vertices[:, 1]), root[2]])
    return camera_ring(np.zeros((1, 3)), n_cameras=n_cameras) + offset


# --------------------------------------------------------------------------- visibility


def segment_distance(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray,
                     q1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest distance between segments ``p0–p1`` and ``q0–q1`` (broadcasting).

    Parameters
    ----------
    p0, p1, q0, q1 : (..., 3) float ndarray

    Returns
    -------
    distance : (...) float ndarray
    t : (...) float ndarray
        Parameter in [0, 1] of the closest point on ``q0–q1``.
    """
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a = np.einsum("...i,...i->...", d1, d1)
    e = np.einsum("...i,...i->...", d2, d2)
    f = np.einsum("...i,...i->...", d2, r)
    c = np.einsum("...i,...i->...", d1, r)
    b = np.einsum("...i,...i->...", d1, d2)
    den = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(den > 1e-12 * a * e, np.clip((b * f - c * e) / den, 0, 1), 0.0)
        t = np.where(e > 1e-15, (b * s + f) / e, 0.0)
        s = np.where(t < 0, np.where(a > 1e-15, np.clip(-c / a, 0, 1), 0.0), s)
        s = np.where(t > 1, np.where(a > 1e-15, np.clip((b - c) / a, 0, 1), 0.0), s)
    t = np.clip(t, 0, 1)
    cp = p0 + d1 * s[..., None]
    cq = q0 + d2 * t[..., None]
    return np.linalg.norm(cp - cq, axis=-1), t


def _point_segment_distance(x: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """``(...)`` distance from points ``x`` to segments ``p0``-``p1`` (all ``(..., 3)``).

    One segment per point (a ray each); the dot products are einsums, unlike
    :func:`~mocapflow.stages.motion.simulate.body.point_segment_distance` (one
    segment, matmul), whose last bits differ: the visibility tests keep this one.
    """
    d = p1 - p0
    L2 = np.einsum("...i,...i->...", d, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip(np.where(L2 > 0, np.einsum("...i,...i->...", x - p0, d) / L2, 0.0), 0, 1)
    return np.linalg.norm(p0 + d * t[..., None] - x, axis=-1)


def _visibility_chunk(item: tuple) -> np.ndarray:
    (X, N, R, p, cams, caps_joint, caps_a, caps_b, caps_r, caps_depth, forward, bind,
     max_cos, offset) = item
    Fc, M, _ = X.shape
    origin = X + offset * N  # (Fc, M, 3)
    to_cam = cams[None, None] - origin[:, :, None]  # (Fc, M, C, 3)
    dist = np.linalg.norm(to_cam, axis=-1)
    facing = np.einsum("fmi,fmci->fmc", N, to_cam) / np.maximum(dist, 1e-12) > max_cos
    f_i, m_i, c_i = np.nonzero(facing)
    o = origin[f_i, m_i]  # (P, 3) ray start
    e = cams[c_i]  # (P, 3) ray end
    blocked = np.zeros(len(f_i), dtype=bool)
    for k in range(len(caps_joint)):
        j = caps_joint[k]
        # the capsule posed in each frame (world), flattened along its posed forward axis
        a = np.einsum("fij,j->fi", R[:, j], caps_a[k] - bind[j]) + p[:, j]
        b = np.einsum("fij,j->fi", R[:, j], caps_b[k] - bind[j]) + p[:, j]
        fw = np.einsum("fij,j->fi", R[:, j], forward)
        s = 1.0 / caps_depth[k] - 1.0
        ak, fk = a[f_i], fw[f_i]
        bb = b + np.einsum("fi,fi->f", b - a, fw)[:, None] * s * fw
        # cull with the bounding sphere of the (stretched) capsule
        centre = 0.5 * (ak + bb[f_i])
        rad = 0.5 * np.linalg.norm(bb[f_i] - ak, axis=1) + caps_r[k].max()
        near = ~blocked & (_point_segment_distance(centre, o, e) < rad)
        if not near.any():
            continue
        idx = np.flatnonzero(near)
        ok_, ek, ak2, fk2 = o[idx], e[idx], ak[idx], fk[idx]
        oo = ok_ + np.einsum("ni,ni->n", ok_ - ak2, fk2)[:, None] * s * fk2
        ee = ek + np.einsum("ni,ni->n", ek - ak2, fk2)[:, None] * s * fk2
        d, t = segment_distance(oo, ee, ak2, bb[f_i[idx]])
        r = caps_r[k, 0] + t * (caps_r[k, 1] - caps_r[k, 0])
        blocked[idx[d < r]] = True
    seen = np.zeros((Fc, M), dtype=np.int16)
    np.add.at(seen, (f_i[~blocked], m_i[~blocked]), 1)
    return seen


def marker_visibility(
    markers: np.ndarray,
    normals: np.ndarray,
    body: Body,
    R: np.ndarray,
    p: np.ndarray,
    cameras: np.ndarray,
    *,
    max_view_angle: float = 80.0,
    offset: float = 0.01,
    min_radius: float = 0.02,
    chunk: int = 16,
    ctx: Context | None = None,
) -> np.ndarray:
    """How many cameras see each marker (ray casting against the body capsules).

    Parameters
    ----------
    markers, normals : (F, M, 3) float ndarray
        Marker centres and skin normals.
    body : Body
    R, p : (F, J, 3, 3), (F, J, 3) float ndarray
        Skinning transforms (move the capsules).
    cameras : (C, 3) float ndarray
    max_view_angle : float
        A marker is seen by a camera within this angle of its normal (degrees).
    offset : float
        Rays start this far out along the normal (metres).
    min_radius : float
        Capsules thinner than this (fingers, toes) are not occluders.
    chunk : int
        Frames per work item (items go through ``ctx.map``).
    ctx : Context, optional

    Returns
    -------
    (F, M) int16 ndarray
    """
    ctx = ctx or Context()
    caps = body.capsules
    big = np.flatnonzero(caps.radius.max(1) >= min_radius)  # fingers and toes do not occlude
    bind = body.bind_positions()
    F = markers.shape[0]
    items = []
    for s in range(0, F, chunk):
        sl = slice(s, min(F, s + chunk))
        items.append((markers[sl], normals[sl], R[sl], p[sl], cameras, caps.joint[big],
                      caps.start[big], caps.end[big], caps.radius[big], caps.depth[big],
                      caps.forward, bind,
                      float(np.cos(np.radians(max_view_angle))), offset))
    return np.concatenate(ctx.map(_visibility_chunk, items), axis=0)


def crowded(positions: np.ndarray, min_separation: float) -> np.ndarray:
    """``(F, M)`` bool: markers closer than ``min_separation`` to another one.

    Their images merge in the cameras (skin folding at the armpit or the groin),
    so the system reconstructs neither.
    """
    out = np.zeros(positions.shape[:2], dtype=bool)
    if min_separation <= 0:
        return out
    for f, P in enumerate(positions):
        pairs = cKDTree(P).query_pairs(min_separation, output_type="ndarray")
        if len(pairs):
            out[f, pairs.ravel()] = True
    return out


# --------------------------------------------------------------------------- fragmentation


def fragment_capture(
    observed: np.ndarray,
    visible: np.ndarray,
    *,
    rate: float,
    rng: np.random.Generator,
    break_rate: float = 0.2,
    ghost_rate: float = 1.0,
    ghost_source: np.ndarray | None = None,
    ghost_normals: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Break marker trajectories into Vicon-style fragments; labels only at the label frame.

    Parameters
    ----------
    observed : (F, M, 3) float ndarray
        Noisy marker positions (ignored where not visible).
    visible : (F, M) bool ndarray
    rate : float
    rng : numpy.random.Generator
    break_rate : float
        Extra trajectory breaks per marker per second of visibility.
    ghost_rate : float
        Ghost trajectories per second (1-15 frames, 4-10 cm off the skin).
    ghost_source, ghost_normals : (F, M, 3) float ndarray, optional
        Where ghosts appear (true markers and normals); no ghosts without them.

    Returns
    -------
    labelled : (F, M, 3) float ndarray
        Each marker's run through the label frame, NaN elsewhere.
    fragments : (F, U, 3) float ndarray
        Every other run and the ghosts, ordered by first frame.
    fragment_marker : (U,) int ndarray
        True marker of each fragment, -1 for ghosts.
    label_frame : int
    """
    F, M, _ = observed.shape
    vis = visible.copy()
    brk = vis & (rng.random((F, M)) < break_rate / rate)
    label_frame = int(np.argmax(vis.sum(1)))
    labelled = np.full_like(observed, np.nan)
    frags: list[tuple[int, int, int, int]] = []  # (start, marker, a, b)
    for m in range(M):
        v = vis[:, m]
        if not v.any():
            continue
        starts = np.flatnonzero(v & np.concatenate([[True], ~v[:-1]]) | brk[:, m])
        starts = starts[v[starts]]
        ends = np.concatenate([starts[1:], [F]])
        for a, b in zip(starts, ends):
            run = np.flatnonzero(v[a:b])
            if len(run) == 0:
                continue
            b2 = a + run[-1] + 1
            # runs are contiguous: cut at the first gap
            gap = np.flatnonzero(~v[a:b2])
            b2 = a + gap[0] if len(gap) else b2
            if a <= label_frame < b2:
                labelled[a:b2, m] = observed[a:b2, m]
            else:
                frags.append((a, m, a, b2))
    ghosts = []
    if ghost_rate > 0 and ghost_source is not None and ghost_normals is not None:
        n_ghost = rng.poisson(ghost_rate * F / rate)
        for _ in range(n_ghost):
            m = int(rng.integers(M))
            a = int(rng.integers(F))
            b = min(F, a + int(rng.integers(1, 16)))
            off = rng.uniform(0.04, 0.10)
            g = ghost_source[a:b, m] + off * ghost_normals[a:b, m] + rng.normal(0, 0.002, 3)
            ghosts.append((a, g))
    order = sorted([(a, 0, k) for k, (a, _, _, _) in enumerate(frags)]
                   + [(a, 1, k) for k, (a, _) in enumerate(ghosts)])
    U = len(order)
    fragments = np.full((F, U, 3), np.nan)
    fragment_marker = np.full(U, -1, dtype=np.int64)
    for u, (_, kind, k) in enumerate(order):
        if kind == 0:
            _, m, a, b = frags[k]
            fragments[a:b, u] = observed[a:b, m]
            fragment_marker[u] = m
        else:
            a, g = ghosts[k]
            fragments[a:a + len(g), u] = g
    return labelled, fragments, fragment_marker, label_frame
