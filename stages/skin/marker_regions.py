"""Body regions named by a capture's marker labels (the upright fit of sparse captures).

Labs name markers by their anatomical place, each marker set in its own words: Plug-in
Gait's ``LASI``, ``C7``, ``STRN``, ``LFHD``; Qualisys' ``L_IAS``, ``CV7``, ``SXS``,
``L_HDF``; ISB-style ``ASISr``, ``T10``, ``XIPH``, ``CLAV_AC``; BTS' ``r asis``, ``c7``,
``sacrum``.  :func:`marker_region` reads the few places that hold still relative to the
trunk in any pose, standing or seated (pelvis, trunk, head, shoulder girdle) from such a
label; :func:`region_vertices` gives the template's vertices of each region from its rig
(the dominant joint of each vertex, :func:`~mocapflow.stages.skin.mesh_fit.template_mesh`).
:func:`~mocapflow.stages.skin.mesh_fit.upright_fit` then matches a named marker to its
region's skin only.  Limbs are left unnamed on purpose: the template's T-pose puts them
where few captures have them (a seated subject's thighs, arms down), so their markers
match the whole skin as before.

Without the names, the upright fit of pyomeca's seated trunk-and-arm capture
(``pyomeca_markers_analogs.c3d``: pelvis 0.17 m and sternum 0.6 m above the origin) laid
the standing template's legs through the trunk markers.  :func:`marker_face` reads
whether a pelvis or trunk marker sits in front (ASIS, sternum, clavicle) or behind (PSIS,
sacrum, spine, scapula), and :func:`body_facing` the way the body faces from them, which
the upright fit turns the template to: the closest points alone had turned it 121 degrees
away on the Qualisys capture.
"""

from __future__ import annotations

import re

import numpy as np

__all__ = ["LIMB_JOINTS", "REGION_JOINTS", "body_facing", "joint_landmark", "label_side",
           "marker_face", "marker_region", "region_vertices"]

#: The template joints (procedural CMU skeleton) whose vertices make each region.
REGION_JOINTS: dict[str, tuple[str, ...]] = {
    "pelvis": ("Hips", "LHipJoint", "RHipJoint", "LowerBack"),
    "trunk": ("LowerBack", "Spine", "Spine1"),
    "upper_trunk": ("Spine1",),  # its upper half (:func:`region_vertices`)
    "head": ("Head",),
    "shoulder": ("Spine1", "LeftShoulder", "RightShoulder"),
}

# names (lower case, spaces, '_' and '-' removed, a side letter or word stripped) per
# region; vertebrae and the sacrum only without a side ("RT1" is a right thigh's first
# marker, "RS1" a shank's, not T1 or S1)
_SIDED = {
    "pelvis": r"asis?|ias|psis?|ips",
    "upper_trunk": r"clav\w*",
    "trunk": r"bak|back|ster\w*|scap\w*",
    "head": r"fhd|bhd|hdf|hdb|head\d*|forehead|temple|ear",
    "shoulder": r"sho|should|shoulder|acro\w*|saj|ac",
}
_UNSIDED = {
    "pelvis": r"asis?|sacr|sacrum|sacral|sa|s1",
    "upper_trunk": r"c7|cv7|t[12]|tv[12]|th[12]|snj|sjn|ij|jn|clav\w*|manub\w*",
    "trunk": r"t\d{1,2}|tv\d{1,2}|th\d{1,2}|strn|ster\w*|xiph\w*|sxs|px|rbak|lbak|back|"
             r"scap\w*",
    "head": r"head\d*|forehead|vertex|hdt|glabella|nasion",
    "shoulder": r"acro\w*",
}  # fmt: skip
# which face of the body a named marker sits on (front: ASIS, sternum, clavicle; back:
# PSIS, sacrum, spine, scapula), matched like the names, on the name with its side
# stripped too (:func:`marker_face`)
_FRONT = r"asis?|ias|strn|ster\w*|xiph\w*|sxs|px|snj|sjn|ij|jn|clav\w*"
_BACK = r"psis?|ips|sacr\w*|sa|s1|c7|cv7|t\d{1,2}|tv\d{1,2}|th\d{1,2}|bak|back|scap\w*"
# markers on a limb joint (lower case, separators removed; matched with and without a
# leading or trailing side letter or word, which lower case cannot tell from pyomeca's
# ``EPICl``, a lateral epicondyle, or ``STYLr``, a radial styloid: the side is read by
# :func:`label_side` from the label's case, else from where the marker lies)
_JOINT_LANDMARKS = {
    "elbow": r"elb\w*|hle|hme|humer\w*|epic\w*|(?:lateral|medial)?epicondyle|olecr\w*",
    "wrist": r"wr[ab]?|wrist\w*|rsp|usp|uhe|styl\w*|(?:radial|ulnar)styloid\w*",
    "knee": r"kne|knee\w*|fle|fme|(?:lateral|medial)(?:femoral)?condyle|lfc|mfc",
    "ankle": r"ank|ankle\w*|fal|tam|mal|malleol\w*|(?:lateral|medial)malleolus|latmal|medmal",
}

