"""Initial guesses: straight line + slerp (free space) and RRT* around the inflated obstacle (obstacle mode).

Both return waypoints ``[T, 4, 4]`` (camera poses) with the endpoints exactly ``x_init`` and ``x_goal``.
Obstacle mode plans the camera position with RRT*; the orientation is slaved to the position (start→goal slerp
at the position's projection onto the start→goal line), which lets every edge check move the whole gripper
sphere set around the hull inflated by ``inflation + margin + rrt.clearance``.
"""

from __future__ import annotations

import numpy as np

from umi_aug.geometry import interpolate_pose
from umi_aug.geometry.so3 import so3_exp_unchecked as _so3_exp, so3_log_unchecked as _so3_log
from umi_aug.traj.constants import RRT_DENSIFY_M, RRT_RELAX_RADIUS_M, RRT_RELAX_SLOPE
from umi_aug.traj.problem import TrajProblem
from umi_aug.traj.rrt import resample_polyline, rrt_star, shortcut_path

__all__ = ["straight_line_guess", "rrt_guess", "demo_entry_index"]


def straight_line_guess(x_init: np.ndarray, x_goal: np.ndarray, T: int) -> np.ndarray:
    """Linear positions + slerped rotations, uniformly in s.

    Args:
        x_init: np.ndarray,  # [B, 4, 4] or [4, 4]
        x_goal: np.ndarray,  # [4, 4]
        T: waypoints.
    Returns:
        np.ndarray,  # [B, T, 4, 4] (or [T, 4, 4])
    """
    single = x_init.ndim == 2
    X = x_init[None] if single else x_init
    s = np.linspace(0.0, 1.0, T)
    out = interpolate_pose(X[:, None], x_goal[None, None], s[None, :])
    out[:, 0], out[:, -1] = X, x_goal
    return out[0] if single else out


