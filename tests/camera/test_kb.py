"""Kannala–Brandt fisheye model (numpy): OpenCV agreement, round trips, validity, Newton inverse, Jacobian."""

from __future__ import annotations

import math
import subprocess
import sys
import warnings

import cv2
import numpy as np
import pytest

from tests.camera._kb_helpers import (
    EPS,
    angle_between,
    gopro,
    gopro_224,
    intrinsics_zoo,
    random_intrinsics,
    rays_at,
    special_thetas,
    theta_tolerance,
)
from umi_aug.camera import kb
from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import CameraError


def _random_front_points(rng: np.random.Generator, n: int, theta_max: float) -> np.ndarray:
    """Random points with z > 0 and theta <= theta_max (< 90 deg), random depths over 4 decades."""
    theta = rng.uniform(0.0, theta_max, n)
    phi = rng.uniform(-math.pi, math.pi, n)
    depth = 10.0 ** rng.uniform(-2, 2, n)
    return rays_at(theta, phi) * depth[:, None]


# ------------------------------------------------------------------------------------------------ OpenCV
@pytest.mark.parametrize("which", range(6))
def test_project_matches_opencv(rng, which):
    intr = intrinsics_zoo(rng)[which]
    tmax = min(intr.theta_max, math.radians(88.0))
    pts = _random_front_points(rng, 2000, tmax)
    pts[0] = [0.0, 0.0, 1.3]  # optical axis
    uv, valid = kb.project(pts, intr)
    assert valid.all()
    uv_cv, _ = cv2.fisheye.projectPoints(
        pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), intr.K, intr.D.reshape(4, 1)
    )
    np.testing.assert_allclose(uv, uv_cv.reshape(-1, 2), rtol=0, atol=1e-6)
    # the peer: distortPoints takes pinhole-normalised points x/z, y/z
    und = (pts[:, :2] / pts[:, 2:]).reshape(-1, 1, 2)
    uv_dp = cv2.fisheye.distortPoints(und, intr.K, intr.D.reshape(4, 1))
    np.testing.assert_allclose(uv, uv_dp.reshape(-1, 2), rtol=0, atol=1e-6)


@pytest.mark.parametrize("which", [0, 1, 3])
def test_unproject_matches_opencv_undistort_in_front(rng, which):
    """Against cv2.fisheye.undistortPoints inside theta < 60 deg (OpenCV's tan(theta) parameterisation and its own
    Newton iteration are not reliable further out or on strongly distorted random models)."""
    intr = intrinsics_zoo(rng)[which]
    rays_true = rays_at(rng.uniform(0, math.radians(60.0), 500), rng.uniform(-math.pi, math.pi, 500))
    uv, _ = kb.project(rays_true, intr)
    rays, valid = kb.unproject(uv, intr)
    assert valid.all()
    assert angle_between(rays, rays_true).max() < 1e-14
    und = cv2.fisheye.undistortPoints(
        uv.reshape(-1, 1, 2), intr.K, intr.D.reshape(4, 1),
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15),
    ).reshape(-1, 2)
    cv_rays = np.concatenate([und, np.ones((len(und), 1))], axis=1)
    cv_rays /= np.linalg.norm(cv_rays, axis=1, keepdims=True)
    assert angle_between(rays, cv_rays).max() < 1e-8


# -------------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("which", range(6))
def test_round_trips_special_angles(rng, which):
    intr = intrinsics_zoo(rng)[which]
    theta = special_thetas(intr)
    phi = rng.uniform(-math.pi, math.pi, (theta.size, 7))
    theta = np.broadcast_to(theta[:, None], phi.shape)
    rays_true = rays_at(theta, phi)
    # ray -> pixel -> ray
    uv, valid = kb.project(rays_true, intr)
    assert valid.all()
    rays, valid2 = kb.unproject(uv, intr)
    assert valid2.all()
    err = angle_between(rays, rays_true)
    assert (err <= theta_tolerance(intr, theta)).all(), (err.max(axis=1), theta[:, 0])
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0, atol=4 * EPS)
    # pixel -> ray -> pixel
    uv2, valid3 = kb.project(rays, intr)
    assert valid3.all()
    assert np.abs(uv2 - uv).max() <= 1e-9


