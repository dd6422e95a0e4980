"""The MakeHuman body: the CC0 base mesh with its CMU-named rig and skin weights.

:func:`load_makehuman_body` reads ``makehuman_base.obj`` (``shared/data/mesh``)
with ``rig.cmu_mb.json`` and ``weights.cmu_mb.json`` beside it: the skeleton
from the rig's joint cubes (:func:`_rig_skeleton`), the ``body`` group's
triangles (:func:`_body_triangles`), the bone weights (:func:`_bone_weights`),
and occluder capsules fitted to the vertices each bone dominates
(:func:`_fit_capsules`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mocapflow.stages.motion.datatypes import Skeleton
from mocapflow.stages.motion.geometry import vertex_normals
from mocapflow.stages.motion.simulate.body import (
    Body,
    BodyError,
    Capsules,
    bind_pose,
    point_segment_distance,
)
from mocapflow.stages.motion.simulate.capsules import occluder_capsules

__all__ = ["load_makehuman_body"]


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
    sk, root = _rig_skeleton(rig, V, groups, rig_path=rig_path, obj_path=obj_path)
    tri = _body_triangles(faces, face_group, obj_path)
    W = _bone_weights(wdoc, sk.names, len(V))
    Vb, tri, Wb = _used_vertices(V, tri, W, root, weights_path)
    # outward winding
    n = vertex_normals(Vb, tri)
    c = Vb.mean(0)
    if np.mean(np.einsum("ij,ij->i", n, Vb - c)) < 0:
        tri = tri[:, [0, 2, 1]]
    caps = occluder_capsules(_fit_capsules(Vb, Wb, sk), Vb, factor=1.0)
    return Body(sk, Vb, tri, Wb, caps, attrs={"source": "makehuman", "obj": obj_path.name})


def _bones_parents_first(rig: dict, rig_path: Path) -> list[str]:
    """The rig's bone names ordered parents before children (one root)."""
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
    return names


def _joint_position(spec: dict, bone: str, V: np.ndarray, groups: dict[str, set[int]], *,
                    rig_path: Path, obj_path: Path) -> np.ndarray:
    """``(3,)`` position of a rig joint: the centre of its ``joint-*`` cube or of its vertices."""
    if spec.get("strategy") == "CUBE":
        g = spec.get("cube_name")
        if g not in groups:
            raise BodyError(f"{rig_path}: bone {bone!r}: joint cube {g!r} not in {obj_path}")
        return V[sorted(groups[g])].mean(0)
    if "vertex_indices" in spec:
        return V[spec["vertex_indices"]].mean(0)
    raise BodyError(f"{rig_path}: bone {bone!r}: unsupported joint strategy {spec!r}")


def _rig_skeleton(rig: dict, V: np.ndarray, groups: dict[str, set[int]], *, rig_path: Path,
                  obj_path: Path) -> tuple[Skeleton, np.ndarray]:
    """The skeleton of the rig (bone heads as joints, tails of leaves as End Sites).

    Returns the skeleton (in the mesh's A-pose, offsets in metres) and the root's
    bind position ``(3,)`` in mesh coordinates.
    """
    names = _bones_parents_first(rig, rig_path)

    def joint_pos(spec: dict, bone: str) -> np.ndarray:
        return _joint_position(spec, bone, V, groups, rig_path=rig_path, obj_path=obj_path)

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
    return sk, heads[0]


def _body_triangles(faces: list[list[int]], face_group: list[str], obj_path: Path) -> np.ndarray:
    """``(T, 3)`` triangles (fans of the polygons) of the OBJ's ``body`` group."""
    body_faces = [f for f, g in zip(faces, face_group) if g == "body"]
    if not body_faces:
        raise BodyError(f"{obj_path}: no 'body' group")
    tri = []
    for f in body_faces:
        for k in range(1, len(f) - 1):
            tri.append([f[0], f[k], f[k + 1]])
    return np.array(tri, dtype=np.int64)


def _bone_weights(wdoc: dict, names: list[str], n_vertices: int) -> np.ndarray:
    """``(V, J)`` skin weights of the weights document (``{"weights": {bone: [[v, w]...]}}``)."""
    W = np.zeros((n_vertices, len(names)))
    for bone, pairs in wdoc.get("weights", {}).items():
        if bone in names and pairs:
            arr = np.asarray(pairs, dtype=np.float64)
            W[arr[:, 0].astype(int), names.index(bone)] = arr[:, 1]
    return W


def _used_vertices(V: np.ndarray, tri: np.ndarray, W: np.ndarray, root: np.ndarray,
                   weights_path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vertices the triangles use, the root at the origin (like ``bind_pose``).

    Returns vertices ``(V', 3)``, re-indexed triangles and normalised weights ``(V', J)``.
    """
    v_used = np.unique(tri)
    Vb = V[v_used] - root
    remap = np.full(len(V), -1)
    remap[v_used] = np.arange(len(v_used))
    tri = remap[tri]
    Wb = W[v_used]
    s = Wb.sum(1, keepdims=True)
    if np.any(s <= 0):
        raise BodyError(f"{weights_path}: {int(np.sum(s <= 0))} body vertices have no weight")
    return Vb, tri, Wb / s


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
            d, _ = point_segment_distance(vj, bind[j], t)
            r = float(np.percentile(d, 30)) * 0.85
            joint.append(j)
            a_.append(bind[j])
            b_.append(t)
            rad.append((r, r))
    return Capsules(np.array(joint), np.array(a_), np.array(b_), np.array(rad),
                    np.ones(len(joint)), np.array([0.0, 0.0, 1.0]))
