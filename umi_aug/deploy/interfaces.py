"""The small interfaces the runner talks to. The real backends (ur-rtde, WSG-50, UVC), the simulated ones (MuJoCo
UR5e, simulated gripper, rendered fisheye camera) and test doubles implement them; none subclasses another
backend. The arms share their host side (:class:`~umi_aug.deploy.arm_process.ArmProcess`), the grippers theirs
(:class:`~umi_aug.deploy.gripper_process.GripperProcess`). The Protocols are ``runtime_checkable``
(``isinstance`` checks that the members exist, not their signatures).

All timestamps are seconds on the runner's clock (``time.monotonic`` for real backends), already corrected for
the device's observation latency (``receive time − obs_latency``).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["RobotInterface", "GripperInterface", "CameraInterface"]


@runtime_checkable
class RobotInterface(Protocol):
    def get_states(self, n: int) -> dict[str, np.ndarray]:
        """Last ``n`` states, oldest first: ``timestamp`` [k], ``tcp_pose`` [k, 6] (base frame, m / rotvec)."""

    def schedule_waypoint(self, pose: np.ndarray, t: float) -> None:
        """Reach TCP ``pose`` [6] at time ``t`` (through the controller's speed-limited interpolator)."""

    def check_ok(self) -> None:
        """Raise :class:`~umi_aug.deploy.safety.SafetyStop` if the robot cannot be commanded (protective or
        emergency stop, safety mode not normal, controller process dead, watchdog)."""

    def stop(self) -> None:
        """Halt motion and release the robot (idempotent; safe on every exit path)."""


@runtime_checkable
class GripperInterface(Protocol):
    def get_states(self, n: int) -> dict[str, np.ndarray]:
        """Last ``n`` states, oldest first: ``timestamp`` [k], ``width`` [k] (m)."""

    def schedule_waypoint(self, width: float, t: float) -> None:
        """Reach jaw opening ``width`` (m) at time ``t``."""

    def check_ok(self) -> None: ...

    def stop(self) -> None: ...


@runtime_checkable
class CameraInterface(Protocol):
    fps: float

    def get_frames(self, n: int) -> dict[str, np.ndarray]:
        """Last ``n`` frames, oldest first: ``timestamp`` [k], ``rgb`` [k, S, S, 3] uint8 (policy image)."""

    def stop(self) -> None: ...
