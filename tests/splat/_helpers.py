"""Shared inputs for the splat tests (everything generated; small images so the dense reference is cheap)."""

from __future__ import annotations

import math

import numpy as np
import torch

from umi_aug.camera import FisheyeIntrinsics, gopro_intrinsics_2_7k
from umi_aug.geometry import make_pose, so3_exp
from umi_aug.splat import Gaussians

PARAMS = ("means", "log_scales", "quats_wxyz", "logit_opacities", "sh0", "sh_rest")


def gopro_small(width: int = 64, height: int = 48) -> FisheyeIntrinsics:
    """UMI's GoPro KB calibration scaled down (theta_max ~ 104 deg, strong distortion)."""
    return gopro_intrinsics_2_7k().scaled(width, height)


def random_kb_intrinsics(rng: np.random.Generator, width: int = 64, height: int = 48) -> FisheyeIntrinsics:
    """Random mild KB distortion, slightly non-square pixels, off-centre principal point."""
    f = float(rng.uniform(0.25, 0.45)) * width
    k = (float(rng.uniform(-0.05, 0.05)), float(rng.uniform(-0.02, 0.02)), float(rng.uniform(-0.004, 0.004)),
         float(rng.uniform(-5e-4, 5e-4)))
    return FisheyeIntrinsics(width, height, f, f * float(rng.uniform(0.97, 1.03)),
                             float(rng.uniform(0.45, 0.55)) * (width - 1), float(rng.uniform(0.45, 0.55)) * (height - 1), k)


def random_pose(rng: np.random.Generator) -> np.ndarray:
    """Random ``T_world_cam`` (any rotation, translation within 1 m)."""
    return make_pose(so3_exp(rng.normal(size=3) * 1.5), rng.uniform(-1, 1, 3))


def rays_at(theta: float, phi: float) -> np.ndarray:
    return np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)])


def single_gaussian(mean, scales, quat=(1.0, 0.0, 0.0, 0.0), opacity=0.8, rgb=(0.9, 0.4, 0.2),
                    dtype=torch.float64) -> Gaussians:
    """One Gaussian with a given colour (SH degree 0)."""
    o = float(opacity)
    logit = math.log(o / (1 - o)) if 0 < o < 1 else (-1e4 if o <= 0 else 1e4)
    return Gaussians.from_numpy(
        {
            "means": np.asarray(mean, float).reshape(1, 3),
            "log_scales": np.log(np.asarray(scales, float)).reshape(1, 3),
            "quats_wxyz": np.asarray(quat, float).reshape(1, 4),
            "logit_opacities": np.array([logit]),
            "sh0": ((np.asarray(rgb, float) - 0.5) / 0.28209479177387814).reshape(1, 3),
        },
        dtype=dtype,
    )


def loss_weights(rng: np.random.Generator, H: int, W: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return (torch.as_tensor(rng.normal(size=(H, W, 3))), torch.as_tensor(rng.normal(size=(H, W))),
            torch.as_tensor(rng.normal(size=(H, W))))


def weighted_loss(out, w) -> torch.Tensor:
    """A scalar touching every output: rgb, alpha and ray depth."""
    w_rgb, w_a, w_d = w
    return (out.rgb * w_rgb).sum() + (out.alpha * w_a).sum() + 0.3 * (out.ray_depth * w_d).sum()
