"""Building blocks: obstacle hull tests, render-prior neighbours, RRT*, gripper spheres, config and demo checks."""

from __future__ import annotations

import numpy as np
import pytest

from umi_aug.errors import GeometryError, TrajError
from umi_aug.geometry import so3_log
from umi_aug.traj import (
    CollisionSpheres,
    ConvexObstacle,
    Demonstration,
    ObjectiveWeights,
    RRTConfig,
    SolverConfig,
    TimingConfig,
    TrajConfig,
    umi_gripper_spheres,
)
from umi_aug.traj.render_prior import RenderPrior
from umi_aug.traj.rrt import resample_polyline, rrt_star, shortcut_path
from umi_aug.traj.synthetic import box_obstacle_points
from tests.geometry._helpers import random_rotations
from tests.traj._helpers import synthetic


# ------------------------------------------------------------------------------------------------ obstacle
def _box_obstacle(rng, inflation):
    c = rng.normal(0, 0.1, 3)
    h = rng.uniform(0.03, 0.08, 3)
    return ConvexObstacle(box_obstacle_points(c, h, yaw=rng.uniform(0, 3), n=200, seed=1), inflation), c, h


def test_obstacle_contains_and_segments_vs_dense_sampling(rng):
    ob, c, h = _box_obstacle(rng, 0.01)
    a = c + rng.normal(0, 0.15, (300, 3))
    b = c + rng.normal(0, 0.15, (300, 3))
    extra = rng.uniform(0, 0.02, 300)
    hit = ob.segments_intersect(a, b, extra)
    u = np.linspace(0, 1, 2001)
    pts = a[:, None] + u[None, :, None] * (b - a)[:, None]
    sampled = ob.contains(pts, extra[:, None]).any(axis=1)
    assert np.all(hit[sampled])  # every sampled intersection is found (exact test is a superset)
    # misses of the sampling are only grazing hits (within the sampling resolution)
    pv = np.max(pts @ ob.normals.T + ob.offsets, axis=-1) - ob.inflation - extra[:, None]
    step = np.linalg.norm(b - a, axis=1) / 2000
    assert np.all(pv[hit & ~sampled].min(axis=1) <= step[hit & ~sampled] + 1e-12)
    assert 0 < hit.mean() < 1
    # point segments reduce to containment; reversed segments give the same answer
    np.testing.assert_array_equal(ob.segments_intersect(a, a, extra), ob.contains(a, extra))
    np.testing.assert_array_equal(ob.segments_intersect(b, a, extra), hit)


def test_obstacle_inflation_and_sdf(rng):
    ob0, c, _ = _box_obstacle(rng, 0.0)
    ob1 = ConvexObstacle(ob0.points, 0.02)
    q = c + rng.normal(0, 0.12, (500, 3))
    np.testing.assert_allclose(ob1.plane_values(q), ob0.plane_values(q) - 0.02)
    d, g = ob1.sdf.distance_and_gradient(q)
    np.testing.assert_allclose(d, ob1.plane_values(q))
    assert np.all(ob1.contains(q) == (d <= 0))
    lo, hi = ob1.bounds()
    assert np.all(ob1.vertices >= lo) and np.all(ob1.vertices <= hi)


@pytest.mark.parametrize("bad", [np.zeros((3, 3)), np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]),
                                 np.full((5, 3), np.nan)])
def test_obstacle_bad_points(bad):
    with pytest.raises(TrajError):
        ConvexObstacle(bad, 0.01)


def test_obstacle_bad_inflation():
    with pytest.raises(TrajError):
        ConvexObstacle(box_obstacle_points([0, 0, 0], [0.1, 0.1, 0.1]), -0.01)


# -------------------------------------------------------------------------------------------- render prior
def test_render_prior_matches_brute_force(rng):
    V = 12
    views = np.zeros((V, 4, 4))
    views[:, :3, :3] = random_rotations(rng, V)
    views[:, :3, 3] = rng.normal(0, 0.1, (V, 3))
    views[:, 3, 3] = 1
    rho, ell, K = 0.25, 0.1, 4
    prior = RenderPrior(views, rho, ell, K, k_candidates=16, max_views=100)
    N = 50
    t = rng.normal(0, 0.12, (N, 3))
    R = random_rotations(rng, N)
    nb = prior.query(t, R)
    cost = rho**2 * nb.n_truncated.astype(float)
    np.add.at(cost, nb.point, np.sum(nb.dt**2, -1) + ell**2 * np.sum(nb.e**2, -1))
    for i in range(N):
        d2 = sorted(min(float(np.sum((t[i] - views[j, :3, 3]) ** 2) + ell**2 * np.sum(
            so3_log(R[i].T @ views[j, :3, :3]) ** 2)), rho**2) for j in range(V))
        assert cost[i] == pytest.approx(sum(d2[:K]), rel=1e-10, abs=1e-14)
    assert nb.point.size > 0 and np.any(nb.n_truncated > 0)


def test_render_prior_subsamples_views():
    views = np.repeat(np.eye(4)[None], 5000, axis=0)
    views[:, 0, 3] = np.linspace(0, 1, 5000)
    prior = RenderPrior(views, 0.1, 0.1, 4, 16, max_views=100)
    assert prior.n_views == 100
    assert prior.positions[0, 0] == 0.0 and prior.positions[-1, 0] == 1.0


