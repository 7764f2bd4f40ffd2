"""UR arm through ur-rtde (UMI's ``RTDEInterpolationController``), in its own process.

The controller loop runs at the controller rate (500 Hz e-Series, 125 Hz CB3): each period it samples the
pose-trajectory interpolator at ``now`` and sends ``servoL(pose, 0.5, 0.5, dt, lookahead_time, gain)`` (positional,
as UMI), pushes the measured state (``timestamp = receive time − obs_latency``) into a shared ring buffer and
drains scheduled waypoints. Added to UMI: protective-stop / e-stop / safety-mode checks every period, a watchdog
on the runner's heartbeat (host side), ur-rtde's robot-side watchdog (``setWatchdog`` at connect, ``kickWatchdog``
every period: the robot stops itself when this process dies), and ``servoStop`` → ``stopScript`` → ``disconnect``
on every exit path (also errors).
The loop starts observe-only (receive interface only, nothing sent) and opens the control interface on
``("enable",)`` (:class:`URServoLoop`).

``rtde_control`` / ``rtde_receive`` are imported by name inside the loop (``URConfig.rtde_modules``), so tests
can inject fakes at the Python module boundary.
"""

from __future__ import annotations

import importlib
import logging
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from umi_aug.config_check import reject_unknown_keys
from umi_aug.deploy.clock import Clock, MonotonicClock
from umi_aug.deploy.arm_process import ArmProcess, drain_waypoint_commands
from umi_aug.deploy.device_process import child_setup, parent_alive, poll_enable
from umi_aug.deploy.interpolator import PoseTrajectoryInterpolator
from umi_aug.deploy.safety import SafetyStop, check_robot_limits
from umi_aug.deploy.shared_state import SharedStateBuffer
from umi_aug.errors import DeployError

__all__ = ["URConfig", "URServoLoop", "URRTDERobot", "SAFETY_MODES"]

log = logging.getLogger(__name__)

CONTROL_RATE_HZ = {"ur5e": 500.0, "ur10e": 500.0, "ur3e": 500.0, "ur16e": 500.0, "ur5": 125.0, "ur10": 125.0,
                   "ur3": 125.0}
# ur-rtde getSafetyMode() values (UR client interface): only NORMAL and REDUCED allow motion
SAFETY_MODES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
                6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
                10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
                13: "SYSTEM_THREE_POSITION_ENABLING_STOP"}


@dataclass
class URConfig:
    """The ``robot:`` block of ``configs/robot/ur5e.yaml`` (UMI's ``eval_robots_config.yaml`` fields + limits).

    Attributes:
        robot_ip: controller address. robot_type: ur5e/ur5/... (sets the control rate).
        tcp_offset: TCP along the flange z axis (m) → ``setTcp([0, 0, tcp_offset, 0, 0, 0])``.
        obs_latency: subtracted from state receive times (s). action_latency: used by the runner (s).
        lookahead_time: servoL lookahead, [0.03, 0.2] s. gain: servoL gain, [100, 2000].
        max_pos_speed, max_rot_speed: interpolator limits (m/s, rad/s), bounded by
            :data:`~umi_aug.deploy.safety.BOUNDS` (1 m/s, π rad/s) unless ``allow_fast_speeds`` (UMI's
            2·√3 m/s, 6·√3 rad/s).
        watchdog_s: stop when the runner process has not beaten the heartbeat for this long (s, in [0.2, 1]):
            it is dead or frozen (a heartbeat thread beats every 0.1 s; a slow policy does not trip it).
        watchdog_min_frequency: the robot-side watchdog (Hz, in [1, 50]): ``setWatchdog(min_frequency)`` right
            after the optional ``moveJ``, ``kickWatchdog()`` every control period; when kicks stop for longer
            than ``1 / min_frequency`` s (this controller process died or froze, the cable dropped), the robot's
            own program stops the arm — the one stop that does not need the host. ur-rtde's default is 10 Hz.
        joints_init: optional start joints (deg) reached with moveJ before servoing.
        rtde_modules: module names providing ``RTDEControlInterface`` / ``RTDEReceiveInterface``.
    """

    robot_ip: str = "192.168.0.8"
    robot_type: str = "ur5e"
    tcp_offset: float = 0.235
    obs_latency: float = 0.0001
    action_latency: float = 0.1
    lookahead_time: float = 0.1
    gain: float = 300.0
    max_pos_speed: float = 0.25
    max_rot_speed: float = 0.6
    watchdog_s: float = 1.0
    watchdog_min_frequency: float = 10.0
    joints_init: list[float] | None = None
    allow_fast_speeds: bool = False
    rtde_modules: list[str] = field(default_factory=lambda: ["rtde_control", "rtde_receive"])

    @property
    def frequency(self) -> float:
        return CONTROL_RATE_HZ[self.robot_type]

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any], where: str = "robot") -> "URConfig":
        """Validated config; one :class:`DeployError` naming the key and value otherwise."""
        reject_unknown_keys(m, cls.__dataclass_fields__, where, DeployError)
        c = cls(**{k: (list(v) if k in ("joints_init", "rtde_modules") and v is not None else v)
                   for k, v in m.items()})
        if c.robot_type not in CONTROL_RATE_HZ:
            raise DeployError(f"{where}.robot_type={c.robot_type!r}; expected one of {sorted(CONTROL_RATE_HZ)}")
        if not 0.03 <= c.lookahead_time <= 0.2:
            raise DeployError(f"{where}.lookahead_time={c.lookahead_time} must be in [0.03, 0.2] s (ur-rtde servoL)")
        if not 100 <= c.gain <= 2000:
            raise DeployError(f"{where}.gain={c.gain} must be in [100, 2000] (ur-rtde servoL)")
        check_robot_limits(c, where)
        if not 0 <= c.tcp_offset < 0.5:
            raise DeployError(f"{where}.tcp_offset={c.tcp_offset} m must be in [0, 0.5)")
        if c.joints_init is not None and len(c.joints_init) != 6:
            raise DeployError(f"{where}.joints_init must be 6 joint angles (deg), got {c.joints_init}")
        if len(c.rtde_modules) != 2:
            raise DeployError(f"{where}.rtde_modules must name 2 modules, got {c.rtde_modules}")
        return c


