"""(b) the ur-rtde backend against a fake rtde_control / rtde_receive injected at the module boundary."""

from __future__ import annotations

import json
import queue
import time

import numpy as np
import pytest

from tests.deploy import fake_rtde
from umi_aug.deploy.clock import FakeClock
from umi_aug.deploy.safety import SafetyStop
from umi_aug.deploy.shared_state import SharedStateBuffer
from umi_aug.deploy.ur_rtde import STATE_FIELDS, URConfig, URRTDERobot, URServoLoop
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
    state = SharedStateBuffer(STATE_FIELDS, 4096)
    return URServoLoop(cfg, cmds, state, _StopAfter(n), _Heartbeat(clock, stale_after), clock), cmds, state


def _names():
    return [c[0] for c in fake_rtde.CALLS]


def test_servol_rate_args_speed_limit_and_clean_stop(clock):
    loop, cmds, state = _loop(clock, n=1500, max_pos_speed=0.1, max_rot_speed=0.5, lookahead_time=0.05, gain=500)
    target = np.array(fake_rtde.POSE0) + [0.15, 0.0, 0.0, 0, 0, 0]
    cmds.put(("waypoint", target, 50.5))  # asks 0.3 m/s; the 0.1 m/s limit stretches it to 1.5 s
    loop.run()
    assert _names()[:2] == ["control.__init__", "setTcp"] and fake_rtde.CALLS[1][1] == [0, 0, 0.235, 0, 0, 0]
    assert fake_rtde.CALLS[0][2] == 500.0
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
    assert np.allclose(np.diff(t), 1 / 125) and fake_rtde.CALLS[0][2] == 125.0


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
    cfg = URConfig.from_mapping({"robot_ip": f"fake?protective_after=400&log={log}", "rtde_modules": FAKE})
    robot = URRTDERobot(cfg, connect_timeout_s=60.0)
    try:
        robot.start()
        st = robot.get_states(5)
        assert np.allclose(st["tcp_pose"][-1], fake_rtde.POSE0)
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
    cfg = URConfig.from_mapping({"robot_ip": f"fake?log={log}", "rtde_modules": FAKE})
    robot = URRTDERobot(cfg, connect_timeout_s=60.0)
    robot.start()
    robot.check_ok()
    robot.stop()
    robot.stop()  # idempotent
    assert [c[0] for c in _read_log(log)][-4:] == STOP_SEQ
