"""Skinned body surfaces for synthetic captures: procedural or the MakeHuman mesh.

A :class:`Body` is a triangle mesh in a bind pose with linear-blend skinning
weights over the joints of a skeleton, plus a set of coarse *capsules* (one per
bone segment, slightly inside the skin) used as occluders by the capture
simulator.

* :func:`procedural_body` builds the surface of any skeleton (BVH, ASF or
  :func:`mocapflow.stages.motion.simulate.motion.procedural_skeleton`): a smooth union
  of tapered capsules around its bones (flattened front-to-back on the torso),
  iso-surfaced with VTK's flying edges and decimated; bone radii come from the
  joint names (CMU, Daz and common naming), scaled to the skeleton's height.
* :func:`load_makehuman_body` reads the CC0 MakeHuman base mesh with its
  CMU-named rig and skin weights (``shared/data/mesh``).
* :func:`skinning_transforms` and :func:`skin` pose a body with a
  :class:`~mocapflow.stages.motion.datatypes.Motion` (joints matched by name; a body whose
  bind pose differs from the motion's rest pose, e.g. MakeHuman's A-pose under a
  T-pose skeleton, is aligned bone by bone).

Coordinates: metres, y up, the body facing +z in its bind pose (the CMU and
MakeHuman convention).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.stages.motion.datatypes import Mesh, Motion, Skeleton
from mocapflow.stages.motion.geometry import vertex_normals
from mocapflow.stages.motion.kinematics import (
    forward_kinematics,
    quat_multiply,
    quat_rotate,
    quat_to_matrix,
)

__all__ = [
    "Body",
    "BodyError",
    "Capsules",
    "bind_pose",
    "load_makehuman_body",
    "procedural_body",
    "skin",
    "skinning_transforms",
]


class BodyError(ValueError):
    """A body cannot be built or posed (bad skeleton, mesh files, joint names)."""


@dataclass(eq=False)
class Capsules:
    """Tapered capsules around bone segments, in the bind pose.

    Parameters
    ----------
    joint : (C,) int ndarray
        Joint whose transform moves each capsule.
    start, end : (C, 3) float ndarray
        Axis end points (metres).
    radius : (C, 2) float ndarray
        Radius at ``start`` and ``end``.
    depth : (C,) float ndarray
        Front-to-back flattening (1 = round; 0.7 = 30 % thinner along ``forward``).
    forward : (3,) float ndarray
        The body's forward direction in the bind pose.
    """

    joint: np.ndarray
    start: np.ndarray
    end: np.ndarray
    radius: np.ndarray
    depth: np.ndarray
    forward: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))

    def __len__(self) -> int:
        return len(self.joint)


@dataclass(eq=False)
class Body:
    """A skinned body surface.

    Parameters
    ----------
    skeleton : Skeleton
        The body's own skeleton (bind pose = identity local rotations).
    vertices : (V, 3) float ndarray
        Skin in the bind pose (metres).
    faces : (T, 3) int ndarray
        Triangles, wound outward.
    weights : (V, J) float ndarray
        Linear-blend skinning weights (rows sum to 1).
    capsules : Capsules
        Coarse occluders (slightly inside the skin).
    alignment : (J, 4) float ndarray
        Per joint, the rotation from the body's bind pose to the rest pose of the
        skeleton that drives it (identity when they agree).
    attrs : dict
        ``source`` etc.
    """

    skeleton: Skeleton
    vertices: np.ndarray
    faces: np.ndarray
    weights: np.ndarray
    capsules: Capsules
    alignment: np.ndarray | None = None
    attrs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        J = self.skeleton.n_joints
        self.vertices = np.asarray(self.vertices, dtype=np.float64)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        self.weights = np.asarray(self.weights, dtype=np.float64)
        if self.weights.shape != (len(self.vertices), J):
            raise BodyError(f"body: weights must be (V={len(self.vertices)}, J={J}), "
                            f"got {self.weights.shape}")
        if self.alignment is None:
            self.alignment = np.tile([1.0, 0.0, 0.0, 0.0], (J, 1))

    @property
    def n_vertices(self) -> int:
        """Number of vertices ``V``."""
        return len(self.vertices)

    @property
    def part(self) -> np.ndarray:
        """``(V,)`` int: the dominant joint of each vertex (largest skin weight)."""
        return np.argmax(self.weights, axis=1)

    @property
    def normals(self) -> np.ndarray:
        """``(V, 3)`` unit vertex normals in the bind pose."""
        return vertex_normals(self.vertices, self.faces)

    def bind_positions(self) -> np.ndarray:
        """``(J, 3)`` joint positions in the bind pose."""
        return bind_pose(self.skeleton)

    def to_mesh(self) -> Mesh:
        """The bind-pose surface as a :class:`Mesh` (``attrs``: joint names, parts)."""
        return Mesh(self.vertices, self.faces, attrs={
            "joint_names": self.skeleton.names, "vertex_part": self.part.tolist(),
            **self.attrs})


# --------------------------------------------------------------------------- geometry helpers


def bind_pose(skeleton: Skeleton) -> np.ndarray:
    """``(J, 3)`` joint positions with identity rotations and the root at the origin."""
    J = skeleton.n_joints
    pos, _ = forward_kinematics(skeleton, np.tile([1.0, 0, 0, 0], (1, J, 1)), np.zeros((1, 3)))
    return pos[0]


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance from points (N, 3) to segment a-b, and the parameter t in [0, 1]."""
    ab = b - a
    L2 = float(ab @ ab)
    t = np.zeros(len(p)) if L2 < 1e-16 else np.clip((p - a) @ ab / L2, 0.0, 1.0)
    q = a + t[:, None] * ab
    return np.linalg.norm(p - q, axis=1), t


