"""UMI's 6-D rotation representation (numpy float64): the first two ROWS of R, flattened.

Encode ``d6 = R[..., :2, :].reshape(..., 6)`` (``umi/common/pose_util.mat_to_rot6d``); decode by Gram–Schmidt
on ``a1 = d6[:3]``, ``a2 = d6[3:]`` with the resulting vectors stacked as ROWS (``pose_util.rot6d_to_mat``).

Degenerate input fallback (documented, deterministic, never NaN): if ``‖a1‖ < NORM_EPS`` then ``b1 = e_x``;
if the residual ``a2 − (b1·a2) b1`` is shorter than ``NORM_EPS·max(1, ‖a2‖)`` (a2 ≈ 0 or a2 ∥ a1) then ``b2`` is
the unit vector of ``e_k − (b1·e_k) b1`` with ``e_k`` the basis axis least aligned with ``b1``.
"""

from __future__ import annotations

import numpy as np

from umi_aug.geometry._checks import as_float
from umi_aug.geometry._constants import NORM_EPS
from umi_aug.geometry.se3 import _make_pose

__all__ = ["mat_to_rot6d", "rot6d_to_mat", "pose_to_pos_rot6d", "pos_rot6d_to_pose"]


def _rot6d_to_mat(d6: np.ndarray) -> np.ndarray:
    a1, a2 = d6[..., :3], d6[..., 3:]
    n1 = np.linalg.norm(a1, axis=-1, keepdims=True)
    deg1 = n1 < NORM_EPS
    b1 = np.where(deg1, np.array([1.0, 0.0, 0.0]), a1 / np.where(deg1, 1.0, n1))
    r = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    nr = np.linalg.norm(r, axis=-1, keepdims=True)
    deg2 = nr < NORM_EPS * np.maximum(1.0, np.linalg.norm(a2, axis=-1, keepdims=True))
    if np.any(deg2):
        k = np.argmin(np.abs(b1), axis=-1)
        e = np.eye(3)[k]
        re = e - np.sum(b1 * e, axis=-1, keepdims=True) * b1
        r = np.where(deg2, re, r)
        nr = np.linalg.norm(r, axis=-1, keepdims=True)
    b2 = r / nr
    b3 = np.cross(b1, b2)
    return np.stack([b1, b2, b3], axis=-2)


def mat_to_rot6d(R: np.ndarray) -> np.ndarray:
    """6-D rotation of a matrix: first two rows, flattened (UMI convention).

    Args:
        R: np.ndarray,  # [..., 3, 3]
    Returns:
        d6: np.ndarray,  # [..., 6] = [R[0, :], R[1, :]]
    """
    R = as_float(R, "R", "mat_to_rot6d", (3, 3))
    return R[..., :2, :].reshape(R.shape[:-2] + (6,)).copy()


def rot6d_to_mat(d6: np.ndarray) -> np.ndarray:
    """Rotation from a 6-D vector by Gram–Schmidt (rows b1, b2, b1×b2); degenerate input → see module doc.

    Args:
        d6: np.ndarray,  # [..., 6] (need not be normalised)
    Returns:
        R: np.ndarray,  # [..., 3, 3]
    """
    return _rot6d_to_mat(as_float(d6, "d6", "rot6d_to_mat", (6,)))


def pose_to_pos_rot6d(T: np.ndarray) -> np.ndarray:
    """4×4 pose → ``[x, y, z, rot6d(6)]`` (UMI's 9-D pose as used in actions).

    Args:
        T: np.ndarray,  # [..., 4, 4]
    Returns:
        p9: np.ndarray,  # [..., 9]
    """
    T = as_float(T, "T", "pose_to_pos_rot6d", (4, 4))
    return np.concatenate([T[..., :3, 3], T[..., :2, :3].reshape(T.shape[:-2] + (6,))], axis=-1)


def pos_rot6d_to_pose(p9: np.ndarray) -> np.ndarray:
    """``[x, y, z, rot6d(6)]`` → 4×4 pose (rotation by Gram–Schmidt).

    Args:
        p9: np.ndarray,  # [..., 9]
    Returns:
        T: np.ndarray,  # [..., 4, 4]
    """
    p9 = as_float(p9, "p9", "pos_rot6d_to_pose", (9,))
    return _make_pose(_rot6d_to_mat(p9[..., 3:]), p9[..., :3])
