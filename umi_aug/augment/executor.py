"""Run independent generation tasks locally (in-process or a process pool) or on Ray, results in input order.

One call, :func:`map_ordered`, so the offline export gives the same dataset whichever executor runs it: tasks are
pure functions of their argument (each episode's randomness comes from a seed derived from its id, never from
which worker runs it) and results come back in the order of ``items``, so they are appended in that order.

* ``"local"`` — ``workers <= 1``: in this process (no pickling, easiest to debug); ``workers > 1``: a ``spawn``
  process pool (spawn, not fork: torch, numba and MuJoCo/EGL thread pools do not survive ``fork``).
* ``"ray"`` — a local Ray cluster with ``workers`` CPUs (no network needed), or an existing cluster when
  ``address`` is given (``"auto"`` or ``"ray://host:10001"``). Ray is imported only here, only then.

With ``build``/``needs``, items wait for a per-key build task (a plain dataset's scene: scene build → its
episodes): builds run as tasks of their own, several at once, ahead of the items that need them, so on N workers
N scenes build in parallel instead of N workers waiting on one scene's lock.

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
from collections.abc import Hashable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
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
                max_in_flight: int | None = None, needs: Callable[[T], Hashable | None] | None = None,
                build: Callable[[Any], Any] | None = None, on_built: Callable[[Any, Any], None] | None = None,
                builds_ahead: int | None = None) -> Iterator[R]:
    """Yield ``fn(item)`` for every item, in the order of ``items``; optionally after a per-key build task.

    With ``build``, every distinct key ``needs(item)`` (None: the item needs nothing) gets ONE ``build(key)``
    task — a scene build, say — that runs before any item with that key. Builds run as their own tasks, up to
    ``builds_ahead`` at once, in the order the items need them, so the scenes of the coming items build in
    parallel while the items of finished ones run (a UMI dataset: scene build → its episodes). A build's error
    is raised where the first item that needs it would have been yielded: every earlier result comes first.

    Args:
        fn: a picklable top-level function (for ``workers > 1`` or Ray); it must be deterministic in its argument.
        items: task arguments (picklable).
        executor: ``"local"`` or ``"ray"``.
        workers: parallel tasks (processes / Ray CPUs). ``local`` with 1 runs in this process.
        address: Ray cluster address (None: start a local cluster with ``workers`` CPUs).
        threads_per_worker: threads per task process (default ``max(1, cores // workers)``).
        max_in_flight: item tasks submitted ahead of the one being yielded (default ``2 * workers``): bounds
            memory and lets a consumer that stops early (or is killed) lose at most this much work.
        needs: item → the key of the build it needs, or None; evaluated here, in the calling process.
        build: picklable ``key → value``, run once per key (its value goes to ``on_built``, here).
        on_built: called here with ``(key, value)`` as each build finishes.
        builds_ahead: unfinished builds at once (default ``workers``).

    Raises:
        AugmentError: unknown executor, ``workers < 1``, ``build`` without ``needs``, or Ray requested but not
            installed.
    """
    if executor not in EXECUTORS:
        raise AugmentError(f"executor={executor!r}: expected one of {list(EXECUTORS)}")
    if int(workers) < 1:
        raise AugmentError(f"workers={workers!r}: need at least 1")
    if (build is None) != (needs is None):
        raise AugmentError("map_ordered: `build` and `needs` go together (the key each item needs, the task that "
                           "builds it)")
    workers = int(workers)
    threads = threads_per_worker or max(1, usable_cores() // workers)
    ahead = max(1, max_in_flight or 2 * workers)
    plan = _Plan(items, needs, build, on_built or (lambda key, value: None), builds_ahead or workers)
    if executor == "ray":
        return _scheduled(plan, fn, ahead, lambda: _RayBackend(workers, address, threads))
    if workers == 1:
        return _in_process(plan, fn)
    return _scheduled(plan, fn, ahead, lambda: _PoolBackend(workers, threads))


@dataclass
class _Plan:
    """The items (consumed lazily when nothing is built), the key each needs (None: nothing) and the builds in
    the order the items first need them (which needs every item's key up front)."""

    items: Iterable
    needs: Callable[[Any], Hashable | None] | None
    build: Callable[[Any], Any] | None
    on_built: Callable[[Any, Any], None]
    builds_ahead: int
    build_order: list = field(init=False)

    def __post_init__(self) -> None:
        if self.needs is None:
            self.build_order = []
            return
        self.items = list(self.items)
        self.build_order = list(dict.fromkeys(k for k in map(self.needs, self.items) if k is not None))

    def key_of(self, item: Any) -> Hashable | None:
        return None if self.needs is None else self.needs(item)


def _in_process(plan: _Plan, fn: Callable[[T], R]) -> Iterator[R]:
    """``workers=1``: each build right before the first item that needs it, then the item, here."""
    done: set = set()
    for item in plan.items:
        key = plan.key_of(item)
        if key is not None and key not in done:
            plan.on_built(key, plan.build(key))
            done.add(key)
        yield fn(item)


class _PoolBackend:
    """A ``spawn`` process pool whose workers die with this process."""

    def __init__(self, workers: int, threads: int) -> None:
        self.threads = threads
        self.pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_worker_init,
                                        initargs=(threads, os.getpid()))

    def submit(self, fn: Callable, arg: Any) -> Future:
        return self.pool.submit(_call, fn, arg, self.threads)

    def wait_any(self, handles: list) -> None:
        wait(handles, return_when=FIRST_COMPLETED)

    def is_done(self, handle: Future) -> bool:
        return handle.done()

    def result(self, handle: Future) -> Any:
        return handle.result()

    def close(self, unfinished: list, finished: bool) -> None:
        for f in unfinished:
            f.cancel()
        if not finished:  # an error, Ctrl-C or a consumer that stopped: do not wait for running tasks
            for p in list((getattr(self.pool, "_processes", None) or {}).values()):
                p.terminate()
        self.pool.shutdown(wait=True, cancel_futures=True)


class _RayBackend:
    """Tasks of one CPU each on a local Ray cluster (``workers`` CPUs) or the one at ``address``."""

    def __init__(self, workers: int, address: str | None, threads: int) -> None:
        ray = self.ray = _ray()
        self.started_here = False
        if not ray.is_initialized():
            kwargs: dict[str, Any] = {"runtime_env": {"env_vars": _threads_env(threads)}, "log_to_driver": False}
            if address:
                ray.init(address=address, **kwargs)
            else:  # this machine's cluster: workers at normal priority, as the process pool's (Ray's default,
                # niceness 15, lets any other busy process starve them: 10-20x slower beside a training run)
                ray.init(num_cpus=workers, include_dashboard=False, _system_config={"worker_niceness": 0}, **kwargs)
            self.started_here = True
            log.info("Ray %s: %s", "connected to " + address if address else f"local cluster, {workers} CPUs",
                     ray.cluster_resources())
        self.threads = threads
        self.remote_call = ray.remote(num_cpus=1)(_call)
        self.shipped: dict[int, Any] = {}  # id(fn) → its object ref: each function is sent to the cluster once

    def submit(self, fn: Callable, arg: Any) -> Any:
        if id(fn) not in self.shipped:
            self.shipped[id(fn)] = (fn, self.ray.put(fn))
        return self.remote_call.remote(self.shipped[id(fn)][1], arg, self.threads)

    def wait_any(self, handles: list) -> None:
        self.ray.wait(handles, num_returns=1)

    def is_done(self, handle: Any) -> bool:
        return bool(self.ray.wait([handle], num_returns=1, timeout=0)[0])

    def result(self, handle: Any) -> Any:
        return self.ray.get(handle)

    def close(self, unfinished: list, finished: bool) -> None:
        for ref in unfinished:
            self.ray.cancel(ref)
        if self.started_here:
            self.ray.shutdown()


def _scheduled(plan: _Plan, fn: Callable[[T], R], ahead: int, make_backend: Callable[[], Any]) -> Iterator[R]:
    """The driver loop shared by the process pool and Ray: builds in need order (≤ ``plan.builds_ahead``
    unfinished), items in input order once their build is done (≤ ``ahead`` beyond the one to yield next),
    results yielded in input order."""
    backend = make_backend()
    source = iter(plan.items)
    head: tuple | None = None  # (key, item): the next item to submit, pulled from `source`
    exhausted = False
    running_builds: dict[Any, Any] = {}  # key → handle
    built: dict[Any, BaseException | None] = {}  # key → None (done) or the build's error
    queued = deque(plan.build_order)
    submitted: dict[int, Any] = {}  # item index → handle
    next_item = 0
    finished = False

    def collect_builds() -> None:
        for key, h in list(running_builds.items()):
            if backend.is_done(h):
                del running_builds[key]
                try:
                    value = backend.result(h)
                except Exception as exc:  # raised where the first item needing it is yielded
                    built[key] = exc
                else:
                    built[key] = None
                    plan.on_built(key, value)

    def submit_ready(i: int) -> None:
        nonlocal next_item, head, exhausted
        while queued and len(running_builds) < plan.builds_ahead:
            key = queued.popleft()
            running_builds[key] = backend.submit(plan.build, key)
        while next_item < i + ahead:
            if head is None:
                try:
                    item = next(source)
                except StopIteration:
                    exhausted = True
                    return
                head = (plan.key_of(item), item)
            key, item = head
            if key is not None and (key not in built or built[key] is not None):
                return  # in order: wait for its build (or raise its error when this item's turn comes)
            submitted[next_item] = backend.submit(fn, item)
            next_item, head = next_item + 1, None

    try:
        i = 0
        while True:
            while True:
                collect_builds()
                submit_ready(i)
                if i in submitted:
                    if backend.is_done(submitted[i]):
                        break
                    backend.wait_any([submitted[i], *running_builds.values()])
                    continue
                if exhausted:  # every item yielded
                    finished = True
                    return
                error = built.get(head[0]) if head is not None else None
                if error is not None:
                    raise error
                backend.wait_any(list(running_builds.values()))  # item i waits for its build
            yield backend.result(submitted.pop(i))
            i += 1
    finally:
        backend.close(list(submitted.values()) + list(running_builds.values()), finished)


def _ray():
    try:
        import ray
    except ImportError as exc:
        raise AugmentError("executor=ray needs Ray: pip install 'umi-aug[ray]' (ray==2.60.0), or use "
                           "executor=local") from exc
    return ray