# --------------------------------------------------------------------------- procedural body

#: (pattern, radius at start, radius at end, depth) for a bone segment, by the
#: name of the joint that owns (moves) it; first match wins (lower-case names).
_RADII: list[tuple[str, float, float, float]] = [
    (r"finger|thumb|index|middle|ring|pinky|carpal", 0.012, 0.010, 1.0),
    (r"toe", 0.030, 0.022, 0.7),
    (r"foot|ankle", 0.040, 0.032, 0.8),
    (r"hand|wrist", 0.034, 0.028, 0.55),
    (r"fore.?arm|elbow|lowarm", 0.042, 0.032, 1.0),
    (r"shoulder|clavicle|collar", 0.060, 0.055, 1.0),
    (r"arm|shldr", 0.052, 0.044, 1.0),
    (r"hipjoint|pelvis", 0.115, 0.095, 0.8),
    (r"up.?leg|thigh", 0.082, 0.056, 1.0),
    (r"leg|shin|calf|knee", 0.056, 0.040, 1.0),
    (r"head", 0.092, 0.092, 1.0),
    (r"neck", 0.056, 0.052, 1.0),
    (r"hips|hip|root|lowerback|spine|back|abdomen|chest|torso|waist", 0.128, 0.132, 0.68),
]
_DEFAULT_RADIUS = (0.04, 0.035, 1.0)


def _radius_for(name: str) -> tuple[float, float, float]:
    n = name.lower()
    for pat, r0, r1, dep in _RADII:
        if re.search(pat, n):
            return r0, r1, dep
    return _DEFAULT_RADIUS


def _forward(skeleton: Skeleton, bind: np.ndarray) -> np.ndarray:
    """Forward direction: horizontal direction of the toes, else +z."""
    toes = [j for j, n in enumerate(skeleton.names) if re.search(r"toe", n.lower())]
    if toes:
        feet = skeleton.parents[toes]
        d = (bind[toes] - bind[feet]).mean(0)
        d[1] = 0.0
        if np.linalg.norm(d) > 1e-6:
            return d / np.linalg.norm(d)
    return np.array([0.0, 0.0, 1.0])


