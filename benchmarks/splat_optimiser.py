"""The 3DGS trainer's per-step update (issue #34 item 1: the 3DGS step's parts on the real episode), in one run:

* ``GaussianAdam.step``: the torch reference (``_step_torch``) with the full update of every parameter and with the
  update that skips the SH coefficients above the rendered degree (``active=``, exact: those have zero gradient and
  zero moments), against the numba kernel (``splat/_optim_kernels.py``, active prefix), per rendered SH degree;
* the MCMC position noise: ``densify._inject_noise_torch`` against ``inject_noise`` (numba).

    python benchmarks/splat_optimiser.py [--gaussians 29229] [--repeats 200] [--rounds 3] [--threads 2]

Prints ms per step (median over rounds; the variants alternate within each round), the ratios, and how far the
kernel's parameters end from the torch reference's after the repeats (max |difference|, float32). Run on idle
cores; the ratios are what carry over between machines.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from umi_aug.runtime import configure_threads  # noqa: E402


def _params(n: int, seed: int):
    import torch

    from umi_aug.splat.gaussians import Gaussians

    gen = torch.Generator().manual_seed(seed)
    g = Gaussians.from_points(torch.rand(n, 3, generator=gen).double().numpy(),
                              torch.rand(n, 3, generator=gen).double().numpy(), 0.01, 0.5, sh_degree=3,
                              dtype=torch.float32)
    return {k: v.detach().clone().requires_grad_(True) for k, v in g.tensors().items()}


def time_steps(n: int, degree: int, variant: str, repeats: int, seed: int):
    """Seconds per ``GaussianAdam`` step over ``repeats`` steps with gradients as the renderer leaves them at
    ``degree`` (zero above it), and the parameters at the end. ``variant``: ``torch full``, ``torch active`` or
    ``kernel``."""
    import torch

    from umi_aug.splat.optim import GaussianAdam

    params = _params(n, seed)
    opt = GaussianAdam(params)
    k = (degree + 1) ** 2 - 1
    lrs = {name: 1e-3 for name in params}
    grads = {name: torch.randn(p.shape, generator=torch.Generator().manual_seed(seed + 1)) for name, p in
             params.items()}
    grads["sh_rest"][:, k:] = 0.0
    for name, p in params.items():
        p.grad = grads[name]
    step = opt.step if variant == "kernel" else opt._step_torch
    active = None if variant == "torch full" else {"sh_rest": k}
    t0 = time.perf_counter()
    for _ in range(repeats):
        step(lrs, active=active)
    return (time.perf_counter() - t0) / repeats, {name: p.detach().clone() for name, p in params.items()}


def time_noise(n: int, kernel: bool, repeats: int, seed: int):
    """Seconds per position-noise call (MCMC, every step) and the means at the end."""
    import torch

    from umi_aug.splat.densify import _inject_noise_torch, inject_noise

    params = {name: p.detach() for name, p in _params(n, seed).items()}
    with torch.no_grad():
        params["logit_opacities"].uniform_(-8.0, 4.0, generator=torch.Generator().manual_seed(seed))
    gen = torch.Generator().manual_seed(seed + 2)
    fn = inject_noise if kernel else _inject_noise_torch
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn(params, 5e5 * 1.6e-4, gen)
    return (time.perf_counter() - t0) / repeats, params["means"].clone()


def _max_diff(a: dict, b: dict) -> float:
    return max(float((a[k].double() - b[k].double()).abs().max()) for k in a)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gaussians", type=int, default=29_229, help="the real episode's 3DGS at 600 steps")
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    configure_threads(args.threads)
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"the 3DGS update, {args.gaussians} Gaussians, ms per step (median of {args.rounds} rounds)")
    for c in ("what", "torch: full update", "torch: active prefix", "numba kernel", "x active", "x full",
              "max |kernel - torch|"):
        t.add_column(c, justify="right")
    variants = ("torch full", "torch active", "kernel")
    for degree in range(4):
        times: dict[str, list[float]] = {v: [] for v in variants}
        diff = 0.0
        for r in range(args.rounds):
            ends = {}
            for v in (variants if r % 2 == 0 else variants[::-1]):
                sec, ends[v] = time_steps(args.gaussians, degree, v, args.repeats, seed=r)
                times[v].append(sec)
            diff = max(diff, _max_diff(ends["kernel"], ends["torch active"]))
        f, p, k = (statistics.median(times[v]) * 1e3 for v in variants)
        t.add_row(f"Adam, SH degree {degree}", f"{f:.2f}", f"{p:.2f}", f"{k:.2f}", f"{p / k:.2f}", f"{f / k:.2f}",
                  f"{diff:.1e}")
    noise: dict[bool, list[float]] = {False: [], True: []}
    diff = 0.0
    for r in range(args.rounds):
        ends = {}
        for kernel in ((False, True) if r % 2 == 0 else (True, False)):
            sec, ends[kernel] = time_noise(args.gaussians, kernel, args.repeats, seed=r)
            noise[kernel].append(sec)
        diff = max(diff, float((ends[True].double() - ends[False].double()).abs().max()))
    tn, kn = statistics.median(noise[False]) * 1e3, statistics.median(noise[True]) * 1e3
    t.add_row("position noise", f"{tn:.2f}", "", f"{kn:.2f}", f"{tn / kn:.2f}", "", f"{diff:.1e}")
    Console(width=140).print(t)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
