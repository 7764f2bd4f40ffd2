"""UMI's fixed camera→TCP offset (``scripts_slam_pipeline/06_generate_dataset_plan.py``), as plain facts.

``pose_cam_tcp = [0, cam_to_center_height, cam_to_mount_offset + tcp_offset, 0, 0, 0]``: translation only, so
the TCP axes equal the OpenCV camera axes (x right, y down, z forward). ``T_world_tcp = T_world_cam @ T_cam_tcp``.
"""

from __future__ import annotations

import numpy as np

from umi_aug.errors import GeometryError
from umi_aug.geometry._checks import as_float
from umi_aug.geometry.se3 import _pose_inverse

__all__ = [
    "UMI_TCP_OFFSET",
    "UMI_CAM_TO_CENTER_HEIGHT",
    "UMI_CAM_TO_MOUNT_OFFSET",
    "umi_T_cam_tcp",
    "tcp_poses_from_camera_poses",
    "camera_poses_from_tcp_poses",
]

UMI_TCP_OFFSET: float = 0.205  # m, gripper tip to mounting screw (06 default `tcp_offset`)
UMI_CAM_TO_CENTER_HEIGHT: float = 0.086  # m
UMI_CAM_TO_MOUNT_OFFSET: float = 0.01465  # m, optical centre to mount, GoPro 9/10/11


def umi_T_cam_tcp(
    tcp_offset: float = UMI_TCP_OFFSET,
    cam_to_center_height: float = UMI_CAM_TO_CENTER_HEIGHT,
    cam_to_mount_offset: float = UMI_CAM_TO_MOUNT_OFFSET,
) -> np.ndarray:
    """UMI's ``T_cam_tcp``: identity rotation, translation ``[0, h, mount + tcp_offset]`` (metres, camera frame).

    Returns:
        T_cam_tcp: np.ndarray,  # [4, 4]
    """
    vals = {"tcp_offset": tcp_offset, "cam_to_center_height": cam_to_center_height,
            "cam_to_mount_offset": cam_to_mount_offset}
    for name, v in vals.items():
        try:
            ok = np.isfinite(float(v))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise GeometryError(f"umi_T_cam_tcp: `{name}` must be a finite float (metres), got {v!r}")
    T = np.eye(4)
    T[:3, 3] = [0.0, float(cam_to_center_height), float(cam_to_mount_offset) + float(tcp_offset)]
    return T


def tcp_poses_from_camera_poses(T_world_cam: np.ndarray, T_cam_tcp: np.ndarray | None = None) -> np.ndarray:
    """``T_world_tcp = T_world_cam @ T_cam_tcp`` (default: :func:`umi_T_cam_tcp`).

    Args:
        T_world_cam: np.ndarray,  # [..., 4, 4]
        T_cam_tcp: np.ndarray | None,  # [4, 4] or [..., 4, 4]
    Returns:
        T_world_tcp: np.ndarray,  # [..., 4, 4]
    """
    T_world_cam = as_float(T_world_cam, "T_world_cam", "tcp_poses_from_camera_poses", (4, 4))
    T_cam_tcp = umi_T_cam_tcp() if T_cam_tcp is None else as_float(
        T_cam_tcp, "T_cam_tcp", "tcp_poses_from_camera_poses", (4, 4))
    return T_world_cam @ T_cam_tcp


def camera_poses_from_tcp_poses(T_world_tcp: np.ndarray, T_cam_tcp: np.ndarray | None = None) -> np.ndarray:
    """``T_world_cam = T_world_tcp @ inv(T_cam_tcp)`` (default: :func:`umi_T_cam_tcp`).

    Args:
        T_world_tcp: np.ndarray,  # [..., 4, 4]
        T_cam_tcp: np.ndarray | None,  # [4, 4] or [..., 4, 4]
    Returns:
        T_world_cam: np.ndarray,  # [..., 4, 4]
    """
    T_world_tcp = as_float(T_world_tcp, "T_world_tcp", "camera_poses_from_tcp_poses", (4, 4))
    T_cam_tcp = umi_T_cam_tcp() if T_cam_tcp is None else as_float(
        T_cam_tcp, "T_cam_tcp", "camera_poses_from_tcp_poses", (4, 4))
    return T_world_tcp @ _pose_inverse(T_cam_tcp)
