"""Solver statuses and the stiff / extreme cases of issue #6."""

from __future__ import annotations

import math

import numpy as np
import pytest

from umi_aug.errors import TrajError
from umi_aug.geometry import make_pose, rotation_geodesic_distance
from umi_aug.traj import (
    ConvexObstacle,
    ObjectiveWeights,
    SolverConfig,
    TrajConfig,
    TrajProblem,
    TrajScene,
    TrajStatus,
    generate,
    plan,
    solve,
)
from umi_aug.traj.init_guess import straight_line_guess
from umi_aug.traj.objective import evaluate
from umi_aug.traj.plan import validate_waypoints
from umi_aug.traj.solver import levenberg_marquardt
from umi_aug.traj.synthetic import box_obstacle_points
from tests.traj._helpers import RADIUS, THETA_50, free_problem, obstacle_problem, synthetic


def _converged(res) -> np.ndarray:
    return np.array([s == TrajStatus.CONVERGED for s in res.status])


def test_free_space_converges_to_a_stationary_point(rng):
    pb = free_problem()
    x = pb.sample_starts(6, rng, THETA_50, RADIUS)
    res = solve(pb, x, rng)
    assert _converged(res).all(), res.reason
    X = res.T_world_cam
    G = straight_line_guess(x, pb.x_goal, pb.T)
    ev0 = evaluate(pb.objective_data, G[:, :, :3, 3], G[:, :, :3, :3], derivs=False)
    assert np.all(res.cost < ev0.cost)
    # a long, tightly converged continuation finds (almost) nothing more: the result is a local minimum
    tight = SolverConfig(max_iterations=300, ftol=1e-12, xtol=1e-14)
    cont = levenberg_marquardt(pb.objective_data, X[:, :, :3, 3], X[:, :, :3, :3], tight)
    assert np.all(cont.cost >= res.cost * (1 - 1e-4))
    np.testing.assert_array_equal(X[:, 0], x)  # endpoints are bit-exact
    np.testing.assert_array_equal(X[:, -1], np.broadcast_to(pb.x_goal, x.shape))
    assert validate_waypoints(pb, X).ok.all()


def test_batch_equals_individual_solves(rng):
    pb = obstacle_problem()
    x = pb.sample_starts(4, rng, THETA_50, RADIUS)
    init = solve(pb, x, 7, max_iterations=0).T_world_cam  # RRT* guesses
    batch = levenberg_marquardt(pb.objective_data, init[:, :, :3, 3], init[:, :, :3, :3], pb.config.solver)
    for b in range(4):
        one = levenberg_marquardt(pb.objective_data, init[b:b + 1, :, :3, 3], init[b:b + 1, :, :3, :3],
                                  pb.config.solver)
        assert one.iterations[0] == batch.iterations[b]
        np.testing.assert_allclose(one.t[0], batch.t[b], rtol=0, atol=1e-12)
        np.testing.assert_allclose(one.R[0], batch.R[b], rtol=0, atol=1e-12)


def test_stiff_collision_weight_1e6_is_stable(rng):
    pb = obstacle_problem(TrajConfig(weights=ObjectiveWeights(collision=1e6)))
    x = pb.sample_starts(8, rng, THETA_50, RADIUS)
    res = solve(pb, x, rng)
    ok = _converged(res)
    assert np.isfinite(res.T_world_cam).all() and np.isfinite(res.cost).all()
    assert ok.mean() >= 0.75, [(s.value, r) for s, r in zip(res.status, res.reason)]
    assert res.check.ok[ok].all()
    assert res.terms["obstacle"][ok].max() < 1e-3 * res.cost[ok].max() + 1e-9 or res.check.ok[ok].all()


def test_start_equal_goal_gives_constant_trajectory():
    pb = obstacle_problem()
    res = solve(pb, pb.x_goal[None], 0)
    assert res.status == [TrajStatus.CONVERGED] and res.iterations[0] == 0
    np.testing.assert_array_equal(res.T_world_cam[0], np.broadcast_to(pb.x_goal, (pb.T, 4, 4)))
    out = plan(pb, pb.x_goal)
    assert np.isfinite(out).all()


def test_theta_zero_reproduces_the_demo_start(rng):
    pb = free_problem()
    x = pb.sample_starts(3, rng, 0.0, RADIUS)
    np.testing.assert_allclose(x, np.broadcast_to(pb.demo.T_world_cam[0], x.shape), atol=1e-12)
    res = solve(pb, x, rng)
    assert _converged(res).all()
    # with the start on the demo, the optimum stays close to the demo's own path
    d = np.linalg.norm(res.T_world_cam[0, :, :3, 3] - pb.funnel_targets, axis=-1)
    assert d.max() < 0.03


