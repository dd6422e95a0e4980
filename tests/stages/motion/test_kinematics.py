"""Quaternions, Euler angles, forward kinematics, Horn's absolute orientation, resampling."""

import numpy as np
import pytest

from mocapflow.stages.motion import absolute_orientation as AO
from mocapflow.stages.motion import kinematics as K
from mocapflow.stages.motion import rotations as Q
from mocapflow.stages.motion.datatypes import Motion, Skeleton


def _rq(rng, *shape):
    return Q.quat_normalize(rng.standard_normal(shape + (4,)))


def _elem(angle, axis):
    """Elementary rotation matrix, written out independently of the module."""
    c, s = np.cos(angle), np.sin(angle)
    if axis == "X":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "Y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _same_rotation(a, b, atol=1e-12):
    return np.all(np.abs(np.abs(np.sum(a * b, axis=-1)) - 1) < atol)


# --------------------------------------------------------------------------- Euler


@pytest.mark.parametrize("order", Q.EULER_ORDERS)
def test_euler_matches_matrix_product_and_round_trips(order):
    rng = np.random.default_rng(Q.EULER_ORDERS.index(order))
    ang = rng.uniform(-np.pi, np.pi, (200, 3))
    if order[0] == order[2]:  # proper Euler: middle angle in (0, pi)
        ang[:, 1] = rng.uniform(0.05, np.pi - 0.05, 200)
    else:  # Tait-Bryan: middle angle in (-pi/2, pi/2)
        ang[:, 1] = rng.uniform(-np.pi / 2 + 0.05, np.pi / 2 - 0.05, 200)
    q = Q.euler_to_quat(ang, order)
    R = Q.quat_to_matrix(q)
    for k in (0, 57, 199):
        a, b, c = (_elem(ang[k, i], order[i]) for i in range(3))
        expect = a @ b @ c
        np.testing.assert_allclose(R[k], expect, atol=1e-14)
    back = Q.quat_to_euler(q, order)
    np.testing.assert_allclose(back, ang, atol=1e-10)
    deg = Q.quat_to_euler(q, order, degrees=True)
    np.testing.assert_allclose(Q.euler_to_quat(deg, order, degrees=True), q, atol=1e-14)


def test_euler_gimbal_lock_still_gives_the_rotation():
    ang = np.array([[0.3, np.pi / 2, -0.4], [0.2, -np.pi / 2, 0.9]])
    q = Q.euler_to_quat(ang, "ZXY")
    assert _same_rotation(Q.euler_to_quat(Q.quat_to_euler(q, "ZXY"), "ZXY"), q, 1e-12)


def test_euler_unknown_order_and_bad_shape_raise():
    with pytest.raises(ValueError, match="unknown rotation order 'XXY'"):
        Q.euler_to_quat(np.zeros(3), "XXY")
    with pytest.raises(ValueError, match="unknown rotation order"):
        Q.quat_to_euler(np.array([1.0, 0, 0, 0]), "XY")
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        Q.euler_to_quat(np.zeros(2), "XYZ")


# --------------------------------------------------------------------------- algebra


def test_product_rotate_matrix_agree():
    rng = np.random.default_rng(1)
    a, b = _rq(rng, 50), _rq(rng, 50)
    v = rng.standard_normal((50, 3))
    Ra, Rb = Q.quat_to_matrix(a), Q.quat_to_matrix(b)
    np.testing.assert_allclose(Q.quat_to_matrix(Q.quat_multiply(a, b)), Ra @ Rb, atol=1e-14)
    np.testing.assert_allclose(Q.quat_rotate(a, v), np.einsum("nij,nj->ni", Ra, v), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(Ra), 1.0, atol=1e-13)
    ident = Q.quat_multiply(a, Q.quat_inverse(a))
    np.testing.assert_allclose(ident, Q.quat_identity((50,)), atol=1e-15)
    # inverse of a non-unit quaternion
    q = 3.0 * a
    np.testing.assert_allclose(Q.quat_multiply(q, Q.quat_inverse(q)), ident, atol=1e-14)


def test_matrix_round_trip_including_half_turns():
    rng = np.random.default_rng(2)
    q = _rq(rng, 100)
    # rotations by ~pi about each axis exercise every Shepperd branch
    q[:3] = Q.quat_from_axis_angle(np.eye(3), np.full(3, np.pi - 1e-9))
    back = Q.quat_from_matrix(Q.quat_to_matrix(q))
    assert np.all(back[:, 0] >= 0)
    assert _same_rotation(back, q, 1e-12)


