"""Trajectory stage (paper §3.2): from one demo, many smooth, collision-free camera/TCP trajectories that start in
a θ-cone around the demo's first viewpoint, funnel into its pre-contact pose and replay its post-contact motion.

Pipeline: :class:`TrajProblem` (demo + scene SDF + render views + optional obstacle hull) → start sampling →
initial guesses (straight line + slerp, or RRT* around the inflated obstacle) → batched Levenberg–Marquardt on the
§3.2 objective (:mod:`.objective`; slow reference :mod:`._ref`) → exact validation → retiming with the
demo's speed profile and velocity-continuous splicing (:mod:`.splice`) → UMI actions and camera poses.
:func:`generate` drives it and returns exactly n episodes or raises :class:`umi_aug.errors.TrajError`.

Frames: camera poses ``T_world_cam`` (OpenCV camera, world = UMI table-tag frame); TCP via UMI's fixed offset.
Units: metres, radians, seconds.
"""

from umi_aug.traj.config import ObjectiveWeights, RRTConfig, SolverConfig, TimingConfig, TrajConfig
from umi_aug.traj.generate import GenerateResult, generate
from umi_aug.geometry.gripper import CollisionSpheres, umi_gripper_spheres
from umi_aug.traj.obstacle import ConvexObstacle
from umi_aug.traj.plan import SolveResult, plan, solve
from umi_aug.traj.problem import Demonstration, TrajProblem, TrajScene
from umi_aug.traj.report import TrajReport, plot_trajectories
from umi_aug.traj.solver import TrajStatus
from umi_aug.traj.splice import AugmentedEpisode, time_and_splice

__all__ = [
    "TrajConfig", "ObjectiveWeights", "SolverConfig", "RRTConfig", "TimingConfig",
    "Demonstration", "TrajScene", "TrajProblem", "ConvexObstacle", "CollisionSpheres", "umi_gripper_spheres",
    "solve", "plan", "SolveResult", "TrajStatus",
    "time_and_splice", "AugmentedEpisode",
    "generate", "GenerateResult", "TrajReport", "plot_trajectories",
]
