"""UMI's ``PoseTrajectoryInterpolator``: a piecewise pose trajectory (lerp position, slerp rotation) that new
waypoints can be scheduled into while it is being executed, with maximum linear/angular speeds.

Poses are ``[x, y, z, rx, ry, rz]`` (metres, rotation vector in radians) of the TCP in the robot base frame;
times are seconds on the controller's clock. A scalar variant (:class:`ScalarTrajectoryInterpolator`) serves the
gripper width and the observation alignment.
"""

from __future__ import annotations

import cv2
import numpy as np

from umi_aug.errors import DeployError
from umi_aug.geometry.se3 import pos_rotvec_to_pose
from umi_aug.geometry.so3 import so3_exp, so3_log

__all__ = ["PoseTrajectoryInterpolator", "ScalarTrajectoryInterpolator", "pose_distance"]


def pose_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(translation distance in m, rotation angle in rad) between two ``[6]`` pos+rotvec poses."""
    Ta, Tb = pos_rotvec_to_pose(np.asarray(a, np.float64)), pos_rotvec_to_pose(np.asarray(b, np.float64))
    dpos = float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]))
    drot = float(np.linalg.norm(so3_log(Ta[:3, :3].T @ Tb[:3, :3])))
    return dpos, drot


class PoseTrajectoryInterpolator:
    """Piecewise pose trajectory through timestamped waypoints; constant (held) outside its time span.

    Args:
        times: [N] strictly increasing seconds.
        poses: [N, 6] pos (m) + rotation vector (rad).
    """

    def __init__(self, times: np.ndarray, poses: np.ndarray) -> None:
        t = np.atleast_1d(np.asarray(times, np.float64))
        p = np.asarray(poses, np.float64).reshape(-1, 6)
        if t.ndim != 1 or len(t) != len(p) or len(t) < 1:
            raise DeployError(f"interpolator: times {t.shape} and poses {p.shape} must be [N] and [N, 6], N >= 1")
        if not (np.isfinite(t).all() and np.isfinite(p).all()):
            raise DeployError("interpolator: non-finite waypoint time or pose")
        if np.any(np.diff(t) <= 0):
            raise DeployError(f"interpolator: waypoint times must increase strictly, got {t.tolist()}")
        self.times = t
        self.poses = p
        self._T = pos_rotvec_to_pose(p)
        # per segment: log(R_iᵀ R_{i+1}) once, so a query costs one exp + one log (the 500 Hz servo loop);
        # the same slerp as interpolate_pose (the reference: umi_aug.deploy._ref._interpolator_reference)
        R = self._T[:, :3, :3]
        self._delta = so3_log(np.swapaxes(R[:-1], -1, -2) @ R[1:]) if len(t) > 1 else np.zeros((0, 3))

    def _segment(self, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Segment index ``i`` and fraction ``s`` in [0, 1] of each query time (clamped to the time span)."""
        tc = np.clip(ts, self.times[0], self.times[-1])
        i = np.clip(np.searchsorted(self.times, tc, side="right") - 1, 0, len(self.times) - 2)
        return i, (tc - self.times[i]) / (self.times[i + 1] - self.times[i])

    def __call__(self, t: float | np.ndarray) -> np.ndarray:
        """Pose(s) at time(s) ``t``: [6] for a scalar, [M, 6] for an array."""
        ts = np.atleast_1d(np.asarray(t, np.float64))
        if len(self.times) == 1:
            out = np.repeat(self.poses, len(ts), axis=0)
        else:
            i, s = self._segment(ts)
            p0, p1 = self.poses[i, :3], self.poses[i + 1, :3]
            pos = np.where((s == 1.0)[:, None], p1, p0 + s[:, None] * (p1 - p0))
            if len(ts) == 1:  # the servo loop's query: OpenCV's Rodrigues (C) for exp and log
                k = int(i[0])
                if s[0] == 1.0:
                    R = self._T[k + 1, :3, :3]
                else:
                    R = self._T[k, :3, :3] @ cv2.Rodrigues(s[0] * self._delta[k])[0]
                out = np.concatenate([pos, cv2.Rodrigues(np.ascontiguousarray(R))[0].reshape(1, 3)], 1)
            else:
                R = self._T[i, :3, :3] @ so3_exp(s[:, None] * self._delta[i])
                R = np.where((s == 1.0)[:, None, None], self._T[i + 1, :3, :3], R)
                out = np.concatenate([pos, so3_log(R)], 1)
        return out[0] if np.ndim(t) == 0 else out

    def trim(self, start: float, end: float) -> "PoseTrajectoryInterpolator":
        """The same trajectory restricted to ``[start, end]`` (end points interpolated)."""
        end = max(start, end)
        inner = self.times[(self.times > start) & (self.times < end)]
        ts = np.concatenate([[start], inner, [end]]) if end > start else np.array([start])
        return PoseTrajectoryInterpolator(ts, self(ts))

    def schedule_waypoint(self, pose: np.ndarray, time: float, max_pos_speed: float, max_rot_speed: float,
                          curr_time: float, last_waypoint_time: float | None = None
                          ) -> "PoseTrajectoryInterpolator":
        """UMI's ``schedule_waypoint``: keep the trajectory from ``curr_time`` to the last scheduled waypoint,
        (everything after now when ``time`` is not after it), and append ``pose`` at ``time`` — later if the move from the
        previous end pose would exceed ``max_pos_speed`` (m/s) or ``max_rot_speed`` (rad/s)."""
        if max_pos_speed <= 0 or max_rot_speed <= 0:
            raise DeployError(f"interpolator: speeds must be > 0, got {max_pos_speed}, {max_rot_speed}")
        pose = np.asarray(pose, np.float64).reshape(6)
        if not np.isfinite(pose).all() or not np.isfinite(time):
            raise DeployError(f"interpolator: non-finite waypoint {pose.tolist()} at t={time}")
        if time <= curr_time:
            return self  # already in the past: UMI ignores it
        if last_waypoint_time is None or time <= last_waypoint_time:
            end = curr_time  # replaces everything planned after now
        else:
            end = max(last_waypoint_time, curr_time)
        trimmed = self.trim(curr_time, end)
        dpos, drot = pose_distance(trimmed(end), pose)
        duration = max(time - end, dpos / max_pos_speed, drot / max_rot_speed)
        ts = np.concatenate([trimmed.times, [end + duration]])
        ps = np.concatenate([trimmed.poses, pose[None]])
        if ts[-2] >= ts[-1]:  # zero-length trimmed tail: replace the last point
            ts, ps = np.delete(ts, -2), np.delete(ps, -2, axis=0)
        return PoseTrajectoryInterpolator(ts, ps)


class ScalarTrajectoryInterpolator:
    """Piecewise-linear ``[N, D]`` values over strictly increasing times, held constant outside them."""

    def __init__(self, times: np.ndarray, values: np.ndarray) -> None:
        t = np.atleast_1d(np.asarray(times, np.float64))
        v = np.asarray(values, np.float64).reshape(len(t), -1)
        if len(t) < 1 or np.any(np.diff(t) <= 0) or not (np.isfinite(t).all() and np.isfinite(v).all()):
            raise DeployError(f"interpolator: need >= 1 finite sample at strictly increasing times, got {t.tolist()[:5]}")
        self.times, self.values = t, v

    def __call__(self, t: float | np.ndarray) -> np.ndarray:
        ts = np.atleast_1d(np.asarray(t, np.float64))
        out = np.stack([np.interp(ts, self.times, self.values[:, d]) for d in range(self.values.shape[1])], -1)
        return out[0] if np.ndim(t) == 0 else out
