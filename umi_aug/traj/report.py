"""Per-trajectory report and the trajectory plot (PNG, written atomically)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from umi_aug.geometry import tcp_poses_from_camera_poses
from umi_aug.io_utils import atomic_path
from umi_aug.traj.problem import TrajProblem

__all__ = ["TrajReport", "render_prior_distance", "plot_trajectories"]


@dataclass
class TrajReport:
    """What happened to one sampled problem. Distances in metres, angles in radians, times in seconds.

    ``min_clearance`` is over the emitted augmented frames (gripper spheres vs the scene SDF and the inflated
    obstacle); ``required_clearance`` the smallest clearance that was required anywhere (the margin, or the
    demo's own clearance in the contact tail). NaN where a quantity does not exist for the status.
    """

    index: int
    status: str
    reason: str = ""
    iterations: int = 0
    solve_time_s: float = float("nan")
    total_time_s: float = float("nan")
    cost: float = float("nan")
    terms: dict = field(default_factory=dict)
    used_rrt: bool = False
    min_clearance: float = float("nan")
    required_clearance: float = float("nan")
    max_speed: float = float("nan")
    max_accel: float = float("nan")
    max_ang_speed: float = float("nan")
    max_ang_accel: float = float("nan")
    max_jerk: float = float("nan")
    rms_jerk: float = float("nan")
    render_distance_mean: float = float("nan")
    render_distance_max: float = float("nan")
    start_error: float = float("nan")
    goal_error: float = float("nan")
    splice_velocity_jump: float = float("nan")
    splice_ang_velocity_jump: float = float("nan")
    blend_max_offset: float = float("nan")
    duration_s: float = float("nan")
    n_frames: int = 0

    def as_dict(self) -> dict:
        return asdict(self)


def render_prior_distance(problem: TrajProblem, T_world_cam: np.ndarray) -> np.ndarray:
    """Distance ``[N]`` (combined SE(3) metric ``sqrt(‖Δt‖² + ℓ²θ²)``, metres) from each pose to its nearest training
    view (searched among the ``render_candidates`` nearest by position)."""
    prior = problem.prior
    t = T_world_cam[:, :3, 3]
    R = T_world_cam[:, :3, :3]
    k = min(prior.k_candidates, prior.n_views)
    _, idx = prior._tree.query(t, k=k)
    idx = idx.reshape(len(t), k)
    dt = t[:, None] - prior.positions[idx]
    Q = np.swapaxes(R, -1, -2)[:, None] @ prior.rotations[idx]
    w = 0.5 * np.stack([Q[..., 2, 1] - Q[..., 1, 2], Q[..., 0, 2] - Q[..., 2, 0], Q[..., 1, 0] - Q[..., 0, 1]], -1)
    ang = np.arctan2(np.linalg.norm(w, axis=-1), 0.5 * (np.trace(Q, axis1=-2, axis2=-1) - 1.0))
    d = np.sqrt(np.sum(dt * dt, -1) + (prior.rot_scale * ang) ** 2)
    return d.min(axis=1)


def plot_trajectories(path: str | Path, problem: TrajProblem, episodes: list, title: str = "",
                      max_episodes: int = 50) -> Path:
    """3-D plot (perspective and top view) of the original demo (camera positions: pre-contact solid, post-contact
    dashed; TCP pre-contact), the augmented pre-contact segments (camera and TCP), their start poses (optical axes)
    and the obstacle hull; PNG written atomically to ``path``."""
    import matplotlib  # lazy, start-up: matplotlib

    matplotlib.use("Agg", force=False)
    # lazy, start-up: matplotlib, mpl_toolkits
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = Figure(figsize=(12, 6), dpi=110)
    demo = problem.demo
    c = demo.contact_index
    P = demo.T_world_cam[:, :3, 3]
    Ptcp = tcp_poses_from_camera_poses(demo.T_world_cam)[:, :3, 3]
    views = [(0, 30, -60, "3-D"), (1, 90, -90, "top view (x–y)")]
    for col, elev, azim, name in views:
        ax = fig.add_subplot(1, 2, col + 1, projection="3d")
        for ep in episodes[:max_episodes]:
            A = ep.T_world_cam[: ep.splice_index + 1, :3, 3]
            Q = ep.T_world_tcp[: ep.splice_index + 1, :3, 3]
            ax.plot(A[:, 0], A[:, 1], A[:, 2], color="tab:blue", lw=0.7, alpha=0.6)
            ax.plot(Q[:, 0], Q[:, 1], Q[:, 2], color="tab:orange", lw=0.5, alpha=0.5)
            z = ep.T_world_cam[0, :3, 2] * 0.05
            ax.quiver(A[0, 0], A[0, 1], A[0, 2], z[0], z[1], z[2], color="tab:blue", lw=0.6)
        ax.plot(P[: c + 1, 0], P[: c + 1, 1], P[: c + 1, 2], color="tab:green", lw=2.5, label="demo camera, pre-contact")
        ax.plot(P[c:, 0], P[c:, 1], P[c:, 2], "--", color="tab:green", lw=1.5, label="demo camera, post-contact")
        ax.plot(Ptcp[: c + 1, 0], Ptcp[: c + 1, 1], Ptcp[: c + 1, 2], color="tab:olive", lw=2.0, label="demo TCP, pre-contact")
        ax.scatter(*P[c], color="k", s=30, label="x_goal (pre-contact)")
        if problem.obstacle is not None:
            ob = problem.obstacle
            tri = ob.points[ob.simplices]
            ax.add_collection3d(Poly3DCollection(tri, alpha=0.25, facecolor="tab:red", edgecolor="tab:red", lw=0.2))
        if episodes:
            ax.plot([], [], color="tab:blue", label=f"augmented camera ({min(len(episodes), max_episodes)})")
            ax.plot([], [], color="tab:orange", label="augmented TCP")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        pts = [P, Ptcp] + [ep.T_world_cam[: ep.splice_index + 1, :3, 3] for ep in episodes[:max_episodes]]
        if problem.obstacle is not None:
            pts.append(problem.obstacle.vertices)
        allp = np.concatenate(pts)
        lo, hi = allp.min(0), allp.max(0)
        mid, half = 0.5 * (lo + hi), 0.5 * float((hi - lo).max()) + 0.02
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_zlim(max(mid[2] - half, lo[2] - 0.02), mid[2] + half)
        ax.set_box_aspect((1, 1, 1))
        if elev == 90:
            ax.set_zticks([])
            ax.set_zlabel("")
        ax.view_init(elev=elev, azim=azim)
        ax.set_title(name)
        if col == 0:
            ax.legend(loc="upper left", fontsize=7)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