def body_capsules(skeleton: Skeleton, *, scale: float | None = None) -> Capsules:
    """Tapered capsules around the bones of a skeleton in its bind pose.

    One capsule per non-degenerate bone (joint → child, or → End Site), moved by
    the joint; branching joints (pelvis, chest) also get capsules to their
    grandchildren so the hip and shoulder girdles are filled.  Radii from the
    joint names (see ``_RADII``), scaled by the skeleton's toe-to-head-top span
    over 1.72 m (a 1.75 m adult); End Site capsules end at the End Site.

    Parameters
    ----------
    skeleton : Skeleton
    scale : float, optional
        Radius scale; default from the skeleton's height.

    Returns
    -------
    Capsules
    """
    bind = bind_pose(skeleton)
    J = skeleton.n_joints
    ends = bind[skeleton.end_parents] + skeleton.end_offsets if len(skeleton.end_parents) else \
        np.zeros((0, 3))
    allp = np.concatenate([bind, ends])
    span = float(allp[:, 1].max() - allp[:, 1].min())
    if scale is None:
        scale = float(np.clip(span / 1.72, 0.4, 3.0)) if span > 0 else 1.0
    joint, a_, b_, rad, dep = [], [], [], [], []

    def add(j: int, a: np.ndarray, b: np.ndarray, r0: float, r1: float, d: float) -> None:
        joint.append(j)
        a_.append(a)
        b_.append(b)
        rad.append((r0 * scale, r1 * scale))
        dep.append(d)

    children = [skeleton.children(j) for j in range(J)]
    for j in range(J):
        r0, r1, d = _radius_for(skeleton.names[j])
        targets = [bind[c] for c in children[j]]
        for e in np.flatnonzero(skeleton.end_parents == j):  # the cap ends at the End Site
            v = ends[e] - bind[j]
            L = float(np.linalg.norm(v))
            targets.append(bind[j] + v * max(L - r1 * scale, 0.5 * L) / max(L, 1e-12))
        for tgt in targets:
            if np.linalg.norm(tgt - bind[j]) > 1e-4:
                add(j, bind[j], tgt, r0, r1, d)
        if len(children[j]) > 1:  # girdle: reach the grandchildren
            for c in children[j]:
                for g in children[c]:
                    rc = _radius_for(skeleton.names[g])
                    if np.linalg.norm(bind[g] - bind[j]) > 1e-4:
                        add(j, bind[j], bind[g], r0, max(rc[0], 0.6 * r0), min(d, 0.85))
        if not targets and not children[j]:
            add(j, bind[j], bind[j], r0, r0, d)  # a leaf without End Site: a ball
    if not joint:
        raise BodyError("procedural_body: the skeleton has no bones")
    return Capsules(np.array(joint), np.array(a_), np.array(b_), np.array(rad),
                    np.array(dep), _forward(skeleton, bind))


def capsule_sdf(points: np.ndarray, caps: Capsules, *, blend: float = 0.03) -> np.ndarray:
    """Signed distance (approximate) to the smooth union of capsules.

    Parameters
    ----------
    points : (N, 3) float ndarray
    caps : Capsules
    blend : float
        Smooth-minimum width (metres) that rounds the unions at the joints.

    Returns
    -------
    (N,) float ndarray
        Negative inside.
    """
    d = _capsule_distances(points, caps)  # (N, C)
    out = d[:, 0]
    for c in range(1, d.shape[1]):
        b = d[:, c]
        h = np.maximum(blend - np.abs(out - b), 0.0) / blend
        out = np.minimum(out, b) - h * h * blend * 0.25
    return out


def _capsule_distances(points: np.ndarray, caps: Capsules) -> np.ndarray:
    """(N, C) signed distance of points to every (flattened, tapered) capsule."""
    f = caps.forward
    out = np.empty((len(points), len(caps)))
    for c in range(len(caps)):
        a, b = caps.start[c], caps.end[c]
        s = 1.0 / caps.depth[c]
        p = points + ((points - a) @ f)[:, None] * (s - 1.0) * f  # stretch along forward
        bb = b + ((b - a) @ f) * (s - 1.0) * f
        dist, t = _segment_distance(p, a, bb)
        out[:, c] = dist - (caps.radius[c, 0] + t * (caps.radius[c, 1] - caps.radius[c, 0]))
    return out


