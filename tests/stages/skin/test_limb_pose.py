"""The template's limbs turned to named joint markers (sparse captures' upright fit)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocapflow.pipeline import Context
from mocapflow.stages.metrics.mesh import stretched_triangles
from mocapflow.stages.skin.limb_pose import (
    joint_regions,
    joint_targets,
    limb_binding,
    pose_limbs,
)
from mocapflow.stages.skin.mesh_fit import template_mesh


@pytest.fixture(scope="module")
def template():
    """The procedural template (T-pose, y up, its left at +x) with its rig."""
    mesh = template_mesh(n_vertices=2000, ctx=Context())["mesh"]
    names = mesh.attrs["joint_names"]
    bones = {k: np.asarray(mesh.attrs["bones"].get(k, np.zeros((2, 3))), dtype=float)
             for k in names}  # fmt: skip
    return mesh, bones, np.asarray(mesh.attrs["vertex_part"])


def _arm_down_targets(bones):
    """The left arm turned 80 degrees down about the body's front axis and the elbow bent
    90 degrees forward: where its elbow and wrist go."""
    shoulder, elbow = bones["LeftArm"]
    down = Rotation.from_rotvec([0.0, 0.0, -np.radians(80.0)])
    new_elbow = shoulder + down.apply(elbow - shoulder)
    forearm = down.apply(bones["LeftForeArm"][1] - bones["LeftForeArm"][0])
    bent = Rotation.from_rotvec(np.radians(90.0) * np.cross(forearm, [0.0, 0.0, 1.0])
                                / np.linalg.norm(np.cross(forearm, [0.0, 0.0, 1.0])))
    new_wrist = new_elbow + bent.apply(forearm)
    return new_elbow, new_wrist


def test_each_bone_points_at_its_joint_marker(template):
    """The upper arm ends on the line to the elbow target, the forearm on the line to the
    wrist target (both reached exactly: the targets keep the bones' lengths); the other
    side, the legs and the head do not move; the skin bends at the joints without a
    triangle stretched beyond 3x."""
    mesh, bones, part = template
    elbow, wrist = _arm_down_targets(bones)
    targets = {("Left", "elbow"): (elbow, np.array([0])), ("Left", "wrist"): (wrist, np.array([1]))}
    V, posed, rep = pose_limbs(mesh.vertices, mesh.faces, bones, part, targets)
    np.testing.assert_allclose(posed["LeftArm"][1], elbow, atol=1e-9)
    np.testing.assert_allclose(posed["LeftForeArm"][1], wrist, atol=1e-9)
    assert rep["turned_deg"] == pytest.approx({"LeftArm": 80.0, "LeftForeArm": 90.0}, abs=1e-6)
    names = list(bones)
    still = np.isin(part, [names.index(j) for j in ("Head", "RightArm", "RightForeArm",
                                                     "LeftUpLeg", "LeftLeg")])
    assert np.abs(V[still] - mesh.vertices[still]).max() == 0.0
    hand = part == names.index("LeftHand")
    assert np.linalg.norm(V[hand] - wrist, axis=1).max() < 0.25  # the hand went with it
    assert not stretched_triangles(V[None], mesh.vertices, mesh.faces).any()


def test_a_rigid_turn_tears_the_skin_that_the_blend_keeps(template):
    """Without the weights' smoothing (``blend=0``) the turned arm tears from the
    shoulder: the blend over the rings is what keeps the skin whole."""
    mesh, bones, part = template
    elbow, wrist = _arm_down_targets(bones)
    targets = {("Left", "elbow"): (elbow, np.array([0])), ("Left", "wrist"): (wrist, np.array([1]))}
    V, _, _ = pose_limbs(mesh.vertices, mesh.faces, bones, part, targets, blend=0.0)
    assert stretched_triangles(V[None], mesh.vertices, mesh.faces).any()


def test_a_target_beyond_reach_leaves_the_bone(template):
    """An elbow marker three upper-arm lengths from the shoulder (a marker named like a
    joint but elsewhere) turns nothing and is reported; a wrist alone turns the straight
    arm to it."""
    mesh, bones, part = template
    shoulder, elbow = bones["LeftArm"]
    far = shoulder + 3.0 * np.linalg.norm(elbow - shoulder) * np.array([0.0, -1.0, 0.0])
    V, _, rep = pose_limbs(mesh.vertices, mesh.faces, bones, part,
                           {("Left", "elbow"): (far, np.array([0]))})  # fmt: skip
    assert rep["turned_deg"] == {} and rep["beyond_reach"]["LeftArm"] == pytest.approx(3.0)
    assert np.array_equal(V, mesh.vertices)
    _, wrist = _arm_down_targets(bones)
    _, posed, rep = pose_limbs(mesh.vertices, mesh.faces, bones, part,
                               {("Left", "wrist"): (wrist, np.array([0]))})  # fmt: skip
    end = posed["LeftForeArm"][1] - shoulder
    assert set(rep["turned_deg"]) == {"LeftArm"}
    np.testing.assert_allclose(end / np.linalg.norm(end),
                               (wrist - shoulder) / np.linalg.norm(wrist - shoulder), atol=1e-9)


def test_joint_targets_read_sides_from_labels_else_from_the_body(template):
    """``LELB`` is the left elbow wherever it is; pyomeca's ``EPICl``/``EPICm`` (lateral and
    medial epicondyles, no side) count for the side they lie on, their mean the joint."""
    mesh, bones, _ = template
    right_elbow = bones["RightArm"][1]
    labels = ["LELB", "Daphnee:EPICl", "Daphnee:EPICm", "LASI", "RWRA"]
    ref = np.array([right_elbow + [0.0, 0.0, 0.03],  # named left, lying right
                    right_elbow + [0.0, 0.03, 0.0], right_elbow - [0.0, 0.03, 0.0],
                    [0.1, 0.0, 0.1], [np.nan] * 3])  # fmt: skip
    t = joint_targets(labels, ref, bones)
    assert set(t) == {("Left", "elbow"), ("Right", "elbow")}
    np.testing.assert_allclose(t[("Right", "elbow")][0], right_elbow, atol=1e-12)
    assert t[("Right", "elbow")][1].tolist() == [1, 2]
    assert t[("Left", "elbow")][1].tolist() == [0]
    regions, masks = joint_regions(mesh.vertices, bones, t, len(labels))
    assert regions == ["Left elbow", "Right elbow", "Right elbow", None, None]
    d = np.linalg.norm(mesh.vertices[masks["Right elbow"]] - right_elbow, axis=1)
    assert len(d) > 5 and d.max() <= 0.08


def test_a_joint_marked_on_one_side_is_centred_inside_the_limb(template):
    """A lone lateral knee marker (Plug-in Gait's ``LKNE``) on the skin beside the
    template's knee: the target is the knee inside, not the marker; a lateral and medial
    pair (``L_FLE``, ``L_FME``) is centred by its mean alone."""
    mesh, bones, _ = template
    hip, knee = bones["LeftUpLeg"]
    axis = (knee - hip) / np.linalg.norm(knee - hip)
    outward = np.array([1.0, 0.0, 0.0])  # the template's left is +x; across the thigh:
    outward -= (outward @ axis) * axis
    rel = mesh.vertices - knee
    level = np.abs(rel @ axis) < 0.02  # the skin around the knee, across the bone
    lateral = mesh.vertices[level][np.argmax(rel[level] @ outward)]
    one = joint_targets(["LKNE"], lateral[None], bones, mesh.vertices)[("Left", "knee")][0]
    # moved in across the thigh by its thickness: on the knee's axis within 1.5 cm (the
    # marker was 5 cm off it)
    assert abs((one - knee) @ outward) < 0.015 < 0.04 < (lateral - knee) @ outward
    assert np.linalg.norm(joint_targets(["LKNE"], lateral[None], bones)[("Left", "knee")][0]
                          - lateral) == 0.0  # without the template's skin: the marker
    medial = 2 * knee - lateral
    pair = joint_targets(["L_FLE", "L_FME"], np.stack([lateral, medial]), bones, mesh.vertices)
    np.testing.assert_allclose(pair[("Left", "knee")][0], knee, atol=1e-12)


def test_limb_binding_holds_a_limb_to_its_own_and_the_body_parts(template):
    """Parts: 0 the pelvis and trunk (``LASI``, ``C7``), 1 the left arm (``LELB``,
    ``LWRA``), 2 unnamed markers.  A leg may follow 0 and 2, not the arm's part; the left
    arm all three; the trunk 0 and 2.  No named marker: nothing to hold."""
    mesh, bones, part = template
    labels = ["LASI", "C7", "LELB", "LWRA", "M1", "M2"]
    ref = np.array([bones["LeftUpLeg"][0], bones["Spine1"][1], bones["LeftArm"][1],
                    bones["LeftForeArm"][1], [0.0, 0.0, 0.3], [0.0, -0.5, 0.3]])  # fmt: skip
    alpha = np.zeros((6, 3))
    alpha[[0, 1], 0] = alpha[[2, 3], 1] = alpha[[4, 5], 2] = 1.0
    allowed = limb_binding(labels, ref, alpha, mesh.vertices, list(bones), part)
    names = list(bones)

    def rows(*joints):
        return allowed[np.isin(part, [names.index(j) for j in joints])]

    assert rows("LeftUpLeg", "RightLeg").tolist() == [[True, False, True]] * len(
        rows("LeftUpLeg", "RightLeg"))
    assert rows("LeftArm", "LeftHand").all()
    assert (rows("Spine", "Head") == [True, False, True]).all()
    assert (rows("RightArm") == [True, False, True]).all()  # the other arm's part: not it
    assert limb_binding(["M1", "M2"], ref[4:], alpha[4:], mesh.vertices, names, part) is None


def test_bind_mesh_holds_vertices_to_their_allowed_parts():
    """Two parts side by side: a vertex over part 1 but allowed part 0 only takes the
    nearest part-0 marker's weights; a vertex allowed nothing with a marker stays bound as
    it was; every row sums to 1."""
    from mocapflow.stages.skin.binding import bind_mesh  # noqa: PLC0415
    from mocapflow.stages.skin.segmentation import Segmentation  # noqa: PLC0415

    ref = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.0, 0.1, 0], [0.3, 0, 0], [0.4, 0, 0],
                    [0.3, 0.1, 0]])  # fmt: skip
    alpha = np.zeros((6, 2))
    alpha[:3, 0] = alpha[3:, 1] = 1.0
    seg = Segmentation([f"M{i}" for i in range(6)], ["a", "b"], alpha, ref,
                       [[0, 1, 2], [3, 4, 5]], ref[[0, 3]], np.stack([np.eye(3)] * 2),
                       np.array([0, 1]))  # fmt: skip
    verts = np.array([[0.05, 0.03, 0.01], [0.35, 0.03, 0.01], [0.36, 0.03, 0.01]])
    free = bind_mesh(verts, seg, min_overlap=0.0)
    np.testing.assert_allclose(free.beta, [[1, 0], [0, 1], [0, 1]])
    allowed = np.array([[True, True], [True, False], [False, False]])
    held = bind_mesh(verts, seg, min_overlap=0.0, allowed=allowed)
    np.testing.assert_allclose(held.beta, [[1, 0], [1, 0], [0, 1]])
