"""Fast batched objective vs the slow per-trajectory reference: values, gradients, GN Hessians."""

from __future__ import annotations

import numpy as np
import pytest

from umi_aug.traj import TrajConfig
from umi_aug.traj.init_guess import straight_line_guess
from umi_aug.traj.objective import evaluate, funnel_weights, smooth_hinge, smoothing_matrices
from umi_aug.traj._ref import _cost_reference, _derivatives_reference, _gradient_reference, _terms_reference
from tests.traj._helpers import RADIUS, THETA_50, obstacle_problem, perturbed, synthetic
from umi_aug.traj import ConvexObstacle, TrajProblem, TrajScene

T_SMALL = 8


def _small_problem(rng, eta: float):
    st = synthetic()
    c = st.demo.contact_index
    near_goal = st.demo.T_world_cam[rng.choice(np.arange(c - 40, c + 1), 6, replace=False)]
    views = np.concatenate([near_goal, st.scan[rng.choice(len(st.scan), 6, replace=False)]])
    cfg = TrajConfig(n_waypoints=T_SMALL, hinge_eta=eta, render_candidates=16, render_radius=0.3)
    return TrajProblem(st.demo, TrajScene(st.sdf, views, ConvexObstacle(st.obstacle_points, 0.01)), cfg)


def _dense(hess_band: np.ndarray) -> np.ndarray:
    n = hess_band.shape[0]
    H = np.zeros((6 * n, 6 * n))
    for k in range(n):
        for d in range(4):
            if k + d < n:
                H[6 * k:6 * k + 6, 6 * (k + d):6 * (k + d) + 6] = hess_band[k, d]
                if d:
                    H[6 * (k + d):6 * (k + d) + 6, 6 * k:6 * k + 6] = hess_band[k, d].T
    return H


@pytest.mark.parametrize("eta", [0.0, 0.01])
def test_fast_objective_matches_reference(rng, eta):
    pb = _small_problem(rng, eta)
    x = pb.sample_starts(2, rng, THETA_50, RADIUS)
    X = perturbed(straight_line_guess(x, pb.x_goal, T_SMALL), rng, pos=0.05, rot=0.3)
    mid = T_SMALL // 2  # move one waypoint so that a fingertip sphere sits inside the inflated hull
    tip = X[:, mid, :3, :3] @ pb.spheres.centers_cam[4] + X[:, mid, :3, 3]
    ob = pb.obstacle
    centre = ob.vertices.mean(axis=0)
    inner = centre - 0.8 * (ob.normals[0] @ centre + ob.offsets[0]) * ob.normals[0]  # near facet 0, off the medial axes
    X[:, mid, :3, 3] += inner - tip
    data = pb.objective_data
    ev = evaluate(data, X[:, :, :3, 3], X[:, :, :3, :3])
    active = {"collision": 0, "obstacle": 0, "render": 0}
    for b in range(len(X)):
        ref = _terms_reference(data, X[b])
        for k, v in ref.items():
            assert ev.terms[k][b] == pytest.approx(v, rel=1e-10, abs=1e-15), k
            if k in active and v > 0:
                active[k] += 1
        assert ev.cost[b] == pytest.approx(_cost_reference(data, X[b]), rel=1e-10)
        g, H = _derivatives_reference(data, X[b])
        np.testing.assert_allclose(ev.grad[b], g, rtol=1e-5, atol=1e-6 * np.abs(g).max())
        np.testing.assert_allclose(_dense(ev.hess[b]), H, rtol=1e-5, atol=1e-6 * np.abs(H).max())
    assert active["obstacle"] > 0  # the comparison exercised the hinge
    assert active["render"] > 0  # and the render prior