def _skin_weights(points: np.ndarray, caps: Capsules, n_joints: int, *,
                  sharpness: float = 9.0, max_influences: int = 4) -> np.ndarray:
    """Weights from the normalised distance of each point to every capsule axis."""
    d = _capsule_distances(points, caps)
    r = caps.radius.mean(1)
    q = (d + r) / r  # ~1 on the capsule's own surface
    q = q - q.min(1, keepdims=True)
    w_c = np.exp(-sharpness * q)
    W = np.zeros((len(points), n_joints))
    for c in range(len(caps)):
        W[:, caps.joint[c]] = np.maximum(W[:, caps.joint[c]], w_c[:, c])
    if max_influences < n_joints:
        cut = -np.sort(-W, axis=1)[:, max_influences - 1 : max_influences]
        W = np.where(W >= cut, W, 0.0)
    W[W < 0.01] = 0.0
    return W / W.sum(1, keepdims=True)


def _sdf_grid(caps: Capsules, lo: np.ndarray, dims: np.ndarray, h: float,
              blend: float) -> np.ndarray:
    """Smooth-union SDF on a regular grid, each capsule evaluated in its bounding box.

    Returns ``(nz, ny, nx)`` (x fastest when raveled, VTK's point order).
    """
    nx, ny, nz = (int(x) for x in dims)
    out = np.full((nz, ny, nx), np.inf)
    f = caps.forward
    for c in range(len(caps)):
        a, b = caps.start[c], caps.end[c]
        r = float(caps.radius[c].max()) + blend + 2 * h
        cl = np.minimum(a, b) - r
        ch = np.maximum(a, b) + r
        i0 = np.clip(np.floor((cl - lo) / h).astype(int), 0, dims - 1)
        i1 = np.clip(np.ceil((ch - lo) / h).astype(int) + 1, 1, dims)
        xs = lo[0] + h * np.arange(i0[0], i1[0])
        ys = lo[1] + h * np.arange(i0[1], i1[1])
        zs = lo[2] + h * np.arange(i0[2], i1[2])
        Z, Y, X = np.meshgrid(zs, ys, xs, indexing="ij")
        p = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
        s_ = 1.0 / caps.depth[c]
        p = p + ((p - a) @ f)[:, None] * (s_ - 1.0) * f
        bb = b + ((b - a) @ f) * (s_ - 1.0) * f
        dist, t = _segment_distance(p, a, bb)
        d = (dist - (caps.radius[c, 0] + t * (caps.radius[c, 1] - caps.radius[c, 0])))
        blk = out[i0[2]:i1[2], i0[1]:i1[1], i0[0]:i1[0]]
        d = d.reshape(blk.shape)
        hh = np.maximum(blend - np.abs(blk - d), 0.0) / blend
        blk[...] = np.minimum(blk, d) - hh * hh * blend * 0.25
    out[~np.isfinite(out)] = 1.0
    return out


