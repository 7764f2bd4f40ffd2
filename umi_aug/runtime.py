"""Process-level runtime settings: thread counts for the 2-core machines this project targets.

Nothing here runs at import time; entry points (CLI, training, benchmarks, tests) call
:func:`configure_threads` once, before heavy libraries start their thread pools.
"""

from __future__ import annotations

import os

#: Environment variables that size the BLAS/OpenMP thread pools of numpy, scipy, torch and numba.
_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


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
    import sys

    if "torch" in sys.modules:
        torch = sys.modules["torch"]
        wanted = int(os.environ.get("OMP_NUM_THREADS", n_threads))
        if torch.get_num_threads() != wanted:
            torch.set_num_threads(wanted)
        return wanted
    return int(os.environ["OMP_NUM_THREADS"])
