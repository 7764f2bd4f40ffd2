"""The §3.2 objective, batched (numpy float64), with its gradient and Gauss–Newton Hessian (fast kernel).

Trajectory ``X = {(R_k, t_k)}_{k=0}^{T-1}`` of camera poses ``T_world_cam``; ``x_0 = x_init`` and ``x_{T-1} = x_goal``
are fixed. Variables: the interior waypoints' left perturbations ``(δt_k, δφ_k)``: ``t_k ← t_k + δt_k``,
``R_k ← Exp(δφ_k) R_k`` (world-frame rotation about the camera centre). Every term is a sum of squared residuals
``Σ r²`` (cost = Σ r², gradient = 2Jᵀr, GN Hessian = 2JᵀJ), normalised to be independent of T:

* funnel     ``W_f Σ_k w_k ‖t_k − t_ee^k‖²``, ``w_k = w_min + (w_max − w_min)(k/T)³`` (k = 1..T), Σ w_k = 1 (m²);
  ``t_ee^k`` = the demo's pre-contact camera positions resampled uniformly in arc length.
* collision  ``(W_c/T) Σ_k Σ_s h_η(m_ks + r_s − sdf(c_ks))²`` over the gripper spheres (centres ``c_ks``, radii
  ``r_s``), for the scene SDF (required clearance ``m_ks`` = margin + buffer, relaxed in the contact tail to the
  demo's own clearance) and, separately, for the inflated obstacle hull (margin + buffer everywhere) (m²).
  ``h_η`` is the hinge ``max(0, x)`` with a C¹ quadratic onset of half-width η (:func:`smooth_hinge`): with a
  plain hinge, spheres parked exactly at the activation boundary are invisible to the GN model and full steps
  push them in (rejections, λ blow-ups; ~2.5× more iterations with the obstacle, measured).
* render     ``(W_r/(T K)) Σ_k Σ_{j ∈ K-NN} min(‖t_k − t_j‖² + ℓ²‖log(R_kᵀ R_j)‖², ρ²)`` (m²; :mod:`.render_prior`).
* smoothness ``W_a ∫‖t''‖² + W_j ∫‖t'''‖² + W_ra ∫‖ω'‖² + W_rj ∫‖ω''‖²`` over s ∈ [0, 1] with h = 1/(T−1):
  ``(T−1)³ Σ‖Δ²t‖²``, ``(T−1)⁵ Σ‖Δ³t‖²``; rotation uses the body increments ``v_k = log(R_kᵀ R_{k+1})``:
  ``(T−1)³ Σ‖Δv‖²``, ``(T−1)⁵ Σ‖Δ²v‖²``.

The Hessian is block-banded: blocks ``(k, k+d)``, d = 0..3, of 6×6 (jerk couples 4 consecutive waypoints).
A slow per-trajectory loop implementation lives in :mod:`._ref`; tests compare the two.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from umi_aug.errors import TrajError
from umi_aug.geometry.sdf import SignedDistanceField
from umi_aug.geometry.so3 import so3_left_jacobian_inv_unchecked as _left_jacobian_inv, so3_log_unchecked as _so3_log
from umi_aug.traj.render_prior import RenderPrior
from umi_aug.traj.scene_grid import SceneGrid

__all__ = ["ObjectiveData", "ObjectiveEval", "TERM_NAMES", "evaluate", "funnel_weights", "smoothing_matrices",
           "smooth_hinge"]

TERM_NAMES: tuple[str, ...] = ("funnel", "collision", "obstacle", "render", "acc", "jerk", "rot_acc", "rot_jerk")


def funnel_weights(T: int, w_min: float, w_max: float) -> np.ndarray:
    """Paper's funnel weights for k = 1..T, normalised to sum 1 → ``[T]`` (index 0 = the start)."""
    k = np.arange(1, T + 1, dtype=np.float64)
    w = w_min + (w_max - w_min) * (k / T) ** 3
    return w / w.sum()


def _diff_matrix(n: int, order: int) -> np.ndarray:
    D = np.eye(n)
    for _ in range(order):
        D = D[1:] - D[:-1]
    return D


def smoothing_matrices(T: int, acc: float, jerk: float, rot_acc: float, rot_jerk: float) -> tuple[np.ndarray, np.ndarray]:
    """``M_t`` [T, T] with translation smoothness = Σ_xyz tᵀ M_t t, and ``S_v`` [T−1, T−1] with rotation
    smoothness = Σ_xyz vᵀ S_v v over the increments v."""
    h = float(T - 1)
    D2, D3 = _diff_matrix(T, 2), _diff_matrix(T, 3)
    M_t = acc * h**3 * D2.T @ D2 + jerk * h**5 * D3.T @ D3
    E1, E2 = _diff_matrix(T - 1, 1), _diff_matrix(T - 1, 2)
    S_v = rot_acc * h**3 * E1.T @ E1 + rot_jerk * h**5 * E2.T @ E2
    return M_t, S_v


