import numpy as np
import pytest

from umi_aug.geometry import mat_to_rot6d, pos_rot6d_to_pose, pose_to_pos_rot6d, rot6d_to_mat, so3_exp
from tests.geometry._helpers import EXTREME_ANGLES, random_poses, random_rotations, rotvecs_with_angle


def _umi_rot6d_to_mat(d6):  # UMI's umi/common/pose_util.py, verbatim logic
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = a1 / np.linalg.norm(a1, axis=-1, keepdims=True)
    b2 = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    b2 = b2 / np.linalg.norm(b2, axis=-1, keepdims=True)
    return np.stack((b1, b2, np.cross(b1, b2, axis=-1)), axis=-2)


def test_rot6d_convention_rows(rng):
    R = random_rotations(rng, 10)
    d6 = mat_to_rot6d(R)
    np.testing.assert_array_equal(d6[:, :3], R[:, 0, :])
    np.testing.assert_array_equal(d6[:, 3:], R[:, 1, :])
    np.testing.assert_allclose(rot6d_to_mat(d6), R, atol=1e-14)


@pytest.mark.parametrize("angle", EXTREME_ANGLES)
def test_rot6d_round_trip_extremes(rng, angle):
    R = so3_exp(rotvecs_with_angle(rng, 20, angle))
    np.testing.assert_allclose(rot6d_to_mat(mat_to_rot6d(R)), R, atol=1e-14)


def test_rot6d_unnormalised_matches_umi(rng):
    d6 = rng.normal(size=(100, 6))
    R = rot6d_to_mat(d6)
    np.testing.assert_allclose(R, _umi_rot6d_to_mat(d6), atol=1e-14)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    np.testing.assert_allclose(mat_to_rot6d(rot6d_to_mat(mat_to_rot6d(R))), mat_to_rot6d(R), atol=1e-14)


def test_rot6d_degenerate_is_finite(rng):
    a = rng.normal(size=3)
    cases = np.array([np.zeros(6), np.r_[a, 2 * a], np.r_[a, np.zeros(3)], np.r_[np.zeros(3), a], np.r_[a, -a]])
    R = rot6d_to_mat(cases)
    assert np.isfinite(R).all()
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    np.testing.assert_allclose(R[1, 0], a / np.linalg.norm(a), atol=1e-15)  # b1 kept when a2 ∥ a1


def test_pose_rot6d_round_trip(rng):
    T = random_poses(rng, 30)
    p9 = pose_to_pos_rot6d(T)
    assert p9.shape == (30, 9)
    np.testing.assert_array_equal(p9[:, :3], T[:, :3, 3])
    np.testing.assert_array_equal(p9[:, 3:], mat_to_rot6d(T[:, :3, :3]))
    np.testing.assert_allclose(pos_rot6d_to_pose(p9), T, atol=1e-14)
