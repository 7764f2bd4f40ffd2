"""(b) the ur-rtde backend against a fake rtde_control / rtde_receive injected at the module boundary."""

from __future__ import annotations

import json
import queue
import time

import numpy as np
import pytest

from tests.deploy import fake_rtde
from umi_aug.deploy.arm_process import STATE_FIELDS
from umi_aug.deploy.clock import FakeClock
from umi_aug.deploy.safety import SafetyStop
from umi_aug.deploy.shared_state import SharedStateBuffer
from umi_aug.deploy.ur_rtde import URConfig, URRTDERobot, URServoLoop
from umi_aug.errors import DeployError

FAKE = ["tests.deploy.fake_rtde", "tests.deploy.fake_rtde"]
STOP_SEQ = ["servoStop", "stopScript", "control.disconnect", "receive.disconnect"]


class _StopAfter:
    """stop_event stand-in: set once the fake has seen ``n`` servoL calls."""

    def __init__(self, n: int) -> None:
        self.n = n

    def is_set(self) -> bool:
        return sum(c[0] == "servoL" for c in fake_rtde.CALLS) >= self.n


class _Heartbeat:
    def __init__(self, clock: FakeClock, stale_after: float = np.inf) -> None:
        self.clock, self.stale_after = clock, stale_after

    @property
    def value(self) -> float:  # the runner keeps beating until stale_after, then goes silent
        return min(self.clock.now(), self.stale_after)


@pytest.fixture
def clock():
    fake_rtde.reset()
    fake_rtde.CLOCK = FakeClock(50.0)
    yield fake_rtde.CLOCK
    fake_rtde.CLOCK = None
    fake_rtde.reset()


def _loop(clock, host="fake", n=1000, stale_after=np.inf, **cfg_kw):
    cfg = URConfig.from_mapping({"robot_ip": host, "rtde_modules": FAKE, **cfg_kw})
    cmds: queue.Queue = queue.Queue()
    cmds.put(("enable",))  # leave the observe-only phase at once
    state = SharedStateBuffer(STATE_FIELDS, 4096)
    return URServoLoop(cfg, cmds, state, _StopAfter(n), _Heartbeat(clock, stale_after), clock), cmds, state


def _names():
    return [c[0] for c in fake_rtde.CALLS if c[0] not in ("receive.__init__", "kickWatchdog")]


def test_servol_rate_args_speed_limit_and_clean_stop(clock):
    loop, cmds, state = _loop(clock, n=1500, max_pos_speed=0.1, max_rot_speed=0.5, lookahead_time=0.05, gain=500)
    target = np.array(fake_rtde.POSE0) + [0.15, 0.0, 0.0, 0, 0, 0]
    cmds.put(("waypoint", target, 50.5))  # asks 0.3 m/s; the 0.1 m/s limit stretches it to 1.5 s
    loop.run()
    assert _names()[:3] == ["control.__init__", "setTcp", "setWatchdog"]
    calls = {c[0]: c for c in fake_rtde.CALLS}
    assert calls["setWatchdog"][2] == 10.0  # robot.watchdog_min_frequency (ur-rtde's default)
    assert calls["setTcp"][1] == [0, 0, 0.235, 0, 0, 0] and calls["control.__init__"][2] == 500.0
    servo = [c for c in fake_rtde.CALLS if c[0] == "servoL"]
    assert len(servo) == 1500
    t = np.array([c[1] for c in servo])
    assert np.allclose(np.diff(t), 1 / 500)  # one servoL per 2 ms period (e-Series rate)
    for c in servo:  # record = (name, time, pose, speed, acceleration, time, lookahead_time, gain), positional
        assert len(c) == 8 and c[3:] == (0.5, 0.5, 1 / 500, 0.05, 500.0)
    poses = np.array([c[2] for c in servo])
    steps = np.linalg.norm(np.diff(poses[:, :3], axis=0), axis=1)
    assert steps.max() <= 0.1 / 500 * (1 + 1e-6)  # max_pos_speed respected at every period
    assert steps.max() >= 0.1 / 500 * 0.99  # ... and used
    assert np.allclose(poses[-1], target, atol=1e-9)  # reached (1500 periods = 3 s > 1.5 s)
    reach_t = t[np.argmax(np.linalg.norm(poses[:, :3] - target[:3], axis=1) < 1e-9)]
    assert reach_t == pytest.approx(50.0 + 1.5, abs=2 / 500)
    assert _names()[-4:] == STOP_SEQ
    st = state.latest(10)
    assert np.allclose(st["tcp_pose"][-1], target) and np.all(np.diff(st["timestamp"]) > 0)


