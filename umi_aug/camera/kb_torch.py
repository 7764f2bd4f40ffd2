"""Kannala–Brandt fisheye model in torch: same semantics as :mod:`umi_aug.camera.kb`, differentiable.

* dtype-preserving (float32 or float64; integer inputs become the default float dtype), batched over leading
  dimensions, device-agnostic;
* gradients are finite everywhere, including the optical axis ``r = 0`` and the image centre (the "double
  where" pattern: a branch that is not selected is evaluated on safe placeholder inputs);
* ``unproject`` solves the KB polynomial by the same guarded Newton iteration (no gradient tape) and attaches
  the exact implicit derivative ``d theta / d theta_d = 1 / theta_d'(theta)`` afterwards, so backpropagation
  does not unroll the loop. Float64 results agree with numpy to ~1e-12.

Shapes: ``points_cam [..., 3]`` (OpenCV camera frame, x right, y down, z forward), ``uv [..., 2]`` pixels with
pixel centres at integer coordinates, ``rays [..., 3]`` unit vectors, ``valid [...]`` bool.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from umi_aug.camera.kb import (
    MIN_POINT_NORM,
    NEWTON_MAX_ITER,
    NEWTON_MIN_DERIVATIVE,
    NEWTON_RESIDUAL_ULPS,
    NEWTON_TOL,
    SMALL_T,
    SMALL_THETA,
    THETA_D_MAX_REL_SLACK,
    THETA_MAX_SLACK,
)
from umi_aug.errors import CameraError

if TYPE_CHECKING:  # pragma: no cover
    from umi_aug.camera.intrinsics import FisheyeIntrinsics

__all__ = ["project", "unproject", "project_jacobian", "project_with_jacobian", "kb_theta_d", "kb_dtheta_d", "kb_inverse_theta"]

Tensor = torch.Tensor


def _as_float_tensor(x: Tensor, name: str, last: int) -> Tensor:
    if not isinstance(x, torch.Tensor):
        x = torch.as_tensor(x)
    if not x.is_floating_point():
        x = x.to(torch.get_default_dtype())
    if x.shape[-1:] != (last,):
        raise CameraError(f"{name} must have shape [..., {last}], got {tuple(x.shape)}")
    return x


def _poly(t2: Tensor, k: tuple[float, ...]) -> Tensor:
    k1, k2, k3, k4 = k
    return 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))


def _dpoly(t2: Tensor, k: tuple[float, ...]) -> Tensor:
    k1, k2, k3, k4 = k
    return k1 + t2 * (2.0 * k2 + t2 * (3.0 * k3 + t2 * 4.0 * k4))


def kb_theta_d(theta: Tensor, k: tuple[float, float, float, float]) -> Tensor:
    """``theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)``; ``theta [...]`` radians -> ``[...]``."""
    return theta * _poly(theta * theta, tuple(float(c) for c in k))


def kb_dtheta_d(theta: Tensor, k: tuple[float, float, float, float]) -> Tensor:
    """``d theta_d / d theta = 1 + 3 k1 theta^2 + 5 k2 theta^4 + 7 k3 theta^6 + 9 k4 theta^8``; ``[...]``."""
    k1, k2, k3, k4 = (float(c) for c in k)
    t2 = theta * theta
    return 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))


def _theta_slack(dtype: torch.dtype) -> float:
    """Rounding slack of the ray-angle validity test (``THETA_MAX_SLACK``, larger in float32)."""
    return max(THETA_MAX_SLACK, NEWTON_RESIDUAL_ULPS * float(torch.finfo(dtype).eps) * 3.2)


def _newton_tol(dtype: torch.dtype) -> float:
    return max(NEWTON_TOL, NEWTON_RESIDUAL_ULPS * float(torch.finfo(dtype).eps))


def _newton_update(th, target, lo, hi, dx, dx_old, k, eps, tol):
    """One guarded-Newton update (bracket, rtsafe rule, bisection fallback, rounding-level stop); all ``[M]``.
    Returns ``th_new, lo, hi, dx_new, dx_old_new, converged``."""
    f = kb_theta_d(th, k) - target
    df = kb_dtheta_d(th, k)
    neg = f < 0
    lo = torch.where(neg, th, lo)
    hi = torch.where(neg, hi, th)
    ok_df = df > NEWTON_MIN_DERIVATIVE
    step = torch.where(ok_df, f / torch.where(ok_df, df, torch.ones_like(df)), torch.zeros_like(f))
    th_newton = th - step
    newton = ok_df & (th_newton >= lo) & (th_newton <= hi) & (2.0 * step.abs() <= dx_old)
    th_new = torch.where(newton, th_newton, 0.5 * (lo + hi))
    keep = f.abs() <= NEWTON_RESIDUAL_ULPS * eps * target  # zero / rounding-level residual: keep theta
    th_new = torch.where(keep & ~newton, th, th_new)
    delta = (th_new - th).abs()
    scale = tol * torch.clamp(th_new, min=1.0)
    conv = keep | (delta <= scale) | ((hi - lo) <= scale)
    return th_new, lo, hi, delta, dx, conv


@torch.no_grad()
def _inverse_theta_nograd(
    td: Tensor, k: tuple[float, ...], theta_max: float, n_iter: int | None, max_iter: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Guarded Newton on detached ``td [...]`` (see :func:`umi_aug.camera.kb.kb_inverse_theta`).

    ``n_iter`` given: exactly that many masked updates over the whole tensor (no host sync, vmap-able).
    ``n_iter=None``: iterate on the shrinking set of unconverged elements only (one host sync per iteration).
    """
    dtype = td.dtype
    eps = float(torch.finfo(dtype).eps)
    tol = _newton_tol(dtype)
    th_max = torch.tensor(theta_max, dtype=dtype, device=td.device)
    td_max = kb_theta_d(th_max, k)
    valid = torch.isfinite(td) & (td >= 0) & (td <= td_max)
    target = torch.where(valid, td, torch.zeros_like(td))
    th = torch.minimum(target, th_max)  # initial guess theta = theta_d
    lo = torch.zeros_like(th)
    hi = torch.full_like(th, theta_max)
    # end points need no iteration
    done = ~valid | (target == 0) | (target == td_max)
    th = torch.where(valid & (target == td_max), hi, th)
    dx = torch.full_like(th, theta_max)  # |step| one and two iterations ago (rtsafe safeguard)
    dx_old = torch.full_like(th, theta_max)
    iters = torch.zeros(td.shape, dtype=torch.int32, device=td.device)
    if n_iter is not None:
        for it in range(1, int(n_iter) + 1):
            th_new, lo, hi, dx_new, dx_old_new, conv = _newton_update(th, target, lo, hi, dx, dx_old, k, eps, tol)
            th = torch.where(done, th, th_new)
            dx, dx_old = torch.where(done, dx, dx_new), torch.where(done, dx_old, dx_old_new)
            iters = torch.where(done, iters, torch.full_like(iters, it))
            done = done | conv
    else:
        shape = th.shape
        th_f, iters_f = th.reshape(-1).clone(), iters.reshape(-1).clone()
        idx = torch.nonzero(~done.reshape(-1)).squeeze(-1)
        tgt, t, l, h, d1, d2 = (a.reshape(-1)[idx] for a in (target, th, lo, hi, dx, dx_old))
        for it in range(1, max_iter + 1):
            if idx.numel() == 0:
                break
            t, l, h, d1, d2, conv = _newton_update(t, tgt, l, h, d1, d2, k, eps, tol)
            th_f[idx] = t
            iters_f[idx] = it
            if bool(conv.any()):
                live = ~conv
                idx, tgt, t, l, h, d1, d2 = idx[live], tgt[live], t[live], l[live], h[live], d1[live], d2[live]
        th, iters = th_f.reshape(shape), iters_f.reshape(shape)
    th = torch.where(valid, th, torch.zeros_like(th))
    return th, valid, iters


