import math

import numpy as np
import pytest
from scipy import stats

from umi_aug.errors import GeometryError
from umi_aug.geometry import (
    look_at_rotation,
    make_pose,
    rotation_between_vectors,
    rotation_geodesic_distance,
    sample_cone_start_poses,
    sample_directions_in_cap,
    sample_rotations_in_ball,
    so3_log,
)
from tests.geometry._helpers import random_axes, random_rotations

P_MIN = 1e-6  # false-alarm rate ~1e-6 per KS check; the negative controls below reject far below it
N_STAT = 20000


def _basis(axis):
    e1 = np.cross(axis, np.eye(3)[np.argmin(np.abs(axis))])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def _ref_setup(rng):
    pivot = rng.normal(0, 0.2, 3)
    T_ref = make_pose(random_rotations(rng, 1)[0], pivot + random_axes(rng, 1)[0] * rng.uniform(0.2, 0.8))
    return T_ref, pivot


def test_cap_positions_uniform_by_area_ks(rng):
    T_ref, pivot = _ref_setup(rng)
    theta = rng.uniform(0.3, 1.2)
    P = sample_cone_start_poses(T_ref, pivot, theta, N_STAT, rng)
    v = P[:, :3, 3] - pivot
    r_ref = np.linalg.norm(T_ref[:3, 3] - pivot)
    np.testing.assert_allclose(np.linalg.norm(v, axis=-1), r_ref, rtol=1e-12)
    axis = (T_ref[:3, 3] - pivot) / r_ref
    d = v / np.linalg.norm(v, axis=-1, keepdims=True)
    cos_a = d @ axis
    assert (np.arccos(np.clip(cos_a, -1, 1)) <= theta + 1e-9).all()
    one_minus = 1.0 - cos_a
    cap = 1.0 - math.cos(theta)
    assert stats.kstest(one_minus, "uniform", args=(0.0, cap)).pvalue > P_MIN
    e1, e2 = _basis(axis)
    phi = np.mod(np.arctan2(d @ e2, d @ e1), 2 * math.pi)
    assert stats.kstest(phi, "uniform", args=(0.0, 2 * math.pi)).pvalue > P_MIN
    # the same test rejects the naive sampler α ~ U[0, θ] at the same sample size
    alpha_naive = rng.uniform(0.0, theta, N_STAT)
    assert stats.kstest(1.0 - np.cos(alpha_naive), "uniform", args=(0.0, cap)).pvalue < P_MIN


@pytest.mark.parametrize("theta", [math.pi, 2.0])
def test_cap_directions_wide(rng, theta):
    axis = random_axes(rng, 1)[0] * 3.0
    d = sample_directions_in_cap(axis, theta, 5000, rng)
    assert d.shape == (5000, 3) and np.isfinite(d).all()
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-14)
    cos_a = d @ (axis / 3.0)
    assert stats.kstest(1.0 - cos_a, "uniform", args=(0.0, 1.0 - math.cos(theta))).pvalue > P_MIN


def test_orientations_look_at_pivot(rng):
    T_ref, pivot = _ref_setup(rng)
    theta = rng.uniform(0.1, 1.0)
    P = sample_cone_start_poses(T_ref, pivot, theta, 500, rng)
    R = P[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-13)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-13)
    to_pivot = pivot - P[:, :3, 3]
    to_pivot /= np.linalg.norm(to_pivot, axis=-1, keepdims=True)
    np.testing.assert_allclose(R[:, :, 2], to_pivot, atol=1e-12)
    # minimal carry along the cap: orientation differs from the re-aimed reference by exactly α
    R_aim = sample_cone_start_poses(T_ref, pivot, 0.0, 1, 0)[0, :3, :3]
    axis = -R_aim[:, 2]
    alpha = np.arccos(np.clip(-to_pivot @ axis, -1, 1))
    np.testing.assert_allclose(rotation_geodesic_distance(R_aim, R), alpha, atol=1e-7)


def test_extra_rotation_deviation(rng):
    T_ref, pivot = _ref_setup(rng)
    extra = 0.15
    P = sample_cone_start_poses(T_ref, pivot, 0.5, 2000, 7, max_extra_rotation=extra)
    P0 = sample_cone_start_poses(T_ref, pivot, 0.5, 2000, 7)
    np.testing.assert_array_equal(P[:, :3, 3], P0[:, :3, 3])  # same positions: extras are drawn last
    to_pivot = pivot - P[:, :3, 3]
    to_pivot /= np.linalg.norm(to_pivot, axis=-1, keepdims=True)
    dev = np.arccos(np.clip(np.sum(P[:, :3, 2] * to_pivot, axis=-1), -1, 1))
    assert dev.max() <= extra + 1e-9 and dev.max() > 0.5 * extra
    assert rotation_geodesic_distance(P0[:, :3, :3], P[:, :3, :3]).max() <= extra + 1e-9


