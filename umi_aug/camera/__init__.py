"""Fisheye camera: Kannala–Brandt model (OpenCV fisheye = UMI GoPro JSON = ORB-SLAM3 KannalaBrandt8),
calibration files, cubemap → fisheye remap for simulated images, and UMI's predefined gripper/mirror masks.

numpy float64 API here; the torch versions of project/unproject/Jacobian live in
:mod:`umi_aug.camera.kb_torch` (importing this package does not import torch).
"""

from umi_aug.camera.calib_io import (
    gopro_intrinsics_2_7k,
    load_intrinsics,
    load_orbslam3_yaml,
    load_umi_intrinsics_json,
    orbslam3_gopro_intrinsics_960x720,
    save_umi_intrinsics_json,
)
from umi_aug.camera.cubemap import (
    FACE_NAMES,
    CubemapFisheyeRemap,
    default_face_size,
    face_intrinsics_matrix,
    face_pixel_rays,
    face_rotation,
)
from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.camera.kb import (
    kb_dtheta_d,
    kb_inverse_theta,
    kb_theta_d,
    project,
    project_jacobian,
    theta_fold,
    unproject,
)
from umi_aug.camera.masks import (
    canonical_to_pixel,
    draw_predefined_mask,
    finger_polygon,
    gripper_polygons,
    mirror_crop_slices,
    mirror_polygons,
    pixel_to_canonical,
    predefined_mask,
)

__all__ = [
    "FACE_NAMES",
    "CubemapFisheyeRemap",
    "FisheyeIntrinsics",
    "canonical_to_pixel",
    "default_face_size",
    "draw_predefined_mask",
    "face_intrinsics_matrix",
    "face_pixel_rays",
    "face_rotation",
    "finger_polygon",
    "gopro_intrinsics_2_7k",
    "gripper_polygons",
    "kb_dtheta_d",
    "kb_inverse_theta",
    "kb_theta_d",
    "load_intrinsics",
    "load_orbslam3_yaml",
    "load_umi_intrinsics_json",
    "mirror_crop_slices",
    "mirror_polygons",
    "orbslam3_gopro_intrinsics_960x720",
    "pixel_to_canonical",
    "predefined_mask",
    "project",
    "project_jacobian",
    "save_umi_intrinsics_json",
    "theta_fold",
    "unproject",
]
