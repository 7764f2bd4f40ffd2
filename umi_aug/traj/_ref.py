"""Slow references of the trajectory stage (gsplat ``_torch_impl`` style: private, for tests and benchmarks only).

They mirror :func:`umi_aug.traj.objective.evaluate` (residuals, per-term costs, gradient and Gauss–Newton Hessian
of the §3.2 objective) for ONE trajectory: plain loops, public geometry functions, derivatives by central finite
differences. :func:`_solve_scipy_reference` is an independent optimiser that mirrors
:func:`umi_aug.traj.solver.levenberg_marquardt`'s minimisation for cross-checks.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import cholesky, solve_triangular
from scipy.optimize import minimize

from umi_aug.geometry import make_pose, so3_exp, so3_left_jacobian, so3_log
from umi_aug.traj.objective import ObjectiveData, evaluate
from umi_aug.traj.solver import damping_metric

def _hinge(x: float, eta: float) -> float:
    """0 below −η, x above η, the quadratic blend (x + η)²/(4η) in between (plain max(0, x) for η = 0)."""
    if eta <= 0:
        return max(0.0, x)
    if x <= -eta:
        return 0.0
    if x >= eta:
        return x
    return (x + eta) ** 2 / (4 * eta)


def _render_residuals(data: ObjectiveData, t: np.ndarray, R: np.ndarray) -> list[float]:
    prior = data.prior
    out: list[float] = []
    if prior is None or data.render_w <= 0:
        return out
    sw = math.sqrt(data.render_w)
    rho, ell = prior.radius, prior.rot_scale
    for k in range(data.T):
        cands = []
        for j in range(prior.n_views):
            dt = t[k] - prior.positions[j]
            e = so3_log(R[k].T @ prior.rotations[j])
            d2 = float(dt @ dt + ell * ell * (e @ e))
            cands.append((min(d2, rho * rho), d2 < rho * rho, dt, e))
        cands.sort(key=lambda c: c[0])
        for slot in range(prior.k):
            if slot < len(cands) and cands[slot][1]:
                _, _, dt, e = cands[slot]
                out.extend(sw * dt)
                out.extend(sw * ell * e)
            else:
                out.extend([sw * rho, 0.0, 0.0, 0.0, 0.0, 0.0])
    return out


def _residual_groups(data: ObjectiveData, T_world_cam: np.ndarray) -> dict[str, list[float]]:
    t = T_world_cam[:, :3, 3]
    R = T_world_cam[:, :3, :3]
    T = data.T
    groups: dict[str, list[float]] = {k: [] for k in
                                      ("funnel", "collision", "obstacle", "render", "acc", "jerk", "rot_acc", "rot_jerk")}
    for k in range(T):
        groups["funnel"].extend(math.sqrt(data.funnel_w[k]) * (t[k] - data.funnel_targets[k]))
    sc = math.sqrt(data.collision_w)
    S = len(data.sphere_radii)
    # every sphere centre in the world, then one distance query per field (the fields are evaluated point by point)
    centres = np.array([[R[k] @ data.sphere_centers[s] + t[k] for s in range(S)] for k in range(T)]).reshape(T * S, 3)
    d_scene = data.scene_sdf.distance_and_gradient(centres)[0].reshape(T, S)
    d_obstacle = None if data.obstacle_sdf is None else data.obstacle_sdf.distance_and_gradient(centres)[0].reshape(T, S)
    for k in range(T):
        for s in range(S):
            d = float(d_scene[k, s])
            groups["collision"].append(sc * _hinge(data.required_scene[k, s] + data.sphere_radii[s] - d, data.hinge_eta))
            if d_obstacle is not None:
                d = float(d_obstacle[k, s])
                groups["obstacle"].append(sc * _hinge(data.required_obstacle + data.sphere_radii[s] - d, data.hinge_eta))
    groups["render"] = _render_residuals(data, t, R)
    h = float(T - 1)
    for k in range(T - 2):
        groups["acc"].extend(math.sqrt(data.acc_w * h**3) * (t[k + 2] - 2 * t[k + 1] + t[k]))
    for k in range(T - 3):
        groups["jerk"].extend(math.sqrt(data.jerk_w * h**5) * (t[k + 3] - 3 * t[k + 2] + 3 * t[k + 1] - t[k]))
    v = [so3_log(R[k].T @ R[k + 1]) for k in range(T - 1)]
    for k in range(T - 2):
        groups["rot_acc"].extend(math.sqrt(data.rot_acc_w * h**3) * (v[k + 1] - v[k]))
    for k in range(T - 3):
        groups["rot_jerk"].extend(math.sqrt(data.rot_jerk_w * h**5) * (v[k + 2] - 2 * v[k + 1] + v[k]))
    return groups


def _residuals_reference(data: ObjectiveData, T_world_cam: np.ndarray) -> np.ndarray:
    """All residuals of one trajectory ``[T, 4, 4]`` (cost = Σ r²) → flat float64 array."""
    g = _residual_groups(data, T_world_cam)
    return np.array([x for k in g for x in g[k]], dtype=np.float64)


def _terms_reference(data: ObjectiveData, T_world_cam: np.ndarray) -> dict[str, float]:
    """Per-term cost of one trajectory."""
    return {k: float(np.sum(np.square(v))) for k, v in _residual_groups(data, T_world_cam).items()}


def _cost_reference(data: ObjectiveData, T_world_cam: np.ndarray) -> float:
    """Total cost ``Σ r²`` of one trajectory (mirrors ``evaluate(...).cost``)."""
    return float(np.sum(np.square(_residuals_reference(data, T_world_cam))))


def _perturb(T_world_cam: np.ndarray, k: int, delta: np.ndarray) -> np.ndarray:
    """Apply the left perturbation ``(δt, δφ)`` [6] to waypoint ``k``: t += δt, R ← Exp(δφ) R."""
    out = T_world_cam.copy()
    out[k] = make_pose(so3_exp(delta[3:]) @ T_world_cam[k, :3, :3], T_world_cam[k, :3, 3] + delta[:3])
    return out


def _gradient_reference(data: ObjectiveData, T_world_cam: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central-difference gradient w.r.t. the interior waypoints' perturbations → ``[T-2, 6]``."""
    T = data.T
    g = np.zeros((T - 2, 6))
    for k in range(1, T - 1):
        for i in range(6):
            e = np.zeros(6)
            e[i] = h
            g[k - 1, i] = (_cost_reference(data, _perturb(T_world_cam, k, e))
                           - _cost_reference(data, _perturb(T_world_cam, k, -e))) / (2 * h)
    return g


