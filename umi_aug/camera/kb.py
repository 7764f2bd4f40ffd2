"""Kannala–Brandt ("KB8") fisheye camera model in numpy float64.

This is the model of OpenCV ``cv2.fisheye``, of UMI's GoPro calibration JSON (OpenICC export) and of ORB-SLAM3's
``KannalaBrandt8`` camera::

    r       = hypot(x, y)
    theta   = atan2(r, z)                                  # angle from the optical axis, radians, in [0, pi]
    theta_d = theta * (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
    u       = fx * theta_d * x / r + cx                    # pixels, pixel centres at integer coordinates
    v       = fy * theta_d * y / r + cy

Points are in the OpenCV camera frame (x right, y down, z forward, any length unit: projection is scale free).
Unlike OpenCV, rays with ``theta > 90 deg`` (``z < 0``) are handled: a ray is valid up to
``intr.theta_max`` (the fold-over angle of the polynomial or the lens limit). The equidistant model is ``k = 0``.

Every function is pure and batched over leading dimensions and returns a boolean validity mask; invalid entries
hold finite placeholders (principal point for pixels, ``(0, 0, 1)`` for rays), never NaN, and no floating-point
warnings are emitted. Importing this module does not import torch (see :mod:`umi_aug.camera.kb_torch`).

All numerical constants of the camera stage (Newton tolerance, iteration cap, small-angle series thresholds,
validity epsilons) are defined once, with the radial polynomial, in :mod:`umi_aug.camera.kb_poly`, and
re-exported here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

from umi_aug.camera.kb_poly import (  # noqa: F401  the radial polynomial and the named constants, re-exported
    _EPS,
    FOLD_GRID_SIZE,
    MIN_POINT_NORM,
    NEWTON_MAX_ITER,
    NEWTON_MIN_DERIVATIVE,
    NEWTON_RESIDUAL_ULPS,
    NEWTON_TOL,
    SMALL_T,
    SMALL_THETA,
    THETA_D_MAX_REL_SLACK,
    THETA_MAX_SLACK,
    THETA_PI_MARGIN,
    _dpoly,
    _k4,
    _poly,
    kb_dtheta_d,
    kb_theta_d,
    theta_fold,
)
from umi_aug.camera.kb_poly import __all__ as _POLY_ALL
from umi_aug.errors import CameraError

if TYPE_CHECKING:  # pragma: no cover
    from umi_aug.camera.intrinsics import FisheyeIntrinsics

__all__ = [*_POLY_ALL, "kb_inverse_theta", "project", "unproject", "project_jacobian"]

# --------------------------------------------------------------------------------------------------------------
# Inverse of the radial polynomial
# --------------------------------------------------------------------------------------------------------------
def kb_inverse_theta(
    theta_d: np.ndarray | float,
    k: Sequence[float],
    theta_max: float,
    max_iter: int = NEWTON_MAX_ITER,
    tol: float = NEWTON_TOL,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve ``kb_theta_d(theta, k) = theta_d`` for ``theta`` in ``[0, theta_max]`` (guarded Newton).

    ``theta_d`` must be strictly increasing on ``[0, theta_max]`` (true for ``theta_max <= theta_fold``).
    Each element keeps a bracket ``[lo, hi]`` (``f(lo) <= 0 <= f(hi)``) starting at ``[0, theta_max]``; the
    initial guess is ``theta = theta_d``; a Newton step that leaves the bracket, that does not at least halve the
    step of two iterations before (``rtsafe`` rule: no Newton cycles), or a derivative below
    ``NEWTON_MIN_DERIVATIVE``, is replaced by bisection. An element stops when its update is
    ``<= tol * max(1, theta)``, its residual is at rounding level (``<= NEWTON_RESIDUAL_ULPS * eps * theta_d``;
    after a last Newton step, never a bisection) or its bracket has collapsed.

    Args:
        theta_d: distorted angles ``[...]`` (dimensionless, ``hypot(x_d, y_d)`` of normalised fisheye coords).
        k: ``(k1, k2, k3, k4)``.
        theta_max: largest valid angle, radians (normally ``intr.theta_max``).
        max_iter: iteration cap; ``max_iter=n, tol=0`` runs exactly ``n`` updates (used for convergence studies).
        tol: convergence tolerance on the theta update, radians.

    Returns:
        ``theta`` float64 ``[...]`` radians (``0`` where invalid), ``valid`` bool ``[...]`` (finite and
        ``0 <= theta_d <= kb_theta_d(theta_max)``), ``n_iter`` int32 ``[...]`` (updates performed; 0 if invalid).
    """
    kk = _k4(k)
    td = np.asarray(theta_d, dtype=np.float64)
    shape = td.shape
    td_flat = td.reshape(-1)
    theta_max = float(theta_max)
    td_max = float(kb_theta_d(theta_max, kk))
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(td_flat) & (td_flat >= 0.0) & (td_flat <= td_max)
    theta = np.zeros(td_flat.shape, dtype=np.float64)
    n_iter = np.zeros(td_flat.shape, dtype=np.int32)

    idx = np.flatnonzero(valid)
    target = td_flat[idx]
    # exact end points: no iterations needed
    at_max = target == td_max
    theta[idx[at_max]] = theta_max
    keep = ~at_max & (target > 0.0)
    idx, target = idx[keep], target[keep]

    th = np.minimum(target, theta_max)  # initial guess theta = theta_d (exact to first order)
    lo = np.zeros_like(th)
    hi = np.full_like(th, theta_max)
    # |step| one and two iterations ago (rtsafe safeguard: a Newton step must at least halve the step taken two
    # iterations before, otherwise bisect; this forbids Newton cycles and guarantees bracket shrinkage)
    dx = np.full_like(th, theta_max)
    dx_old = np.full_like(th, theta_max)
    it = 0
    while idx.size and it < max_iter:
        it += 1
        f = th * _poly(th * th, kk) - target
        df = kb_dtheta_d(th, kk)
        # shrink the bracket with the sign of the residual
        neg = f < 0.0
        lo = np.where(neg, th, lo)
        hi = np.where(neg, hi, th)
        ok_df = df > NEWTON_MIN_DERIVATIVE
        step = np.where(ok_df, f / np.where(ok_df, df, 1.0), 0.0)
        th_newton = th - step
        newton = ok_df & (th_newton >= lo) & (th_newton <= hi) & (2.0 * np.abs(step) <= dx_old)
        th_new = np.where(newton, th_newton, 0.5 * (lo + hi))
        # residual zero or at rounding level: the current iterate is as good as the data allow, keep it (next to
        # the fold-over a further step would only amplify rounding noise by 1/theta_d')
        keep = np.abs(f) <= NEWTON_RESIDUAL_ULPS * _EPS * target
        th_new = np.where(keep & ~newton, th, th_new)  # a last Newton step is still welcome, a bisection not
        delta = np.abs(th_new - th)
        dx_old, dx = dx, delta
        th = th_new
        n_iter[idx] = it
        scale = tol * np.maximum(1.0, th)
        done = keep | (delta <= scale) | ((hi - lo) <= scale)
        theta[idx] = th
        if done.any():
            live = ~done
            idx, target, th, lo, hi = idx[live], target[live], th[live], lo[live], hi[live]
            dx, dx_old = dx[live], dx_old[live]
    return theta.reshape(shape), valid.reshape(shape), n_iter.reshape(shape)


