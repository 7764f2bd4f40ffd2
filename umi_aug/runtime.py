"""Process-level runtime settings: thread counts for the 2-core machines this project targets, and where an
application's library logs go.

Nothing here runs at import time; entry points (CLI, training, benchmarks, tests) call
:func:`configure_threads` once, before heavy libraries start their thread pools.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import subprocess
import sys
import threading
import warnings
from pathlib import Path
from typing import Any, Callable, Iterator

#: Environment variables that size the BLAS/OpenMP thread pools of numpy, scipy, torch and numba.
_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


def quiet_numba_threading_warning() -> None:
    """Keep numba's "TBB threading layer requires TBB version ..." warning off the console: numba tries TBB first
    and warns when the installed TBB is too old, then uses OpenMP, which is what runs here anyway; a library
    message a user can do nothing about. Called by :func:`configure_threads` and by the modules that hold parallel
    kernels (a library user may never call the former)."""
    warnings.filterwarnings("ignore", message="The TBB threading layer requires TBB version", module=r"numba(\.|$)")


def configure_threads(n_threads: int | None = None) -> int:
    """Set thread-pool sizes to the number of usable cores unless the user already chose them.

    OpenBLAS is kept single-threaded: scipy's optimisers on 2 cores ran ~10x slower with the default
    OpenBLAS threading (../shared/spec/environment.md). Existing environment values always win.

    Args:
        n_threads: threads for OpenMP/MKL/numba/torch; defaults to the CPU count this process may use.

    Returns:
        The thread count applied to torch (if torch is already imported or importable cheaply).
    """
    if n_threads is None:
        try:
            n_threads = len(os.sched_getaffinity(0))
        except AttributeError:  # pragma: no cover - non-Linux
            n_threads = os.cpu_count() or 1
    n_threads = max(1, int(n_threads))
    for var in _THREAD_VARS:
        os.environ.setdefault(var, str(n_threads))
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    # Idle OpenMP workers sleep instead of spinning: with 2 cores, spinning threads steal the core another
    # stage (numba rasteriser, MuJoCo, JPEG-XL) needs; measured 64 → 42 ms/frame for the 100k-Gaussian render.
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")

    quiet_numba_threading_warning()

    if "torch" in sys.modules:
        torch = sys.modules["torch"]
        wanted = int(os.environ.get("OMP_NUM_THREADS", n_threads))
        if torch.get_num_threads() != wanted:
            torch.set_num_threads(wanted)
        return wanted
    return int(os.environ["OMP_NUM_THREADS"])


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, a job scheduler), raised like Ctrl-C's KeyboardInterrupt so that every
    ``except KeyboardInterrupt`` clean-up (workers stopped, nothing half-written kept) runs for it too."""


def run_interruptible(main: Callable[[], Any], interrupted_line: Callable[[str], str]) -> None:
    """Run a script's ``main()`` with SIGTERM ending it like Ctrl-C: one line on stderr,
    ``interrupted_line(how)`` (``how`` = ``"SIGTERM"`` or ``"Ctrl-C"``), and exit code 143 / 130."""
    try:
        with terminate_like_ctrl_c():
            main()
    except KeyboardInterrupt as exc:
        how, code = interruption(exc)
        print(interrupted_line(how), file=sys.stderr)
        sys.exit(code)


def _raise_terminated(signum, frame) -> None:  # noqa: ARG001 - signal handler signature
    raise Terminated()


def interruption(exc: KeyboardInterrupt) -> tuple[str, int]:
    """How an entry point names an interruption and the exit code it ends with (128 + the signal's number, as a
    shell reports a killed command): ``("SIGTERM", 143)`` for :class:`Terminated`, ``("Ctrl-C", 130)`` otherwise."""
    return ("SIGTERM", 143) if isinstance(exc, Terminated) else ("Ctrl-C", 130)


@contextlib.contextmanager
def terminate_like_ctrl_c() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`Terminated` in the main thread (the previous handler is put back
    afterwards; elsewhere than the main thread nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


def restore_python_signal_handlers() -> None:
    """Re-install Python's own SIGTERM handler after importing a native library that replaced it (pycolmap's
    glog installs a "failure signal handler" that prints a native stack trace and kills the process)."""
    if threading.current_thread() is threading.main_thread():
        handler = signal.getsignal(signal.SIGTERM)
        if handler is not None:
            signal.signal(signal.SIGTERM, handler)


def make_out_dir(path: str | os.PathLike, key: str, error: type[Exception]) -> Path:
    """Create the results folder ``path`` of an app (``key`` = the setting that named it, e.g. ``out_dir``), or
    raise ``error`` in one line: ``out_dir=…: is a file, not a folder; …`` / ``…: cannot be created (…)``."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise error(f"{key}={path}: is a file, not a folder; the results are written into a folder: choose another "
                    f"{key}")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise error(f"{key}={path}: the folder cannot be created ({exc.strerror}: {exc.filename}); choose another "
                    f"{key}") from exc
    return path


def log_to_file(path: str | os.PathLike, quiet: tuple[str, ...] = ("robosuite", "robomimic")) -> None:
    """Send library logs (INFO and up) to ``path`` instead of the console: the root logger's handlers are
    replaced by one file handler, and the loggers named in ``quiet`` are raised to WARNING. For applications
    (``eval/*.py``) that print their own summary; the folder of ``path`` is created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    fh = logging.FileHandler(path)
    fh.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s: %(message)s"))
    root.addHandler(fh)
    root.setLevel(logging.INFO)
    for name in quiet:
        logging.getLogger(name).setLevel(logging.WARNING)


def _background_child_setup(niceness: int = 10) -> None:
    """``preexec_fn`` of :func:`start_background_helper`: low priority (``nice``), and killed with its parent
    (Linux ``PR_SET_PDEATHSIG``: a Ctrl-C of the pipeline leaves no helper running)."""
    os.nice(niceness)
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass


def start_background_helper(module: str, args: list[str], *, stdin_bytes: bytes | None = None, output=None):
    """Start ``python -m module *args`` as a helper that only uses a core the pipeline leaves idle: ``nice`` 10,
    one thread per pool (OpenMP, MKL, numba), killed with its parent. ``stdin_bytes`` (small: it must fit the pipe)
    is written to its stdin; ``output``: an open binary file for its stdout + stderr (None: discarded). Returns the
    ``subprocess.Popen``, or None when no process could be started (callers treat the helper as optional)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1", MKL_NUM_THREADS="1")
    sink = output if output is not None else subprocess.DEVNULL
    try:
        child = subprocess.Popen([sys.executable, "-m", module, *args], env=env,
                                 stdin=subprocess.DEVNULL if stdin_bytes is None else subprocess.PIPE,
                                 stdout=sink, stderr=subprocess.STDOUT if output is not None else subprocess.DEVNULL,
                                 preexec_fn=_background_child_setup)
    except OSError:
        return None
    if stdin_bytes is not None:
        try:
            child.stdin.write(stdin_bytes)
            child.stdin.close()
        except OSError:  # the child died at once: it reports nothing, the caller does without it
            pass
    return child
