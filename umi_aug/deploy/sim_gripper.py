"""The simulated gripper (:class:`SimGripper`): a two-finger parallel gripper, position controlled, width in
metres, its fingers move at most ``max_speed``; driven by the WSG-50's control loop (:func:`~umi_aug.deploy.
gripper_process.run_gripper_loop`) through a simulated driver, so it is the WSG-50 interface and timing.

One of the three roles of the simulated UR5e (:mod:`umi_aug.deploy.sim_ur5e`); :class:`SimGripper` implements
:class:`~umi_aug.deploy.interfaces.GripperInterface` through the host side it shares with the WSG-50 backend
(:class:`~umi_aug.deploy.gripper_process.GripperProcess`). Its process dies with the runner
(:func:`~umi_aug.deploy.device_process.child_setup`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from umi_aug.config_check import reject_unknown_keys, require_positive
from umi_aug.deploy.device_process import child_setup
from umi_aug.deploy.gripper_process import GripperProcess, run_gripper_loop
from umi_aug.deploy.shared_state import SharedStateBuffer
from umi_aug.errors import DeployError

__all__ = ["SimGripperConfig", "SimFingerDriver", "SimGripper"]


@dataclass
class SimGripperConfig:
    """The ``gripper:`` block of ``configs/robot/sim_ur5e.yaml`` (metres, seconds)."""

    obs_latency: float = 0.01
    action_latency: float = 0.1
    frequency: float = 30.0
    max_speed: float = 0.2
    max_width: float = 0.09  # the scene gripper's stroke
    width_init: float = 0.08
    home_to_open: bool = False

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any], where: str = "gripper") -> "SimGripperConfig":
        reject_unknown_keys(m, cls.__dataclass_fields__, where, DeployError)
        c = cls(**dict(m))
        require_positive(where, c, ("frequency", "max_speed", "max_width", "action_latency"), DeployError)
        if not (c.frequency <= 100 and 0 <= c.width_init <= c.max_width):
            raise DeployError(f"{where}: need frequency <= 100 Hz and 0 <= width_init <= max_width, got "
                              f"{c.frequency}, {c.width_init}, {c.max_width}")
        return c


class SimFingerDriver:
    """A parallel two-finger gripper answering the :class:`~umi_aug.deploy.wsg50.WSG50Driver` calls the control
    loop (:func:`~umi_aug.deploy.gripper_process.run_gripper_loop`) makes (millimetres): the jaw width moves towards the commanded position at most ``max_speed``."""

    def __init__(self, cfg: SimGripperConfig, clock: Any = time.monotonic) -> None:
        self.max_mm, self.speed_mm = 1000.0 * cfg.max_width, 1000.0 * cfg.max_speed
        self.pos = self.target = 1000.0 * cfg.width_init
        self.vel = 0.0
        self.clock = clock
        self.t = clock()

    def _advance(self) -> None:
        t = self.clock()
        step = float(np.clip(self.target - self.pos, -self.speed_mm * (t - self.t), self.speed_mm * (t - self.t)))
        self.vel = step / (t - self.t) if t > self.t else 0.0
        self.pos += step
        self.t = t

    def ack_fault(self) -> None:
        pass

    def homing(self, positive: bool = True) -> None:
        """Open (``positive``) or close fully, blocking until there (as the WSG-50's homing)."""
        self.target = self.max_mm if positive else 0.0
        while abs(self.pos - self.target) > 1e-6:
            time.sleep(0.005)
            self._advance()

    def measure(self) -> dict[str, float]:
        self._advance()
        return {"state": 0, "position": self.pos, "velocity": self.vel, "force": 0.0, "gripper_time": self.t}

    def position_pd(self, position_mm: float, velocity_mm_s: float, *_: float, **__: float) -> dict[str, float]:
        self._advance()
        self.target = float(np.clip(position_mm, 0.0, self.max_mm))
        return self.measure()


def _sim_gripper_main(cfg: SimGripperConfig, commands: Any, state: SharedStateBuffer, stop_event: Any,
                      errors: Any, enabled: Any, parent_pid: int) -> None:
    child_setup(parent_pid)
    try:
        run_gripper_loop(SimFingerDriver(cfg), cfg, commands, state, stop_event, enabled, parent_pid)
    except BaseException as exc:  # noqa: BLE001 - reported to the runner
        errors.put(f"{type(exc).__name__}: {exc}")


class SimGripper(GripperProcess):
    """:class:`~umi_aug.deploy.interfaces.GripperInterface` of the simulated gripper (the gripper process host side
    and the WSG-50's loop, a simulated driver)."""

    process_main = staticmethod(_sim_gripper_main)

    def __init__(self, cfg: SimGripperConfig, ctx: Any = None, connect_timeout_s: float = 10.0) -> None:
        super().__init__(cfg, "simulated gripper", ctx, connect_timeout_s)
