"""Build / read one UMI episode dict (the keys UMI's 07_generate_replay_buffer.py writes) from TCP poses."""

from __future__ import annotations

from typing import Mapping

import numpy as np

from umi_aug.errors import DatasetError
from umi_aug.geometry import pos_rotvec_to_pose, pose_to_pos_rotvec


def _pose6(pose: np.ndarray, name: str) -> np.ndarray:
    """Accept a 4×4 pose or a UMI 6-vector; return the float64 (6,) ``[x, y, z, rx, ry, rz]``."""
    p = np.asarray(pose, dtype=np.float64)
    if p.shape == (4, 4):
        p = pose_to_pos_rotvec(p)
    if p.shape != (6,) or not np.isfinite(p).all():
        raise DatasetError(f"make_umi_episode: `{name}` must be a finite 4x4 pose or [x,y,z,rx,ry,rz], "
                           f"got shape {np.shape(pose)}")
    return p


def make_umi_episode(
    T_world_tcp: np.ndarray,  # [T, 4, 4] float, metres, TCP pose in the table-tag frame
    gripper_width: np.ndarray,  # [T] or [T, 1] metres, 0 = closed
    images: Mapping[int, np.ndarray] | None = None,  # {j: [T, H, W, 3] uint8 RGB}
    robot: int = 0,
    demo_start_pose: np.ndarray | None = None,  # [4, 4] or [6]
    demo_end_pose: np.ndarray | None = None,  # [4, 4] or [6]
) -> dict[str, np.ndarray]:
    """Build the UMI replay-buffer keys of one episode for gripper ``robot`` (= i) and cameras ``j``.

    Returns:
        ``robot{i}_eef_pos`` (T,3) float32 m; ``robot{i}_eef_rot_axis_angle`` (T,3) float32 rotation
        vector (rad); ``robot{i}_gripper_width`` (T,1) float32 m; ``robot{i}_demo_start_pose`` /
        ``robot{i}_demo_end_pose`` (T,6) float64 ``[pos, rotvec]`` repeated on every row (default: the
        first / last pose of this episode); ``camera{j}_rgb`` (T,H,W,3) uint8.

    Raises:
        DatasetError: wrong shapes/dtypes, non-finite values or mismatched lengths.
    """
    T = np.asarray(T_world_tcp, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] < 1:
        raise DatasetError(f"make_umi_episode: `T_world_tcp` must be (T, 4, 4) with T >= 1, got {T.shape}")
    if not np.isfinite(T).all():
        raise DatasetError(f"make_umi_episode: `T_world_tcp` holds NaN/Inf at step "
                           f"{int(np.argmin(np.isfinite(T).reshape(len(T), -1).all(1)))}")
    n = T.shape[0]
    g = np.asarray(gripper_width, dtype=np.float64)
    if g.shape not in ((n,), (n, 1)) or not np.isfinite(g).all():
        raise DatasetError(f"make_umi_episode: `gripper_width` must be finite (T,) or (T, 1) with T={n}, "
                           f"got shape {g.shape}")
    pose6 = pose_to_pos_rotvec(T)
    start = pose6[0] if demo_start_pose is None else _pose6(demo_start_pose, "demo_start_pose")
    end = pose6[-1] if demo_end_pose is None else _pose6(demo_end_pose, "demo_end_pose")
    p = f"robot{robot}_"
    out: dict[str, np.ndarray] = {
        p + "eef_pos": pose6[:, :3].astype(np.float32),
        p + "eef_rot_axis_angle": pose6[:, 3:].astype(np.float32),
        p + "gripper_width": g.reshape(n, 1).astype(np.float32),
        p + "demo_start_pose": np.repeat(start[None].astype(np.float64), n, axis=0),
        p + "demo_end_pose": np.repeat(end[None].astype(np.float64), n, axis=0),
    }
    for j, img in sorted((images or {}).items()):
        img = np.asarray(img)
        if img.dtype != np.uint8 or img.ndim != 4 or img.shape[0] != n or img.shape[-1] != 3:
            raise DatasetError(f"make_umi_episode: images[{j}] must be uint8 (T={n}, H, W, 3) RGB, "
                               f"got {img.dtype} {img.shape}")
        out[f"camera{j}_rgb"] = img
    return out


def episode_tcp_poses(episode: Mapping[str, np.ndarray], robot: int = 0) -> np.ndarray:
    """Inverse of :func:`make_umi_episode` for the poses: ``robot{i}_eef_pos`` + ``_eef_rot_axis_angle``
    → ``T_world_tcp`` float64 (T, 4, 4) (metres, table-tag frame)."""
    p = f"robot{robot}_"
    for k in (p + "eef_pos", p + "eef_rot_axis_angle"):
        if k not in episode:
            raise DatasetError(f"episode_tcp_poses: missing key '{k}' (have {sorted(episode)})")
    pos = np.asarray(episode[p + "eef_pos"], dtype=np.float64)
    rot = np.asarray(episode[p + "eef_rot_axis_angle"], dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1:] != (3,) or rot.shape != pos.shape:
        raise DatasetError(f"episode_tcp_poses: '{p}eef_pos' {pos.shape} and '{p}eef_rot_axis_angle' "
                           f"{rot.shape} must both be (T, 3)")
    return pos_rotvec_to_pose(np.concatenate([pos, rot], axis=1))
