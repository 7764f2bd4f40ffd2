"""Safety checks applied to every commanded pose and every observation before the robot acts on it.

Poses are ``[x, y, z, rx, ry, rz]`` of the TCP in the robot base frame (m, rad). What stops the runner raises
:class:`SafetyStop` (one message naming the value and the limit); the table-height clamp and the gripper range
only modify the command (as UMI does).

The limits themselves are bounded by what a UR5e and UMI's own settings allow (:data:`BOUNDS`, each with its
source): a config outside them is one :class:`DeployError` naming the key, the value and the bound, raised while
the config is read — before any device starts. :func:`check_start_pose` is the start-up check (current TCP inside
the box and above the table) run before the first command.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from umi_aug.config_check import reject_unknown_keys
from umi_aug.deploy.interpolator import pose_distance
from umi_aug.errors import DeployError
from umi_aug.geometry.so3 import so3_exp

__all__ = ["SafetyLimits", "SafetyStop", "clamp_to_table", "check_command", "check_obs_age", "check_start_pose",
           "check_robot_limits", "BOUNDS", "FAST_BOUNDS", "UR5E_REACH_M", "UR5E_SHOULDER_HEIGHT_M"]

FINGER_THICKNESS_M = 25.5e-3  # UMI's solve_table_collision

UR5E_REACH_M = 0.85  # UR5e datasheet: reach 850 mm (shoulder axis → tool flange)
UR5E_SHOULDER_HEIGHT_M = 0.1625  # UR5e DH d1 (base frame origin → shoulder axis, m)
START_TABLE_TOLERANCE_M = 1e-3  # start-up check: finger corners at most this far below height_threshold

#: Every bounded limit: key → (lowest, highest, source). The lowest bound is exclusive when it is 0, inclusive
#: otherwise; the highest is inclusive. A config value outside is one DeployError naming key, value and bound.
BOUNDS: dict[str, tuple[float, float, str]] = {
    "max_pos_speed": (0.0, 1.0, "m/s; UR's default TCP speed limit (#31); above it only with "
                                "robot.allow_fast_speeds=true"),
    "max_rot_speed": (0.0, math.pi, "rad/s; the UR5e's wrist joint speed limit, 180°/s (datasheet); above it "
                                    "only with robot.allow_fast_speeds=true"),
    "watchdog_s": (0.2, 1.0, "s; ≥ 2 heartbeat periods of 0.1 s, ≤ 1 s: the arm may not run unsupervised longer"),
    "watchdog_min_frequency": (1.0, 50.0, "Hz; ur-rtde setWatchdog: ≥ 1 Hz = the robot stops within 1 s of the "
                                          "last kick; ≤ 50 Hz so one late 500 Hz period cannot trip it"),
    "max_joint_speed": (0.0, math.pi, "rad/s; the UR5e's joint speed limit, 180°/s (datasheet)"),
    "stop_deceleration": (1.0, 20.0, "m/s²; the simulated arm's stop, as ur-rtde servoStop(a), default 10 m/s²: "
                                     "≥ 1 m/s² stops a 1 m/s TCP within 0.5 m; ≤ 20 m/s² the sim's joint PD "
                                     "still follows"),
    "stop_rot_deceleration": (math.pi, 20.0 * math.pi, "rad/s²; the simulated arm's stop: the linear bounds × "
                                                        "(π rad/s ÷ 1 m/s), the ratio of the speed bounds"),
    "max_obs_age_s": (0.0, 1.0, "s; UMI's camera latency is 0.17 s + a few frames: older than 1 s is a "
                                "stalled stream"),
    "max_step_m": (0.0, 0.5, "m; a UMI chunk (16 actions × 0.1 s) at the default 0.25 m/s spans 0.4 m"),
    "max_step_rad": (0.0, math.pi, "rad; no rotation is larger"),
    "height_threshold": (-0.1, 1.0, "m; UMI's is −0.024 (fingers may press 24 mm into the table); more than "
                                    "0.1 m below the base plane is below any table the arm stands on"),
    "gripper_max_m": (0.0, 0.11, "m; the WSG-50's stroke is 110 mm (UMI uses 0.09)"),
}
#: With ``robot.allow_fast_speeds=true``: UMI's own eval limits (``eval_real.py``: max_pos_speed 2·√3 m/s,
#: max_rot_speed 6·√3 rad/s) — still subject to the robot's safety configuration.
FAST_BOUNDS: dict[str, tuple[float, float, str]] = {
    "max_pos_speed": (0.0, 2.0 * math.sqrt(3.0), "m/s; UMI eval_real.py's interpolator limit (allow_fast_speeds)"),
    "max_rot_speed": (0.0, 6.0 * math.sqrt(3.0), "rad/s; UMI eval_real.py's interpolator limit "
                                                 "(allow_fast_speeds)"),
}


def check_bound(where: str, key: str, value: Any, bounds: Mapping[str, tuple[float, float, str]] = BOUNDS) -> None:
    """Raise :class:`DeployError` naming ``where.key``, the value and the bound if ``value`` is outside it."""
    lo, hi, why = bounds[key]
    v = float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else float("nan")
    ok = math.isfinite(v) and (v > lo if lo == 0.0 else v >= lo) and v <= hi
    if not ok:
        left = "(" if lo == 0.0 else "["
        raise DeployError(f"{where}.{key}={value!r} is outside {left}{lo:g}, {hi:g}] ({why})")


def check_robot_limits(c: Any, where: str) -> None:
    """The bounded robot-block limits of a UR or simulated UR config ``c`` (speeds, watchdogs, joint speed, the
    simulated arm's stop decelerations)."""
    fast = bool(getattr(c, "allow_fast_speeds", False))
    for k in ("max_pos_speed", "max_rot_speed"):
        check_bound(where, k, getattr(c, k), FAST_BOUNDS if fast else BOUNDS)
    for k in ("watchdog_s", "watchdog_min_frequency", "max_joint_speed", "stop_deceleration",
              "stop_rot_deceleration"):
        if hasattr(c, k):
            check_bound(where, k, getattr(c, k))


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
    def from_mapping(cls, m: Mapping[str, Any], where: str = "safety", tcp_offset: float | None = None
                     ) -> "SafetyLimits":
        """Build from a config mapping; unknown keys, bad values and values outside :data:`BOUNDS` raise
        :class:`DeployError` naming them. With ``tcp_offset`` (m) every corner of the workspace box must lie
        within the arm's reach: ``UR5E_REACH_M + tcp_offset`` from the shoulder (``UR5E_SHOULDER_HEIGHT_M``
        above the base origin)."""
        reject_unknown_keys(m, cls.__dataclass_fields__, where, DeployError)
        lim = cls(**{k: (list(v) if k.startswith("workspace") else float(v)) for k, v in m.items()})
        lo, hi = np.asarray(lim.workspace_min, float), np.asarray(lim.workspace_max, float)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()
                                                        and (lo < hi).all()):
            raise DeployError(f"{where}.workspace_min/max must be 3 numbers each with min < max, got "
                              f"{lim.workspace_min} / {lim.workspace_max}")
        for k in ("max_step_m", "max_step_rad", "max_obs_age_s", "height_threshold", "gripper_max_m"):
            check_bound(where, k, getattr(lim, k))
        if not 0 <= lim.gripper_min_m < lim.gripper_max_m:
            raise DeployError(f"{where}.gripper_min_m/gripper_max_m must satisfy 0 <= min < max, got "
                              f"{lim.gripper_min_m} / {lim.gripper_max_m}")
        if lim.height_threshold >= hi[2]:
            raise DeployError(f"{where}.height_threshold={lim.height_threshold} m must be below "
                              f"workspace_max z={hi[2]} m (no pose would be allowed)")
        if tcp_offset is not None:
            _check_box_in_reach(lo, hi, float(tcp_offset), where)
        return lim