def kb_inverse_theta(
    theta_d: Tensor,
    k: tuple[float, float, float, float],
    theta_max: float,
    n_iter: int | None = None,
    max_iter: int = NEWTON_MAX_ITER,
) -> tuple[Tensor, Tensor, Tensor]:
    """Differentiable inverse of the KB polynomial on ``[0, theta_max]``.

    Args:
        theta_d: ``[...]`` distorted angles (float32/float64).
        k: ``(k1, k2, k3, k4)``.
        theta_max: largest valid angle, radians.
        n_iter: run exactly this many guarded-Newton updates (fixed cost, no host sync); ``None``: iterate until
            every element has converged (``max_iter`` at most).
        max_iter: cap when ``n_iter`` is None.

    Returns:
        ``theta [...]`` (same dtype, 0 where invalid; gradient ``1/theta_d'(theta)`` w.r.t. ``theta_d``),
        ``valid [...]`` bool, ``iters [...]`` int32.
    """
    kk = tuple(float(c) for c in k)
    th, valid, iters = _inverse_theta_nograd(theta_d.detach(), kk, float(theta_max), n_iter, max_iter)
    if theta_d.requires_grad:
        dtd = kb_dtheta_d(th, kk)
        ok = valid & (dtd > NEWTON_MIN_DERIVATIVE)
        inv = torch.where(ok, 1.0 / torch.where(ok, dtd, torch.ones_like(dtd)), torch.zeros_like(dtd))
        td_safe = torch.where(valid, theta_d, torch.zeros_like(theta_d))
        th = th + (td_safe - td_safe.detach()) * inv  # value unchanged, exact implicit derivative
    return th, valid, iters


