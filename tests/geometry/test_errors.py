import numpy as np
import pytest

import umi_aug.geometry as g
from umi_aug.errors import GeometryError

I3, I4 = np.eye(3), np.eye(4)
NAN3 = np.array([0.0, np.nan, 0.0])

CASES = [
    (g.hat, (np.zeros(4),), "v"),
    (g.vee, (np.zeros((3, 4)),), "M"),
    (g.so3_exp, (np.zeros((5, 2)),), "rotvec"),
    (g.so3_exp, (NAN3,), "rotvec"),
    (g.so3_exp, (np.array([np.inf, 0, 0]),), "rotvec"),
    (g.so3_log, (np.zeros((2, 3)),), "R"),
    (g.so3_log, (np.full((3, 3), np.nan),), "R"),
    (g.so3_left_jacobian, (np.zeros(2),), "phi"),
    (g.rotation_geodesic_distance, (I3, np.zeros((3,))), "R2"),
    (g.project_to_rotation, (np.zeros((4, 4)),), "M"),
    (g.make_pose, (I3, np.zeros(4)), "t"),
    (g.make_pose, (np.eye(3)[None].repeat(2, 0), np.zeros((3, 3))), "broadcast"),
    (g.pose_inverse, (I3,), "T"),
    (g.transform_points, (I4, np.zeros((4, 2))), "p"),
    (g.pos_rotvec_to_pose, (np.zeros(7),), "pose6"),
    (g.pos_rotvec_to_pose, (np.r_[NAN3, NAN3],), "pose6"),
    (g.pose_to_pos_rotvec, (np.zeros((4, 3)),), "T"),
    (g.se3_exp, (np.zeros(3),), "xi"),
    (g.se3_log, (np.zeros(6),), "T"),
    (g.quat_wxyz_to_matrix, (np.zeros(4),), "quat_wxyz"),
    (g.quat_wxyz_to_matrix, (np.zeros(3),), "quat_wxyz"),
    (g.quat_xyzw_to_matrix, (np.zeros(4),), "quat_xyzw"),
    (g.pos_quat_wxyz_to_pose, (np.zeros(3), np.zeros(4)), "quat_wxyz"),
    (g.pos_quat_xyzw_to_pose, (np.zeros(2), np.r_[0, 0, 0, 1.0]), "pos"),
    (g.matrix_to_quat_wxyz, (np.zeros(9),), "R"),
    (g.mat_to_rot6d, (np.zeros(6),), "R"),
    (g.rot6d_to_mat, (np.zeros(9),), "d6"),
    (g.rot6d_to_mat, (np.r_[NAN3, NAN3],), "d6"),
    (g.pos_rot6d_to_pose, (np.zeros(6),), "p9"),
    (g.slerp_rotations, (I3, I3, np.nan), "s"),
    (g.interpolate_pose, (I4, np.zeros((4, 3)), 0.5), "T1"),
    (g.relative_pose, (I3, I4), "T_base"),
    (g.absolute_pose, (I4, np.full((4, 4), np.nan)), "T_rel"),
    (g.convert_pose_representation, (I4, I3, "relative"), "base_pose"),
    (g.tcp_poses_from_camera_poses, (I3,), "T_world_cam"),
    (g.camera_poses_from_tcp_poses, (I4, I3), "T_cam_tcp"),
    (g.look_at_rotation, (np.zeros(3), np.ones(2), np.ones(3)), "target"),
    (g.so3_exp, ("abc",), "rotvec"),
]


@pytest.mark.parametrize("func,args,name", CASES, ids=[f"{c[0].__name__}-{c[2]}-{i}" for i, c in enumerate(CASES)])
def test_bad_input_raises_geometry_error(func, args, name):
    with pytest.raises(GeometryError) as exc:
        func(*args)
    assert name in str(exc.value)
    assert isinstance(exc.value, ValueError)


def test_shape_message_names_shape_and_expectation():
    with pytest.raises(GeometryError, match=r"so3_exp: `rotvec` has shape \(5, 2\); expected \[\.\.\., 3\]"):
        g.so3_exp(np.zeros((5, 2)))


def test_any_float_input_returns_float64(rng):
    for dt in (np.float16, np.float32, np.int64):
        v = (rng.normal(size=(3, 3)) * 2).astype(dt)
        assert g.so3_exp(v).dtype == np.float64
    assert g.so3_exp([0.1, 0.2, 0.3]).shape == (3, 3)