def test_theta_zero_is_exact():
    intr = gopro()
    uv, valid = kb.project(np.array([0.0, 0.0, 2.5]), intr)
    assert valid and uv[0] == intr.cx and uv[1] == intr.cy
    rays, valid, n = kb.unproject(np.array([intr.cx, intr.cy]), intr, return_iterations=True)
    assert valid and n == 0
    assert rays.tolist() == [0.0, 0.0, 1.0]
    # tiny offsets from the principal point: the limit theta_d -> 0 is smooth (principal point at 0 so that the
    # offsets are representable)
    eq = FisheyeIntrinsics(100, 100, 40.0, 40.0, 0.0, 0.0, intr.k)
    for d in (1e-300, 1e-200, 1e-15, 1e-9, 1e-5):
        r, v = kb.unproject(np.array([d, -2 * d]), eq)
        assert v and np.isfinite(r).all()
        td = math.hypot(d, 2 * d) / 40.0
        th = float(kb.kb_inverse_theta(td, eq.k, eq.theta_max)[0])
        expect = [math.sin(th) / td * (d / 40.0), -math.sin(th) / td * (2 * d / 40.0), math.cos(th)]
        np.testing.assert_allclose(r, expect, rtol=1e-15, atol=0)


def test_random_pixels_round_trip(rng):
    for intr in (gopro(), gopro_224(), random_intrinsics(rng)):
        uv = rng.uniform([-0.5, -0.5], [intr.width - 0.5, intr.height - 0.5], size=(20000, 2))
        rays, valid = kb.unproject(uv, intr)
        assert np.isfinite(rays).all()
        uv2, valid2 = kb.project(rays, intr)
        assert (valid2 | ~valid).all()
        assert np.abs(uv2 - uv)[valid].max() <= 1e-9


def test_outside_image_circle_invalid_finite():
    intr = gopro()
    td = intr.theta_d_max
    cases = np.array(
        [
            [intr.cx + intr.fx * td * (1 + 1e-9), intr.cy],
            [intr.cx, intr.cy - intr.fy * td * 1.5],
            [0.0, 0.0],  # a corner of the 4:3 frame (r ~ 1690 px > 1103 px)
            [1e300, -1e300],
            [np.inf, 5.0],
            [np.nan, 5.0],
            [-np.inf, np.nan],
        ]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rays, valid, n = kb.unproject(cases, intr, return_iterations=True)
    assert not valid.any()
    assert np.isfinite(rays).all()
    assert (rays == [0.0, 0.0, 1.0]).all()
    assert (n == 0).all()
    # exactly on the circle is valid, and maps to theta_max
    on = np.array([intr.cx + intr.fx * td, intr.cy])
    r, v = kb.unproject(on, intr)
    assert v
    assert abs(math.atan2(math.hypot(r[0], r[1]), r[2]) - intr.theta_max) < 1e-12


def test_umi_224_crop_corners():
    intr = gopro_224()
    corners = np.array([[0, 0], [223, 0], [0, 223], [223, 223]], dtype=float)
    rays, valid = kb.unproject(corners, intr)
    assert not valid.any() and np.isfinite(rays).all()
    # edge midpoints lie inside the circle at ~82 deg (notes: 165 deg edge-to-edge)
    mids = np.array([[0, intr.cy], [223, intr.cy], [intr.cx, 0], [intr.cx, 223]], dtype=float)
    rays, valid = kb.unproject(mids, intr)
    assert valid.all()
    theta = np.degrees(np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2]))
    assert np.all((theta > 80) & (theta < 84.5)), theta
    # fraction of the 224x224 image inside the circle ~ 87.9 %, and ~3.6 % beyond 90 deg (notes)
    v, u = np.mgrid[0:224, 0:224]
    rays, valid = kb.unproject(np.stack([u, v], -1).astype(float), intr)
    assert abs(valid.mean() - 0.879) < 0.01
    assert abs((valid & (rays[..., 2] < 0)).mean() - 0.036) < 0.01


