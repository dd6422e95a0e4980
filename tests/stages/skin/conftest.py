"""Shared helpers of the skin tests: a synthetic limb with known near-rigid parts.

``limb_capture`` (used by the segmentation, deformation and rendering tests) builds a
range-of-motion trial of a bending, twisting, bulging cylinder with its markers,
marker surface, detailed mesh and ground truth.
"""

from __future__ import annotations

import numpy as np

from mocapflow.pipeline import Context
from mocapflow.stages.motion.datatypes import Markers, Mesh
from mocapflow.stages.skin.binding import bind_mesh
from mocapflow.stages.skin.blend import vertex_operator
from mocapflow.stages.skin.parts import fit_part, prepare_part
from mocapflow.stages.skin.segment import segment


def rot_x(a):
    """Rotations about x, ``(..., 3, 3)``."""
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(np.shape(a) + (3, 3))
    R[..., 0, 0] = 1
    R[..., 1, 1], R[..., 1, 2], R[..., 2, 1], R[..., 2, 2] = c, -s, s, c
    return R


def rot_y(a):
    """Rotations about y, ``(..., 3, 3)``."""
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(np.shape(a) + (3, 3))
    R[..., 1, 1] = 1
    R[..., 0, 0], R[..., 0, 2], R[..., 2, 0], R[..., 2, 2] = c, s, -s, c
    return R


def grid_cylinder(n_around, n_along, *, radius=0.05, length=0.6, jitter=0.0, rng=None):
    """Points on a cylinder along y and the triangles of their grid."""
    th = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    y = np.linspace(0.02, length - 0.02, n_along)
    T, Y = np.meshgrid(th, y)
    if jitter:
        T = T + rng.uniform(-jitter, jitter, T.shape) * (2 * np.pi / n_around)
    P = np.stack([radius * np.cos(T), Y, radius * np.sin(T)], -1).reshape(-1, 3)
    faces = []
    for j in range(n_along - 1):
        for i in range(n_around):
            a, b = j * n_around + i, j * n_around + (i + 1) % n_around
            faces += [(a, b, b + n_around), (a, b + n_around, a + n_around)]
    return P, np.array(faces)


def deform_limb(P, theta, twist, bulge, *, joints=(0.3,), blend=0.03):
    """Bend the limb by ``theta`` at each joint (lower segments twist too) + a bulge.

    Returns ``(F, N, 3)``; the upper segment bulges radially (Gaussian bump that
    grows with the bend) -- a smooth non-rigid deformation.
    """
    y = P[:, 1]
    bump = np.exp(-((y - 0.15) / 0.08) ** 2) * (y < joints[0])
    s = 1 + bulge * np.sin(theta / 2)[:, None] ** 2 * bump[None]
    Q = np.repeat(P[None], len(theta), 0)
    Q[..., 0] *= s
    Q[..., 2] *= s
    for j in sorted(joints, reverse=True):  # distal joints first
        Rl = rot_x(theta) @ rot_y(twist)
        moved = np.einsum("fij,fnj->fni", Rl, Q - [0, j, 0]) + [0, j, 0]
        w = np.clip((y - (j - blend)) / (2 * blend), 0, 1)
        w = w * w * (3 - 2 * w)
        Q = (1 - w)[None, :, None] * Q + w[None, :, None] * moved
    return Q


def limb_capture(n_frames=120, *, seed=0, n_around=10, n_rings=14, mesh=(32, 40), bulge=0.25,
                 noise=0.0, joints=(0.3,)):  # fmt: skip
    """A range-of-motion trial of a limb with known parts, markers, mesh and truth."""
    rng = np.random.default_rng(seed)
    ref, faces = grid_cylinder(n_around, n_rings, jitter=0.25, rng=rng)
    t = np.linspace(0, 1, n_frames)
    theta = np.deg2rad(55) * (1 - np.cos(2 * np.pi * 2 * t))
    twist = np.deg2rad(30) * np.sin(2 * np.pi * 3 * t)
    X = deform_limb(ref, theta, twist, bulge, joints=joints)
    Vr, Vf = grid_cylinder(*mesh)
    V = deform_limb(Vr, theta, twist, bulge, joints=joints)
    Rg = rot_y(np.pi * t) @ rot_x(0.3 * np.sin(2 * np.pi * t))
    tg = np.stack([t, 0.1 * np.sin(2 * np.pi * t), 0 * t], -1)
    X = np.einsum("fij,fnj->fni", Rg, X) + tg[:, None]
    V = np.einsum("fij,fnj->fni", Rg, V) + tg[:, None]
    X = X + rng.normal(0, noise, X.shape)
    parts = np.searchsorted(np.asarray(joints), ref[:, 1])
    labels = [f"M{i:03d}" for i in range(len(ref))]
    return {
        "markers": Markers(X, labels, 120.0),
        "surface": Mesh(ref, faces, attrs={"labels": labels}),
        "parts": parts,
        "mesh": Mesh(Vr, Vf),
        "truth": V,
    }


def limb_deform_setup(n_frames: int) -> dict:
    """:func:`limb_capture` (no noise) segmented, bound (``sharpness`` 4) and fitted per part
    (``quadratic_residual``), with its :func:`~mocapflow.stages.skin.blend.vertex_operator`:
    the set-up of the deformation speed tests (keys ``d, seg, mesh, beta, models, fits, op``)."""
    d = limb_capture(n_frames=n_frames, noise=0.0)
    seg = segment(d["markers"], d["surface"], ctx=Context())["segmentation"]
    mesh, x = d["mesh"], d["markers"].positions
    beta = bind_mesh(mesh.vertices, seg, sharpness=4.0).beta
    models = [prepare_part(seg, p) for p in range(seg.n_parts)]
    fits = [fit_part(m, x[:, m.members], mode="quadratic_residual") for m in models]
    op = vertex_operator(models, len(mesh.vertices), residual=True, rest=mesh.vertices, beta=beta)
    return {"d": d, "seg": seg, "mesh": mesh, "beta": beta, "models": models, "fits": fits,
            "op": op}  # fmt: skip
