"""Known non-rigid skin motion on top of linear-blend skinning.

:class:`SkinDynamics`: *muscle bulges* along the bind-pose normal proportional
to a joint's flexion angle (biceps <- elbow, quadriceps <- knee, calf <- ankle,
deltoid <- shoulder); *flesh jiggle*: a damped spring per soft region (belly,
buttocks, thighs, upper-arm undersides, chest) driven by the acceleration of
its anchor point; *breathing*: a sinusoidal swell of the chest and belly.
Vertices and markers move with the same fields, so the per-frame mesh of a
simulated capture is the true skin under its markers.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from mocapflow.stages.motion.datatypes import Motion
from mocapflow.stages.motion.rotations import quat_angle, quat_identity
from mocapflow.stages.motion.simulate.body import Body, skin
from mocapflow.stages.motion.simulate.markers import find_joint

__all__ = ["SkinDynamics"]


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
                j = find_joint(names, bone_p.format(s=s))
                d = find_joint(names, drv_p.format(s=s))
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
        sp = find_joint(names, "Spine")
        if torso and sp is not None:
            jig.append((np.isin(part, torso) * side(fwd, 1.5), sp, 3.5, 0.18, 1.0))
        hips = find_joint(names, "Hips")
        if hipj and hips is not None:
            jig.append((np.isin(part, hipj) * side(-fwd, 1.5), hips, 4.0, 0.2, 0.8))
        s1 = find_joint(names, "Spine1")
        if chest and s1 is not None:
            jig.append((np.isin(part, chest) * side(fwd, 2.0), s1, 4.5, 0.22, 0.5))
        for s in ("Left", "Right"):
            j = find_joint(names, f"{s}UpLeg")
            if j is not None and sk.children(j):
                jig.append((along(j, sk.children(j)[0], 0.4, 0.25) * (part == j), j, 5.0,
                            0.25, 0.8))
            j = find_joint(names, f"{s}Arm")
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
        reg = self.regions(body, points, normals, part)
        s = _normal_offsets(reg, body, motion, len(points), R.shape[0], rng=rng)
        # linear-blend skinning of the bind-pose points moved along their normals
        out = skin(body, R, p, points=points[None] + s[:, :, None] * normals[None],
                   weights=weights)
        bind = body.bind_positions()
        for b in reg["jiggle"]:
            out += _jiggle(b, points, bind, R, p, motion.rate)
        return out


def _normal_offsets(reg: dict[str, list[dict[str, Any]]], body: Body, motion: Motion,
                    n_points: int, n_frames: int, *, rng: np.random.Generator) -> np.ndarray:
    """``(F, N)`` pose-space displacements along the bind normal: bulges and breathing.

    A bulge grows with its driver joint's rotation angle (up to 1.5 × its
    amplitude beyond 90°); each breathing region draws its rate (±15 %) and
    phase from ``rng``.
    """
    F = n_frames
    sk = body.skeleton
    s = np.zeros((F, n_points))
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
    return s


def _jiggle(b: dict[str, Any], points: np.ndarray, bind: np.ndarray, R: np.ndarray,
            p: np.ndarray, rate: float) -> np.ndarray:
    """``(F, N, 3)`` jiggle of one soft region: a damped spring driven by its anchor.

    The spring (frequency ``b["freq"]``, damping ratio ``b["damping"]``) is driven
    by the world acceleration of the region's centroid carried by the anchor
    joint, integrated semi-implicitly per frame, scaled by ``b["gain"]``, capped
    at 3 cm and spread by the region's mask.
    """
    F = R.shape[0]
    dt = 1.0 / rate
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
    return disp[:, None, :] * m[None, :, None]