# ------------------------------------------------------------------------------------------------ project
def test_project_validity_and_placeholders():
    intr = gopro()
    pts = np.array(
        [
            [0.0, 0.0, 0.0],  # camera centre
            [np.nan, 0.0, 1.0],
            [np.inf, 0.0, 1.0],
            [0.0, 0.0, -1.0],  # straight back (theta = pi)
            [math.sin(math.radians(120)), 0.0, math.cos(math.radians(120))],  # beyond the fold-over
            [math.sin(math.radians(100)), 0.0, math.cos(math.radians(100))],  # behind the image plane, valid
            [1e-100, 2e-100, 3e-100],  # tiny but a direction
            [1e200, -1e200, 3e200],
            [1e-160, 0.0, 1e-160],  # below MIN_POINT_NORM: the camera centre
        ]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        uv, valid = kb.project(pts, intr)
    assert valid.tolist() == [False, False, False, False, False, True, True, True, False]
    assert np.isfinite(uv).all()
    assert (uv[~valid] == [intr.cx, intr.cy]).all()
    np.testing.assert_allclose(uv[6], kb.project(np.array([1.0, 2.0, 3.0]), intr)[0], rtol=1e-14)
    np.testing.assert_allclose(uv[7], kb.project(np.array([1.0, -1.0, 3.0]), intr)[0], rtol=1e-14)


def test_project_small_r_limit(rng):
    """theta_d/r -> 1/z: exact on the axis, continuous across the series threshold."""
    intr = random_intrinsics(rng)
    z = float(rng.uniform(0.5, 3.0))
    for r in (0.0, 1e-300, 1e-12, 1e-6, kb.SMALL_T * z * (1 - 1e-12), kb.SMALL_T * z * (1 + 1e-12), 0.3):
        p = np.array([r * 0.6, r * 0.8, z])
        uv, valid = kb.project(p, intr)
        theta = math.atan2(r, z)
        td = theta * (1 + sum(c * theta ** (2 * i + 2) for i, c in enumerate(intr.k)))
        scale = td / r if r > 0 else 1.0 / z
        expect = [intr.fx * scale * p[0] + intr.cx, intr.fy * scale * p[1] + intr.cy]
        assert valid
        np.testing.assert_allclose(uv, expect, rtol=1e-15, atol=1e-12)


def test_batched_shapes(rng):
    intr = random_intrinsics(rng)
    pts = rng.normal(size=(2, 3, 4, 3))
    uv, valid = kb.project(pts, intr)
    assert uv.shape == (2, 3, 4, 2) and valid.shape == (2, 3, 4)
    rays, v2 = kb.unproject(uv, intr)
    assert rays.shape == (2, 3, 4, 3) and v2.shape == (2, 3, 4)
    J, v3 = kb.project_jacobian(pts, intr)
    assert J.shape == (2, 3, 4, 2, 3) and v3.shape == (2, 3, 4)
    uv1, v1 = kb.project(pts[1, 2, 3], intr)
    assert uv1.shape == (2,) and v1.shape == ()
    assert np.array_equal(uv1, uv[1, 2, 3])
    with pytest.raises(CameraError):
        kb.project(np.zeros((4, 2)), intr)
    with pytest.raises(CameraError):
        kb.unproject(np.zeros((4, 3)), intr)


def test_theta_limit_restricts_validity():
    intr = FisheyeIntrinsics(2704, 2028, 796.85, 796.85, 1352.0, 1014.0, (-0.02, -0.019, 0.0017, -0.00017),
                             theta_limit=math.radians(95))
    assert intr.theta_max == pytest.approx(math.radians(95))
    _, valid = kb.project(rays_at(np.radians([94.9, 95.1]), [0.3, 0.3]), intr)
    assert valid.tolist() == [True, False]
    r = intr.cx + intr.fx * kb.kb_theta_d(math.radians(96), intr.k)
    _, valid = kb.unproject(np.array([r, intr.cy]), intr)
    assert not valid


# ----------------------------------------------------------------------------------------- Newton inverse
def test_inverse_theta_converges_fast(rng):
    intr = gopro()
    theta = np.concatenate([rng.uniform(0, math.pi / 2, 20000), [0.0, 1e-300, 1e-12, 1e-6]])
    th, valid, n = kb.kb_inverse_theta(kb.kb_theta_d(theta, intr.k), intr.k, intr.theta_max)
    assert valid.all()
    # ~1e-15 rad: a few ulps of theta_d divided by the slope theta_d' (0.35 at 90 deg for this lens)
    assert (np.abs(th - theta) <= 8 * EPS * np.maximum(theta, 1) / kb.kb_dtheta_d(theta, intr.k)).all()
    assert np.abs(th - theta).max() <= 5e-15
    assert n.max() <= 7 and n.mean() < 5
    # up to the fold-over: error bounded by the conditioning, and iterations stay bounded
    theta = np.linspace(0, intr.theta_max, 50001)
    th, valid, n = kb.kb_inverse_theta(kb.kb_theta_d(theta, intr.k), intr.k, intr.theta_max)
    assert valid.all()
    assert (np.abs(th - theta) <= theta_tolerance(intr, theta, base=1e-15)).all()
    assert n.max() < kb.NEWTON_MAX_ITER // 2


def test_inverse_theta_random_polynomials(rng):
    """Bracketing keeps the iteration inside [0, theta_max] for strongly distorted models (folds < 90 deg)."""
    for _ in range(20):
        k = tuple(rng.uniform(-1, 1, 4) * [0.3, 0.1, 0.03, 0.01])
        intr = FisheyeIntrinsics(100, 100, 50.0, 50.0, 50.0, 50.0, k)
        theta = np.linspace(0, intr.theta_max, 2001)
        td = kb.kb_theta_d(theta, k)
        th, valid, n = kb.kb_inverse_theta(td, k, intr.theta_max)
        assert valid.all()
        assert (th >= 0).all() and (th <= intr.theta_max).all()
        assert (np.abs(th - theta) <= theta_tolerance(intr, theta, base=1e-14)).all()
        assert n.max() < kb.NEWTON_MAX_ITER


def test_inverse_theta_invalid_and_max_iter():
    intr = gopro()
    td = np.array([-1e-3, intr.theta_d_max * 1.01, np.nan, np.inf, 0.0, intr.theta_d_max])
    th, valid, n = kb.kb_inverse_theta(td, intr.k, intr.theta_max)
    assert valid.tolist() == [False, False, False, False, True, True]
    assert th.tolist()[:5] == [0.0] * 5 and th[5] == intr.theta_max
    assert n.tolist() == [0] * 6
    # tol=0, max_iter=m runs exactly m updates on a generic input; the error shrinks with m
    errs = []
    theta = 1.2
    for m in (1, 2, 3):
        th, _, n = kb.kb_inverse_theta(kb.kb_theta_d(theta, intr.k), intr.k, intr.theta_max, max_iter=m, tol=0.0)
        assert n == m
        errs.append(abs(th - theta))
    assert errs[0] > errs[1] > errs[2]


# ----------------------------------------------------------------------------------------------- Jacobian
def _fd_jacobian(p: np.ndarray, intr: FisheyeIntrinsics, h_rel: float = 1e-6) -> np.ndarray:
    h = h_rel * np.linalg.norm(p, axis=-1)
    J = np.zeros(p.shape[:-1] + (2, 3))
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1.0
        up, _ = kb.project(p + h[..., None] * e, intr)
        um, _ = kb.project(p - h[..., None] * e, intr)
        J[..., :, i] = (up - um) / (2 * h[..., None])
    return J


def test_jacobian_vs_finite_differences(rng):
    for intr in (gopro(), random_intrinsics(rng)):
        theta = np.concatenate([rng.uniform(0, intr.theta_max - 0.05, 300), np.radians([60, 95, 100])])
        theta = theta[theta < intr.theta_max - 0.02]
        pts = rays_at(theta, rng.uniform(-math.pi, math.pi, theta.size)) * rng.uniform(0.1, 10, theta.size)[:, None]
        J, valid = kb.project_jacobian(pts, intr)
        assert valid.all()
        Jn = _fd_jacobian(pts, intr)
        scale = np.abs(J).max(axis=(-1, -2), keepdims=True)
        assert (np.abs(J - Jn) <= 1e-6 * scale + 1e-7).all()


def test_jacobian_on_axis_and_tiny_r(rng):
    intr = random_intrinsics(rng)
    z = float(rng.uniform(0.3, 3.0))
    J, valid = kb.project_jacobian(np.array([0.0, 0.0, z]), intr)
    assert valid
    np.testing.assert_allclose(J, [[intr.fx / z, 0, 0], [0, intr.fy / z, 0]], rtol=1e-15, atol=0)
    # tiny r (series branch), both sides of the series threshold, and moderate r: compare with FD
    for t in (1e-12, 1e-7, 1e-4, kb.SMALL_T * (1 - 1e-9), kb.SMALL_T * (1 + 1e-9), 0.05):
        p = np.array([t * z * 0.6, -t * z * 0.8, z])
        J, valid = kb.project_jacobian(p, intr)
        Jn = _fd_jacobian(p, intr, h_rel=1e-5)
        np.testing.assert_allclose(J, Jn, rtol=0, atol=2e-6 * intr.fx / z)
    # the two branches agree at the threshold to rounding
    a = kb.project_jacobian(np.array([kb.SMALL_T * (1 - 1e-12), 0.0, 1.0]), intr)[0]
    b = kb.project_jacobian(np.array([kb.SMALL_T * (1 + 1e-12), 0.0, 1.0]), intr)[0]
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-10 * intr.fx)


def test_jacobian_beyond_90_degrees(rng):
    intr = gopro()
    theta = np.radians([90.0, 95.0, 100.0, 103.0])
    pts = rays_at(theta, rng.uniform(-math.pi, math.pi, 4)) * 2.0
    J, valid = kb.project_jacobian(pts, intr)
    assert valid.all()
    np.testing.assert_allclose(J, _fd_jacobian(pts, intr), rtol=0, atol=1e-5 * intr.fx)
    # invalid points: zero Jacobian, finite
    J, valid = kb.project_jacobian(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [np.nan, 1, 1]]), intr)
    assert not valid.any() and (J == 0).all()


def test_jacobian_scale_invariance(rng):
    intr = random_intrinsics(rng)
    p = rng.normal(size=3)
    p[2] = abs(p[2]) + 0.5
    J1, _ = kb.project_jacobian(p, intr)
    J2, _ = kb.project_jacobian(p * 1e-3, intr)
    np.testing.assert_allclose(J2, J1 * 1e3, rtol=1e-12)


# ----------------------------------------------------------------------------------------------- hygiene
def test_importing_kb_does_not_import_torch():
    code = "import sys, umi_aug.camera.kb, umi_aug.camera.intrinsics; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
