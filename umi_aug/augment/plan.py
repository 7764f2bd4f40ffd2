"""One augmented episode from ``(demo, aug_id, mode)`` alone: cone start (+ obstacle placement) → optimised,
validated trajectory → retimed and spliced :class:`umi_aug.traj.AugmentedEpisode` (paper §3.2).

Determinism: every random draw comes from :func:`episode_seed` ``(cfg.seed, demo_index, aug_id, mode)`` and the
attempt number, never from batch order or from which process runs it. A failed attempt (infeasible start, solver
failure, collision, timing, no obstacle placement) is resampled with the next attempt number, up to
``cfg.max_attempts``; the failures are recorded.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from umi_aug.errors import AugmentError, ReconError, TrajError
from umi_aug.geometry import pose_to_pos_rotvec, tcp_poses_from_camera_poses
from umi_aug.recon.obstacles import sample_obstacle_placement
from umi_aug.traj import ConvexObstacle
from umi_aug.traj.generate import finish_batch
from umi_aug.traj.plan import solve
from umi_aug.traj.splice import AugmentedEpisode

__all__ = ["MODE_CODES", "RERENDER_MODE", "episode_seed", "ObstacleRecord", "PlannedEpisode", "PlanOutcome",
           "plan_episode", "rerender_episode", "try_plan_episode"]

from umi_aug.augment.obstacle_stage import scaled_obstacle_asset
from umi_aug.augment.session_assets import SessionAssets

log = logging.getLogger(__name__)

#: Integer code of each episode kind (stored per episode in the exported zarr, ``meta/aug_mode``): ``rerender`` is a
#: demo again, its approach rendered by the scene model at its own poses (:func:`rerender_episode`).
MODE_CODES: dict[str, int] = {"original": 0, "freespace": 1, "obstacle": 2, "rerender": 3}
#: The mode of a demo's re-rendered copy (:func:`rerender_episode`).
RERENDER_MODE = "rerender"
#: Height above the support plane (m) below which the placement ignores the reconstructed SDF (at least 2 voxels).
SUPPORT_BAND_M: float = 0.02


def episode_seed(seed: int, demo_index: int, aug_id: int, mode: str) -> int:
    """The derived 63-bit seed of one augmented episode (``numpy.random.SeedSequence`` of the four values)."""
    if mode not in MODE_CODES:
        raise AugmentError(f"episode_seed: mode {mode!r} not in {sorted(MODE_CODES)}")
    ss = np.random.SeedSequence([int(seed) & 0xFFFFFFFF, int(demo_index), int(aug_id), MODE_CODES[mode]])
    return int(ss.generate_state(1, np.uint64)[0] >> np.uint64(1))


@dataclass
class ObstacleRecord:
    """The obstacle of an obstacle-mode episode.

    Attributes:
        asset: asset name (config entry); scale: size factor applied in the object frame;
        T_world_obj: np.ndarray,  # [4, 4] pose of the object frame (bottom centre, z up), world metres
        inflation: metres; hull_world: np.ndarray,  # [V, 3] convex-hull vertices (not inflated), world metres
    """

    asset: str
    scale: float
    T_world_obj: np.ndarray
    inflation: float
    hull_world: np.ndarray

    def convex_obstacle(self):
        """The inflated hull as :class:`umi_aug.traj.ConvexObstacle`."""
        return ConvexObstacle(self.hull_world, self.inflation)


@dataclass
class PlannedEpisode:
    """A planned (not yet rendered) augmented episode.

    Attributes:
        demo_index / demo_name / aug_id / mode / seed: identity (seed = :func:`episode_seed`).
        attempts: attempts used (1 = first try); episode: :class:`umi_aug.traj.AugmentedEpisode`
        (``T_world_cam`` [N, 4, 4], ``actions`` [N, 7], ``splice_index``, ``source_contact_index``);
        report: the trajectory report (JSON dict); obstacle: ObstacleRecord | None; failures: reasons of the
        failed attempts; plan_s: wall time.
    """

    demo_index: int
    demo_name: str
    aug_id: int
    mode: str
    seed: int
    attempts: int
    episode: object
    report: dict
    obstacle: ObstacleRecord | None = None
    failures: list[str] = field(default_factory=list)
    plan_s: float = 0.0

    @property
    def n_frames(self) -> int:
        return int(len(self.episode.timestamps))

    @property
    def splice_index(self) -> int:
        return int(self.episode.splice_index)


@dataclass
class PlanOutcome:
    """``planned`` (None after the retry budget) plus every failed attempt's reason."""

    planned: PlannedEpisode | None
    attempts: int
    failures: list[str]
    plan_s: float