#: The template joints (both templates' rigs) each limb joint ends, and the joints a turn
#: of that bone carries (it and every joint below it), per side.
LIMB_JOINTS: dict[str, tuple[str, str, tuple[str, ...]]] = {
    "elbow": ("Arm", "ForeArm", ("Arm", "ForeArm", "Hand", "FingerBase", "HandFinger1",
                                 "Fingers", "Thumb")),
    "wrist": ("ForeArm", "Hand", ("ForeArm", "Hand", "FingerBase", "HandFinger1", "Fingers",
                                  "Thumb")),
    "knee": ("UpLeg", "Leg", ("UpLeg", "Leg", "Foot", "ToeBase")),
    "ankle": ("Leg", "Foot", ("Leg", "Foot", "ToeBase")),
}

_LEAD_SIDE = re.compile(r"^(?:left|right|l|r)(?=.)")
_TRAIL_SIDE = re.compile(r"(?<=.)(?:left|right|l|r)$")
_SIDE = re.compile(f"{_LEAD_SIDE.pattern}|{_TRAIL_SIDE.pattern}")


def _normal(label: str) -> str:
    name = label.rsplit(":", 1)[-1].lower()
    return re.sub(r"[\s_\-.]+", "", name)


def marker_region(label: str) -> str | None:
    """The body region (a key of :data:`REGION_JOINTS`) a marker label names, or None.

    The subject prefix (``Daphnee:``) and case are dropped; a left or right side
    (``L``/``R``/``Left``/``Right`` before or after the name, ``_`` or a space between
    allowed) is stripped for the sided names.  Numbered cluster markers (``Head1``) keep
    their region.

    Examples: ``LASI``, ``L_IAS``, ``Daphnee:ASISr``, ``r asis`` -> pelvis; ``C7``,
    ``CV7``, ``T10``, ``STRN``, ``SXS``, ``CLAV_AC`` -> trunk; ``LFHD``, ``R_HDB``,
    ``Head2``, ``BodyL:TempleL`` -> head; ``LSHO``, ``AcromionR``, ``L_SAJ`` -> shoulder;
    ``RT1`` (a thigh cluster), ``LKNE``, ``ArmL1`` -> None.
    """
    name = _normal(label)
    for region, pattern in _UNSIDED.items():
        if re.fullmatch(pattern, name):
            return region
    bare = _SIDE.sub("", name, count=1)
    if bare and bare != name:
        for region, pattern in _SIDED.items():
            if re.fullmatch(rf"(?:{pattern})\d*", bare):
                return region
    return None


def joint_landmark(label: str) -> str | None:
    """The limb joint (``"elbow"``, ``"wrist"``, ``"knee"`` or ``"ankle"``) a marker label
    names, or None.

    Examples: ``LELB``, ``L_HLE``, ``Daphnee:EPICl``, ``LateralEpicondyleL`` -> elbow;
    ``LWRA``, ``R_RSP``, ``R_UHE``, ``Daphnee:STYLu``, ``RadialStyloidR`` -> wrist;
    ``LKNE``, ``L_FLE``, ``R_FME`` -> knee; ``RANK``, ``L_FAL``, ``R_TAM`` -> ankle;
    ``LTHI``, ``RSK2``, ``ArmL1`` -> None.  The label's side is not read (see
    :func:`~mocapflow.stages.skin.limb_pose.joint_targets`).
    """
    name = _normal(label)
    for bare in dict.fromkeys((name, _LEAD_SIDE.sub("", name), _TRAIL_SIDE.sub("", name))):
        for joint, pattern in _JOINT_LANDMARKS.items():
            if bare and re.fullmatch(pattern, bare):
                return joint
    return None