@dataclass
class ObjectiveData:
    """Constant per-problem arrays of the objective (built by :class:`umi_aug.traj.problem.TrajProblem`).

    Attributes:
        T: waypoints.
        funnel_targets: np.ndarray,  # [T, 3] t_ee^k, world, metres
        funnel_w: np.ndarray,  # [T] W_f · w_k
        sphere_centers: np.ndarray,  # [S, 3] camera frame, metres
        sphere_radii: np.ndarray,  # [S]
        required_scene: np.ndarray,  # [T, S] clearance the optimiser aims at w.r.t. the scene SDF (metres)
        required_obstacle: float,  # clearance aimed at w.r.t. the inflated obstacle (metres)
        scene_sdf: SignedDistanceField
        obstacle_sdf: SignedDistanceField | None
        collision_w: float,  # W_c / T
        hinge_eta: float,  # half-width of the smoothed hinge onset (metres; 0 = plain hinge)
        prior: RenderPrior | None
        render_w: float,  # W_r / (T K)
        acc_w, jerk_w, rot_acc_w, rot_jerk_w: float,  # smoothness weights (per ∫ over s ∈ [0, 1])
        scene_bound: Callable[[], SceneGrid] | None,  # lazily built conservative lower bound of the scene SDF
            (only skips exact queries that cannot change the result; None = always query exactly)
        M_t: np.ndarray,  # [T, T] (derived) translation smoothness = Σ_xyz tᵀ M_t t
        S_v: np.ndarray,  # [T-1, T-1] (derived) rotation smoothness = Σ_xyz vᵀ S_v v
    """

    T: int
    funnel_targets: np.ndarray
    funnel_w: np.ndarray
    sphere_centers: np.ndarray
    sphere_radii: np.ndarray
    required_scene: np.ndarray
    required_obstacle: float
    scene_sdf: SignedDistanceField
    obstacle_sdf: SignedDistanceField | None
    collision_w: float
    hinge_eta: float
    prior: RenderPrior | None
    render_w: float
    acc_w: float
    jerk_w: float
    rot_acc_w: float
    rot_jerk_w: float
    scene_bound: Callable[[], SceneGrid] | None = None
    M_t: np.ndarray = field(init=False, repr=False)
    S_v: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        T = self.T
        self.M_t, self.S_v = smoothing_matrices(T, self.acc_w, self.jerk_w, self.rot_acc_w, self.rot_jerk_w)
        n = T - 2
        # banded (offsets 0..3) interior part of 2·M_t, and band of S_v (offsets −2..2) over increments
        self._Mt_band = np.zeros((n, 4))
        for d in range(4):
            k = np.arange(n - d)
            self._Mt_band[k, d] = 2.0 * self.M_t[k + 1, k + 1 + d]
        self._Sv_band = np.zeros((T - 1, 5))
        for dl in range(-2, 3):
            i = np.arange(max(0, -dl), min(T - 1, T - 1 - dl))
            self._Sv_band[i, dl + 2] = self.S_v[i, i + dl]


@dataclass
class ObjectiveEval:
    """Cost of B trajectories and (optionally) derivatives w.r.t. the interior perturbations.

    Attributes:
        cost: np.ndarray,  # [B]
        terms: dict[str, np.ndarray],  # name → [B] weighted contribution (sum = cost)
        grad: np.ndarray | None,  # [B, T-2, 6] (δt, δφ) per interior waypoint
        hess: np.ndarray | None,  # [B, T-2, 4, 6, 6] GN Hessian blocks (k, k+d)
    """

    cost: np.ndarray
    terms: dict[str, np.ndarray]
    grad: np.ndarray | None = None
    hess: np.ndarray | None = None


def _hat(v: np.ndarray) -> np.ndarray:
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = np.zeros_like(x)
    return np.stack([o, -z, y, z, o, -x, -y, x, o], axis=-1).reshape(v.shape[:-1] + (3, 3))


def smooth_hinge(x: np.ndarray, eta: float) -> tuple[np.ndarray, np.ndarray]:
    """C¹ hinge residual and its derivative: 0 for x ≤ −η, (x + η)²/(4η) on (−η, η), x for x ≥ η (plain
    ``max(0, x)`` when η = 0). Its square is the per-sphere collision cost."""
    if eta <= 0:
        return np.maximum(x, 0.0), (x > 0).astype(np.float64)
    mid = (x > -eta) & (x < eta)
    r = np.where(x >= eta, x, np.where(mid, (x + eta) ** 2 / (4 * eta), 0.0))
    dr = np.where(x >= eta, 1.0, np.where(mid, (x + eta) / (2 * eta), 0.0))
    return r, dr