class _AboveSupport:
    """The scene SDF for the obstacle-vs-scene test of the placement, ignoring points within ``band`` metres above
    the support plane: the obstacle stands on the table, and a reconstructed SDF is unreliable to a voxel or two
    next to a surface, so its base would always look like it intersects the table."""

    def __init__(self, sdf, z_min: float) -> None:
        self.sdf, self.z_min = sdf, float(z_min)

    def distance_and_gradient(self, points_world: np.ndarray):
        p = np.asarray(points_world, dtype=np.float64)
        d, g = self.sdf.distance_and_gradient(p)
        low = p[..., 2] < self.z_min
        d = np.where(low, 1.0, d)
        g = np.where(low[..., None], np.array([0.0, 0.0, 1.0]), g)
        return d, g


def _frames_clear_of_hull(problem, obstacle, T_world_cam: np.ndarray) -> bool:
    """No gripper sphere (nor the camera centre) of any frame is inside the inflated hull."""
    pts = problem.sphere_points(T_world_cam)  # [N, S, 3]
    inside = obstacle.contains(pts, problem.spheres.radii).any()
    inside |= bool(obstacle.contains(T_world_cam[:, :3, 3]).any())
    return not inside


def draw_obstacle_asset(oc, rng: np.random.Generator) -> str:
    """The obstacle asset of one planning attempt: the first draw of the attempt's generator."""
    return oc.assets[int(rng.integers(len(oc.assets)))]


def first_attempt_obstacle_asset(cfg, demo_index: int, aug_id: int) -> str:
    """The obstacle asset that the first planning attempt of obstacle job ``(demo_index, aug_id)`` draws (a later
    attempt, after a failed one, draws again)."""
    rng = np.random.default_rng([episode_seed(cfg.seed, int(demo_index), int(aug_id), "obstacle"), 0])
    return draw_obstacle_asset(cfg.obstacle, rng)


def first_attempt_obstacle_assets(cfg, demo_indices) -> list[str]:
    """The distinct obstacle assets of :func:`first_attempt_obstacle_asset` over the run's obstacle-mode jobs, in
    the order the export first needs them (cheap: one random draw per job, nothing planned); [] without obstacle
    mode."""
    if "obstacle" not in cfg.modes:
        return []
    jobs = ((d, a) for d in demo_indices for a in range(cfg.n_per_demo))
    return list(dict.fromkeys(first_attempt_obstacle_asset(cfg, d, a) for d, a in jobs))


def try_plan_episode(assets: SessionAssets, demo_index: int, aug_id: int, mode: str) -> PlanOutcome:
    """:func:`plan_episode` with the failure record (see there)."""
    cfg = assets.cfg
    if mode not in ("freespace", "obstacle"):
        raise AugmentError(f"plan_episode: mode {mode!r}; expected 'freespace' or 'obstacle'")
    d = assets.demo(demo_index)
    seed = episode_seed(cfg.seed, demo_index, aug_id, mode)
    t0 = time.perf_counter()
    failures: list[str] = []
    for attempt in range(cfg.max_attempts):
        rng = np.random.default_rng([seed, attempt])
        record = None
        try:
            if mode == "obstacle":
                oc = cfg.obstacle
                name = draw_obstacle_asset(oc, rng)
                scale = float(rng.uniform(*oc.scale_range))
                asset = scaled_obstacle_asset(name, scale)
                band = max(SUPPORT_BAND_M, 2.0 * float(getattr(assets.sdf, "voxel", 0.0)))
                pl = sample_obstacle_placement(asset, d.T_world_cam, d.gripper_width, int(d.contact_index), rng,
                                               scene_sdf=_AboveSupport(assets.sdf, band), inflation=oc.inflation_m,
                                               clearance=oc.clearance_m, max_tries=oc.placement_tries)
                record = ObstacleRecord(name, scale, pl.T_world_obj, float(oc.inflation_m), pl.hull_world)
                obstacle = ConvexObstacle(pl.hull_world, oc.inflation_m)
                problem = assets.make_problem(demo_index, obstacle)
            else:
                obstacle = None
                problem = assets.traj_problem(demo_index)
            x_init = problem.sample_starts(1, rng, math.radians(cfg.cone_half_angle_deg), cfg.cone_radius_m,
                                           None, math.radians(cfg.max_extra_rotation_deg))
            res = solve(problem, x_init, rng)
            eps, reps = finish_batch(problem, x_init, res)
        except (ReconError, TrajError) as exc:
            failures.append(f"attempt {attempt}: {type(exc).__name__}: {exc}")
            continue
        ep, rep = eps[0], reps[0]
        if ep is None:
            failures.append(f"attempt {attempt}: {rep.status}: {rep.reason}")
            continue
        if obstacle is not None and not _frames_clear_of_hull(problem, obstacle, ep.T_world_cam):
            failures.append(f"attempt {attempt}: a frame's gripper is inside the inflated obstacle hull")
            continue
        why = assets.embodiment_failure(demo_index, ep)
        if why is not None:
            failures.append(f"attempt {attempt}: not executable by the robot: {why}")
            continue
        dt = time.perf_counter() - t0
        planned = PlannedEpisode(int(demo_index), d.name, int(aug_id), mode, seed, attempt + 1, ep,
                                 _report_dict(rep), record, failures, dt)
        return PlanOutcome(planned, attempt + 1, failures, dt)
    log.warning("plan_episode: demo %s aug %d (%s) failed after %d attempts: %s", d.name, aug_id, mode,
                cfg.max_attempts, failures[-1] if failures else "")
    return PlanOutcome(None, cfg.max_attempts, failures, time.perf_counter() - t0)


