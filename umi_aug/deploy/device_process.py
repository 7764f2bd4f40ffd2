"""Base of the device backends that run their loop in a child process (robot, gripper): start and wait for the
first state, command queue, error reporting as one :class:`SafetyStop`, stop with join / terminate."""

from __future__ import annotations

import logging
import multiprocessing as mp
import queue
import time
from typing import Any, Callable, Mapping

from umi_aug.deploy.safety import SafetyStop
from umi_aug.deploy.shared_state import SharedStateBuffer
from umi_aug.errors import DeployError

__all__ = ["DeviceProcess"]

log = logging.getLogger(__name__)


class DeviceProcess:
    """A device loop ``target(*args, commands, state, stop_event, errors)`` in a child process.

    Args:
        what: the device, for messages ("robot 192.168.0.8"). fields/capacity: state ring-buffer layout.
        ctx: multiprocessing context (default spawn). connect_timeout_s: wait for the first state this long.
    """

    def __init__(self, what: str, fields: Mapping[str, int], capacity: int, ctx: Any = None,
                 connect_timeout_s: float = 10.0) -> None:
        self.what = what
        self._ctx = ctx or mp.get_context("spawn")
        self.state = SharedStateBuffer(fields, capacity, self._ctx)
        self._cmd, self._errors, self._stop = self._ctx.Queue(), self._ctx.Queue(), self._ctx.Event()
        self._proc: Any = None
        self._error: str | None = None
        self.connect_timeout_s = connect_timeout_s

    def _start_process(self, target: Callable[..., None], *args: Any) -> None:
        self._proc = self._ctx.Process(target=target, name=self.what.split()[0], daemon=True,
                                       args=(*args, self._cmd, self.state, self._stop, self._errors))
        self._proc.start()
        deadline = time.monotonic() + self.connect_timeout_s
        while self.state.count == 0:
            self.check_ok()
            if time.monotonic() > deadline:
                self.stop()
                raise DeployError(f"{self.what}: no state within {self.connect_timeout_s} s")
            time.sleep(0.01)

    def get_states(self, n: int) -> dict:
        return self.state.latest(n)

    def check_ok(self) -> None:
        """Raise :class:`SafetyStop` with the child's error, or if the child died."""
        if self._error is None:
            try:
                self._error = self._errors.get_nowait()
            except queue.Empty:
                pass
        if self._error is not None:
            raise SafetyStop(f"{self.what} stopped: {self._error}")
        if self._proc is not None and not self._proc.is_alive():
            raise SafetyStop(f"{self.what} process exited (code {self._proc.exitcode})")

    def stop(self) -> None:
        """Ask the loop to stop (it runs its own cleanup), wait, terminate if it hangs. Idempotent."""
        if self._proc is None:
            return
        self._stop.set()
        self._proc.join(timeout=5.0)
        if self._proc.is_alive():
            log.error("%s process did not stop in 5 s; terminating it", self.what)
            self._proc.terminate()
            self._proc.join(timeout=2.0)
        self._proc = None
