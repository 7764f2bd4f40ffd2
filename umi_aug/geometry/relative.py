"""UMI's relative pose representation (``diffusion_policy/common/pose_repr_util.convert_pose_mat_rep``).

``relative_pose(T_base, T) = inv(T_base) @ T`` expresses ``T`` in the frame of ``T_base`` (UMI uses the last
observed pose as the base); ``absolute_pose`` undoes it.
"""

from __future__ import annotations

import numpy as np

from umi_aug.errors import GeometryError
from umi_aug.geometry._checks import as_float
from umi_aug.geometry.se3 import _pose_inverse

__all__ = ["relative_pose", "absolute_pose", "convert_pose_representation", "POSE_REPRESENTATIONS"]

POSE_REPRESENTATIONS: tuple[str, ...] = ("abs", "relative")


def relative_pose(T_base: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``inv(T_base) @ T`` (rigid inverse), batch dims broadcast.

    Args:
        T_base: np.ndarray,  # [..., 4, 4] T_world_base
        T: np.ndarray,  # [..., 4, 4] T_world_x
    Returns:
        np.ndarray,  # [..., 4, 4] T_base_x
    """
    T_base = as_float(T_base, "T_base", "relative_pose", (4, 4))
    T = as_float(T, "T", "relative_pose", (4, 4))
    try:
        return _pose_inverse(T_base) @ T
    except ValueError as exc:
        raise GeometryError(
            f"relative_pose: batch shapes of `T_base` {T_base.shape} and `T` {T.shape} do not broadcast"
        ) from exc


def absolute_pose(T_base: np.ndarray, T_rel: np.ndarray) -> np.ndarray:
    """``T_base @ T_rel``, the inverse of :func:`relative_pose`.

    Args:
        T_base: np.ndarray,  # [..., 4, 4] T_world_base
        T_rel: np.ndarray,  # [..., 4, 4] T_base_x
    Returns:
        np.ndarray,  # [..., 4, 4] T_world_x
    """
    T_base = as_float(T_base, "T_base", "absolute_pose", (4, 4))
    T_rel = as_float(T_rel, "T_rel", "absolute_pose", (4, 4))
    try:
        return T_base @ T_rel
    except ValueError as exc:
        raise GeometryError(
            f"absolute_pose: batch shapes of `T_base` {T_base.shape} and `T_rel` {T_rel.shape} do not broadcast"
        ) from exc


def convert_pose_representation(
    poses: np.ndarray, base_pose: np.ndarray, rep: str, backward: bool = False
) -> np.ndarray:
    """UMI ``convert_pose_mat_rep``: forward (training) ``abs`` → unchanged, ``relative`` → ``inv(base) @ poses``;
    backward (deployment) ``relative`` → ``base @ poses``.

    Args:
        poses: np.ndarray,  # [..., 4, 4]
        base_pose: np.ndarray,  # [4, 4] (or broadcastable [..., 4, 4])
        rep: str,  # "abs" or "relative" (UMI pose_repr names)
        backward: bool,  # False: abs → rep; True: rep → abs
    Returns:
        np.ndarray,  # [..., 4, 4]
    """
    if rep not in POSE_REPRESENTATIONS:
        raise GeometryError(
            f"convert_pose_representation: `rep` is {rep!r}; expected one of {list(POSE_REPRESENTATIONS)}"
        )
    poses = as_float(poses, "poses", "convert_pose_representation", (4, 4))
    base_pose = as_float(base_pose, "base_pose", "convert_pose_representation", (4, 4))
    if rep == "abs":
        return poses.copy()
    return absolute_pose(base_pose, poses) if backward else relative_pose(base_pose, poses)
