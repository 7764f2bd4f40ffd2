"""Policy-stage throughput: data loader samples/s and training steps/s (small encoder vs. CLIP ViT-B/16).

Run: ``OMP_NUM_THREADS=2 python benchmarks/policy.py [--dataset PATH] [--device cuda] [--batch 8] [--steps 3]``.

* Data: UMI sampling (obs horizon 2, action horizon 16, down-sampling 3) from a UMI ``.zarr.zip`` with 224²
  JPEG-XL images (default: a synthetic one written to a temporary folder: 4 episodes × 120 frames); samples/s
  of :class:`UmiPolicyDataset` through a DataLoader (batch ``--batch``, ``--workers`` workers), including image
  decoding, relative-pose conversion and collation.
* Training: one optimiser step (forward with train-time augmentation, backward, AdamW, EMA) at batch ``--batch``
  on a pre-loaded batch, for ``policy=small`` (ResNet-18 layout at 1/4 width, U-Net 64/128/256),
  ``policy=resnet18`` and ``policy=clip_vit_b16`` (the paper's: ViT-B/16 + U-Net 256/512/1024). ``--device cuda``
  runs the same on a GPU (bf16 autocast with ``--amp bf16``).
"""

from __future__ import annotations

import argparse
import copy
import logging
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from umi_aug.runtime import configure_threads  # noqa: E402

POLICIES = {
    "small": {"encoder": {"name": "resnet", "resnet_width": 16, "image_norm": "imagenet"},
              "down_dims": [64, 128, 256], "diffusion_step_embed_dim": 64},
    "resnet18": {"encoder": {"name": "resnet", "resnet_width": 64, "image_norm": "imagenet"}},
    "clip_vit_b16": {},
}


def make_bench_dataset(path: Path, n_episodes: int = 4, length: int = 120, seed: int = 0) -> Path:
    from umi_aug.data import ReplayBuffer, make_umi_episode
    from umi_aug.geometry import pos_rotvec_to_pose

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:224, 0:224] / 224.0
    buf = ReplayBuffer.create()
    for _ in range(n_episodes):
        s = np.linspace(0, 1, length)[:, None]
        pose6 = np.concatenate([rng.normal(0, 0.2, 3) + s * rng.normal(0, 0.3, 3),
                                rng.normal(0, 0.5, 3) + s * rng.normal(0, 0.5, 3)], axis=1)
        ph = rng.uniform(0, 6.3, 3)
        imgs = np.stack([np.stack([128 + 80 * np.sin(6 * xx + 4 * c * yy + ph[c] + 3 * k / length) + 20 * rng.standard_normal((224, 224))
                                   for c in range(3)], -1) for k in range(length)])
        buf.add_episode(make_umi_episode(pos_rotvec_to_pose(pose6), rng.uniform(0, 0.08, length),
                                         {0: np.clip(imgs, 0, 255).astype(np.uint8)}))
    buf.save(path)
    return path


def bench_loader(path: Path, batch: int, workers: int, n_batches: int) -> dict:
    import torch

    from umi_aug.policy.config import TaskConfig
    from umi_aug.policy.dataset import UmiPolicyDataset

    ds = UmiPolicyDataset(path, TaskConfig(dataset_path=str(path), val_ratio=0.0), "train")
    t0 = time.perf_counter()
    ds.fit_normalizer()
    t_norm = time.perf_counter() - t0
    dl = torch.utils.data.DataLoader(ds, batch_size=batch, shuffle=True, num_workers=workers,
                                     generator=torch.Generator().manual_seed(0))
    it = iter(dl)
    next(it)  # warm-up (worker start, first zip open)
    t0 = time.perf_counter()
    n = 0
    for _ in range(n_batches):
        b = next(it)
        n += b["action"].shape[0]
    dt = time.perf_counter() - t0
    return {"samples": len(ds), "samples_per_s": n / dt, "normalizer_fit_s": t_norm}


