"""How closely does a square policy reproduce its own training labels? Open-loop chunk error on training samples.

Run: ``python benchmarks/square_chunk_fit.py CKPT [CKPT ...] [--samples 384]``

For ``--samples`` random training samples of the checkpoint's own dataset (its ``task`` config; eval-mode encoder,
one sampling seed), the predicted action chunk against the label chunk: position error (mm, median and 90th
percentile) at chunk targets 0, 7 and 15, and how often the gripper command falls on the wrong side of eval's
close threshold (all targets; and in chunks whose labels open AND close, where the grasp is timed). A policy that
fits its labels closely here but fails closed loop fails on states it was not trained on, not on capacity.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def chunk_fit(checkpoint: str, n_samples: int, seed: int = 0) -> dict:
    """Chunk errors of ``checkpoint`` on ``n_samples`` random samples of its training set (see module doc)."""
    import torch

    from umi_aug.policy.dataset import UmiPolicyDataset
    from umi_aug.policy.inference import Policy
    from umi_aug.square.commands import GRIPPER_CLOSE_BELOW_M

    pol = Policy.from_checkpoint(checkpoint)
    ds = UmiPolicyDataset(pol.cfg.task.dataset_path, pol.cfg.task, "train")
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
    args = ap.parse_args()
    from umi_aug.runtime import configure_threads

    configure_threads()
    print(f"{'checkpoint':<58}{'target 0 mm':>13}{'target 7 mm':>13}{'target 15 mm':>14}{'grip wrong':>12}"
          f"{'at grasp':>10}")
    for ck in args.checkpoints:
        r = chunk_fit(ck, args.samples)
        cells = "".join(f"{'%.1f / %.1f' % tuple(r['pos_mm'][t]):>13}" for t in (0, 7)) + \
            f"{'%.1f / %.1f' % tuple(r['pos_mm'][15]):>14}"
        print(f"{ck[-58:]:<58}{cells}{r['gripper_wrong']:>12.3f}{r['gripper_wrong_transition']:>10.3f}")
    print(f"\n(median / 90th percentile over {args.samples} training samples; 'at grasp': chunks whose labels open "
          "and close)")


if __name__ == "__main__":
    main()
