"""Differentiable EWA projection of 3D Gaussians through the full Kannala–Brandt fisheye model (torch).

For a Gaussian with mean ``mu`` (world), rotation ``R`` and scales ``s``, seen from ``T_world_cam``:

* ``p = R_cw mu + t_cw`` (OpenCV camera frame); ``ray_depth = |p|`` (distance along the ray, not z: Gaussians
  beyond 90 deg, z < 0, are ordered and rendered like any other);
* ``(u, v) = KB(p)`` and ``J = dKB/dp`` [2, 3] including the distortion ``k1..k4``
  (:func:`umi_aug.camera.kb_torch.project_jacobian`, exact on the optical axis, finite past 90 deg);
* ``Sigma_2D = (J R_cw R S)(J R_cw R S)^T + lambda I`` with the filter ``lambda`` (``"inria"`` 0.3 px^2,
  ``"mip"`` 0.1 px^2 with opacity compensation ``sqrt(det Sigma / det(Sigma + lambda I))``, ``"none"``);
  ``det`` by Cauchy–Binet (sum of squared 2x2 minors of ``J R_cw R S``: never negative, exact for needles);
* colour from SH along the world direction camera centre -> mean, ``max(0, SH + 0.5)``.

Culling (a culled Gaussian gets exactly zero gradient, never NaN): centre inside the near sphere or beyond
``far``; ray angle beyond ``intr.theta_max`` (KB fold-over / lens limit: the mean falls outside the image
circle); near-singular ``Sigma_2D``; opacity below the alpha threshold (no pixel can reach it); opacity-aware
bounding box (``d^T Sigma^-1 d <= 2 ln(255 o)``) outside the image.

Two implementations with the same outputs: :func:`project_gaussians` with ``fast=False`` is the torch-autograd
reference (differentiable w.r.t. the pose too); ``fast=True`` runs :class:`ProjectGaussians`, a
``torch.autograd.Function`` with a numba forward and a hand-written numba backward
(:mod:`umi_aug.splat._project_kernels`, float64 inside; no pose gradient, so a pose that requires grad falls back
to the reference). The inference path runs the same formulas in numba
(:func:`umi_aug.splat._kernels.project_kernel`); the reference renderer in :mod:`umi_aug.splat._torch_impl` uses
an autograd Jacobian instead of the analytic one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from umi_aug.camera import kb_torch
from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import SplatError
from umi_aug.geometry.se3_torch import quat_wxyz_to_matrix
from umi_aug.splat import _project_kernels as PK
from umi_aug.splat._constants import (
    ALPHA_THRESHOLD,
    BBOX_MARGIN_PX,
    BBOX_MARGIN_REL,
    DEFAULT_FAR,
    DEFAULT_NEAR,
    FILTER_COMPENSATED,
    FILTER_DILATION,
    LOG_INV_ALPHA_THRESHOLD,
    MIN_DET_2D_ABS,
    MIN_DET_2D_REL,
)
from umi_aug.splat.gaussians import Gaussians
from umi_aug.splat.sh import eval_sh, view_directions

__all__ = ["Projected", "ProjectGaussians", "project_gaussians", "camera_from_pose", "check_filter"]

Tensor = torch.Tensor


def check_filter(filter: str) -> tuple[float, bool]:
    """``(dilation px^2, compensate)`` of a filter name; raises :class:`SplatError` for an unknown one."""
    if filter not in FILTER_DILATION:
        raise SplatError(f"unknown filter {filter!r}; expected one of {sorted(FILTER_DILATION)}")
    return FILTER_DILATION[filter], filter in FILTER_COMPENSATED


def camera_from_pose(T_world_cam, dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor]:
    """``R_cw [3, 3]``, ``t_cw [3]`` and the camera centre ``[3]`` (world) from ``T_world_cam [4, 4]``.

    Raises:
        SplatError: wrong shape or non-finite pose.
    """
    T = torch.as_tensor(T_world_cam)
    if T.shape != (4, 4):
        raise SplatError(f"T_world_cam must have shape [4, 4], got {list(T.shape)}")
    T = T.to(dtype)
    if not bool(torch.isfinite(T.detach()).all()):
        raise SplatError(f"T_world_cam has non-finite entries: {T.detach().tolist()}")
    R_wc = T[:3, :3]
    t_wc = T[:3, 3]
    R_cw = R_wc.transpose(0, 1)
    return R_cw, -(R_cw @ t_wc), t_wc


def _kb_project_with_jacobian(p: Tensor, intr: FisheyeIntrinsics) -> tuple[Tensor, Tensor]:
    """Projection and its Jacobian for points already known to be valid (:func:`kb_torch.project_with_jacobian`:
    one normalisation and one evaluation of the radial terms; exact on the optical axis).

    Args:
        p: Tensor,  # [V, 3] camera frame
    Returns:
        uv: Tensor,  # [V, 2] pixels
        J: Tensor,  # [V, 2, 3] d(u, v)/d(x, y, z), pixels per metre
    """
    uv, J, _ = kb_torch.project_with_jacobian(p, intr)
    return uv, J


@dataclass
class Projected:
    """Visible Gaussians after projection (all tensors ``[V, ...]``, differentiable where the inputs are).

    Attributes:
        ids: Tensor,  # [V] int64 rows of the input Gaussians
        means2d: Tensor,  # [V, 2] pixels (u, v), pixel centres at integers
        conics: Tensor,  # [V, 3] (a, b, c) of Sigma_2D^-1 = [[a, b], [b, c]], 1/px^2
        opacities: Tensor,  # [V] sigmoid(logit) x compensation
        colors: Tensor,  # [V, 3] RGB (SH, clamped at 0)
        depths: Tensor,  # [V] ray distance to the mean, metres
        cov2d: Tensor,  # [V, 3] (xx, xy, yy) of Sigma_2D incl. the filter, px^2
    """

    ids: Tensor
    means2d: Tensor
    conics: Tensor
    opacities: Tensor
    colors: Tensor
    depths: Tensor
    cov2d: Tensor

    def __len__(self) -> int:
        return int(self.ids.shape[0])


def project_gaussians(
    gaussians: Gaussians,
    T_world_cam: Tensor | np.ndarray,  # [4, 4] camera pose, metres
    intr: FisheyeIntrinsics,
    sh_degree: int | None = None,
    filter: str = "inria",
    near: float = DEFAULT_NEAR,
    far: float = DEFAULT_FAR,
    *,
    fast: bool = False,
    timings: dict[str, float] | None = None,
) -> Projected:
    """Project, cull and shade the Gaussians (differentiable w.r.t. every Gaussian parameter and the pose).

    Args:
        gaussians: the scene (any float dtype; the computation runs in that dtype).
        T_world_cam: camera pose ``[4, 4]`` (``p_world = T_world_cam @ p_cam``, OpenCV camera frame).
        intr: KB fisheye intrinsics (image size included).
        sh_degree: SH degree to evaluate (default and maximum: the scene's).
        filter: ``"inria"`` | ``"mip"`` | ``"none"`` (see module docstring).
        near, far: culling sphere radii around the camera centre, metres.
        fast: numba forward + hand-written backward (:class:`ProjectGaussians`) unless the pose requires grad;
            False: the torch-autograd reference.
        timings: with ``fast``, ``timings["project_backward"]`` receives the backward's seconds.

    Returns:
        :class:`Projected` for the visible Gaussians.
    """
    dilation, compensate = check_filter(filter)
    g = gaussians
    deg = g.sh_degree if sh_degree is None else min(int(sh_degree), g.sh_degree)
    dt = g.dtype
    if fast and not torch.as_tensor(T_world_cam).requires_grad and dt in (torch.float32, torch.float64):
        return _project_fast(g, T_world_cam, intr, deg, dilation, compensate, near, far, timings)
    R_cw, t_cw, campos = camera_from_pose(T_world_cam, dt)

    # cheap detached pre-cull (near/far sphere, ray angle) so the differentiable part only sees safe inputs
    with torch.no_grad():
        p_all = g.means.detach() @ R_cw.detach().T + t_cw.detach()
        d_all = torch.linalg.vector_norm(p_all, dim=-1)
        _, ok_proj = kb_torch.project(p_all, intr)
        pre = ok_proj & (d_all > near) & (d_all < far) & torch.isfinite(d_all)
        ids0 = torch.nonzero(pre).squeeze(-1)

    sel = lambda t: t.index_select(0, ids0)  # noqa: E731  (backward = index_add, cheaper than index_put)
    means = sel(g.means)
    p = means @ R_cw.T + t_cw
    depth = torch.sqrt((p * p).sum(-1))
    uv, J = _kb_project_with_jacobian(p, intr)  # [V, 2], [V, 2, 3]
    R = quat_wxyz_to_matrix(sel(g.quats_wxyz))  # [V, 3, 3]
    s = torch.exp(sel(g.log_scales))
    M = (R_cw @ R) * s[:, None, :]  # columns scaled: R_cw R diag(s)
    JM = J @ M  # [V, 2, 3]
    A, B = JM[:, 0, :], JM[:, 1, :]
    sxx0 = (A * A).sum(-1)
    sxy = (A * B).sum(-1)
    syy0 = (B * B).sum(-1)
    m01 = A[:, 0] * B[:, 1] - A[:, 1] * B[:, 0]
    m02 = A[:, 0] * B[:, 2] - A[:, 2] * B[:, 0]
    m12 = A[:, 1] * B[:, 2] - A[:, 2] * B[:, 1]
    det0 = m01 * m01 + m02 * m02 + m12 * m12
    sxx = sxx0 + dilation
    syy = syy0 + dilation
    det = det0 + dilation * (sxx0 + syy0) + dilation * dilation
    half_tr = 0.5 * (sxx + syy)
    ok = (det > MIN_DET_2D_ABS) & (det > MIN_DET_2D_REL * half_tr * half_tr) & torch.isfinite(det)
    det_safe = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([syy / det_safe, -sxy / det_safe, sxx / det_safe], dim=-1)
    op = torch.sigmoid(sel(g.logit_opacities))
    if compensate:
        pos = ok & (det0 > 0)
        ratio = torch.where(pos, det0 / det_safe, torch.ones_like(det0))
        op = torch.where(pos, op * torch.sqrt(ratio), torch.zeros_like(op))
    ok = ok & (op >= ALPHA_THRESHOLD)
    with torch.no_grad():  # opacity-aware bounding box inside the image?
        lim = 2.0 * (torch.log(torch.where(ok, op, torch.ones_like(op))) + LOG_INV_ALPHA_THRESHOLD)
        hx = torch.sqrt(torch.clamp_min(lim * sxx, 0)) * (1 + BBOX_MARGIN_REL) + BBOX_MARGIN_PX
        hy = torch.sqrt(torch.clamp_min(lim * syy, 0)) * (1 + BBOX_MARGIN_REL) + BBOX_MARGIN_PX
        u, v = uv[:, 0].detach(), uv[:, 1].detach()
        inside = (u + hx >= 0) & (u - hx <= intr.width - 1) & (v + hy >= 0) & (v - hy <= intr.height - 1)
        keep = torch.nonzero(ok & inside).squeeze(-1)
    ids = ids0.index_select(0, keep)
    kp = lambda t: t.index_select(0, keep)  # noqa: E731
    dirs = view_directions(kp(means), campos)
    sh = torch.cat([g.sh0.index_select(0, ids)[:, None, :], g.sh_rest.index_select(0, ids)], dim=1)
    colors = torch.clamp_min(eval_sh(deg, sh, dirs) + 0.5, 0.0)
    return Projected(
        ids=ids,
        means2d=kp(uv),
        conics=kp(conics),
        opacities=kp(op),
        colors=colors,
        depths=kp(depth),
        cov2d=kp(torch.stack([sxx, sxy, syy], dim=-1)),
    )


@dataclass
class _Setup:
    """Camera and settings of one :class:`ProjectGaussians` call (float64 numpy)."""

    R_cw: np.ndarray  # [3, 3]
    t_cw: np.ndarray  # [3]
    campos: np.ndarray  # [3] camera centre, world
    cam: np.ndarray  # [9] fx, fy, cx, cy, k1..k4, theta_max
    sh_degree: int
    near: float
    far: float
    dilation: float
    compensate: bool
    theta_slack: float
    width: int
    height: int
    timings: dict[str, float] | None


def _np(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy())


def _gather_visible_numpy(out: np.ndarray, ids: np.ndarray, dtype) -> list[np.ndarray]:
    """:func:`umi_aug.splat._project_kernels.gather_visible_kernel` in numpy (what the forward did before it; the
    reference of ``tests/splat/test_project_fast.py``): the six output column groups of rows ``ids``."""
    vis = out[ids]
    return [vis[:, a:b].astype(dtype) if b - a > 1 else vis[:, a].astype(dtype) for a, b in ProjectGaussians.COLUMNS]


def _grad_views(grads: Sequence[Tensor | None], V: int, dtype) -> list[np.ndarray]:
    """The output gradients as ``[V, w]`` numpy views (no copy; ``[0, w]`` for one that is None)."""
    return [np.empty((0, b - a), dtype=dtype) if g is None else g.detach().cpu().numpy().reshape(V, b - a)
            for g, (a, b) in zip(grads, ProjectGaussians.COLUMNS)]


def _grad_out(grads: Sequence[Tensor | None], V: int, dtype) -> np.ndarray:
    """``[V, PROJ_COLS]`` float64: the six output gradients where :func:`PK.project_bwd_kernel` reads them
    (:func:`PK.gather_grad_out_kernel`; reference :func:`_grad_out_reference`)."""
    out = np.empty((V, PK.PROJ_COLS), dtype=np.float64)
    PK.gather_grad_out_kernel(*_grad_views(grads, V, dtype), out)
    return out


def _grad_out_reference(grads: Sequence[Tensor | None], V: int) -> np.ndarray:
    """:func:`_grad_out` in numpy (what the backward did before the kernel; ``tests/splat/test_project_fast.py``)."""
    out = np.zeros((V, PK.PROJ_COLS), dtype=np.float64)
    for g, (a, b) in zip(grads, ProjectGaussians.COLUMNS):
        if g is not None:
            out[:, a:b] = g.detach().cpu().numpy().reshape(V, b - a)
    return out


class ProjectGaussians(torch.autograd.Function):
    """:func:`project_gaussians` as numba kernels: ``forward(means, log_scales, quats_wxyz, logit_opacities, sh0,
    sh_rest, setup)`` returns ``(means2d [V, 2], conics [V, 3], opacities [V], colors [V, 3], depths [V],
    cov2d [V, 3], ids [V])`` — the column groups of :mod:`umi_aug.splat._project_kernels` as separate tensors in the
    scene's dtype (computed in float64), so that autograd hands their gradients straight to :meth:`backward`
    (slices of one output tensor cost a zero-filled full-size gradient each). The backward recomputes the visible
    Gaussians and writes the gradients of all six parameters (zero for culled rows)."""

    #: Output column ranges (start, stop) of the six differentiable outputs in ``PK.PROJ_COLS``.
    COLUMNS = ((0, 2), (2, 5), (5, 6), (6, 9), (9, 10), (10, 13))

    @staticmethod
    def forward(ctx, means, log_scales, quats, logit_op, sh0, sh_rest, setup: _Setup):
        arrs = [_np(t) for t in (means, log_scales, quats, logit_op, sh0, sh_rest)]
        n = arrs[0].shape[0]
        out = np.empty((n, PK.PROJ_COLS), dtype=np.float64)
        valid = np.empty(n, dtype=np.bool_)
        PK.project_fwd_kernel(
            *arrs, setup.sh_degree, setup.R_cw, setup.t_cw, setup.campos, setup.cam, setup.near, setup.far,
            setup.dilation, setup.compensate, setup.theta_slack, setup.width, setup.height, out, valid,
        )
        ids = np.flatnonzero(valid)
        ctx.save_for_backward(means, log_scales, quats, logit_op, sh0, sh_rest)
        ctx.setup, ctx.ids = setup, ids
        ids_t = torch.from_numpy(ids)
        ctx.mark_non_differentiable(ids_t)
        np_dt = np.float64 if means.dtype == torch.float64 else np.float32
        parts = [np.empty((ids.size, b - a) if b - a > 1 else ids.size, dtype=np_dt)
                 for a, b in ProjectGaussians.COLUMNS]  # each its own contiguous array
        PK.gather_visible_kernel(out, ids, *parts)
        return (*(torch.from_numpy(x) for x in parts), ids_t)

    @staticmethod
    def backward(ctx, *grads_out):
        t0 = time.perf_counter()
        su = ctx.setup
        tensors = ctx.saved_tensors
        arrs = [_np(t) for t in tensors]
        grads = [np.zeros(a.shape, dtype=a.dtype) for a in arrs]
        if any(g is not None for g in grads_out[:-1]) and ctx.ids.size:
            g_out = _grad_out(grads_out[:-1], ctx.ids.size, arrs[0].dtype)
            PK.project_bwd_kernel(
                ctx.ids, *arrs, su.sh_degree, su.R_cw, su.t_cw, su.campos, su.cam, su.dilation, su.compensate,
                g_out, *grads,
            )
        if su.timings is not None:
            su.timings["project_backward"] = su.timings.get("project_backward", 0.0) + time.perf_counter() - t0
        return (*(torch.from_numpy(x) for x in grads), None)


def _project_fast(g: Gaussians, T_world_cam, intr: FisheyeIntrinsics, deg: int, dilation: float, compensate: bool,
                  near: float, far: float, timings: dict[str, float] | None) -> Projected:
    """:class:`Projected` from :class:`ProjectGaussians` (the fast path of :func:`project_gaussians`)."""
    R_cw, t_cw, campos = (x.detach().numpy() for x in camera_from_pose(torch.as_tensor(T_world_cam).detach(),
                                                                         torch.float64))
    cam = np.array([intr.fx, intr.fy, intr.cx, intr.cy, *intr.k, intr.theta_max], dtype=np.float64)
    setup = _Setup(np.ascontiguousarray(R_cw), np.ascontiguousarray(t_cw), np.ascontiguousarray(campos), cam,
                   int(deg), float(near), float(far), float(dilation), bool(compensate),
                   kb_torch._theta_slack(g.dtype), intr.width, intr.height, timings)
    means2d, conics, opacities, colors, depths, cov2d, ids = ProjectGaussians.apply(
        g.means, g.log_scales, g.quats_wxyz, g.logit_opacities, g.sh0, g.sh_rest, setup)
    return Projected(ids=ids, means2d=means2d, conics=conics, opacities=opacities, colors=colors, depths=depths,
                     cov2d=cov2d)
