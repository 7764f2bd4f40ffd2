"""SE(3), 6-D rotations, relative poses and quaternions in torch: mirror of the numpy API (batched,
dtype-preserving, autograd-safe; shape checks only). Poses ``T_<to>_<from>`` [..., 4, 4], metres, radians.

Differences from numpy (no value-dependent raising in torch): a zero-norm quaternion maps to the identity
rotation; degenerate 6-D input uses the same fallback as :mod:`.rot6d` (with eps 1e-6 in float32).
"""

from __future__ import annotations

import torch

from umi_aug.errors import GeometryError
from umi_aug.geometry._torch_checks import as_tensor, norm_eps, safe_norm
from umi_aug.geometry.so3_torch import _left_jacobian, _left_jacobian_inv, _so3_exp, _so3_log

__all__ = [
    "make_pose",
    "pose_inverse",
    "transform_points",
    "pos_rotvec_to_pose",
    "pose_to_pos_rotvec",
    "se3_exp",
    "se3_log",
    "mat_to_rot6d",
    "rot6d_to_mat",
    "relative_pose",
    "absolute_pose",
    "quat_wxyz_to_matrix",
    "matrix_to_quat_wxyz",
]


def _make_pose(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    batch = torch.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    R = R.expand(batch + (3, 3))
    t = t.expand(batch + (3,))
    top = torch.cat([R, t[..., None]], dim=-1)
    bottom = torch.zeros(batch + (1, 4), dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def make_pose(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Homogeneous pose from rotation and translation.

    Args:
        R: Tensor,  # [..., 3, 3]
        t: Tensor,  # [..., 3] metres (batch broadcasts with R)
    Returns:
        T: Tensor,  # [..., 4, 4]
    """
    R = as_tensor(R, "R", "make_pose", (3, 3))
    t = as_tensor(t, "t", "make_pose", (3,))
    try:
        return _make_pose(R, t)
    except RuntimeError as exc:
        raise GeometryError(
            f"make_pose: batch shapes of `R` {tuple(R.shape)} and `t` {tuple(t.shape)} do not broadcast"
        ) from exc


def _pose_inverse(T: torch.Tensor) -> torch.Tensor:
    Rt = T[..., :3, :3].transpose(-1, -2)
    return _make_pose(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def pose_inverse(T: torch.Tensor) -> torch.Tensor:
    """Rigid inverse (Rᵀ, −Rᵀt).

    Args:
        T: Tensor,  # [..., 4, 4]
    Returns:
        Tensor,  # [..., 4, 4]
    """
    return _pose_inverse(as_tensor(T, "T", "pose_inverse", (4, 4)))


def transform_points(T: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """``R p + t`` for points in the <from> frame.

    Args:
        T: Tensor,  # [..., 4, 4]
        p: Tensor,  # [..., N, 3] (batch broadcasts with T) or [3]
    Returns:
        Tensor,  # [..., N, 3] (or [..., 3] when p is [3])
    """
    T = as_tensor(T, "T", "transform_points", (4, 4))
    p = as_tensor(p, "p", "transform_points", (3,))
    single = p.dim() == 1
    if single:
        p = p[None]
    out = p @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]
    return out[..., 0, :] if single else out


def pos_rotvec_to_pose(pose6: torch.Tensor) -> torch.Tensor:
    """UMI ``[x, y, z, rx, ry, rz]`` → 4×4 pose.

    Args:
        pose6: Tensor,  # [..., 6]
    Returns:
        Tensor,  # [..., 4, 4]
    """
    pose6 = as_tensor(pose6, "pose6", "pos_rotvec_to_pose", (6,))
    return _make_pose(_so3_exp(pose6[..., 3:]), pose6[..., :3])


def pose_to_pos_rotvec(T: torch.Tensor) -> torch.Tensor:
    """4×4 pose → UMI ``[x, y, z, rx, ry, rz]``.

    Args:
        T: Tensor,  # [..., 4, 4]
    Returns:
        Tensor,  # [..., 6]
    """
    T = as_tensor(T, "T", "pose_to_pos_rotvec", (4, 4))
    return torch.cat([T[..., :3, 3], _so3_log(T[..., :3, :3])], dim=-1)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """SE(3) exp of ``xi = [rho, phi]`` (translation first).

    Args:
        xi: Tensor,  # [..., 6]
    Returns:
        Tensor,  # [..., 4, 4]
    """
    xi = as_tensor(xi, "xi", "se3_exp", (6,))
    rho, phi = xi[..., :3], xi[..., 3:]
    return _make_pose(_so3_exp(phi), (_left_jacobian(phi) @ rho[..., None])[..., 0])


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """SE(3) log → ``[rho, phi]`` with angle in [0, π].

    Args:
        T: Tensor,  # [..., 4, 4]
    Returns:
        Tensor,  # [..., 6]
    """
    T = as_tensor(T, "T", "se3_log", (4, 4))
    phi = _so3_log(T[..., :3, :3])
    rho = (_left_jacobian_inv(phi) @ T[..., :3, 3:4])[..., 0]
    return torch.cat([rho, phi], dim=-1)


def mat_to_rot6d(R: torch.Tensor) -> torch.Tensor:
    """First two ROWS of R, flattened (UMI).

    Args:
        R: Tensor,  # [..., 3, 3]
    Returns:
        Tensor,  # [..., 6]
    """
    R = as_tensor(R, "R", "mat_to_rot6d", (3, 3))
    return R[..., :2, :].reshape(R.shape[:-2] + (6,))


def _normalize_with_fallback(
    v: torch.Tensor, eps: float, fallback: torch.Tensor, ref: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    n, _ = safe_norm(v)
    deg = n < eps * ref
    n_div = torch.where(deg, torch.ones_like(n), n)
    return torch.where(deg[..., None], fallback, v / n_div[..., None]), deg


def rot6d_to_mat(d6: torch.Tensor) -> torch.Tensor:
    """Gram–Schmidt decode (rows b1, b2, b1×b2); degenerate input → finite fallback (see module doc).

    Args:
        d6: Tensor,  # [..., 6]
    Returns:
        R: Tensor,  # [..., 3, 3]
    """
    d6 = as_tensor(d6, "d6", "rot6d_to_mat", (6,))
    eps = norm_eps(d6.dtype)
    a1, a2 = d6[..., :3], d6[..., 3:]
    one = torch.ones(a1.shape[:-1], dtype=d6.dtype, device=d6.device)
    ex = torch.zeros_like(a1)
    ex[..., 0] = 1.0
    b1, _ = _normalize_with_fallback(a1, eps, ex, one)
    r = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    e = torch.nn.functional.one_hot(b1.detach().abs().argmin(-1), 3).to(d6.dtype)
    re = e - (b1 * e).sum(-1, keepdim=True) * b1
    re_unit = re / safe_norm(re)[0].clamp_min(1e-3)[..., None]  # ‖re‖ ≥ √(2/3) by construction
    a2n, _ = safe_norm(a2)
    b2, _ = _normalize_with_fallback(r, eps, re_unit, torch.clamp(a2n, min=1.0))
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-2)


def relative_pose(T_base: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    """``inv(T_base) @ T`` (UMI relative representation).

    Args:
        T_base: Tensor,  # [..., 4, 4]
        T: Tensor,  # [..., 4, 4]
    Returns:
        Tensor,  # [..., 4, 4]
    """
    T_base = as_tensor(T_base, "T_base", "relative_pose", (4, 4))
    T = as_tensor(T, "T", "relative_pose", (4, 4))
    return _pose_inverse(T_base) @ T


def absolute_pose(T_base: torch.Tensor, T_rel: torch.Tensor) -> torch.Tensor:
    """``T_base @ T_rel``.

    Args:
        T_base: Tensor,  # [..., 4, 4]
        T_rel: Tensor,  # [..., 4, 4]
    Returns:
        Tensor,  # [..., 4, 4]
    """
    T_base = as_tensor(T_base, "T_base", "absolute_pose", (4, 4))
    T_rel = as_tensor(T_rel, "T_rel", "absolute_pose", (4, 4))
    return T_base @ T_rel


def quat_wxyz_to_matrix(quat_wxyz: torch.Tensor) -> torch.Tensor:
    """Rotation of a quaternion ``[w, x, y, z]`` (normalised; zero norm → identity, no raise in torch).

    Args:
        quat_wxyz: Tensor,  # [..., 4]
    Returns:
        Tensor,  # [..., 3, 3]
    """
    q = as_tensor(quat_wxyz, "quat_wxyz", "quat_wxyz_to_matrix", (4,))
    n, pos = safe_norm(q, 1e-30)
    q = q / torch.where(pos, n, torch.ones_like(n))[..., None]
    w, x, y, z = q.unbind(-1)
    m = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return m.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat_wxyz(R: torch.Tensor) -> torch.Tensor:
    """Shepperd's method, canonical ``w >= 0`` (differentiable, no square roots).

    Args:
        R: Tensor,  # [..., 3, 3]
    Returns:
        quat_wxyz: Tensor,  # [..., 4]
    """
    R = as_tensor(R, "R", "matrix_to_quat_wxyz", (3, 3))
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    d21, d02, d10 = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]
    s21, s02, s10 = R[..., 2, 1] + R[..., 1, 2], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 0] + R[..., 0, 1]
    cand = torch.stack(
        [
            torch.stack([1 + tr, d21, d02, d10], dim=-1),
            torch.stack([d21, 1 + m00 - m11 - m22, s10, s02], dim=-1),
            torch.stack([d02, s10, 1 - m00 + m11 - m22, s21], dim=-1),
            torch.stack([d10, s02, s21, 1 - m00 - m11 + m22], dim=-1),
        ],
        dim=-2,
    )
    k = torch.stack([tr, m00, m11, m22], dim=-1).argmax(-1)
    q = torch.gather(cand, -2, k[..., None, None].expand(cand.shape[:-2] + (1, 4)))[..., 0, :]
    n, pos = safe_norm(q, 1e-30)
    q = q / torch.where(pos, n, torch.ones_like(n))[..., None]
    return torch.where(q[..., :1] < 0, -q, q)
