import math

import numpy as np
import pytest

from umi_aug.errors import GeometryError
from umi_aug.geometry import (
    PoseTrajectoryInterpolator,
    interpolate_pose,
    rotation_geodesic_distance,
    slerp_rotations,
    so3_exp,
    so3_log,
)
from tests.geometry._helpers import random_poses, random_rotations, rotvecs_with_angle


def test_slerp_endpoints_midpoint_constant_velocity(rng):
    R0 = random_rotations(rng, 50)
    R1 = R0 @ so3_exp(rotvecs_with_angle(rng, 50, 1.0) * rng.uniform(0.01, 3.1, (50, 1)))
    np.testing.assert_array_equal(slerp_rotations(R0, R1, 0.0), R0)
    np.testing.assert_array_equal(slerp_rotations(R0, R1, 1.0), R1)
    total = rotation_geodesic_distance(R0, R1)
    mid = slerp_rotations(R0, R1, 0.5)
    np.testing.assert_allclose(rotation_geodesic_distance(R0, mid), total / 2, atol=1e-12)
    np.testing.assert_allclose(rotation_geodesic_distance(mid, R1), total / 2, atol=1e-12)
    s = np.linspace(0, 1, 11)
    Rs = slerp_rotations(R0[:, None], R1[:, None], s)  # [50, 11, 3, 3]
    steps = rotation_geodesic_distance(Rs[:, :-1], Rs[:, 1:])
    np.testing.assert_allclose(steps, np.broadcast_to(total[:, None] / 10, steps.shape), atol=1e-12)
    # one rotation axis throughout (geodesic): relative rotvecs are parallel
    rel = so3_log(np.swapaxes(R0, -1, -2)[:, None] @ Rs[:, 1:])
    np.testing.assert_allclose(rel / s[None, 1:, None], np.broadcast_to(rel[:, -1:], rel.shape), atol=1e-11)


def test_slerp_identical_and_opposite(rng):
    R = random_rotations(rng, 5)
    np.testing.assert_allclose(slerp_rotations(R, R, 0.3), R, atol=1e-15)
    Rpi = R @ so3_exp(rotvecs_with_angle(rng, 5, math.pi))
    mid = slerp_rotations(R, Rpi, 0.5)
    assert np.isfinite(mid).all()
    np.testing.assert_allclose(rotation_geodesic_distance(R, mid), math.pi / 2, atol=1e-12)


def test_interpolate_pose(rng):
    T0, T1 = random_poses(rng, 20), random_poses(rng, 20)
    np.testing.assert_array_equal(interpolate_pose(T0, T1, 0.0), T0)
    np.testing.assert_array_equal(interpolate_pose(T0, T1, 1.0), T1)
    s = rng.uniform(0, 1, 20)
    T = interpolate_pose(T0, T1, s)
    np.testing.assert_allclose(T[:, :3, 3], T0[:, :3, 3] + s[:, None] * (T1[:, :3, 3] - T0[:, :3, 3]), atol=1e-14)
    np.testing.assert_allclose(T[:, :3, :3], slerp_rotations(T0[:, :3, :3], T1[:, :3, :3], s), atol=0)
    np.testing.assert_array_equal(T[:, 3], np.broadcast_to([0, 0, 0, 1.0], (20, 4)))


def test_trajectory_interpolator(rng):
    n = 12
    times = np.cumsum(rng.uniform(0.01, 0.1, n))
    poses = random_poses(rng, n)
    f = PoseTrajectoryInterpolator(times, poses)
    np.testing.assert_allclose(f(times), poses, atol=1e-14)
    tq = rng.uniform(times[0] - 0.2, times[-1] + 0.2, 200)
    out = f(tq)
    assert out.shape == (200, 4, 4)
    i = np.clip(np.searchsorted(times, tq, side="right") - 1, 0, n - 2)
    s = np.clip((tq - times[i]) / (times[i + 1] - times[i]), 0, 1)
    np.testing.assert_allclose(out, interpolate_pose(poses[i], poses[i + 1], s), atol=1e-12)
    np.testing.assert_array_equal(f(np.array([times[0] - 1.0])), poses[:1])
    np.testing.assert_array_equal(f(np.array([times[-1] + 1.0])), poses[-1:])
    assert f(float(times[3])).shape == (4, 4)


def test_trajectory_interpolator_single_and_errors(rng):
    P = random_poses(rng, 3)
    f = PoseTrajectoryInterpolator(np.array([0.5]), P[:1])
    np.testing.assert_array_equal(f(np.array([0.0, 0.5, 9.0])), np.broadcast_to(P[0], (3, 4, 4)))
    with pytest.raises(GeometryError, match="strictly increasing"):
        PoseTrajectoryInterpolator(np.array([0.0, 1.0, 1.0]), P)
    with pytest.raises(GeometryError, match="poses"):
        PoseTrajectoryInterpolator(np.array([0.0, 1.0]), P)
    with pytest.raises(GeometryError, match="times"):
        PoseTrajectoryInterpolator(np.zeros((3, 1)), P)
    with pytest.raises(GeometryError, match="t_query"):
        PoseTrajectoryInterpolator(np.arange(3.0), P)(np.array([np.nan]))
