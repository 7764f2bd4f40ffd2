"""Small UMI datasets (generated) and UMI's facts for the contract tests of :mod:`umi_aug.umi_compat`.

The facts are UMI's ``task/umi.yaml`` dataset block and the training path's requirements as umi_stack.md §8 states
them (UMI at main, checked 2026-11-26); UMI's code itself is never part of this repository. Where UMI's
``diffusion_policy`` package is importable (a user's checkout on ``PYTHONPATH``), ``UMI`` below is True and the same
tests also run against UMI's real classes.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

#: image side of the test datasets (UMI's is 224; the contract does not depend on it)
SIZE = 32
#: episode lengths (UMI's action window at down-sampling 3 is 46 frames)
LENGTHS = (60, 55, 70, 50, 64)


def umi_available() -> bool:
    """UMI's dataset classes import here (its checkout + its small pure-Python deps on ``PYTHONPATH``)."""
    if importlib.util.find_spec("diffusion_policy") is None:
        return False
    try:
        import diffusion_policy.dataset.umi_dataset  # noqa: F401
    except ImportError:
        return False
    return True


UMI = umi_available()


def umi_task_shape_meta(size: int = SIZE, wrt_start: bool = True) -> dict:
    """``task/umi.yaml``'s ``shape_meta`` as Hydra resolves it (horizons 2, latency 0 — its latencies ×
    ``dataset_frequeny: 0`` —, down-sampling 3, action 16 × 10), with ``size``² images."""
    low = dict(horizon=2, latency_steps=0.0, down_sample_steps=3, type="low_dim", ignore_by_policy=False)
    obs = {"camera0_rgb": dict(shape=[3, size, size], horizon=2, latency_steps=0, down_sample_steps=3, type="rgb",
                               ignore_by_policy=False),
           "robot0_eef_pos": dict(shape=[3], **low),
           "robot0_eef_rot_axis_angle": dict(raw_shape=[3], shape=[6], rotation_rep="rotation_6d", **low),
           "robot0_gripper_width": dict(shape=[1], **low)}
    if wrt_start:
        obs["robot0_eef_rot_axis_angle_wrt_start"] = dict(raw_shape=[3], shape=[6], **low)
    return {"obs": obs, "action": dict(shape=[10], horizon=16, latency_steps=0, down_sample_steps=3,
                                       rotation_rep="rotation_6d")}


def umi_task_dataset_kwargs(dataset_path: str | Path, size: int = SIZE) -> dict:
    """Exactly the keyword arguments ``task/umi.yaml``'s ``dataset:`` block passes (umi_stack.md §8)."""
    return {"shape_meta": umi_task_shape_meta(size), "dataset_path": str(dataset_path), "cache_dir": None,
            "pose_repr": {"obs_pose_repr": "relative", "action_pose_repr": "relative"}, "action_padding": False,
            "temporally_independent_normalization": False, "repeat_frame_prob": 0.0, "max_duration": None,
            "seed": 42, "val_ratio": 0.05}


def smooth_episode(rng: np.random.Generator, n: int, size: int = SIZE, grasp_at: int | None = None) -> dict:
    """A UMI episode: a smooth TCP path (metres / radians), the gripper open (0.085 m) until ``grasp_at`` then
    closed (0.03 m), ``size``² random-ish frames."""
    from umi_aug.data import make_umi_episode
    from umi_aug.geometry import pos_rotvec_to_pose

    t = np.linspace(0.0, 1.0, n)[:, None]
    p0, p1 = rng.normal(0, 0.2, 3), rng.normal(0, 0.2, 3)
    r0, r1 = rng.normal(0, 0.8, 3), rng.normal(0, 0.8, 3)
    pose6 = np.concatenate([p0 + (p1 - p0) * t + 0.01 * np.sin(7 * t), r0 + (r1 - r0) * t], axis=1)
    g = np.full(n, 0.085)
    if grasp_at is not None:
        g[grasp_at:] = 0.03
    yy, xx = np.mgrid[0:size, 0:size] / size
    frames = np.stack([np.stack([128 + 100 * np.sin(6 * xx + k * 0.3 + c) * np.cos(4 * yy) for c in range(3)], -1)
                       for k in range(n)])
    return make_umi_episode(pos_rotvec_to_pose(pose6), g, {0: np.clip(frames, 0, 255).astype(np.uint8)})


def write_dataset(path: Path, rng: np.random.Generator, lengths=LENGTHS, grasp_frac: float = 0.15,
                  source_episode: list[int] | None = None) -> Path:
    """A UMI ``.zarr.zip`` (or zarr directory) of smooth episodes; ``source_episode`` writes umi-aug export
    records (``meta/aug_source_episode``) too."""
    from umi_aug.data import ReplayBuffer

    rb = ReplayBuffer.create()
    for n in lengths:
        rb.add_episode(smooth_episode(rng, n, grasp_at=int(n * grasp_frac)))
    if source_episode is not None:
        rb.meta.array("aug_source_episode", np.asarray(source_episode, np.int64), compressor=None)
    return rb.save(path)


@pytest.fixture(scope="module")
def umi_zip(tmp_path_factory) -> Path:
    """The contract tests' dataset: 5 episodes, 32² images (seeded: the module's tests share it)."""
    return write_dataset(tmp_path_factory.mktemp("umi_compat") / "dataset.zarr.zip", np.random.default_rng(30))