def test_log_exp_rotvec_angle():
    rng = np.random.default_rng(3)
    q = _rq(rng, 100)
    np.testing.assert_allclose(Q.quat_exp(Q.quat_log(q)), q, atol=1e-14)
    r = Q.quat_to_rotvec(q)
    theta = np.linalg.norm(r, axis=-1)
    assert np.all(theta <= np.pi + 1e-12)
    assert _same_rotation(Q.quat_from_rotvec(r), q)
    np.testing.assert_allclose(theta, Q.quat_angle(Q.quat_identity((100,)), q), atol=1e-12)
    # known case: 90 deg about z
    qz = Q.quat_from_axis_angle(np.array([0, 0, 1.0]), np.pi / 2)
    np.testing.assert_allclose(Q.quat_to_rotvec(qz), [0, 0, np.pi / 2], atol=1e-15)
    np.testing.assert_allclose(Q.quat_log(qz), [0, 0, np.pi / 4], atol=1e-15)
    # tiny angles stay accurate
    small = Q.quat_from_rotvec(np.array([1e-10, 0, 0]))
    np.testing.assert_allclose(Q.quat_to_rotvec(small), [1e-10, 0, 0], rtol=1e-9)
    # sign-insensitive geodesic angle
    a, b = _rq(rng, 20), _rq(rng, 20)
    np.testing.assert_allclose(Q.quat_angle(a, b), Q.quat_angle(a, -b), atol=1e-12)


def test_slerp_constant_speed_and_shortest_arc():
    axis = np.array([0.3, -0.5, 0.8])
    a = Q.quat_from_axis_angle(axis, 0.2)
    b = Q.quat_from_axis_angle(axis, 1.4)
    t = np.linspace(0, 1, 7)
    s = Q.quat_slerp(a, -b, t)  # -b: same rotation, the long way round in 4-D
    expect = Q.quat_from_axis_angle(axis, 0.2 + 1.2 * t)
    assert _same_rotation(s, expect)
    np.testing.assert_allclose(Q.quat_slerp(a, a, 0.5), a, atol=1e-15)  # degenerate arc


def test_continuity_removes_sign_flips():
    rng = np.random.default_rng(4)
    axis = np.array([0.0, 1.0, 0.0])
    q = Q.quat_from_axis_angle(axis, np.linspace(0, 6 * np.pi, 300))[:, None].repeat(3, axis=1)
    flipped = q * rng.choice([-1.0, 1.0], (300, 3, 1))
    c = Q.quat_continuity(flipped, axis=0)
    assert np.all(np.sum(c[1:] * c[:-1], axis=-1) > 0)
    assert _same_rotation(c, q)
    with pytest.raises(ValueError):
        Q.quat_continuity(q, axis=-1)


def test_markley_average():
    rng = np.random.default_rng(5)
    q0 = _rq(rng)
    # symmetric perturbations average back to q0 exactly
    d = rng.standard_normal((10, 3)) * 0.1
    pert = np.concatenate([Q.quat_from_rotvec(d), Q.quat_from_rotvec(-d)])
    qs = Q.quat_multiply(q0, pert)
    qs[::2] *= -1  # signs must not matter
    avg = Q.quat_average(qs)
    assert Q.quat_angle(avg, q0) < 1e-3
    # weights: one dominant quaternion
    w = np.zeros(20)
    w[3] = 1.0
    assert Q.quat_angle(Q.quat_average(qs, w), qs[3]) < 1e-7
    # NaN rows ignored; batch axis
    qs2 = np.concatenate([qs, np.full((1, 4), np.nan)])
    assert Q.quat_angle(Q.quat_average(qs2), avg) < 1e-12
    batch = np.stack([qs, qs], axis=1)  # (20, 2, 4)
    np.testing.assert_allclose(Q.quat_average(batch, axis=0), [avg, avg], atol=1e-12)


def test_six_d():
    rng = np.random.default_rng(6)
    q = _rq(rng, 30)
    d6 = Q.quat_to_6d(q)
    R = Q.quat_to_matrix(q)
    np.testing.assert_allclose(d6, np.concatenate([R[:, :, 0], R[:, :, 1]], -1), atol=1e-15)
    assert _same_rotation(Q.quat_from_6d(d6 + 0.0), q)


