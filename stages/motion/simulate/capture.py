"""Dense-marker capture simulator with ground truth (for Park & Hodgins 2006).

A body (:mod:`mocapflow.stages.motion.simulate.body`) is driven by a motion with
linear-blend skinning **plus known non-rigid skin motion**, ~350 markers are
stuck on its skin, and a Vicon-like capture of them is simulated:

* **markers** — weighted farthest-point sampling of points spread over the
  skin (:class:`SurfacePoints`: triangle + barycentric coordinates), denser at
  the elbows and shoulders (``density``), sparser on the head, hands and feet,
  none on the soles nor where the calibration pose hides them (so every marker
  can be labelled); marker centres sit ``marker_radius`` above the skin.  With
  350 markers on a 1.75 m body the nearest-marker distance is 45-65 mm (median
  ~58 mm) and the mean one-ring distance ~75 mm.
* **skin motion** (:class:`SkinDynamics`) — *muscle bulges* along the bind-pose
  normal proportional to a joint's flexion angle (biceps ← elbow, quadriceps ←
  knee, calf ← ankle, deltoid ← shoulder); *flesh jiggle*: a damped spring per
  soft region (belly, buttocks, thighs, upper-arm undersides, chest) driven by
  the acceleration of its anchor point; *breathing*: a sinusoidal swell of the
  chest and belly.  Vertices and markers move with the same fields, so the
  per-frame mesh is the true skin under the markers.
* **occlusion** — ``n_cameras`` cameras on a ring around the capture volume; a
  marker is reconstructed when at least ``min_cameras`` see it: its normal faces
  the camera (within ``max_view_angle``) and the ray to the camera misses every
  body capsule (a coarse occluder slightly inside the skin; ray–capsule tests
  vectorised over frames, markers, cameras and capsules); markers closer than
  ``min_separation`` to another (skin folds) merge in the images and are lost.
* **measurement noise** — isotropic Gaussian, ``noise`` metres.
* **fragmentation** — the way Vicon output comes: every visible run of a marker
  is its own trajectory, runs break at random (``break_rate`` per marker per
  second), and short ghost trajectories appear off the skin (``ghost_rate`` per
  second).  The runs crossing the *label frame* (the frame with the most visible
  markers, the reference frame the ``clean`` stage picks by default) carry the
  marker labels; every other run is an unlabelled fragment ``*N``.

The capture starts with ``calibration`` seconds in the skeleton's rest pose
(T-pose), blended into the motion.

Ground truth (``truth`` record, see :func:`simulate_capture`): true marker
positions, visibility, part (dominant skin-weight joint) and body region per
marker, the true fragment → marker map, the bind-pose marker layout, and the
true mesh per frame (``mesh`` output).  :func:`score_merges` and
:func:`region_errors` score a cleaned capture against it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context, FilePath, stage
from mocapflow.stages.motion.datatypes import Markers, Mesh, Motion
from mocapflow.stages.motion.geometry import vertex_normals
from mocapflow.stages.motion.kinematics import (
    quat_angle,
    quat_from_axis_angle,
    quat_identity,
    quat_slerp,
)

from .body import Body, load_makehuman_body, procedural_body, skin, skinning_transforms

__all__ = [
    "REGIONS",
    "SurfacePoints",
    "SkinDynamics",
    "calibration_cameras",
    "camera_ring",
    "capture_motion",
    "crowded",
    "fragment_capture",
    "gap_mask",
    "marker_regions",
    "marker_visibility",
    "place_markers",
    "region_errors",
    "score_merges",
    "sample_surface",
    "segment_distance",
    "capture_body",
    "simulate_capture",
]

#: Body regions of the Table-2 style report, in order.
REGIONS = ("abdomen", "elbow", "thigh", "knee", "chest", "back", "shoulder", "upper_arm",
           "forearm", "calf", "pelvis", "neck", "head", "hand", "foot")


# --------------------------------------------------------------------------- names


def _find(names: list[str], pattern: str) -> int | None:
    rx = re.compile(pattern, re.I)
    for i, n in enumerate(names):
        if rx.fullmatch(n):
            return i
    return None


def _sides(names: list[str], pattern: str) -> list[int]:
    """Joint indices for a CMU-style name pattern with ``{s}`` = Left/Right."""
    out = []
    for s in ("Left", "Right"):
        j = _find(names, pattern.format(s=s))
        if j is not None:
            out.append(j)
    return out


# --------------------------------------------------------------------------- markers


@dataclass(eq=False)
class SurfacePoints:
    """Points on a body's skin, as triangles and barycentric coordinates.

    Attributes
    ----------
    face : (N,) int ndarray
        Triangle of each point.
    barycentric : (N, 3) float ndarray
        Weights of the triangle's corners.
    """

    face: np.ndarray
    barycentric: np.ndarray

    def interpolate(self, body: Body, values: np.ndarray) -> np.ndarray:
        """Per-vertex ``values (..., V, k)`` at the points -> ``(..., N, k)``."""
        corners = body.faces[self.face]  # (N, 3)
        return np.einsum("nc,...nck->...nk", self.barycentric, values[..., corners, :])

    def points(self, body: Body) -> np.ndarray:
        """``(N, 3)`` bind-pose positions."""
        return self.interpolate(body, body.vertices)

    def normals(self, body: Body) -> np.ndarray:
        """``(N, 3)`` bind-pose unit normals (interpolated vertex normals)."""
        n = self.interpolate(body, body.normals)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def weights(self, body: Body) -> np.ndarray:
        """``(N, J)`` skinning weights (interpolated)."""
        return self.interpolate(body, body.weights)


def sample_surface(body: Body, n: int, *, rng: np.random.Generator) -> SurfacePoints:
    """``n`` points spread uniformly (by area) over the body's triangles."""
    v, f = body.vertices, body.faces
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    face = rng.choice(len(f), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s1 = np.sqrt(r1)
    bary = np.stack([1 - s1, s1 * (1 - r2), s1 * r2], axis=1)
    return SurfacePoints(face, bary)


def place_markers(
    body: Body,
    n_markers: int,
    *,
    rng: np.random.Generator,
    density: dict[str, float] | None = None,
    eligible: np.ndarray | None = None,
    n_candidates: int = 20000,
) -> SurfacePoints:
    """Place ``n_markers`` markers on the skin by weighted farthest-point sampling.

    Candidates are points spread uniformly over the skin; the next marker is the
    candidate maximising ``density × distance to the nearest chosen marker``,
    so spacing scales like ``1 / density``.

    Parameters
    ----------
    body : Body
    n_markers : int
    rng : numpy.random.Generator
        Candidate points and the first marker.
    density : dict, optional
        ``{"joint": factor near elbows/shoulders, "extremity": factor on head,
        hands, feet}``; default ``{"joint": 1.5, "extremity": 0.45}``.
    eligible : (V,) bool ndarray, optional
        Vertices allowed (e.g. those visible in the calibration pose, so every
        marker can be labelled): a candidate needs all three corners eligible.
        Soles and fingers are never eligible.
    n_candidates : int
        Candidate points.

    Returns
    -------
    SurfacePoints
    """
    dens = {"joint": 1.5, "extremity": 0.45, **(density or {})}
    names = body.skeleton.names
    bind = body.bind_positions()
    cand = sample_surface(body, n_candidates, rng=rng)
    P, n = cand.points(body), cand.normals(body)
    part = np.argmax(cand.weights(body), axis=1)
    w = np.ones(len(P))
    for j in _sides(names, "{s}ForeArm") + _sides(names, "{s}Arm"):
        d = np.linalg.norm(P - bind[j], axis=1)
        w = np.maximum(w, 1.0 + (dens["joint"] - 1.0) * np.exp(-0.5 * (d / 0.07) ** 2))
    extremity = [j for j, nm in enumerate(names)
                 if re.search(r"head|hand|finger|thumb|foot|toe", nm, re.I)]
    w[np.isin(part, extremity)] *= dens["extremity"]
    feet = [j for j, nm in enumerate(names) if re.search(r"foot|toe", nm, re.I)]
    fingers = [j for j, nm in enumerate(names) if re.search(r"finger|thumb", nm, re.I)]
    ok = ~(np.isin(part, feet) & (n[:, 1] < -0.5)) & ~np.isin(part, fingers)  # no soles
    if eligible is not None:
        ok &= np.asarray(eligible, bool)[body.faces[cand.face]].all(1)
    idx = np.flatnonzero(ok)
    if n_markers > len(idx):
        raise ValueError(f"place_markers: {n_markers} markers but only {len(idx)} eligible "
                         "skin points")
    Pc, wc = P[idx], w[idx]
    chosen = [int(rng.integers(len(idx)))]
    dmin = np.linalg.norm(Pc - Pc[chosen[0]], axis=1)
    for _ in range(n_markers - 1):
        k = int(np.argmax(dmin * wc))
        chosen.append(k)
        dmin = np.minimum(dmin, np.linalg.norm(Pc - Pc[k], axis=1))
    sel = idx[np.array(chosen)]
    return SurfacePoints(cand.face[sel], cand.barycentric[sel])


def marker_regions(body: Body, points: np.ndarray, normals: np.ndarray,
                   part: np.ndarray) -> np.ndarray:
    """Body region (index into :data:`REGIONS`) of skin points.

    Parameters
    ----------
    body : Body
    points, normals : (M, 3) float ndarray
        Bind-pose positions and normals.
    part : (M,) int ndarray
        Dominant joint.

    Returns
    -------
    (M,) int ndarray
    """
    names = body.skeleton.names
    bind = body.bind_positions()
    P, n = points, normals
    pname = [names[j].lower() for j in part]
    out = np.empty(len(P), dtype=np.int64)
    near = {}
    for key, pat, r in (("elbow", "{s}ForeArm", 0.075), ("knee", "{s}Leg", 0.085),
                        ("shoulder", "{s}Arm", 0.08)):
        js = _sides(names, pat)
        d = np.min([np.linalg.norm(P - bind[j], axis=1) for j in js], axis=0) if js else \
            np.full(len(P), np.inf)
        near[key] = d < r
    for i, pn in enumerate(pname):
        if near["elbow"][i]:
            reg = "elbow"
        elif near["knee"][i]:
            reg = "knee"
        elif near["shoulder"][i]:
            reg = "shoulder"
        elif re.search(r"finger|thumb|hand", pn):
            reg = "hand"
        elif re.search(r"foot|toe", pn):
            reg = "foot"
        elif "head" in pn:
            reg = "head"
        elif "neck" in pn:
            reg = "neck"
        elif "forearm" in pn:
            reg = "forearm"
        elif re.search(r"arm|clavicle|shoulder", pn):
            reg = "upper_arm" if "arm" in pn else "shoulder"
        elif re.search(r"upleg|thigh", pn):
            reg = "thigh"
        elif re.search(r"leg|shin|calf", pn):
            reg = "calf"
        elif re.search(r"spine1|chest", pn):
            reg = "chest" if n[i, 2] > 0.2 else "back"
        elif re.search(r"hipjoint|pelvis", pn):
            reg = "pelvis"
        else:  # hips, lower back, spine
            reg = "abdomen" if n[i, 2] > 0.2 else ("back" if n[i, 2] < -0.2 else "pelvis")
        out[i] = REGIONS.index(reg)
    return out


# --------------------------------------------------------------------------- skin dynamics


@dataclass
class SkinDynamics:
    """Known non-rigid skin motion on top of linear-blend skinning.

    Attributes
    ----------
    bulge : float
        Scale of the muscle bulges (1 = about 1 cm at 90° of flexion).
    jiggle : float
        Scale of the flesh jiggle springs.
    breathing : float
        Scale of breathing (1 = 4 mm swell at 0.25 Hz).
    """

    bulge: float = 1.0
    jiggle: float = 1.0
    breathing: float = 1.0

    def regions(self, body: Body, points: np.ndarray, normals: np.ndarray,
                part: np.ndarray) -> dict[str, list[dict[str, Any]]]:
        """Masks of every effect over bind-pose points (vertices or markers)."""
        names = body.skeleton.names
        bind = body.bind_positions()
        sk = body.skeleton
        out: dict[str, list[dict[str, Any]]] = {"bulge": [], "jiggle": [], "breathing": []}

        def along(j: int, c: int, centre: float, width: float) -> np.ndarray:
            a, b = bind[j], bind[c]
            ab = b - a
            t = (points - a) @ ab / max(ab @ ab, 1e-12)
            return np.exp(-0.5 * ((t - centre) / width) ** 2)

        def side(direction: np.ndarray, k: float = 1.0) -> np.ndarray:
            return np.clip(normals @ direction, 0.0, 1.0) ** k

        fwd, up = np.array([0.0, 0, 1]), np.array([0.0, 1, 0])
        # bulges: (bone pattern, driver pattern, centre, width, direction, amplitude)
        specs = [("{s}Arm", "{s}ForeArm", 0.55, 0.22, fwd, 0.012),
                 ("{s}UpLeg", "{s}Leg", 0.45, 0.22, fwd, 0.010),
                 ("{s}Leg", "{s}Foot", 0.30, 0.18, -fwd, 0.008),
                 ("{s}Arm", "{s}Arm", 0.12, 0.15, up, 0.008)]
        for bone_p, drv_p, c0, wd, dirn, amp in specs:
            for s in ("Left", "Right"):
                j = _find(names, bone_p.format(s=s))
                d = _find(names, drv_p.format(s=s))
                kids = sk.children(j) if j is not None else []
                if j is None or d is None or not kids:
                    continue
                mask = along(j, kids[0], c0, wd) * side(dirn) * (part == j)
                if mask.max() > 0:
                    out["bulge"].append({"mask": mask, "driver": d, "amp": amp * self.bulge})
        # jiggle: (region selector, anchor joint pattern, frequency Hz, damping, gain)
        torso = [j for j, nm in enumerate(names)
                 if re.search(r"^(hips|lowerback|spine)$", nm, re.I)]
        chest = [j for j, nm in enumerate(names) if re.search(r"^spine1$", nm, re.I)]
        hipj = [j for j, nm in enumerate(names) if re.search(r"hips|hipjoint", nm, re.I)]
        jig = []
        sp = _find(names, "Spine")
        if torso and sp is not None:
            jig.append((np.isin(part, torso) * side(fwd, 1.5), sp, 3.5, 0.18, 1.0))
        hips = _find(names, "Hips")
        if hipj and hips is not None:
            jig.append((np.isin(part, hipj) * side(-fwd, 1.5), hips, 4.0, 0.2, 0.8))
        s1 = _find(names, "Spine1")
        if chest and s1 is not None:
            jig.append((np.isin(part, chest) * side(fwd, 2.0), s1, 4.5, 0.22, 0.5))
        for s in ("Left", "Right"):
            j = _find(names, f"{s}UpLeg")
            if j is not None and sk.children(j):
                jig.append((along(j, sk.children(j)[0], 0.4, 0.25) * (part == j), j, 5.0,
                            0.25, 0.8))
            j = _find(names, f"{s}Arm")
            if j is not None and sk.children(j):
                jig.append((along(j, sk.children(j)[0], 0.5, 0.25) * (part == j)
                            * side(-up, 1.0), j, 5.5, 0.25, 0.7))
        for mask, anchor, f, z, g in jig:
            if mask.max() > 0:
                out["jiggle"].append({"mask": mask, "anchor": anchor, "freq": f, "damping": z,
                                      "gain": g * self.jiggle})
        if torso or chest:
            m = np.isin(part, torso + chest) * side(fwd, 1.0)
            out["breathing"].append({"mask": m, "amp": 0.004 * self.breathing, "freq": 0.25})
        return out

    def apply(
        self,
        body: Body,
        motion: Motion,
        R: np.ndarray,
        p: np.ndarray,
        points: np.ndarray,
        normals: np.ndarray,
        weights: np.ndarray,
        part: np.ndarray,
        *,
        rng: np.random.Generator,
    ) -> np.ndarray:
        """Skinned positions of bind-pose points with bulges, jiggle and breathing.

        Parameters
        ----------
        body : Body
        motion : Motion
        R, p : (F, J, 3, 3), (F, J, 3) float ndarray
            Skinning transforms (:func:`skinning_transforms`).
        points, normals : (N, 3) float ndarray
            Bind-pose points and their normals.
        weights : (N, J) float ndarray
        part : (N,) int ndarray
            Dominant joint per point (selects the regions).
        rng : numpy.random.Generator
            Breathing phase and rate.

        Returns
        -------
        (F, N, 3) float ndarray
        """
        F = R.shape[0]
        reg = self.regions(body, points, normals, part)
        sk = body.skeleton
        # pose-space displacements along the bind normal
        s = np.zeros((F, len(points)))
        if reg["bulge"]:
            ang = quat_angle(motion.rotations, quat_identity(motion.rotations.shape[:-1]))
            mnames = {n: i for i, n in enumerate(motion.skeleton.names)}
            for b in reg["bulge"]:
                k = mnames.get(sk.names[b["driver"]])
                if k is None:
                    continue
                a = np.clip(ang[:, k] / (np.pi / 2), 0.0, 1.5)
                s += b["amp"] * a[:, None] * b["mask"][None]
        t = np.arange(F) / motion.rate
        for b in reg["breathing"]:
            f = b["freq"] * rng.uniform(0.85, 1.15)
            ph = rng.uniform(0, 2 * np.pi)
            s += b["amp"] * 0.5 * (1 + np.sin(2 * np.pi * f * t + ph))[:, None] * b["mask"][None]
        bind = body.bind_positions()
        out = np.zeros((F, len(points), 3))
        for j in np.flatnonzero(weights.max(0) > 0):
            idx = np.flatnonzero(weights[:, j] > 0)
            local = points[idx][None] + s[:, idx, None] * normals[idx][None] - bind[j]
            moved = np.einsum("fij,fnj->fni", R[:, j], local) + p[:, j, None]
            out[:, idx] += weights[idx, j][None, :, None] * moved
        # jiggle: damped springs driven by anchor accelerations (world frame)
        dt = 1.0 / motion.rate
        for b in reg["jiggle"]:
            j = b["anchor"]
            m = b["mask"]
            c = (points * m[:, None]).sum(0) / max(m.sum(), 1e-12)
            anchor = np.einsum("fij,j->fi", R[:, j], c - bind[j]) + p[:, j]
            acc = np.gradient(np.gradient(anchor, dt, axis=0), dt, axis=0)
            w0 = 2 * np.pi * b["freq"]
            u = np.zeros(3)
            v = np.zeros(3)
            disp = np.zeros((F, 3))
            for f in range(F):
                v += dt * (-acc[f] - 2 * b["damping"] * w0 * v - w0 * w0 * u)
                u += dt * v
                disp[f] = u
            disp *= b["gain"]
            nrm = np.linalg.norm(disp, axis=1, keepdims=True)
            disp *= np.minimum(1.0, 0.03 / np.maximum(nrm, 1e-12))
            out += disp[:, None, :] * m[None, :, None]
        return out


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


# --------------------------------------------------------------------------- motion


def capture_motion(
    kind: str, n_frames: int, *, rate: float, rng: np.random.Generator,
    calibration: float = 0.5, calibration_abduction: float = 12.0, bvh: str | None = None,
) -> Motion:
    """The motion of a simulated capture, starting with a rest-pose calibration.

    Parameters
    ----------
    kind : {"dynamic", "walk", "range_of_motion"}
        ``dynamic``: a run on a treadmill (forward progression removed);
        ``walk``: a treadmill walk; ``range_of_motion``: joint groups flexed in
        turn.  Ignored when ``bvh`` is given.
    n_frames : int
        Total frames, calibration included.
    rate : float
    rng : numpy.random.Generator
    calibration : float
        Seconds of calibration pose at the start (the rest pose, arms out, with
        the legs abducted by ``calibration_abduction`` degrees so the inner
        thighs are visible), then 0.25 s of blending into the motion.
    calibration_abduction : float
        Hip abduction of the calibration pose (degrees).
    bvh : str, optional
        A BVH file to drive the body instead (resampled to ``rate``).

    Returns
    -------
    Motion
    """
    from .motion import procedural_range_of_motion, procedural_walk

    n_cal = int(round(calibration * rate))
    n_blend = int(round(0.25 * rate)) if n_cal else 0
    n_mot = max(n_frames - n_cal, 1)
    if bvh is not None:
        from mocapflow.stages.motion.formats.bvh import read_bvh
        from mocapflow.stages.motion.kinematics import resample_motion

        m = read_bvh(bvh)
        if abs(m.rate - rate) > 1e-6:
            m = resample_motion(m, rate)
        if m.n_frames < n_mot:
            raise ValueError(f"{bvh}: {m.n_frames} frames at {rate} Hz, {n_mot} needed")
        m = m.replace(root_position=m.root_position[:n_mot], rotations=m.rotations[:n_mot],
                      translations=None if m.translations is None else m.translations[:n_mot])
    elif kind in ("dynamic", "walk"):
        m = procedural_walk(n_mot, rate=rate, gait="run" if kind == "dynamic" else "walk",
                            seed=rng)
        root = m.root_position.copy()
        root[:, [0, 2]] -= np.linspace(root[0, [0, 2]], root[-1, [0, 2]], n_mot)  # treadmill
        m = m.replace(root_position=root)
    elif kind == "range_of_motion":
        m = procedural_range_of_motion(n_mot, rate=rate, seed=rng)
    else:
        raise ValueError(f"unknown capture motion {kind!r} (dynamic, walk, range_of_motion)")
    if n_cal == 0:
        return m
    J = m.skeleton.n_joints
    rest = quat_identity((n_cal, J))
    # calibration "star" pose: legs abducted so the inner thighs are seen too
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        j = _find(m.skeleton.names, f"{side}UpLeg")
        if j is not None:
            rest[:, j] = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]),
                                              np.radians(sign * calibration_abduction))
    u = np.clip((np.arange(n_cal) - (n_cal - n_blend)) / max(n_blend, 1), 0, 1)
    u = u * u * (3 - 2 * u)
    rot = quat_slerp(rest, np.broadcast_to(m.rotations[0], rest.shape), u[:, None])
    root = np.broadcast_to(m.root_position[0], (n_cal, 3))
    tr = None
    if m.translations is not None:
        first = np.broadcast_to(m.translations[0], (n_cal,) + m.translations.shape[1:])
        tr = np.concatenate([first, m.translations])
    out = m.replace(rotations=np.concatenate([rot, m.rotations])[:n_frames],
                    root_position=np.concatenate([root, m.root_position])[:n_frames],
                    translations=None if tr is None else tr[:n_frames])
    out.attrs["calibration_frames"] = n_cal
    return out