def check_robot_safety(rr: Any) -> None:
    """Raise :class:`SafetyStop` when the receive interface reports a stop or a non-normal safety mode."""
    if not rr.isConnected():
        raise SafetyStop("lost the RTDE connection to the robot")
    if rr.isEmergencyStopped():
        raise SafetyStop("robot emergency stop is active; release it and restart the runner")
    if rr.isProtectiveStopped():
        raise SafetyStop("robot is in protective stop (collision or limit); unlock it on the pendant and restart")
    mode = int(rr.getSafetyMode())
    if mode not in (1, 2):
        raise SafetyStop(f"robot safety mode is {SAFETY_MODES.get(mode, mode)} ({mode}); only NORMAL/REDUCED allow "
                         f"motion")


class URServoLoop:
    """The controller loop (process-independent so tests can run it in-thread with a fake clock).

    Two phases. **Observe-only** (from the start): only the receive interface is open; every period the measured
    state is published (``target_pose`` = the measured pose); nothing is sent to the robot (a dry run stays
    here). **Control** (after an ``("enable",)`` command): the control interface is opened (ur-rtde uploads and
    starts its program on the robot), ``setTcp``, optional ``moveJ``, then ``servoL`` every period.

    Args:
        cfg: robot config. commands: queue of ``("enable",)`` / ``("waypoint", pose[6], t)`` / ``("stop",)``.
        state: ring buffer with :data:`~umi_aug.deploy.arm_process.STATE_FIELDS`. stop_event: set → leave the loop
            cleanly.
        heartbeat: shared double, last runner heartbeat time (host-side watchdog). clock: the time base.
        enabled: shared int set to 1 once servoing (None: not reported). parent_pid: the runner's pid; the loop
            stops when it is no longer the parent (None: not checked).
    """

    def __init__(self, cfg: URConfig, commands: Any, state: SharedStateBuffer, stop_event: Any, heartbeat: Any,
                 clock: Clock | None = None, enabled: Any = None, parent_pid: int | None = None) -> None:
        self.cfg, self.commands, self.state, self.stop_event = cfg, commands, state, stop_event
        self.heartbeat = heartbeat
        self.clock = clock or MonotonicClock()
        self.enabled, self.parent_pid = enabled, parent_pid

    def run(self) -> None:
        """Connect read-only, observe until enabled, then servo until stopped. Once the control interface is
        open, every exit runs ``servoStop``/``stopScript``/``disconnect``. Errors propagate."""
        cfg = self.cfg
        mod_c, mod_r = (importlib.import_module(n) for n in cfg.rtde_modules)
        rr = mod_r.RTDEReceiveInterface(cfg.robot_ip, cfg.frequency)
        rc = None
        try:
            if self._observe(rr):
                rc = mod_c.RTDEControlInterface(cfg.robot_ip, cfg.frequency)
                self._servo(rc, rr)
        finally:
            steps = [("receive.disconnect", rr.disconnect)]
            if rc is not None:
                steps = [("servoStop", lambda: rc.servoStop()), ("stopScript", rc.stopScript),
                         ("disconnect", rc.disconnect)] + steps
            for name, fn in steps:
                try:
                    fn()
                except Exception as exc:  # noqa: BLE001 - every stop step must run
                    log.error("ur-rtde %s failed: %s", name, exc)

    def _check_host(self, t_now: float) -> None:
        """Host-side watchdog: the runner's heartbeat is fresh and the runner is still this process's parent."""
        age = t_now - float(self.heartbeat.value)
        if age > self.cfg.watchdog_s:
            raise SafetyStop(f"watchdog: no heartbeat from the runner for {age:.2f} s > robot.watchdog_s="
                             f"{self.cfg.watchdog_s}")
        if not parent_alive(self.parent_pid):
            raise SafetyStop(f"the runner process {self.parent_pid} died")

    def _publish(self, rr: Any, t_recv: float, target: Any) -> None:
        self.state.put({"timestamp": t_recv - self.cfg.obs_latency, "tcp_pose": rr.getActualTCPPose(),
                        "tcp_speed": rr.getActualTCPSpeed(), "q": rr.getActualQ(), "qd": rr.getActualQd(),
                        "target_pose": target})

    def _observe(self, rr: Any) -> bool:
        """Observe-only phase (receive interface only). Returns True on ``("enable",)``, False on stop."""
        dt = 1.0 / self.cfg.frequency
        while not self.stop_event.is_set():
            t_now = self.clock.now()
            self._check_host(t_now)
            check_robot_safety(rr)
            cmd = poll_enable(self.commands)
            if cmd is not None:
                return cmd == "enable"
            self._publish(rr, self.clock.now(), rr.getActualTCPPose())
            self.clock.sleep_until(t_now + dt)
        return False

    def _servo(self, rc: Any, rr: Any) -> None:
        cfg = self.cfg
        dt = 1.0 / cfg.frequency
        rc.setTcp([0.0, 0.0, float(cfg.tcp_offset), 0.0, 0.0, 0.0])
        check_robot_safety(rr)
        if cfg.joints_init is not None:  # blocking: the watchdog is set after it (it would trip during moveJ)
            rc.moveJ(list(np.deg2rad(cfg.joints_init)), 1.05, 1.4)
        # robot-side watchdog: the robot's program stops the arm when this process stops kicking it
        rc.setWatchdog(float(cfg.watchdog_min_frequency))
        rc.kickWatchdog()
        t_now = self.clock.now()
        interp = PoseTrajectoryInterpolator([t_now], [np.asarray(rr.getActualTCPPose(), float)])
        last_wp: float | None = None
        if self.enabled is not None:
            self.enabled.value = 1
        while not self.stop_event.is_set():
            t_period = rc.initPeriod()
            t_now = self.clock.now()
            check_robot_safety(rr)
            self._check_host(t_now)
            pose = interp(t_now)
            rc.kickWatchdog()
            if not rc.servoL(pose.tolist(), 0.5, 0.5, dt, cfg.lookahead_time, cfg.gain):
                raise SafetyStop("servoL was refused by the controller (program stopped? the robot-side watchdog "
                                 f"stops it when not kicked for 1/{cfg.watchdog_min_frequency} s)")
            self._publish(rr, self.clock.now(), pose)
            interp, last_wp, stop = drain_waypoint_commands(self.commands, interp, last_wp, t_now + dt,
                                                            cfg.max_pos_speed, cfg.max_rot_speed)
            if stop:
                return
            rc.waitPeriod(t_period)


def _process_main(cfg: URConfig, heartbeat: Any, commands: Any, state: SharedStateBuffer, stop_event: Any,
                  errors: Any, enabled: Any, parent_pid: int) -> None:
    child_setup(parent_pid)
    try:
        URServoLoop(cfg, commands, state, stop_event, heartbeat, enabled=enabled, parent_pid=parent_pid).run()
    except BaseException as exc:  # noqa: BLE001 - reported to the runner
        errors.put(str(exc) if isinstance(exc, DeployError) else f"{type(exc).__name__}: {exc}")


class URRTDERobot(ArmProcess):
    """:class:`~umi_aug.deploy.interfaces.RobotInterface` of a UR arm: :class:`URServoLoop` in a child process behind
    the shared host side (:class:`~umi_aug.deploy.arm_process.ArmProcess`: state buffer, command queue, heartbeat).

    Times are ``time.monotonic`` seconds (one clock for all processes of the machine).
    """

    process_main = staticmethod(_process_main)

    def __init__(self, cfg: URConfig, ctx: Any = None, capacity: int = 2048, connect_timeout_s: float = 10.0) -> None:
        super().__init__(cfg, f"robot controller {cfg.robot_ip}", ctx, capacity, connect_timeout_s)
