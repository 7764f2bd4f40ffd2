"""#31 item 2, last sentence: the simulated UR5e stops the way ``servoStop`` does. Whatever stops it — the runner's
stop, a ``("stop",)`` command, the heartbeat watchdog, the runner's death (parent check or the parent-death
signal) — the TCP decelerates to rest at ``robot.stop_deceleration`` (ur-rtde's ``servoStop(a)``, default
10 m/s²): it neither freezes where it was nor runs on to its last target. Measured on the published state stream
against a fake clock (simulated time); nothing here reads or compares the wall clock."""

from __future__ import annotations

import os
import queue
import re
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from umi_aug.deploy.arm_process import STATE_FIELDS
from umi_aug.deploy.clock import FakeClock
from umi_aug.deploy.safety import SafetyStop
from umi_aug.deploy.shared_state import SharedStateBuffer
from umi_aug.errors import DeployError

ROOT = Path(__file__).resolve().parents[2]
START = np.array([0.0, -0.45, 0.30])  # the shipped joints_init's TCP (m, base frame)
TARGET = np.array([0.1, -0.7, 0.2, np.pi, 0.0, 0.0])  # 0.29 m from START: still far when the stop comes
T_STOP = 0.6  # s (sim time): the arm moves at max_pos_speed by then (it starts ~0.1 s after the waypoint)


def sim_robot_block(**over: float) -> dict:
    """The ``robot:`` block of the shipped configs/robot/sim_ur5e.yaml with ``over`` applied."""
    return {**yaml.safe_load((ROOT / "configs" / "robot" / "sim_ur5e.yaml").read_text())["robot"], **over}


class _Beat:
    """The runner's heartbeat: fresh until ``silent_from`` (sim time, s), then no more beats."""

    def __init__(self, clock: FakeClock, silent_from: float = np.inf) -> None:
        self.clock, self.silent_from = clock, silent_from

    @property
    def value(self) -> float:
        return min(self.clock.now(), self.silent_from)


class _Event:
    """``stop_event``: set from ``t_set`` (sim time, s) on; ``on_check(t)`` is called at every look (a hook for
    the triggers that are not the event itself)."""

    def __init__(self, clock: FakeClock, t_set: float = np.inf, on_check=None) -> None:
        self.clock, self.t_set, self.on_check = clock, t_set, on_check

    def is_set(self) -> bool:
        if self.on_check is not None:
            self.on_check(self.clock.now())
        return self.clock.now() >= self.t_set


class _Commands:
    """The command queue: ``("enable",)`` and the waypoint at once, ``("stop",)`` from ``t_stop`` on."""

    def __init__(self, clock: FakeClock, t_stop: float = np.inf) -> None:
        self.clock, self.t_stop = clock, t_stop
        self.items = [("enable",), ("waypoint", TARGET.copy(), 0.01)]

    def get_nowait(self):
        if self.items:
            return self.items.pop(0)
        if self.clock.now() >= self.t_stop:
            self.t_stop = np.inf
            return ("stop",)
        raise queue.Empty


def _run(trigger: str, monkeypatch, **over: float):
    """Servo towards TARGET at max_pos_speed and stop at T_STOP by ``trigger``. Returns (config, loop, states
    [all published], the SafetyStop raised or None)."""
    import umi_aug.deploy.sim_arm as sim_mod
    from umi_aug.deploy.sim_ur5e import SimServoLoop, SimURConfig

    if trigger == "watchdog":
        over.setdefault("watchdog_s", 0.2)  # the bound's lowest value
    cfg = SimURConfig.from_mapping(sim_robot_block(**over))
    clock = FakeClock(0.0)
    beat = _Beat(clock, T_STOP - cfg.watchdog_s if trigger == "watchdog" else np.inf)
    commands = _Commands(clock, T_STOP if trigger == "stop_command" else np.inf)
    if trigger == "parent_died":  # the runner is no longer the parent from T_STOP on (os.getppid() changed)
        monkeypatch.setattr(sim_mod, "parent_alive", lambda pid: pid is None or clock.now() < T_STOP)
    sent = []

    def send_sigterm(t: float) -> None:  # the parent-death signal, delivered by the kernel at T_STOP
        if t >= T_STOP and not sent:
            sent.append(t)
            os.kill(os.getpid(), signal.SIGTERM)

    event = _Event(clock, T_STOP if trigger == "stop_event" else np.inf,
                   send_sigterm if trigger == "signal" else None)
    st = SharedStateBuffer(STATE_FIELDS, capacity=2000)
    loop = SimServoLoop(cfg, commands, st, event, beat, clock,
                        parent_pid=os.getppid() if trigger == "parent_died" else None)
    old = None
    if trigger == "signal":  # the handler the arm's process installs; parent pid -1 = "not my parent": died
        old = signal.signal(signal.SIGTERM, sim_mod.stop_on_signal(loop, -1, backstop_s=None))
    err = None
    try:
        loop.run()
    except SafetyStop as exc:
        err = exc
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)
    return cfg, loop, st.latest(10**6), err


