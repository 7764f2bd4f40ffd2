"""UMI replay-buffer key names and the per-step shapes/dtypes UMI expects (umi_stack.md §1)."""

from __future__ import annotations

import re

import numpy as np

DATA_GROUP = "data"
META_GROUP = "meta"
EPISODE_ENDS = "episode_ends"

#: Optional ``meta/`` array (umi-aug's, UMI ignores it): int64 ``[n_episodes]``, which current steps of an episode
#: are training samples: ``-1`` every step (UMI's rule), ``k >= 0`` only step ``k`` (episode-relative). A SPARTN
#: short episode is one sample (its perturbed step), not a window at each of its frames.
SAMPLE_STEP_KEY = "umi_aug_sample_step"

#: Optional ``data/`` array (umi-aug's; UMI's own dataset ignores it): float (N, 7·R) ABSOLUTE COMMANDED targets,
#: per arm [pos(3) m, rotvec(3) rad, gripper width m]; row t = the target commanded for step t (row 0: the start
#: pose). Written where the robot's controller lags its targets (the square env: ``umi_aug.square.commands``);
#: the policy labels with it when ``task.action_key`` names it.
ACTION_KEY = "action"

#: ``camera{j}_rgb``: uint8 (N, H, W, 3) RGB images.
IMAGE_KEY_RE = re.compile(r"^camera\d+_rgb$")

#: Pose / gripper keys → required per-step shape. All must be finite.
LOWDIM_KEY_SHAPES: tuple[tuple[re.Pattern[str], tuple[int, ...]], ...] = (
    (re.compile(r"^robot\d+_eef_pos$"), (3,)),
    (re.compile(r"^robot\d+_eef_rot_axis_angle$"), (3,)),
    (re.compile(r"^robot\d+_gripper_width$"), (1,)),
    (re.compile(r"^robot\d+_demo_start_pose$"), (6,)),
    (re.compile(r"^robot\d+_demo_end_pose$"), (6,)),
)

#: Target chunk size UMI's ``get_optimal_chunks`` aims for (bytes).
TARGET_CHUNK_BYTES = 2_000_000


def is_image_key(key: str) -> bool:
    """True for ``camera{j}_rgb`` keys."""
    return IMAGE_KEY_RE.match(key) is not None


def pose_key_shape(key: str) -> tuple[int, ...] | None:
    """Per-step shape required for a pose/gripper key (e.g. ``(3,)`` for ``robot0_eef_pos``), else None."""
    for pattern, shape in LOWDIM_KEY_SHAPES:
        if pattern.match(key):
            return shape
    return None


def time_chunks(shape: tuple[int, ...], dtype: np.dtype) -> tuple[int, ...]:
    """Chunks along time only, ~2 MB per chunk at most, as UMI's ``get_optimal_chunks`` gives for
    low-dimensional arrays: ``(min(T, ceil(2e6 / row_bytes)), *shape[1:])`` (at least 1 row)."""
    row_bytes = max(1, int(np.dtype(dtype).itemsize * int(np.prod(shape[1:], dtype=np.int64))))
    length = max(1, min(int(shape[0]), -(-TARGET_CHUNK_BYTES // row_bytes)))
    return (length,) + tuple(int(s) for s in shape[1:])
