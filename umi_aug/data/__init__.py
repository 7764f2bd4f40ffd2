"""Data stage: UMI zarr replay buffers (read/write, byte-compatible with UMI), their validation, the UMI
JPEG XL codec, episode building from TCP poses and ORB-SLAM3 ``camera_trajectory.csv`` files.

Importing this package registers nothing and opens nothing; :meth:`ReplayBuffer.open` / ``create`` call
:func:`register_codecs`.
"""

from umi_aug.data.codecs import (
    UmiJpegXl,
    register_codecs,
    resolve_compressor,
    umi_default_compressor,
    umi_disk_compressor,
    umi_image_compressor,
    umi_lowdim_compressor,
)
from umi_aug.data.replay_buffer import ReplayBuffer
from umi_aug.data.trajectory_csv import (
    CameraTrajectory,
    read_camera_trajectory_csv,
    write_camera_trajectory_csv,
)
from umi_aug.data.umi_episode import episode_tcp_poses, make_umi_episode
from umi_aug.data.validate import ArrayInfo, ValidationReport, validate_replay_buffer

__all__ = [
    "UmiJpegXl", "register_codecs", "resolve_compressor", "umi_default_compressor", "umi_disk_compressor",
    "umi_image_compressor", "umi_lowdim_compressor",
    "ReplayBuffer", "make_umi_episode", "episode_tcp_poses",
    "validate_replay_buffer", "ValidationReport", "ArrayInfo",
    "CameraTrajectory", "read_camera_trajectory_csv", "write_camera_trajectory_csv",
]