def _derivatives_reference(data: ObjectiveData, T_world_cam: np.ndarray,
                           h: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Both central-difference gradient ``[T-2, 6]`` (of the cost) and GN Hessian ``2 JᵀJ`` from one set of
    perturbed residual evaluations."""
    T = data.T
    g = np.zeros((T - 2, 6))
    cols = []
    for k in range(1, T - 1):
        for i in range(6):
            e = np.zeros(6)
            e[i] = h
            rp = _residuals_reference(data, _perturb(T_world_cam, k, e))
            rm = _residuals_reference(data, _perturb(T_world_cam, k, -e))
            g[k - 1, i] = (np.sum(rp * rp) - np.sum(rm * rm)) / (2 * h)
            cols.append((rp - rm) / (2 * h))
    J = np.stack(cols, axis=1)
    return g, 2.0 * J.T @ J


def _gn_hessian_reference(data: ObjectiveData, T_world_cam: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Dense GN Hessian ``2 JᵀJ`` [6(T-2), 6(T-2)] with J by central differences of the residuals."""
    T = data.T
    cols = []
    for k in range(1, T - 1):
        for i in range(6):
            e = np.zeros(6)
            e[i] = h
            cols.append((_residuals_reference(data, _perturb(T_world_cam, k, e))
                         - _residuals_reference(data, _perturb(T_world_cam, k, -e))) / (2 * h))
    J = np.stack(cols, axis=1)
    return 2.0 * J.T @ J


def _solve_scipy_reference(data: ObjectiveData, T_world_cam: np.ndarray, maxiter: int = 3000,
                           gtol: float = 1e-12) -> tuple[np.ndarray, float, int]:
    """Independent optimiser for cross-checks: scipy L-BFGS-B on ONE trajectory ``[T, 4, 4]``.

    Variables ``x = (δt_k, φ_k)`` about the initial waypoints with ``R_k = Exp(φ_k) R̄_k`` (gradient w.r.t. φ by the
    chain rule through the SO(3) left Jacobian: ``g_φ = J_l(φ)ᵀ g_left``), preconditioned by the constant
    smoothness metric ``A = L Lᵀ`` (``y = Lᵀ x``; without it L-BFGS stalls on the ~9-decade Hessian). Objective and
    left-perturbation gradient come from the fast kernel (whose gradient the tests check against finite
    differences of this module's reference).

    Returns:
        (T_world_cam [T, 4, 4], cost, iterations)
    """
    T = data.T
    n = T - 2
    t0 = T_world_cam[:, :3, 3].copy()
    R0 = T_world_cam[:, :3, :3].copy()
    Ab = damping_metric(data)
    A = np.zeros((6 * n, 6 * n))
    for k in range(n):
        for d in range(4):
            if k + d < n:
                A[6 * k:6 * k + 6, 6 * (k + d):6 * (k + d) + 6] = Ab[k, d]
                A[6 * (k + d):6 * (k + d) + 6, 6 * k:6 * k + 6] = Ab[k, d].T
    L = cholesky(A, lower=True)

    def unpack(y):
        x = solve_triangular(L.T, y, lower=False)
        d = x.reshape(n, 6)
        t = t0.copy()
        R = R0.copy()
        t[1:-1] += d[:, :3]
        R[1:-1] = so3_exp(d[:, 3:]) @ R0[1:-1]
        return t, R, d

    def fun(y):
        t, R, d = unpack(y)
        ev = evaluate(data, t[None], R[None], derivs=True)
        g = ev.grad[0].copy()
        Jl = so3_left_jacobian(d[:, 3:])
        g[:, 3:] = np.einsum("kji,kj->ki", Jl, g[:, 3:])
        return float(ev.cost[0]), solve_triangular(L, g.reshape(-1), lower=True)

    res = minimize(fun, np.zeros(6 * n), jac=True, method="L-BFGS-B",
                   options={"maxiter": maxiter, "maxfun": 4 * maxiter, "gtol": gtol, "ftol": 1e-15, "maxcor": 30})
    t, R, _ = unpack(res.x)
    out = T_world_cam.copy()
    out[:, :3, 3] = t
    out[:, :3, :3] = R
    return out, float(res.fun), int(res.nit)