def _collision(sdf: SignedDistanceField, a: np.ndarray, p: np.ndarray, required: np.ndarray, radii: np.ndarray,
               weight: float, eta: float, derivs: bool, grad: np.ndarray | None, hess: np.ndarray | None,
               bound: SceneGrid | None = None) -> np.ndarray:
    """Smoothed-hinge term for sphere points ``p`` [B, T, S, 3] (``a`` = R c, the lever arm). Adds to grad/hess in
    place (interior waypoints). Returns the cost [B].

    With a conservative lower bound of the SDF (``bound``), only spheres whose bound does not already clear the
    hinge (``lb < required + r + η``) are queried exactly; the others contribute exactly zero either way."""
    thresh = required + radii + max(eta, 0.0)
    if bound is None:
        d, g = sdf.distance_and_gradient(p)
    else:
        cand = bound.lower_bound(p) < thresh
        d = np.full(p.shape[:-1], np.inf)
        g = np.zeros(p.shape)
        if cand.any():
            d[cand], g[cand] = sdf.distance_and_gradient(p[cand])
    viol = required + radii - d  # [B, T, S]
    h, dh = smooth_hinge(viol, eta)
    cost = weight * np.sum(h * h, axis=(1, 2))
    if derivs and np.any(dh[:, 1:-1] > 0):
        hi, gi, ai = h[:, 1:-1], g[:, 1:-1] * dh[:, 1:-1, :, None], a[:, 1:-1]
        J = np.concatenate([-gi, np.cross(gi, ai)], axis=-1)  # [B, n, S, 6], residual = sqrt(w) h
        grad += 2.0 * weight * (hi[..., None, :] @ J)[..., 0, :]
        hess[:, :, 0] += 2.0 * weight * (np.swapaxes(J, -1, -2) @ J)
    return cost


