"""How fast this machine is running right now: a fixed piece of CPU work timed in seconds, to print beside a benchmark
whose wall time is compared across sittings or sessions.

    python benchmarks/machine_probe.py            # one line: seconds for each part (lower = faster)
    python benchmarks/machine_probe.py --rounds 3 # the median of 3

This machine's speed drifts by hours with nothing else running on it (``docs/real_scale.md`` 1k-1m: the same code's
``umi-aug augment -n 2`` took 59-61 s in one sitting and 86-94 s in another). Timings taken in different sittings compare only
when the probe read the same in both; within one sitting, compare interleaved runs. The parts:

* ``numba 1 thread`` / ``numba 2 threads``: a float64 loop (square root, exponential) over 4,096 lanes x 60,000
  steps, compiled before timing; the two-thread time is about half the one-thread time on 2 idle cores (more means a
  core was busy with something else);
* ``matmul``: six 700 x 700 float64 products on numpy's BLAS;
* ``python``: a 3M-term sum in the interpreter (one core, no native code).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from umi_aug.runtime import configure_threads  # noqa: E402


def _loop_kernel():
    """The compiled loop (numba imported on first use, not at import time)."""
    import numba as nb
    import numpy as np

    @nb.njit(parallel=True, fastmath=False, cache=False)
    def loop(a, steps):  # pragma: no cover - compiled
        out = np.zeros(a.shape[0])
        for i in nb.prange(a.shape[0]):
            s = 0.0
            x = a[i]
            for _ in range(steps):
                x = x * 1.0000001 + 1e-7
                s += np.sqrt(x) * np.exp(-x * 1e-3)
            out[i] = s
        return out

    return loop


def probe(rounds: int = 1) -> dict[str, float]:
    """Median seconds of each part over ``rounds`` rounds."""
    import numba as nb
    import numpy as np

    loop = _loop_kernel()
    lanes = np.random.default_rng(0).random(4096)
    loop(lanes, 10)  # compile
    m = np.random.default_rng(1).random((700, 700))
    times: dict[str, list[float]] = {"numba 1 thread": [], "numba 2 threads": [], "matmul": [], "python": []}
    threads = nb.get_num_threads()
    try:
        for _ in range(rounds):
            for name, n in (("numba 1 thread", 1), ("numba 2 threads", min(2, nb.config.NUMBA_NUM_THREADS))):
                nb.set_num_threads(n)
                t = time.perf_counter()
                loop(lanes, 60_000)
                times[name].append(time.perf_counter() - t)
            t = time.perf_counter()
            for _ in range(6):
                m @ m
            times["matmul"].append(time.perf_counter() - t)
            t = time.perf_counter()
            sum(i * i for i in range(3_000_000))
            times["python"].append(time.perf_counter() - t)
    finally:
        nb.set_num_threads(threads)
    return {k: statistics.median(v) for k, v in times.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=1)
    args = ap.parse_args()
    if args.rounds < 1:
        ap.error(f"--rounds must be >= 1, got {args.rounds}")
    configure_threads(2)
    res = probe(args.rounds)
    print(time.strftime("%H:%M:%S"), "probe s:", "  ".join(f"{k} {v:.3f}" for k, v in res.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
