"""A fake ``rtde_control`` + ``rtde_receive`` (both classes in one module) for the ur-rtde backend tests.

Behaviour comes from the host string, a query like ``"fake?protective_after=50&log=/tmp/calls.jsonl"``:
``protective_after`` / ``estop_after`` / ``safety_mode_after`` (=N:mode) / ``raise_after`` / ``disconnect_after``
(counted in servoL calls). In-thread tests set :data:`CLOCK` to a FakeClock; :data:`CALLS` records every call.
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


class _Robot:
    """Shared state of the fake controller: the TCP follows servoL targets exactly."""

    def __init__(self, host: str) -> None:
        q = urllib.parse.parse_qs(urllib.parse.urlparse(host).query)
        self.opt = {k: v[0] for k, v in q.items()}
        self.pose = list(POSE0)
        self.n_servo = 0
        self.connected = True

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

    def servoL(self, *args):  # positional only (a keyword argument is a TypeError, as a strict binding)
        self.r.n_servo += 1
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