def label_side(label: str) -> str | None:
    """``"Left"`` or ``"Right"`` when a label's case marks its side, else None: a leading
    ``L``/``R`` before a capital, ``_`` or space (``LELB``, ``L_HLE``, ``R KNE``), a
    leading ``Left``/``Right`` word, or a trailing capital ``L``/``R`` after a small
    letter (``LateralEpicondyleL``).  Not pyomeca's ``EPICl`` (lateral) or ``STYLr``
    (radial), nor ``LateralEpicondyle``'s leading capital."""
    name = label.rsplit(":", 1)[-1].strip()
    m = re.match(r"(Left|Right|LEFT|RIGHT|left|right)(?=[A-Z_\s.\-]|$)|([LR])(?=[A-Z0-9_\s.\-])",
                 name)
    if m is None:
        m = re.search(r"(?<=[a-z])([LR])$|[_\s.\-](L|R|Left|Right|left|right)$", name)
    if m is None:
        return None
    word = next(g for g in m.groups() if g)
    return "Left" if word[0] in "Ll" else "Right"


def marker_face(label: str) -> str | None:
    """``"front"`` or ``"back"``: the face of the trunk or pelvis a marker named by
    :func:`marker_region` sits on (``LASI``, ``L_IAS``, ``STRN``, ``CLAV``, ``SXS`` in front;
    ``LPSI``, ``SACR``, ``C7``, ``T10``, ``RBAK``, ``R_SCAP`` behind), else None."""
    if marker_region(label) not in ("pelvis", "trunk", "upper_trunk"):
        return None
    name = _normal(label)
    for bare in (name, _SIDE.sub("", name, count=1)):
        for face, pattern in (("front", _FRONT), ("back", _BACK)):
            if bare and re.fullmatch(rf"(?:{pattern})\d*", bare):
                return face
    return None


def body_facing(labels: list[str], reference: np.ndarray, up: np.ndarray) -> np.ndarray | None:
    """``(3,)`` unit horizontal direction the body faces, from its named front and back
    markers (:func:`marker_face`): per region (pelvis, trunk) with both, the mean front
    marker less the mean back one, off ``up``; the regions' directions averaged.  None
    without such a pair or where they cancel out."""
    ref = np.asarray(reference, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    total = np.zeros(3)
    for region in ("pelvis", "trunk"):
        faces = [(i, marker_face(lb)) for i, lb in enumerate(labels)
                 if _trunk(marker_region(lb)) == region and np.isfinite(ref[i]).all()]
        front = [i for i, f in faces if f == "front"]
        back = [i for i, f in faces if f == "back"]
        if front and back:
            d = ref[front].mean(0) - ref[back].mean(0)
            d -= (d @ up) * up
            n = np.linalg.norm(d)
            if n > 1e-6:
                total += d / n
    n = np.linalg.norm(total)
    return total / n if n > 1e-6 else None


def _trunk(region: str | None) -> str | None:
    """The trunk's regions as one (the body's facing is read per pelvis and trunk)."""
    return "trunk" if region == "upper_trunk" else region


def region_vertices(joint_names: list[str], vertex_part: np.ndarray,
                    heights: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """``{region: (V,) bool}``: the template vertices of each region of
    :data:`REGION_JOINTS` (``vertex_part (V,)``: each vertex's dominant joint, an index
    into ``joint_names``); regions with no vertex are left out.  ``upper_trunk`` is the
    upper half of its joints' vertices by ``heights (V,)`` (along the template's up
    axis; without them it is left out): the clavicles, C7 and the jugular notch sit
    there, and matched to the whole chest they had pyomeca's seated trunk fitted into
    the standing template's belly."""
    part = np.asarray(vertex_part)
    out = {}
    for region, joints in REGION_JOINTS.items():
        ids = [joint_names.index(j) for j in joints if j in joint_names]
        mask = np.isin(part, ids)
        if region == "upper_trunk":
            if heights is None or not mask.any():
                continue
            h = np.asarray(heights)
            mask &= h >= np.median(h[mask])
        if mask.any():
            out[region] = mask
    return out
