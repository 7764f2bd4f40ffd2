import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from umi_aug.geometry import (
    make_pose,
    matrix_to_quat_wxyz,
    matrix_to_quat_xyzw,
    pos_quat_wxyz_to_pose,
    pos_quat_xyzw_to_pose,
    pos_rotvec_to_pose,
    pose_inverse,
    pose_to_pos_quat_wxyz,
    pose_to_pos_quat_xyzw,
    pose_to_pos_rotvec,
    quat_wxyz_to_matrix,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_matrix,
    quat_xyzw_to_wxyz,
    se3_exp,
    se3_log,
    so3_exp,
    transform_points,
)
from tests.geometry._helpers import EXTREME_ANGLES, random_poses, random_rotations, rotvecs_with_angle


def test_make_pose_inverse_transform(rng):
    T = random_poses(rng, 20)
    assert np.array_equal(make_pose(T[:, :3, :3], T[:, :3, 3]), T)
    np.testing.assert_allclose(pose_inverse(T) @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-14)
    np.testing.assert_allclose(pose_inverse(T), np.linalg.inv(T), atol=1e-13)
    p = rng.normal(size=(20, 5, 3))
    ph = np.concatenate([p, np.ones((20, 5, 1))], axis=-1)
    np.testing.assert_allclose(transform_points(T, p), np.einsum("nij,nkj->nki", T, ph)[..., :3], atol=1e-14)
    np.testing.assert_allclose(transform_points(T[0], p[0, 0]), (T[0] @ ph[0, 0])[:3], atol=1e-14)
    assert transform_points(T[0], p).shape == (20, 5, 3)  # one pose, batch of point sets
    assert make_pose(np.eye(3), np.zeros((4, 3))).shape == (4, 4, 4)  # broadcast


@pytest.mark.parametrize("angle", EXTREME_ANGLES)
def test_pose6_round_trip(rng, angle):
    pose6 = np.concatenate([rng.normal(size=(30, 3)), rotvecs_with_angle(rng, 30, angle)], axis=-1)
    T = pos_rotvec_to_pose(pose6)
    assert T.shape == (30, 4, 4) and np.isfinite(T).all()
    np.testing.assert_allclose(T[:, :3, :3], Rotation.from_rotvec(pose6[:, 3:]).as_matrix(), atol=1e-12)
    back = pose_to_pos_rotvec(T)
    assert np.isfinite(back).all()
    np.testing.assert_array_equal(back[:, :3], pose6[:, :3])
    np.testing.assert_allclose(pos_rotvec_to_pose(back), T, atol=1e-12)


def test_pose6_float32_input(rng):
    pose6 = rng.normal(size=(4, 6))
    # rotation vectors with angle < pi: so3_log returns the angle in [0, pi], so larger angles come back as
    # the equivalent vector (2*pi - angle about the opposite axis)
    axis = pose6[:, 3:] / np.linalg.norm(pose6[:, 3:], axis=-1, keepdims=True)
    pose6[:, 3:] = axis * rng.uniform(0.0, np.pi - 1e-3, size=(4, 1))
    pose6 = pose6.astype(np.float32)
    T = pos_rotvec_to_pose(pose6)
    assert T.dtype == np.float64
    np.testing.assert_allclose(pose_to_pos_rotvec(T), pose6.astype(np.float64), atol=1e-12)


@pytest.mark.parametrize("angle", EXTREME_ANGLES)
def test_se3_exp_log(rng, angle):
    xi = np.concatenate([rng.normal(size=(30, 3)), rotvecs_with_angle(rng, 30, angle)], axis=-1)
    T = se3_exp(xi)
    assert np.isfinite(T).all()
    np.testing.assert_allclose(T[:, :3, :3], so3_exp(xi[:, 3:]), atol=0)
    xi2 = se3_log(T)
    assert np.isfinite(xi2).all()
    np.testing.assert_allclose(se3_exp(xi2), T, atol=1e-12)
    if angle < math.pi - 1e-12:
        np.testing.assert_allclose(xi2, xi, atol=1e-9 if angle > 3 else 1e-12)


def test_se3_exp_matches_matrix_exponential(rng):
    from scipy.linalg import expm

    xi = np.concatenate([rng.normal(size=3), rotvecs_with_angle(rng, 1, 2.0)[0]])
    M = np.zeros((4, 4))
    M[:3, :3] = np.array([[0, -xi[5], xi[4]], [xi[5], 0, -xi[3]], [-xi[4], xi[3], 0]])
    M[:3, 3] = xi[:3]
    np.testing.assert_allclose(se3_exp(xi), expm(M), atol=1e-12)


def test_quaternions_vs_scipy(rng):
    R = random_rotations(rng, 300)
    q_xyzw = matrix_to_quat_xyzw(R)
    ref = Rotation.from_matrix(R).as_quat()
    ref = np.where(ref[:, 3:] < 0, -ref, ref)
    np.testing.assert_allclose(q_xyzw, ref, atol=1e-12)
    q_wxyz = matrix_to_quat_wxyz(R)
    assert (q_wxyz[:, 0] >= 0).all()
    np.testing.assert_array_equal(quat_wxyz_to_xyzw(q_wxyz), q_xyzw)
    np.testing.assert_array_equal(quat_xyzw_to_wxyz(q_xyzw), q_wxyz)
    np.testing.assert_allclose(quat_wxyz_to_matrix(q_wxyz), R, atol=1e-12)
    np.testing.assert_allclose(quat_xyzw_to_matrix(q_xyzw), R, atol=1e-12)
    np.testing.assert_allclose(quat_xyzw_to_matrix(3.0 * ref), R, atol=1e-12)  # normalised
    np.testing.assert_allclose(quat_wxyz_to_matrix(-q_wxyz), R, atol=1e-12)  # q and −q


@pytest.mark.parametrize("angle", EXTREME_ANGLES)
def test_quaternion_extremes(rng, angle):
    R = so3_exp(rotvecs_with_angle(rng, 40, angle))
    q = matrix_to_quat_wxyz(R)
    assert np.isfinite(q).all()
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(quat_wxyz_to_matrix(q), R, atol=1e-12)
    ref = Rotation.from_matrix(R).as_quat()[:, [3, 0, 1, 2]]
    err = np.minimum(np.abs(q - ref).max(-1), np.abs(q + ref).max(-1))
    assert err.max() < 1e-12


def test_pose_quat_round_trips(rng):
    T = random_poses(rng, 50)
    pos, q = pose_to_pos_quat_wxyz(T)
    np.testing.assert_allclose(pos_quat_wxyz_to_pose(pos, q), T, atol=1e-12)
    pos2, q2 = pose_to_pos_quat_xyzw(T)
    np.testing.assert_array_equal(pos2, pos)
    np.testing.assert_array_equal(q2, quat_wxyz_to_xyzw(q))
    np.testing.assert_allclose(pos_quat_xyzw_to_pose(pos2, q2), T, atol=1e-12)
    # quat → pose → quat (both orders)
    qr = rng.normal(size=(50, 4))
    qr /= np.linalg.norm(qr, axis=-1, keepdims=True)
    qr = np.where(qr[:, :1] < 0, -qr, qr)
    np.testing.assert_allclose(pose_to_pos_quat_wxyz(pos_quat_wxyz_to_pose(pos, qr))[1], qr, atol=1e-12)
    qx = quat_wxyz_to_xyzw(qr)
    np.testing.assert_allclose(pose_to_pos_quat_xyzw(pos_quat_xyzw_to_pose(pos, qx))[1], qx, atol=1e-12)
