"""Shared inputs for the Kannala–Brandt camera tests (no files, everything generated)."""

from __future__ import annotations

import math

import numpy as np

from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.camera.kb import kb_dtheta_d, kb_theta_d

# UMI's published GoPro 10 + Max Lens Mod calibration at 2704x2028 (traj_sdf_sim_notes.md §4)
GOPRO_F = 796.8544625226342
GOPRO_CX = 1354.4265245977356
GOPRO_CY = 1011.4847310011687
GOPRO_K = (-0.02196117964405394, -0.018959717016668237, 0.001693880829392453, -0.00016807228608000285)
EPS = float(np.finfo(np.float64).eps)


def gopro() -> FisheyeIntrinsics:
    return FisheyeIntrinsics(2704, 2028, GOPRO_F, GOPRO_F, GOPRO_CX, GOPRO_CY, GOPRO_K)


def gopro_224() -> FisheyeIntrinsics:
    return gopro().umi_policy(224)


def random_intrinsics(rng: np.random.Generator) -> FisheyeIntrinsics:
    """Random plausible KB intrinsics (mild distortion, slightly non-square pixels)."""
    w = int(rng.integers(200, 3000))
    h = int(rng.integers(200, 2500))
    fx = float(rng.uniform(0.15, 0.6) * w)
    fy = fx * float(rng.uniform(0.97, 1.03))
    cx = float(rng.uniform(0.4, 0.6) * w)
    cy = float(rng.uniform(0.4, 0.6) * h)
    k = (
        float(rng.uniform(-0.06, 0.06)),
        float(rng.uniform(-0.02, 0.02)),
        float(rng.uniform(-0.004, 0.004)),
        float(rng.uniform(-0.0006, 0.0006)),
    )
    return FisheyeIntrinsics(w, h, fx, fy, cx, cy, k)


def intrinsics_zoo(rng: np.random.Generator) -> list[FisheyeIntrinsics]:
    """GoPro full res, GoPro 224², equidistant, ORB-SLAM3 KB8 and two random models."""
    return [
        gopro(),
        gopro_224(),
        FisheyeIntrinsics.equidistant(640, 480, 200.0),
        FisheyeIntrinsics(960, 720, 282.907, 282.907, 480.0, 360.0, (-0.017458, -0.028083, 0.012833, -0.004520)),
        random_intrinsics(rng),
        random_intrinsics(rng),
    ]


def special_thetas(intr: FisheyeIntrinsics) -> np.ndarray:
    """The stability cases of the brief, clipped to the valid range of ``intr``."""
    t = [0.0, 1e-12, 1e-6, math.radians(45), math.radians(89.9), math.pi / 2, math.radians(100)]
    if math.isfinite(intr.theta_fold):
        t.append(intr.theta_fold - 1e-6)
    t.append(intr.theta_max)
    t = np.array(t)
    return t[t <= intr.theta_max]


def rays_at(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Unit rays ``[..., 3]`` at angle ``theta`` from +z and azimuth ``phi`` (OpenCV camera frame)."""
    theta, phi = np.broadcast_arrays(np.asarray(theta, float), np.asarray(phi, float))
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad) between vectors ``[..., 3]``, accurate for tiny angles."""
    c = np.linalg.norm(np.cross(a, b), axis=-1)
    d = (a * b).sum(-1)
    return np.arctan2(c, d)


def theta_tolerance(intr: FisheyeIntrinsics, theta: np.ndarray, base: float = 1e-12) -> np.ndarray:
    """Round-trip tolerance on theta: ``base`` plus the conditioning of the inverse next to the fold-over
    (rounding of theta_d amplified by 1/theta_d')."""
    td = kb_theta_d(theta, intr.k)
    dtd = np.maximum(kb_dtheta_d(theta, intr.k), 1e-300)
    return base + 64 * EPS * np.maximum(td, 1.0) / dtd
