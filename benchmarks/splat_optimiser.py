"""The 3DGS trainer's optimiser step: the full Adam update of every parameter against the update that skips the SH
coefficients above the rendered degree (``GaussianAdam.step(active=...)``, exact: those have zero gradient and zero
moments), per rendered SH degree, in one run (issue #34 item 1: the 3DGS step's parts on the real episode).

    python benchmarks/splat_optimiser.py [--gaussians 15750] [--repeats 200] [--rounds 3] [--threads 2]

Prints ms per step (median over rounds; the two variants alternate within each round) and the ratio. Run on idle
cores; the ratio is what carries over between machines.
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


def time_steps(n: int, degree: int, active: bool, repeats: int, seed: int) -> float:
    """Seconds per ``GaussianAdam.step`` over ``repeats`` steps with gradients as the renderer leaves them at
    ``degree`` (zero above it)."""
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
    t0 = time.perf_counter()
    for _ in range(repeats):
        opt.step(lrs, active={"sh_rest": k} if active else None)
    return (time.perf_counter() - t0) / repeats


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gaussians", type=int, default=15_750, help="the real episode's 3DGS at 600 steps")
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    configure_threads(args.threads)
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"GaussianAdam.step, {args.gaussians} Gaussians, ms per step (median of {args.rounds} rounds)")
    for c in ("rendered SH degree", "full update", "active prefix", "x"):
        t.add_column(c, justify="right")
    for degree in range(4):
        full, part = [], []
        for r in range(args.rounds):
            order = (False, True) if r % 2 == 0 else (True, False)
            for active in order:
                s = time_steps(args.gaussians, degree, active, args.repeats, seed=r)
                (part if active else full).append(s)
        f, p = statistics.median(full) * 1e3, statistics.median(part) * 1e3
        t.add_row(str(degree), f"{f:.2f}", f"{p:.2f}", f"{f / p:.2f}")
    Console(width=120).print(t)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
