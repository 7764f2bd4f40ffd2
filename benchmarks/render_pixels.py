"""What leaving out the pixels nobody reads saves, on the real UMI episode's 3DGS scene (issue #34):

1. a 3DGS training step (render + masked loss + backward, full size and the coarse half size) rendering every pixel
   against only the loss mask's (``render(pixels=)``, ``SplatTrainConfig.loss_pixels_only``): the gripper,
   mirrors and the corners outside the image circle;
2. a new export frame (``render_view``) rendering every pixel against only those the gripper overlay does not
   cover completely (the export's ``overlay_pixels`` fast path).

Both pairs must give the same numbers (loss and every gradient; the frame after the overlay): checked on every
frame. Times are interleaved per frame (full, then part) over ``--rounds`` rounds; the table prints the medians
and the ratio of the sums (full / part), with the Gaussian-pixel evaluations the rasteriser visited.

    python benchmarks/render_pixels.py --work /tmp/render_pixels   # builds the episode's scene once (cached there)

Run on idle cores: timings are wall seconds on this machine as it is.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from real_scene_cost import REAL, real_episode_assets  # noqa: E402
from umi_aug.runtime import configure_threads  # noqa: E402


def _train_step(g, T, intr, target, mask, pixels):
    """One training step's render + loss + backward; its loss, gradients and rasteriser evaluations."""
    import torch

    from umi_aug.splat import render
    from umi_aug.splat.losses import photometric_loss

    t0 = time.perf_counter()
    out = render(g, T, intr, torch.zeros(3), pixels=pixels)
    loss, _ = photometric_loss(out.rgb, target, mask)
    grads = torch.autograd.grad(loss, list(g))
    return time.perf_counter() - t0, loss.detach(), grads, out.meta["n_evals"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default=str(REAL))
    ap.add_argument("--work", default="/tmp/umi_aug_render_pixels", help="stage cache of the episode's scene")
    ap.add_argument("--frames", type=int, default=12, help="pre-contact frames timed (evenly spaced)")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    configure_threads()
    import numpy as np
    import torch
    from rich.console import Console
    from rich.table import Table

    from umi_aug.augment.overlay import composite_overlay
    from umi_aug.augment.render import render_view
    from umi_aug.splat.train_session import loss_mask

    t0 = time.perf_counter()
    assets, error = real_episode_assets(Path(args.dataset), Path(args.work))
    if error:
        print(error, file=sys.stderr)
        return 2
    build_s = time.perf_counter() - t0
    d = assets.demos[0]
    idx = np.linspace(0, int(d.contact_index), args.frames).round().astype(int)
    originals = assets.original_frames(0, idx)
    g32 = assets.gaussians
    intr = assets.policy_intrinsics
    rows: dict[str, dict[str, list]] = {}

    def add(name: str, full_s: float, part_s: float, ev_full: int, ev_part: int) -> None:
        r = rows.setdefault(name, {"full": [], "part": [], "ev_full": [], "ev_part": []})
        r["full"].append(full_s)
        r["part"].append(part_s)
        r["ev_full"].append(ev_full)
        r["ev_part"].append(ev_part)

    for f in (1, 2):  # 1: full size; 2: the coarse half of the dataset default's steps
        it = intr if f == 1 else intr.scaled(intr.width // f, intr.height // f)
        mask = loss_mask(it)
        g = g32.detach().requires_grad_(True)
        for _ in range(args.rounds):
            for k, o in zip(idx, originals):
                img = o if f == 1 else o.reshape(it.height, f, it.width, f, 3).mean(axis=(1, 3))
                target = torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32) / 255.0)
                T = d.T_world_cam[k]
                a = _train_step(g, T, it, target, torch.from_numpy(mask), None)
                b = _train_step(g, T, it, target, torch.from_numpy(mask), mask)
                if not (torch.equal(a[1], b[1]) and all(torch.equal(x, y) for x, y in zip(a[2], b[2]))):
                    print(f"error: frame {k} at 1/{f}: the loss or a gradient differs", file=sys.stderr)
                    return 1
                add(f"training step, {it.width}x{it.height}", a[0], b[0], a[3], b[3])
    keep = assets.rendered_pixels
    alpha = assets.overlay_alpha
    with torch.no_grad():
        for _ in range(args.rounds):
            for k, o in zip(idx, originals):
                t1 = time.perf_counter()
                full = render_view(assets, d.T_world_cam[k])
                t2 = time.perf_counter()
                part = render_view(assets, d.T_world_cam[k], pixels=keep)
                t3 = time.perf_counter()
                if not np.array_equal(composite_overlay(full, o, alpha), composite_overlay(part, o, alpha)):
                    print(f"error: frame {k}: the overlaid frame differs", file=sys.stderr)
                    return 1
                add(f"export frame, {intr.width}x{intr.height}", t2 - t1, t3 - t2, 0, 0)

    console = Console(width=160)
    t = Table(title=f"the real episode's 3DGS ({g32.n} Gaussians), {len(idx)} pre-contact frames x {args.rounds} "
                    f"rounds; loss mask keeps {loss_mask(intr).mean():.0%} of a frame, the overlay leaves "
                    f"{keep.mean():.0%} to render (scene built or read in {build_s:.0f} s)")
    for c in ("what", "every pixel: median ms", "only the pixels read: median ms", "x (sum full / sum part)",
              "evals every pixel", "evals pixels read"):
        t.add_column(c, justify="right")
    for name, r in rows.items():
        t.add_row(name, f"{1e3 * statistics.median(r['full']):.1f}", f"{1e3 * statistics.median(r['part']):.1f}",
                  f"{sum(r['full']) / sum(r['part']):.2f}",
                  f"{statistics.median(r['ev_full']):.0f}" if any(r["ev_full"]) else "—",
                  f"{statistics.median(r['ev_part']):.0f}" if any(r["ev_part"]) else "—")
    console.print(t)
    console.print("same loss and gradients on every training step, same overlaid frame on every export frame")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