def _measure(s: dict, obs_latency: float, t_stop: float) -> dict:
    """The stop read off the state stream: speed when the stop began (the loop noticed it at ``t_stop``: T_STOP,
    or one 2-ms period later for a command, which is read after the period's physics), distance from there to
    rest, the time 99 % of that distance took and the largest deceleration over 10 ms (five 2-ms states), all in
    simulated time. (A state stamped t − obs_latency shows the arm after that period's physics, at t + 2 ms: the
    last state of a period before ``t_stop`` is the arm at ``t_stop``.)"""
    t, p = s["timestamp"], s["tcp_pose"][:, :3]
    v = np.linalg.norm(s["tcp_speed"][:, :3], axis=1)
    i0 = int(np.searchsorted(t + obs_latency, t_stop - 1e-9)) - 1  # the last state published before the stop
    d = np.linalg.norm(p[i0:] - p[i0], axis=1)
    dist = float(d[-1])
    k99 = int(np.argmax(d >= 0.99 * dist))
    w = 5
    dec = -(v[i0 + w:] - v[i0:-w]) / (t[i0 + w:] - t[i0:-w])
    return {"v0": float(v[i0]), "dist": dist, "t99": float(t[i0 + k99] - t[i0]), "max_dec": float(dec.max()),
            "v_end": float(v[-1]), "v_10ms": float(v[i0 + 5]), "p_stop": p[i0], "p_end": p[-1],
            "dt": np.diff(t[i0:])}


@pytest.mark.parametrize("trigger, reason", [
    ("stop_event", None),  # the runner's stop (DeviceProcess.stop): returns
    ("stop_command", None),  # ("stop",), the servoStop of the queue: returns
    ("watchdog", r"watchdog: no heartbeat from the runner"),
    ("parent_died", r"the runner process \d+ died"),
    ("signal", r"the runner process -1 died"),  # the parent-death signal (SIGTERM) → stop_on_signal
])
def test_every_stop_decelerates_the_sim_arm_like_servostop(trigger, reason, monkeypatch):
    a = 2.0  # m/s²: a stop of 0.125 s over 15.6 mm from 0.25 m/s, long enough to measure on 2 ms states
    cfg, loop, s, err = _run(trigger, monkeypatch, stop_deceleration=a)
    if reason is None:
        assert err is None
    else:
        assert err is not None and re.search(reason, str(err)), err
    assert T_STOP - 1e-9 <= loop.last_stop["t_clock"] <= T_STOP + 0.002 + 1e-9  # noticed within one period
    m = _measure(s, cfg.obs_latency, loop.last_stop["t_clock"])
    v0 = m["v0"]
    assert v0 == pytest.approx(cfg.max_pos_speed, rel=0.03)  # it was moving at full speed when stopped
    expected = v0 ** 2 / (2 * a)  # servoStop(a): a linear ramp to rest
    assert m["dist"] == pytest.approx(expected, rel=0.05, abs=5e-4)  # not frozen, not run on
    assert m["t99"] == pytest.approx(0.9 * v0 / a, abs=0.01)  # 1 − (1 − τ/T)² = 0.99 at τ = 0.9·T
    assert m["max_dec"] <= 1.25 * a  # bounded deceleration (the sim's joint PD adds up to ~17 % over 10 ms)
    assert m["v_10ms"] > v0 - 1.2 * a * 0.010  # 10 ms later still moving: no instant freeze
    assert m["v_end"] < 2e-3  # at rest at the end
    # it did not go on to its last target: still as far from it as the stop distance allows
    left = np.linalg.norm(TARGET[:3] - m["p_stop"]) - np.linalg.norm(TARGET[:3] - m["p_end"])
    assert left == pytest.approx(expected, rel=0.05, abs=5e-4)
    assert np.allclose(m["dt"], 0.002, atol=1e-9)  # the states go on every 2 ms period during the stop
    st = loop.last_stop
    assert st["settled"] and st["fault"] == (reason is not None)
    assert st["ramp_s"] == pytest.approx(v0 / a, rel=0.03) and st["to_rest_s"] < st["ramp_s"] + 0.3


