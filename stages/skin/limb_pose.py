"""The template's limbs turned to the capture's named joint markers (sparse captures).

Below Park & Hodgins' density the template is only scaled, turned and shifted onto the
markers (:func:`~mocapflow.stages.skin.mesh_fit.upright_fit`), so its limbs keep the
template's T-pose: on the Qualisys walk the arms stood out sideways while the arm markers
hung beside the hips, and each arm vertex was bound to whichever part was nearest.
Where the capture names its elbow, wrist, knee and ankle markers (``LELB``, ``L_HLE``,
``LWRA``, ``R_RSP``, ``LKNE``, ``L_FAL``, ...;
:func:`~mocapflow.stages.skin.marker_regions.joint_landmark`), each limb bone of the
template is turned about its proximal joint so that its distal joint points at those
markers (:func:`joint_targets`, :func:`pose_limbs`): the upper arm to the elbow, the
forearm to the wrist, the thigh to the knee, the shank to the ankle (an upper arm with
no elbow marker but a wrist one: the straight arm to the wrist).  A vertex turns with the
bone its rig gives it (its dominant joint), the weights smoothed over a few rings of the
mesh so that the skin bends at the joint instead of tearing (:func:`_blend_weights`).  A
joint marked on one side only is centred inside the limb (:func:`joint_targets`); the
fit then matches the joint markers to the skin around the turned joints
(:func:`joint_regions`; the rounds: :func:`~mocapflow.stages.skin.mesh_fit._posed_fit`).
:func:`limb_binding` then holds a limb's skin to its own limb's parts and the body's
when the mesh is bound (:func:`~mocapflow.stages.skin.binding.bind_mesh`).

Measured on the shared captures (``python benchmarks/sparse_fit.py``: the skin graph's
segmentation, 13,000 vertices, ``marker_offset`` 7 mm), the named joint markers' median
distance to the fitted body, T-pose -> turned: Qualisys walk 145 -> 3 mm, Plug-in Gait
calibration 105 -> 5, pyomeca 41 -> 10, basket 66 -> 2; all markers' median 73 -> 13,
39 -> 11, 45 -> 21, 23 -> 17 mm.  The racing athlete, bent forward over the wheelchair,
stays in the T-pose: the upright template's shoulders are 1.8-2.3 upper arms from the
elbow markers (:data:`BONE_REACH`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from mocapflow.stages.motion.geometry import mesh_laplacian
from mocapflow.stages.skin.marker_regions import (
    LIMB_JOINTS,
    joint_landmark,
    label_side,
    marker_region,
)

__all__ = ["BONE_REACH", "JOINT_RADIUS", "joint_regions", "joint_targets", "limb_binding",
           "pose_limbs"]

#: A joint marker is aimed at only if its distance from the bone's proximal joint is within
#: this range of the bone's length (a marker named like a joint but elsewhere, or a body
#: far from the template's proportions, leaves the bone as it is).
BONE_REACH = (0.55, 1.6)

#: Skin within this distance (m, fitted template) of a limb joint is that joint's region:
#: where its markers are matched when the posed template is fitted again
#: (:func:`joint_regions`).
JOINT_RADIUS = 0.08

#: Reach (m) of the skin's bend about a turned joint (:func:`pose_limbs`' ``blend``).
BLEND = 0.05

#: Turn weights below this are none (the averaging's far tail: a shoulder's turn
#: leaves the head where it is).
MIN_WEIGHT = 0.01

#: Joint markers closer together than this (m) mark one side of the joint only
#: (:func:`joint_targets`); a lateral and a medial epicondyle lie 6-10 cm apart.
PAIR_SPREAD = 0.04

#: The limb chains: (proximal joint marker, distal joint marker) per limb.
CHAINS = (("elbow", "wrist"), ("knee", "ankle"))
#: Each joint marker's chain, by its proximal joint.
_CHAIN_OF = {joint: first for first, second in CHAINS for joint in (first, second)}

_SIDES = ("Left", "Right")


def _joint(names: list[str], side: str, suffix: str) -> str | None:
    """The rig's joint ``side + suffix`` (``LeftForeArm``), or ``side[0] + suffix``
    (``LThumb``), or None."""
    for name in (f"{side}{suffix}", f"{side[0]}{suffix}"):
        if name in names:
            return name
    return None


def joint_targets(
    labels: list[str], reference: np.ndarray, bones: dict[str, np.ndarray],
    vertices: np.ndarray | None = None,
) -> dict[tuple[str, str], tuple[np.ndarray, np.ndarray]]:
    """Where the capture puts each named limb joint: ``{(side, joint): (position (3,),
    marker indices (k,))}``.

    A marker naming a joint (:func:`~mocapflow.stages.skin.marker_regions.joint_landmark`)
    counts for the side its label's case marks
    (:func:`~mocapflow.stages.skin.marker_regions.label_side`: ``LELB``, ``R_FME``,
    ``RadialStyloidR``); without one (pyomeca's ``EPICl`` is a *lateral* epicondyle), for
    the side of the body it lies on: left of the template's midline (the mean of its left
    and right shoulders for arm joints, hips for leg joints) when it lies towards the
    template's left shoulder (hip).  The joint's position is the mean of its
    markers (a lateral and a medial epicondyle: the joint centre; one side only: moved
    inside the limb, see ``vertices``).

    Parameters
    ----------
    labels : list of str
        ``M`` marker labels.
    reference : (M, 3) float ndarray
        Their reference positions (NaN: not seen), in the fitted template's frame.
    bones : dict
        ``{joint: (2, 3) [start, end]}`` of the fitted template.
    vertices : (V, 3) float ndarray, optional
        The fitted template: a joint marked on one side only (markers within
        :data:`PAIR_SPREAD` of each other: Plug-in Gait's ``LKNE``, ``LANK``, ``LELB`` on
        the lateral epicondyles and malleolus) has its centre that far inside the limb,
        towards the body's midline, as the template's limb is thick there
        (:func:`_limb_radius`); aimed at the marker itself the limb's skin stood 44-65
        mm off PiG's knee, ankle and elbow markers.

    Returns
    -------
    dict
    """
    ref = np.asarray(reference, dtype=np.float64)
    names = list(bones)
    out: dict[tuple[str, str], list] = {}
    for i, label in enumerate(labels):
        joint = joint_landmark(label)
        if joint is None or not np.isfinite(ref[i]).all():
            continue
        ends = [_joint(names, side, LIMB_JOINTS[_CHAIN_OF[joint]][0]) for side in _SIDES]
        if None in ends:
            continue
        side = label_side(label)
        if side is None:  # where it lies, against the template's midline
            left, right = (np.asarray(bones[e])[0] for e in ends)
            side = _SIDES[0] if (ref[i] - (left + right) / 2) @ (left - right) > 0 else \
                _SIDES[1]  # fmt: skip
        out.setdefault((side, joint), []).append(i)
    targets = {k: ref[v].mean(axis=0) for k, v in out.items()}
    shifted = {}
    for (side, joint), idx in out.items():
        centre = targets[(side, joint)]
        spread = max((np.linalg.norm(ref[a] - ref[b]) for a in idx for b in idx), default=0.0)
        first = _CHAIN_OF[joint]
        ends = [_joint(names, sd, LIMB_JOINTS[first][0]) for sd in _SIDES]
        bone = _joint(names, side, LIMB_JOINTS[joint][0])
        if vertices is not None and spread < PAIR_SPREAD and bone:
            left, right = (np.asarray(bones[e])[0] for e in ends)
            # the limb's axis into this joint: from its marked proximal joint, else from
            # the shoulder (hip); the centre lies inward across it
            root = np.asarray(bones[ends[_SIDES.index(side)]])[0]
            parent = targets.get((side, first), root) if joint != first else root
            axis = centre - parent
            inward = right - left if side == _SIDES[0] else left - right
            if np.linalg.norm(axis) > 0:
                axis = axis / np.linalg.norm(axis)
                inward = inward - (inward @ axis) * axis
            if np.linalg.norm(inward) > 1e-9:
                inward = inward / np.linalg.norm(inward)
                start, end = np.asarray(bones[bone])
                centre = centre + inward * _limb_radius(vertices, end, end - start)
        shifted[(side, joint)] = (centre, np.array(idx))
    return shifted


def _limb_radius(vertices: np.ndarray, joint: np.ndarray, bone: np.ndarray) -> float:
    """The template's thickness at a limb joint: the median distance from the bone's axis
    ``bone (3,)`` to the skin within 2 cm of the joint along it and :data:`JOINT_RADIUS`
    across it."""
    axis = bone / np.linalg.norm(bone)
    rel = np.asarray(vertices) - joint
    along = rel @ axis
    across = np.linalg.norm(rel - along[:, None] * axis, axis=1)
    near = across[(np.abs(along) < 0.02) & (across <= JOINT_RADIUS)]
    return float(np.median(near)) if near.size else 0.0


def _adjacency(faces: np.ndarray, n: int) -> sp.csr_matrix:
    """Row-normalised vertex adjacency ``D⁻¹A`` of a triangle mesh ``(n, n)``: the
    off-diagonal of :func:`~mocapflow.stages.motion.geometry.mesh_laplacian`, negated."""
    L = mesh_laplacian(n, np.asarray(faces, dtype=np.int64))
    return (sp.diags(L.diagonal()) - L).tocsr()


def _blend_weights(moving: np.ndarray, adjacency: sp.csr_matrix, rings: int) -> np.ndarray:
    """``(V,)`` weights of a bone's turn: 1 on the vertices it carries, 0 elsewhere,
    averaged over neighbours ``rings`` times (the skin bends over a few rings around the
    joint; a vertex far inside the limb or the trunk keeps 1 or 0)."""
    w = moving.astype(np.float64)
    for _ in range(rings):
        w = adjacency @ w
    return w


def _aim(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotation vector of the smallest turn taking direction ``u`` to ``v``."""
    u = u / np.linalg.norm(u)
    v = v / np.linalg.norm(v)
    axis = np.cross(u, v)
    s = np.linalg.norm(axis)
    angle = float(np.arctan2(s, u @ v))
    if s < 1e-12:  # parallel (no turn) or opposite (no unique turn: left as it is)
        return np.zeros(3)
    return axis / s * angle


