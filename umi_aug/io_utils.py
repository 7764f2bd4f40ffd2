"""Small file-system helpers shared by every stage: atomic writes (write to ``<path>.tmp-<random>``, rename).

Nothing is ever left half-written: if the body of :func:`atomic_path` raises, the temporary file or
directory is removed and the destination is untouched.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import secrets
import shutil
import time
from pathlib import Path
from typing import Iterator


def temp_sibling(path: str | os.PathLike) -> Path:
    """Return an unused temporary path next to ``path``: ``<path>.tmp-<random hex>`` (same file system,
    so the final rename is atomic)."""
    path = Path(path)
    return path.with_name(f"{path.name}.tmp-{secrets.token_hex(4)}")


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, overwrite: bool = True) -> Iterator[Path]:
    """Context manager yielding a temporary path to write ``path`` (a file or a directory) into.

    On normal exit the temporary is renamed onto ``path`` (an existing destination is replaced when
    ``overwrite``; a directory destination is moved aside first and deleted after the swap). On an exception
    the temporary is deleted and the exception propagates.

    Example::

        with atomic_path("out/dataset.zarr.zip") as tmp:
            write_zip(tmp)
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists and overwrite=False")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_sibling(path)
    try:
        yield tmp
        if not tmp.exists():
            raise FileNotFoundError(f"atomic write of {path}: nothing was written to the temporary path {tmp}")
        if path.is_dir() and not path.is_symlink():
            old = temp_sibling(path)
            os.replace(path, old)
            os.replace(tmp, path)
            _remove(old)
        else:
            os.replace(tmp, path)
    except BaseException:
        _remove(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


# ------------------------------------------------------------------------------------------- output safety
LOCK_SUFFIX = ".lock"


class PathLock:
    """An exclusive, advisory lock on an output path: ``<path>.lock`` holding the owner's PID.

    Uses ``fcntl.flock`` on the lock file, so the kernel drops the lock when its holder dies (a lock file left by
    a killed run is simply taken over); a second process trying to take a held lock fails at once with an error
    naming the holder's PID. Use as a context manager or call :meth:`acquire` / :meth:`release`.

    Args:
        path: the path being protected (the lock file is ``<path>.lock`` next to it, or ``<path>/.umi_aug.lock``
            when ``inside=True`` for a folder).
        what: how messages call the path (``"output"``, ``"work dir"``).
        error: exception type raised when the lock is held.
    """

    def __init__(self, path: str | os.PathLike, what: str = "output", error: type[Exception] = RuntimeError,
                 inside: bool = False) -> None:
        self.path = Path(path)
        self.lock_path = self.path / ".umi_aug.lock" if inside else self.path.with_name(self.path.name + LOCK_SUFFIX)
        self.what, self.error = what, error
        self._fd: int | None = None

    def acquire(self) -> "PathLock":
        self.lock_path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.pread(fd, 64, 0).decode("ascii", "replace").strip() or "?"
            os.close(fd)
            raise self.error(f"{self.path}: the {self.what} is in use by another umi-aug run (PID {holder}, lock "
                             f"{self.lock_path}); wait for it to finish, stop it (kill {holder}), or choose "
                             f"another path") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is None:
            return

        with contextlib.suppress(FileNotFoundError):
            self.lock_path.unlink()  # while still holding it: a waiter re-checks on its own fresh file
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> "PathLock":
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def tree_size(path: str | os.PathLike) -> int:
    """Bytes of a file, or of every file under a folder (0 when missing)."""
    p = Path(path)
    if p.is_file():
        return p.stat().st_size
    total = 0
    for dirpath, _dirs, files in os.walk(p):
        for f in files:
            with contextlib.suppress(OSError):
                total += os.stat(os.path.join(dirpath, f)).st_size
    return total


def check_free_space(path: str | os.PathLike, need_bytes: int, what: str,
                     error: type[Exception] = RuntimeError) -> int:
    """Raise ``error`` when the file system that will hold ``path`` has less than ``need_bytes`` free.

    Returns the free bytes. ``what`` says what the space is for (it goes into the message).
    """
    p = Path(path).absolute()
    probe = p
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if need_bytes > free:
        raise error(f"{p}: not enough free disk space on {probe}: {what} needs about {human_bytes(need_bytes)}, "
                    f"{human_bytes(free)} free; free some space or choose another path")
    return free


def human_bytes(n: float) -> str:
    """``n`` bytes as text with a binary unit (``"3.2 GiB"``)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024.0
    return f"{n:.1f} TiB"  # pragma: no cover


def remove_tree_atomically(path: str | os.PathLike) -> None:
    """Delete a file or folder so that a kill at any moment leaves either all of it or nothing under ``path``:
    it is renamed to ``<path>.tmp-<random>`` first (atomic), then deleted."""
    p = Path(path)
    if not p.exists() and not p.is_symlink():
        return
    trash = temp_sibling(p)
    os.replace(p, trash)
    _remove(trash)


def is_inside(path: str | os.PathLike, other: str | os.PathLike) -> bool:
    """True when ``path`` is ``other`` or lies inside it (both resolved)."""
    a, b = Path(path).resolve(), Path(other).resolve()
    return a == b or b in a.parents


class RunLockedError(OSError):
    """Another live process holds the :func:`exclusive_run_lock` of the same file."""


@contextlib.contextmanager
def exclusive_run_lock(path: str | os.PathLike, what: str) -> Iterator[Path]:
    """Hold an exclusive, NON-blocking ``flock`` on ``path`` for the duration of the block, so that two runs of a
    long job (``what``) cannot write the same outputs at once. The holder's pid and start time are written into
    the file; the kernel releases the lock when the holder dies, so a crashed run never blocks the next one.

    Raises:
        RunLockedError: another process holds it; the message names ``what``, the lock file and the holder's pid.
    """
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(p, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
            except ValueError:
                holder = {}
            raise RunLockedError(
                f"{p}: another {what} is running (pid {holder.get('pid', '?')}, started "
                f"{holder.get('started', '?')}); wait for it to finish or stop it, then rerun") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"pid": os.getpid(), "started": time.strftime("%Y-%m-%d %H:%M:%S")}).encode(), 0)
        yield p
    finally:
        os.close(fd)  # closing the descriptor releases the flock
