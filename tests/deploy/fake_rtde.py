"""A fake ``rtde_control`` + ``rtde_receive`` (both classes in one module) for the ur-rtde backend tests.

Behaviour comes from the host string, a query like ``"fake?protective_after=50&log=/tmp/calls.jsonl"``:
``protective_after`` / ``estop_after`` / ``safety_mode_after`` (=N:mode) / ``raise_after`` / ``disconnect_after``
(counted in servoL calls); ``stall_after=N:S`` freezes the host for S seconds (fake clock) at the N-th servoL.
In-thread tests set :data:`CLOCK` to a FakeClock; :data:`CALLS` records every call (and ``log`` a JSON line each).

The robot side of ur-rtde's watchdog is modelled by :class:`RobotSide`: after ``setWatchdog(f)`` the robot's
program stops (it servos no more; ``servoL`` is refused) once no ``kickWatchdog`` arrived for ``1/f`` s. It is a
rule on the messages the robot received, so a test can also apply it to the call log of a host process it
killed (:meth:`RobotSide.from_log`), independently of that process.
"""

from __future__ import annotations

import json
import time
import urllib.parse

import numpy as np

CLOCK = None  # FakeClock or None (real time)
CALLS: list[tuple] = []
POSE0 = [0.4, 0.0, 0.3, np.pi, 0.0, 0.0]


def _now() -> float:
    return CLOCK.now() if CLOCK is not None else time.monotonic()


class RobotSide:
    """The robot's half of ur-rtde's watchdog (times in seconds on the host's monotonic / fake clock)."""

    def __init__(self) -> None:
        self.min_frequency: float | None = None
        self.last_kick: float | None = None

    def set_watchdog(self, min_frequency: float, t: float) -> None:
        self.min_frequency, self.last_kick = float(min_frequency), float(t)

    def kick(self, t: float) -> None:
        self.last_kick = float(t)

    @property
    def stop_time(self) -> float | None:
        """When the robot's program stops (no kick for 1/min_frequency s); None: no watchdog set."""
        if self.min_frequency is None:
            return None
        return self.last_kick + 1.0 / self.min_frequency

    def running(self, t: float) -> bool:
        """Whether the robot's program (servoing) still runs at time ``t``."""
        return self.stop_time is None or t <= self.stop_time

    @classmethod
    def from_log(cls, path) -> "RobotSide":
        """The robot side after the messages in a ``log`` file (``setWatchdog`` / ``kickWatchdog`` records)."""
        side = cls()
        for line in open(path):
            c = json.loads(line)
            if c[0] == "setWatchdog":
                side.set_watchdog(c[2], c[1])
            elif c[0] == "kickWatchdog":
                side.kick(c[1])
        return side


class _Robot:
    """Shared state of the fake controller: the TCP follows servoL targets exactly while the robot's program runs."""

    def __init__(self, host: str) -> None:
        q = urllib.parse.parse_qs(urllib.parse.urlparse(host).query)
        self.opt = {k: v[0] for k, v in q.items()}
        self.pose = list(POSE0)
        self.n_servo = 0
        self.connected = True
        self.side = RobotSide()

    def after(self, key: str) -> bool:
        return key in self.opt and self.n_servo >= int(self.opt[key].split(":")[0])

    def record(self, *call) -> None:
        CALLS.append(call)
        if "log" in self.opt:
            with open(self.opt["log"], "a") as f:
                f.write(json.dumps([str(call[0])] + [np.asarray(c).tolist() if not isinstance(c, str) else c
                                                      for c in call[1:]]) + "\n")


_ROBOTS: dict[str, _Robot] = {}


def _robot(host: str) -> _Robot:
    return _ROBOTS.setdefault(host, _Robot(host))


def reset() -> None:
    CALLS.clear()
    _ROBOTS.clear()


class RTDEControlInterface:
    def __init__(self, hostname, frequency=-1.0, *args):
        self.r = _robot(hostname)
        self.dt = 1.0 / frequency
        self.r.record("control.__init__", hostname, frequency)

    def setTcp(self, tcp):
        self.r.record("setTcp", list(tcp))
        return True

    def moveJ(self, q, speed, acc):
        self.r.record("moveJ", list(q), speed, acc)
        return True

    def initPeriod(self):
        return _now()

    def waitPeriod(self, t_start):
        if CLOCK is not None:
            CLOCK.sleep_until(t_start + self.dt)
        else:
            d = t_start + self.dt - time.monotonic()
            if d > 0:
                time.sleep(d)

    def setWatchdog(self, min_frequency=10.0):
        self.r.side.set_watchdog(min_frequency, _now())
        self.r.record("setWatchdog", _now(), float(min_frequency))
        return True

    def kickWatchdog(self):
        self.r.side.kick(_now())
        self.r.record("kickWatchdog", _now())
        return True

    def servoL(self, *args):  # positional only (a keyword argument is a TypeError, as a strict binding)
        self.r.n_servo += 1
        stall = self.r.opt.get("stall_after")
        if stall and CLOCK is not None and self.r.n_servo == int(stall.split(":")[0]):
            CLOCK.advance(float(stall.split(":")[1]))  # the host froze (no kick) this long before this call
        if not self.r.side.running(_now()):  # the robot's program stopped itself: nothing moves
            self.r.record("servoL refused", _now(), *args)
            return False
        self.r.record("servoL", _now(), *args)
        if self.r.after("raise_after"):
            raise RuntimeError("fake RTDE: socket error")
        self.r.pose = list(args[0])
        return True

    def servoStop(self, a=10.0):
        self.r.record("servoStop")
        return True

    def stopScript(self):
        self.r.record("stopScript")

    def disconnect(self):
        self.r.record("control.disconnect")


class RTDEReceiveInterface:
    def __init__(self, hostname, frequency=-1.0, *args):
        self.r = _robot(hostname)
        self.r.record("receive.__init__", hostname, frequency)

    def isConnected(self):
        return not self.r.after("disconnect_after")

    def isEmergencyStopped(self):
        return self.r.after("estop_after")

    def isProtectiveStopped(self):
        return self.r.after("protective_after")

    def getSafetyMode(self):
        if self.r.after("safety_mode_after"):
            return int(self.r.opt["safety_mode_after"].split(":")[1])
        return 1

    def getActualTCPPose(self):
        return list(self.r.pose)

    def getActualTCPSpeed(self):
        return [0.0] * 6

    def getActualQ(self):
        return [0.0, -1.57, 1.57, -1.57, -1.57, 0.0]

    def getActualQd(self):
        return [0.0] * 6

    def disconnect(self):
        self.r.record("receive.disconnect")
