"""SE(3) poses in numpy (float64): build/invert/apply 4×4 poses, UMI 6-vectors, exp/log, quaternions.

A pose ``T_<to>_<from>`` is a 4×4 homogeneous matrix, ``p_to = T_to_from @ p_from``; translations in metres,
rotation vectors in radians. UMI's 6-vector pose is ``[x, y, z, rx, ry, rz]`` (position + rotation vector).
Quaternions are named by component order: ``quat_wxyz`` (MuJoCo, 3DGS PLY) or ``quat_xyzw`` (scipy, ROS,
ORB-SLAM CSV). All functions are batched over leading dims ``[...]``.
"""

from __future__ import annotations

import numpy as np

from umi_aug.errors import GeometryError
from umi_aug.geometry._checks import as_float
from umi_aug.geometry.so3 import _left_jacobian, _left_jacobian_inv, _so3_exp, _so3_log

__all__ = [
    "make_pose",
    "pose_inverse",
    "transform_points",
    "pos_rotvec_to_pose",
    "pose_to_pos_rotvec",
    "se3_exp",
    "se3_log",
    "quat_wxyz_to_matrix",
    "matrix_to_quat_wxyz",
    "quat_xyzw_to_matrix",
    "matrix_to_quat_xyzw",
    "quat_wxyz_to_xyzw",
    "quat_xyzw_to_wxyz",
    "pose_to_pos_quat_wxyz",
    "pos_quat_wxyz_to_pose",
    "pose_to_pos_quat_xyzw",
    "pos_quat_xyzw_to_pose",
]


def _make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    batch = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(batch + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Homogeneous pose from a rotation and a translation.

    Args:
        R: np.ndarray,  # [..., 3, 3] rotation of T_<to>_<from>
        t: np.ndarray,  # [..., 3] translation (origin of <from> in <to>), metres; batch broadcasts with R
    Returns:
        T: np.ndarray,  # [..., 4, 4]
    """
    R = as_float(R, "R", "make_pose", (3, 3))
    t = as_float(t, "t", "make_pose", (3,))
    try:
        return _make_pose(R, t)
    except ValueError as exc:
        raise GeometryError(f"make_pose: batch shapes of `R` {R.shape} and `t` {t.shape} do not broadcast") from exc


def _pose_inverse(T: np.ndarray) -> np.ndarray:
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return _make_pose(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def pose_inverse(T: np.ndarray) -> np.ndarray:
    """Rigid inverse ``T_<from>_<to>`` of ``T_<to>_<from>`` (Rᵀ, −Rᵀt; exact, no general matrix inverse).

    Args:
        T: np.ndarray,  # [..., 4, 4]
    Returns:
        np.ndarray,  # [..., 4, 4]
    """
    return _pose_inverse(as_float(T, "T", "pose_inverse", (4, 4)))


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply ``T_<to>_<from>`` to points given in <from>: ``R p + t``.

    Args:
        T: np.ndarray,  # [..., 4, 4]
        p: np.ndarray,  # [..., N, 3] (batch broadcasts with T's), or [3] for one point
    Returns:
        np.ndarray,  # [..., N, 3] in <to> (or [..., 3] when p is [3])
    """
    T = as_float(T, "T", "transform_points", (4, 4))
    p = as_float(p, "p", "transform_points", (3,))
    single = p.ndim == 1
    if single:
        p = p[None]
    try:
        out = p @ np.swapaxes(T[..., :3, :3], -1, -2) + T[..., None, :3, 3]
    except ValueError as exc:
        raise GeometryError(
            f"transform_points: batch shapes of `T` {T.shape} and `p` {p.shape} do not broadcast; "
            f"expected T [..., 4, 4] and p [..., N, 3]"
        ) from exc
    return out[..., 0, :] if single else out


def pos_rotvec_to_pose(pose6: np.ndarray) -> np.ndarray:
    """UMI 6-vector ``[x, y, z, rx, ry, rz]`` (metres, rotation vector in radians) → 4×4 pose.

    Args:
        pose6: np.ndarray,  # [..., 6]
    Returns:
        T: np.ndarray,  # [..., 4, 4]
    """
    pose6 = as_float(pose6, "pose6", "pos_rotvec_to_pose", (6,))
    return _make_pose(_so3_exp(pose6[..., 3:]), pose6[..., :3])


def pose_to_pos_rotvec(T: np.ndarray) -> np.ndarray:
    """4×4 pose → UMI 6-vector ``[x, y, z, rx, ry, rz]`` (rotation angle in [0, π]).

    Args:
        T: np.ndarray,  # [..., 4, 4]
    Returns:
        pose6: np.ndarray,  # [..., 6]
    """
    T = as_float(T, "T", "pose_to_pos_rotvec", (4, 4))
    return np.concatenate([T[..., :3, 3], _so3_log(T[..., :3, :3])], axis=-1)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """SE(3) exponential of a twist ``xi = [rho, phi]`` (translation part first): ``R = exp(phi)``,
    ``t = J_l(phi) rho``.

    Args:
        xi: np.ndarray,  # [..., 6] rho (metres), phi (radians)
    Returns:
        T: np.ndarray,  # [..., 4, 4]
    """
    xi = as_float(xi, "xi", "se3_exp", (6,))
    rho, phi = xi[..., :3], xi[..., 3:]
    t = np.einsum("...ij,...j->...i", _left_jacobian(phi), rho)
    return _make_pose(_so3_exp(phi), t)


def se3_log(T: np.ndarray) -> np.ndarray:
    """SE(3) logarithm: ``phi = so3_log(R)`` (angle in [0, π]), ``rho = J_l(phi)⁻¹ t``.

    Args:
        T: np.ndarray,  # [..., 4, 4]
    Returns:
        xi: np.ndarray,  # [..., 6] = [rho, phi]
    """
    T = as_float(T, "T", "se3_log", (4, 4))
    phi = _so3_log(T[..., :3, :3])
    rho = np.einsum("...ij,...j->...i", _left_jacobian_inv(phi, "se3_log"), T[..., :3, 3])
    return np.concatenate([rho, phi], axis=-1)


# ----------------------------------------------------------------------------------------------- quaternions
def _normalize_quat(q: np.ndarray, name: str, func: str) -> np.ndarray:
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n <= 1e-300):
        raise GeometryError(f"{func}: `{name}` (shape {q.shape}) contains a zero-norm quaternion")
    return q / n