def _report_dict(rep) -> dict:
    out = {}
    for k, v in vars(rep).items():
        if isinstance(v, (np.floating, np.integer)):
            v = v.item()
        if isinstance(v, float) and not math.isfinite(v):
            v = None
        if isinstance(v, dict):
            v = {kk: float(vv) for kk, vv in v.items()}
        out[k] = v
    return out


def rerender_episode(assets: SessionAssets, demo_index: int) -> PlannedEpisode:
    """Demo ``demo_index`` itself as a :class:`PlannedEpisode` of mode ``"rerender"`` (``aug_id`` 0): its own camera
    poses, gripper widths and frame count, spliced at its contact frame, so that rendering frames ``0 .. c-1``
    shows the demo's approach as the scene model renders it (the look of the augmented episodes' new frames) and
    the frames from ``c`` on are its own. Nothing is planned or drawn: the same for every seed.

    Raises:
        AugmentError: the demo has no contact frame (:meth:`SessionAssets.demo`).
    """
    d = assets.demo(demo_index)
    c = int(d.contact_index)
    T_cam = np.asarray(d.T_world_cam, np.float64)
    width = np.asarray(d.gripper_width, np.float64).reshape(-1)
    # UMI's camera→TCP offset; the export writes the demo's own stored rows, not these
    T_tcp = tcp_poses_from_camera_poses(T_cam)
    actions = np.concatenate([pose_to_pos_rotvec(T_tcp), width[:, None]], axis=1)
    ts = np.asarray(d.timestamps, np.float64)
    progress = np.linspace(0.0, 1.0, c + 1) if c > 0 else np.ones(1)
    ep = AugmentedEpisode(ts - ts[0], T_cam, T_tcp, width, actions, c, progress, c)
    seed = episode_seed(assets.cfg.seed, demo_index, 0, RERENDER_MODE)
    return PlannedEpisode(int(demo_index), d.name, 0, RERENDER_MODE, seed, 1, ep, {"status": RERENDER_MODE})


def plan_episode(assets: SessionAssets, demo_index: int, aug_id: int, mode: str) -> PlannedEpisode | None:
    """Plan augmented episode ``aug_id`` of demo ``demo_index`` in ``mode`` (``"freespace"`` / ``"obstacle"``).

    Deterministic from ``(assets.cfg.seed, demo_index, aug_id, mode)`` alone. Per attempt: (obstacle mode) an asset,
    scale and placement that blocks the demo's straight approach (:func:`umi_aug.recon.sample_obstacle_placement`);
    one start pose in the θ-cone; the batched solver on that one start; retiming + splicing + validation
    (:func:`umi_aug.traj.generate.finish_batch`); in obstacle mode a final check that no frame — including the
    replayed post-contact ones — puts a gripper sphere or the camera inside the inflated hull.

    Returns:
        the :class:`PlannedEpisode`, or None when all ``cfg.max_attempts`` attempts failed.
    """
    return try_plan_episode(assets, demo_index, aug_id, mode).planned
