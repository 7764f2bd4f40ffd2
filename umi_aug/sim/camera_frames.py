"""The one place where OpenCV camera axes meet MuJoCo/OpenGL camera axes.

OpenCV camera frame (the project convention): x right, y down, z forward (optical axis).
MuJoCo camera frame (MJCF ``<camera>``, ``mjvGLCamera``, OpenGL): x right, y up, looks along −z.

The two frames share the origin and the x axis; y and z are negated: ``R_world_mjcam = R_world_cvcam @
diag(1, −1, −1)``. The map is its own inverse. Everything in :mod:`umi_aug.sim` that hands a pose to MuJoCo goes
through :func:`opencv_to_mujoco_camera`; nothing outside ``umi_aug.sim`` ever sees a MuJoCo camera frame.
"""

from __future__ import annotations

import numpy as np

from umi_aug.errors import SimError

__all__ = ["CV_TO_MJ_CAMERA_AXES", "opencv_to_mujoco_camera", "mujoco_to_opencv_camera", "mujoco_camera_vectors"]

#: ``R_cvcam_mjcam``: columns are the MuJoCo camera axes expressed in the OpenCV camera frame (self-inverse).
CV_TO_MJ_CAMERA_AXES: np.ndarray = np.diag([1.0, -1.0, -1.0])


def _as_pose(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] not in ((4, 4), (3, 3)) or not np.all(np.isfinite(T)):
        raise SimError(f"{name} must be finite [..., 4, 4] (pose) or [..., 3, 3] (rotation), got shape {T.shape}")
    return T


def opencv_to_mujoco_camera(T_world_cam: np.ndarray) -> np.ndarray:
    """Convert a camera pose/rotation with OpenCV axes to the same camera with MuJoCo/OpenGL axes.

    Args:
        T_world_cam: np.ndarray,  # [..., 4, 4] pose or [..., 3, 3] rotation; camera axes x right, y down, z fwd
    Returns:
        T_world_mjcam: np.ndarray,  # same shape; camera axes x right, y up, looking along −z (MuJoCo/OpenGL).
            The position (translation) is unchanged; rotation columns 1 and 2 are negated.
    """
    T = _as_pose(T_world_cam, "T_world_cam").copy()
    T[..., :3, 1] *= -1.0
    T[..., :3, 2] *= -1.0
    return T


def mujoco_to_opencv_camera(T_world_mjcam: np.ndarray) -> np.ndarray:
    """Inverse of :func:`opencv_to_mujoco_camera` (the same axis flip: it is an involution).

    Args:
        T_world_mjcam: np.ndarray,  # [..., 4, 4] or [..., 3, 3], MuJoCo camera axes
    Returns:
        T_world_cam: np.ndarray,  # same shape, OpenCV camera axes
    """
    return opencv_to_mujoco_camera(T_world_mjcam)


def mujoco_camera_vectors(R_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ``forward`` and ``up`` unit vectors MuJoCo's ``mjvGLCamera`` wants, from an OpenCV-axes rotation.

    Args:
        R_world_cam: np.ndarray,  # [3, 3] (or the rotation block of a [4, 4] pose), OpenCV camera axes
    Returns:
        forward: np.ndarray,  # [3] world direction of the optical axis (= −z of the MuJoCo camera)
        up: np.ndarray,       # [3] world direction of image "up" (= +y of the MuJoCo camera)
    """
    R = _as_pose(R_world_cam, "R_world_cam")[..., :3, :3]
    R_mj = opencv_to_mujoco_camera(R)
    return -R_mj[..., :, 2], R_mj[..., :, 1]
