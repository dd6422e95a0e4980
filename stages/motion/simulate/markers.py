"""Marker layouts on a body's skin, and the body region of each marker.

* :class:`SurfacePoints` — points on the skin as triangles and barycentric
  coordinates (they move with the skin);
* :func:`place_markers` — weighted farthest-point sampling of points spread
  over the skin (:func:`sample_surface`), denser at the elbows and shoulders
  (``density``), sparser on the head, hands and feet, none on the soles nor
  where the calibration pose hides them (so every marker can be labelled).
  With 350 markers on a 1.75 m body the nearest-marker distance is 45-65 mm
  (median ~58 mm) and the mean one-ring distance ~75 mm;
* :func:`marker_regions` — the body region (:data:`REGIONS`, the rows of
  P&H Table 2) of each marker;
* :func:`find_joint`, :func:`side_joints` — joints by CMU-style name patterns.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from mocapflow.stages.motion.simulate.body import Body

__all__ = [
    "REGIONS",
    "SurfacePoints",
    "find_joint",
    "marker_regions",
    "place_markers",
    "sample_surface",
    "side_joints",
]

#: Body regions of the Table-2 style report, in order.
REGIONS = ("abdomen", "elbow", "thigh", "knee", "chest", "back", "shoulder", "upper_arm",
           "forearm", "calf", "pelvis", "neck", "head", "hand", "foot")


# --------------------------------------------------------------------------- names


def find_joint(names: list[str], pattern: str) -> int | None:
    """Index of the first joint whose name matches ``pattern`` in full (case-blind), or None."""
    rx = re.compile(pattern, re.I)
    for i, n in enumerate(names):
        if rx.fullmatch(n):
            return i
    return None


def side_joints(names: list[str], pattern: str) -> list[int]:
    """Joint indices for a CMU-style name pattern with ``{s}`` = Left/Right."""
    out = []
    for s in ("Left", "Right"):
        j = find_joint(names, pattern.format(s=s))
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
    for j in side_joints(names, "{s}ForeArm") + side_joints(names, "{s}Arm"):
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
        js = side_joints(names, pat)
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