def test_default_stop_deceleration_is_servostops_10_m_s2(monkeypatch):
    """The shipped config stops at ur-rtde's servoStop default, 10 m/s²: 0.25 m/s → rest in 25 ms over 3.1 mm."""
    cfg, loop, s, err = _run("stop_command", monkeypatch)
    assert cfg.stop_deceleration == 10.0 and err is None
    m = _measure(s, cfg.obs_latency, loop.last_stop["t_clock"])
    assert m["dist"] == pytest.approx(m["v0"] ** 2 / 20.0, rel=0.05, abs=3e-4)
    assert m["t99"] == pytest.approx(0.9 * m["v0"] / 10.0, abs=0.006)
    assert m["max_dec"] <= 1.25 * 10.0 and m["v_end"] < 2e-3


def test_stop_from_rest_ends_at_once(monkeypatch):
    """An arm that stands (observe-only, or already at its target) stops in the period the stop comes."""
    from umi_aug.deploy.sim_ur5e import SimServoLoop, SimURConfig

    cfg = SimURConfig.from_mapping(sim_robot_block())
    clock = FakeClock(0.0)
    st = SharedStateBuffer(STATE_FIELDS, capacity=200)
    loop = SimServoLoop(cfg, queue.Queue(), st, _Event(clock, 0.1), _Beat(clock), clock)
    loop.run()
    assert loop.last_stop["ramp_s"] == 0.0 and loop.last_stop["to_rest_s"] == 0.0
    assert clock.now() == pytest.approx(0.1, abs=1e-9) and st.count == 50


def test_stop_ramp_profile():
    """StopRamp: straight on along the twist, speed falling linearly to 0 in max(|v|/a, |ω|/α), then holding."""
    from umi_aug.deploy.sim_ur5e import StopRamp
    from umi_aug.geometry.se3 import pos_rotvec_to_pose

    T0 = pos_rotvec_to_pose(np.array([0.1, -0.4, 0.3, np.pi, 0.0, 0.0]))
    r = StopRamp.start(T0, np.array([0.3, 0.0, -0.4, 0.0, 0.0, 1.0]), 10.0, 4.0)
    assert r.duration == pytest.approx(0.25)  # the rotation decides: 1 rad/s at 4 rad/s²
    assert np.allclose(r.pose(0.0)[:3], T0[:3, 3])
    assert np.allclose(r.pose(1.0)[:3], T0[:3, 3] + np.array([0.3, 0.0, -0.4]) * 0.125)  # |v|·duration/2
    assert np.allclose(r.pose(1.0), r.pose(r.duration))
    h = 1e-6  # speed at τ: (1 − τ/duration)·|twist|
    for tau in (0.0, 0.1, 0.2):
        vel = (r.pose(tau + h)[:3] - r.pose(tau)[:3]) / h
        assert np.linalg.norm(vel) == pytest.approx(0.5 * (1 - tau / 0.25), abs=1e-4)
    assert StopRamp.start(T0, np.zeros(6), 10.0, 31.4).duration == 0.0


def test_stop_deceleration_is_bounded():
    from umi_aug.deploy.sim_ur5e import SimURConfig

    with pytest.raises(DeployError, match=r"robot\.stop_deceleration=0\.5 is outside \[1, 20\]"):
        SimURConfig.from_mapping(sim_robot_block(stop_deceleration=0.5))
    with pytest.raises(DeployError, match=r"robot\.stop_rot_deceleration=100 is outside"):
        SimURConfig.from_mapping(sim_robot_block(stop_rot_deceleration=100))


