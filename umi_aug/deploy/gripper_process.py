"""The gripper control loop and the host side of a gripper process, shared by the WSG-50 and the simulated gripper.

:func:`run_gripper_loop` is UMI's ``WSGController`` loop on any driver that answers the WSG-50 calls (in
millimetres: :class:`umi_aug.deploy.wsg50.WSG50Driver`, or :class:`umi_aug.deploy.sim_gripper.SimFingerDriver`);
:class:`GripperProcess` implements :class:`~umi_aug.deploy.interfaces.GripperInterface` on top of
:class:`~umi_aug.deploy.device_process.DeviceProcess` with the state ring buffer :data:`GRIPPER_STATE_FIELDS`.
Widths are metres, times ``time.monotonic`` seconds.
"""

from __future__ import annotations

import queue
import time
from typing import Any, Callable

from umi_aug.deploy.device_process import DeviceProcess, parent_alive, poll_enable
from umi_aug.deploy.interpolator import PoseTrajectoryInterpolator
from umi_aug.deploy.safety import SafetyStop
from umi_aug.deploy.shared_state import SharedStateBuffer

__all__ = ["GripperProcess", "GRIPPER_STATE_FIELDS", "run_gripper_loop"]

#: Record layout of the gripper state ring buffer (m, m/s, N).
GRIPPER_STATE_FIELDS = {"timestamp": 1, "width": 1, "velocity": 1, "force": 1, "target": 1}


def run_gripper_loop(drv: Any, cfg: Any, commands: Any, state: SharedStateBuffer, stop_event: Any,
                     enabled: Any = None, parent_pid: int | None = None) -> None:
    """The gripper control loop (UMI's ``WSGController``) on a connected driver, every ``1/cfg.frequency`` s.

    Observe-only until an ``("enable",)`` command: only ``measure`` (a read) and the state is published. Then
    ``ack_fault``, ``homing`` when ``cfg.home_to_open``, ``enabled.value = 1`` and, every period, track the width
    interpolator (position + feed-forward velocity, ``position_pd``), push the measured state (``timestamp =
    receive time − obs_latency``) and drain scheduled ``("waypoint", width_m, t)`` commands. ``drv`` has the
    :class:`~umi_aug.deploy.wsg50.WSG50Driver` methods ``ack_fault``, ``homing``, ``measure``, ``position_pd``
    (millimetres): the WSG-50's client or the simulated gripper's
    :class:`~umi_aug.deploy.sim_gripper.SimFingerDriver`. The loop ends on ``stop_event`` or a ``("stop",)``
    command, or with :class:`~umi_aug.deploy.safety.SafetyStop` when ``parent_pid`` is no longer this process's
    parent."""
    dt = 1.0 / cfg.frequency

    def publish(info: dict[str, float], target: float) -> None:
        state.put({"timestamp": time.monotonic() - cfg.obs_latency, "width": info["position"] / 1000.0,
                   "velocity": info["velocity"] / 1000.0, "force": info["force"], "target": target})

    def check_parent() -> None:
        if not parent_alive(parent_pid):
            raise SafetyStop(f"the runner process {parent_pid} died")

    t_next = time.monotonic()
    while True:  # observe-only
        if stop_event.is_set():
            return
        check_parent()
        cmd = poll_enable(commands)
        if cmd == "stop":
            return
        if cmd == "enable":
            break
        info = drv.measure()
        publish(info, info["position"] / 1000.0)
        t_next += dt
        time.sleep(max(0.0, t_next - time.monotonic()))
    drv.ack_fault()
    if cfg.home_to_open:
        drv.homing(True)
    info = drv.measure()
    w0 = info["position"] / 1000.0
    publish(info, w0)
    interp = PoseTrajectoryInterpolator([time.monotonic()], [[w0, 0, 0, 0, 0, 0]])
    last_wp = None
    if enabled is not None:
        enabled.value = 1
    t_start, it = time.monotonic(), 0
    while not stop_event.is_set():
        check_parent()
        t_now = time.monotonic()
        w = float(interp(t_now + dt)[0])
        v = (w - float(interp(t_now)[0])) / dt
        publish(drv.position_pd(w * 1000.0, v * 1000.0), w)
        while True:
            try:
                cmd = commands.get_nowait()
            except queue.Empty:
                break
            if cmd[0] == "stop":
                return
            if cmd[0] != "waypoint":
                continue
            _, width, t_wp = cmd
            interp = interp.schedule_waypoint([width, 0, 0, 0, 0, 0], t_wp, cfg.max_speed, 1.0, t_now, last_wp)
            last_wp = t_wp
        it += 1
        time.sleep(max(0.0, t_start + it * dt - time.monotonic()))


class GripperProcess(DeviceProcess):
    """:class:`~umi_aug.deploy.interfaces.GripperInterface` backed by a gripper loop in a child process.

    Subclasses set :attr:`process_main`, the child's entry point ``main(cfg, commands, state, stop_event, errors,
    enabled, parent_pid)`` (both run :func:`run_gripper_loop`, each on its own driver).

    Args:
        cfg: the gripper config. what: the device, for messages. ctx: multiprocessing context (default spawn).
        connect_timeout_s: wait for the first state this long (s).
    """

    process_main: Callable[..., None]

    def __init__(self, cfg: Any, what: str, ctx: Any = None, connect_timeout_s: float = 10.0) -> None:
        super().__init__(what, GRIPPER_STATE_FIELDS, 256, ctx, connect_timeout_s)
        self.cfg = cfg

    def start(self) -> None:
        self._start_process(self.process_main, self.cfg)

    def schedule_waypoint(self, width: float, t: float) -> None:
        """Queue jaw opening ``width`` (m) at ``t`` (s); refused before :meth:`enable` (observe-only)."""
        self._require_enabled("waypoint")
        self._cmd.put(("waypoint", float(width), float(t)))