def bench_train(path: Path, name: str, batch: int, steps: int, device: str, amp: str) -> dict:
    import torch

    from umi_aug.policy.config import structured_config
    from umi_aug.policy.dataset import UmiPolicyDataset
    from umi_aug.policy.diffusion_policy import DiffusionUnetPolicy
    from umi_aug.policy.ema import EMA

    cfg = structured_config({"task": {"dataset_path": str(path), "val_ratio": 0.0}, "policy": POLICIES[name]})
    ds = UmiPolicyDataset(path, cfg.task, "train")
    torch.manual_seed(0)
    policy = DiffusionUnetPolicy(ds.shape_meta, cfg.policy, warn_random_init=False).to(device)
    policy.set_normalizer(ds.fit_normalizer())
    ema = EMA(copy.deepcopy(policy))
    opt = torch.optim.AdamW(policy.parameters(), lr=3e-4, betas=(0.95, 0.999), weight_decay=1e-6)
    b = torch.utils.data.default_collate([ds[i % len(ds)] for i in range(batch)])
    b = {"obs": {k: v.to(device) for k, v in b["obs"].items()}, "action": b["action"].to(device)}
    ctx = torch.autocast(device_type=torch.device(device).type, dtype=torch.bfloat16) if amp == "bf16" else None
    n_params = sum(p.numel() for p in policy.parameters())

    def step():
        if ctx is not None:
            with ctx:
                loss = policy.compute_loss(b)
        else:
            loss = policy.compute_loss(b)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        ema.step(policy)

    def sync():
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    step()  # warm-up
    sync()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    sync()
    dt = (time.perf_counter() - t0) / steps
    policy.eval()
    t0 = time.perf_counter()
    policy.predict_action({k: v[:1] for k, v in b["obs"].items()})
    sync()
    t_inf = time.perf_counter() - t0
    return {"policy": name, "params_M": n_params / 1e6, "steps_per_s": 1.0 / dt, "s_per_step": dt,
            "samples_per_s": batch / dt, "predict_action_s": t_inf}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", default=None, help="UMI .zarr.zip with 224² camera0_rgb (default: synthetic)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--amp", default="none", choices=["none", "bf16"])
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--steps", type=int, default=3, help="timed optimiser steps per policy (after 1 warm-up)")
    ap.add_argument("--workers", type=int, default=0)
    ap.add_argument("--loader-batches", type=int, default=10)
    ap.add_argument("--policies", default="small,resnet18,clip_vit_b16")
    args = ap.parse_args()
    configure_threads()
    import torch

    logging.basicConfig(level=logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(args.dataset) if args.dataset else make_bench_dataset(Path(tmp) / "dataset.zarr.zip")
        dev = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else platform.processor() or "cpu"
        print(f"policy benchmark — device {args.device} ({dev}), torch {torch.__version__}, "
              f"{torch.get_num_threads()} threads, batch {args.batch}, dataset {path.name if args.dataset else 'synthetic 4×120 frames 224²'}")
        ld = bench_loader(path, args.batch, args.workers, args.loader_batches)
        print(f"\ndata loader ({args.workers} workers, batch {args.batch}, obs 2 × 224² JPEG-XL frames + 16×10 "
              f"actions per sample): {ld['samples_per_s']:.1f} samples/s; normaliser fit over {ld['samples']} "
              f"samples (no image decoded): {ld['normalizer_fit_s'] * 1000:.1f} ms\n")
        rows = [bench_train(path, name, args.batch, args.steps, args.device, args.amp)
                for name in args.policies.split(",")]
        head = f"{'policy':<14}{'params (M)':>11}{'steps/s':>10}{'s/step':>9}{'samples/s':>11}{'predict_action (s)':>20}"
        print(head)
        print("-" * len(head))
        for r in rows:
            print(f"{r['policy']:<14}{r['params_M']:>11.1f}{r['steps_per_s']:>10.3f}{r['s_per_step']:>9.2f}"
                  f"{r['samples_per_s']:>11.2f}{r['predict_action_s']:>20.3f}")
        print("\n(training step = forward with train-time crop + colour jitter, backward, AdamW, EMA update; "
              "predict_action = batch 1 with the policy's inference steps)")


if __name__ == "__main__":
    main()
