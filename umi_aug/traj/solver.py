"""Batched Levenberg–Marquardt on the §3.2 objective (Gauss–Newton Hessian, block-banded linear solves).

Each trajectory has its own damping λ, its own accept/reject decision and its own stopping test, so a batch
behaves exactly like B independent solves (deterministic; no cross-talk), while the expensive parts (objective,
SDF queries, Jacobians) run vectorised over the batch. Converged trajectories leave the active set.

Linear solve: the GN Hessian of the interior waypoints is block-banded (6×6 blocks, 3 off-diagonal blocks,
scalar bandwidth 23); it is copied into LAPACK's symmetric band storage and solved with ``scipy.linalg.
solveh_banded`` (Cholesky, O(n·23²) per trajectory).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
from scipy.linalg import LinAlgError, solveh_banded

from umi_aug.geometry.so3 import _so3_exp
from umi_aug.traj.config import SolverConfig
from umi_aug.traj.constants import LM_CONVERGED_LAMBDA, LM_MIN_GAIN, LM_STAGNATION_WINDOW
from umi_aug.traj.objective import TERM_NAMES, ObjectiveData, evaluate, smoothing_matrices

__all__ = ["TrajStatus", "LMResult", "levenberg_marquardt"]


_BAND_U = 23  # scalar upper bandwidth: 6·4 − 1


class TrajStatus(str, Enum):
    """Outcome of one trajectory. Only ``CONVERGED`` (and, when allowed, ``ITERATION_LIMIT``) is ever emitted."""

    CONVERGED = "converged"
    INFEASIBLE_START = "infeasible_start"  #: x_init in collision / inside the inflated obstacle
    PLANNER_FAILED = "planner_failed"  #: RRT* found no path around the obstacle
    COLLISION = "collision"  #: optimised (or retimed) trajectory violates the clearance / hull test
    ITERATION_LIMIT = "iteration_limit"  #: not converged within max_iterations
    TIMING_FAILED = "timing_failed"  #: no time parameterisation within the speed/accel bounds
    NUMERICAL = "numerical"  #: non-finite values (never emitted)


@dataclass
class LMResult:
    """Per-trajectory outcome of :func:`levenberg_marquardt`.

    Attributes:
        t: np.ndarray,  # [B, T, 3]
        R: np.ndarray,  # [B, T, 3, 3]
        cost: np.ndarray,  # [B]
        terms: dict[str, np.ndarray],  # name → [B]
        iterations: np.ndarray,  # [B] int, LM iterations (one linear solve + one objective evaluation each)
        converged: np.ndarray,  # [B] bool
        finite: np.ndarray,  # [B] bool
        grad_norm: np.ndarray,  # [B] ‖grad‖∞ at the final iterate
    """

    t: np.ndarray
    R: np.ndarray
    cost: np.ndarray
    terms: dict[str, np.ndarray]
    iterations: np.ndarray
    converged: np.ndarray
    finite: np.ndarray
    grad_norm: np.ndarray


def _band_index(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat source indices into hess[b].reshape(-1) ([n, 4, 6, 6]) and destinations into ab.reshape(-1) ([24, 6n])."""
    k, d, p, q = np.meshgrid(np.arange(n), np.arange(4), np.arange(6), np.arange(6), indexing="ij")
    i = 6 * k + p
    j = 6 * (k + d) + q
    keep = (k + d < n) & (i <= j)
    src = (((k * 4 + d) * 6 + p) * 6 + q)[keep]
    dst = ((_BAND_U + i - j) * (6 * n) + j)[keep]
    return src, dst


