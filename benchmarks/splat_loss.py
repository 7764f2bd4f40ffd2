"""The 3DGS trainer's photometric loss (L1 + D-SSIM, forward and backward) with the target's SSIM window statistics
recomputed every step (the reference) against kept per view (``ssim_target_stats``, what ``train_splat`` does), in
one run, per image size (issue #34 item 1: the 3DGS step's parts on the real episode).

    python benchmarks/splat_loss.py [--sizes 112 224] [--repeats 50] [--rounds 3] [--threads 2]

Prints ms per loss forward + backward (median over rounds; the two variants alternate within each round), the ratio,
and the largest difference of the loss and of the prediction's gradient between the two (float32). Run on idle cores;
the ratio is what carries over between machines.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from umi_aug.runtime import configure_threads  # noqa: E402


def time_loss(size: int, cached: bool, repeats: int, seed: int) -> tuple[float, float, "object"]:
    """Seconds per ``photometric_loss`` forward + backward on a ``size``² view (random prediction and target, 90 %
    of the pixels masked in), the last loss value and the prediction's gradient."""
    import torch

    from umi_aug.splat.losses import photometric_loss, ssim_target_stats

    gen = torch.Generator().manual_seed(seed)
    target = torch.rand(size, size, 3, generator=gen)
    mask = torch.rand(size, size, generator=gen) > 0.1
    pred = torch.rand(size, size, 3, generator=gen).requires_grad_(True)
    stats = ssim_target_stats(target) if cached else None
    loss = None
    t0 = time.perf_counter()
    for _ in range(repeats):
        pred.grad = None
        loss, _ = photometric_loss(pred, target, mask, 0.2, target_stats=stats)
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

    t = Table(title=f"photometric_loss forward + backward, ms (median of {args.rounds} rounds, {args.threads} threads)")
    for c in ("image", "target stats each step", "target stats kept", "x", "max |Δ loss|", "max |Δ grad|"):
        t.add_column(c, justify="right")
    for size in args.sizes:
        time_loss(size, True, 3, seed=0)  # warm-up
        time_loss(size, False, 3, seed=0)
        ref, kept = [], []
        d_loss = d_grad = 0.0
        for r in range(args.rounds):
            out = {}
            for cached in ((False, True) if r % 2 == 0 else (True, False)):
                s, lv, g = time_loss(size, cached, args.repeats, seed=r)
                (kept if cached else ref).append(s)
                out[cached] = (lv, g)
            d_loss = max(d_loss, abs(out[True][0] - out[False][0]))
            d_grad = max(d_grad, float((out[True][1] - out[False][1]).abs().max()))
        a, b = statistics.median(ref) * 1e3, statistics.median(kept) * 1e3
        t.add_row(f"{size}²", f"{a:.2f}", f"{b:.2f}", f"{a / b:.2f}", f"{d_loss:.1e}", f"{d_grad:.1e}")
    Console().print(t)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
