"""SO(3) in torch: batched, dtype-preserving (float32/float64), autograd-safe mirror of :mod:`.so3`.

Branches are selected with the double-``torch.where`` trick (the unused branch only ever sees safe values), so
gradients are finite at exactly θ = 0 and near/at θ = π. Thresholds: :mod:`umi_aug.geometry._constants`.
No value-dependent validation (only shape checks), so these functions are safe inside hot loops and on GPU.
"""

from __future__ import annotations

import torch

from umi_aug.geometry._constants import EXP_TAYLOR_ANGLE, LOG_PI_BRANCH_COS, LOG_TAYLOR_SIN
from umi_aug.geometry._torch_checks import as_tensor, jac_threshold, safe_norm

__all__ = [
    "hat",
    "vee",
    "so3_exp",
    "so3_log",
    "rotation_geodesic_distance",
    "so3_left_jacobian",
    "so3_left_jacobian_inv",
]


def _hat(v: torch.Tensor) -> torch.Tensor:
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(v.shape[:-1] + (3, 3))


def _vee(M: torch.Tensor) -> torch.Tensor:
    return 0.5 * torch.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], dim=-1
    )


def hat(v: torch.Tensor) -> torch.Tensor:
    """Skew matrix, ``hat(v) @ p == cross(v, p)``.

    Args:
        v: Tensor,  # [..., 3]
    Returns:
        Tensor,  # [..., 3, 3]
    """
    return _hat(as_tensor(v, "v", "hat", (3,)))


def vee(M: torch.Tensor) -> torch.Tensor:
    """Vector of the skew part ``(M − Mᵀ)/2``.

    Args:
        M: Tensor,  # [..., 3, 3]
    Returns:
        Tensor,  # [..., 3]
    """
    return _vee(as_tensor(M, "M", "vee", (3, 3)))


def _theta2_split(theta2: torch.Tensor, threshold: float) -> tuple[torch.Tensor, torch.Tensor]:
    small = theta2 < threshold * threshold
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    return small, theta