def _normalise_points(points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Unit directions ``[..., 3]`` ((0,0,1) where invalid), norms ``[...]`` (1 where invalid), validity."""
    finite = torch.isfinite(points).all(dim=-1)
    p = torch.where(finite[..., None], points, torch.zeros_like(points))
    m = p.abs().amax(dim=-1)
    valid = finite & (m > MIN_POINT_NORM)
    m_safe = torch.where(valid, m, torch.ones_like(m))
    q = p / m_safe[..., None]
    n2 = (q * q).sum(dim=-1)
    n = torch.sqrt(torch.where(valid, n2, torch.ones_like(n2)))
    d = q / n[..., None]
    axis = torch.zeros_like(d)
    axis[..., 2] = 1.0
    d = torch.where(valid[..., None], d, axis)
    return d, m_safe * n, valid


def _radial_terms(d: Tensor, k: tuple[float, ...], jacobian: bool):
    """Torch twin of ``kb._radial_terms``: ``theta, s, A, s_z, series`` for unit directions ``d [..., 3]``."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    r2 = x * x + y * y
    pos = r2 > 0
    r = torch.where(pos, torch.sqrt(torch.where(pos, r2, torch.ones_like(r2))), torch.zeros_like(r2))
    theta = torch.atan2(r, z)
    series = (z > 0) & (r <= SMALL_T * z)
    one = torch.ones_like(r)
    # direct branch (safe inputs where the series branch or r = 0 takes over)
    r_d = torch.where(series | ~pos, one, r)
    th_d = torch.where(series, one, theta)
    td = th_d * _poly(th_d * th_d, k)
    s_dir = td / r_d
    # series branch (safe inputs elsewhere)
    z_s = torch.where(series, z, one)
    q = torch.where(series, r2 / (z_s * z_s), torch.zeros_like(r2))
    a = 1.0 + q * (-1.0 / 3.0 + q * (1.0 / 5.0 + q * (-1.0 / 7.0 + q * (1.0 / 9.0))))
    w = q * a * a
    P = _poly(w, k)
    G = a * P
    s = torch.where(series, G / z_s, s_dir)
    A = s_z = None
    if jacobian:
        rho2 = r2 + z * z
        dtd = kb_dtheta_d(th_d, k)
        A_dir = (dtd * z / rho2 - td / r_d) / (r_d * r_d)
        sz_dir = -dtd / rho2
        da = -1.0 / 3.0 + q * (2.0 / 5.0 + q * (-3.0 / 7.0 + q * (4.0 / 9.0)))
        dG = da * P + a * _dpoly(w, k) * (a * a + 2.0 * q * a * da)
        A = torch.where(series, 2.0 * dG / (z_s * z_s * z_s), A_dir)
        s_z = torch.where(series, -(G + 2.0 * q * dG) / (z_s * z_s), sz_dir)
    return theta, s, A, s_z, series


def project(points_cam: Tensor, intr: "FisheyeIntrinsics") -> tuple[Tensor, Tensor]:
    """Project camera-frame points to fisheye pixels (differentiable).

    Args:
        points_cam: ``[..., 3]`` points in the OpenCV camera frame (any length unit).
        intr: fisheye intrinsics.

    Returns:
        ``uv [..., 2]`` pixels (same dtype/device; principal point where invalid) and ``valid [...]`` bool
        (finite, not at the camera centre, ``theta <= intr.theta_max``).
    """
    points_cam = _as_float_tensor(points_cam, "points_cam", 3)
    k = tuple(float(c) for c in intr.k)
    d, _, ok = _normalise_points(points_cam)
    theta, s, _, _, _ = _radial_terms(d, k, jacobian=False)
    valid = ok & (theta <= intr.theta_max + _theta_slack(d.dtype))
    u = torch.where(valid, intr.fx * s * d[..., 0] + intr.cx, torch.full_like(s, intr.cx))
    v = torch.where(valid, intr.fy * s * d[..., 1] + intr.cy, torch.full_like(s, intr.cy))
    return torch.stack([u, v], dim=-1), valid


def project_with_jacobian(points_cam: Tensor, intr: "FisheyeIntrinsics") -> tuple[Tensor, Tensor, Tensor]:
    """Fused :func:`project` + :func:`project_jacobian`: one normalisation and one evaluation of the radial
    terms (what an EWA splatter needs per Gaussian).

    Args:
        points_cam: Tensor,  # [..., 3] OpenCV camera frame

    Returns:
        uv: Tensor,  # [..., 2] pixels (principal point where invalid)
        J: Tensor,  # [..., 2, 3] d(u, v)/d(x, y, z), pixels per length unit (zeros where invalid)
        valid: Tensor,  # [...] bool
    """
    points_cam = _as_float_tensor(points_cam, "points_cam", 3)
    k = tuple(float(c) for c in intr.k)
    d, norm, ok = _normalise_points(points_cam)
    theta, s, A, s_z, series = _radial_terms(d, k, jacobian=True)
    valid = ok & (theta <= intr.theta_max + _theta_slack(d.dtype))
    x, y = d[..., 0], d[..., 1]
    r2 = x * x + y * y
    r2_safe = torch.where(r2 > 0, r2, torch.ones_like(r2))
    B = torch.where(series, A, A * r2)
    cxx = torch.where(series, x * x, x * x / r2_safe)
    cxy = torch.where(series, x * y, x * y / r2_safe)
    cyy = torch.where(series, y * y, y * y / r2_safe)
    fx, fy = intr.fx, intr.fy
    uv = torch.stack([fx * s * x + intr.cx, fy * s * y + intr.cy], dim=-1)
    uv = torch.where(valid[..., None], uv, uv.new_tensor([intr.cx, intr.cy]))
    row_u = torch.stack([fx * (s + cxx * B), fx * cxy * B, fx * x * s_z], dim=-1)
    row_v = torch.stack([fy * cxy * B, fy * (s + cyy * B), fy * y * s_z], dim=-1)
    J = torch.stack([row_u, row_v], dim=-2) / norm[..., None, None]
    J = torch.where(valid[..., None, None], J, torch.zeros_like(J))
    return uv, J, valid


def project_jacobian(points_cam: Tensor, intr: "FisheyeIntrinsics") -> tuple[Tensor, Tensor]:
    """Analytic ``d(u, v)/d(x, y, z)`` ``[..., 2, 3]`` (pixels per length unit; zeros where invalid) and
    ``valid [...]``; exact at ``r = 0`` and valid for ``z < 0``. Same formulas as the numpy version."""
    _, J, valid = project_with_jacobian(points_cam, intr)
    return J, valid


def unproject(
    uv: Tensor,
    intr: "FisheyeIntrinsics",
    n_iter: int | None = None,
    return_iterations: bool = False,
) -> tuple[Tensor, Tensor] | tuple[Tensor, Tensor, Tensor]:
    """Back-project pixels to unit rays (differentiable w.r.t. ``uv``).

    Args:
        uv: ``[..., 2]`` pixel coordinates (column, row; pixel centres at integers), float32/float64.
        intr: fisheye intrinsics.
        n_iter: fixed number of Newton updates (no host synchronisation, usable under ``torch.func.vmap`` /
            ``torch.compile``; 8 suffice away from the fold-over for float64, 5 for float32, ~60 reach the
            fold-over); ``None`` iterates to convergence (data-dependent loop).
        return_iterations: also return the per-pixel iteration count (int32).

    Returns:
        ``rays [..., 3]`` unit vectors in the OpenCV camera frame ((0, 0, 1) where invalid), ``valid [...]``
        bool (finite and ``theta_d <= intr.theta_d_max``), optionally ``iters [...]``.
    """
    uv = _as_float_tensor(uv, "uv", 2)
    k = tuple(float(c) for c in intr.k)
    slack = max(THETA_D_MAX_REL_SLACK, NEWTON_RESIDUAL_ULPS * float(torch.finfo(uv.dtype).eps))
    finite = torch.isfinite(uv).all(dim=-1)
    uv_safe = torch.where(finite[..., None], uv, torch.zeros_like(uv))
    xd = (uv_safe[..., 0] - intr.cx) / intr.fx
    yd = (uv_safe[..., 1] - intr.cy) / intr.fy
    pos = (xd != 0) | (yd != 0)
    one = torch.ones_like(xd)
    td = torch.where(pos, torch.hypot(torch.where(pos, xd, one), torch.where(pos, yd, one)), torch.zeros_like(xd))
    td = torch.where(finite, td, torch.full_like(td, float("inf")))
    td_max = float(kb_theta_d(torch.tensor(intr.theta_max, dtype=td.dtype), k))
    td = torch.where((td > td_max) & (td <= td_max * (1.0 + slack)), torch.full_like(td, td_max), td)
    theta, valid, iters = kb_inverse_theta(td, k, intr.theta_max, n_iter=n_iter)
    small = theta.abs() <= SMALL_THETA
    t2 = theta * theta
    ser = 1.0 + t2 * (-1.0 / 6.0 + t2 * (1.0 / 120.0 + t2 * (-1.0 / 5040.0)))
    th_safe = torch.where(small, torch.ones_like(theta), theta)
    sinc = torch.where(small, ser, torch.sin(th_safe) / th_safe)
    factor = sinc / _poly(t2, k)
    zero = torch.zeros_like(xd)
    xd, yd = torch.where(valid, xd, zero), torch.where(valid, yd, zero)
    rays = torch.stack([factor * xd, factor * yd, torch.cos(theta)], dim=-1)
    rays = rays / torch.sqrt((rays * rays).sum(dim=-1, keepdim=True))
    axis = torch.zeros_like(rays)
    axis[..., 2] = 1.0
    rays = torch.where(valid[..., None], rays, axis)
    if return_iterations:
        return rays, valid, iters
    return rays, valid
