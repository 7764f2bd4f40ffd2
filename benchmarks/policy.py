"""Policy-stage throughput: data loader samples/s and training steps/s (small encoder vs. CLIP ViT-B/16).

Run: ``OMP_NUM_THREADS=2 python benchmarks/policy.py [--dataset PATH] [--device cuda] [--batch 8] [--steps 3]``.

* Data: UMI sampling (obs horizon 2, action horizon 16, down-sampling 3) from a UMI ``.zarr.zip`` with 224²
  JPEG-XL images (default: a synthetic one written to a temporary folder: 4 episodes × 120 frames); samples/s
  of :class:`UmiPolicyDataset` through a DataLoader (batch ``--batch``, ``--workers`` workers), including image
  decoding, relative-pose conversion and collation.
* Training loop (``--loop DATASET``, issue #29): ``TrainWorkspace.run`` end to end on a square demo dataset (84²,
  commanded-target labels) at batch 64 for ``policy=small`` on this machine's threads — steps/s of the whole loop
  (data, augmentation, forward, backward, AdamW, EMA), measured between step 5 and the last, for today's path
  (frames decoded per sample; the sector-by-sector HSV of the colour jitter) and the fast one (frames decoded once
  into memory; the sector-free HSV), in one run, alternating.
* Recipes (``--recipes DATASET``, issue #29 part 3): the same whole loop for the learning-curve recipes
  (diffusion or regression head, average or spatial-softmax pooling, 2 or 1 image frames) in one run, alternating,
  so their training minutes can be compared on a quiet machine (the curves' own clocks ran beside other work).
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


LOOP_VARIANTS: dict[str, dict] = {
    "before: per-sample decode, NCHW, ref. HSV": {"frames_in_memory_gb": 0.0, "hsv": "reference",
                                                  "channels_last": False, "amp": "none"},
    "+ frames decoded once into memory": {"frames_in_memory_gb": 4.0, "hsv": "reference", "channels_last": False,
                                          "amp": "none"},
    "+ sector-free HSV (colour jitter)": {"frames_in_memory_gb": 4.0, "hsv": "fast", "channels_last": False,
                                          "amp": "none"},
    "+ channels-last ResNet (after, fp32)": {"frames_in_memory_gb": 4.0, "hsv": "fast", "channels_last": True,
                                             "amp": "none"},
    "+ bf16 autocast (after, device.amp=bf16)": {"frames_in_memory_gb": 4.0, "hsv": "fast", "channels_last": True,
                                                 "amp": "bf16"},
}


def _merge(into: dict, extra: dict) -> dict:
    """Deep-merge ``extra`` into ``into`` (nested dicts merged key by key, other values replaced)."""
    for k, v in extra.items():
        if isinstance(v, dict) and isinstance(into.get(k), dict):
            _merge(into[k], v)
        else:
            into[k] = v
    return into


_REG = {"action_head": "regression", "head_hidden_dims": [1024, 1024], "regression_loss": "l1"}
_SSM = {"encoder": {"resnet_pool": "spatial_softmax", "spatial_softmax_keypoints": 32}}
#: The learning-curve recipes (train.py overrides in the name) as overrides of the fast loop's config.
RECIPES: dict[str, dict] = {
    "policy=small (diffusion, 2 frames)": {},
    "policy=small task.img_obs_horizon=1": {"task": {"img_obs_horizon": 1}},
    "policy=small_regression": {"policy": dict(_REG)},
    "policy=small_regression_ssm": {"policy": {**_REG, **_SSM}},
    "policy=small_regression_ssm img_obs_horizon=1": {"policy": {**_REG, **_SSM}, "task": {"img_obs_horizon": 1}},
    "the study's (cpu_regression): + task.obs_pose_repr=abs": {
        "policy": {**_REG, **_SSM}, "task": {"img_obs_horizon": 1, "obs_pose_repr": "abs"}},
    "the study's + policy.encoder.resnet_width=64 (ResNet-18)": {
        "policy": {**_REG, "encoder": {**_SSM["encoder"], "resnet_width": 64}},
        "task": {"img_obs_horizon": 1, "obs_pose_repr": "abs"}},
}


def bench_loop(path: Path, variant: dict, steps: int, batch: int, out: Path, extra: dict | None = None) -> dict:
    """``TrainWorkspace.run`` for ``steps`` steps; steps/s between step 5 and the last (from ``logs.jsonl``)."""
    import json

    import umi_aug.policy.image_aug as image_aug
    from umi_aug.policy.config import structured_config
    from umi_aug.policy.workspace import TrainWorkspace

    over = {"output_dir": str(out), "task": {"name": "square", "dataset_path": str(path), "image_size": 84,
                                              "obs_down_sample_steps": 1, "val_ratio": 0.0, "action_key": "action"},
            "policy": {"name": "small", "encoder": {"name": "resnet", "resnet_width": 16, "image_norm": "imagenet",
                                                    "channels_last": variant["channels_last"]},
                       "down_dims": [64, 128, 256], "diffusion_step_embed_dim": 64, "num_inference_steps": 8},
            "device": {"name": "cpu", "device": "cpu", "num_workers": 0, "amp": variant["amp"]},
            "dataloader": {"batch_size": batch, "frames_in_memory_gb": variant["frames_in_memory_gb"]},
            "training": {"max_steps": steps, "num_epochs": 100000, "lr_warmup_steps": 10, "val_every": 0,
                         "sample_every": 0, "checkpoint_every": 0, "checkpoint_every_steps": 0, "resume": False,
                         "progress_bar": False}}
    _merge(over, extra or {})
    fast = image_aug.hsv_to_rgb
    if variant["hsv"] == "reference":
        image_aug.hsv_to_rgb = image_aug._hsv_to_rgb_reference
    try:
        t0 = time.perf_counter()
        TrainWorkspace(structured_config(over)).run()
        wall = time.perf_counter() - t0
    finally:
        image_aug.hsv_to_rgb = fast
    rows = [json.loads(x) for x in (out / "logs.jsonl").read_text().splitlines() if '"train_loss"' in x]
    t = {r["step"]: r["time"] for r in rows}
    return {"steps_per_s": (steps - 5) / (t[steps] - t[5]), "wall_s": wall, "first_step_s": t[1]}


def _alternated_loops(path: Path, runs: dict[str, tuple[dict, dict]], steps: int, rounds: int) -> dict[str, list]:
    """:func:`bench_loop` for every ``name → (variant, config overrides)``, the names alternated over ``rounds``."""
    res: dict[str, list] = {k: [] for k in runs}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(rounds):
            for i, (name, (variant, extra)) in enumerate(runs.items()):
                res[name].append(bench_loop(path, variant, steps, 64, Path(tmp) / f"{r}_{i}", copy.deepcopy(extra)))
    return res


def _speed_table(res: dict[str, list], label: str) -> None:
    """Print steps/s of every run, the median's ratio to the first row's, steps/hour and minutes per 1000 steps."""
    base = np.median([x["steps_per_s"] for x in next(iter(res.values()))])
    head = f"{label:<48}{'steps/s (runs)':>20}{'×':>7}{'steps/hour':>12}{'min / 1000 steps':>18}"
    print(head + "\n" + "-" * len(head))
    for name, xs in res.items():
        v = [x["steps_per_s"] for x in xs]
        med = float(np.median(v))
        print(f"{name:<48}{' / '.join(f'{x:.2f}' for x in v):>20}{med / base:>7.2f}{med * 3600:>12.0f}"
              f"{1000 / med / 60:>18.2f}")


def bench_phases(path: Path, batch: int = 64, reps: int = 8) -> list[tuple[str, float]]:
    """Where one step of the fast loop goes (policy=small, 84², fp32, channels-last): seconds per phase, each
    timed alone over ``reps`` repetitions after a warm-up — the floor the loop's steps/s sits on."""
    import torch

    from umi_aug.policy.config import structured_config
    from umi_aug.policy.dataset import UmiPolicyDataset
    from umi_aug.policy.diffusion_policy import DiffusionUnetPolicy
    from umi_aug.policy.ema import EMA
    from umi_aug.policy.image_aug import color_jitter, random_crop_resize

    cfg = structured_config({"task": {"name": "square", "dataset_path": str(path), "image_size": 84,
                                      "obs_down_sample_steps": 1, "val_ratio": 0.0, "action_key": "action"},
                             "policy": {"name": "small", "encoder": {"name": "resnet", "resnet_width": 16,
                                                                     "image_norm": "imagenet"},
                                        "down_dims": [64, 128, 256], "diffusion_step_embed_dim": 64}})
    ds = UmiPolicyDataset(path, cfg.task, "train")
    ds.frames_in_memory(4.0)
    torch.manual_seed(0)
    policy = DiffusionUnetPolicy(ds.shape_meta, cfg.policy, warn_random_init=False)
    policy.set_normalizer(ds.fit_normalizer())
    ema = EMA(copy.deepcopy(policy))
    opt = torch.optim.AdamW(policy.parameters(), lr=3e-4)
    rng = np.random.default_rng(0)
    b = ds.batch(rng.integers(0, len(ds), batch))
    img = b["obs"]["camera0_rgb"]
    enc = policy.obs_encoder
    nobs = policy.normalizer.normalize(b["obs"])
    nact = policy.normalizer.normalize(b["action"], "action")

    def timed(fn) -> float:
        fn()
        t0 = time.perf_counter()
        for _ in range(reps):
            fn()
        return (time.perf_counter() - t0) / reps

    def fwd_bwd():
        loss = policy.compute_loss(b)
        opt.zero_grad(set_to_none=True)
        loss.backward()

    def backbone_fwd():
        with torch.no_grad():
            x = nobs["camera0_rgb"]
            enc.backbones["camera0_rgb"](x.reshape(-1, *x.shape[2:]))

    with torch.no_grad():
        cond = enc(nobs)
    rows = [("batch from memory (frames + poses → tensors)", timed(lambda: ds.batch(rng.integers(0, len(ds), batch)))),
            ("random crop + resize", timed(lambda: random_crop_resize(img, 0.95))),
            ("colour jitter", timed(lambda: color_jitter(img, 0.3, 0.4, 0.5, 0.08))),
            ("ResNet forward (2 frames × batch)", timed(backbone_fwd))]
    with torch.no_grad():
        t_unet = timed(lambda: policy.model(nact, torch.randint(0, 50, (batch,)), global_cond=cond))
    rows.append(("U-Net forward", t_unet))
    total = timed(fwd_bwd)
    rows.append(("forward + backward, whole policy", total))
    rows.append(("AdamW + EMA", timed(lambda: (opt.step(), ema.step(policy)))))
    return rows


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
    ap.add_argument("--loop", default=None, metavar="DATASET",
                    help="time the training loop on this square demo zarr (umi-aug square-demos --image-size 84)")
    ap.add_argument("--loop-steps", type=int, default=40)
    ap.add_argument("--loop-rounds", type=int, default=2)
    ap.add_argument("--recipes", default=None, metavar="DATASET",
                    help="time the learning-curve recipes' whole training loop on this 84² square demo dataset")
    ap.add_argument("--only", default="", help="with --recipes: only the recipes whose name contains this text")
    args = ap.parse_args()
    configure_threads()
    import torch

    logging.basicConfig(level=logging.WARNING)
    if args.recipes:
        print(f"training loop per recipe — batch 64, 84² square demos {args.recipes}, {torch.get_num_threads()} "
              f"threads, {args.loop_steps} steps per run, {args.loop_rounds} rounds alternating")
        fast = LOOP_VARIANTS["+ channels-last ResNet (after, fp32)"]
        chosen = {k: (fast, v) for k, v in RECIPES.items() if args.only in k}
        if not chosen:
            ap.error(f"--only {args.only!r} matches no recipe; the recipes are: {'; '.join(RECIPES)}")
        _speed_table(_alternated_loops(Path(args.recipes), chosen,
                                       args.loop_steps, args.loop_rounds), "recipe (train.py overrides)")
        return
    if args.loop:
        print(f"training loop — policy=small, batch 64, 84² square demos {args.loop}, {torch.get_num_threads()} "
              f"threads, {args.loop_steps} steps per run, {args.loop_rounds} rounds alternating")
        _speed_table(_alternated_loops(Path(args.loop), {k: (v, {}) for k, v in LOOP_VARIANTS.items()},
                                       args.loop_steps, args.loop_rounds), "variant")
        rows = bench_phases(Path(args.loop))
        print("\nwhere a step goes (fast loop, fp32; each phase timed alone):")
        for name, sec in rows:
            print(f"  {name:<48}{sec * 1000:>8.1f} ms")
        return
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