def procedural_body(
    skeleton: Skeleton,
    *,
    resolution: float = 0.012,
    n_vertices: int = 5000,
    blend: float = 0.03,
) -> Body:
    """A smooth body surface around any skeleton, with skinning weights.

    Parameters
    ----------
    skeleton : Skeleton
        Its rest pose (identity rotations) is the bind pose.
    resolution : float
        Voxel size of the iso-surface (metres).
    n_vertices : int
        Target vertex count after decimation.
    blend : float
        Smooth-union width at the joints (metres).

    Returns
    -------
    Body
        ``attrs``: ``source = "procedural"``, ``resolution``.

    Raises
    ------
    BodyError
        A skeleton without bones.
    """
    import pyvista as pv

    caps = body_capsules(skeleton)
    pad = float(caps.radius.max()) + 3 * resolution
    lo = np.minimum(caps.start.min(0), caps.end.min(0)) - pad
    hi = np.maximum(caps.start.max(0), caps.end.max(0)) + pad
    dims = np.ceil((hi - lo) / resolution).astype(int) + 1
    grid = pv.ImageData(dimensions=tuple(int(x) for x in dims),
                        spacing=(resolution,) * 3, origin=tuple(lo))
    grid.point_data["sdf"] = _sdf_grid(caps, lo, dims, resolution, blend).ravel()
    surf = grid.contour([0.0], scalars="sdf", method="flying_edges").triangulate().clean()
    surf = surf.connectivity("largest") if surf.n_points else surf
    if surf.n_points > n_vertices:
        surf = surf.decimate(1.0 - n_vertices / surf.n_points).clean()
    v = np.asarray(surf.points, dtype=np.float64)
    f = np.asarray(surf.faces).reshape(-1, 4)[:, 1:].astype(np.int64)
    if len(v) == 0 or len(f) == 0:
        raise BodyError("procedural_body: empty surface (skeleton too small for the resolution?)")
    v, f = _compact(v, f)
    # wind outward: normals along the SDF gradient
    n = vertex_normals(v, f)
    g = _sdf_gradient(v, caps, blend)
    if np.mean(np.einsum("ij,ij->i", n, g)) < 0:
        f = f[:, [0, 2, 1]]
    W = _skin_weights(v, caps, skeleton.n_joints)
    return Body(skeleton, v, f, W, _inside(caps, v), attrs={"source": "procedural",
                                                       "resolution": resolution})


def _compact(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used = np.unique(f)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    f = remap[f]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    return v[used], f


def _sdf_gradient(p: np.ndarray, caps: Capsules, blend: float, h: float = 1e-3) -> np.ndarray:
    g = np.stack([(capsule_sdf(p + h * e, caps, blend=blend) - capsule_sdf(p - h * e, caps,
                                                                           blend=blend))
                  for e in np.eye(3)], axis=1)
    return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)


def _inside(caps: Capsules, vertices: np.ndarray, *, factor: float = 0.9,
            margin: float = 0.006) -> Capsules:
    """Occluder capsules shrunk by ``factor`` and further until every skin vertex is at
    least ``margin`` outside them (markers on the skin must never start inside one)."""
    r = caps.radius * factor
    shr = Capsules(caps.joint, caps.start, caps.end, r, caps.depth, caps.forward)
    slack = _capsule_distances(vertices, shr).min(0)  # (C,) most negative = deepest vertex
    cut = np.clip(margin - slack, 0.0, None)
    r = np.maximum(r - cut[:, None], 0.0)
    keep = r.max(1) > 0.005
    return Capsules(caps.joint[keep], caps.start[keep], caps.end[keep], r[keep],
                    caps.depth[keep], caps.forward)


# --------------------------------------------------------------------------- MakeHuman


def _read_obj(path: Path) -> tuple[np.ndarray, list[list[int]], list[str], dict[str, set[int]]]:
    """Vertices, polygon faces, the group of each face, and the vertices of each group."""
    verts: list[list[float]] = []
    faces: list[list[int]] = []
    face_group: list[str] = []
    groups: dict[str, set[int]] = {}
    cur = ""
    try:
        with open(path) as fh:
            for line in fh:
                if line.startswith("v "):
                    verts.append([float(x) for x in line.split()[1:4]])
                elif line.startswith("g "):
                    parts = line.split(maxsplit=1)
                    cur = parts[1].strip() if len(parts) > 1 else ""
                elif line.startswith("f "):
                    idx = [int(t.split("/")[0]) - 1 for t in line.split()[1:]]
                    faces.append(idx)
                    face_group.append(cur)
                    groups.setdefault(cur, set()).update(idx)
    except (OSError, ValueError) as e:
        raise BodyError(f"MakeHuman mesh {path}: cannot read OBJ ({e})") from None
    if not verts or not faces:
        raise BodyError(f"MakeHuman mesh {path}: no vertices or faces")
    return np.array(verts), faces, face_group, groups