class _Validity:
    """Vectorised edge test for camera positions. The orientation at a position ``p`` is a fixed function of it —
    the start→goal slerp at the fraction ``s(p)`` of the projection of ``p`` onto the start→goal line — so every
    gripper sphere can be checked: sphere chords between samples along the edge against the hull inflated by
    ``inflation + margin + extra`` (exact), and the camera centre against the scene SDF (>= ``clearance``, relaxed
    linearly towards the start and the goal, which are given)."""

    def __init__(self, problem: TrajProblem, x_init: np.ndarray, x_goal: np.ndarray) -> None:
        self.pb = problem
        cfg = problem.config.rrt
        self.step = cfg.segment_check_step
        self.p0, self.p1 = x_init[:3, 3], x_goal[:3, 3]
        self.R0, self.R1 = x_init[:3, :3], x_goal[:3, :3]
        self.omega = _so3_log(self.R0.T @ self.R1)  # R(s) = R0 Exp(s ω): the start→goal slerp
        d = self.p1 - self.p0
        self.dd = float(d @ d)
        self.margin = problem.config.margin
        ends = np.stack([x_init, x_goal])
        end_clr = problem.obstacle_clearance(ends).min(axis=-1)  # [2] clearance of the given endpoints
        self.start_ok = bool(end_clr.min() >= self.margin)
        self.target = self.margin + cfg.clearance
        self.end_clr = end_clr - 1e-6  # the endpoints themselves must pass the (closed) test
        self.ends = np.stack([self.p0, self.p1])
        self.ends_d = np.maximum(problem.scene_bound.lower_bound(self.ends), 0.0)
        self.clearance = cfg.clearance

    def fraction(self, p: np.ndarray) -> np.ndarray:
        if self.dd <= 1e-18:
            return np.zeros(p.shape[:-1])
        return np.clip((p - self.p0) @ (self.p1 - self.p0) / self.dd, 0.0, 1.0)

    def poses(self, p: np.ndarray) -> np.ndarray:
        s = self.fraction(p)
        R = self.R0 @ _so3_exp(s[..., None] * self.omega)
        T = np.zeros(p.shape[:-1] + (4, 4))
        T[..., :3, :3] = R
        T[..., :3, 3] = p
        T[..., 3, 3] = 1.0
        return T

    def __call__(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        a = np.atleast_2d(a)
        b = np.atleast_2d(b)
        L = np.linalg.norm(b - a, axis=1)
        m = int(np.clip(np.ceil(L.max() / self.step), 1, 200)) + 1
        u = np.linspace(0.0, 1.0, m)
        P = a[:, None] + u[None, :, None] * (b - a)[:, None]  # [N, m, 3]
        dist_end = np.linalg.norm(P[:, :, None] - self.ends, axis=-1)  # [N, m, 2]
        # hull clearance required of every sphere: margin + rrt.clearance, relaxed near the given endpoints to their
        # own clearance (flat within RRT_RELAX_RADIUS_M, then growing): the endpoints are fixed and must be reachable
        relax = self.end_clr + RRT_RELAX_SLOPE * np.maximum(dist_end - RRT_RELAX_RADIUS_M, 0.0)
        req = np.minimum(self.target, np.min(relax, axis=-1))  # [N, m]
        req = np.minimum(req[:, :-1], req[:, 1:])
        spheres = self.pb.sphere_points(self.poses(P))  # [N, m, S, 3]
        extra = self.pb.spheres.radii + req[..., None]
        ok = ~self.pb.obstacle.segments_intersect(spheres[:, :-1], spheres[:, 1:], extra).any(axis=(1, 2))
        if not ok.any():
            return ok
        d = self.pb.scene_bound.lower_bound(P)
        req_s = np.minimum(self.clearance, np.min(self.ends_d + 0.5 * dist_end, axis=-1))
        return ok & np.all(d >= req_s - 1e-12, axis=1)


def demo_entry_index(problem: TrajProblem) -> int:
    """Demo frame where obstacle-mode guesses join the demo's pre-contact path (cached on the problem).

    Walking back from the pre-contact pose along the demo while every frame keeps the margin from the inflated
    hull (and no sphere chord touches it), the first frame whose clearance reaches ``margin + rrt.clearance``;
    the earliest frame of that valid tail when none does. RRT* then only has to reach this roomier pose, and the guess
    follows the demo from there — which is where the funnel term pulls the trajectory anyway."""
    cached = getattr(problem, "_rrt_entry_index", None)
    if cached is not None:
        return cached
    c = problem.demo.contact_index
    entry = c
    if problem.obstacle is not None:
        pre = problem.demo.pre
        target = problem.config.margin + problem.config.rrt.clearance
        clr = problem.obstacle_clearance(pre).min(axis=-1)
        pts = problem.sphere_points(pre)
        chord_hit = problem.obstacle.segments_intersect(pts[:-1], pts[1:], problem.spheres.radii
                                                        + problem.config.margin).any(axis=-1)
        k = c
        while k >= 0 and clr[k] >= problem.config.margin and (k == c or not chord_hit[k]):
            entry = k  # no frame with the target clearance: the earliest frame of the valid tail
            if clr[k] >= target:
                break
            k -= 1
    problem._rrt_entry_index = entry
    return entry


def _resample_poses(P: np.ndarray, T: int) -> np.ndarray:
    """``T`` poses uniformly spaced in position arc length along a dense pose polyline ``P`` [M, 4, 4]."""
    seg = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    lam = np.concatenate([[0.0], np.cumsum(seg)])
    if lam[-1] <= 0:
        return np.repeat(P[:1], T, axis=0)
    u = np.linspace(0.0, lam[-1], T)
    i = np.clip(np.searchsorted(lam, u, side="right") - 1, 0, len(P) - 2)
    f = np.where(seg[i] > 0, (u - lam[i]) / np.where(seg[i] > 0, seg[i], 1.0), 0.0)
    return interpolate_pose(P[i], P[i + 1], np.clip(f, 0.0, 1.0))


def rrt_guess(problem: TrajProblem, x_init: np.ndarray, rng: np.random.Generator) -> np.ndarray | None:
    """Obstacle-mode initial guess for one start: RRT* of the camera position from ``x_init`` to the demo's entry
    pose (:func:`demo_entry_index`; orientation slaved to the position, see :class:`_Validity`), shortcut, then the
    demo's own frames to the pre-contact pose; resampled uniformly in arc length to T waypoints.

    Returns ``[T, 4, 4]`` (the straight line when it already clears the inflated hull by the margin) or None when
    the planner found no path (or the start is within the margin of the inflated hull).
    """
    cfg = problem.config.rrt
    T = problem.T
    x_goal = problem.x_goal
    line = straight_line_guess(x_init, x_goal, T)
    if problem.obstacle is None or np.all(problem.obstacle_clearance(line) >= problem.config.margin):
        return line  # the straight line already clears the inflated hull: RRT* would return it
    e = demo_entry_index(problem)
    x_entry = problem.demo.T_world_cam[e]
    valid = _Validity(problem, x_init, x_entry)
    if not valid.start_ok:
        return None
    p0, p1 = x_init[:3, 3], x_entry[:3, 3]
    lo, hi = _bounds(problem, p0, p1)
    path = rrt_star(p0, p1, valid, lo, hi, cfg, rng)
    if path is None:
        return None
    path = shortcut_path(path, valid, cfg.shortcut_passes, rng)
    dense, _ = resample_polyline(path, max(2, int(np.ceil(_length(path) / RRT_DENSIFY_M)) + 1))
    P = np.concatenate([valid.poses(dense), problem.demo.T_world_cam[e + 1: problem.demo.contact_index + 1]])
    out = _resample_poses(P, T)
    out[0], out[-1] = x_init, x_goal
    return out


def _length(path: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())


def _bounds(problem: TrajProblem, p0: np.ndarray, p1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if problem.scene.bounds is not None:
        lo, hi = (np.asarray(b, dtype=np.float64) for b in problem.scene.bounds)
        return lo, hi
    pad = problem.config.rrt.bounds_pad
    olo, ohi = problem.obstacle.bounds(problem.config.rrt.clearance)
    lo = np.minimum(np.minimum(p0, p1), olo) - pad
    hi = np.maximum(np.maximum(p0, p1), ohi) + pad
    lo[2] = min(p0[2], p1[2], olo[2])  # obstacles stand on something: no detours below the lowest of these
    return lo, hi