def test_half_angle_zero_returns_reaimed_reference(rng):
    T_ref, pivot = _ref_setup(rng)
    P = sample_cone_start_poses(T_ref, pivot, 0.0, 4, rng)
    np.testing.assert_allclose(P[:, :3, 3], np.broadcast_to(T_ref[:3, 3], (4, 3)), atol=1e-14)
    want_z = (pivot - T_ref[:3, 3]) / np.linalg.norm(pivot - T_ref[:3, 3])
    np.testing.assert_allclose(P[:, :3, 2], np.broadcast_to(want_z, (4, 3)), atol=1e-14)
    # minimal re-aim: rotation angle equals the angle between the old and new optical axes
    mis = math.acos(np.clip(T_ref[:3, 2] @ want_z, -1, 1))
    np.testing.assert_allclose(rotation_geodesic_distance(T_ref[:3, :3], P[:, :3, :3]), mis, atol=1e-7)
    # a reference already looking at the pivot is returned unchanged
    T_look = make_pose(look_at_rotation(T_ref[:3, 3], pivot, np.array([0, 0, 1.0])), T_ref[:3, 3])
    P_look = sample_cone_start_poses(T_look, pivot, 0.0, 2, rng)
    np.testing.assert_allclose(P_look, np.broadcast_to(T_look, (2, 4, 4)), atol=1e-14)


def test_half_angle_pi_and_shell(rng):
    T_ref, pivot = _ref_setup(rng)
    P = sample_cone_start_poses(T_ref, pivot, math.pi, 3000, rng, radius=(0.3, 0.6), max_extra_rotation=math.pi)
    assert np.isfinite(P).all()
    r = np.linalg.norm(P[:, :3, 3] - pivot, axis=-1)
    assert r.min() >= 0.3 - 1e-12 and r.max() <= 0.6 + 1e-12
    assert stats.kstest(r**3, "uniform", args=(0.3**3, 0.6**3 - 0.3**3)).pvalue > P_MIN
    P2 = sample_cone_start_poses(T_ref, pivot, 0.4, 10, rng, radius=1.25)
    np.testing.assert_allclose(np.linalg.norm(P2[:, :3, 3] - pivot, axis=-1), 1.25, rtol=1e-12)


def test_seeded_determinism(rng):
    T_ref, pivot = _ref_setup(rng)
    kw = dict(radius=(0.2, 0.4), max_extra_rotation=0.3)
    a = sample_cone_start_poses(T_ref, pivot, 0.6, 100, 1234, **kw)
    b = sample_cone_start_poses(T_ref, pivot, 0.6, 100, np.random.default_rng(1234), **kw)
    c = sample_cone_start_poses(T_ref, pivot, 0.6, 100, 1235, **kw)
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()
    assert sample_rotations_in_ball(0.5, 10, 3).tobytes() == sample_rotations_in_ball(0.5, 10, 3).tobytes()


@pytest.mark.parametrize("beta", [0.05, 0.8, math.pi])
def test_rotation_ball_angle_distribution(rng, beta):
    R = sample_rotations_in_ball(beta, 5000 if beta > 0.1 else 2000, rng)
    ang = np.linalg.norm(so3_log(R), axis=-1)
    assert ang.max() <= beta + 1e-12
    cdf = lambda a: (a - np.sin(a)) / (beta - math.sin(beta))  # noqa: E731
    assert stats.kstest(ang, cdf).pvalue > P_MIN
    assert stats.kstest(ang, "uniform", args=(0, beta)).pvalue < P_MIN  # not uniform in angle
    np.testing.assert_array_equal(sample_rotations_in_ball(0.0, 3, rng), np.broadcast_to(np.eye(3), (3, 3, 3)))