def test_cb3_rate(clock):
    loop, cmds, state = _loop(clock, n=20, robot_type="ur5")
    loop.run()
    t = np.array([c[1] for c in fake_rtde.CALLS if c[0] == "servoL"])
    assert np.allclose(np.diff(t), 1 / 125) and fake_rtde.CALLS[1][:3] == ("control.__init__", "fake", 125.0)


def test_exception_in_servol_still_runs_stop_sequence(clock):
    loop, cmds, state = _loop(clock, host="fake?raise_after=30")
    with pytest.raises(RuntimeError, match="socket error"):
        loop.run()
    assert _names()[-4:] == STOP_SEQ and _names().count("servoL") == 30


@pytest.mark.parametrize("host, msg", [
    ("fake?protective_after=40", "protective stop"),
    ("fake?estop_after=40", "emergency stop"),
    ("fake?safety_mode_after=40:5", "SAFEGUARD_STOP"),
    ("fake?disconnect_after=40", "lost the RTDE connection"),
])
def test_robot_safety_states_halt_cleanly(clock, host, msg):
    loop, cmds, state = _loop(clock, host=host)
    cmds.put(("waypoint", np.array(fake_rtde.POSE0) + [0.05, 0, 0, 0, 0, 0], 51.0))
    with pytest.raises(SafetyStop, match=msg):
        loop.run()
    assert _names().count("servoL") == 40  # no command after the stop was seen
    assert _names()[-4:] == STOP_SEQ


def test_watchdog(clock):
    loop, cmds, state = _loop(clock, stale_after=50.3, watchdog_s=0.5)
    with pytest.raises(SafetyStop, match="watchdog"):
        loop.run()
    t = [c[1] for c in fake_rtde.CALLS if c[0] == "servoL"]
    assert t[-1] == pytest.approx(50.8, abs=2 / 500) and _names()[-4:] == STOP_SEQ


def test_config_validation():
    with pytest.raises(DeployError, match="lookahead_time=0.5"):
        URConfig.from_mapping({"lookahead_time": 0.5})
    with pytest.raises(DeployError, match="gain=50"):
        URConfig.from_mapping({"gain": 50})
    with pytest.raises(DeployError, match="robot_type='ur7'"):
        URConfig.from_mapping({"robot_type": "ur7"})
    with pytest.raises(DeployError, match=r"unknown key\(s\) \['tcp_ofset'\]"):
        URConfig.from_mapping({"tcp_ofset": 0.2})


def _read_log(path):
    return [json.loads(line) for line in open(path)] if path.exists() else []


def test_process_backend_protective_stop_and_clean_exit(tmp_path):
    """The real child process (spawn) with the fake module: states flow back, waypoints flow in, a protective
    stop surfaces as one SafetyStop in the parent, and the child ran the stop sequence."""
    log = tmp_path / "calls.jsonl"
    # 1 Hz robot-side watchdog: a real-time child on a loaded machine may miss 0.1 s (ur-rtde's default 10 Hz)
    cfg = URConfig.from_mapping({"robot_ip": f"fake?protective_after=400&log={log}", "rtde_modules": FAKE,
                                 "watchdog_min_frequency": 1.0})
    robot = URRTDERobot(cfg, connect_timeout_s=60.0)
    try:
        robot.start()
        st = robot.get_states(5)
        assert np.allclose(st["tcp_pose"][-1], fake_rtde.POSE0)
        with pytest.raises(SafetyStop, match="observe-only"):  # not enabled yet: refused in the runner process
            robot.schedule_waypoint(np.array(fake_rtde.POSE0), time.monotonic() + 0.2)
        robot.enable()
        robot.schedule_waypoint(np.array(fake_rtde.POSE0) + [0.02, 0, 0, 0, 0, 0], time.monotonic() + 0.2)
        deadline = time.monotonic() + 30.0
        with pytest.raises(SafetyStop, match="protective stop"):
            while time.monotonic() < deadline:
                robot.check_ok()
                time.sleep(0.02)
    finally:
        robot.stop()
    names = [c[0] for c in _read_log(log)]
    assert names[-4:] == STOP_SEQ
    servo = [c for c in _read_log(log) if c[0] == "servoL"]
    assert len(servo) == 400 and servo[-1][2][0] > fake_rtde.POSE0[0]  # it moved towards the waypoint


def test_process_backend_normal_stop(tmp_path):
    log = tmp_path / "calls.jsonl"
    cfg = URConfig.from_mapping({"robot_ip": f"fake?log={log}", "rtde_modules": FAKE, "watchdog_min_frequency": 1.0})
    robot = URRTDERobot(cfg, connect_timeout_s=60.0)
    robot.start()
    robot.check_ok()
    robot.enable()
    assert robot.enabled
    robot.stop()
    robot.stop()  # idempotent
    names = [c[0] for c in _read_log(log)]
    assert names[:3] == ["receive.__init__", "control.__init__", "setTcp"] and names[-4:] == STOP_SEQ