def _exp_coeffs(theta2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    small, th = _theta2_split(theta2, EXP_TAYLOR_ANGLE)
    a = torch.where(small, 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0, torch.sin(th) / th)
    h = 0.5 * th
    sh = torch.sin(h) / h
    b = torch.where(small, 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0, 0.5 * sh * sh)
    return a, b


def _eye(like: torch.Tensor) -> torch.Tensor:
    return torch.eye(3, dtype=like.dtype, device=like.device)


def _so3_exp(rotvec: torch.Tensor) -> torch.Tensor:
    a, b = _exp_coeffs((rotvec * rotvec).sum(-1))
    K = _hat(rotvec)
    return _eye(rotvec) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def so3_exp(rotvec: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of a rotation vector (Rodrigues); ``d R / d rotvec_i`` at 0 is ``hat(e_i)``.

    Args:
        rotvec: Tensor,  # [..., 3] radians
    Returns:
        R: Tensor,  # [..., 3, 3]
    """
    return _so3_exp(as_tensor(rotvec, "rotvec", "so3_exp", (3,)))


def _so3_log(R: torch.Tensor) -> torch.Tensor:
    w = _vee(R)
    s, _ = safe_norm(w)
    s2 = (w * w).sum(-1)
    c = 0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0)
    theta = torch.atan2(s, c)
    small = s < LOG_TAYLOR_SIN
    s_div = torch.where(small, torch.ones_like(s), s)
    ratio = torch.where(small, 1.0 + s2 / 6.0 + 0.075 * s2 * s2, theta / s_div)
    generic = w * ratio[..., None]
    # near π: axis from the symmetric part (1 − c) n nᵀ, largest diagonal column; sign from the skew part.
    B = 0.5 * (R + R.transpose(-1, -2)) - c[..., None, None] * _eye(R)
    i = torch.diagonal(B, dim1=-2, dim2=-1).argmax(-1)
    col = torch.gather(B, -1, i[..., None, None].expand(B.shape[:-1] + (1,)))[..., 0]
    cn, cpos = safe_norm(col, 1e-12)
    n = col / torch.where(cpos, cn, torch.ones_like(cn))[..., None]
    sign = torch.where((n * w).sum(-1) < 0, -torch.ones_like(s), torch.ones_like(s))
    near_pi = n * (sign * theta)[..., None]
    return torch.where((c < LOG_PI_BRANCH_COS)[..., None], near_pi, generic)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vector of a rotation matrix, angle in [0, π] (same branches as the numpy version).

    Args:
        R: Tensor,  # [..., 3, 3]
    Returns:
        rotvec: Tensor,  # [..., 3] radians
    """
    return _so3_log(as_tensor(R, "R", "so3_log", (3, 3)))


def rotation_geodesic_distance(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Angle of ``R1ᵀ R2`` in [0, π] via atan2 (gradient 0 where R1 == R2).

    Args:
        R1: Tensor,  # [..., 3, 3]
        R2: Tensor,  # [..., 3, 3] (batch broadcasts)
    Returns:
        Tensor,  # [...] radians
    """
    R1 = as_tensor(R1, "R1", "rotation_geodesic_distance", (3, 3))
    R2 = as_tensor(R2, "R2", "rotation_geodesic_distance", (3, 3))
    Rrel = R1.transpose(-1, -2) @ R2
    s, _ = safe_norm(_vee(Rrel))
    c = 0.5 * (Rrel[..., 0, 0] + Rrel[..., 1, 1] + Rrel[..., 2, 2] - 1.0)
    return torch.atan2(s, c)


def _jac_c(theta2: torch.Tensor) -> torch.Tensor:
    small, th = _theta2_split(theta2, jac_threshold(theta2.dtype))
    t2 = theta2
    series = 1 / 6 - t2 / 120 * (1 - t2 / 42 * (1 - t2 / 72 * (1 - t2 / 110)))
    return torch.where(small, series, (th - torch.sin(th)) / (th * th * th))


def _jac_inv_d(theta2: torch.Tensor) -> torch.Tensor:
    small, th = _theta2_split(theta2, jac_threshold(theta2.dtype))
    t2 = theta2
    series = 1 / 12 + t2 / 720 + t2 * t2 / 30240 + t2**3 / 1209600 + t2**4 / 47900160
    h = 0.5 * th
    return torch.where(small, series, 1.0 / (th * th) - torch.cos(h) / (2.0 * th * torch.sin(h)))


def _left_jacobian(phi: torch.Tensor) -> torch.Tensor:
    theta2 = (phi * phi).sum(-1)
    _, b = _exp_coeffs(theta2)
    K = _hat(phi)
    return _eye(phi) + b[..., None, None] * K + _jac_c(theta2)[..., None, None] * (K @ K)


def _left_jacobian_inv(phi: torch.Tensor) -> torch.Tensor:
    theta2 = (phi * phi).sum(-1)
    K = _hat(phi)
    return _eye(phi) - 0.5 * K + _jac_inv_d(theta2)[..., None, None] * (K @ K)


def so3_left_jacobian(phi: torch.Tensor) -> torch.Tensor:
    """Left Jacobian of SO(3) (see numpy :func:`umi_aug.geometry.so3_left_jacobian`).

    Args:
        phi: Tensor,  # [..., 3] radians
    Returns:
        Tensor,  # [..., 3, 3]
    """
    return _left_jacobian(as_tensor(phi, "phi", "so3_left_jacobian", (3,)))


def so3_left_jacobian_inv(phi: torch.Tensor) -> torch.Tensor:
    """Inverse left Jacobian; valid for angles < 2π (not checked: no value branching in torch).

    Args:
        phi: Tensor,  # [..., 3] radians
    Returns:
        Tensor,  # [..., 3, 3]
    """
    return _left_jacobian_inv(as_tensor(phi, "phi", "so3_left_jacobian_inv", (3,)))