def pose_limbs(
    vertices: np.ndarray,
    faces: np.ndarray,
    bones: dict[str, np.ndarray],
    vertex_part: np.ndarray,
    targets: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]],
    *,
    blend: float = BLEND,
) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, Any]]:
    """Turn the template's limb bones so that their distal joints point at ``targets``.

    For each side and limb (arm: elbow then wrist; leg: knee then ankle), the upper bone
    (``LeftArm``, ``LeftUpLeg``) is turned about its proximal joint by the smallest
    rotation taking its distal joint's direction to the first target's; then the lower
    bone (``LeftForeArm``, ``LeftLeg``) about the turned middle joint to the second
    target.  With only the second target, the upper bone is turned so that the lower
    bone's end points at it (a straight limb).  A target outside :data:`BONE_REACH` of
    the bone's (or straight limb's) length leaves that bone as it is.

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        Fitted template.
    faces : (T, 3) int ndarray
    bones : dict
        ``{joint name: (2, 3) [start, end]}`` of the fitted template (its rig's names:
        ``LeftArm``, ``LeftForeArm``, ``LeftUpLeg``, ``LeftLeg``, ...).
    vertex_part : (V,) int ndarray
        Each vertex's dominant joint, an index into ``list(bones)``.
    targets : dict
        :func:`joint_targets`.
    blend : float
        Reach (m) of the skin's bend about a turned joint: each turn's weights are
        averaged over ``(blend / median edge length)²`` rings of neighbours
        (:func:`_blend_weights`; 0: each vertex turns with its dominant joint alone, which
        tears the skin at the joint).

    Returns
    -------
    vertices : (V, 3) float ndarray
    bones : dict
        The turned bones.
    report : dict
        ``turned_deg``: ``{bone: degrees}`` of each turn made; ``beyond_reach``: ``{bone:
        target distance / bone length}`` of the bones left as they were.
    """
    V = np.array(vertices, dtype=np.float64)
    names = list(bones)
    bones = {k: np.array(v, dtype=np.float64).reshape(2, 3) for k, v in bones.items()}
    part = np.asarray(vertex_part)
    adjacency = None
    f = np.asarray(faces, dtype=np.int64)
    edge = float(np.median(np.linalg.norm(V[f] - V[np.roll(f, 1, axis=1)], axis=-1))) \
        if len(f) else 1.0  # fmt: skip
    rings = int(round((blend / edge) ** 2)) if edge > 0 else 0
    turned: dict[str, float] = {}
    beyond: dict[str, float] = {}

    def reach(bone: str, d: np.ndarray, length: float) -> bool:
        """Whether a target ``d`` from the bone's pivot is within :data:`BONE_REACH` of
        ``length`` (else noted in the report's ``beyond``)."""
        ratio = float(np.linalg.norm(d) / max(length, 1e-12))
        if BONE_REACH[0] <= ratio <= BONE_REACH[1]:
            return True
        beyond[bone] = round(ratio, 2)
        return False

    def carried(joint: str, side: str) -> list[str]:
        """The rig's joints a turn of ``joint``'s upper bone carries on ``side``."""
        return [j for s in LIMB_JOINTS[joint][2] if (j := _joint(names, side, s)) is not None]

    def turn(bone: str, distal: list[str], rv: np.ndarray) -> None:
        nonlocal V, adjacency
        angle = float(np.linalg.norm(rv))
        if angle < 1e-9:
            return
        adjacency = _adjacency(faces, len(V)) if adjacency is None else adjacency
        ids = [names.index(j) for j in distal]
        w = _blend_weights(np.isin(part, ids), adjacency, rings)
        sel = w >= MIN_WEIGHT
        pivot = bones[bone][0]
        V[sel] = Rotation.from_rotvec(w[sel, None] * rv).apply(V[sel] - pivot) + pivot
        R = Rotation.from_rotvec(rv)
        for j in distal:
            bones[j] = R.apply(bones[j] - pivot) + pivot
        turned[bone] = round(float(np.degrees(angle)), 2)

    for side in _SIDES:
        for first, second in CHAINS:
            upper = _joint(names, side, LIMB_JOINTS[first][0])
            lower = _joint(names, side, LIMB_JOINTS[first][1])
            if upper is None or lower is None:
                continue
            own, own_lower = carried(first, side), carried(second, side)
            a, b = targets.get((side, first)), targets.get((side, second))
            head = bones[upper][0]
            if a is not None:
                d = a[0] - head
                if reach(upper, d, np.linalg.norm(bones[upper][1] - head)):
                    turn(upper, own, _aim(bones[upper][1] - head, d))
                else:
                    a = None
            elif b is not None:  # the straight limb to the distal target
                end = bones[lower][1]
                d = b[0] - head
                if reach(upper, d, np.linalg.norm(end - head)):
                    turn(upper, own, _aim(end - head, d))
                continue
            if b is not None and a is not None:
                mid = bones[lower][0]
                d = b[0] - mid
                if reach(lower, d, np.linalg.norm(bones[lower][1] - mid)):
                    turn(lower, own_lower, _aim(bones[lower][1] - mid, d))
    return V, bones, {"turned_deg": turned, "beyond_reach": beyond}