def test_theta_180_samples_are_reported_or_solved():
    pb = free_problem()
    x = pb.sample_starts(24, 11, math.pi, RADIUS)
    ang = rotation_geodesic_distance(x[:, :3, :3], pb.x_goal[:3, :3])
    assert ang.max() > math.radians(150)  # the full sphere: starts facing away from the goal orientation
    res = solve(pb, x, 11)
    ok = _converged(res)
    assert ok.mean() >= 0.9, [(s.value, r) for s, r in zip(res.status, res.reason)]
    assert res.check.ok[ok].all() and np.isfinite(res.T_world_cam).all()
    # a larger sphere reaches into the table: those starts are reported, not optimised
    x2 = pb.sample_starts(24, 12, math.pi, 0.35)
    res2 = solve(pb, x2, 12)
    assert TrajStatus.INFEASIBLE_START in res2.status
    assert all(s in (TrajStatus.CONVERGED, TrajStatus.INFEASIBLE_START) for s in res2.status)
    g = generate(pb, 3, seed=5, half_angle=math.pi, radius=0.35)
    assert len(g.episodes) == 3 and g.status_counts.get("infeasible_start", 0) >= 0


def test_start_inside_inflated_obstacle_is_a_clear_error():
    st = synthetic()
    pb = obstacle_problem()
    inside = make_pose(np.eye(3), pb.obstacle.vertices.mean(axis=0))
    with pytest.raises(TrajError, match="inside the inflated obstacle"):
        plan(pb, inside)
    res = solve(pb, inside[None], 0)
    assert res.status == [TrajStatus.INFEASIBLE_START] and "inside the inflated obstacle" in res.reason[0]
    assert st is not None


def test_goal_inside_obstacle_is_rejected_at_problem_construction():
    st = synthetic()
    goal_tcp = st.demo.x_goal[:3, 3] + st.demo.x_goal[:3, 2] * 0.2
    pts = box_obstacle_points(goal_tcp, [0.03, 0.03, 0.03])
    with pytest.raises(TrajError, match="pre-contact pose"):
        TrajProblem(st.demo, TrajScene(st.sdf, st.render_views, ConvexObstacle(pts, 0.01)))


def _wall_problem() -> TrajProblem:
    """A wall (thin box far wider and taller than the planning box) between the start region and the mug."""
    st = synthetic()
    wall = box_obstacle_points([0.0, 0.155, 1.0], [3.0, 0.01, 1.0], n=50)
    cfg = TrajConfig(solver=SolverConfig(max_iterations=20))
    return TrajProblem(st.demo, TrajScene(st.sdf, st.render_views, ConvexObstacle(wall, 0.005)), cfg)


def test_obstacle_blocking_every_path_fails_clearly_without_hanging():
    pb = _wall_problem()
    x = pb.sample_starts(3, 0, np.radians(10), RADIUS)
    res = solve(pb, x, 0)
    assert all(s in (TrajStatus.PLANNER_FAILED, TrajStatus.INFEASIBLE_START) for s in res.status)
    assert TrajStatus.PLANNER_FAILED in res.status
    with pytest.raises(TrajError, match="planner_failed"):  # after its 2 rounds (a hang meets pytest's timeout)
        generate(pb, 2, seed=0, half_angle=np.radians(10), radius=RADIUS, max_rounds=2)


def test_nan_sdf_never_passes():
    st = synthetic()

    class NanAbove:  # a broken SDF: NaN in part of the workspace the starts reach
        def distance_and_gradient(self, p):
            d, g = st.sdf.distance_and_gradient(p)
            return np.where(p[..., 2] > 0.36, np.nan, d), g

    with pytest.raises(TrajError, match="non-finite"):  # the demo itself reaches there
        TrajProblem(st.demo, TrajScene(NanAbove(), st.render_views))
    pb = free_problem()
    pb.scene.sdf = NanAbove()  # swapped after construction: caught while solving / validating
    pb.objective_data.scene_sdf = pb.scene.sdf
    with pytest.raises(TrajError, match="non-finite"):
        generate(pb, 2, seed=0, half_angle=THETA_50, radius=RADIUS, max_rounds=1)


def test_iteration_limit_status():
    pb = obstacle_problem(TrajConfig(solver=SolverConfig(max_iterations=1)))
    x = pb.sample_starts(6, 2, THETA_50, RADIUS)
    res = solve(pb, x, 2)
    assert TrajStatus.ITERATION_LIMIT in res.status
    with pytest.raises(TrajError, match="iteration_limit|collision"):
        generate(pb, 4, seed=1, half_angle=THETA_50, radius=RADIUS, max_rounds=1)