def test_process_backend_observe_only_opens_no_control_interface(tmp_path):
    """Started but never enabled (a dry run, or a refused confirmation): states flow, nothing is sent."""
    log = tmp_path / "calls.jsonl"
    cfg = URConfig.from_mapping({"robot_ip": f"fake?log={log}", "rtde_modules": FAKE})
    robot = URRTDERobot(cfg, connect_timeout_s=60.0)
    robot.start()
    try:
        assert np.allclose(robot.get_states(1)["tcp_pose"][-1], fake_rtde.POSE0) and not robot.enabled
        robot.check_ok()
    finally:
        robot.stop()
    assert [c[0] for c in _read_log(log)] == ["receive.__init__", "receive.disconnect"]


# ------------------------------------------------------------------ #31 item 1: the robot-side watchdog
def test_every_servo_period_kicks_the_robot_watchdog(clock):
    loop, cmds, state = _loop(clock, n=200, watchdog_min_frequency=5.0)
    loop.run()
    kinds = [c[0] for c in fake_rtde.CALLS if c[0] in ("setWatchdog", "kickWatchdog", "servoL")]
    assert kinds[0] == "setWatchdog" and [c[2] for c in fake_rtde.CALLS if c[0] == "setWatchdog"] == [5.0]
    body = kinds[2:]  # setWatchdog + its first kick, then kick → servoL every period
    assert body == ["kickWatchdog", "servoL"] * 200


def test_a_frozen_host_is_stopped_by_the_robot_itself(clock):
    """The host stops kicking for 0.3 s > 1/5 Hz (frozen before its 100th servoL): the robot's own program has
    stopped, the late servoL is refused, nothing moved, and the host halts with one message."""
    loop, cmds, state = _loop(clock, host="fake?stall_after=100:0.3", watchdog_min_frequency=5.0)
    cmds.put(("waypoint", np.array(fake_rtde.POSE0) + [0.05, 0, 0, 0, 0, 0], 51.0))
    with pytest.raises(SafetyStop, match=r"servoL was refused by the controller .* robot-side watchdog"):
        loop.run()
    names = _names()
    assert names.count("servoL") == 99 and names.count("servoL refused") == 1 and names[-4:] == STOP_SEQ
    robot = fake_rtde._ROBOTS["fake?stall_after=100:0.3"]
    assert robot.side.stop_time == pytest.approx(50.0 + 99 / 500 + 0.2, abs=1e-9)  # last kick + 1/5 Hz


def test_killed_host_process_the_robot_stops_within_the_watchdog_period(tmp_path):
    """SIGKILL of the controller process (the host side; no stop sequence can run): the robot side, applied to the
    messages the robot received, has stopped its program at most 1/min_frequency after the kill — and it would
    run on forever without the watchdog (no setWatchdog: stop_time None)."""
    import os
    import signal

    log = tmp_path / "calls.jsonl"
    cfg = URConfig.from_mapping({"robot_ip": f"fake?log={log}", "rtde_modules": FAKE, "watchdog_min_frequency": 1.0})
    robot = URRTDERobot(cfg, connect_timeout_s=60.0)
    robot.start()
    try:
        robot.enable()
        robot.schedule_waypoint(np.array(fake_rtde.POSE0) + [0.05, 0, 0, 0, 0, 0], time.monotonic() + 2.0)
        deadline = time.monotonic() + 60.0
        while sum(1 for line in open(log) if '"servoL"' in line) < 20:  # servoing towards the waypoint
            assert time.monotonic() < deadline, "no servoL within 60 s"
            time.sleep(0.01)
        pid = robot._proc.pid
        os.kill(pid, signal.SIGKILL)
        robot._proc.join(10)
        t_kill = time.monotonic()
        assert robot._proc.exitcode == -signal.SIGKILL
    finally:
        robot.stop()
    calls = [json.loads(line) for line in open(log)]
    assert [c[0] for c in calls if c[0] in ("servoStop", "stopScript")] == []  # the host's stop sequence never ran
    side = fake_rtde.RobotSide.from_log(log)
    assert side.min_frequency == 1.0 and side.last_kick <= t_kill
    assert side.stop_time <= t_kill + 1.0 and not side.running(t_kill + 1.0 + 1e-6)
    assert side.running(side.last_kick)  # it was servoing until the kicks stopped
    assert fake_rtde.RobotSide().stop_time is None  # without setWatchdog the program would never stop
