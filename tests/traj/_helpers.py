"""Shared builders for the trajectory tests (everything generated here; nothing downloaded)."""

from __future__ import annotations

import numpy as np

from umi_aug.geometry import make_pose, so3_exp
from umi_aug.traj import ConvexObstacle, TrajConfig, TrajProblem, TrajScene
from umi_aug.traj.synthetic import SyntheticTabletop

THETA_50 = np.radians(50.0)
RADIUS = 0.15

_SYNTH: dict = {}


def synthetic() -> SyntheticTabletop:
    if "s" not in _SYNTH:
        _SYNTH["s"] = SyntheticTabletop.build(seed=0)
    return _SYNTH["s"]


def free_problem(config: TrajConfig | None = None) -> TrajProblem:
    st = synthetic()
    return TrajProblem(st.demo, TrajScene(st.sdf, st.render_views), config)


def obstacle_problem(config: TrajConfig | None = None, inflation: float = 0.01) -> TrajProblem:
    st = synthetic()
    return TrajProblem(st.demo, TrajScene(st.sdf, st.render_views, ConvexObstacle(st.obstacle_points, inflation)),
                       config)


def perturbed(X: np.ndarray, rng: np.random.Generator, pos: float, rot: float) -> np.ndarray:
    """Random interior perturbation of waypoints [B, T, 4, 4] (endpoints untouched)."""
    out = X.copy()
    B, T = X.shape[:2]
    for b in range(B):
        for k in range(1, T - 1):
            out[b, k] = make_pose(so3_exp(rng.normal(0, rot, 3)) @ X[b, k, :3, :3], X[b, k, :3, 3] + rng.normal(0, pos, 3))
    return out


def sphere_points_bruteforce(problem: TrajProblem, T_world_cam: np.ndarray) -> np.ndarray:
    """Sphere centres [N, S, 3] by an explicit loop (independent of CollisionSpheres.world)."""
    c = problem.spheres.centers_cam
    out = np.empty((len(T_world_cam), len(c), 3))
    for i, T in enumerate(T_world_cam):
        for s in range(len(c)):
            out[i, s] = T[:3, :3] @ c[s] + T[:3, 3]
    return out


def assert_episode_collision_free(problem: TrajProblem, ep, chord_samples: int = 8) -> None:
    """Independent check of an emitted episode's augmented frames: every gripper sphere keeps the margin from
    the scene SDF at every frame (the synthetic demo needs no contact-tail relaxation), and densely sampled sphere
    chords between frames stay outside the inflated hull (+ sphere radius)."""
    n = ep.splice_index
    pre = ep.T_world_cam[: n + 1]
    pts = sphere_points_bruteforce(problem, pre)
    r = problem.spheres.radii
    d = problem.scene.sdf.distance_and_gradient(pts)[0]
    assert np.isfinite(d).all()
    assert (d - r).min() >= problem.config.margin - 1e-12, (d - r).min()
    ob = problem.obstacle
    if ob is not None and n > 0:
        u = np.linspace(0.0, 1.0, chord_samples + 1)
        seg = pts[:-1, None] + u[None, :, None, None] * (pts[1:] - pts[:-1])[:, None]
        planes = np.max(seg @ ob.normals.T + ob.offsets, axis=-1) - ob.inflation  # [N-1, u, S]
        assert (planes - r).min() > 0.0, (planes - r).min()
