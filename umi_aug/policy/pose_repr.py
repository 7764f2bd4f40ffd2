"""UMI's pose representations for policy observations and actions (numpy, float64).

Training (``UmiDataset.__getitem__``) and deployment (``get_real_umi_obs_dict`` / ``get_real_umi_action``) use
the same maps, so they live here once:

* relative: ``T_rel = inv(T_cur) @ T_t`` with ``T_cur`` the LAST observed TCP pose (UMI converts the actions with
  ``obs_pose_repr``; both default to ``relative``); ``abs`` leaves poses unchanged.
* 10-D action per arm: ``[pos(3), rot6d(6), gripper(1)]`` with rot6d = first two ROWS of R.
* ``wrt_start``: rot6d of ``inv(T_start) @ T_t`` (UMI keeps only the rotation part).
* Environment actions: ``[pos(3), rotvec(3), gripper(1)]`` absolute TCP poses (7 per arm).
"""

from __future__ import annotations

import numpy as np

from umi_aug.errors import PolicyError
from umi_aug.geometry import (
    convert_pose_representation, pos_rot6d_to_pose, pos_rotvec_to_pose, pose_to_pos_rot6d, pose_to_pos_rotvec,
)

__all__ = ["obs_pose_to_model", "abs_actions_to_model", "model_actions_to_abs", "wrt_start_rot6d", "as_pose_mat"]


def as_pose_mat(pose: np.ndarray, name: str = "pose") -> np.ndarray:
    """A 4×4 pose (``[..., 4, 4]``) or UMI 6-vector (``[..., 6]`` = pos + rotvec) → float64 ``[..., 4, 4]``."""
    p = np.asarray(pose, dtype=np.float64)
    if p.shape[-2:] == (4, 4):
        return p
    if p.shape[-1:] == (6,):
        return pos_rotvec_to_pose(p)
    raise PolicyError(f"`{name}` must be [..., 4, 4] or [..., 6] (pos + rotvec), got shape {p.shape}")


def _bases(T_cur: np.ndarray, n: int) -> list[np.ndarray]:
    """Per-arm base poses ``[..., 1, 4, 4]`` (broadcast over the horizon) from ``[..., 4, 4]`` (one arm) or
    ``[..., R, 4, 4]`` (R arms), or the same as pos+rotvec 6-vectors."""
    base = as_pose_mat(T_cur, "T_cur")
    if n == 1:
        return [base[..., None, :, :]]
    if base.ndim < 3 or base.shape[-3] != n:
        raise PolicyError(f"`T_cur` must hold one pose per arm ([..., {n}, 4, 4] or [..., {n}, 6]), got {base.shape}")
    return [base[..., i, None, :, :] for i in range(n)]


def obs_pose_to_model(pos: np.ndarray, rotvec: np.ndarray, rep: str = "relative") -> tuple[np.ndarray, np.ndarray]:
    """Observed TCP poses → the policy's pose observation.

    Args:
        pos: np.ndarray,  # [..., To, 3] metres
        rotvec: np.ndarray,  # [..., To, 3] radians
        rep: "relative" (base = last pose along To) or "abs"
    Returns:
        (pos [..., To, 3], rot6d [..., To, 6]) float64
    """
    T = pos_rotvec_to_pose(np.concatenate([np.asarray(pos, np.float64), np.asarray(rotvec, np.float64)], axis=-1))
    T = convert_pose_representation(T, T[..., -1:, :, :], rep)
    p9 = pose_to_pos_rot6d(T)
    return p9[..., :3], p9[..., 3:]


def abs_actions_to_model(action7: np.ndarray, T_cur: np.ndarray, rep: str = "relative") -> np.ndarray:
    """Absolute env actions ``[pos, rotvec, gripper]`` → 10-D model actions relative to ``T_cur``.

    Args:
        action7: np.ndarray,  # [..., H, 7 · R]
        T_cur: np.ndarray,  # [..., 4, 4] (R = 1) or [..., R, 4, 4]; or pos+rotvec [..., (R,) 6]
        rep: "relative" or "abs"
    Returns:
        np.ndarray,  # [..., H, 10 · R] = per arm [pos(3), rot6d(6), gripper(1)]
    """
    a = np.asarray(action7, dtype=np.float64)
    if a.shape[-1] % 7:
        raise PolicyError(f"abs_actions_to_model: last axis must be 7 per arm, got {a.shape}")
    n = a.shape[-1] // 7
    base = _bases(T_cur, n)
    out = []
    for i in range(n):
        Ti = pos_rotvec_to_pose(a[..., 7 * i: 7 * i + 6])
        rel = convert_pose_representation(Ti, base[i], rep)
        out += [pose_to_pos_rot6d(rel), a[..., 7 * i + 6: 7 * i + 7]]
    return np.concatenate(out, axis=-1)


def model_actions_to_abs(action10: np.ndarray, T_cur: np.ndarray, rep: str = "relative") -> np.ndarray:
    """10-D model actions → absolute env actions (``get_real_umi_action``): ``T_cur @ T_rel`` → [pos, rotvec, g].

    Args:
        action10: np.ndarray,  # [..., H, 10 · R]
        T_cur: np.ndarray,  # [..., 4, 4] (R = 1) or [..., R, 4, 4]; or pos+rotvec [..., (R,) 6]
        rep: "relative" or "abs"
    Returns:
        np.ndarray,  # [..., H, 7 · R] float64
    """
    a = np.asarray(action10, dtype=np.float64)
    if a.shape[-1] % 10:
        raise PolicyError(f"model_actions_to_abs: last axis must be 10 per arm, got {a.shape}")
    n = a.shape[-1] // 10
    base = _bases(T_cur, n)
    out = []
    for i in range(n):
        rel = pos_rot6d_to_pose(a[..., 10 * i: 10 * i + 9])
        T = convert_pose_representation(rel, base[i], rep, backward=True)
        out += [pose_to_pos_rotvec(T), a[..., 10 * i + 9: 10 * i + 10]]
    return np.concatenate(out, axis=-1)


def wrt_start_rot6d(pos: np.ndarray, rotvec: np.ndarray, start_pose: np.ndarray) -> np.ndarray:
    """rot6d of the observed poses relative to the episode start pose (UMI's ``*_rot_axis_angle_wrt_start``).

    Args:
        pos, rotvec: np.ndarray,  # [..., To, 3]
        start_pose: np.ndarray,  # [..., 6] pos + rotvec, or [..., 4, 4]
    Returns:
        np.ndarray,  # [..., To, 6]
    """
    T = pos_rotvec_to_pose(np.concatenate([np.asarray(pos, np.float64), np.asarray(rotvec, np.float64)], axis=-1))
    S = as_pose_mat(start_pose, "start_pose")[..., None, :, :]
    return pose_to_pos_rot6d(convert_pose_representation(T, S, "relative"))[..., 3:]
