"""Problem definition (paper §3.2): the demo, the scene, the gripper, and the per-demo constant arrays.

One :class:`TrajProblem` per demonstration; it is solved for many start poses ``x_init`` at once. Poses are
camera poses ``T_world_cam`` (OpenCV camera, world = UMI table-tag frame), metres, radians, seconds.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from umi_aug.errors import GeometryError, TrajError
from umi_aug.geometry import rotation_geodesic_distance, sample_cone_start_poses
from umi_aug.geometry.sdf import SignedDistanceField, check_sdf_output
from umi_aug.traj.config import ObjectiveWeights, TrajConfig
from umi_aug.geometry.gripper import CollisionSpheres, umi_gripper_spheres
from umi_aug.traj.objective import ObjectiveData, funnel_weights
from umi_aug.traj.obstacle import ConvexObstacle
from umi_aug.traj.render_prior import RenderPrior
from umi_aug.traj.scene_grid import SceneGrid
from umi_aug.traj.constants import SCENE_GRID_MAX_POINTS, SCENE_GRID_PAD_M, SCENE_GRID_STEP_M

__all__ = ["Demonstration", "TrajScene", "TrajProblem", "path_progress"]


def path_progress(T_world_cam: np.ndarray, rot_scale: float) -> np.ndarray:
    """Cumulative arc length ``[N]`` of a pose sequence ``[N, 4, 4]`` in the metric ‖Δt‖ + rot_scale·|Δθ| (m)."""
    if T_world_cam.shape[0] < 2:
        return np.zeros(T_world_cam.shape[0])
    dt = np.linalg.norm(np.diff(T_world_cam[:, :3, 3], axis=0), axis=-1)
    dth = rotation_geodesic_distance(T_world_cam[:-1, :3, :3], T_world_cam[1:, :3, :3])
    return np.concatenate([[0.0], np.cumsum(dt + rot_scale * dth)])


@dataclass(frozen=True)
class Demonstration:
    """One recorded demo, split at the contact index.

    Attributes:
        T_world_cam: np.ndarray,  # [H, 4, 4] camera poses O_ee
        timestamps: np.ndarray,  # [H] seconds, strictly increasing
        gripper_width: np.ndarray,  # [H] metres (UMI: 0 = closed)
        contact_index: int,  # first contact frame c (1 <= c <= H-1): x_goal = T_world_cam[c] is the
            pre-contact pose; frames [0, c] are replaced, frames [c, H) are replayed as recorded.
    """

    T_world_cam: np.ndarray
    timestamps: np.ndarray
    gripper_width: np.ndarray
    contact_index: int

    def __post_init__(self) -> None:
        P = np.asarray(self.T_world_cam, dtype=np.float64)
        ts = np.asarray(self.timestamps, dtype=np.float64)
        w = np.asarray(self.gripper_width, dtype=np.float64).reshape(-1)
        H = P.shape[0] if P.ndim == 3 else -1
        if P.ndim != 3 or P.shape[1:] != (4, 4) or H < 2:
            raise TrajError(f"Demonstration: `T_world_cam` must be [H >= 2, 4, 4], got {P.shape}")
        if not np.isfinite(P).all():
            raise TrajError("Demonstration: `T_world_cam` holds NaN/Inf")
        if not np.allclose(np.swapaxes(P[:, :3, :3], -1, -2) @ P[:, :3, :3], np.eye(3), atol=1e-6):
            raise TrajError("Demonstration: `T_world_cam` rotations are not orthonormal (atol 1e-6)")
        if ts.shape != (H,) or not np.isfinite(ts).all() or np.any(np.diff(ts) <= 0):
            raise TrajError(f"Demonstration: `timestamps` must be finite, strictly increasing, shape [{H}]; "
                            f"got shape {ts.shape}")
        if w.shape != (H,) or not np.isfinite(w).all() or np.any(w < 0):
            raise TrajError(f"Demonstration: `gripper_width` must be finite, >= 0, shape [{H}]; got {w.shape}")
        c = self.contact_index
        if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or not 1 <= int(c) <= H - 1:
            raise TrajError(f"Demonstration: `contact_index` = {c!r}; expected an int in [1, {H - 1}] "
                            f"(at least 2 pre-contact frames and 1 post-contact frame)")
        object.__setattr__(self, "T_world_cam", P)
        object.__setattr__(self, "timestamps", ts)
        object.__setattr__(self, "gripper_width", w)
        object.__setattr__(self, "contact_index", int(c))

    @property
    def x_goal(self) -> np.ndarray:
        """Pre-contact pose ``[4, 4]``."""
        return self.T_world_cam[self.contact_index]

    @property
    def pre(self) -> np.ndarray:
        """Pre-contact poses ``[c+1, 4, 4]`` (ending at x_goal)."""
        return self.T_world_cam[: self.contact_index + 1]

    @property
    def frame_dt(self) -> float:
        """Median frame period (s)."""
        return float(np.median(np.diff(self.timestamps)))


@dataclass
class TrajScene:
    """What the trajectories must respect.

    Attributes:
        sdf: scene signed distance (from reconstruction, or analytic while developing).
        render_views: np.ndarray | None,  # [V, 4, 4] views the 3DGS was trained on (demo + scan poses);
            None → the demo's own poses.
        obstacle: ConvexObstacle | None, an added obstacle (obstacle augmentation mode).
        bounds: (lo [3], hi [3]) | None, workspace box for RRT* sampling (None → derived from the problem).
    """

    sdf: SignedDistanceField
    render_views: np.ndarray | None = None
    obstacle: ConvexObstacle | None = None
    bounds: tuple[np.ndarray, np.ndarray] | None = None


class TrajProblem:
    """Per-demo constant data: funnel targets and weights, gripper spheres, required clearances, render prior.

    Args:
        demo: the demonstration (x_goal = its pre-contact pose).
        scene: SDF, training views, optional obstacle.
        config: weights, waypoints, margins, solver/RRT/timing settings.
        spheres: gripper collision spheres (camera frame); default: :func:`umi_gripper_spheres` at the min and
            max pre-contact gripper width (one width when they differ by < 5 mm).

    Raises:
        TrajError: the SDF is not usable, or the obstacle overlaps the pre-contact pose or the replayed
            post-contact motion (then no augmented episode can be collision-free).
    """

    def __init__(self, demo: Demonstration, scene: TrajScene, config: TrajConfig | None = None,
                 spheres: CollisionSpheres | None = None) -> None:
        self.demo = demo
        self.scene = scene
        self.config = cfg = config or TrajConfig()
        if not hasattr(scene.sdf, "distance_and_gradient"):
            raise TrajError(f"TrajProblem: scene.sdf ({type(scene.sdf).__name__}) is not a SignedDistanceField")
        c = demo.contact_index
        if spheres is None:
            wmin, wmax = float(demo.gripper_width[: c + 1].min()), float(demo.gripper_width[: c + 1].max())
            spheres = umi_gripper_spheres((wmin, wmax) if wmax - wmin >= 0.005 else wmax)
        self.spheres = spheres
        T = self.T = cfg.n_waypoints
        self.x_goal = demo.x_goal.copy()

        # funnel: demo pre-contact positions resampled uniformly in (position) arc length
        pre = demo.pre
        lam = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pre[:, :3, 3], axis=0), axis=-1))])
        if lam[-1] > 1e-9:
            u = np.linspace(0.0, lam[-1], T)
            targets = np.stack([np.interp(u, lam, pre[:, i, 3]) for i in range(3)], -1)
        else:
            idx = np.linspace(0.0, len(pre) - 1, T)
            targets = np.stack([np.interp(idx, np.arange(len(pre)), pre[:, i, 3]) for i in range(3)], -1)
        self.funnel_targets = targets
        w = cfg.weights
        self.funnel_weights = funnel_weights(T, w.funnel_w_min, w.funnel_w_max)

        # clearances
        self.obstacle = scene.obstacle
        self.scene_clearance_demo = self.sphere_clearance(pre)  # [c+1, S] scene clearance along the demo
        tail = self._tail_mask_demo(pre)
        demo_tail_min = self.scene_clearance_demo[tail].min(axis=0)  # [S]
        self.required_tail = np.minimum(cfg.margin, demo_tail_min)  # [S]
        s_k = np.linspace(0.0, 1.0, T)
        self.required_scene = self.required_clearance(s_k)  # [T, S]
        if self.obstacle is not None:
            self._check_obstacle_vs_demo()

        views = demo.T_world_cam if scene.render_views is None else np.asarray(scene.render_views, dtype=np.float64)
        self.prior = RenderPrior(views, cfg.render_radius, cfg.render_rot_scale, cfg.render_k,
                                 cfg.render_candidates, cfg.render_max_views, cfg.render_min_separation)
        self.objective_data = self._objective_data(cfg.weights)

    # ------------------------------------------------------------------------------------------------ helpers
    def _tail_mask_demo(self, pre: np.ndarray) -> np.ndarray:
        lam = path_progress(pre, self.config.timing.rot_scale)
        if lam[-1] <= 0:
            return np.ones(len(pre), dtype=bool)
        return lam / lam[-1] >= 1.0 - self.config.contact_tail_fraction - 1e-12

    def required_clearance(self, s: np.ndarray) -> np.ndarray:
        """Required scene clearance ``[N, S]`` (metres) at path progress ``s`` [N] ∈ [0, 1]: the margin, or in the
        contact tail (s ≥ 1 − contact_tail_fraction) the smaller of the margin and the demo's own minimum clearance
        of that sphere over its tail (the demo proved that approach physically)."""
        s = np.asarray(s, dtype=np.float64)
        out = np.full(s.shape + (len(self.spheres),), self.config.margin)
        in_tail = s >= 1.0 - self.config.contact_tail_fraction - 1e-12
        out[in_tail] = self.required_tail
        return out

    @property
    def scene_bound(self) -> SceneGrid:
        """Cached conservative lower bound of the scene SDF (:class:`SceneGrid`) over the demo, the render views and
        the obstacle, padded; built on first use (one SDF query of ≤ ``SCENE_GRID_MAX_POINTS`` points)."""
        grid = self.__dict__.get("_scene_bound")
        if grid is None:
            pts = [self.demo.T_world_cam[:, :3, 3], self.prior.positions]
            if self.obstacle is not None:
                pts.append(self.obstacle.vertices)
            allp = np.concatenate(pts)
            lo, hi = allp.min(0) - SCENE_GRID_PAD_M, allp.max(0) + SCENE_GRID_PAD_M
            step = max(SCENE_GRID_STEP_M, float(np.prod(hi - lo) / SCENE_GRID_MAX_POINTS) ** (1.0 / 3.0))
            grid = SceneGrid(self.scene.sdf, lo, hi, step)
            self.__dict__["_scene_bound"] = grid
        return grid

    def sphere_points(self, T_world_cam: np.ndarray) -> np.ndarray:
        """Sphere centres ``[..., S, 3]`` for poses ``[..., 4, 4]``."""
        return self.spheres.world(T_world_cam)

    def sphere_clearance(self, T_world_cam: np.ndarray) -> np.ndarray:
        """Scene clearance ``sdf(centre) − radius`` of every sphere → ``[..., S]`` (metres)."""
        p = self.sphere_points(T_world_cam)
        d, g = self.scene.sdf.distance_and_gradient(p)
        try:
            check_sdf_output(np.asarray(d), np.asarray(g), p.shape, "TrajProblem: scene.sdf")
        except GeometryError as exc:
            raise TrajError(f"{exc} (queried at {p.reshape(-1, 3).shape[0]} gripper-sphere centres)") from exc
        return d - self.spheres.radii

    def obstacle_clearance(self, T_world_cam: np.ndarray) -> np.ndarray:
        """Clearance to the inflated obstacle hull (exact inside/facet regions, lower bound near edges) → ``[..., S]``;
        +inf without an obstacle."""
        p = self.sphere_points(T_world_cam)
        if self.obstacle is None:
            return np.full(p.shape[:-1], np.inf)
        return self.obstacle.plane_values(p) - self.spheres.radii

    def _check_obstacle_vs_demo(self) -> None:
        c = self.demo.contact_index
        goal_clr = self.obstacle_clearance(self.x_goal)
        if np.any(goal_clr < self.config.margin):
            s = int(np.argmin(goal_clr))
            raise TrajError(
                f"TrajProblem: the pre-contact pose (demo frame {c}) is inside or within the margin "
                f"{self.config.margin} m of the inflated obstacle (sphere '{self.spheres.names[s]}' clearance "
                f"{goal_clr[s]:.4f} m); every augmented trajectory must end there — move or shrink the obstacle")
        post = self.demo.T_world_cam[c:]
        pts = self.sphere_points(post)
        a, b = pts[:-1], pts[1:]
        hit = self.obstacle.segments_intersect(a, b, self.spheres.radii)
        if np.any(hit):
            f = int(np.argwhere(hit)[0, 0]) + c
            raise TrajError(f"TrajProblem: the obstacle overlaps the replayed post-contact motion (demo frames "
                            f"{f}–{f + 1}); the original post-contact segment cannot be kept collision-free")

    def _objective_data(self, w: ObjectiveWeights) -> ObjectiveData:
        cfg = self.config
        return ObjectiveData(
            T=self.T,
            funnel_targets=self.funnel_targets,
            funnel_w=w.funnel * self.funnel_weights,
            sphere_centers=self.spheres.centers_cam,
            sphere_radii=self.spheres.radii,
            required_scene=self.required_scene + cfg.collision_buffer,
            required_obstacle=cfg.margin + cfg.collision_buffer,
            scene_sdf=self.scene.sdf,
            scene_bound=lambda: self.scene_bound,
            obstacle_sdf=None if self.obstacle is None else self.obstacle.sdf,
            collision_w=w.collision / self.T,
            hinge_eta=cfg.hinge_eta,
            prior=self.prior,
            render_w=w.render / (self.T * cfg.render_k),
            acc_w=w.acc, jerk_w=w.jerk, rot_acc_w=w.rot_acc, rot_jerk_w=w.rot_jerk,
        )

    def with_weights(self, weights: ObjectiveWeights) -> "TrajProblem":
        """A shallow copy of this problem with other objective weights (same demo, scene, spheres, prior)."""
        p = copy.copy(self)
        p.config = dataclasses.replace(self.config, weights=weights)
        p.funnel_weights = funnel_weights(self.T, weights.funnel_w_min, weights.funnel_w_max)
        p.objective_data = p._objective_data(weights)
        for cached in ("_rrt_entry_index",):
            p.__dict__.pop(cached, None)
        return p

    # --------------------------------------------------------------------------------------------- sampling
    def default_pivot(self, radius: float) -> np.ndarray:
        """The point ``radius`` metres in front of the demo's first camera (optical axis): the centre of the
        sphere of radius r on which the paper's cone starts lie."""
        T0 = self.demo.T_world_cam[0]
        return T0[:3, 3] + radius * T0[:3, 2]

    def sample_starts(self, n: int, rng: np.random.Generator | int, half_angle: float, radius: float,
                      pivot: np.ndarray | None = None, max_extra_rotation: float = 0.0) -> np.ndarray:
        """Start poses ``x_init`` ``[n, 4, 4]`` in the paper's θ-cone around the demo's first viewpoint: positions
        uniform by area on the cap of half-angle θ of the sphere of radius r around ``pivot`` (default
        :meth:`default_pivot`), cameras re-aimed at the pivot (:func:`umi_aug.geometry.sample_cone_start_poses`).
        """
        try:
            theta, r = float(half_angle), float(radius)
        except (TypeError, ValueError) as exc:
            raise TrajError(f"sample_starts: half_angle / radius must be floats, got {half_angle!r}, {radius!r}") from exc
        if not 0.0 <= theta <= math.pi:
            raise TrajError(f"sample_starts: half_angle = {half_angle!r}; expected radians in [0, π]")
        if not (r > 0 and math.isfinite(r)):
            raise TrajError(f"sample_starts: radius = {radius!r}; expected metres > 0")
        piv = self.default_pivot(r) if pivot is None else np.asarray(pivot, dtype=np.float64)
        try:
            return sample_cone_start_poses(self.demo.T_world_cam[0], piv, theta, n, rng, radius=r,
                                           max_extra_rotation=float(max_extra_rotation))
        except GeometryError as exc:
            raise TrajError(f"sample_starts: {exc}") from exc