def _quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    m = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return m.reshape(q.shape[:-1] + (3, 3))


def _matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Shepperd: pick the largest of (tr, R00, R11, R22) so the divisor is ≥ 1/2."""
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    d21, d02, d10 = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]
    s21, s02, s10 = R[..., 2, 1] + R[..., 1, 2], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 0] + R[..., 0, 1]
    cand = np.stack(
        [
            np.stack([1 + tr, d21, d02, d10], axis=-1),
            np.stack([d21, 1 + m00 - m11 - m22, s10, s02], axis=-1),
            np.stack([d02, s10, 1 - m00 + m11 - m22, s21], axis=-1),
            np.stack([d10, s02, s21, 1 - m00 - m11 + m22], axis=-1),
        ],
        axis=-2,
    )  # [..., 4, 4]: row k is 4 q_k q (k = w, x, y, z)
    k = np.argmax(np.stack([tr, m00, m11, m22], axis=-1), axis=-1)
    q = np.take_along_axis(cand, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0.0, -q, q)


def quat_wxyz_to_matrix(quat_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion ``[w, x, y, z]`` (normalised first; zero norm → GeometryError).

    Args:
        quat_wxyz: np.ndarray,  # [..., 4]
    Returns:
        R: np.ndarray,  # [..., 3, 3]
    """
    q = as_float(quat_wxyz, "quat_wxyz", "quat_wxyz_to_matrix", (4,))
    return _quat_wxyz_to_matrix(_normalize_quat(q, "quat_wxyz", "quat_wxyz_to_matrix"))


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``[w, x, y, z]`` of a rotation matrix (Shepperd's method), canonical ``w >= 0``
    (at w = 0 exactly, q and −q are both valid; the sign Shepperd's branch gives is returned).

    Args:
        R: np.ndarray,  # [..., 3, 3]
    Returns:
        quat_wxyz: np.ndarray,  # [..., 4]
    """
    return _matrix_to_quat_wxyz(as_float(R, "R", "matrix_to_quat_wxyz", (3, 3)))


def quat_wxyz_to_xyzw(quat_wxyz: np.ndarray) -> np.ndarray:
    """Reorder ``[w, x, y, z]`` → ``[x, y, z, w]`` (no normalisation).

    Args:
        quat_wxyz: np.ndarray,  # [..., 4]
    Returns:
        quat_xyzw: np.ndarray,  # [..., 4]
    """
    q = as_float(quat_wxyz, "quat_wxyz", "quat_wxyz_to_xyzw", (4,))
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def quat_xyzw_to_wxyz(quat_xyzw: np.ndarray) -> np.ndarray:
    """Reorder ``[x, y, z, w]`` → ``[w, x, y, z]`` (no normalisation).

    Args:
        quat_xyzw: np.ndarray,  # [..., 4]
    Returns:
        quat_wxyz: np.ndarray,  # [..., 4]
    """
    q = as_float(quat_xyzw, "quat_xyzw", "quat_xyzw_to_wxyz", (4,))
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def quat_xyzw_to_matrix(quat_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion ``[x, y, z, w]`` (scipy/ROS order; normalised first).

    Args:
        quat_xyzw: np.ndarray,  # [..., 4]
    Returns:
        R: np.ndarray,  # [..., 3, 3]
    """
    q = as_float(quat_xyzw, "quat_xyzw", "quat_xyzw_to_matrix", (4,))
    q = np.concatenate([q[..., 3:], q[..., :3]], axis=-1)
    return _quat_wxyz_to_matrix(_normalize_quat(q, "quat_xyzw", "quat_xyzw_to_matrix"))


def matrix_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``[x, y, z, w]`` of a rotation matrix, canonical ``w >= 0``.

    Args:
        R: np.ndarray,  # [..., 3, 3]
    Returns:
        quat_xyzw: np.ndarray,  # [..., 4]
    """
    q = _matrix_to_quat_wxyz(as_float(R, "R", "matrix_to_quat_xyzw", (3, 3)))
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def pose_to_pos_quat_wxyz(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """4×4 pose → (position, quaternion wxyz with w >= 0).

    Args:
        T: np.ndarray,  # [..., 4, 4]
    Returns:
        pos: np.ndarray,  # [..., 3] metres
        quat_wxyz: np.ndarray,  # [..., 4]
    """
    T = as_float(T, "T", "pose_to_pos_quat_wxyz", (4, 4))
    return T[..., :3, 3].copy(), _matrix_to_quat_wxyz(T[..., :3, :3])


def pos_quat_wxyz_to_pose(pos: np.ndarray, quat_wxyz: np.ndarray) -> np.ndarray:
    """(position, quaternion wxyz) → 4×4 pose (quaternion normalised; zero norm → GeometryError).

    Args:
        pos: np.ndarray,  # [..., 3] metres
        quat_wxyz: np.ndarray,  # [..., 4] (batch broadcasts with pos)
    Returns:
        T: np.ndarray,  # [..., 4, 4]
    """
    pos = as_float(pos, "pos", "pos_quat_wxyz_to_pose", (3,))
    q = as_float(quat_wxyz, "quat_wxyz", "pos_quat_wxyz_to_pose", (4,))
    R = _quat_wxyz_to_matrix(_normalize_quat(q, "quat_wxyz", "pos_quat_wxyz_to_pose"))
    try:
        return _make_pose(R, pos)
    except ValueError as exc:
        raise GeometryError(
            f"pos_quat_wxyz_to_pose: batch shapes of `pos` {pos.shape} and `quat_wxyz` {q.shape} do not broadcast"
        ) from exc


def pose_to_pos_quat_xyzw(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """4×4 pose → (position, quaternion xyzw with w >= 0), the ORB-SLAM CSV / scipy order.

    Args:
        T: np.ndarray,  # [..., 4, 4]
    Returns:
        pos: np.ndarray,  # [..., 3] metres
        quat_xyzw: np.ndarray,  # [..., 4]
    """
    T = as_float(T, "T", "pose_to_pos_quat_xyzw", (4, 4))
    q = _matrix_to_quat_wxyz(T[..., :3, :3])
    return T[..., :3, 3].copy(), np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def pos_quat_xyzw_to_pose(pos: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """(position, quaternion xyzw) → 4×4 pose (quaternion normalised; zero norm → GeometryError).

    Args:
        pos: np.ndarray,  # [..., 3] metres
        quat_xyzw: np.ndarray,  # [..., 4] (batch broadcasts with pos)
    Returns:
        T: np.ndarray,  # [..., 4, 4]
    """
    pos = as_float(pos, "pos", "pos_quat_xyzw_to_pose", (3,))
    q = as_float(quat_xyzw, "quat_xyzw", "pos_quat_xyzw_to_pose", (4,))
    q = np.concatenate([q[..., 3:], q[..., :3]], axis=-1)
    R = _quat_wxyz_to_matrix(_normalize_quat(q, "quat_xyzw", "pos_quat_xyzw_to_pose"))
    try:
        return _make_pose(R, pos)
    except ValueError as exc:
        raise GeometryError(
            f"pos_quat_xyzw_to_pose: batch shapes of `pos` {pos.shape} and `quat_xyzw` {q.shape} do not broadcast"
        ) from exc