# --------------------------------------------------------------------------- FK


def _random_skeleton(rng, J=12):
    parents = [-1] + [int(rng.integers(0, j)) for j in range(1, J)]
    channels = [["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"]]
    channels += [["Zrotation", "Xrotation", "Yrotation"]] * (J - 1)
    return Skeleton(
        names=[f"j{j}" for j in range(J)],
        parents=np.array(parents),
        offsets=rng.standard_normal((J, 3)),
        channels=channels,
        end_parents=np.array([J - 1, 2]),
        end_offsets=rng.standard_normal((2, 3)),
    )


def _fk_matrices(sk, rotations, root, translations=None):
    """Independent FK with 4x4 homogeneous transforms, one frame at a time."""
    F, J = rotations.shape[:2]
    out = np.zeros((F, J, 3))
    ends = np.zeros((F, len(sk.end_parents), 3))
    for f in range(F):
        world = []
        for j in range(J):
            T = np.eye(4)
            T[:3, :3] = Q.quat_to_matrix(rotations[f, j])
            if j == 0:
                T[:3, 3] = root[f]
                world.append(T)
            else:
                T[:3, 3] = sk.offsets[j] if translations is None else translations[f, j]
                world.append(world[sk.parents[j]] @ T)
            out[f, j] = world[j][:3, 3]
        for e, p in enumerate(sk.end_parents):
            ends[f, e] = (world[p] @ np.append(sk.end_offsets[e], 1.0))[:3]
    return out, ends


def test_forward_kinematics_against_matrix_chain():
    rng = np.random.default_rng(7)
    sk = _random_skeleton(rng)
    rot = _rq(rng, 5, sk.n_joints)
    root = rng.standard_normal((5, 3))
    pos, grot = K.forward_kinematics(sk, rot, root)
    ref, ref_ends = _fk_matrices(sk, rot, root)
    np.testing.assert_allclose(pos, ref, atol=1e-12)
    np.testing.assert_allclose(K.end_site_positions(sk, pos, grot), ref_ends, atol=1e-12)
    # per-frame translations replace offsets
    tr = rng.standard_normal((5, sk.n_joints, 3))
    pos_t, _ = K.forward_kinematics(sk, rot, root, translations=tr)
    np.testing.assert_allclose(pos_t, _fk_matrices(sk, rot, root, tr)[0], atol=1e-12)
    with pytest.raises(ValueError, match="rotations must be"):
        K.forward_kinematics(sk, rot[:, :3], root)


def test_forward_kinematics_known_chain():
    sk = Skeleton(
        ["a", "b", "c"],
        np.array([-1, 0, 1]),
        np.array([[0, 0, 0], [1.0, 0, 0], [1.0, 0, 0]]),
        [[], [], []],
    )
    rot = Q.quat_identity((1, 3))
    rot[0, 1] = Q.quat_from_axis_angle(np.array([0, 0, 1.0]), np.pi / 2)
    pos, _ = K.forward_kinematics(sk, rot, np.array([[0.0, 0.0, 5.0]]))
    np.testing.assert_allclose(pos[0], [[0, 0, 5], [1, 0, 5], [1, 1, 5]], atol=1e-15)


# --------------------------------------------------------------------------- Horn


def _random_rt(rng):
    return Q.quat_to_matrix(_rq(rng)), rng.standard_normal(3) * 5


def test_horn_noiseless_recovers_exactly():
    rng = np.random.default_rng(8)
    for n in (3, 4, 50):
        R, t = _random_rt(rng)
        src = rng.standard_normal((n, 3))
        R_hat, t_hat = AO.absolute_orientation(src, src @ R.T + t)
        np.testing.assert_allclose(R_hat, R, atol=1e-9)
        np.testing.assert_allclose(t_hat, t, atol=1e-9)
    # weighted, with outliers down-weighted to zero and NaN rows
    src = rng.standard_normal((30, 3))
    tgt = src @ R.T + t
    tgt[:5] += 10.0
    tgt[5] = np.nan
    w = np.ones(30)
    w[:5] = 0.0
    R_hat, t_hat = AO.absolute_orientation(src, tgt, weights=w)
    np.testing.assert_allclose(R_hat, R, atol=1e-9)
    np.testing.assert_allclose(t_hat, t, atol=1e-9)


