"""Synthetic data for the data-stage tests (small: 64×64 images, a few frames)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import zarr

from umi_aug.data import make_umi_episode
from umi_aug.geometry import pos_rotvec_to_pose

#: Mean-abs-error bound for JPEG XL level 99 on smooth synthetic images (measured ~0.3-0.45 grey levels).
JXL_MAE_BOUND = 1.0
#: Max-abs-error bound for the same content (measured ≤ 6 grey levels).
JXL_MAX_BOUND = 16


def smooth_images(rng: np.random.Generator, n: int, h: int = 64, w: int = 64) -> np.ndarray:
    """uint8 [n, h, w, 3] smooth RGB frames: low-frequency sinusoids plus a ramp, random phases."""
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    frames = []
    for _ in range(n):
        chans = []
        for _c in range(3):
            f = rng.uniform(0.5, 3.0, 2)
            ph = rng.uniform(0.0, 2 * np.pi, 2)
            chans.append(128 + 60 * np.sin(2 * np.pi * f[0] * xx + ph[0]) * np.cos(2 * np.pi * f[1] * yy + ph[1])
                         + 40 * (xx - yy))
        frames.append(np.stack(chans, axis=-1))
    return np.clip(np.round(frames), 0, 255).astype(np.uint8)


def random_tcp_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """float64 [n, 4, 4] random TCP poses (positions ~0.3 m, rotation angles < π)."""
    pose6 = np.concatenate([rng.normal(0, 0.3, (n, 3)), rng.normal(0, 0.8, (n, 3))], axis=1)
    return pos_rotvec_to_pose(pose6)


def random_episode(rng: np.random.Generator, n: int, images: bool = True, size: int = 64,
                   cameras: tuple[int, ...] = (0,)) -> dict[str, np.ndarray]:
    """A UMI episode dict with ``n`` steps (robot0 keys, optional camera keys with smooth images)."""
    imgs = {j: smooth_images(rng, n, size, size) for j in cameras} if images else None
    return make_umi_episode(random_tcp_poses(rng, n), rng.uniform(0.0, 0.09, n), imgs)


def write_raw_buffer(path: Path, data: dict[str, np.ndarray], ends: np.ndarray | None,
                     compressor=None) -> Path:
    """Write a (possibly malformed) buffer with plain zarr: ``data/<key>`` arrays and ``meta/episode_ends``
    (skipped when ``ends`` is None)."""
    root = zarr.open_group(zarr.DirectoryStore(str(path)), mode="w")
    dg = root.require_group("data")
    meta = root.require_group("meta")
    if ends is not None:
        meta.array("episode_ends", np.asarray(ends), compressor=None)
    for k, v in data.items():
        dg.array(k, v, compressor=compressor, chunks=(1,) + v.shape[1:] if k.endswith("_rgb") else None)
    return path


def lowdim_data(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    """Valid robot0 low-dimensional arrays with ``n`` rows."""
    return {
        "robot0_eef_pos": rng.normal(size=(n, 3)).astype(np.float32),
        "robot0_eef_rot_axis_angle": rng.normal(size=(n, 3)).astype(np.float32),
        "robot0_gripper_width": rng.uniform(0, 0.08, (n, 1)).astype(np.float32),
        "robot0_demo_start_pose": np.repeat(rng.normal(size=(1, 6)), n, axis=0),
        "robot0_demo_end_pose": np.repeat(rng.normal(size=(1, 6)), n, axis=0),
    }
