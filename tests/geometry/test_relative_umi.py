import numpy as np
import pytest

from umi_aug.errors import GeometryError
from umi_aug.geometry import (
    absolute_pose,
    camera_poses_from_tcp_poses,
    convert_pose_representation,
    relative_pose,
    tcp_poses_from_camera_poses,
    transform_points,
    umi_T_cam_tcp,
)
from tests.geometry._helpers import random_poses


def test_relative_absolute_inverse(rng):
    T_cur = random_poses(rng, 1)[0]
    T = random_poses(rng, 16)
    rel = relative_pose(T_cur, T)
    np.testing.assert_allclose(rel, np.linalg.inv(T_cur) @ T, atol=1e-12)  # UMI semantics
    np.testing.assert_allclose(absolute_pose(T_cur, rel), T, atol=1e-12)
    np.testing.assert_allclose(relative_pose(T_cur, T_cur), np.eye(4), atol=1e-14)
    np.testing.assert_allclose(relative_pose(T, absolute_pose(T, T[::-1])), T[::-1], atol=1e-12)


def test_convert_pose_representation(rng):
    base = random_poses(rng, 1)[0]
    P = random_poses(rng, 8)
    np.testing.assert_array_equal(convert_pose_representation(P, base, "abs"), P)
    np.testing.assert_array_equal(convert_pose_representation(P, base, "abs", backward=True), P)
    rel = convert_pose_representation(P, base, "relative")
    np.testing.assert_allclose(rel, np.linalg.inv(base) @ P, atol=1e-12)
    np.testing.assert_allclose(convert_pose_representation(rel, base, "relative", backward=True), P, atol=1e-12)
    with pytest.raises(GeometryError, match=r"'delta'.*\['abs', 'relative'\]"):
        convert_pose_representation(P, base, "delta")


def test_umi_cam_tcp():
    T = umi_T_cam_tcp()
    np.testing.assert_array_equal(T[:3, :3], np.eye(3))
    np.testing.assert_allclose(T[:3, 3], [0.0, 0.086, 0.01465 + 0.205], atol=1e-15)
    np.testing.assert_allclose(umi_T_cam_tcp(tcp_offset=0.0)[:3, 3], [0.0, 0.086, 0.01465], atol=1e-15)
    with pytest.raises(GeometryError, match="tcp_offset"):
        umi_T_cam_tcp(tcp_offset=float("nan"))


def test_tcp_camera_round_trip(rng):
    T_world_cam = random_poses(rng, 10)
    T_world_tcp = tcp_poses_from_camera_poses(T_world_cam)
    # the TCP sits 0.21965 m in front of the camera along its optical axis, 0.086 m along +y (down)
    np.testing.assert_allclose(
        T_world_tcp[:, :3, 3], transform_points(T_world_cam, np.array([0.0, 0.086, 0.21965])), atol=1e-14
    )
    np.testing.assert_allclose(T_world_tcp[:, :3, :3], T_world_cam[:, :3, :3], atol=0)
    np.testing.assert_allclose(camera_poses_from_tcp_poses(T_world_tcp), T_world_cam, atol=1e-14)
    custom = umi_T_cam_tcp(tcp_offset=0.1)
    np.testing.assert_allclose(
        camera_poses_from_tcp_poses(tcp_poses_from_camera_poses(T_world_cam, custom), custom), T_world_cam, atol=1e-14
    )
