"""Clocks for the deployment loop. All times are seconds on one monotonic time base (``time.monotonic``)."""

from __future__ import annotations

import time
from typing import Protocol

__all__ = ["Clock", "MonotonicClock", "FakeClock"]


class Clock(Protocol):
    """What the runner needs from time: read it and wait for it."""

    def now(self) -> float:
        """Current time, seconds."""

    def sleep_until(self, t: float) -> None:
        """Return at (or right after) time ``t``; immediately if ``t`` is in the past."""


class MonotonicClock:
    """The machine's monotonic clock (shared by all processes of one machine)."""

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, t: float) -> None:
        dt = t - time.monotonic()
        if dt > 0:
            time.sleep(dt)


class FakeClock:
    """A clock that only moves when told to (tests). ``sleep_until`` jumps forward; ``advance`` adds time."""

    def __init__(self, t0: float = 0.0) -> None:
        self.t = float(t0)
        self.sleeps: list[float] = []

    def now(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        self.t += float(dt)

    def sleep_until(self, t: float) -> None:
        self.sleeps.append(float(t))
        self.t = max(self.t, float(t))
