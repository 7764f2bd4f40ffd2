"""Base of the device backends that run their loop in a child process (robot, gripper): start and wait for the
first state, command queue, error reporting as one :class:`SafetyStop`, stop with join / terminate.

Two phases: a child starts **observe-only** (it reads the device and publishes states; it sends no motion and no
device command) and starts commanding only after :meth:`DeviceProcess.enable` — which a dry run never calls, and
which a real arm gets only after the operator's confirmation (:mod:`umi_aug.deploy.app`). Waypoints before
``enable`` are refused on both sides of the queue.

No child outlives the runner: each child's entry point calls :func:`child_setup` first, which asks the kernel to
SIGKILL it when the runner dies (``PR_SET_PDEATHSIG``, the augment workers' :func:`~umi_aug.augment.executor.
die_with_parent`; the simulated arm asks for SIGTERM instead and decelerates to rest before it exits), and the
loops call :func:`parent_alive` every period (a check that does not depend on the signal)."""

from __future__ import annotations

import ctypes
import logging
import multiprocessing as mp
import os
import queue
import signal
import time
from typing import Any, Callable, Mapping

from umi_aug.augment.executor import PR_SET_PDEATHSIG, die_with_parent
from umi_aug.deploy.safety import SafetyStop
from umi_aug.deploy.shared_state import SharedStateBuffer
from umi_aug.errors import DeployError

__all__ = ["DeviceProcess", "child_setup", "parent_alive", "poll_enable"]

log = logging.getLogger(__name__)


def child_setup(parent_pid: int, death_signal: int = signal.SIGKILL) -> None:
    """First call of every device child: die with the runner (``death_signal`` on the parent's death, or exit now
    if it is already gone; Linux) and leave SIGINT to the runner (a Ctrl-C reaches the whole process group; the
    runner stops its children in order, each running its own stop sequence).

    Args:
        parent_pid: the runner's pid.
        death_signal: the signal the kernel sends this process when the runner dies. SIGKILL (default) for
            children that have nothing to wind down; the simulated arm asks for SIGTERM and handles it by
            decelerating to rest first (:func:`umi_aug.deploy.sim_arm.stop_on_signal`, with a SIGALRM backstop),
            as the real arm's own program does when ur-rtde's watchdog fires.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if die_with_parent(parent_pid) and death_signal != signal.SIGKILL:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(death_signal), 0, 0, 0)
        if os.getppid() != parent_pid:  # the runner died between the two prctl calls
            os._exit(1)


def parent_alive(parent_pid: int | None) -> bool:
    """Whether the runner process ``parent_pid`` is still this process's parent (None: not checked)."""
    return parent_pid is None or os.getppid() == parent_pid


def poll_enable(commands: Any) -> str | None:
    """Observe-only phase of a device loop: take the next queued command. Returns ``"enable"``, ``"stop"`` or None
    (queue empty).

    Raises:
        DeployError: a waypoint arrived before ``enable`` (the device must not move yet).
    """
    try:
        cmd = commands.get_nowait()
    except queue.Empty:
        return None
    if cmd[0] in ("enable", "stop"):
        return cmd[0]
    raise DeployError(f"device got a {cmd[0]!r} command before it was enabled (observe-only: dry run or not "
                      f"confirmed); nothing was sent to the device")


class DeviceProcess:
    """A device loop ``target(*args, commands, state, stop_event, errors, enabled, parent_pid)`` in a child process.

    ``enabled`` is a shared int the child sets to 1 once it commands the device (after ``("enable",)``);
    ``parent_pid`` is the runner's pid (for :func:`child_setup` / :func:`parent_alive`).

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
        self._enabled = self._ctx.Value("i", 0, lock=False)
        self._proc: Any = None
        self._error: str | None = None
        self.connect_timeout_s = connect_timeout_s

    def _start_process(self, target: Callable[..., None], *args: Any) -> None:
        self._proc = self._ctx.Process(target=target, name=self.what.split()[0], daemon=True,
                                       args=(*args, self._cmd, self.state, self._stop, self._errors, self._enabled,
                                             os.getpid()))
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

    @property
    def enabled(self) -> bool:
        """Whether the child commands the device (after :meth:`enable`); False = observe-only."""
        return bool(self._enabled.value)

    def enable(self, timeout_s: float | None = None) -> None:
        """Leave the observe-only phase: the child connects its command channel and starts commanding (a real
        arm: ``setTcp``, ``setWatchdog``, optional ``moveJ``, ``servoL``; a WSG-50: fault ack, homing, position
        control). Waits until the child reports it (default wait: ``connect_timeout_s`` + 60 s for a ``moveJ``).

        Raises:
            SafetyStop: the child failed while enabling. DeployError: it did not report within the wait.
        """
        if self._proc is None:
            raise DeployError(f"{self.what}: enable() before start()")
        self._cmd.put(("enable",))
        wait = self.connect_timeout_s + 60.0 if timeout_s is None else float(timeout_s)
        deadline = time.monotonic() + wait
        while not self._enabled.value:
            self.check_ok()
            if time.monotonic() > deadline:
                raise DeployError(f"{self.what}: not enabled within {wait:.0f} s")
            time.sleep(0.01)

    def _require_enabled(self, what: str) -> None:
        if not self._enabled.value:
            raise SafetyStop(f"{self.what}: {what} refused: the device is observe-only (dry run, or enable() not "
                             f"called after the confirmation)")

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
