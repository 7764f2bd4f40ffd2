"""Augmentation pipeline benchmark (issue #9): episodes/hour end to end, the per-stage split, on-the-fly Dataset
samples/s with 0 and 2 DataLoader workers, and error against run time for a few quality settings (3DGS Gaussian
budget / training steps → PSNR of augmented frames against the simulator's ground truth vs episodes/hour).

    python benchmarks/augment.py                       # makes a synthetic session in /tmp/umi_aug_bench_augment
    python benchmarks/augment.py --session DIR --episodes 16 --settings small:10000:800 base:25000:1500

One-time stages (reconstruction, 3DGS training) are reported separately from the per-episode cost; the
episodes/hour figure is the per-episode steady state (plan + render + write) on this machine.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from umi_aug.runtime import configure_threads  # noqa: E402


def _session(path: Path, scan_frames: int) -> Path:
    from umi_aug.sim.session import make_session

    if not (path / "dataset.zarr.zip").is_file():
        make_session(path, seed=0, n_demos=1, scan_frames=scan_frames, benchmark_frames=0, overwrite=True)
    return path


def _dataset_rate(session: Path, assets, workers: int, n: int) -> float:
    import torch

    from umi_aug.policy.augmented_dataset import AugmentedUmiDataset
    from umi_aug.policy.config import TaskConfig
    from umi_aug.policy.dataset import UmiPolicyDataset

    task = TaskConfig(image_size=assets.cfg.image_size, val_ratio=0.0)
    original = UmiPolicyDataset(session / "dataset.zarr.zip", task, "train")
    ds = AugmentedUmiDataset(original, assets, ("freespace",), ratio=0.9, n_aug_per_demo=n, seed=1)
    idx = list(range(len(original), len(original) + n))
    loader = torch.utils.data.DataLoader(torch.utils.data.Subset(ds, idx), batch_size=8, num_workers=workers,
                                         multiprocessing_context="spawn" if workers else None)
    t0 = time.perf_counter()
    count = sum(len(b["action"]) for b in loader)
    return count / (time.perf_counter() - t0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--session", default=None, help="UMI session (default: a synthetic one, made once)")
    p.add_argument("--work", default="/tmp/umi_aug_bench_augment")
    p.add_argument("--scan-frames", type=int, default=120)
    p.add_argument("--episodes", type=int, default=8, help="augmented episodes per setting")
    p.add_argument("--settings", nargs="+", default=["small:10000:600", "base:25000:1500", "large:60000:3000"],
                   help="name:max_gaussians:iterations")
    p.add_argument("--gt-frames", type=int, default=24)
    p.add_argument("--dataset-samples", type=int, default=32)
    args = p.parse_args()
    configure_threads()
    logging.basicConfig(level=logging.WARNING)
    from rich.console import Console
    from rich.table import Table

    from umi_aug.augment import AugmentConfig, SplatStageConfig, export, prepare_session
    from umi_aug.demo.pipeline import compare_with_ground_truth

    console = Console(width=200)
    work = Path(args.work)
    session = Path(args.session) if args.session else _session(work / "session", args.scan_frames)
    rows = []
    for spec in args.settings:
        name, budget, iters = spec.split(":")
        cfg = AugmentConfig(mode="freespace", n_per_demo=args.episodes, seed=0,
                            splat=SplatStageConfig(iterations=int(iters), max_gaussians=int(budget)))
        out = work / f"export_{name}.zarr.zip"
        if out.exists():
            out.unlink()
        t0 = time.perf_counter()
        s = export(session, out, cfg, work_dir=work / "work", resume=False, pictures=False, progress=False)
        wall = time.perf_counter() - t0
        assets = prepare_session(session, work / "work", cfg, progress=False)
        gt = compare_with_ground_truth(session, out, assets, args.gt_frames, work / f"render_vs_gt_{name}.png",
                                       lambda m: None)
        per_ep = sum(s.timings_s.get(k, 0.0) for k in ("plan_s", "render_s", "write_s")) / max(1, s.n_augmented)
        splat = assets.stages["splat"].info
        rows.append({"setting": name, "gaussians": int(budget), "iterations": int(iters),
                     "one_time_s": round(sum(v["seconds"] for v in s.stages.values()), 1),
                     "heldout_psnr": splat.get("heldout_psnr"), "gt_psnr": gt.get("psnr_db_median"),
                     "plan_s_per_ep": s.timings_s.get("plan_s", 0) / max(1, s.n_augmented),
                     "render_s_per_ep": s.timings_s.get("render_s", 0) / max(1, s.n_augmented),
                     "write_s_per_ep": s.timings_s.get("write_s", 0) / max(1, s.n_augmented),
                     "frames_per_ep": s.frames_rendered / max(1, s.n_augmented),
                     "episodes_per_hour": 3600.0 / per_ep if per_ep > 0 else float("nan"),
                     "failed": s.n_failed, "resampled": s.n_resampled, "wall_s": round(wall, 1)})
        last_assets = assets

    t = Table(title=f"augmentation end to end ({args.episodes} free-space episodes per setting, 224², "
                    f"{os.cpu_count()} CPUs)")
    for col in ("setting", "Gaussians", "3DGS steps", "one-time s", "held-out dB", "vs GT dB", "plan s/ep",
                "render s/ep", "write s/ep", "new frames/ep", "episodes/hour", "failed", "resampled"):
        t.add_column(col, justify="right")
    for r in rows:
        t.add_row(r["setting"], str(r["gaussians"]), str(r["iterations"]), f"{r['one_time_s']:.0f}",
                  f"{r['heldout_psnr'] or float('nan'):.2f}", f"{r['gt_psnr'] or float('nan'):.2f}",
                  f"{r['plan_s_per_ep']:.2f}", f"{r['render_s_per_ep']:.2f}", f"{r['write_s_per_ep']:.2f}",
                  f"{r['frames_per_ep']:.0f}", f"{r['episodes_per_hour']:.0f}", str(r["failed"]), str(r["resampled"]))
    console.print(t)

    d = Table(title=f"on-the-fly AugmentedUmiDataset ({rows[-1]['setting']} scene, batch 8, "
                    f"{args.dataset_samples} augmented samples)")
    d.add_column("DataLoader workers", justify="right")
    d.add_column("samples/s", justify="right")
    rates = {}
    for workers in (0, 2):
        rates[workers] = _dataset_rate(session, last_assets, workers, args.dataset_samples)
        d.add_row(str(workers), f"{rates[workers]:.1f}")
    console.print(d)
    (work / "augment_benchmark.json").write_text(json.dumps({"rows": rows, "dataset_samples_per_s": rates}, indent=2))


if __name__ == "__main__":
    main()
