"""Geodesic interpolation of rotations and poses (numpy float64).

Rotation: ``R(s) = R0 @ exp(s · log(R0ᵀ R1))`` (constant angular velocity along the shortest geodesic; at a
relative angle of exactly π the direction is whichever axis :func:`so3_log` returns). Translation: linear.
``s = 0`` returns the first pose and ``s = 1`` the second one exactly; other ``s`` extrapolate.
"""

from __future__ import annotations

import numpy as np

from umi_aug.errors import GeometryError
from umi_aug.geometry._checks import as_float
from umi_aug.geometry.se3 import _make_pose
from umi_aug.geometry.so3 import _so3_exp, _so3_log

__all__ = ["slerp_rotations", "interpolate_pose", "PoseTrajectoryInterpolator"]


def _slerp(R0: np.ndarray, R1: np.ndarray, s: np.ndarray) -> np.ndarray:
    delta = _so3_log(np.swapaxes(R0, -1, -2) @ R1)
    out = R0 @ _so3_exp(s[..., None] * delta)
    return np.where((s == 1.0)[..., None, None], R1, out)


def _broadcast(a: np.ndarray, b: np.ndarray, s: np.ndarray, names: tuple[str, str], who: str, mat: int):
    """Broadcast two ``[..., mat, mat]`` arrays and a fraction ``s [...]`` to one batch shape (GeometryError if
    they do not broadcast)."""
    try:
        batch = np.broadcast_shapes(a.shape[:-2], b.shape[:-2], s.shape)
    except ValueError as exc:
        raise GeometryError(
            f"{who}: batch shapes of `{names[0]}` {a.shape}, `{names[1]}` {b.shape} and `s` {s.shape} do not broadcast"
        ) from exc
    return np.broadcast_to(a, batch + (mat, mat)), np.broadcast_to(b, batch + (mat, mat)), np.broadcast_to(s, batch)


def slerp_rotations(R0: np.ndarray, R1: np.ndarray, s: np.ndarray | float) -> np.ndarray:
    """Geodesic interpolation between rotations.

    Args:
        R0: np.ndarray,  # [..., 3, 3]
        R1: np.ndarray,  # [..., 3, 3]
        s: np.ndarray | float,  # [...] fraction in [0, 1]; R0, R1 and s broadcast
    Returns:
        R: np.ndarray,  # [..., 3, 3]
    """
    R0 = as_float(R0, "R0", "slerp_rotations", (3, 3))
    R1 = as_float(R1, "R1", "slerp_rotations", (3, 3))
    s = as_float(s, "s", "slerp_rotations")
    return _slerp(*_broadcast(R0, R1, s, ("R0", "R1"), "slerp_rotations", 3))


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, s: np.ndarray | float) -> np.ndarray:
    """Pose interpolation: slerp of the rotation, lerp of the translation (not the SE(3) screw motion).

    Args:
        T0: np.ndarray,  # [..., 4, 4]
        T1: np.ndarray,  # [..., 4, 4]
        s: np.ndarray | float,  # [...] fraction in [0, 1]; T0, T1 and s broadcast
    Returns:
        T: np.ndarray,  # [..., 4, 4]
    """
    T0 = as_float(T0, "T0", "interpolate_pose", (4, 4))
    T1 = as_float(T1, "T1", "interpolate_pose", (4, 4))
    s = as_float(s, "s", "interpolate_pose")
    T0, T1, s = _broadcast(T0, T1, s, ("T0", "T1"), "interpolate_pose", 4)
    R = _slerp(T0[..., :3, :3], T1[..., :3, :3], s)
    t0, t1 = T0[..., :3, 3], T1[..., :3, 3]
    t = np.where((s == 1.0)[..., None], t1, t0 + s[..., None] * (t1 - t0))
    return _make_pose(R, t)


class PoseTrajectoryInterpolator:
    """Piecewise pose interpolation of a timestamped trajectory (slerp rotation, lerp translation).

    Queries before ``times[0]`` / after ``times[-1]`` are clamped to the first / last pose; a knot time returns
    its pose exactly. ``N = 1`` gives a constant trajectory.

    Args:
        times: np.ndarray,  # [N] seconds, strictly increasing
        poses: np.ndarray,  # [N, 4, 4] T_world_x
    """

    def __init__(self, times: np.ndarray, poses: np.ndarray) -> None:
        times = as_float(times, "times", "PoseTrajectoryInterpolator")
        poses = as_float(poses, "poses", "PoseTrajectoryInterpolator", (4, 4))
        if times.ndim != 1 or times.shape[0] < 1:
            raise GeometryError(f"PoseTrajectoryInterpolator: `times` has shape {times.shape}; expected [N], N >= 1")
        if poses.shape != (times.shape[0], 4, 4):
            raise GeometryError(
                f"PoseTrajectoryInterpolator: `poses` has shape {poses.shape}; expected [{times.shape[0]}, 4, 4]"
            )
        dt = np.diff(times)
        if np.any(dt <= 0):
            i = int(np.argmax(dt <= 0))
            raise GeometryError(
                f"PoseTrajectoryInterpolator: `times` must be strictly increasing; times[{i}]={times[i]!r} "
                f">= times[{i + 1}]={times[i + 1]!r}"
            )
        self.times = times
        self.poses = poses
        R = poses[:, :3, :3]
        self._delta = _so3_log(np.swapaxes(R[:-1], -1, -2) @ R[1:])  # [N-1, 3]
        self._dt = dt

    def __call__(self, t_query: np.ndarray | float) -> np.ndarray:
        """Interpolated poses.

        Args:
            t_query: np.ndarray | float,  # [M] (or any shape [...]) seconds
        Returns:
            np.ndarray,  # [M, 4, 4] (or [..., 4, 4])
        """
        t = as_float(t_query, "t_query", "PoseTrajectoryInterpolator.__call__")
        n = self.times.shape[0]
        if n == 1:
            return np.broadcast_to(self.poses[0], t.shape + (4, 4)).copy()
        i = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, n - 2)
        s = np.clip((t - self.times[i]) / self._dt[i], 0.0, 1.0)
        P0 = self.poses[i]
        R = P0[..., :3, :3] @ _so3_exp(s[..., None] * self._delta[i])
        t0, t1 = P0[..., :3, 3], self.poses[i + 1][..., :3, 3]
        out = _make_pose(R, t0 + s[..., None] * (t1 - t0))
        return np.where((t >= self.times[-1])[..., None, None], self.poses[-1], out)