def joint_regions(
    vertices: np.ndarray, bones: dict[str, np.ndarray],
    targets: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]], n_markers: int,
) -> tuple[list[str | None], dict[str, np.ndarray]]:
    """The posed template's skin around each named limb joint, as regions its markers
    are matched to (:func:`~mocapflow.stages.skin.mesh_fit.upright_fit`'s
    ``marker_regions`` and ``region_masks``).

    Parameters
    ----------
    vertices : (V, 3) float ndarray
        The posed template.
    bones : dict
        Its bones (:func:`pose_limbs`' second output).
    targets : dict
        :func:`joint_targets`.
    n_markers : int

    Returns
    -------
    marker_regions : list of (str or None)
        ``"<side> <joint>"`` for the joint markers, None for the others.
    region_masks : dict
        ``{"<side> <joint>": (V,) bool}``: the vertices within :data:`JOINT_RADIUS` of
        the joint.
    """
    names = list(bones)
    regions: list[str | None] = [None] * n_markers
    masks: dict[str, np.ndarray] = {}
    for (side, joint), (_, idx) in targets.items():
        bone = _joint(names, side, LIMB_JOINTS[joint][0])
        if bone is None:
            continue
        centre = np.asarray(bones[bone])[1]
        mask = np.linalg.norm(np.asarray(vertices) - centre, axis=1) <= JOINT_RADIUS
        if mask.any():
            key = f"{side} {joint}"
            masks[key] = mask
            for i in idx:
                regions[int(i)] = key
    return regions, masks