_BAND_CACHE: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def damping_metric(data: ObjectiveData) -> np.ndarray:
    """Constant damping matrix ``A`` [n, 4, 6, 6] (band blocks): the smoothness Hessian with identity increment
    Jacobians, ``2 M ⊗ I₃`` for translation (acc/jerk weights) and rotation (rot_acc/rot_jerk weights), plus a tiny
    multiple of I for definiteness. Damping with it (``H + λA``) makes large-λ steps CHOMP-like covariant
    gradient steps (smooth updates) instead of shrinking the weakly curved low-frequency modes to nothing; the
    Hessian spans ~9 decades, so neither ``λI`` nor Marquardt's ``λ diag(H)`` work well here."""
    cached = getattr(data, "_damping_A", None)
    if cached is not None:
        return cached

    T = data.T
    n = T - 2
    M_t, _ = smoothing_matrices(T, data.acc_w, data.jerk_w, 0.0, 0.0)
    M_r, _ = smoothing_matrices(T, data.rot_acc_w, data.rot_jerk_w, 0.0, 0.0)
    A = np.zeros((n, 4, 6, 6))
    for d in range(4):
        k = np.arange(n - d)
        for x in range(3):
            A[k, d, x, x] = 2.0 * M_t[k + 1, k + 1 + d]
            A[k, d, 3 + x, 3 + x] = 2.0 * M_r[k + 1, k + 1 + d]
    diag = np.diagonal(A[:, 0], axis1=-2, axis2=-1)
    eps = 1e-6 * float(diag.mean()) if diag.mean() > 0 else 1.0
    A[:, 0] += eps * np.eye(6)
    data._damping_A = A
    return A


