"""#31 item 2: no child process outlives the runner. ``eval/deploy_ur.py`` on the simulated UR5e (arm, gripper and
camera processes plus multiprocessing's resource tracker) is SIGKILLed; its children, listed by PID before, are
all gone after (``PR_SET_PDEATHSIG`` in every device child, the tracker exits when its last client is gone)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _proc_stat(pid: int) -> tuple[int, str, int] | None:
    """(parent pid, state letter, start time in clock ticks) of a live process; None when it is gone."""
    try:
        raw = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    fields = raw[raw.rindex(")") + 2:].split()  # after "pid (comm) "
    return int(fields[1]), fields[0], int(fields[19])


def children_of(pid: int) -> dict[int, int]:
    """Live descendants of ``pid``: {pid: start time} (start time tells a reused pid apart)."""
    procs = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            st = _proc_stat(int(d.name))
            if st is not None and st[1] != "Z":
                procs[int(d.name)] = st
    out, todo = {}, [pid]
    while todo:
        p = todo.pop()
        for c, (ppid, _, start) in procs.items():
            if ppid == p and c not in out:
                out[c] = start
                todo.append(c)
    return out


def alive(pid: int, start: int) -> bool:
    st = _proc_stat(pid)
    return st is not None and st[1] != "Z" and st[2] == start  # a zombie waits for init's reaping: dead


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signal is Linux (prctl)")
def test_sigkill_of_the_runner_kills_every_child(tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    kids: dict[int, int] = {}
    runner = subprocess.Popen(
        [sys.executable, str(ROOT / "eval" / "deploy_ur.py"), "robot=sim_ur5e", "policy=reach", "dry_run=true",
         "max_duration=300", f"out_dir={tmp_path / 'run'}", f"hydra.run.dir={tmp_path / 'h'}"],
        cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        # wait (no fixed sleep) until the arm, gripper and camera processes and the resource tracker exist
        deadline = time.monotonic() + 240.0
        while True:
            kids = children_of(runner.pid)
            cmd = [_cmdline(p) for p in kids]
            if sum("spawn_main" in c for c in cmd) >= 3 and any("resource_tracker" in c for c in cmd):
                break
            assert runner.poll() is None, f"the runner exited early (code {runner.returncode})"
            assert time.monotonic() < deadline, f"children never all started: {cmd}"
            time.sleep(0.2)
        time.sleep(0.5)  # let them settle into their loops (not a timing assertion)
        kids = children_of(runner.pid)
        assert len(kids) >= 4, kids
        runner.send_signal(signal.SIGKILL)
        runner.wait(30)
        deadline = time.monotonic() + 60.0
        while any(alive(p, s) for p, s in kids.items()) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = {p: _cmdline(p) for p, s in kids.items() if alive(p, s)}
        assert left == {}, f"children outlived the SIGKILLed runner: {left}"
    finally:
        if runner.poll() is None:
            runner.kill()
            runner.wait(30)
        for p, start in kids.items():  # a failed run leaves no orphans behind (by PID, only those listed)
            if alive(p, start):
                os.kill(p, signal.SIGKILL)
