import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from umi_aug.geometry import (
    hat,
    project_to_rotation,
    rotation_geodesic_distance,
    so3_exp,
    so3_left_jacobian,
    so3_left_jacobian_inv,
    so3_log,
    vee,
)
from tests.geometry._helpers import (
    EXTREME_ANGLES,
    random_rotations,
    random_rotvecs,
    rotvec_close_mod_pi,
    rotvecs_with_angle,
)


def test_hat_vee(rng):
    v = rng.normal(size=(7, 3))
    p = rng.normal(size=(7, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", hat(v), p), np.cross(v, p), atol=1e-14)
    np.testing.assert_array_equal(vee(hat(v)), v)
    assert hat(v[0]).shape == (3, 3)


def test_exp_log_random_vs_scipy(rng):
    v = random_rotvecs(rng, 500).reshape(5, 100, 3)
    R = so3_exp(v)
    assert R.shape == (5, 100, 3, 3) and R.dtype == np.float64
    np.testing.assert_allclose(R, Rotation.from_rotvec(v.reshape(-1, 3)).as_matrix().reshape(R.shape), atol=1e-12)
    np.testing.assert_allclose(so3_log(R), v, atol=1e-12)
    Rs = random_rotations(rng, 300)
    np.testing.assert_allclose(so3_log(Rs), Rotation.from_matrix(Rs).as_rotvec(), atol=1e-12)
    np.testing.assert_allclose(so3_exp(so3_log(Rs)), Rs, atol=1e-12)


def test_exp_accepts_large_angles(rng):
    v = rotvecs_with_angle(rng, 20, 5.0)
    np.testing.assert_allclose(so3_exp(v), Rotation.from_rotvec(v).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(so3_log(so3_exp(v)), -v / 5.0 * (2 * math.pi - 5.0), atol=1e-12)


@pytest.mark.parametrize("angle", EXTREME_ANGLES)
def test_exp_log_extremes(rng, angle):
    v = rotvecs_with_angle(rng, 50, angle)
    R = so3_exp(v)
    assert np.isfinite(R).all()
    np.testing.assert_allclose(R, Rotation.from_rotvec(v).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    back = so3_log(R)
    assert np.isfinite(back).all()
    assert rotvec_close_mod_pi(back, v, angle, 1e-12)
    ang = np.linalg.norm(back, axis=-1)
    assert (ang <= math.pi + 1e-15).all()
    np.testing.assert_allclose(ang, angle, atol=1e-12, rtol=1e-12)
    np.testing.assert_allclose(so3_exp(back), R, atol=1e-12)
    if 0 < angle <= 1e-6:  # tiny angles keep full relative precision
        np.testing.assert_allclose(back, v, rtol=1e-14, atol=0)


def test_log_exact_pi_axes():
    for axis in np.eye(3):
        R = np.diag(2 * axis**2 - 1)  # rotation by π about a basis axis
        v = so3_log(R)
        assert np.isfinite(v).all()
        assert abs(np.linalg.norm(v) - math.pi) < 1e-15
        np.testing.assert_allclose(np.abs(v) / math.pi, axis, atol=1e-15)
    assert np.array_equal(so3_log(np.eye(3)), np.zeros(3))


def test_geodesic_distance_vs_scipy(rng):
    R1, R2 = random_rotations(rng, 200), random_rotations(rng, 200)
    ref = (Rotation.from_matrix(R1).inv() * Rotation.from_matrix(R2)).magnitude()
    np.testing.assert_allclose(rotation_geodesic_distance(R1, R2), ref, atol=1e-12)
    for angle in EXTREME_ANGLES:
        d = rotation_geodesic_distance(R1[:20], R1[:20] @ so3_exp(rotvecs_with_angle(rng, 20, angle)))
        assert np.isfinite(d).all()
        np.testing.assert_allclose(d, angle, atol=2e-15 if angle < 1 else 1e-12, rtol=1e-12)
    assert rotation_geodesic_distance(R1[0], R2).shape == (200,)


def _numeric_left_jacobian(phi: np.ndarray, h: float = 1e-6) -> np.ndarray:
    # J_l: exp(phi + d) ≈ exp(J_l d) exp(phi)
    J = np.zeros((3, 3))
    R = so3_exp(phi)
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        J[:, i] = (so3_log(so3_exp(phi + d) @ R.T) - so3_log(so3_exp(phi - d) @ R.T)) / (2 * h)
    return J


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-3, 0.29, 0.31, 1.5, 3.0, math.pi])
def test_left_jacobian(rng, angle):
    phi = rotvecs_with_angle(rng, 1, angle)[0]
    J = so3_left_jacobian(phi)
    np.testing.assert_allclose(J, _numeric_left_jacobian(phi), atol=1e-8)
    np.testing.assert_allclose(so3_left_jacobian_inv(phi) @ J, np.eye(3), atol=1e-13)
    # closed forms at small/large angles agree with the series on both sides of the threshold
    np.testing.assert_allclose(so3_left_jacobian(phi[None])[0], J, atol=0)


def test_left_jacobian_inv_singular_at_two_pi():
    from umi_aug.errors import GeometryError

    with pytest.raises(GeometryError, match="phi"):
        so3_left_jacobian_inv(np.array([2 * math.pi, 0.0, 0.0]))


def test_project_to_rotation(rng):
    R = random_rotations(rng, 50)
    noisy = R + rng.normal(0, 1e-3, R.shape)
    P = project_to_rotation(noisy)
    np.testing.assert_allclose(P @ np.swapaxes(P, -1, -2), np.broadcast_to(np.eye(3), P.shape), atol=1e-13)
    np.testing.assert_allclose(np.linalg.det(P), 1.0, atol=1e-13)
    assert np.abs(P - R).max() < 1e-2
    np.testing.assert_allclose(project_to_rotation(R), R, atol=1e-13)
    reflect = -R[0]  # det −1 input → proper rotation
    assert abs(np.linalg.det(project_to_rotation(reflect)) - 1.0) < 1e-12