# ------------------------------------------------------------------------------- the runner dies (processes)
def _runner_standin(cfg, heartbeat, commands, state, stop_event, errors, enabled, child_pid) -> None:
    """A runner process: starts the simulated arm's process as its child (what SimUR5eRobot.start does, with the
    test's shared buffers), reports the child's pid, then beats the heartbeat until it is SIGKILLed."""
    import multiprocessing as mp

    from umi_aug.deploy.sim_arm import _sim_robot_main

    p = mp.get_context("spawn").Process(target=_sim_robot_main, daemon=False,
                                        args=(cfg, heartbeat, commands, state, stop_event, errors, enabled,
                                              os.getpid()))
    p.start()
    child_pid.value = p.pid
    while True:
        heartbeat.value = time.monotonic()
        time.sleep(0.05)


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signal is Linux (prctl)")
def test_sigkilled_runner_leaves_the_sim_arm_decelerated_to_rest():
    """The runner is SIGKILLed while the simulated arm moves: the arm's process gets its parent-death signal,
    decelerates the TCP to rest (the last published state stands still; a SIGKILLed arm process would have left
    its last state moving at full speed), reports why, and exits. Only the state stream and the reports are
    asserted — no duration."""
    import multiprocessing as mp

    from umi_aug.deploy.sim_ur5e import SimURConfig

    ctx = mp.get_context("spawn")
    cfg = SimURConfig.from_mapping(sim_robot_block(stop_deceleration=1.0))  # 0.1 m/s → rest in 0.1 s, 5 mm
    state = SharedStateBuffer(STATE_FIELDS, capacity=4096, ctx=ctx)
    commands, errors, stop_event = ctx.Queue(), ctx.Queue(), ctx.Event()
    heartbeat, enabled = ctx.Value("d", time.monotonic() + 60.0, lock=False), ctx.Value("i", 0, lock=False)
    child_pid = ctx.Value("i", 0, lock=False)
    runner = ctx.Process(target=_runner_standin, daemon=False,
                         args=(cfg, heartbeat, commands, state, stop_event, errors, enabled, child_pid))
    runner.start()
    try:
        deadline = time.monotonic() + 180.0  # model load on a loaded machine; a guard, not a measurement
        while state.count == 0:
            assert runner.is_alive() and time.monotonic() < deadline, "the arm process never published a state"
            time.sleep(0.05)
        commands.put(("enable",))
        # 0.4 m in 4 s: 0.1 m/s, straight down and towards the table's far side (inside the reach)
        goal = np.array([0.0, -0.75, 0.02, np.pi, 0.0, 0.0])
        commands.put(("waypoint", goal, time.monotonic() + 4.0))
        while True:  # wait until the arm cruises (state stream), then kill the runner
            s = state.latest(1)
            if np.linalg.norm(s["tcp_speed"][-1][:3]) > 0.08:
                break
            assert errors.empty(), errors.get()
            assert time.monotonic() < deadline, "the arm never reached its cruise speed"
            time.sleep(0.01)
        runner.kill()
        runner.join(30)
        msg = errors.get(timeout=60.0)  # the arm's process reports after its stop
        assert "the runner process" in msg and "died" in msg, msg
        last = state.latest(1)
        assert np.linalg.norm(last["tcp_speed"][-1][:3]) < 2e-3, last["tcp_speed"][-1]  # at rest, not frozen
        assert np.linalg.norm(last["tcp_pose"][-1][:3] - goal[:3]) > 0.05  # stopped, not run on to the goal
        pid = child_pid.value
        deadline = time.monotonic() + 60.0
        while Path(f"/proc/{pid}").exists() and _state_letter(pid) not in ("Z", None):
            assert time.monotonic() < deadline, f"the arm process {pid} outlived its stop"
            time.sleep(0.05)
    finally:
        if runner.is_alive():
            runner.kill()
            runner.join(10)
        pid = child_pid.value
        if pid and _state_letter(pid) not in ("Z", None):
            os.kill(pid, signal.SIGKILL)


def _state_letter(pid: int) -> str | None:
    """The /proc state letter of ``pid`` (None: gone)."""
    try:
        raw = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return raw[raw.rindex(")") + 2:].split()[0]
