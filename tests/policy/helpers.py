"""Synthetic UMI datasets and tiny configs for the policy tests (small images, tiny networks, CPU)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from umi_aug.data import ReplayBuffer, make_umi_episode
from umi_aug.geometry import pos_rotvec_to_pose
from umi_aug.policy.config import TrainConfig, structured_config

#: Image side of the test datasets (the ViT patch must divide it).
SIZE = 32


def smooth_trajectory(rng: np.random.Generator, n: int, motion_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """TCP poses [n, 4, 4] moving smoothly (≈ 0.3 m, ≈ 1 rad over the episode, both times ``motion_scale``) and
    gripper widths [n]."""
    s = np.linspace(0.0, 1.0, n)[:, None]
    p0, v = rng.normal(0, 0.2, 3), motion_scale * rng.normal(0, 0.3, 3)
    r0, w = rng.normal(0, 0.5, 3), motion_scale * rng.normal(0, 0.6, 3)
    pose6 = np.concatenate([p0 + s * v + 0.002 * rng.normal(size=(n, 3)), r0 + s * w], axis=1)
    grip = 0.08 * (0.5 + 0.5 * np.cos(np.pi * s[:, 0] * rng.uniform(0.5, 2.0)))
    return pos_rotvec_to_pose(pose6), grip


def images(rng: np.random.Generator, n: int, size: int = SIZE) -> np.ndarray:
    """uint8 [n, size, size, 3]: a smooth colour field whose content drifts along the episode."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    ph = rng.uniform(0, 2 * np.pi, 3)
    out = [np.stack([128 + 90 * np.sin(2 * np.pi * (xx + 0.7 * c * yy) + ph[c] + 3.0 * k / n) for c in range(3)], -1)
           for k in range(n)]
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def make_dataset(path: Path, rng: np.random.Generator, n_episodes: int = 4, length: int = 40,
                 size: int = SIZE, lengths: list[int] | None = None, motion_scale: float = 1.0) -> Path:
    """Write a UMI ``dataset.zarr.zip`` (or directory) with ``n_episodes`` smooth episodes
    (:func:`smooth_trajectory` with ``motion_scale``)."""
    buf = ReplayBuffer.create()
    for k in range(n_episodes):
        n = lengths[k] if lengths else length
        T, g = smooth_trajectory(rng, n, motion_scale)
        buf.add_episode(make_umi_episode(T, g, {0: images(rng, n, size)}))
    buf.save(path)
    return path


def tiny_config(dataset: Path, tmp: Path, encoder: str = "resnet", **task) -> TrainConfig:
    """A CPU-sized training config: tiny encoder (ResNet width 8 or a 2-layer 64-wide ViT), U-Net [32, 64]."""
    enc = ({"name": "resnet", "resnet_width": 8, "resnet_blocks": [1, 1, 1, 1], "image_norm": "imagenet"}
           if encoder == "resnet" else
           {"name": "clip_vit", "vit_hidden_size": 64, "vit_layers": 2, "vit_heads": 2, "vit_mlp_size": 128,
            "vit_patch_size": 8})
    t = {"name": "test", "dataset_path": str(dataset), "image_size": SIZE, "obs_down_sample_steps": 2,
         "val_ratio": 0.25}
    t.update(task)
    return structured_config({
        "output_dir": str(tmp / "run"),
        "task": t,
        "policy": {"name": "tiny", "encoder": enc, "diffusion_step_embed_dim": 32, "down_dims": [32, 64],
                   "kernel_size": 3, "n_groups": 8, "num_inference_steps": 4,
                   "noise_scheduler": {"num_train_timesteps": 20}},
        "device": {"name": "cpu", "device": "cpu", "threads": 1, "num_workers": 0},
        "dataloader": {"batch_size": 8, "val_batch_size": 8},
        "training": {"num_epochs": 1, "lr": 1e-3, "lr_warmup_steps": 2, "progress_bar": False, "checkpoint_every": 1,
                     "sample_every": 1, "max_val_steps": 1},
    })


def make_tiny_checkpoint(tmp: Path, length: int = 40, obs_down_sample_steps: int = 1, motion_scale: float = 1.0
                         ) -> Path:
    """``tmp/tiny.ckpt``: a random-weight tiny policy (:func:`tiny_config`) with a normaliser fitted on a 2-episode
    synthetic dataset of ``length`` steps (motion times ``motion_scale``), in the trained-checkpoint format — enough
    to run a closed loop. The sampler clips to the normaliser's range, so a smaller ``motion_scale`` bounds how far
    from the current pose its (random) commands can go."""
    from umi_aug.policy.checkpoint import save_checkpoint
    from umi_aug.policy.config import config_to_dict, shape_meta
    from umi_aug.policy.dataset import UmiPolicyDataset
    from umi_aug.policy.diffusion_policy import DiffusionUnetPolicy

    ds = make_dataset(tmp / "d.zarr.zip", np.random.default_rng(0), n_episodes=2, length=length,
                      motion_scale=motion_scale)
    cfg = tiny_config(ds, tmp, obs_down_sample_steps=obs_down_sample_steps, val_ratio=0.0)
    model = DiffusionUnetPolicy(shape_meta(cfg.task), cfg.policy, warn_random_init=False)
    model.set_normalizer(UmiPolicyDataset(ds, cfg.task, split="all").fit_normalizer())
    return save_checkpoint(tmp / "tiny.ckpt", {"cfg": config_to_dict(cfg), "state_dicts": {"model": model.state_dict()},
                                               "pickles": {"global_step": 0, "epoch": 0, "epoch_done": True}})


def max_relative_step_m(ckpt) -> float:
    """Upper bound (m) on how far a checkpoint's relative-pose command can be from the pose it was predicted from:
    the norm of the per-axis largest |value| its action-position normaliser maps onto [-1, 1] (the sampler clips)."""
    from umi_aug.policy.checkpoint import load_checkpoint

    sd = load_checkpoint(ckpt)["state_dicts"]["model"]
    scale = next(v for k, v in sd.items() if k.endswith("p_action_scale")).numpy()[:3]
    offset = next(v for k, v in sd.items() if k.endswith("p_action_offset")).numpy()[:3]
    ends = np.stack([(-1.0 - offset) / scale, (1.0 - offset) / scale])
    return float(np.linalg.norm(np.abs(ends).max(axis=0)))


def with_commanded_targets(src, dst, rng, shape=None, nan_row=None):
    """A copy of dataset ``src`` plus an ``action`` key: commanded targets near the poses (+ 0 / 0.08 widths)."""
    buf = ReplayBuffer.open(src, mode="a", load_to_memory=True)
    n = buf.n_steps
    pose6 = np.concatenate([buf["robot0_eef_pos"][:], buf["robot0_eef_rot_axis_angle"][:]], 1).astype(np.float64)
    act = np.concatenate([pose6 + rng.normal(scale=0.01, size=(n, 6)), rng.choice([0.0, 0.08], (n, 1))], 1)
    if shape is not None:
        act = np.zeros(shape)
    if nan_row is not None:
        act[nan_row, 2] = np.nan
    buf.data.array("action", act.astype(np.float32))
    buf.save(dst)
    return dst, act.astype(np.float32).astype(np.float64), pose6