# --------------------------------------------------------------------------------------------------------------
# Projection helpers
# --------------------------------------------------------------------------------------------------------------
def _atan_over_t_series(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``a(q) = atan(t)/t`` and ``da/dq`` for ``q = t^2`` small (Taylor series, error ~ q^5/11)."""
    a = 1.0 + q * (-1.0 / 3.0 + q * (1.0 / 5.0 + q * (-1.0 / 7.0 + q * (1.0 / 9.0))))
    da = -1.0 / 3.0 + q * (2.0 / 5.0 + q * (-3.0 / 7.0 + q * (4.0 / 9.0)))
    return a, da


def _normalise_points(points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return unit directions ``[..., 3]`` (placeholder (0,0,1) where invalid), the norms ``[...]`` (1 where
    invalid) and the validity ``[...]`` (finite and not at the camera centre)."""
    p = np.asarray(points_cam, dtype=np.float64)
    _check_last_dim(p, 3, "points_cam")
    p = p.reshape(-1, 3)  # flat working copy (callers reshape back)
    finite = np.isfinite(p).all(axis=-1)
    p_safe = np.where(finite[..., None], p, 0.0)
    m = np.abs(p_safe).max(axis=-1)
    valid = finite & (m > MIN_POINT_NORM)
    m_safe = np.where(valid, m, 1.0)
    q = p_safe / m_safe[..., None]
    n = np.sqrt((q * q).sum(axis=-1))  # in [1, sqrt(3)]
    n = np.where(valid, n, 1.0)
    d = q / n[..., None]
    d = np.where(valid[..., None], d, np.array([0.0, 0.0, 1.0]))
    return d, np.where(valid, m_safe * n, 1.0), valid


def _radial_terms(
    d: np.ndarray, k: tuple[float, float, float, float], jacobian: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray]:
    """For unit directions ``d [..., 3]``: ``theta``, ``s = theta_d / r``, ``A`` with ``ds/dx = x A``,
    ``ds/dy = y A`` and ``s_z = ds/dz`` (derivatives at the unit point; ``None`` unless ``jacobian``), and the
    series-branch mask.

    Series branch (``z > 0`` and ``r <= SMALL_T z``): with ``q = r^2/z^2``, ``a = atan(t)/t``,
    ``G(q) = a P(q a^2)``: ``s = G/z``, ``A = 2 G'(q)/z^3``, ``ds/dz = -(G + 2 q G')/z^2`` — the exact limit
    ``s -> 1/z``, ``A -> (2 k1 - 2/3)/z^3`` at ``r = 0``. Direct branch: ``s = theta_d / r``,
    ``A = (theta_d' z/rho^2 - theta_d/r)/r^2``, ``ds/dz = -theta_d'/rho^2``.
    """
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    r2 = x * x + y * y
    r = np.sqrt(r2)
    theta = np.arctan2(r, z)
    series = (z > 0.0) & (r <= SMALL_T * z)
    # direct branch everywhere (r replaced by 1 where it is 0 or the series branch takes over)
    r_d = np.where(series | (r <= 0.0), 1.0, r)
    td = theta * _poly(theta * theta, k)
    s = td / r_d
    A = s_z = None
    if jacobian:
        rho2 = r2 + z * z
        dtd = kb_dtheta_d(theta, k)
        A = (dtd * z / rho2 - td / r_d) / (r_d * r_d)
        s_z = -dtd / rho2
    # series branch on its (usually tiny) subset
    if series.any():
        zs = z[series]
        q = r2[series] / (zs * zs)
        a, da = _atan_over_t_series(q)
        w = q * a * a
        P = _poly(w, k)
        G = a * P
        s[series] = G / zs
        if jacobian:
            dG = da * P + a * _dpoly(w, k) * (a * a + 2.0 * q * a * da)
            A[series] = 2.0 * dG / (zs * zs * zs)
            s_z[series] = -(G + 2.0 * q * dG) / (zs * zs)
    return theta, s, A, s_z, series


def _check_last_dim(arr: np.ndarray, n: int, name: str) -> None:
    if arr.shape[-1:] != (n,):
        raise CameraError(f"{name} must have shape [..., {n}], got {arr.shape}")


# --------------------------------------------------------------------------------------------------------------
# Public model
# --------------------------------------------------------------------------------------------------------------
def project(points_cam: np.ndarray, intr: "FisheyeIntrinsics") -> tuple[np.ndarray, np.ndarray]:
    """Project camera-frame points to fisheye pixels.

    Args:
        points_cam: ``[..., 3]`` points (or directions) in the OpenCV camera frame (x right, y down, z forward);
            any length unit, only the direction matters.
        intr: the fisheye intrinsics (pixels).

    Returns:
        ``uv`` float64 ``[..., 2]`` pixel coordinates ``(u, v)`` = (column, row), pixel centres at integers;
        ``valid`` bool ``[...]``: point finite, not at the camera centre and ``theta <= intr.theta_max``
        (+ ``THETA_MAX_SLACK`` for rounding).
        Invalid entries hold the principal point ``(cx, cy)``. Valid pixels may still lie outside the image
        rectangle; check ``0 <= u <= W-1`` etc. yourself when needed.
    """
    k = _k4(intr.k)
    lead = np.shape(points_cam)[:-1]
    d, _, ok = _normalise_points(points_cam)
    theta, s, _, _, _ = _radial_terms(d, k)
    valid = ok & (theta <= intr.theta_max + THETA_MAX_SLACK)
    u = intr.fx * s * d[..., 0] + intr.cx
    v = intr.fy * s * d[..., 1] + intr.cy
    uv = np.stack([np.where(valid, u, intr.cx), np.where(valid, v, intr.cy)], axis=-1)
    return uv.reshape(lead + (2,)), valid.reshape(lead)


def project_jacobian(points_cam: np.ndarray, intr: "FisheyeIntrinsics") -> tuple[np.ndarray, np.ndarray]:
    """Analytic Jacobian ``d(u, v) / d(x, y, z)`` of :func:`project`.

    Exact on the optical axis (``r = 0``: ``[[fx/z, 0, 0], [0, fy/z, 0]]``) and valid past 90 deg (``z < 0``).

    Args:
        points_cam: ``[..., 3]`` camera-frame points (OpenCV frame); the Jacobian is with respect to these
            coordinates, in pixels per length unit.
        intr: fisheye intrinsics.

    Returns:
        ``J`` float64 ``[..., 2, 3]`` (zeros where invalid) and ``valid`` bool ``[...]`` (as :func:`project`).
    """
    k = _k4(intr.k)
    lead = np.shape(points_cam)[:-1]
    d, norm, ok = _normalise_points(points_cam)
    theta, s, A, s_z, series = _radial_terms(d, k, jacobian=True)
    valid = ok & (theta <= intr.theta_max + THETA_MAX_SLACK)
    x, y = d[..., 0], d[..., 1]
    r2 = x * x + y * y
    # x^2 A etc.: in the direct branch write as (x^2/r^2)(r^2 A) so r -> 0 never divides 0 by 0
    r2_safe = np.where(r2 > 0.0, r2, 1.0)
    B = np.where(series, A, A * r2)  # series: A itself; direct: r^2 A
    cxx = np.where(series, x * x, x * x / r2_safe)
    cxy = np.where(series, x * y, x * y / r2_safe)
    cyy = np.where(series, y * y, y * y / r2_safe)
    fx, fy = intr.fx, intr.fy
    J = np.empty(d.shape[:-1] + (2, 3), dtype=np.float64)
    J[..., 0, 0] = fx * (s + cxx * B)
    J[..., 0, 1] = fx * cxy * B
    J[..., 0, 2] = fx * x * s_z
    J[..., 1, 0] = fy * cxy * B
    J[..., 1, 1] = fy * (s + cyy * B)
    J[..., 1, 2] = fy * y * s_z
    # chain rule through the normalisation p = norm * d: u is homogeneous of degree 0, so du/dp = du/dd / norm
    J = J / norm[..., None, None]
    J = np.where(valid[..., None, None], J, 0.0)
    return J.reshape(lead + (2, 3)), valid.reshape(lead)


def unproject(
    uv: np.ndarray, intr: "FisheyeIntrinsics", return_iterations: bool = False
) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Back-project fisheye pixels to unit rays in the camera frame.

    ``x_d = (u - cx)/fx``, ``y_d = (v - cy)/fy``, ``theta_d = hypot(x_d, y_d)``, ``theta`` = guarded-Newton
    inverse of the KB polynomial, ``ray = (sin(theta) x_d/theta_d, sin(theta) y_d/theta_d, cos(theta))`` with
    the exact ``theta_d -> 0`` limit (``sin(theta)/theta_d = (sin(theta)/theta) / P(theta^2)``).

    Args:
        uv: ``[..., 2]`` pixel coordinates ``(u, v)`` (column, row; pixel centres at integers).
        intr: fisheye intrinsics.
        return_iterations: also return the Newton iteration count per pixel.

    Returns:
        ``rays`` float64 ``[..., 3]`` unit vectors in the OpenCV camera frame (``z < 0`` for theta > 90 deg),
        ``valid`` bool ``[...]`` (finite and inside the image circle, ``theta_d <= intr.theta_d_max`` up to
        ``THETA_D_MAX_REL_SLACK``; invalid
        rays are ``(0, 0, 1)``), and if requested ``n_iter`` int32 ``[...]``.
    """
    k = _k4(intr.k)
    uv = np.asarray(uv, dtype=np.float64)
    _check_last_dim(uv, 2, "uv")
    finite = np.isfinite(uv).all(axis=-1)
    uv_safe = np.where(finite[..., None], uv, 0.0)
    xd = (uv_safe[..., 0] - intr.cx) / intr.fx
    yd = (uv_safe[..., 1] - intr.cy) / intr.fy
    td = np.hypot(xd, yd)
    td = np.where(finite, td, np.inf)
    td_max = intr.theta_d_max
    td = np.where((td > td_max) & (td <= td_max * (1.0 + THETA_D_MAX_REL_SLACK)), td_max, td)
    theta, valid, n_iter = kb_inverse_theta(td, k, intr.theta_max)
    factor = _sin_over_theta(theta) / _poly(theta * theta, k)  # sin(theta)/theta_d, exact at 0
    xd, yd = np.where(valid, xd, 0.0), np.where(valid, yd, 0.0)  # no overflow for huge invalid pixels
    rays = np.stack([factor * xd, factor * yd, np.cos(theta)], axis=-1)
    rays = rays / np.sqrt((rays * rays).sum(axis=-1, keepdims=True))
    rays = np.where(valid[..., None], rays, np.array([0.0, 0.0, 1.0]))
    if return_iterations:
        return rays, valid, n_iter
    return rays, valid


def _sin_over_theta(theta: np.ndarray) -> np.ndarray:
    """``sin(theta)/theta`` with its series below ``SMALL_THETA`` (exact 1 at 0)."""
    small = np.abs(theta) <= SMALL_THETA
    t2 = theta * theta
    ser = 1.0 + t2 * (-1.0 / 6.0 + t2 * (1.0 / 120.0 + t2 * (-1.0 / 5040.0)))
    th_safe = np.where(small, 1.0, theta)
    return np.where(small, ser, np.sin(th_safe) / th_safe)
