"""Slow references of the splat stage (gsplat ``_torch_impl`` style: private, for tests and benchmarks only).

* :func:`_render_reference` mirrors :func:`umi_aug.splat.renderer.render` (the numba fast path) and
  :func:`_project_reference` its projection :func:`umi_aug.splat.project.project_gaussians`: a dense float64
  pure-torch renderer, described below.
* :func:`_ssim_map_reference` mirrors :func:`umi_aug.splat.losses.ssim_map` (explicit SSIM windows).

The dense float64 renderer:

Written for clarity, not speed: every Gaussian is evaluated at every pixel, composited front to back in the
order of ray distance (distance from the camera centre to the Gaussian's mean, ties by index), with the same
thresholds as the fast path (alpha = min(0.99, o exp(-q/2)), skip alpha < 1/255, stop before T < 1e-4).
Gradients come from plain torch autograd. Independent of the fast path where it matters:

* the projection Jacobian is obtained by autograd of :func:`umi_aug.camera.kb_torch.project` (not the analytic
  ``project_jacobian``), ``Sigma_cam = R_cw R S^2 R^T R_cw^T``, the conic by ``torch.linalg.inv``;
* no tiles, no bounding boxes (a Gaussian whose footprint misses the image simply contributes nothing), so the
  opacity-aware boxes and tile tests of the fast path are checked too;
* compositing by cumulative products over the sorted Gaussian axis.

Memory is ``O(pixels x Gaussians)`` per chunk of pixels; use it on small images / few Gaussians.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from umi_aug.camera import kb_torch
from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.geometry.se3_torch import quat_wxyz_to_matrix
from umi_aug.splat._constants import (
    ALPHA_THRESHOLD,
    DEFAULT_FAR,
    DEFAULT_FILTER,
    DEFAULT_NEAR,
    MAX_ALPHA,
    MIN_DET_2D_ABS,
    MIN_DET_2D_REL,
    TRANSMITTANCE_THRESHOLD,
)
from umi_aug.splat.gaussians import Gaussians
from umi_aug.splat.losses import SSIM_C1, SSIM_C2, SSIM_WINDOW, gaussian_window_1d
from umi_aug.splat.project import camera_from_pose, check_filter
from umi_aug.splat.renderer import RenderOutput, _background, _compose
from umi_aug.splat.sh import eval_sh, view_directions

Tensor = torch.Tensor

#: Relative band around a threshold inside which float32 and float64 may legitimately decide differently
#: (reported per pixel as ``meta["near_threshold"]``).
AMBIGUITY_BAND: float = 1e-4


def _autograd_jacobian(p: Tensor, intr: FisheyeIntrinsics) -> tuple[Tensor, Tensor]:
    """``uv [V, 2]`` and ``J = d uv / d p`` ``[V, 2, 3]`` by autograd (differentiable again: create_graph)."""
    graph = p.requires_grad and torch.is_grad_enabled()
    with torch.enable_grad():
        p_in = p if graph else p.detach().requires_grad_(True)
        uv, _ = kb_torch.project(p_in, intr)
        if uv.shape[0] == 0:
            return uv.detach(), p.new_zeros(0, 2, 3)
        ju = torch.autograd.grad(uv[:, 0].sum(), p_in, create_graph=graph, retain_graph=True)[0]
        jv = torch.autograd.grad(uv[:, 1].sum(), p_in, create_graph=graph)[0]
    J = torch.stack([ju, jv], dim=1)
    return (uv, J) if graph else (uv.detach(), J.detach())


def _project_reference(
    g: Gaussians, T_world_cam, intr: FisheyeIntrinsics, sh_degree: int, filter: str, near: float, far: float
) -> dict[str, Tensor]:
    """Reference of :func:`umi_aug.splat.project.project_gaussians` (float64): ids, means2d, conics [V, 2, 2],
    opacities, colors, depths, cov2d [V, 2, 2] of the Gaussians that pass the near/far, ray-angle, determinant and opacity culls."""
    dilation, compensate = check_filter(filter)
    R_cw, t_cw, campos = camera_from_pose(T_world_cam, torch.float64)
    with torch.no_grad():
        p_all = g.means.detach() @ R_cw.detach().T + t_cw.detach()
        d_all = torch.linalg.vector_norm(p_all, dim=-1)
        _, ok = kb_torch.project(p_all, intr)
        ids = torch.nonzero(ok & (d_all > near) & (d_all < far)).squeeze(-1)
    p = g.means[ids] @ R_cw.T + t_cw
    depth = torch.linalg.vector_norm(p, dim=-1)
    uv, J = _autograd_jacobian(p, intr)
    R = quat_wxyz_to_matrix(g.quats_wxyz[ids])
    S2 = torch.diag_embed(torch.exp(2.0 * g.log_scales[ids]))
    cov_world = R @ S2 @ R.transpose(-1, -2)
    cov_cam = R_cw @ cov_world @ R_cw.T
    cov0 = J @ cov_cam @ J.transpose(-1, -2)
    cov = cov0 + dilation * torch.eye(2, dtype=cov0.dtype)
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0]
    half_tr = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    ok_det = (det > MIN_DET_2D_ABS) & (det > MIN_DET_2D_REL * half_tr * half_tr)
    eye = torch.eye(2, dtype=cov.dtype).expand_as(cov)
    conic = torch.linalg.inv(torch.where(ok_det[:, None, None], cov, eye))
    op = torch.sigmoid(g.logit_opacities[ids])
    if compensate:
        det0 = torch.clamp_min(cov0[:, 0, 0] * cov0[:, 1, 1] - cov0[:, 0, 1] * cov0[:, 1, 0], 0.0)
        pos = ok_det & (det0 > 0)
        op = torch.where(pos, op * torch.sqrt(torch.where(pos, det0 / torch.where(ok_det, det, 1.0), 1.0)), 0.0 * op)
    keep = ok_det & (op >= ALPHA_THRESHOLD)
    dirs = view_directions(g.means[ids], campos)
    colors = torch.clamp_min(eval_sh(sh_degree, g.sh[ids], dirs) + 0.5, 0.0)
    k = torch.nonzero(keep).squeeze(-1)
    return {
        "ids": ids[k], "means2d": uv[k], "conics": conic[k], "opacities": op[k], "colors": colors[k],
        "depths": depth[k], "cov2d": cov[k],
    }


def _render_reference(
    gaussians: Gaussians,
    T_world_cam: Tensor | np.ndarray,  # [4, 4]
    intr: FisheyeIntrinsics,
    background: Tensor | np.ndarray | Sequence[float] | None = None,
    sh_degree: int | None = None,
    *,
    filter: str = DEFAULT_FILTER,
    near: float = DEFAULT_NEAR,
    far: float = DEFAULT_FAR,
    pixel_chunk: int | None = None,
    min_transmittance: float = TRANSMITTANCE_THRESHOLD,
) -> RenderOutput:
    """Reference of :func:`umi_aug.splat.render`: dense float64 render with its semantics (differentiable by autograd).

    ``meta["near_threshold"]`` ([H, W] bool) marks pixels where a (Gaussian, pixel) alpha lies within
    ``AMBIGUITY_BAND`` (relative) of ``ALPHA_THRESHOLD`` or a transmittance within it of ``min_transmittance``
    (early termination, default ``TRANSMITTANCE_THRESHOLD``): there a float32 renderer may legitimately take the
    other branch.
    """
    g = gaussians.to(torch.float64)
    H, W = intr.height, intr.width
    deg = g.sh_degree if sh_degree is None else min(int(sh_degree), g.sh_degree)
    bg = _background(background, torch.float64, H, W)
    proj = _project_reference(g, T_world_cam, intr, deg, filter, near, far)
    order = torch.sort(proj["depths"].detach(), stable=True).indices
    mu = proj["means2d"][order]
    conic = proj["conics"][order]
    op = proj["opacities"][order]
    col = proj["colors"][order]
    dep = proj["depths"][order]
    V = mu.shape[0]
    vv, uu = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    pix = torch.stack([uu.reshape(-1), vv.reshape(-1)], dim=-1)  # [P, 2] (u, v)
    P = pix.shape[0]
    chunk = pixel_chunk or max(1, min(P, 4_000_000 // max(V, 1)))
    rgb_parts, d_parts, t_parts, amb_parts = [], [], [], []
    for s in range(0, P, chunk):
        px = pix[s : s + chunk]
        d = px[:, None, :] - mu[None, :, :]  # [p, V, 2]
        q = (
            conic[None, :, 0, 0] * d[..., 0] * d[..., 0]
            + 2.0 * conic[None, :, 0, 1] * d[..., 0] * d[..., 1]
            + conic[None, :, 1, 1] * d[..., 1] * d[..., 1]
        )
        power = -0.5 * q
        raw = op[None, :] * torch.exp(power)
        alpha = torch.clamp(raw, max=MAX_ALPHA)
        skip = (alpha < ALPHA_THRESHOLD) | (power > 0)
        alpha = torch.where(skip, torch.zeros_like(alpha), alpha)
        T_incl = torch.cumprod(1.0 - alpha, dim=1)
        alive = T_incl >= min_transmittance
        alpha = torch.where(alive, alpha, torch.zeros_like(alpha))
        one_minus = 1.0 - alpha
        T_excl = torch.cat([torch.ones_like(one_minus[:, :1]), torch.cumprod(one_minus, dim=1)[:, :-1]], dim=1)
        w = alpha * T_excl
        rgb_parts.append(w @ col)
        d_parts.append(w @ dep)
        t_parts.append(torch.prod(one_minus, dim=1))
        with torch.no_grad():
            near_a = ((raw / ALPHA_THRESHOLD - 1.0).abs() < AMBIGUITY_BAND).any(dim=1)
            near_t = ((T_incl / min_transmittance - 1.0).abs() < AMBIGUITY_BAND).any(dim=1)
            amb_parts.append(near_a | near_t)
    rgb_acc = torch.cat(rgb_parts).reshape(H, W, 3)
    depth_acc = torch.cat(d_parts).reshape(H, W)
    T = torch.cat(t_parts).reshape(H, W)
    rgb, alpha_img, ray_depth = _compose(rgb_acc, depth_acc, T, bg)
    meta = {
        "ids": proj["ids"][order],
        "n_visible": V,
        "near_threshold": torch.cat(amb_parts).reshape(H, W),
        "projected": proj,
    }
    return RenderOutput(rgb=rgb, alpha=alpha_img, ray_depth=ray_depth, meta=meta)


def _ssim_map_reference(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Reference of :func:`umi_aug.splat.losses.ssim_map`: direct float64 SSIM ``[H, W, 3]``: for every pixel and
    channel, explicit weighted means, variances and covariance over the 11x11 window (pixels outside the image count
    as 0, like zero padding). Slow; tests only."""
    x = np.asarray(pred, dtype=np.float64)
    y = np.asarray(target, dtype=np.float64)
    H, W, C = x.shape
    g = gaussian_window_1d(dtype=torch.float64).numpy()
    win = np.outer(g, g)
    r = SSIM_WINDOW // 2
    xp = np.pad(x, ((r, r), (r, r), (0, 0)))
    yp = np.pad(y, ((r, r), (r, r), (0, 0)))
    out = np.empty_like(x)
    for i in range(H):
        for j in range(W):
            for c in range(C):
                a = xp[i : i + 2 * r + 1, j : j + 2 * r + 1, c]
                b = yp[i : i + 2 * r + 1, j : j + 2 * r + 1, c]
                mx, my = (win * a).sum(), (win * b).sum()
                vx = (win * a * a).sum() - mx * mx
                vy = (win * b * b).sum() - my * my
                cxy = (win * a * b).sum() - mx * my
                out[i, j, c] = ((2 * mx * my + SSIM_C1) * (2 * cxy + SSIM_C2)) / (
                    (mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2))
    return out
