"""The 3DGS kernels' numba cache, made stale by an edit of any file the kernels compile from.

numba keeps a compiled function in ``__pycache__`` (or under ``NUMBA_CACHE_DIR``) with a hash of the ONE file that
defines it, and loads it while that file is unchanged. The kernels here also compile code from other files: the
projection kernels call :func:`umi_aug.splat._kernels._kb_project_jacobian`, and every kernel freezes constants of
``splat/_constants.py`` and ``camera/kb_poly.py`` into its machine code. An edit of one of those files alone (a
checkout, a patch) left the kernels of the other files running the old code. The locators installed here stamp
each kernel-module function with the hashes of all of :data:`KERNEL_SOURCES`, so any edit of any of them recompiles
every kernel; cache paths are numba's own (in-tree, or ``NUMBA_CACHE_DIR`` when set). Functions of other files
keep numba's locators.
"""

from __future__ import annotations

import os
from pathlib import Path

from numba.core import caching

__all__ = ["KERNEL_SOURCES", "install"]

_ROOT = Path(__file__).resolve().parents[1]
#: The files the 3DGS kernels compile from: the four kernel modules and every ``umi_aug`` module they import names
#: from (``camera/kb.py`` re-exports ``camera/kb_poly.py``'s constants). ``tests/splat/test_kernel_flags.py``
#: checks that the kernel modules import from no other ``umi_aug`` module.
KERNEL_SOURCES: tuple[Path, ...] = tuple(_ROOT / p for p in (
    "splat/_kernels.py", "splat/_project_kernels.py", "splat/_loss_kernels.py", "splat/_optim_kernels.py",
    "splat/_constants.py", "camera/kb.py", "camera/kb_poly.py", "runtime.py"))
_KERNEL_MODULES = frozenset(str(p) for p in KERNEL_SOURCES[:4])


class _KernelSetStamp:
    """``get_source_stamp``: the content hashes of every file of :data:`KERNEL_SOURCES` (numba's own per-file
    hash, memoised by modification time and size)."""

    @classmethod
    def from_function(cls, py_func, py_file):
        if str(Path(py_file).resolve()) not in _KERNEL_MODULES:
            return None
        return super().from_function(py_func, py_file)

    def get_source_stamp(self):
        stamps = []
        for path in KERNEL_SOURCES:
            st = os.stat(path)
            stamps.append(caching._hash_source_file(str(path), st.st_mtime, st.st_size))
        return tuple(stamps)


class KernelUserProvidedCacheLocator(_KernelSetStamp, caching.UserProvidedCacheLocator):
    """numba's ``NUMBA_CACHE_DIR`` locator, stamped with every kernel source."""


class KernelInTreeCacheLocator(_KernelSetStamp, caching.InTreeCacheLocator):
    """numba's ``__pycache__`` locator, stamped with every kernel source."""


def install() -> None:
    """Put the two locators first in numba's list (idempotent); called by each kernel module before its first
    ``@njit(cache=True)``. Functions outside the kernel modules are not theirs (``from_function`` returns None)."""
    classes = caching.CacheImpl._locator_classes
    for cls in (KernelInTreeCacheLocator, KernelUserProvidedCacheLocator):
        if cls not in classes:
            classes.insert(0, cls)