def test_horn_noisy_residual_matches_noise():
    rng = np.random.default_rng(9)
    R, t = _random_rt(rng)
    n, sigma = 4000, 0.01
    src = rng.uniform(-1, 1, (n, 3))
    tgt = src @ R.T + t + rng.normal(0, sigma, (n, 3))
    R_hat, t_hat = AO.absolute_orientation(src, tgt)
    resid = tgt - (src @ R_hat.T + t_hat)
    rms = np.sqrt(np.mean(np.sum(resid**2, axis=1)))
    expect = sigma * np.sqrt(3 - 6 / n)  # E[SSR] = sigma^2 (3N - 6)
    assert abs(rms / expect - 1) < 0.05
    # and the fit is no worse than the true transform
    true_rms = np.sqrt(np.mean(np.sum((tgt - (src @ R.T + t)) ** 2, axis=1)))
    assert rms <= true_rms
    assert np.degrees(np.arccos((np.trace(R_hat.T @ R) - 1) / 2)) < 0.05


def test_horn_never_reflects():
    rng = np.random.default_rng(10)
    src = rng.standard_normal((20, 3))
    tgt = src * np.array([-1.0, 1.0, 1.0])  # a mirror image
    R_hat, _ = AO.absolute_orientation(src, tgt)
    np.testing.assert_allclose(np.linalg.det(R_hat), 1.0, atol=1e-12)
    np.testing.assert_allclose(R_hat @ R_hat.T, np.eye(3), atol=1e-12)


def test_horn_degenerate_inputs_raise():
    rng = np.random.default_rng(11)
    two = rng.standard_normal((2, 3))
    with pytest.raises(AO.DegenerateFitError, match="at least 3 non-collinear.*got 2 usable"):
        AO.absolute_orientation(two, two)
    line = np.linspace(0, 1, 6)[:, None] * np.array([1.0, 2.0, 3.0]) + 0.5
    with pytest.raises(AO.DegenerateFitError, match="collinear"):
        AO.absolute_orientation(line, line + 1)
    pts = rng.standard_normal((5, 3))
    with pytest.raises(AO.DegenerateFitError):
        AO.absolute_orientation(pts, pts, weights=np.array([1.0, 1.0, 0, 0, 0]))
    nan = pts.copy()
    nan[2:] = np.nan
    with pytest.raises(AO.DegenerateFitError, match="got 2 usable of 5"):
        AO.absolute_orientation(nan, pts)
    with pytest.raises(AO.DegenerateFitError):  # coincident points
        AO.absolute_orientation(np.ones((4, 3)), pts[:4])
    assert issubclass(AO.DegenerateFitError, ValueError)
    with pytest.raises(ValueError, match="both be"):
        AO.absolute_orientation(pts, pts[:4])


def test_horn_batch_matches_single_and_handles_nan():
    rng = np.random.default_rng(12)
    B, N = 40, 12
    Rs = Q.quat_to_matrix(_rq(rng, B))
    ts = rng.standard_normal((B, 3))
    src = rng.standard_normal((B, N, 3))
    tgt = np.einsum("bij,bnj->bni", Rs, src) + ts[:, None] + rng.normal(0, 0.01, (B, N, 3))
    w = rng.uniform(0.5, 2.0, (B, N))
    src[1, :4] = np.nan  # ignored rows
    w[2, 0] = np.nan
    src[3, 2:] = np.nan  # only 2 usable points: degenerate -> NaN
    R_b, t_b = AO.absolute_orientation_batch(src, tgt, weights=w)
    assert np.isnan(R_b[3]).all() and np.isnan(t_b[3]).all()
    for b in (0, 1, 2, 17, 39):
        R1, t1 = AO.absolute_orientation(src[b], tgt[b], weights=w[b])
        np.testing.assert_allclose(R_b[b], R1, atol=1e-12)
        np.testing.assert_allclose(t_b[b], t1, atol=1e-12)
    ok = np.arange(B) != 3
    np.testing.assert_allclose(R_b[ok], Rs[ok], atol=0.05)