def load_makehuman_body(
    obj_path: str | Path,
    *,
    rig_path: str | Path | None = None,
    weights_path: str | Path | None = None,
    unit: float = 0.1,
) -> Body:
    """The MakeHuman base mesh with its CMU-named rig and skin weights.

    Parameters
    ----------
    obj_path : str or Path
        ``makehuman_base.obj`` (decimetres, y up); only the ``body`` group is kept.
    rig_path, weights_path : str or Path, optional
        ``rig.cmu_mb.json`` / ``weights.cmu_mb.json``; default: beside the OBJ.
    unit : float
        Metres per OBJ unit (0.1).

    Returns
    -------
    Body
        Skeleton from the rig (joint positions = centres of the ``joint-*`` cubes
        or vertex means), bind pose = the mesh's A-pose; capsules fitted to the
        vertices each bone dominates.

    Raises
    ------
    BodyError
        Missing/corrupt files, a bone whose joint cube is absent.
    """
    obj_path = Path(obj_path)
    rig_path = Path(rig_path) if rig_path else obj_path.with_name("rig.cmu_mb.json")
    weights_path = Path(weights_path) if weights_path else obj_path.with_name("weights.cmu_mb.json")
    V, faces, face_group, groups = _read_obj(obj_path)
    try:
        rig = json.loads(rig_path.read_text())
        wdoc = json.loads(weights_path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise BodyError(f"MakeHuman rig/weights: cannot read ({e})") from None
    V = V * unit

    def joint_pos(spec: dict, bone: str) -> np.ndarray:
        if spec.get("strategy") == "CUBE":
            g = spec.get("cube_name")
            if g not in groups:
                raise BodyError(f"{rig_path}: bone {bone!r}: joint cube {g!r} not in {obj_path}")
            return V[sorted(groups[g])].mean(0)
        if "vertex_indices" in spec:
            return V[spec["vertex_indices"]].mean(0)
        raise BodyError(f"{rig_path}: bone {bone!r}: unsupported joint strategy {spec!r}")

    # parents before children
    names: list[str] = []
    pending = dict(rig)
    while pending:
        progressed = False
        for bone, spec in list(pending.items()):
            par = spec.get("parent") or ""
            if par == "" or par in names:
                names.append(bone)
                del pending[bone]
                progressed = True
        if not progressed:
            raise BodyError(f"{rig_path}: bones with unknown parents: {sorted(pending)}")
    roots = [n for n in names if not rig[n].get("parent")]
    if len(roots) != 1:
        raise BodyError(f"{rig_path}: expected one root bone, got {roots}")
    heads = np.array([joint_pos(rig[n]["head"], n) for n in names])
    tails = np.array([joint_pos(rig[n]["tail"], n) for n in names])
    parents = np.array([-1] + [names.index(rig[n]["parent"]) for n in names[1:]])
    offsets = heads - np.where(parents[:, None] >= 0, heads[np.maximum(parents, 0)], 0.0)
    offsets[0] = 0.0
    leaves = [j for j in range(len(names)) if not np.any(parents == j)]
    rot = ["Zrotation", "Yrotation", "Xrotation"]
    channels = [["Xposition", "Yposition", "Zposition", *rot]] + [rot] * (len(names) - 1)
    sk = Skeleton(names, parents, offsets, channels, end_parents=np.array(leaves, dtype=np.int64),
                  end_offsets=tails[leaves] - heads[leaves],
                  attrs={"source": obj_path.name, "root_bind_position": heads[0].tolist()})
    # body group only
    body_faces = [f for f, g in zip(faces, face_group) if g == "body"]
    if not body_faces:
        raise BodyError(f"{obj_path}: no 'body' group")
    tri = []
    for f in body_faces:
        for k in range(1, len(f) - 1):
            tri.append([f[0], f[k], f[k + 1]])
    tri = np.array(tri, dtype=np.int64)
    W = np.zeros((len(V), len(names)))
    for bone, pairs in wdoc.get("weights", {}).items():
        if bone in names and pairs:
            arr = np.asarray(pairs, dtype=np.float64)
            W[arr[:, 0].astype(int), names.index(bone)] = arr[:, 1]
    v_used = np.unique(tri)
    Vb = V[v_used] - heads[0]  # root at the origin, like bind_pose()
    remap = np.full(len(V), -1)
    remap[v_used] = np.arange(len(v_used))
    tri = remap[tri]
    Wb = W[v_used]
    s = Wb.sum(1, keepdims=True)
    if np.any(s <= 0):
        raise BodyError(f"{weights_path}: {int(np.sum(s <= 0))} body vertices have no weight")
    Wb = Wb / s
    # outward winding
    n = vertex_normals(Vb, tri)
    c = Vb.mean(0)
    if np.mean(np.einsum("ij,ij->i", n, Vb - c)) < 0:
        tri = tri[:, [0, 2, 1]]
    caps = _inside(_fit_capsules(Vb, Wb, sk), Vb, factor=1.0)
    return Body(sk, Vb, tri, Wb, caps, attrs={"source": "makehuman", "obj": obj_path.name})


def _fit_capsules(V: np.ndarray, W: np.ndarray, sk: Skeleton) -> Capsules:
    bind = bind_pose(sk)
    part = np.argmax(W, 1)
    J = sk.n_joints
    joint, a_, b_, rad = [], [], [], []
    for j in range(J):
        kids = sk.children(j)
        tgt = [bind[c] for c in kids] or [bind[sk.end_parents[e]] + sk.end_offsets[e]
                                           for e in np.flatnonzero(sk.end_parents == j)]
        vj = V[part == j]
        if len(vj) < 10:
            continue
        for t in tgt:
            if np.linalg.norm(t - bind[j]) < 1e-3:
                continue
            d, _ = _segment_distance(vj, bind[j], t)
            r = float(np.percentile(d, 30)) * 0.85
            joint.append(j)
            a_.append(bind[j])
            b_.append(t)
            rad.append((r, r))
    return Capsules(np.array(joint), np.array(a_), np.array(b_), np.array(rad),
                    np.ones(len(joint)), np.array([0.0, 0.0, 1.0]))


# --------------------------------------------------------------------------- posing


def _min_rotation(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Quaternion of the smallest rotation taking direction u to v."""
    u = u / np.linalg.norm(u)
    v = v / np.linalg.norm(v)
    c = float(u @ v)
    if c < -0.999999:
        axis = np.cross(u, [1.0, 0, 0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(u, [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return np.array([0.0, *axis])
    q = np.array([1.0 + c, *np.cross(u, v)])
    return q / np.linalg.norm(q)


def align_to(body: Body, skeleton: Skeleton) -> np.ndarray:
    """Per body joint, the rotation from the body's bind pose to ``skeleton``'s rest pose.

    Bones are matched by joint name; each matched bone's direction (to the child
    present in both) is rotated minimally onto the skeleton's.

    Returns
    -------
    (J, 4) float ndarray
    """
    bs = body.skeleton
    bb, sb = bind_pose(bs), bind_pose(skeleton)
    sidx = {n: i for i, n in enumerate(skeleton.names)}
    out = np.tile([1.0, 0, 0, 0], (bs.n_joints, 1))
    for j, name in enumerate(bs.names):
        if name not in sidx or j == 0:
            continue
        best = None
        for c in bs.children(j):
            cn = bs.names[c]
            if cn not in sidx:
                continue
            u = bb[c] - bb[j]
            v = sb[sidx[cn]] - sb[sidx[name]]
            if np.linalg.norm(u) < 1e-4 or np.linalg.norm(v) < 1e-4:
                continue
            cos = u @ v / np.linalg.norm(u) / np.linalg.norm(v)
            if best is None or cos > best[0]:
                best = (cos, u, v)
        if best is not None:
            out[j] = _min_rotation(best[1], best[2])
        else:
            out[j] = out[bs.parents[j]]
    return out


def skinning_transforms(body: Body, motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """World transforms of the body's joints over a motion.

    A body point ``v`` (bind pose) bound to joint ``j`` goes to
    ``R[f, j] @ (v - bind[j]) + p[f, j]``.

    Parameters
    ----------
    body : Body
    motion : Motion
        Its joints are matched to the body's by name; body joints the motion
        lacks follow their parent.  When the skeletons differ, bones are aligned
        with :func:`align_to` and the root translation is scaled by the ratio of
        hip heights.

    Returns
    -------
    R : (F, J, 3, 3) float ndarray
    p : (F, J, 3) float ndarray

    Raises
    ------
    BodyError
        The motion shares no joint name with the body (other than none at all).
    """
    bs, ms = body.skeleton, motion.skeleton
    F = motion.n_frames
    if bs is ms or (bs.names == ms.names and np.allclose(bs.offsets, ms.offsets)):
        pos, grot = forward_kinematics(ms, motion.rotations, motion.root_position,
                                       translations=motion.translations)
        return quat_to_matrix(grot), pos
    sidx = {n: i for i, n in enumerate(ms.names)}
    shared = [n for n in bs.names if n in sidx]
    if len(shared) < 2 or bs.names[0] not in sidx:
        raise BodyError(
            f"the motion's skeleton ({ms.names[:5]}…) does not match the body's joint names "
            f"({bs.names[:5]}…); they must share the root and the bones to drive")
    _, mgrot = forward_kinematics(ms, motion.rotations, motion.root_position,
                                  translations=motion.translations)
    A = align_to(body, ms)
    J = bs.n_joints
    grot = np.empty((F, J, 4))
    pos = np.empty((F, J, 3))
    bb, sb = bind_pose(bs), bind_pose(ms)
    scale = (bb[:, 1].max() - bb[:, 1].min()) / max(sb[:, 1].max() - sb[:, 1].min(), 1e-9)
    for j in range(J):
        name = bs.names[j]
        p = bs.parents[j]
        if name in sidx:
            grot[:, j] = quat_multiply(mgrot[:, sidx[name]], A[j])
        else:
            grot[:, j] = grot[:, p]
        if p < 0:
            pos[:, j] = motion.root_position * scale
        else:
            pos[:, j] = pos[:, p] + quat_rotate(grot[:, p], bs.offsets[j])
    return quat_to_matrix(grot), pos


def skin(
    body: Body,
    R: np.ndarray,
    p: np.ndarray,
    *,
    points: np.ndarray | None = None,
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """Linear-blend skinning.

    Parameters
    ----------
    body : Body
    R : (F, J, 3, 3) float ndarray
    p : (F, J, 3) float ndarray
        From :func:`skinning_transforms`.
    points : (N, 3) float ndarray, optional
        Bind-pose points to skin (default: the body's vertices), or ``(F, N, 3)``
        per-frame bind-space points (pose-space deformations).
    weights : (N, J) float ndarray, optional
        Their weights (default: the body's).

    Returns
    -------
    (F, N, 3) float ndarray
    """
    pts = body.vertices if points is None else np.asarray(points, dtype=np.float64)
    W = body.weights if weights is None else np.asarray(weights, dtype=np.float64)
    bind = body.bind_positions()
    F = R.shape[0]
    out = np.zeros((F, pts.shape[-2], 3))
    for j in np.flatnonzero(W.max(0) > 0):
        idx = np.flatnonzero(W[:, j] > 0)
        moved = _rotate(R[:, j], pts[..., idx, :] - bind[j]) + p[:, j, None]
        out[:, idx] += W[idx, j][None, :, None] * moved
    return out


def _rotate(R: np.ndarray, local: np.ndarray) -> np.ndarray:
    """R (F,3,3) applied to local (N,3) or (F,N,3) -> (F,N,3)."""
    if local.ndim == 2:
        return np.einsum("fij,nj->fni", R, local)
    return np.einsum("fij,fnj->fni", R, local)