def crowded(positions: np.ndarray, min_separation: float) -> np.ndarray:
    """``(F, M)`` bool: markers closer than ``min_separation`` to another one.

    Their images merge in the cameras (skin folding at the armpit or the groin),
    so the system reconstructs neither.
    """
    from scipy.spatial import cKDTree

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


def _vertex_normals_at(vertices: np.ndarray, faces: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Vertex normals ``(F, len(at), 3)`` of only the vertices ``at``."""
    touch = np.isin(faces, at).any(1)
    sub = faces[touch]
    used, inv = np.unique(sub, return_inverse=True)
    n = vertex_normals(vertices[:, used], inv.reshape(-1, 3))
    return n[:, np.searchsorted(used, at)]


# --------------------------------------------------------------------------- simulation


def _layout_rng(rng: np.random.Generator) -> np.random.Generator:
    """A generator for the marker layout, derived from ``rng``'s seed, not its state.

    The layout stream is a fixed child of ``rng``'s seed sequence, so it neither
    depends on what the motion draws before it nor changes the main stream (a
    generator without a seed sequence gives up 4 draws instead, before the motion).
    """
    seq = getattr(rng.bit_generator, "seed_seq", None)
    if not isinstance(seq, np.random.SeedSequence):
        return np.random.default_rng(rng.bit_generator.random_raw(4))
    child = np.random.SeedSequence(seq.entropy, spawn_key=(*seq.spawn_key, 0x5EED1A))
    return np.random.default_rng(child)


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


def capture_body(motion: Motion, *, body_mesh: str | None = None,
                 body_vertices: int = 3000) -> Body:
    """The body a capture is simulated on.

    Parameters
    ----------
    motion : Motion
        The driving motion (its skeleton shapes a procedural body).
    body_mesh : str, optional
        The MakeHuman ``makehuman_base.obj`` (rig and weights JSON beside it).
    body_vertices : int
        Vertex count of the procedural body.

    Returns
    -------
    Body
    """
    if body_mesh is not None:
        return load_makehuman_body(body_mesh)
    return procedural_body(motion.skeleton, n_vertices=body_vertices)


def _marker_sites(body: Body, motion: Motion, R: np.ndarray, p: np.ndarray, n_markers: int, *,
                  n_cameras: int, min_cameras: int, marker_radius: float,
                  rng: np.random.Generator) -> SurfacePoints:
    """Marker sites where the calibration pose (frame 0) shows them, so all can be labelled.

    The layout depends on the body and ``rng`` (the layout stream) only, never on
    the motion: a range-of-motion trial and a dynamic trial of one seed share it.
    """
    v0 = skin(body, R[:1], p[:1])
    n0 = vertex_normals(v0, body.faces)
    cams0 = calibration_cameras(v0[0], motion.root_position[0], n_cameras=n_cameras)
    seen0 = marker_visibility(v0 + marker_radius * n0, n0, body, R[:1], p[:1], cams0)[0]
    return place_markers(body, n_markers, rng=rng, eligible=seen0 >= min_cameras + 1)


def _moving_skin(body: Body, motion: Motion, R: np.ndarray, p: np.ndarray,
                 sites: SurfacePoints, dynamics: SkinDynamics, *, marker_radius: float,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True skin ``(F, V, 3)``, true marker centres ``(F, M, 3)`` and their normals.

    Markers are bind-pose points ``marker_radius`` above the skin, carried by the
    skin's weights and the same non-rigid fields as the vertices.
    """
    skin_n, skin_w = sites.normals(body), sites.weights(body)
    mpts = sites.points(body) + marker_radius * skin_n
    pts = np.concatenate([body.vertices, mpts])
    nrm = np.concatenate([body.normals, skin_n])
    W = np.concatenate([body.weights, skin_w])
    part = np.concatenate([body.part, np.argmax(skin_w, axis=1)])
    allpos = dynamics.apply(body, motion, R, p, pts, nrm, W, part, rng=rng)
    V = body.n_vertices
    mesh_seq, true = allpos[:, :V], allpos[:, V:]
    corners = np.unique(body.faces[sites.face])
    vn = np.zeros(mesh_seq.shape[:1] + (body.n_vertices, 3))
    vn[:, corners] = _vertex_normals_at(mesh_seq, body.faces, corners)
    normals = sites.interpolate(body, vn)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return mesh_seq, true, normals


def _capture_truth(body: Body, sites: SurfacePoints, true: np.ndarray, *, visible, seen,
                   frag_marker, label_frame, labels, cams, noise, marker_radius, rate,
                   motion_name) -> dict[str, Any]:
    """The ``truth`` record of :func:`simulate_capture`."""
    skin_pts, skin_n, skin_w = sites.points(body), sites.normals(body), sites.weights(body)
    skin_part = np.argmax(skin_w, axis=1)
    return {
        "positions": true,
        "visible": visible,
        "n_cameras_seeing": seen.astype(np.int16),
        "part": skin_part.astype(np.int64),
        "part_names": list(body.skeleton.names),
        "marker_weights": skin_w,
        "region": marker_regions(body, skin_pts, skin_n, skin_part),
        "region_names": list(REGIONS),
        "marker_face": sites.face.astype(np.int64),
        "marker_barycentric": sites.barycentric,
        "bind_pose": skin_pts + marker_radius * skin_n,
        "reference_pose": true[label_frame],
        "fragment_marker": frag_marker,
        "label_frame": label_frame,
        "labels": labels,
        "cameras": cams,
        "noise": noise,
        "marker_radius": marker_radius,
        "rate": rate,
        "motion": motion_name,
    }


@stage("simulate_capture", outputs=("markers", "truth", "mesh", "motion"))
def simulate_capture(
    *,
    n_markers: int = 350,
    n_frames: int = 900,
    rate: float = 120.0,
    motion: Literal["dynamic", "walk", "range_of_motion"] = "dynamic",
    seed: int = 0,
    bvh: FilePath | None = None,
    body_mesh: FilePath | None = None,
    body_vertices: int = 3000,
    noise: float = 0.0003,
    n_cameras: int = 12,
    min_cameras: int = 2,
    calibration: float = 0.5,
    bulge: float = 1.0,
    jiggle: float = 1.0,
    breathing: float = 1.0,
    break_rate: float = 0.2,
    ghost_rate: float = 1.0,
    marker_radius: float = 0.007,
    min_separation: float = 0.02,
    ctx: Context,
) -> dict[str, Any]:
    """Simulate a dense-marker capture (Park & Hodgins style) with ground truth.

    Parameters
    ----------
    n_markers : int
        Markers on the skin (~350 gives 5-7 cm spacing, denser at elbows/shoulders).
    n_frames : int
        Frames, the rest-pose calibration included.
    rate : float
        Frames per second.
    motion : {"dynamic", "walk", "range_of_motion"}
        Treadmill run, treadmill walk, or joint groups flexed in turn.
    seed : int
        Seeds ``ctx.rng`` (motion variation, layout, noise, fragmentation).  The
        marker layout comes from its own stream of that seed and from the
        calibration pose only, so trials of one seed and part id with different
        ``motion`` (a range-of-motion trial and a dynamic one) share the body,
        the marker labels and their placement.
    bvh : FilePath, optional
        Drive the body with this BVH instead of a procedural motion.
    body_mesh : FilePath, optional
        The MakeHuman ``makehuman_base.obj`` (rig and weights JSON beside it);
        default: a procedural body built around the motion's skeleton.
    body_vertices : int
        Vertex count of the procedural body (and of the ``mesh`` output).
    noise : float
        Measurement noise, standard deviation per axis (metres).
    n_cameras, min_cameras : int
        Cameras on the ring; cameras needed to reconstruct a marker.
    calibration : float
        Seconds of T-pose at the start.
    bulge, jiggle, breathing : float
        Scales of the non-rigid skin motion (0 disables).
    break_rate : float
        Extra trajectory breaks per marker per second.
    ghost_rate : float
        Ghost trajectories per second.
    marker_radius : float
        Metres from the skin to a marker's centre.
    min_separation : float
        Markers closer than this to another (skin folds) merge in the images and
        are lost, metres.
    ctx : Context
        ``ctx.rng`` drives everything random; ``ctx.map`` the visibility tests.

    Returns
    -------
    dict
        ``markers`` (:class:`Markers`: labelled runs through the label frame,
        unlabelled fragments ``*N``), ``truth`` (record: ``positions (F, M, 3)``
        true marker centres, ``visible (F, M)``, ``part (M,)`` dominant joint
        with ``part_names``, ``marker_weights (M, J)``, ``region (M,)`` with
        ``region_names``, ``marker_face (M,)`` / ``marker_barycentric (M, 3)``:
        the skin point under each marker on ``mesh`` (the marker sits
        ``marker_radius`` above it along the normal),
        ``bind_pose (M, 3)``, ``reference_pose (M, 3)`` true positions at the
        label frame, ``fragment_marker (U,)`` true marker per fragment (-1 ghost),
        ``label_frame``, ``cameras (C, 3)``, ``noise``), ``mesh`` (:class:`Mesh`,
        true skin ``(F, V, 3)``), ``motion`` (the driving :class:`Motion`).
    """
    rng = ctx.rng
    layout_rng = _layout_rng(rng)
    if n_markers < 4:
        raise ValueError(f"simulate_capture: n_markers must be >= 4, got {n_markers}")
    if n_frames < 2 or rate <= 0:
        raise ValueError("simulate_capture: need n_frames >= 2 and rate > 0")
    mot = capture_motion(motion, n_frames, rate=rate, rng=rng, calibration=calibration, bvh=bvh)
    body = capture_body(mot, body_mesh=body_mesh, body_vertices=body_vertices)
    R, p = skinning_transforms(body, mot)
    cams = camera_ring(mot.root_position, n_cameras=n_cameras)
    sites = _marker_sites(body, mot, R, p, n_markers, n_cameras=n_cameras,
                          min_cameras=min_cameras, marker_radius=marker_radius, rng=layout_rng)
    dynamics = SkinDynamics(bulge=bulge, jiggle=jiggle, breathing=breathing)
    mesh_seq, true, normals = _moving_skin(body, mot, R, p, sites, dynamics,
                                           marker_radius=marker_radius, rng=rng)
    seen = marker_visibility(true, normals, body, R, p, cams, ctx=ctx)
    visible = (seen >= min_cameras) & ~crowded(true, min_separation)
    observed = true + rng.normal(0.0, noise, true.shape)
    labelled, frags, frag_marker, label_frame = fragment_capture(
        observed, visible, rate=rate, rng=rng, break_rate=break_rate, ghost_rate=ghost_rate,
        ghost_source=true, ghost_normals=normals)
    labels = [f"M{i + 1:03d}" for i in range(n_markers)]
    markers = Markers(
        positions=labelled, labels=labels, rate=rate, first_frame=0,
        fragments=frags, fragment_labels=[f"*{u + 1}" for u in range(frags.shape[1])],
        attrs={"source": "simulate_capture", "source_unit": "m", "motion": motion,
               "label_frame": label_frame})
    truth = _capture_truth(
        body, sites, true, visible=visible, seen=seen, frag_marker=frag_marker,
        label_frame=label_frame, labels=labels, cams=cams, noise=noise,
        marker_radius=marker_radius, rate=rate,
        motion_name=motion if bvh is None else Path(bvh).name)
    truth["seed"] = int(seed)
    mesh = Mesh(mesh_seq, body.faces, rate=rate, attrs={
        "source": body.attrs.get("source", "procedural"),
        "joint_names": list(body.skeleton.names),
        "vertex_part": body.part.tolist(),
        "marker_face": sites.face.tolist(),
    })
    return {"markers": markers, "truth": truth, "mesh": mesh, "motion": mot}


# --------------------------------------------------------------------------- scoring


def gap_mask(
    visible: np.ndarray,
    reference: np.ndarray,
    *,
    rate: float,
    duration: float,
    fraction: float,
    clustered: bool,
    rng: np.random.Generator,
    first_frame: int = 0,
) -> np.ndarray:
    """Samples to delete for a gap-filling benchmark (only originally visible ones).

    ``ceil(fraction × M)`` markers (at least one) each lose ``duration`` seconds
    at once: placed independently (random markers, each its own random start)
    or clustered (the markers nearest a random marker in ``reference``, one
    common start).

    Parameters
    ----------
    visible : (F, M) bool ndarray
        Originally visible samples.
    reference : (M, 3) float ndarray
        Marker layout for the clustered placement (NaN rows are never chosen).
    rate : float
    duration : float
        Gap length in seconds (capped at the capture length).
    fraction : float
        Share of the markers gapped at once.
    clustered : bool
    rng : numpy.random.Generator
    first_frame : int
        Gaps lie in frames ``first_frame`` and later (e.g. after a
        calibration pose that is not part of the motion under test).

    Returns
    -------
    (F, M) bool ndarray
    """
    F, M = visible.shape
    if not 0 <= first_frame < F:
        raise ValueError(f"gap_mask: first_frame {first_frame} outside the {F} frames")
    mask = np.zeros((F, M), dtype=bool)
    if first_frame:
        mask[first_frame:] = gap_mask(visible[first_frame:], reference, rate=rate,
                                      duration=duration, fraction=fraction,
                                      clustered=clustered, rng=rng)
        return mask
    L = int(min(F, max(1, round(duration * rate))))
    ok = np.flatnonzero(np.isfinite(reference).all(1) & visible.any(0))
    k = int(min(len(ok), max(1, np.ceil(fraction * M))))
    if k == 0:
        return mask
    if clustered:
        c = ok[rng.integers(len(ok))]
        d = np.linalg.norm(reference[ok] - reference[c], axis=1)
        chosen = ok[np.argsort(d)[:k]]
        s0 = int(rng.integers(0, F - L + 1))
        mask[s0:s0 + L, chosen] = True
    else:
        chosen = rng.choice(ok, size=k, replace=False)
        for m in chosen:
            s0 = int(rng.integers(0, F - L + 1))
            mask[s0:s0 + L, m] = True
    return mask & visible


def score_merges(
    merges: list[dict[str, Any]],
    fragment_labels: list[str],
    fragment_marker: np.ndarray,
    labels: list[str],
) -> dict[str, Any]:
    """Count right and wrong merges against the true fragment → marker map.

    Parameters
    ----------
    merges : list of dict
        ``report["merges"]`` of the clean stage (``fragment``, ``label``).
    fragment_labels : list of str
        The capture's fragment names (before cleaning).
    fragment_marker : (U,) int ndarray
        True marker per fragment (-1 ghost).
    labels : list of str

    Returns
    -------
    dict
        ``merged``, ``wrong``, ``ghosts_merged``, ``wrong_list``, ``mergeable``
        (fragments of real markers), ``missed`` (real fragments not merged).
    """
    fidx = {f: u for u, f in enumerate(fragment_labels)}
    lidx = {lb: i for i, lb in enumerate(labels)}
    wrong = []
    ghosts = 0
    merged = set()
    for mg in merges:
        u = fidx[mg["fragment"]]
        merged.add(u)
        t = int(fragment_marker[u])
        if t < 0:
            ghosts += 1
        if t != lidx[mg["label"]]:
            wrong.append({"fragment": mg["fragment"], "label": mg["label"],
                          "true": labels[t] if t >= 0 else "ghost"})
    real = np.flatnonzero(fragment_marker >= 0)
    return {"merged": len(merges), "wrong": len(wrong), "ghosts_merged": ghosts,
            "wrong_list": wrong, "mergeable": int(len(real)),
            "missed": int(len([u for u in real if u not in merged]))}


def region_errors(
    estimate: np.ndarray,
    truth_positions: np.ndarray,
    mask: np.ndarray,
    region: np.ndarray,
    mean_distance: np.ndarray,
    *,
    region_names: tuple[str, ...] | list[str] = REGIONS,
) -> dict[str, dict[str, float]]:
    """Mean and max error per body region, normalised by mean neighbour distance.

    Parameters
    ----------
    estimate, truth_positions : (F, M, 3) float ndarray
    mask : (F, M) bool ndarray
        Samples to score (e.g. filled holes).
    region : (M,) int ndarray
    mean_distance : (M,) float ndarray
        Each marker's mean neighbour distance (metres).
    region_names : sequence of str

    Returns
    -------
    dict
        ``region -> {"n", "mean", "max", "mean_mm", "max_mm", "unfilled"}``, plus
        ``"all"``.  ``unfilled`` counts masked samples left NaN (not in the errors).
    """
    err = np.linalg.norm(estimate - truth_positions, axis=-1)
    norm = err / mean_distance[None, :]
    out: dict[str, dict[str, float]] = {}
    groups = [(nm, region == k) for k, nm in enumerate(region_names)]
    groups.append(("all", np.ones(len(region), dtype=bool)))
    for nm, sel in groups:
        msk = mask & sel[None, :]
        if not msk.any():
            continue
        e, en = err[msk], norm[msk]
        ok = np.isfinite(e)
        out[nm] = {
            "n": int(ok.sum()),
            "unfilled": int((~ok).sum()),
            "mean": float(en[ok].mean()) if ok.any() else float("nan"),
            "max": float(en[ok].max()) if ok.any() else float("nan"),
            "mean_mm": float(e[ok].mean() * 1000) if ok.any() else float("nan"),
            "max_mm": float(e[ok].max() * 1000) if ok.any() else float("nan"),
        }
    return out