def test_horn_batch_same_bits_with_or_without_unusable_sets():
    """A batch whose sets are all usable (the common case in clean) is solved without the
    masks and copies of the general path; every set's R and t must be the same bits as
    when the batch also holds an unusable set (NaN rows, too few points, collinear)."""
    rng = np.random.default_rng(3)
    B, N = 64, 9
    Rs = Q.quat_to_matrix(_rq(rng, B))
    src = rng.standard_normal((B, N, 3)) * 0.1
    tgt = np.einsum("bij,bnj->bni", Rs, src) + rng.standard_normal((B, 1, 3))
    tgt += rng.normal(0, 1e-3, (B, N, 3))
    w = rng.uniform(0.5, 2.0, (B, N))
    R_fast, t_fast = AO.absolute_orientation_batch(src, tgt, weights=w)
    bad_src = np.stack([src[0], np.outer(np.arange(N), [1.0, 2.0, 3.0]), src[1]])
    bad_src[0, 2:] = np.nan  # too few points (2)
    bad_src[2, 0] = np.nan  # one ignored row: usable, but the batch takes the masks
    bad_tgt = np.stack([tgt[0], np.outer(np.arange(N), [1.0, 2.0, 3.0]) + 1.0, tgt[1]])
    R_mix, t_mix = AO.absolute_orientation_batch(
        np.concatenate([src, bad_src]), np.concatenate([tgt, bad_tgt]),
        weights=np.concatenate([w, w[:3]]))
    np.testing.assert_array_equal(R_mix[:B], R_fast)
    np.testing.assert_array_equal(t_mix[:B], t_fast)
    assert np.isnan(R_mix[B : B + 2]).all() and np.isfinite(R_mix[B + 2]).all()


def test_horn_batch_each_set_the_same_bits_wherever_it_lies():
    """Every set's R and t are the same bits alone, in a batch, or in the batch shifted by
    1-5 sets (another place in memory), for 3-32 points, weighted or not, nearly planar
    or not.  np.einsum summed the quartic's c0 with SIMD accumulators split by where the
    row lay: on these sets 30 of 7,803 fits differed in their last bits (up to 1.6e-14
    in R on a real basket_sprint gap), so clean's fits shared between gaps (regress's
    _RigidFits) would have depended on which gaps came together."""
    rng = np.random.default_rng(0)
    for k in (3, 4, 5, 8, 9, 10, 16, 17, 32):
        B = 200
        src = rng.normal(size=(B, k, 3)) * 0.1
        src[::7, :, 2] *= 1e-4  # nearly planar
        Rs = Q.quat_to_matrix(_rq(rng, B))
        tgt = np.einsum("bij,bnj->bni", Rs, src) + rng.normal(size=(B, 1, 3))
        tgt += rng.normal(size=(B, k, 3)) * 1e-3
        w = rng.uniform(0.1, 1, size=(B, k)) if k % 2 else np.ones((B, k))
        R, t = AO.absolute_orientation_batch(src, tgt, weights=w)
        assert np.isfinite(R).all()
        for shift in (1, 2, 3, 5):
            Rs_, ts_ = AO.absolute_orientation_batch(
                np.concatenate([src[:shift], src]), np.concatenate([tgt[:shift], tgt]),
                weights=np.concatenate([w[:shift], w]))
            np.testing.assert_array_equal(Rs_[shift:], R)
            np.testing.assert_array_equal(ts_[shift:], t)
        for i in range(0, B, 3):
            R1, t1 = AO.absolute_orientation_batch(src[i:i + 1], tgt[i:i + 1],
                                                   weights=w[i:i + 1])
            np.testing.assert_array_equal(R1[0], R[i])
            np.testing.assert_array_equal(t1[0], t[i])


