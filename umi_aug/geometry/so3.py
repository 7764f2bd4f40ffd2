"""SO(3) in numpy (float64): hat/vee, exp/log, left Jacobians, geodesic distance, projection.

Rotations are 3×3 matrices ``R`` acting on column vectors (``p_to = R @ p_from``); rotation vectors are
``rotvec = θ·axis`` in radians. Every function is batched over leading dims ``[...]`` and returns float64.
Accuracy: round trips are at machine precision at θ = 0, tiny θ and θ → π (see ``_constants`` for the branch
analysis); no NaN is produced for finite input.
"""

from __future__ import annotations

import numpy as np

from umi_aug.errors import GeometryError
from umi_aug.geometry._checks import as_float
from umi_aug.geometry._constants import (
    EXP_TAYLOR_ANGLE,
    JAC_SERIES_ANGLE,
    LOG_PI_BRANCH_COS,
    LOG_TAYLOR_SIN,
    TWO_PI,
)

__all__ = [
    "so3_exp_unchecked",
    "so3_log_unchecked",
    "so3_left_jacobian_inv_unchecked",
    "hat",
    "vee",
    "so3_exp",
    "so3_log",
    "so3_left_jacobian",
    "so3_left_jacobian_inv",
    "rotation_geodesic_distance",
    "project_to_rotation",
]


def _hat(v: np.ndarray) -> np.ndarray:
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = np.zeros_like(x)
    return np.stack([o, -z, y, z, o, -x, -y, x, o], axis=-1).reshape(v.shape[:-1] + (3, 3))


def _vee(M: np.ndarray) -> np.ndarray:
    return 0.5 * np.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], axis=-1
    )


