"""The square task's wrist camera: its pose in OpenCV axes, the GoPro fisheye intrinsics, fisheye rendering.

The physical camera is robosuite's Panda ``robot0_eye_in_hand`` (in ``robot0_right_hand``, 5 cm off the flange
axis, looking along the gripper's approach axis). We keep its pose and replace its 75° pinhole lens by UMI's
GoPro fisheye (Kannala–Brandt; ``umi_aug/assets/gopro_intrinsics_2_7k.json`` scaled to the policy resolution,
UMI's centre-square crop). The pose conversion MuJoCo → OpenCV axes goes through
:func:`umi_aug.sim.camera_frames.mujoco_to_opencv_camera` only.
"""

from __future__ import annotations

import numpy as np

from umi_aug.camera import FisheyeIntrinsics, gopro_intrinsics_2_7k
from umi_aug.errors import SimError
from umi_aug.sim.camera_frames import mujoco_to_opencv_camera
from umi_aug.sim.fisheye_renderer import FisheyeRenderer
from umi_aug.sim.raster import RasterOptions

__all__ = ["WRIST_CAMERA", "T_CAM_TCP", "NEAR_M", "FAR_M", "wrist_intrinsics", "camera_pose_cv", "WristFisheyeCamera"]

#: MuJoCo name of the wrist camera in robosuite's Panda model.
WRIST_CAMERA: str = "robot0_eye_in_hand"
#: Camera→TCP offset of robosuite's Panda (OpenCV camera axes, metres): the TCP is the grip site, 5 cm across
#: the flange axis from the camera (camera ``pos="0.05 0 0"`` in ``right_hand``) and 9.7 cm ahead of it along the
#: optical axis (grip site 0.097 m along the hand's z). Translation only, as UMI's ``T_cam_tcp``; tested against
#: :meth:`SquareEnv.T_cam_tcp`.
T_CAM_TCP: np.ndarray = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.05], [0.0, 0.0, 1.0, 0.097],
                                  [0.0, 0.0, 0.0, 1.0]])
T_CAM_TCP.setflags(write=False)
#: Clip planes of the fisheye cube faces, metres (the fingers are ~4 cm from the camera; the room ~3 m).
NEAR_M: float = 0.005
FAR_M: float = 10.0


def wrist_intrinsics(size: int = 224) -> FisheyeIntrinsics:
    """UMI GoPro 2.7k fisheye scaled to UMI's ``size × size`` policy image (224 default, 84 option)."""
    if int(size) < 8:
        raise SimError(f"wrist_intrinsics: image size must be >= 8 pixels, got {size!r}")
    return gopro_intrinsics_2_7k().umi_policy(int(size))


def camera_pose_cv(model, data, camera: str = WRIST_CAMERA) -> np.ndarray:
    """World pose of a MuJoCo camera with OpenCV axes (x right, y down, z forward), metres.

    Args:
        model, data: raw ``mujoco.MjModel`` / ``mujoco.MjData`` (kinematics up to date).
        camera: camera name.
    Returns:
        T_world_cam: np.ndarray,  # [4, 4]
    """
    import mujoco  # lazy, optional dependency: mujoco

    cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    if cid < 0:
        raise SimError(f"camera_pose_cv: the model has no camera named {camera!r}")
    T = np.eye(4)
    T[:3, :3] = np.asarray(data.cam_xmat[cid], dtype=np.float64).reshape(3, 3)
    T[:3, 3] = data.cam_xpos[cid]
    return mujoco_to_opencv_camera(T)


class WristFisheyeCamera:
    """A :class:`~umi_aug.sim.fisheye_renderer.FisheyeRenderer` bound to one ``MjModel`` (RGB only).

    Args:
        model: raw ``mujoco.MjModel`` of the environment.
        size: output image size (square).
    """

    def __init__(self, model, size: int = 224) -> None:
        self.model = model
        self.intr = wrist_intrinsics(size)
        self.size = int(size)
        self.renderer = FisheyeRenderer(model, self.intr, options=RasterOptions(near=NEAR_M, far=FAR_M))

    def render(self, data, T_world_cam: np.ndarray) -> np.ndarray:
        """Fisheye RGB of ``data``'s scene seen from ``T_world_cam``.

        Args:
            data: raw ``mujoco.MjData`` (kinematics up to date).
            T_world_cam: np.ndarray,  # [4, 4] OpenCV axes, metres
        Returns:
            rgb: np.ndarray,  # [size, size, 3] uint8; black outside the image circle
        """
        return self.renderer.render(T_world_cam, data, rgb=True, depth=False).rgb

    def close(self) -> None:
        """Free the GL context."""
        self.renderer.close()
