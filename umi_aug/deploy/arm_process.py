"""The host side of an arm controller that runs in a child process, shared by the real and the simulated arm.

:class:`ArmProcess` implements :class:`~umi_aug.deploy.interfaces.RobotInterface` on top of
:class:`~umi_aug.deploy.device_process.DeviceProcess`: the state ring buffer (:data:`STATE_FIELDS`), the command
queue (``("enable",)`` / ``("waypoint", pose[6], t)`` / ``("stop",)``) and a heartbeat the runner beats from a
thread (the controller's host-side watchdog). What runs in the child is the subclass's ``process_main``: ur-rtde's
servo loop (:class:`umi_aug.deploy.ur_rtde.URRTDERobot`) or the MuJoCo UR5e's
(:class:`umi_aug.deploy.sim_arm.SimUR5eRobot`). Both loops apply the queued waypoints with
:func:`drain_waypoint_commands`.

Times are ``time.monotonic`` seconds (one clock for all processes of the machine); poses are the TCP in the robot
base frame, ``[x, y, z, rx, ry, rz]`` (m, rotation vector).
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any, Callable

import numpy as np

from umi_aug.deploy.device_process import DeviceProcess
from umi_aug.deploy.interpolator import PoseTrajectoryInterpolator

__all__ = ["ArmProcess", "STATE_FIELDS", "drain_waypoint_commands"]

#: Record layout of the arm state ring buffer: receive time − obs_latency (s), TCP pose [6] and speed [6] (m, rad,
#: m/s, rad/s; base frame), joints [6] (rad) and their speeds (rad/s), the servo target pose [6].
STATE_FIELDS = {"timestamp": 1, "tcp_pose": 6, "tcp_speed": 6, "q": 6, "qd": 6, "target_pose": 6}
#: The runner's heartbeat period (s): far below every ``robot.watchdog_s`` (≥ 0.2 s).
HEARTBEAT_PERIOD_S = 0.1


def drain_waypoint_commands(commands: Any, interp: PoseTrajectoryInterpolator, last_wp: float | None,
                            curr_time: float, max_pos_speed: float, max_rot_speed: float
                            ) -> tuple[PoseTrajectoryInterpolator, float | None, bool]:
    """Apply every queued ``("waypoint", pose, t)`` command to the interpolator (UMI's ``schedule_waypoint``
    semantics, speed-limited, from ``curr_time`` = the next servo period, s); a ``("stop",)`` command ends the loop.

    Returns:
        (interpolator, time of the last scheduled waypoint, whether a stop was received)
    """
    while True:
        try:
            cmd = commands.get_nowait()
        except queue.Empty:
            return interp, last_wp, False
        if cmd[0] == "stop":
            return interp, last_wp, True
        if cmd[0] == "enable":  # already enabled
            continue
        _, wp, t_wp = cmd
        interp = interp.schedule_waypoint(np.asarray(wp, float), float(t_wp), max_pos_speed, max_rot_speed,
                                          curr_time=curr_time, last_waypoint_time=last_wp)
        last_wp = float(t_wp)


class ArmProcess(DeviceProcess):
    """:class:`~umi_aug.deploy.interfaces.RobotInterface` backed by a servo loop in a child process.

    Subclasses set :attr:`process_main`, the child's entry point ``main(cfg, heartbeat, commands, state,
    stop_event, errors, enabled, parent_pid)``; ``cfg`` travels to it (pickled) and needs ``watchdog_s``.

    Args:
        cfg: the robot config. what: the device, for messages. ctx: multiprocessing context (default spawn).
        capacity: state records kept. connect_timeout_s: wait for the first state this long (s).
    """

    process_main: Callable[..., None]

    def __init__(self, cfg: Any, what: str, ctx: Any = None, capacity: int = 2048,
                 connect_timeout_s: float = 10.0) -> None:
        super().__init__(what, STATE_FIELDS, capacity, ctx, connect_timeout_s)
        self.cfg = cfg
        self._heartbeat = self._ctx.Value("d", time.monotonic(), lock=False)
        self._beating = threading.Event()
        self._beat_thread: threading.Thread | None = None

    def start(self) -> None:
        """Start the controller process, wait for its first state, then beat the heartbeat from a thread of
        this process every 0.1 s (the watchdog catches a dead or frozen runner process, not a slow policy)."""
        self._heartbeat.value = time.monotonic() + self.connect_timeout_s  # grace while connecting
        self._start_process(self.process_main, self.cfg, self._heartbeat)
        self._beating.clear()
        self._beat_thread = threading.Thread(target=self._beat, name="arm_heartbeat", daemon=True)
        self._beat_thread.start()

    def _beat(self) -> None:
        while not self._beating.wait(HEARTBEAT_PERIOD_S):
            self.heartbeat()

    def stop(self) -> None:
        self._beating.set()
        super().stop()

    def heartbeat(self) -> None:
        self._heartbeat.value = time.monotonic()

    def get_states(self, n: int) -> dict[str, np.ndarray]:
        self.heartbeat()
        return self.state.latest(n)

    def schedule_waypoint(self, pose: np.ndarray, t: float) -> None:
        """Queue TCP ``pose`` [6] (base frame) at ``t`` (s); refused before :meth:`enable` (observe-only)."""
        self._require_enabled("waypoint")
        self.heartbeat()
        self._cmd.put(("waypoint", np.asarray(pose, float).reshape(6), float(t)))

    def check_ok(self) -> None:
        super().check_ok()
        self.heartbeat()
