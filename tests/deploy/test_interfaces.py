"""Every robot / gripper / camera backend — real, simulated and the tests' doubles — implements its Protocol of
``umi_aug.deploy.interfaces`` (members present, the Protocol's parameters first and by name, any extra ones
optional), and no simulated backend subclasses a real one (they share neutral host-side bases instead)."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from tests.deploy.fakes import FakeCamera, KinematicGripper, KinematicRobot
from umi_aug.deploy.arm_process import ArmProcess
from umi_aug.deploy.camera import CameraConfig, UVCCamera
from umi_aug.deploy.clock import FakeClock
from umi_aug.deploy.gripper_process import GripperProcess
from umi_aug.deploy.interfaces import CameraInterface, GripperInterface, RobotInterface
from umi_aug.deploy.sim_arm import SimUR5eRobot, SimURConfig
from umi_aug.deploy.sim_camera import SimCameraConfig, SimFisheyeCamera
from umi_aug.deploy.sim_gripper import SimGripper, SimGripperConfig
from umi_aug.deploy.ur_rtde import URConfig, URRTDERobot
from umi_aug.deploy.wsg50 import WSG50Gripper, WSGConfig

BACKENDS = [(RobotInterface, URRTDERobot), (RobotInterface, SimUR5eRobot), (RobotInterface, KinematicRobot),
            (GripperInterface, WSG50Gripper), (GripperInterface, SimGripper), (GripperInterface, KinematicGripper),
            (CameraInterface, UVCCamera), (CameraInterface, SimFisheyeCamera), (CameraInterface, FakeCamera)]


def _methods(proto: type) -> list[str]:
    return [n for n, v in vars(proto).items() if callable(v) and not n.startswith("_")]


@pytest.mark.parametrize("proto, cls", BACKENDS, ids=[c.__name__ for _, c in BACKENDS])
def test_backend_class_has_the_protocols_methods_and_signatures(proto, cls):
    assert _methods(proto), proto
    for name in _methods(proto):
        impl = getattr(cls, name, None)
        assert callable(impl), f"{cls.__name__} has no method {name}"
        want = list(inspect.signature(getattr(proto, name)).parameters.values())[1:]  # without self
        got = list(inspect.signature(impl).parameters.values())[1:]
        assert [p.name for p in got[:len(want)]] == [p.name for p in want], (cls.__name__, name, got, want)
        extra = got[len(want):]
        assert all(p.default is not p.empty or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD) for p in extra), \
            (cls.__name__, name, extra)


def test_backend_instances_satisfy_the_runtime_checkable_protocols():
    """Built, not started (no process, no device): ``isinstance`` against each Protocol, the camera's ``fps``
    attribute included."""
    robots = [URRTDERobot(URConfig()), SimUR5eRobot(SimURConfig()), KinematicRobot(FakeClock(), np.zeros(6))]
    grippers = [WSG50Gripper(WSGConfig()), SimGripper(SimGripperConfig()), KinematicGripper(FakeClock())]
    cameras = [UVCCamera(CameraConfig()), SimFisheyeCamera(SimCameraConfig(), robots[1], grippers[1], np.eye(4)),
               FakeCamera(FakeClock())]
    for proto, objs in ((RobotInterface, robots), (GripperInterface, grippers), (CameraInterface, cameras)):
        for obj in objs:
            assert isinstance(obj, proto), (type(obj).__name__, proto.__name__)
    assert not isinstance(cameras[0], RobotInterface)  # the check is not vacuous
    assert all(isinstance(c.fps, float) for c in cameras[:2])


def test_simulated_backends_do_not_subclass_real_ones():
    real = (URRTDERobot, WSG50Gripper, UVCCamera)
    for sim in (SimUR5eRobot, SimGripper, SimFisheyeCamera):
        assert not issubclass(sim, real), sim.__mro__
    assert issubclass(SimUR5eRobot, ArmProcess) and issubclass(URRTDERobot, ArmProcess)
    assert issubclass(SimGripper, GripperProcess) and issubclass(WSG50Gripper, GripperProcess)