def test_adjugate_column_is_a_column_of_the_adjugate():
    """:func:`_adjugate_column` reads one column of adj(N - λI) out of the ten cofactors of
    the symmetric matrix: the column of the largest diagonal entry, as det · inverse."""
    rng = np.random.default_rng(4)
    M = rng.standard_normal((50, 3, 3))
    N = AO._horn_matrix(M)
    lam = rng.uniform(-1, 1, 50)
    q, d = AO._adjugate_column(N, lam)
    A = N - lam[:, None, None] * np.eye(4)
    adj = np.linalg.inv(A) * np.linalg.det(A)[:, None, None]
    col = np.argmax(np.abs(np.diagonal(adj, axis1=1, axis2=2)), axis=1)
    np.testing.assert_allclose(q, adj[np.arange(50), :, col], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(d, np.abs(adj[np.arange(50), col, col]), rtol=1e-9)


# --------------------------------------------------------------------------- resampling


def _constant_spin_motion(F=121, rate=120.0):
    sk = Skeleton(
        ["r", "c"],
        np.array([-1, 0]),
        np.array([[0, 0, 0], [0, 1.0, 0]]),
        [
            ["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"],
            ["Zrotation", "Xrotation", "Yrotation"],
        ],
    )
    t = np.arange(F) / rate
    rot = np.zeros((F, 2, 4))
    rot[:, 0] = Q.quat_from_axis_angle(np.array([0, 1.0, 0]), 2.0 * t)  # 2 rad/s
    rot[:, 1] = Q.quat_from_axis_angle(np.array([1.0, 0, 0]), -1.0 * t)
    rot[::3] *= -1  # sign flips must not matter
    root = np.stack([0.5 * t, np.ones(F), np.zeros(F)], 1)
    return Motion(sk, root, rot, rate, attrs={"source_unit": "m"})


def test_resample_motion_down_and_up():
    m = _constant_spin_motion()
    down = K.resample_motion(m, 30.0)
    assert down.n_frames == 31 and down.rate == 30.0 and down.skeleton is m.skeleton
    assert _same_rotation(down.rotations, m.rotations[::4])
    np.testing.assert_allclose(down.root_position, m.root_position[::4], atol=1e-14)
    up = K.resample_motion(down, 120.0)
    assert up.n_frames == 121
    # slerp at constant angular velocity reproduces the in-between frames exactly
    assert _same_rotation(up.rotations, m.rotations, 1e-12)
    np.testing.assert_allclose(up.root_position, m.root_position, atol=1e-14)
    odd = K.resample_motion(m, 50.0)  # duration 1 s -> 51 frames
    assert odd.n_frames == 51
    assert odd.attrs["resampled_from_rate"] == 120.0
    with pytest.raises(ValueError, match="rate must be > 0"):
        K.resample_motion(m, 0)



def _circle_walk(t: np.ndarray) -> np.ndarray:
    """Root of a walk at 0.5 m/s along its heading 2t (yaw about y, facing +z at 0)."""
    return np.stack([0.25 * (1 - np.cos(2 * t)), np.ones_like(t), 0.25 * np.sin(2 * t)], 1)


def test_loop_resampled_as_one_goes_on_at_its_wrap():
    """A loop of 0.5 s of a walk on a circle does not close in space: it goes on one step
    after its last frame, and resampled cyclically its last -> first step is one ordinary
    step, as many frames as the loop's duration holds."""
    m = _constant_spin_motion()  # 121 frames at 120 Hz, heading 2 rad/s
    t = np.arange(70) / 120
    loop = m.replace(root_position=_circle_walk(t[:60]), rotations=m.rotations[:60])
    padded = K.loop_continuation(loop, 3)
    assert padded.n_frames == 66
    # the continued frames are the next frames of the same walk
    np.testing.assert_allclose(padded.root_position[63:], _circle_walk(t[60:63]), atol=1e-4)
    h, _ = Q.heading_split(padded.rotations[:, 0])
    np.testing.assert_allclose(np.diff(h), 2.0 / 120, atol=1e-9)
    before = _circle_walk(-np.arange(3, 0, -1) / 120)
    np.testing.assert_allclose(padded.root_position[:3], before, atol=1e-4)
    down = K.resample_motion(loop, 30.0, method="spline", cyclic=True)
    assert down.n_frames == 15  # 60 frames at 120 Hz = 0.5 s = 15 frames at 30 Hz
    np.testing.assert_allclose(down.root_position, _circle_walk(np.arange(15) / 30), atol=1e-4)
    # a loop that closes in space (a lap of a ring, the heading one whole turn) goes on in place
    u = np.arange(120) / 120 * 2 * np.pi
    lap = Motion(m.skeleton, _circle_walk(u / 2),
                 np.stack([Q.yaw_quaternion(u), Q.quat_identity((120,))], 1), 120.0)
    cont = K.loop_continuation(lap, 2)
    np.testing.assert_allclose(cont.root_position[-2:], lap.root_position[:2], atol=1e-12)
    np.testing.assert_allclose(cont.root_position[:2], lap.root_position[-2:], atol=1e-12)
