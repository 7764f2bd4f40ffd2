"""The 3DGS trainer's photometric loss (L1 + D-SSIM, forward and backward) with the target's SSIM window statistics
recomputed every step (the reference) against kept per view (``ssim_target_stats``), and the fused numba loss with
the statistics kept (``photometric_loss_fused``, what ``train_splat`` does), in one run, per image size (issue #34
item 1: the 3DGS step's parts on the real episode).

    python benchmarks/splat_loss.py [--sizes 112 224] [--repeats 50] [--rounds 3] [--threads 2]

Prints ms per loss forward + backward (median over rounds; the variants rotate within each round), the ratios to
the reference, and the largest difference of the loss and of the prediction's gradient from the reference
(float32). Run on idle cores; the ratio is what carries over between machines.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from umi_aug.runtime import configure_threads  # noqa: E402


#: variant → (loss function name in umi_aug.splat.losses, target statistics kept per view)
VARIANTS = {"reference": ("photometric_loss", False), "kept": ("photometric_loss", True),
            "fused": ("photometric_loss_fused", True)}


def time_loss(size: int, variant: str, repeats: int, seed: int) -> tuple[float, float, "object"]:
    """Seconds per loss forward + backward of ``variant`` on a ``size``² view (random prediction and target, 90 %
    of the pixels masked in), the last loss value and the prediction's gradient."""
    import torch

    from umi_aug.splat import losses
    from umi_aug.splat.losses import ssim_target_stats

    name, cached = VARIANTS[variant]
    loss_fn = getattr(losses, name)

    gen = torch.Generator().manual_seed(seed)
    target = torch.rand(size, size, 3, generator=gen)
    mask = torch.rand(size, size, generator=gen) > 0.1
    pred = torch.rand(size, size, 3, generator=gen).requires_grad_(True)
    stats = ssim_target_stats(target) if cached else None
    loss = None
    t0 = time.perf_counter()
    for _ in range(repeats):
        pred.grad = None
        loss, _ = loss_fn(pred, target, mask, 0.2, target_stats=stats)
        loss.backward()
    return (time.perf_counter() - t0) / repeats, float(loss.detach()), pred.grad.clone()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[112, 224], help="112: a coarse step, 224: a full one")
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    configure_threads(args.threads)
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"photometric loss forward + backward, ms (median of {args.rounds} rounds, {args.threads} threads)")
    for c in ("image", "target stats each step", "target stats kept", "fused (numba)", "x kept", "x fused",
              "fused: max |Δ loss|", "fused: max |Δ grad|"):
        t.add_column(c, justify="right")
    names = list(VARIANTS)
    for size in args.sizes:
        for v in names:  # warm-up (numba compilation, torch's first calls)
            time_loss(size, v, 3, seed=0)
        secs: dict[str, list[float]] = {v: [] for v in names}
        d_loss = d_grad = 0.0
        for r in range(args.rounds):
            out = {}
            for v in names[r % len(names):] + names[:r % len(names)]:
                s, lv, g = time_loss(size, v, args.repeats, seed=r)
                secs[v].append(s)
                out[v] = (lv, g)
            d_loss = max(d_loss, abs(out["fused"][0] - out["reference"][0]))
            d_grad = max(d_grad, float((out["fused"][1] - out["reference"][1]).abs().max()))
        a, b, c = (statistics.median(secs[v]) * 1e3 for v in names)
        t.add_row(f"{size}²", f"{a:.2f}", f"{b:.2f}", f"{c:.2f}", f"{a / b:.2f}", f"{a / c:.2f}", f"{d_loss:.1e}",
                  f"{d_grad:.1e}")
    Console().print(t)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
