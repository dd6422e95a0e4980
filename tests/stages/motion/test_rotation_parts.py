"""Quaternion products written out component by component, and forward kinematics on them.

Known answers from SciPy's ``Rotation`` (an independent implementation): products,
rotated vectors and a branching skeleton's world positions; the ``*_parts`` forms
must give the very same numbers as the array forms.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocapflow.stages.motion import kinematics as K
from mocapflow.stages.motion import rotations as Q
from mocapflow.stages.motion.datatypes import Skeleton


def _unit(rng, *shape):
    q = rng.standard_normal(shape + (4,))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _scipy(q):
    """SciPy rotations of ``(..., 4)`` ``(w, x, y, z)`` quaternions (flattened)."""
    return Rotation.from_quat(np.array(q).reshape(-1, 4)[:, [1, 2, 3, 0]])


@pytest.mark.parametrize("sa, sb", [((4,), (6, 4)), ((6, 4), (6, 4)), ((3, 1, 4), (1, 5, 4))])
def test_quat_multiply_matches_scipy_composition(sa, sb):
    rng = np.random.default_rng(1)
    a, b = _unit(rng, *sa[:-1]), _unit(rng, *sb[:-1])
    ab = Q.quat_multiply(a, b)
    shape = np.broadcast_shapes(sa, sb)
    assert ab.shape == shape
    A, B = (np.broadcast_to(x, shape) for x in (a, b))
    expect = (_scipy(A) * _scipy(B)).as_matrix()  # b first, then a
    np.testing.assert_allclose(Q.quat_to_matrix(ab).reshape(-1, 3, 3), expect, atol=1e-14)
    # the unit norm survives and the product of a quaternion with its conjugate is 1
    np.testing.assert_allclose(np.linalg.norm(ab, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(Q.quat_multiply(a, Q.quat_conjugate(a)),
                               np.broadcast_to([1.0, 0, 0, 0], a.shape), atol=1e-15)


@pytest.mark.parametrize("sq, sv", [((4,), (7, 3)), ((7, 4), (7, 3)), ((2, 1, 4), (1, 4, 3))])
def test_quat_rotate_matches_scipy_apply(sq, sv):
    rng = np.random.default_rng(2)
    q, v = _unit(rng, *sq[:-1]), rng.standard_normal(sv)
    out = Q.quat_rotate(q, v)
    lead = np.broadcast_shapes(sq[:-1], sv[:-1])
    assert out.shape == lead + (3,)
    qq = np.broadcast_to(q, lead + (4,))
    vv = np.broadcast_to(v, lead + (3,)).reshape(-1, 3).copy()
    np.testing.assert_allclose(out.reshape(-1, 3), _scipy(qq).apply(vv), atol=1e-14)
    # a quarter turn about z takes x to y (exact up to the rounding of cos/sin)
    qz = Q.quat_from_axis_angle(np.array([0, 0, 1.0]), np.pi / 2)
    np.testing.assert_allclose(Q.quat_rotate(qz, [1.0, 0, 0]), [0, 1, 0], atol=1e-15)


def test_parts_give_the_same_numbers_as_the_array_forms():
    rng = np.random.default_rng(3)
    a, b, v = _unit(rng, 50), _unit(rng, 50), rng.standard_normal((50, 3))
    ab = np.stack(Q.quat_multiply_parts(a.T, b.T), axis=-1)
    assert np.array_equal(ab, Q.quat_multiply(a, b))
    av = np.stack(Q.quat_rotate_parts(a.T, v.T), axis=-1)
    assert np.array_equal(av, Q.quat_rotate(a, v))


def test_products_of_mismatched_shapes_raise():
    with pytest.raises(ValueError):
        Q.quat_multiply(np.zeros((3, 4)), np.zeros((5, 4)))
    with pytest.raises(ValueError):
        Q.quat_rotate(np.zeros((3, 4)), np.zeros((5, 3)))


def _branching():
    """Root with three branches of different depths (several joints per depth)."""
    parents = np.array([-1, 0, 1, 0, 3, 2, 0, 4, 4])
    rng = np.random.default_rng(4)
    return Skeleton([f"j{k}" for k in range(9)], parents, rng.standard_normal((9, 3)),
                    [[] for _ in range(9)])


def _fk_scipy(sk, rot, root, translations=None):
    """World positions by composing SciPy rotations joint by joint (one pose)."""
    J = sk.n_joints
    world = [_scipy(rot[0])]
    pos = np.zeros((J, 3))
    pos[0] = root
    for j in range(1, J):
        p = sk.parents[j]
        off = sk.offsets[j]
        if translations is not None and np.isfinite(translations[j]).all():
            off = translations[j]
        pos[j] = pos[p] + world[p].apply(off)[0]
        world.append(world[p] * _scipy(rot[j]))
    return pos, np.array([w.as_matrix()[0] for w in world])


def test_forward_kinematics_on_a_branching_tree_matches_scipy():
    sk = _branching()
    rng = np.random.default_rng(5)
    rot = _unit(rng, 2, 3, sk.n_joints)  # two leading axes
    root = rng.standard_normal((2, 3, 3))
    tr = np.where(rng.random((2, 3, sk.n_joints, 1)) < 0.5,
                  rng.standard_normal((2, 3, sk.n_joints, 3)), np.nan)
    for translations in (None, tr):
        pos, grot = K.forward_kinematics(sk, rot, root, translations=translations)
        assert pos.shape == (2, 3, sk.n_joints, 3) and grot.shape == (2, 3, sk.n_joints, 4)
        assert pos.flags.c_contiguous and grot.flags.c_contiguous
        for i, k in np.ndindex(2, 3):
            t = None if translations is None else translations[i, k]
            ref_pos, ref_mat = _fk_scipy(sk, rot[i, k], root[i, k], t)
            np.testing.assert_allclose(pos[i, k], ref_pos, atol=1e-12)
            np.testing.assert_allclose(Q.quat_to_matrix(grot[i, k]), ref_mat, atol=1e-12)
    # one pose (no leading axis) is the same as a one-frame motion
    one, _ = K.forward_kinematics(sk, rot[0, 0], root[0, 0])
    np.testing.assert_array_equal(one, K.forward_kinematics(sk, rot[0, :1], root[0, :1])[0][0])
    with pytest.raises(ValueError, match="rotations must be"):
        K.forward_kinematics(sk, rot[..., :4, :], root)