# ---------------------------------------------------------------------------------------------------- RRT*
def _box_validity(lo_box, hi_box):
    def free(a, b):
        a, b = np.atleast_2d(a), np.atleast_2d(b)
        u = np.linspace(0, 1, 200)
        p = a[:, None] + u[None, :, None] * (b - a)[:, None]
        inside = np.all((p > lo_box) & (p < hi_box), axis=-1)
        return ~inside.any(axis=1)
    return free


def test_rrt_star_finds_a_valid_path_around_a_box(rng):
    free = _box_validity(np.array([-0.1, -0.5, -0.5]), np.array([0.1, 0.5, 0.5]))
    start, goal = np.array([-0.5, 0.0, 0.0]), np.array([0.5, 0.0, 0.0])
    assert not free(start, goal)[0]
    cfg = RRTConfig(max_iterations=2000, step=0.1, rewire_radius=0.25)
    path = rrt_star(start, goal, free, np.array([-1.0, -1.0, -1.0]), np.array([1.0, 1.0, 1.0]), cfg, rng)
    assert path is not None
    np.testing.assert_array_equal(path[0], start)
    np.testing.assert_array_equal(path[-1], goal)
    assert free(path[:-1], path[1:]).all()
    short = shortcut_path(path, free, 30, rng)
    assert free(short[:-1], short[1:]).all()
    assert np.linalg.norm(np.diff(short, axis=0), axis=1).sum() <= np.linalg.norm(np.diff(path, axis=0), axis=1).sum() + 1e-12
    pts, s = resample_polyline(short, 64)
    np.testing.assert_array_equal(pts[0], start)
    np.testing.assert_array_equal(pts[-1], goal)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    assert seg.max() - seg.min() < 1e-9 + 0.5 * seg.mean()  # uniform in arc length (corners cut)


def test_rrt_star_fails_cleanly_when_blocked(rng):
    free = _box_validity(np.array([-0.1, -2.0, -2.0]), np.array([0.1, 2.0, 2.0]))  # wall through the bounds
    cfg = RRTConfig(max_iterations=300)
    path = rrt_star(np.array([-0.5, 0, 0]), np.array([0.5, 0, 0]), free, -np.ones(3), np.ones(3), cfg, rng)
    assert path is None


def test_rrt_straight_line_when_free(rng):
    free = _box_validity(np.array([5.0, 5, 5]), np.array([6.0, 6, 6]))
    path = rrt_star(np.zeros(3), np.ones(3), free, -np.ones(3), 2 * np.ones(3), RRTConfig(), rng)
    np.testing.assert_array_equal(path, [np.zeros(3), np.ones(3)])


# ------------------------------------------------------------------------------------------------- gripper
def test_gripper_spheres_cover_fingers_at_width():
    s = umi_gripper_spheres(0.08)
    tips = [i for i, n in enumerate(s.names) if n.startswith("finger_right")]
    # the inner face of each finger sphere touches x = width/2 (fingers sit outside the opening)
    np.testing.assert_allclose(s.centers_cam[tips, 0] - s.radii[tips], 0.04)
    assert s.centers_cam[:, 2].max() + s.radii.max() >= 0.226  # reaches UMI's fingertips
    two = umi_gripper_spheres((0.03, 0.08))
    assert len(two) == len(s) + 12
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]
    np.testing.assert_allclose(s.world(T), s.centers_cam + [1, 2, 3])
    with pytest.raises(GeometryError):
        umi_gripper_spheres(-0.01)
    with pytest.raises(GeometryError):
        CollisionSpheres(np.zeros((2, 3)), np.array([0.1, -0.1]), ("a", "b"))


# ------------------------------------------------------------------------------------------ config / demo
@pytest.mark.parametrize("make", [
    lambda: ObjectiveWeights(collision=-1.0),
    lambda: ObjectiveWeights(funnel_w_max=1.5),
    lambda: ObjectiveWeights(acc=float("nan")),
    lambda: SolverConfig(max_iterations=0),
    lambda: RRTConfig(goal_bias=2.0),
    lambda: TimingConfig(max_speed=0.0),
    lambda: TimingConfig(stretch_factor=1.0),
    lambda: TrajConfig(n_waypoints=3),
    lambda: TrajConfig(render_k=8, render_candidates=4),
    lambda: TrajConfig(contact_tail_fraction=1.0),
])
def test_config_validation(make):
    with pytest.raises(TrajError):
        make()


def test_demonstration_validation():
    d = synthetic().demo
    P, ts, w = d.T_world_cam, d.timestamps, d.gripper_width
    with pytest.raises(TrajError, match="contact_index"):
        Demonstration(P, ts, w, 0)
    with pytest.raises(TrajError, match="contact_index"):
        Demonstration(P, ts, w, len(P))
    with pytest.raises(TrajError, match="timestamps"):
        Demonstration(P, ts[::-1], w, 10)
    bad = P.copy()
    bad[3, 0, 3] = np.nan
    with pytest.raises(TrajError, match="NaN"):
        Demonstration(bad, ts, w, 10)
    with pytest.raises(TrajError, match="gripper_width"):
        Demonstration(P, ts, -w, 10)
    ok = Demonstration(P, ts, w[:, None], 10)
    assert ok.gripper_width.shape == (len(P),) and ok.pre.shape == (11, 4, 4)
    assert ok.frame_dt == pytest.approx(1001 / 60000)
