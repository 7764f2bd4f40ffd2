"""Safety checks applied to every commanded pose and every observation before the robot acts on it.

Poses are ``[x, y, z, rx, ry, rz]`` of the TCP in the robot base frame (m, rad). What stops the runner raises
:class:`SafetyStop` (one message naming the value and the limit); the table-height clamp and the gripper range
only modify the command (as UMI does).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from umi_aug.deploy.interpolator import pose_distance
from umi_aug.deploy.config_check import reject_unknown_keys
from umi_aug.errors import DeployError
from umi_aug.geometry.so3 import so3_exp

__all__ = ["SafetyLimits", "SafetyStop", "clamp_to_table", "check_command", "check_obs_age"]

FINGER_THICKNESS_M = 25.5e-3  # UMI's solve_table_collision


class SafetyStop(DeployError):
    """The runner must stop the robot now (bad command, stale observation, lost connection, robot fault)."""


@dataclass
class SafetyLimits:
    """Limits from the robot config (``safety:`` block of ``configs/robot/*.yaml``).

    Attributes:
        workspace_min, workspace_max: TCP position box in the robot base frame (m); outside → stop.
        height_threshold: lowest z (m, base frame) any finger corner may reach; the TCP is raised to respect it.
        max_step_m, max_step_rad: largest distance between a commanded pose and the current TCP pose; more → stop.
        max_obs_age_s: an observation older than this (now − its timestamp) is refused → stop.
        gripper_min_m, gripper_max_m: commanded gripper widths are clipped to this range.
    """

    workspace_min: list[float] = field(default_factory=lambda: [-0.8, -0.8, -0.1])
    workspace_max: list[float] = field(default_factory=lambda: [0.8, 0.8, 0.8])
    height_threshold: float = -0.024
    max_step_m: float = 0.25
    max_step_rad: float = 1.0
    max_obs_age_s: float = 0.5
    gripper_min_m: float = 0.0
    gripper_max_m: float = 0.09

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any], where: str = "safety") -> "SafetyLimits":
        """Build from a config mapping; unknown keys and bad values raise :class:`DeployError` naming them."""
        reject_unknown_keys(m, cls.__dataclass_fields__, where)
        lim = cls(**{k: (list(v) if k.startswith("workspace") else float(v)) for k, v in m.items()})
        lo, hi = np.asarray(lim.workspace_min, float), np.asarray(lim.workspace_max, float)
        if lo.shape != (3,) or hi.shape != (3,) or not (lo < hi).all():
            raise DeployError(f"{where}.workspace_min/max must be 3 numbers each with min < max, got "
                              f"{lim.workspace_min} / {lim.workspace_max}")
        for k in ("max_step_m", "max_step_rad", "max_obs_age_s"):
            if not float(getattr(lim, k)) > 0:
                raise DeployError(f"{where}.{k} must be > 0, got {getattr(lim, k)}")
        if not 0 <= lim.gripper_min_m < lim.gripper_max_m:
            raise DeployError(f"{where}.gripper_min_m/gripper_max_m must satisfy 0 <= min < max, got "
                              f"{lim.gripper_min_m} / {lim.gripper_max_m}")
        return lim


def clamp_to_table(pose: np.ndarray, gripper_width: float, height_threshold: float) -> np.ndarray:
    """UMI's ``solve_table_collision``: raise the TCP so that the four finger-corner keypoints
    (±width/2 along the TCP x axis, ±thickness/2 along y, in the TCP plane) stay at z >= ``height_threshold``."""
    pose = np.array(pose, np.float64).reshape(6)
    dx, dy = gripper_width / 2.0, FINGER_THICKNESS_M / 2.0
    kp = np.array([[sx * dx, sy * dy, 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    z = (kp @ so3_exp(pose[3:6]).T)[:, 2] + pose[2]
    pose[2] += max(height_threshold - float(z.min()), 0.0)
    return pose


def check_command(pose: np.ndarray, gripper_width: float, current_pose: np.ndarray, lim: SafetyLimits
                  ) -> tuple[np.ndarray, float]:
    """Validate one commanded TCP pose + gripper width against ``lim``; return the (clamped) command.

    Raises:
        SafetyStop: non-finite values, a position outside the workspace box (after the table clamp), or a step
            from ``current_pose`` longer than ``max_step_m`` / ``max_step_rad``.
    """
    pose = np.asarray(pose, np.float64).reshape(6)
    if not (np.isfinite(pose).all() and np.isfinite(gripper_width)):
        raise SafetyStop(f"policy produced a non-finite command: pose={pose.tolist()}, gripper={gripper_width}")
    width = float(np.clip(gripper_width, lim.gripper_min_m, lim.gripper_max_m))
    pose = clamp_to_table(pose, width, lim.height_threshold)
    lo, hi = np.asarray(lim.workspace_min, float), np.asarray(lim.workspace_max, float)
    if (pose[:3] < lo).any() or (pose[:3] > hi).any():
        raise SafetyStop(f"commanded TCP position {np.round(pose[:3], 4).tolist()} m is outside the workspace box "
                         f"min={lo.tolist()} max={hi.tolist()} (robot config safety.workspace_min/max)")
    dpos, drot = pose_distance(current_pose, pose)
    if dpos > lim.max_step_m or drot > lim.max_step_rad:
        raise SafetyStop(f"commanded TCP pose is {dpos:.3f} m / {drot:.3f} rad from the current pose; limits "
                         f"safety.max_step_m={lim.max_step_m}, max_step_rad={lim.max_step_rad}")
    return pose, width


def check_obs_age(what: str, timestamp: float, now: float, lim: SafetyLimits) -> None:
    """Refuse an observation (``what``: 'camera', 'robot', 'gripper') older than ``lim.max_obs_age_s``."""
    age = now - float(timestamp)
    if not np.isfinite(age) or age > lim.max_obs_age_s:
        raise SafetyStop(f"stale {what} observation: {age:.3f} s old > safety.max_obs_age_s={lim.max_obs_age_s} "
                         f"(lost connection or stalled stream?)")
