"""A simulated UR5e behind the deployment interfaces (``robot=sim_ur5e``): arm, gripper and wrist camera, each
in its own process like the real backends, so the runner code is the same for sim and real.

One module per role, each implementing a Protocol of :mod:`umi_aug.deploy.interfaces`:

* **arm** (:mod:`umi_aug.deploy.sim_arm`): MuJoCo UR5e physics (:class:`UR5eSim`) and the servo loop that
  mirrors ur-rtde's controller process (:class:`SimServoLoop`, :class:`StopRamp`) behind
  :class:`SimUR5eRobot` (``RobotInterface``);
* **gripper** (:mod:`umi_aug.deploy.sim_gripper`): :class:`SimGripper` (``GripperInterface``), the WSG-50 loop
  driving :class:`SimFingerDriver`;
* **camera** (:mod:`umi_aug.deploy.sim_camera`): :class:`SimFisheyeCamera` (``CameraInterface``), the tabletop
  scene rendered through the GoPro fisheye into the policy image.

This module gathers their public names, the ones configs, the deploy app and the tests import.
"""

from umi_aug.deploy.sim_arm import (
    JOINT_NAMES,
    TCP_SITE,
    SimServoLoop,
    SimURConfig,
    SimUR5eRobot,
    StopRamp,
    UR5eSim,
    base_pose_matrix,
    stop_on_signal,
    stop_time_bound,
    ur5e_fk_dh,
    ur5e_mjcf_path,
)
from umi_aug.deploy.sim_camera import SimCameraConfig, SimFisheyeCamera
from umi_aug.deploy.sim_gripper import SimFingerDriver, SimGripper, SimGripperConfig

__all__ = ["SimURConfig", "SimGripperConfig", "SimCameraConfig", "UR5eSim", "SimServoLoop", "SimUR5eRobot",
           "SimFingerDriver", "SimGripper", "SimFisheyeCamera", "ur5e_mjcf_path", "base_pose_matrix", "ur5e_fk_dh",
           "JOINT_NAMES", "TCP_SITE", "StopRamp", "stop_on_signal", "stop_time_bound"]