def test_rotation_ball_full_is_haar(rng):
    # at β = π the axis of R·e_z must be uniform on S²: z-component uniform in [−1, 1] (Archimedes)
    R = sample_rotations_in_ball(math.pi, N_STAT // 4, rng)
    assert stats.kstest(R[:, 2, 2], "uniform", args=(-1, 2)).pvalue > P_MIN


def test_rotation_between_vectors(rng):
    a = rng.normal(size=(200, 3))
    b = rng.normal(size=(200, 3))
    R = rotation_between_vectors(a, b)
    au, bu = (x / np.linalg.norm(x, axis=-1, keepdims=True) for x in (a, b))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R, au), bu, atol=1e-14)
    ang = np.arccos(np.clip(np.sum(au * bu, -1), -1, 1))
    np.testing.assert_allclose(np.linalg.norm(so3_log(R), axis=-1), ang, atol=1e-7)  # minimal
    for eps in [0.0, 1e-16, 1e-12, 1e-8]:
        bb = -au + eps * rng.normal(size=au.shape)
        Rb = rotation_between_vectors(au, bb)
        assert np.isfinite(Rb).all()
        bbu = bb / np.linalg.norm(bb, axis=-1, keepdims=True)
        np.testing.assert_allclose(np.einsum("nij,nj->ni", Rb, au), bbu, atol=1e-14)
        np.testing.assert_allclose(np.linalg.det(Rb), 1.0, atol=1e-14)
    np.testing.assert_allclose(rotation_between_vectors(au, au), np.broadcast_to(np.eye(3), R.shape), atol=1e-15)


def test_look_at_rotation(rng):
    cam = rng.normal(size=(100, 3))
    tgt = rng.normal(size=(100, 3))
    up = np.array([0.0, 0.0, 1.0])
    R = look_at_rotation(cam, tgt, up)
    f = (tgt - cam) / np.linalg.norm(tgt - cam, axis=-1, keepdims=True)
    np.testing.assert_allclose(R[:, :, 2], f, atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-13)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    assert (R[:, :, 1] @ up <= 1e-12).all()  # y (down) has no upward component
    np.testing.assert_allclose(R[:, :, 0] @ up, 0.0, atol=1e-14)  # no roll: x horizontal
    # fixed example: looking along world +x with z up → right = −y, down = −z
    R1 = look_at_rotation(np.zeros(3), np.array([2.0, 0, 0]), up)
    np.testing.assert_allclose(R1, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-15)
    R2 = look_at_rotation(np.zeros(3), np.array([0, 0, -3.0]), up)  # forward ∥ up: fallback hint
    assert np.isfinite(R2).all()
    np.testing.assert_allclose(R2[:, 2], [0, 0, -1.0], atol=1e-15)
    np.testing.assert_allclose(R2 @ R2.T, np.eye(3), atol=1e-15)


def test_cone_bad_inputs():
    T = np.eye(4)
    piv = np.array([0.0, 0.0, 1.0])
    with pytest.raises(GeometryError, match="half_angle"):
        sample_cone_start_poses(T, piv, -0.1, 3, 0)
    with pytest.raises(GeometryError, match="half_angle"):
        sample_cone_start_poses(T, piv, 4.0, 3, 0)
    with pytest.raises(GeometryError, match="radius"):
        sample_cone_start_poses(T, piv, 0.1, 3, 0, radius=0.0)
    with pytest.raises(GeometryError, match="radius"):
        sample_cone_start_poses(T, piv, 0.1, 3, 0, radius=(0.5, 0.2))
    with pytest.raises(GeometryError, match="`n`"):
        sample_cone_start_poses(T, piv, 0.1, 0, 0)
    with pytest.raises(GeometryError, match="rng"):
        sample_cone_start_poses(T, piv, 0.1, 3, "seed")
    with pytest.raises(GeometryError, match="max_extra_rotation"):
        sample_cone_start_poses(T, piv, 0.1, 3, 0, max_extra_rotation=-1)
    with pytest.raises(GeometryError, match="pivot_world"):
        sample_cone_start_poses(T, np.zeros(3), 0.1, 3, 0)
    with pytest.raises(GeometryError, match="pivot_world"):
        sample_cone_start_poses(T, np.array([0, np.nan, 1]), 0.1, 3, 0)
    with pytest.raises(GeometryError, match="T_world_cam_ref"):
        sample_cone_start_poses(np.eye(3), piv, 0.1, 3, 0)
    with pytest.raises(GeometryError, match="max_angle"):
        sample_rotations_in_ball(4.0, 3, 0)
    with pytest.raises(GeometryError, match="axis"):
        sample_directions_in_cap(np.zeros(3), 0.1, 3, 0)
    with pytest.raises(GeometryError, match="target"):
        look_at_rotation(np.ones(3), np.ones(3), np.array([0, 0, 1.0]))
    with pytest.raises(GeometryError, match="b"):
        rotation_between_vectors(np.ones(3), np.zeros(3))