def hat(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix of a 3-vector: ``hat(v) @ p == cross(v, p)``.

    Args:
        v: np.ndarray,  # [..., 3]
    Returns:
        np.ndarray,  # [..., 3, 3]
    """
    return _hat(as_float(v, "v", "hat", (3,)))


def vee(M: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat`: the vector of the skew-symmetric part ``(M − Mᵀ)/2``.

    Args:
        M: np.ndarray,  # [..., 3, 3]
    Returns:
        np.ndarray,  # [..., 3]
    """
    return _vee(as_float(M, "M", "vee", (3, 3)))


def _sinc(x: np.ndarray) -> np.ndarray:
    """sin(x)/x for x >= 0 with its Taylor branch below EXP_TAYLOR_ANGLE (no 0/0)."""
    small = x < EXP_TAYLOR_ANGLE
    xs = np.where(small, 1.0, x)
    x2 = x * x
    return np.where(small, 1.0 - x2 / 6.0 + x2 * x2 / 120.0, np.sin(xs) / xs)


def _exp_coeffs(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A = sin θ/θ, B = (1 − cos θ)/θ² = ½ sinc²(θ/2), both cancellation-free."""
    a = _sinc(theta)
    h = _sinc(0.5 * theta)
    return a, 0.5 * h * h


def _so3_exp(rotvec: np.ndarray) -> np.ndarray:
    # R = I + A K + B K² with K² = v vᵀ − θ² I, written element-wise (no batched 3×3 matmuls).
    x, y, z = rotvec[..., 0], rotvec[..., 1], rotvec[..., 2]
    theta2 = x * x + y * y + z * z
    a, b = _exp_coeffs(np.sqrt(theta2))
    c = 1.0 - b * theta2  # = cos θ
    bx, by, bz = b * x, b * y, b * z
    ax, ay, az = a * x, a * y, a * z
    bxy, bxz, byz = bx * y, bx * z, by * z
    R = np.empty(rotvec.shape[:-1] + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = c + bx * x, bxy - az, bxz + ay
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = bxy + az, c + by * y, byz - ax
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = bxz - ay, byz + ax, c + bz * z
    return R


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues), any angle.

    Args:
        rotvec: np.ndarray,  # [..., 3] axis·angle, radians
    Returns:
        R: np.ndarray,  # [..., 3, 3]
    """
    return _so3_exp(as_float(rotvec, "rotvec", "so3_exp", (3,)))


def _so3_log(R: np.ndarray) -> np.ndarray:
    w = _vee(R)  # = sin θ · n for a rotation
    s = np.linalg.norm(w, axis=-1)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    theta = np.arctan2(s, c)
    # generic / small-angle branch: rotvec = w · θ / sin θ
    small = s < LOG_TAYLOR_SIN
    s_safe = np.where(small, 1.0, s)
    s2 = s * s
    ratio = np.where(small, 1.0 + s2 / 6.0 + 3.0 * s2 * s2 / 40.0, theta / s_safe)
    out = w * ratio[..., None]
    near_pi = c < LOG_PI_BRANCH_COS
    if np.any(near_pi):
        Rp, wp, cp, tp = R[near_pi], w[near_pi], c[near_pi], theta[near_pi]
        B = 0.5 * (Rp + np.swapaxes(Rp, -1, -2)) - cp[:, None, None] * np.eye(3)  # (1 − c) n nᵀ
        i = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        col = np.take_along_axis(B, i[:, None, None], axis=-1)[..., 0]  # (1 − c) n_i n
        n = col / np.linalg.norm(col, axis=-1, keepdims=True)  # ‖col‖ ≥ (1 − c)/√3 ≥ 1/√3
        sign = np.where(np.sum(n * wp, axis=-1) < 0.0, -1.0, 1.0)
        out[near_pi] = n * (sign * tp)[:, None]
    return out


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix, angle in [0, π].

    Near θ = 0 a Taylor branch is used; for θ > π/2 the axis comes from the symmetric part ``R + Rᵀ`` (largest
    diagonal column), its sign from the skew part, so θ → π and θ = π are exact (at θ = π exactly, ``±axis``
    are equally valid and the sign is whatever the skew part's rounding gives, ``+`` when it is zero).

    Args:
        R: np.ndarray,  # [..., 3, 3] rotation (assumed orthonormal; see :func:`project_to_rotation`)
    Returns:
        rotvec: np.ndarray,  # [..., 3] radians
    """
    return _so3_log(as_float(R, "R", "so3_log", (3, 3)))


def _jac_series_c(theta: np.ndarray, threshold: float = JAC_SERIES_ANGLE) -> np.ndarray:
    """C(θ) = (θ − sin θ)/θ³."""
    small = theta < threshold
    ts = np.where(small, 1.0, theta)
    t2 = theta * theta
    series = 1 / 6 - t2 / 120 * (1 - t2 / 42 * (1 - t2 / 72 * (1 - t2 / 110)))
    return np.where(small, series, (ts - np.sin(ts)) / (ts * ts * ts))


def _jac_inv_series_d(theta: np.ndarray, threshold: float = JAC_SERIES_ANGLE) -> np.ndarray:
    """D(θ) = 1/θ² − cot(θ/2)/(2θ), valid for 0 ≤ θ < 2π."""
    small = theta < threshold
    ts = np.where(small, 1.0, theta)
    t2 = theta * theta
    series = 1 / 12 + t2 / 720 + t2 * t2 / 30240 + t2**3 / 1209600 + t2**4 / 47900160
    half = 0.5 * ts
    return np.where(small, series, 1.0 / (ts * ts) - np.cos(half) / (2.0 * ts * np.sin(half)))


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(phi, axis=-1)
    _, b = _exp_coeffs(theta)
    c = _jac_series_c(theta)
    K = _hat(phi)
    return np.eye(3) + b[..., None, None] * K + c[..., None, None] * (K @ K)


def _left_jacobian_inv(phi: np.ndarray, func: str = "so3_left_jacobian_inv") -> np.ndarray:
    theta = np.linalg.norm(phi, axis=-1)
    if np.any(theta >= TWO_PI - 1e-6):
        raise GeometryError(
            f"{func}: `phi` has angle(s) up to {float(theta.max()):.6g} rad; the inverse left Jacobian is "
            f"singular at 2π, expected angles < 2π (use so3_log output, angle ≤ π)"
        )
    d = _jac_inv_series_d(theta)
    K = _hat(phi)
    return np.eye(3) - 0.5 * K + d[..., None, None] * (K @ K)


def so3_left_jacobian(phi: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3): ``J = I + (1−cos θ)/θ² K + (θ−sin θ)/θ³ K²`` with ``K = hat(phi)``.

    Args:
        phi: np.ndarray,  # [..., 3] rotation vector, radians
    Returns:
        J: np.ndarray,  # [..., 3, 3]
    """
    return _left_jacobian(as_float(phi, "phi", "so3_left_jacobian", (3,)))


def so3_left_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """Inverse left Jacobian: ``J⁻¹ = I − K/2 + (1/θ² − cot(θ/2)/(2θ)) K²``; defined for angles < 2π.

    Args:
        phi: np.ndarray,  # [..., 3] rotation vector, radians, |phi| < 2π (GeometryError otherwise)
    Returns:
        J_inv: np.ndarray,  # [..., 3, 3]
    """
    return _left_jacobian_inv(as_float(phi, "phi", "so3_left_jacobian_inv", (3,)))


def _geodesic(R1: np.ndarray, R2: np.ndarray) -> np.ndarray:
    Rrel = np.swapaxes(R1, -1, -2) @ R2
    s = np.linalg.norm(_vee(Rrel), axis=-1)
    c = 0.5 * (np.trace(Rrel, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(s, c)


def rotation_geodesic_distance(R1: np.ndarray, R2: np.ndarray) -> np.ndarray:
    """Angle of ``R1ᵀ R2`` in [0, π] via ``atan2(‖skew‖, (tr − 1)/2)`` (accurate near 0 and near π).

    Args:
        R1: np.ndarray,  # [..., 3, 3]
        R2: np.ndarray,  # [..., 3, 3] (batch dims broadcast with R1)
    Returns:
        angle: np.ndarray,  # [...] radians
    """
    R1 = as_float(R1, "R1", "rotation_geodesic_distance", (3, 3))
    R2 = as_float(R2, "R2", "rotation_geodesic_distance", (3, 3))
    return _geodesic(R1, R2)


def project_to_rotation(M: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius norm) to ``M`` via SVD, with det = +1.

    Args:
        M: np.ndarray,  # [..., 3, 3]
    Returns:
        R: np.ndarray,  # [..., 3, 3]
    """
    M = as_float(M, "M", "project_to_rotation", (3, 3))
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


# Fast paths for inner loops whose inputs are already validated (float64, finite, shape [..., 3] / [..., 3, 3]):
# the same kernels as the public functions, without the per-call shape/finiteness checks.
def so3_exp_unchecked(rotvec: np.ndarray) -> np.ndarray:
    """:func:`so3_exp` without input validation; ``rotvec`` must be finite float64 ``[..., 3]``."""
    return _so3_exp(rotvec)


def so3_log_unchecked(R: np.ndarray) -> np.ndarray:
    """:func:`so3_log` without input validation; ``R`` must be a finite float64 rotation ``[..., 3, 3]``."""
    return _so3_log(R)


def so3_left_jacobian_inv_unchecked(phi: np.ndarray) -> np.ndarray:
    """:func:`so3_left_jacobian_inv` without shape/finiteness validation (angles ≥ 2π still raise)."""
    return _left_jacobian_inv(phi)