def _vertex_limbs(names: list[str], vertex_part: np.ndarray) -> np.ndarray:
    """``(V,)`` object array: ``"arm Left"``, ``"leg Right"``, ... for a vertex whose
    dominant joint is on a limb (the joints an upper arm's or thigh's turn carries), else
    ``"body"``."""
    limb_of = {}
    for limb, joint in (("arm", "elbow"), ("leg", "knee")):
        for side in _SIDES:
            for s in LIMB_JOINTS[joint][2]:
                j = _joint(names, side, s)
                if j is not None:
                    limb_of[names.index(j)] = f"{limb} {side}"
    table = np.array([limb_of.get(i, "body") for i in range(len(names))], dtype=object)
    return table[np.asarray(vertex_part)]


def limb_binding(
    labels: list[str], reference: np.ndarray, part_weights: np.ndarray,
    vertices: np.ndarray, joint_names: list[str], vertex_part: np.ndarray,
) -> np.ndarray | None:
    """``(V, P)`` bool: the parts each template vertex may follow — a limb's skin its own
    limb's parts and the body's, the body's skin the body's parts
    (:func:`~mocapflow.stages.skin.binding.bind_mesh`'s ``allowed``).

    A part is the body's when one of its markers names the pelvis, trunk, head or shoulder
    girdle (:func:`~mocapflow.stages.skin.marker_regions.marker_region`), an arm's or leg's
    when one names its elbow or wrist, knee or ankle
    (:func:`~mocapflow.stages.skin.marker_regions.joint_landmark`; the side from the label,
    else from the nearest limb of the fitted template); a part with no such marker may be
    followed by any vertex.  On pyomeca's seated capture the standing template's left thigh
    lies where the forearm hangs: bound to the forearm's part, the whole leg swung up with
    the box; held to the body's parts it stays with the pelvis.

    Parameters
    ----------
    labels : list of str
        ``M`` marker labels of the segmentation.
    reference : (M, 3) float ndarray
    part_weights : (M, P) float ndarray
        The segmentation's ``α`` (a marker counts for its largest).
    vertices : (V, 3) float ndarray
        The fitted template (its limbs posed to the markers).
    joint_names : list of str
    vertex_part : (V,) int ndarray
        Each vertex's dominant joint.

    Returns
    -------
    (V, P) bool ndarray, or None when no marker names a place (nothing to hold).
    """
    ref = np.asarray(reference, dtype=np.float64)
    alpha = np.asarray(part_weights, dtype=np.float64)
    vlimb = _vertex_limbs(list(joint_names), vertex_part)
    V = np.asarray(vertices, dtype=np.float64)
    P = alpha.shape[1]
    kinds: list[set[str]] = [set() for _ in range(P)]
    for i, label in enumerate(labels):
        if not np.isfinite(ref[i]).all():
            continue
        kind = None
        if marker_region(label) is not None:
            kind = "body"
        elif (joint := joint_landmark(label)) is not None:
            limb = "arm" if _CHAIN_OF[joint] == "elbow" else "leg"
            side = label_side(label)
            if side is None:  # the side of the nearest vertex of such a limb
                on = np.flatnonzero(np.char.startswith(vlimb.astype(str), limb))
                if not on.size:
                    continue
                side = vlimb[on[np.argmin(np.linalg.norm(V[on] - ref[i], axis=1))]].split()[1]
            kind = f"{limb} {side}"
        if kind is not None:
            kinds[int(np.argmax(alpha[i]))].add(kind)
    if not any(kinds):
        return None
    allowed = np.ones((len(V), P), dtype=bool)
    for p, k in enumerate(kinds):
        if k:  # the body's skin follows the body's parts; a limb's its own and the body's
            allowed[:, p] = np.isin(vlimb, list(k)) | (("body" in k) & (vlimb != "body"))
    return allowed
