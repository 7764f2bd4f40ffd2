"""Real spherical harmonics up to degree 3 (the 3DGS colour model), in torch.

Colour of a Gaussian seen along the unit direction ``d`` (world frame, from the camera centre to the Gaussian's
mean): ``rgb = max(0, sum_k Y_k(d) * sh[k] + 0.5)`` with the INRIA constants and sign convention
(``utils/sh_utils.py``; gsplat ``_spherical_harmonics``). ``sh[0]`` is the DC term (``f_dc`` in the PLY).
"""

from __future__ import annotations

import torch

from umi_aug.errors import SplatError
from umi_aug.splat._constants import MAX_SH_DEGREE, SH_C0, SH_C1, SH_C2, SH_C3, SH_COEFFS

__all__ = ["sh_basis", "eval_sh", "sh_to_rgb", "rgb_to_sh", "num_sh_coeffs", "view_directions"]

Tensor = torch.Tensor


def num_sh_coeffs(degree: int) -> int:
    """``(degree + 1)^2`` coefficients per colour channel."""
    if not 0 <= int(degree) <= MAX_SH_DEGREE:
        raise SplatError(f"SH degree must be in [0, {MAX_SH_DEGREE}], got {degree!r}")
    return SH_COEFFS[int(degree)]


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Real SH basis ``Y_k(d)`` for ``k < (degree+1)^2``.

    Args:
        degree: 0..3.
        dirs: Tensor,  # [..., 3] unit directions (world frame)
    Returns:
        Tensor,  # [..., (degree+1)^2]
    """
    num_sh_coeffs(degree)
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, sh: Tensor, dirs: Tensor) -> Tensor:
    """Raw SH colour ``sum_k Y_k(d) sh[k]`` (no +0.5 offset, no clamp).

    Args:
        degree: degree to evaluate (uses the first ``(degree+1)^2`` coefficients of ``sh``).
        sh: Tensor,  # [..., K, 3] with K >= (degree+1)^2
        dirs: Tensor,  # [..., 3] unit view directions (camera centre -> Gaussian, world frame)
    Returns:
        Tensor,  # [..., 3]
    """
    k = num_sh_coeffs(degree)
    if sh.shape[-2] < k:
        raise SplatError(f"eval_sh: degree {degree} needs {k} SH coefficients, got {sh.shape[-2]}")
    basis = sh_basis(degree, dirs)
    return (basis[..., None] * sh[..., :k, :]).sum(dim=-2)


def view_directions(means: Tensor, cam_center: Tensor) -> Tensor:
    """Unit directions from the camera centre to each mean (world frame); ``(0, 0, 1)`` for a mean at the
    centre (finite gradient there).

    Args:
        means: Tensor,  # [N, 3] world, metres
        cam_center: Tensor,  # [3] world, metres
    Returns:
        Tensor,  # [N, 3]
    """
    v = means - cam_center
    n2 = (v * v).sum(-1, keepdim=True)
    pos = n2 > 0
    n = torch.sqrt(torch.where(pos, n2, torch.ones_like(n2)))
    d = v / n
    axis = torch.zeros_like(d)
    axis[..., 2] = 1.0
    return torch.where(pos, d, axis)


def sh_to_rgb(sh_colour: Tensor) -> Tensor:
    """``max(0, sh_colour + 0.5)`` (3DGS convention)."""
    return torch.clamp_min(sh_colour + 0.5, 0.0)


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """DC coefficient that renders ``rgb`` (``(rgb - 0.5) / C0``)."""
    return (rgb - 0.5) / SH_C0
