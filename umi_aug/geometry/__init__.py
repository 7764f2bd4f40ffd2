"""Geometry stage: SO(3)/SE(3), quaternions, 6-D rotations, interpolation, UMI pose facts, cone sampling.

The numpy float64 API is exported here. The torch API lives in :mod:`umi_aug.geometry.so3_torch` and
:mod:`umi_aug.geometry.se3_torch` (import them explicitly; importing this package does not import torch).
Conventions: poses ``T_<to>_<from>`` (4×4, metres), rotation vectors in radians, quaternions named
``quat_wxyz`` / ``quat_xyzw``, 6-D rotation = first two ROWS of R. Bad input raises
:class:`umi_aug.errors.GeometryError`.
"""

from umi_aug.geometry.cone import (
    look_at_rotation,
    rotation_between_vectors,
    sample_cone_start_poses,
    sample_directions_in_cap,
    sample_rotations_in_ball,
)
from umi_aug.geometry.interp import PoseTrajectoryInterpolator, interpolate_pose, slerp_rotations
from umi_aug.geometry.relative import (
    POSE_REPRESENTATIONS,
    absolute_pose,
    convert_pose_representation,
    relative_pose,
)
from umi_aug.geometry.rot6d import mat_to_rot6d, pos_rot6d_to_pose, pose_to_pos_rot6d, rot6d_to_mat
from umi_aug.geometry.se3 import (
    make_pose,
    matrix_to_quat_wxyz,
    matrix_to_quat_xyzw,
    pos_quat_wxyz_to_pose,
    pos_quat_xyzw_to_pose,
    pos_rotvec_to_pose,
    pose_inverse,
    pose_to_pos_quat_wxyz,
    pose_to_pos_quat_xyzw,
    pose_to_pos_rotvec,
    quat_wxyz_to_matrix,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_matrix,
    quat_xyzw_to_wxyz,
    se3_exp,
    se3_log,
    transform_points,
)
from umi_aug.geometry.so3 import (
    hat,
    project_to_rotation,
    rotation_geodesic_distance,
    so3_exp,
    so3_left_jacobian,
    so3_left_jacobian_inv,
    so3_log,
    vee,
)
from umi_aug.geometry.umi import (
    UMI_CAM_TO_CENTER_HEIGHT,
    UMI_CAM_TO_MOUNT_OFFSET,
    UMI_TCP_OFFSET,
    camera_poses_from_tcp_poses,
    tcp_poses_from_camera_poses,
    umi_T_cam_tcp,
)

__all__ = [
    # so3
    "hat", "vee", "so3_exp", "so3_log", "so3_left_jacobian", "so3_left_jacobian_inv",
    "rotation_geodesic_distance", "project_to_rotation",
    # se3
    "make_pose", "pose_inverse", "transform_points", "pos_rotvec_to_pose", "pose_to_pos_rotvec",
    "se3_exp", "se3_log", "quat_wxyz_to_matrix", "matrix_to_quat_wxyz", "quat_xyzw_to_matrix",
    "matrix_to_quat_xyzw", "quat_wxyz_to_xyzw", "quat_xyzw_to_wxyz", "pose_to_pos_quat_wxyz",
    "pos_quat_wxyz_to_pose", "pose_to_pos_quat_xyzw", "pos_quat_xyzw_to_pose",
    # rot6d
    "mat_to_rot6d", "rot6d_to_mat", "pose_to_pos_rot6d", "pos_rot6d_to_pose",
    # interp
    "slerp_rotations", "interpolate_pose", "PoseTrajectoryInterpolator",
    # relative
    "relative_pose", "absolute_pose", "convert_pose_representation", "POSE_REPRESENTATIONS",
    # umi
    "umi_T_cam_tcp", "tcp_poses_from_camera_poses", "camera_poses_from_tcp_poses",
    "UMI_TCP_OFFSET", "UMI_CAM_TO_CENTER_HEIGHT", "UMI_CAM_TO_MOUNT_OFFSET",
    # cone
    "sample_directions_in_cap", "sample_rotations_in_ball", "look_at_rotation", "rotation_between_vectors",
    "sample_cone_start_poses",
]
