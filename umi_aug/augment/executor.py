"""Run independent generation tasks locally (in-process or a process pool) or on Ray, results in input order.

One call, :func:`map_ordered`, so the offline export gives the same dataset whichever executor runs it: tasks are
pure functions of their argument (each episode's randomness comes from a seed derived from its id, never from
which worker runs it) and results come back in the order of ``items``, so they are appended in that order.

* ``"local"`` — ``workers <= 1``: in this process (no pickling, easiest to debug); ``workers > 1``: a ``spawn``
  process pool (spawn, not fork: torch, numba and MuJoCo/EGL thread pools do not survive ``fork``).
* ``"ray"`` — a local Ray cluster with ``workers`` CPUs (no network needed), or an existing cluster when
  ``address`` is given (``"auto"`` or ``"ray://host:10001"``). Ray is imported only here, only then.

No worker outlives its parent: on Linux each pool worker asks the kernel for SIGKILL when its parent dies
(``prctl(PR_SET_PDEATHSIG)``) and checks that the parent is still there; workers ignore SIGINT (a Ctrl-C in the
terminal reaches the whole process group: the parent alone handles it and terminates its workers).

Each worker process runs with ``threads_per_worker`` BLAS/OpenMP/numba/torch threads (default: cores / workers),
so ``workers x threads`` never oversubscribes the machine.
"""

from __future__ import annotations

import ctypes
import logging
import multiprocessing as mp
import os
import signal
import sys
from collections import deque
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Callable, Iterable, Iterator, TypeVar

from umi_aug.errors import AugmentError
from umi_aug.runtime import configure_threads

__all__ = ["EXECUTORS", "map_ordered", "usable_cores"]

log = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")

#: Executor names accepted by :func:`map_ordered` (``AugmentConfig.executor``).
EXECUTORS: tuple[str, ...] = ("local", "ray")


def usable_cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - non-Linux
        return os.cpu_count() or 1


def _threads_env(threads: int) -> dict[str, str]:
    return {"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads), "NUMBA_NUM_THREADS": str(threads),
            "OPENBLAS_NUM_THREADS": "1", "OMP_WAIT_POLICY": "passive"}


PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int | None = None) -> bool:
    """Make the kernel SIGKILL this process when its parent dies (Linux ``prctl(PR_SET_PDEATHSIG)``); if the
    parent (``parent_pid``) is already gone, exit now. Returns False where unsupported (no-op)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        ok = libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False
    if parent_pid is not None and os.getppid() != parent_pid:  # the parent died before prctl
        os._exit(1)
    return ok


def _worker_init(threads: int, parent_pid: int | None = None) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    die_with_parent(parent_pid)
    os.environ.update(_threads_env(threads))
    configure_threads(threads)


def _call(fn: Callable[[T], R], item: T, threads: int) -> R:
    """Body of one task on a worker: size the thread pools, then run ``fn(item)``."""
    configure_threads(threads)
    return fn(item)


def map_ordered(fn: Callable[[T], R], items: Iterable[T], *, executor: str = "local", workers: int = 1,
                address: str | None = None, threads_per_worker: int | None = None,
                max_in_flight: int | None = None) -> Iterator[R]:
    """Yield ``fn(item)`` for every item, in the order of ``items``.

    Args:
        fn: a picklable top-level function (for ``workers > 1`` or Ray); it must be deterministic in its argument.
        items: task arguments (picklable).
        executor: ``"local"`` or ``"ray"``.
        workers: parallel tasks (processes / Ray CPUs). ``local`` with 1 runs in this process.
        address: Ray cluster address (None: start a local cluster with ``workers`` CPUs).
        threads_per_worker: threads per task process (default ``max(1, cores // workers)``).
        max_in_flight: tasks submitted ahead of the one being yielded (default ``2 * workers``): bounds memory
            and lets a consumer that stops early (or is killed) lose at most this much work.

    Raises:
        AugmentError: unknown executor, ``workers < 1``, or Ray requested but not installed.
    """
    if executor not in EXECUTORS:
        raise AugmentError(f"executor={executor!r}: expected one of {list(EXECUTORS)}")
    if int(workers) < 1:
        raise AugmentError(f"workers={workers!r}: need at least 1")
    workers = int(workers)
    threads = threads_per_worker or max(1, usable_cores() // workers)
    ahead = max_in_flight or 2 * workers
    if executor == "ray":
        return _map_ray(fn, items, workers, address, threads, ahead)
    if workers == 1:
        return (fn(item) for item in items)
    return _map_pool(fn, items, workers, threads, ahead)


def _map_pool(fn: Callable[[T], R], items: Iterable[T], workers: int, threads: int, ahead: int) -> Iterator[R]:
    pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_worker_init,
                               initargs=(threads, os.getpid()))
    pending: deque = deque()
    finished = False
    try:
        for item in items:
            pending.append(pool.submit(_call, fn, item, threads))
            if len(pending) >= ahead:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
        finished = True
    finally:
        for f in pending:
            f.cancel()
        if not finished:  # an error, Ctrl-C or a consumer that stopped: do not wait for running tasks
            for p in list((getattr(pool, "_processes", None) or {}).values()):
                p.terminate()
        pool.shutdown(wait=True, cancel_futures=True)


def _ray():
    try:
        import ray
    except ImportError as exc:
        raise AugmentError("executor=ray needs Ray: pip install 'umi-aug[ray]' (ray==2.60.0), or use "
                           "executor=local") from exc
    return ray


def _map_ray(fn: Callable[[T], R], items: Iterable[T], workers: int, address: str | None, threads: int,
             ahead: int) -> Iterator[R]:
    ray = _ray()
    started_here = False
    if not ray.is_initialized():
        kwargs: dict[str, Any] = {"runtime_env": {"env_vars": _threads_env(threads)}, "log_to_driver": False}
        if address:
            ray.init(address=address, **kwargs)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, **kwargs)
        started_here = True
        log.info("Ray %s: %s", "connected to " + address if address else f"local cluster, {workers} CPUs",
                 ray.cluster_resources())
    remote_call = ray.remote(num_cpus=1)(_call)
    fn_ref = ray.put(fn)
    pending: deque = deque()
    try:
        for item in items:
            pending.append(remote_call.remote(fn_ref, item, threads))
            if len(pending) >= ahead:
                yield ray.get(pending.popleft())
        while pending:
            yield ray.get(pending.popleft())
    finally:
        for ref in pending:
            ray.cancel(ref)
        if started_here:
            ray.shutdown()