def _band_matvec(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``A x`` for symmetric band blocks A [B or 1, n, 4, 6, 6] and x [B, n, 6]."""
    n = x.shape[1]
    y = np.einsum("bkij,bkj->bki", A[:, :, 0], x)
    for d in range(1, 4):
        if n - d <= 0:
            break
        y[:, : n - d] += np.einsum("bkij,bkj->bki", A[:, : n - d, d], x[:, d:])
        y[:, d:] += np.einsum("bkji,bkj->bki", A[:, : n - d, d], x[:, : n - d])
    return y


def _solve_banded(hess: np.ndarray, grad: np.ndarray, lam: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve ``(H + λA) δ = −g`` per trajectory (Cholesky in LAPACK band storage). Returns (δ [B, n, 6], ok [B])."""
    B, n = grad.shape[:2]
    if n not in _BAND_CACHE:
        _BAND_CACHE[n] = _band_index(n)
    src, dst = _BAND_CACHE[n]
    M = hess + lam[:, None, None, None, None] * A[None]
    ab = np.zeros((B, _BAND_U + 1, 6 * n))
    ab.reshape(B, -1)[:, dst] = M.reshape(B, -1)[:, src]
    rhs = -grad.reshape(B, -1)
    delta = np.zeros_like(rhs)
    ok = np.ones(B, dtype=bool)
    for b in range(B):
        try:
            delta[b] = solveh_banded(ab[b], rhs[b], overwrite_ab=True, check_finite=False)
        except (LinAlgError, ValueError):
            ok[b] = False
    ok &= np.isfinite(delta).all(axis=1)
    return delta.reshape(B, n, 6), ok


def _apply(t: np.ndarray, R: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t2 = t.copy()
    R2 = R.copy()
    t2[:, 1:-1] += delta[..., :3]
    R2[:, 1:-1] = _so3_exp(delta[..., 3:]) @ R[:, 1:-1]
    return t2, R2


def levenberg_marquardt(data: ObjectiveData, t: np.ndarray, R: np.ndarray, cfg: SolverConfig,
                        max_iterations: int | None = None, trace: list | None = None) -> LMResult:
    """Minimise the objective for B trajectories from their initial guesses (endpoints stay fixed).

    Args:
        data: the problem's objective data.
        t: np.ndarray,  # [B, T, 3] initial positions (t[:, 0], t[:, -1] are the fixed endpoints)
        R: np.ndarray,  # [B, T, 3, 3] initial rotations
        cfg: solver settings.
        max_iterations: overrides ``cfg.max_iterations`` (for iteration-budget studies).
        trace: if a list, one dict per iteration is appended (cost [B], λ [B], accepted mask, active mask).
    """
    max_it = cfg.max_iterations if max_iterations is None else int(max_iterations)
    t = np.array(t, dtype=np.float64)
    R = np.array(R, dtype=np.float64)
    B = t.shape[0]
    A = damping_metric(data)
    ev = evaluate(data, t, R, derivs=True)
    cost, grad, hess = ev.cost.copy(), ev.grad, ev.hess
    terms = {k: v.copy() for k, v in ev.terms.items()}
    lam = np.full(B, cfg.lambda_init)
    nu = np.full(B, 2.0)
    iters = np.zeros(B, dtype=np.int64)
    converged = np.zeros(B, dtype=bool)
    finite = np.isfinite(cost) & np.isfinite(grad).all(axis=(1, 2)) & np.isfinite(hess).all(axis=(1, 2, 3, 4))
    active = finite.copy()
    gnorm = np.abs(grad).max(axis=(1, 2))
    converged |= active & (gnorm <= cfg.gtol)
    active &= ~converged
    # stagnation window: at a kink of the objective (hinge onset, K-NN set change of the render prior) the GN
    # model is poor, λ grows and steps shrink; declare convergence when the cost fell by less than ftol
    # (relative) over the last LM_STAGNATION_WINDOW accepted steps.
    win_cost = cost.copy()
    n_acc = np.zeros(B, dtype=np.int64)  # accepted steps so far
    win_start = np.zeros(B, dtype=np.int64)
    for _ in range(max_it):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        delta, ok = _solve_banded(hess[idx], grad[idx], lam[idx], A)
        iters[idx] += 1
        t_new, R_new = _apply(t[idx], R[idx], delta)
        ev_new = evaluate(data, t_new, R_new, derivs=True)
        g = grad[idx].reshape(idx.size, -1)
        dl = delta.reshape(idx.size, -1)
        dAd = np.sum(_band_matvec(A[None], delta) * delta, axis=(1, 2))
        pred = -0.5 * np.sum(g * dl, axis=1) + 0.5 * lam[idx] * dAd
        actual = cost[idx] - ev_new.cost
        fin_new = (np.isfinite(ev_new.cost) & np.isfinite(ev_new.grad).all(axis=(1, 2))
                   & np.isfinite(ev_new.hess).all(axis=(1, 2, 3, 4)))
        gain = np.where(pred > 0, actual / np.where(pred > 0, pred, 1.0), -1.0)
        accept = ok & fin_new & (actual > 0) & (gain > LM_MIN_GAIN)
        a = idx[accept]
        if a.size:
            rel = actual[accept] / np.maximum(cost[a], 1e-300)
            step = np.abs(dl[accept]).max(axis=1)
            undamped = lam[a] <= LM_CONVERGED_LAMBDA  # the step was (close to) a full Gauss–Newton step
            t[a], R[a] = t_new[accept], R_new[accept]
            cost[a] = ev_new.cost[accept]
            grad[a], hess[a] = ev_new.grad[accept], ev_new.hess[accept]
            for k in TERM_NAMES:
                terms[k][a] = ev_new.terms[k][accept]
            lam[a] *= np.maximum(1.0 / 3.0, 1.0 - (2.0 * gain[accept] - 1.0) ** 3)  # Nielsen's update
            nu[a] = 2.0
            n_acc[a] += 1
            gnorm[a] = np.abs(ev_new.grad[accept]).max(axis=(1, 2))
            done = (undamped & ((rel <= cfg.ftol) | (step <= cfg.xtol))) | (gnorm[a] <= cfg.gtol)
            converged[a[done]] = True
            active[a[done]] = False
        r = idx[~accept]
        if r.size:
            lam[r] *= nu[r]
            nu[r] *= 2.0
            stalled = lam[r] > cfg.lambda_max
            converged[r[stalled]] = True  # no decrease possible at machine precision: a stationary point
            active[r[stalled]] = False
        if trace is not None:
            acc_mask = np.zeros(B, dtype=bool)
            acc_mask[a] = True
            trace.append({"cost": cost.copy(), "lam": lam.copy(), "accepted": acc_mask, "active": active.copy()})
        w = idx[active[idx] & (n_acc[idx] - win_start[idx] >= LM_STAGNATION_WINDOW)]
        if w.size:
            stag = (win_cost[w] - cost[w]) <= cfg.ftol * np.abs(win_cost[w])
            converged[w[stag]] = True
            active[w[stag]] = False
            win_cost[w], win_start[w] = cost[w], n_acc[w]
    return LMResult(t=t, R=R, cost=cost, terms=terms, iterations=iters, converged=converged,
                    finite=finite & np.isfinite(t).all(axis=(1, 2)) & np.isfinite(R).all(axis=(1, 2, 3)),
                    grad_norm=gnorm)