def evaluate(data: ObjectiveData, t: np.ndarray, R: np.ndarray, derivs: bool = True) -> ObjectiveEval:
    """Evaluate the objective of B trajectories.

    Args:
        data: the problem's constant arrays.
        t: np.ndarray,  # [B, T, 3] camera positions, world, metres
        R: np.ndarray,  # [B, T, 3, 3] R_world_cam
        derivs: also compute the gradient and GN Hessian (interior waypoints).
    Returns:
        ObjectiveEval
    """
    B, T = t.shape[:2]
    if T != data.T:
        raise TrajError(f"objective: trajectories have {T} waypoints, the problem {data.T}")
    n = T - 2
    grad = np.zeros((B, n, 6)) if derivs else None
    hess = np.zeros((B, n, 4, 6, 6)) if derivs else None
    terms: dict[str, np.ndarray] = {}

    # ---- funnel
    diff = t - data.funnel_targets
    terms["funnel"] = np.einsum("k,bkx,bkx->b", data.funnel_w, diff, diff)
    if derivs:
        grad[:, :, :3] += 2.0 * data.funnel_w[None, 1:-1, None] * diff[:, 1:-1]
        hess[:, :, 0, [0, 1, 2], [0, 1, 2]] += 2.0 * data.funnel_w[None, 1:-1, None]

    # ---- collision: scene and inflated obstacle
    a = np.swapaxes(R @ data.sphere_centers.T, -1, -2)  # [B, T, S, 3] lever arms R c
    p = a + t[:, :, None, :]
    bound = data.scene_bound() if data.scene_bound is not None else None
    terms["collision"] = _collision(data.scene_sdf, a, p, data.required_scene, data.sphere_radii,
                                    data.collision_w, data.hinge_eta, derivs, grad, hess, bound)
    if data.obstacle_sdf is not None:
        terms["obstacle"] = _collision(data.obstacle_sdf, a, p, np.float64(data.required_obstacle),
                                       data.sphere_radii, data.collision_w, data.hinge_eta, derivs, grad, hess)
    else:
        terms["obstacle"] = np.zeros(B)

    # ---- render prior
    if data.prior is not None and data.render_w > 0:
        rho2 = data.prior.radius ** 2
        ell2 = data.prior.rot_scale ** 2
        nb = data.prior.query(t.reshape(-1, 3), R.reshape(-1, 3, 3))
        pair_cost = np.sum(nb.dt * nb.dt, -1) + ell2 * np.sum(nb.e * nb.e, -1)
        cost_pt = rho2 * nb.n_truncated.astype(np.float64) + np.bincount(nb.point, pair_cost, minlength=B * T)
        terms["render"] = data.render_w * cost_pt.reshape(B, T).sum(1)
        if derivs and nb.point.size:
            b_idx, k_idx = np.divmod(nb.point, T)
            inner = (k_idx > 0) & (k_idx < T - 1)
            if inner.any():
                pts = nb.point[inner]  # ascending (pairs come out of a row-major nonzero)
                dt, e = nb.dt[inner], nb.e[inner]
                Rk = R.reshape(-1, 3, 3)[pts]
                w2 = 2.0 * data.render_w
                M = _left_jacobian_inv(e) @ np.swapaxes(Rk, -1, -2)  # d e / d δφ = −M ;  Mᵀ e = R_k e
                per_pair = np.concatenate([w2 * dt, -w2 * ell2 * np.einsum("pij,pj->pi", Rk, e),
                                           (w2 * ell2 * np.swapaxes(M, -1, -2) @ M).reshape(-1, 9)], axis=1)
                uniq, starts, counts = np.unique(pts, return_index=True, return_counts=True)
                summed = np.add.reduceat(per_pair, starts, axis=0)  # [U, 15]
                ub, uk = np.divmod(uniq, T)
                uk = uk - 1
                grad[ub, uk] += summed[:, :6]  # unique (b, k)
                blk = np.zeros((uniq.size, 6, 6))
                blk[:, [0, 1, 2], [0, 1, 2]] = (w2 * counts)[:, None]
                blk[:, 3:, 3:] = summed[:, 6:].reshape(-1, 3, 3)
                hess[ub, uk, 0] += blk  # (b, k) pairs are unique here, so fancy-index += is safe
    else:
        terms["render"] = np.zeros(B)

    # ---- translation smoothness (linear)
    Mt_t = data.M_t @ t
    h = float(T - 1)
    d2 = t[:, 2:] - 2 * t[:, 1:-1] + t[:, :-2]
    d3 = t[:, 3:] - 3 * t[:, 2:-1] + 3 * t[:, 1:-2] - t[:, :-3]
    terms["acc"] = data.acc_w * h**3 * np.sum(d2 * d2, axis=(1, 2))
    terms["jerk"] = data.jerk_w * h**5 * np.sum(d3 * d3, axis=(1, 2))
    if derivs:
        grad[:, :, :3] += 2.0 * Mt_t[:, 1:-1]
        for d in range(4):
            blk = data._Mt_band[: n - d, d]
            for x in range(3):
                hess[:, : n - d, d, x, x] += blk

    # ---- rotation smoothness on body increments v_k = log(R_kᵀ R_{k+1})
    Rt = np.swapaxes(R, -1, -2)
    v = _so3_log(Rt[:, :-1] @ R[:, 1:])  # [B, T-1, 3]
    e1 = v[:, 1:] - v[:, :-1]
    e2 = v[:, 2:] - 2 * v[:, 1:-1] + v[:, :-2]
    terms["rot_acc"] = data.rot_acc_w * h**3 * np.sum(e1 * e1, axis=(1, 2))
    terms["rot_jerk"] = data.rot_jerk_w * h**5 * np.sum(e2 * e2, axis=(1, 2))
    if derivs:
        gv = 2.0 * (data.S_v @ v)  # [B, T-1, 3]
        Jinv = _left_jacobian_inv(v)  # [B, T-1, 3, 3]
        A = -Jinv @ Rt[:, :-1]  # dv_i/dδφ_i
        Bm = np.swapaxes(Jinv, -1, -2) @ Rt[:, 1:]  # dv_i/dδφ_{i+1}
        # interior k = 1..T-2: Ĉ[k,0] = A_k (increment k), Ĉ[k,1] = B_{k-1} (increment k-1)
        C0, C1 = A[:, 1:], Bm[:, :-1]  # [B, n, 3, 3]
        grad[:, :, 3:] += np.einsum("bkji,bkj->bki", C0, gv[:, 1:]) + np.einsum("bkji,bkj->bki", C1, gv[:, :-1])
        Chat = (C0, C1)
        Sb = data._Sv_band
        for d in range(4):
            m = n - d
            if m <= 0:
                continue
            acc = np.zeros((B, m, 3, 3))
            for a_ in (0, 1):
                for b_ in (0, 1):
                    dl = d - b_ + a_
                    if abs(dl) > 2:
                        continue
                    s = Sb[np.arange(m) + 1 - a_, dl + 2]  # i = k − a (interior k = idx + 1)
                    acc += 2.0 * s[None, :, None, None] * np.swapaxes(Chat[a_][:, :m], -1, -2) @ Chat[b_][:, d:d + m]
            hess[:, :m, d, 3:, 3:] += acc

    cost = sum(terms[k] for k in TERM_NAMES)
    return ObjectiveEval(cost=cost, terms=terms, grad=grad, hess=hess)