def test_scene_collision_term_matches_reference_when_active(rng):
    pb = _small_problem(rng, 0.01)
    x = pb.sample_starts(2, rng, THETA_50, RADIUS)
    X = straight_line_guess(x, pb.x_goal, T_SMALL)
    X[:, 1:-1, 2, 3] -= rng.uniform(0.25, 0.35, (2, T_SMALL - 2))  # push the middle into the table
    data = pb.objective_data
    ev = evaluate(data, X[:, :, :3, 3], X[:, :, :3, :3])
    for b in range(2):
        ref = _terms_reference(data, X[b])
        assert ref["collision"] > 0
        assert ev.terms["collision"][b] == pytest.approx(ref["collision"], rel=1e-10)
        g = _gradient_reference(data, X[b])
        np.testing.assert_allclose(ev.grad[b], g, rtol=1e-5, atol=1e-6 * np.abs(g).max())


def test_funnel_weights():
    w = funnel_weights(64, 0.02, 1.0)
    assert w.sum() == pytest.approx(1.0, abs=1e-15)
    assert np.all(np.diff(w) > 0) and w[-1] / w[0] > 10
    k = np.arange(1, 65)
    raw = 0.02 + 0.98 * (k / 64) ** 3
    np.testing.assert_allclose(w, raw / raw.sum())
    np.testing.assert_allclose(funnel_weights(5, 0.3, 0.3), 0.2)


def test_smoothing_matrices_match_explicit_differences(rng):
    T = 9
    t = rng.normal(size=(T, 3))
    M, S = smoothing_matrices(T, 2.0, 3.0, 5.0, 7.0)
    h = T - 1
    acc = sum(np.sum((t[k + 2] - 2 * t[k + 1] + t[k]) ** 2) for k in range(T - 2))
    jerk = sum(np.sum((t[k + 3] - 3 * t[k + 2] + 3 * t[k + 1] - t[k]) ** 2) for k in range(T - 3))
    assert np.einsum("kx,kl,lx->", t, M, t) == pytest.approx(2.0 * h**3 * acc + 3.0 * h**5 * jerk, rel=1e-12)
    v = rng.normal(size=(T - 1, 3))
    a2 = sum(np.sum((v[k + 1] - v[k]) ** 2) for k in range(T - 2))
    j2 = sum(np.sum((v[k + 2] - 2 * v[k + 1] + v[k]) ** 2) for k in range(T - 3))
    assert np.einsum("kx,kl,lx->", v, S, v) == pytest.approx(5.0 * h**3 * a2 + 7.0 * h**5 * j2, rel=1e-12)


def test_smooth_hinge_is_c1():
    eta = 0.01
    x = np.linspace(-0.03, 0.03, 60001)
    r, dr = smooth_hinge(x, eta)
    assert np.all(r >= 0) and np.all(np.diff(r) >= 0)
    np.testing.assert_allclose(np.gradient(r, x), dr, atol=2e-3)
    assert np.max(np.abs(np.diff(dr))) < 1e-2  # no jump in the derivative
    np.testing.assert_array_equal(smooth_hinge(x, 0.0)[0], np.maximum(x, 0))
    assert smooth_hinge(np.array([eta]), eta)[0][0] == pytest.approx(eta)


def test_objective_is_finite_at_degenerate_inputs():
    pb = obstacle_problem()
    X = np.repeat(pb.x_goal[None, None], 64, axis=1)  # every waypoint at the goal
    ev = evaluate(pb.objective_data, X[:, :, :3, 3], X[:, :, :3, :3])
    assert np.isfinite(ev.cost).all() and np.isfinite(ev.grad).all() and np.isfinite(ev.hess).all()
    Rpi = X.copy()
    Rpi[0, 1:-1, :3, :3] = X[0, 1:-1, :3, :3] @ np.diag([1.0, -1.0, -1.0])  # neighbours differ by exactly π
    ev = evaluate(pb.objective_data, Rpi[:, :, :3, 3], Rpi[:, :, :3, :3])
    assert np.isfinite(ev.cost).all() and np.isfinite(ev.grad).all() and np.isfinite(ev.hess).all()
