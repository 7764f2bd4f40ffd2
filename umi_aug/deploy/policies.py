"""Policies the runner can drive besides a trained checkpoint (``Policy.from_checkpoint``); each implements the
policy contract of :mod:`umi_aug.policy.contract` (``reset()``, ``predict_action(obs_dict) -> {"action": …}``)."""

from __future__ import annotations

import numpy as np

from umi_aug.deploy.interpolator import pose_distance
from umi_aug.errors import DeployError
from umi_aug.geometry.interp import interpolate_pose
from umi_aug.geometry.se3 import pos_rotvec_to_pose, pose_to_pos_rotvec
from umi_aug.policy.contract import ACTION_KEY

__all__ = ["ReachPolicy", "REACH_MAX_DISTANCE_BOUND_M"]

#: Largest ``policy.max_distance_m`` accepted (m): the UR5e's reach, 0.85 m (UR5e datasheet), i.e. a reach may
#: never cross the whole workspace in one go.
REACH_MAX_DISTANCE_BOUND_M = 0.85


class ReachPolicy:
    """Scripted: move the TCP in a straight line (slerped rotation) to ``target`` [6] (base frame, m / rotvec)
    at ``speed`` m/s and ``rot_speed`` rad/s, gripper to ``gripper_width``; returns ``{"action": [n_steps, 7]}``
    absolute actions spaced ``dt`` like a trained policy's chunk (the first is the current step).

    A target farther than ``max_distance_m`` (m, at most :data:`REACH_MAX_DISTANCE_BOUND_M`) from the observed
    TCP is refused with :class:`DeployError` (the runner's pre-flight observation asks first, before anything
    moves): the reach starts from wherever the arm is, so a far target means a wrong target or a wrong start."""

    def __init__(self, target: list[float], speed: float = 0.05, rot_speed: float = 0.3, dt: float = 0.1,
                 n_steps: int = 16, gripper_width: float = 0.05, max_distance_m: float = 0.5) -> None:
        self.target = np.asarray(target, np.float64).reshape(-1)
        if self.target.shape != (6,) or not np.isfinite(self.target).all():
            raise DeployError(f"policy.target must be 6 finite numbers [x, y, z, rx, ry, rz], got {target}")
        if not (speed > 0 and rot_speed > 0 and dt > 0 and n_steps >= 1):
            raise DeployError(f"reach policy: speed, rot_speed, dt must be > 0 and n_steps >= 1, got speed={speed}, "
                              f"rot_speed={rot_speed}, dt={dt}, n_steps={n_steps}")
        if not 0 < max_distance_m <= REACH_MAX_DISTANCE_BOUND_M:
            raise DeployError(f"policy.max_distance_m={max_distance_m} must be in (0, {REACH_MAX_DISTANCE_BOUND_M}] m "
                              f"(the UR5e's reach)")
        self.speed, self.rot_speed, self.dt, self.n_steps, self.width = speed, rot_speed, dt, n_steps, gripper_width
        self.max_distance_m = float(max_distance_m)

    def reset(self) -> None:
        pass

    def predict_action(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        cur = np.concatenate([np.asarray(obs["robot0_eef_pos"])[-1], np.asarray(obs["robot0_eef_rot_axis_angle"])[-1]])
        dpos, drot = pose_distance(cur, self.target)
        if dpos > self.max_distance_m:
            raise DeployError(f"policy.target={np.round(self.target, 4).tolist()} is {dpos:.3f} m from the current TCP "
                              f"{np.round(cur[:3], 4).tolist()} m > policy.max_distance_m={self.max_distance_m}; "
                              f"move the arm closer or fix the target")
        dur = max(dpos / self.speed, drot / self.rot_speed, 1e-9)
        s = np.clip(np.arange(self.n_steps) * self.dt / dur, 0.0, 1.0)
        T = interpolate_pose(pos_rotvec_to_pose(cur), pos_rotvec_to_pose(self.target), s)
        out = np.empty((self.n_steps, 7))
        out[:, :6] = pose_to_pos_rotvec(T)
        out[:, 6] = self.width
        return {ACTION_KEY: out}