def _check_box_in_reach(lo: np.ndarray, hi: np.ndarray, tcp_offset: float, where: str) -> None:
    """Every corner of the box [lo, hi] (m, base frame) within ``UR5E_REACH_M + tcp_offset`` of the shoulder."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    d = np.linalg.norm(corners - [0.0, 0.0, UR5E_SHOULDER_HEIGHT_M], axis=1)
    reach = UR5E_REACH_M + tcp_offset
    if d.max() > reach:
        c = corners[int(np.argmax(d))]
        raise DeployError(f"{where}.workspace_min/max: corner {np.round(c, 3).tolist()} m is {d.max():.3f} m from "
                          f"the shoulder > the reach {reach:.3f} m (UR5e 0.85 m + tcp_offset {tcp_offset} m); "
                          f"shrink the box")


def check_start_pose(tcp_pose: np.ndarray, gripper_width: float, lim: SafetyLimits) -> None:
    """Start-up check before the first command: the current TCP [6] (base frame) is inside the workspace box and
    its finger corners (at ``gripper_width``, m) are above ``height_threshold``.

    Raises:
        SafetyStop: naming the pose and the limit; nothing has been commanded yet.
    """
    pose = np.asarray(tcp_pose, np.float64).reshape(6)
    lo, hi = np.asarray(lim.workspace_min, float), np.asarray(lim.workspace_max, float)
    if not np.isfinite(pose).all():
        raise SafetyStop(f"start-up check: the current TCP pose is not finite: {pose.tolist()}")
    if (pose[:3] < lo).any() or (pose[:3] > hi).any():
        raise SafetyStop(f"start-up check: the current TCP {np.round(pose[:3], 4).tolist()} m is outside the "
                         f"workspace box min={lo.tolist()} max={hi.tolist()} (safety.workspace_min/max); move the "
                         f"arm into the box (or fix the box) before starting")
    width = float(np.clip(gripper_width, lim.gripper_min_m, lim.gripper_max_m))
    below = clamp_to_table(pose, width, lim.height_threshold)[2] - pose[2]
    if below > START_TABLE_TOLERANCE_M:
        raise SafetyStop(f"start-up check: the fingers of the current TCP {np.round(pose[:3], 4).tolist()} m are "
                         f"{1000 * below:.1f} mm below safety.height_threshold={lim.height_threshold} m; raise the "
                         f"arm before starting")


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
