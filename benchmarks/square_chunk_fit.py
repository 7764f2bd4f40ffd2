"""How closely does a square policy reproduce its own training labels? Open-loop chunk error on training samples.

Run: ``python benchmarks/square_chunk_fit.py CKPT [CKPT ...] [--samples 384] [--dataset HELDOUT.zarr.zip]``

For ``--samples`` random training samples of the checkpoint's own dataset (its ``task`` config; eval-mode encoder,
one sampling seed), the predicted action chunk against the label chunk: position error (mm, median and 90th
percentile) at chunk targets 0, 7 and 15, and how often the gripper command falls on the wrong side of eval's
close threshold (all targets; and in chunks whose labels open AND close, where the grasp is timed). A policy that
fits its labels closely here but fails closed loop fails on states it was not trained on, not on capacity.

``--dataset`` measures the same on another replay buffer instead, e.g. demos from seeds no training demo used
(``umi-aug square-demos --n 10 --start-seed 5000 --image-size 84 --out square_demos_heldout``): every episode,
no start-pose noise. Training error against held-out error is the policy's generalisation gap, open loop.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def chunk_fit(checkpoint: str, n_samples: int, seed: int = 0, dataset: str | None = None) -> dict:
    """Chunk errors of ``checkpoint`` on ``n_samples`` random samples of its training set, or of every episode of
    the replay buffer ``dataset`` (see module doc)."""
    import torch

    from umi_aug.policy.dataset import UmiPolicyDataset
    from umi_aug.policy.inference import Policy
    from umi_aug.square.commands import GRIPPER_CLOSE_BELOW_M

    pol = Policy.from_checkpoint(checkpoint)
    if dataset is None:
        ds = UmiPolicyDataset(pol.cfg.task.dataset_path, pol.cfg.task, "train")
    else:
        ds = UmiPolicyDataset(dataset, pol.cfg.task, "all", start_pose_noise=0.0)
    idx = np.random.default_rng(seed).choice(len(ds), min(n_samples, len(ds)), replace=False)
    batch = torch.utils.data.default_collate([ds[int(i)] for i in idx])
    with torch.no_grad():
        pred = pol.model.predict_action(batch["obs"], generator=torch.Generator().manual_seed(seed))["action"]
    lab = batch["action"]
    pos_mm = ((pred[..., :3] - lab[..., :3]).norm(dim=-1) * 1000.0).numpy()
    closing = (lab[..., 9] < GRIPPER_CLOSE_BELOW_M).numpy()
    wrong = (pred[..., 9] < GRIPPER_CLOSE_BELOW_M).numpy() != closing
    trans = closing.any(1) & (~closing).any(1)
    return {"pos_mm": {t: np.percentile(pos_mm[:, t], [50, 90]) for t in (0, 7, 15)},
            "gripper_wrong": float(wrong.mean()), "gripper_wrong_transition": float(wrong[trans].mean()),
            "n_transition": int(trans.sum()), "n": len(idx)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="+")
    ap.add_argument("--samples", type=int, default=384)
    ap.add_argument("--dataset", default=None, help="replay buffer to measure on instead of the training set")
    args = ap.parse_args()
    from umi_aug.runtime import configure_threads

    configure_threads()
    print(f"{'checkpoint':<58}{'target 0 mm':>13}{'target 7 mm':>13}{'target 15 mm':>14}{'grip wrong':>12}"
          f"{'at grasp':>10}")
    for ck in args.checkpoints:
        r = chunk_fit(ck, args.samples, dataset=args.dataset)
        cells = "".join(f"{'%.1f / %.1f' % tuple(r['pos_mm'][t]):>13}" for t in (0, 7)) + \
            f"{'%.1f / %.1f' % tuple(r['pos_mm'][15]):>14}"
        print(f"{ck[-58:]:<58}{cells}{r['gripper_wrong']:>12.3f}{r['gripper_wrong_transition']:>10.3f}")
    where = "training samples" if args.dataset is None else f"samples of {args.dataset}"
    print(f"\n(median / 90th percentile over {args.samples} {where}; 'at grasp': chunks whose labels open "
          "and close)")


if __name__ == "__main__":
    main()
