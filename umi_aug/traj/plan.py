"""Solve a batch of trajectory problems: start checks, initial guesses, batched LM, exact validation.

``solve`` returns optimised waypoints with a per-trajectory :class:`TrajStatus`; nothing here raises for a
single bad trajectory (it is reported). :func:`plan` is the one-start convenience that raises
:class:`TrajError` when that start is infeasible.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from umi_aug.errors import TrajError
from umi_aug.geometry import rotation_geodesic_distance
from umi_aug.traj.constants import DEGENERATE_TOL
from umi_aug.traj.init_guess import rrt_guess, straight_line_guess
from umi_aug.traj.objective import TERM_NAMES
from umi_aug.traj.problem import TrajProblem
from umi_aug.traj.solver import TrajStatus, levenberg_marquardt

__all__ = ["SolveResult", "solve", "plan", "check_starts", "validate_waypoints", "WaypointCheck"]

log = logging.getLogger(__name__)


@dataclass
class WaypointCheck:
    """Exact validation of waypoint trajectories ``[B, T, 4, 4]`` (or frame sequences).

    Attributes:
        scene_slack: np.ndarray,  # [B] min over frames/spheres of clearance − required clearance (m; >= 0 is ok)
        obstacle_slack: np.ndarray,  # [B] min of obstacle clearance − margin (+inf without obstacle)
        hull_hit: np.ndarray,  # [B] bool: a sphere chord between consecutive frames touches the inflated hull
        lipschitz_ok: np.ndarray,  # [B] bool: no sphere can penetrate the scene between consecutive frames
        min_clearance: np.ndarray,  # [B] min over frames/spheres of the scene and obstacle clearance (m)
    """

    scene_slack: np.ndarray
    obstacle_slack: np.ndarray
    hull_hit: np.ndarray
    lipschitz_ok: np.ndarray
    min_clearance: np.ndarray

    @property
    def ok(self) -> np.ndarray:
        return (self.scene_slack >= 0) & (self.obstacle_slack >= 0) & ~self.hull_hit & self.lipschitz_ok


def validate_waypoints(problem: TrajProblem, X: np.ndarray, s: np.ndarray | None = None) -> WaypointCheck:
    """Check trajectories against the margins (at the frames) and the inflated hull (exactly, on the chords).

    Args:
        X: np.ndarray,  # [B, N, 4, 4] camera poses
        s: np.ndarray | None,  # [B, N] or [N] path progress in [0, 1] (default: uniform); selects the contact tail
    """
    B, N = X.shape[:2]
    if s is None:
        s = np.linspace(0.0, 1.0, N)
    s = np.broadcast_to(s, (B, N))
    clr = problem.sphere_clearance(X)  # [B, N, S]
    req = problem.required_clearance(s)  # [B, N, S]
    scene_slack = (clr - req).min(axis=(1, 2))
    pts = problem.sphere_points(X)  # [B, N, S, 3]
    step = np.linalg.norm(np.diff(pts, axis=1), axis=-1)  # [B, N-1, S]
    # 1-Lipschitz SDF: along a chord of length L the distance drops by at most L/2 below the ends' minimum
    lip = np.minimum(clr[:, :-1], clr[:, 1:]) - 0.5 * step
    lip_req = np.minimum(req[:, :-1], req[:, 1:])
    lipschitz_ok = np.all(lip >= np.minimum(0.0, lip_req) - 1e-12, axis=(1, 2))
    min_clr = clr.min(axis=(1, 2))
    if problem.obstacle is not None:
        oc = problem.obstacle_clearance(X)
        obstacle_slack = (oc - problem.config.margin).min(axis=(1, 2))
        hull_hit = problem.obstacle.segments_intersect(pts[:, :-1], pts[:, 1:], problem.spheres.radii).any(axis=(1, 2))
        hull_hit |= problem.obstacle.contains(pts, problem.spheres.radii).any(axis=(1, 2))
        min_clr = np.minimum(min_clr, oc.min(axis=(1, 2)))
    else:
        obstacle_slack = np.full(B, np.inf)
        hull_hit = np.zeros(B, dtype=bool)
    return WaypointCheck(scene_slack, obstacle_slack, hull_hit, lipschitz_ok, min_clr)


def check_starts(problem: TrajProblem, x_init: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Feasibility of start poses ``[B, 4, 4]``: every sphere at least the margin from the scene and outside the
    inflated hull by the margin. Returns (ok [B], reason per start ('' when ok))."""
    clr = problem.sphere_clearance(x_init).min(axis=-1)
    ok = clr >= problem.config.margin
    reasons = ["" if o else f"start clearance {c:.4f} m < margin {problem.config.margin} m (scene)"
               for o, c in zip(ok, clr)]
    if problem.obstacle is not None:
        pts = problem.sphere_points(x_init)
        inside = problem.obstacle.contains(pts, problem.spheres.radii).any(axis=-1)
        oc = problem.obstacle_clearance(x_init).min(axis=-1)
        for b in range(len(ok)):
            if inside[b]:
                reasons[b] = "start is inside the inflated obstacle hull"
            elif oc[b] < problem.config.margin and not reasons[b]:
                reasons[b] = f"start is {oc[b]:.4f} m from the inflated obstacle (< margin {problem.config.margin} m)"
        ok &= oc >= problem.config.margin
    return ok, reasons


@dataclass
class SolveResult:
    """Optimised waypoints and per-trajectory outcome.

    Attributes:
        T_world_cam: np.ndarray,  # [B, T, 4, 4] (for failed starts: the initial guess or the start repeated)
        status: list[TrajStatus]  # [B]
        reason: list[str]  # [B] human-readable detail ('' when converged)
        iterations: np.ndarray,  # [B] LM iterations
        solve_time_s: np.ndarray,  # [B] wall time of the trajectory's batch / batch size (amortised), incl. RRT*
        cost: np.ndarray,  # [B]
        terms: dict[str, np.ndarray],  # [B] each
        check: WaypointCheck
        used_rrt: np.ndarray,  # [B] bool
    """

    T_world_cam: np.ndarray
    status: list
    reason: list
    iterations: np.ndarray
    solve_time_s: np.ndarray
    cost: np.ndarray
    terms: dict
    check: WaypointCheck
    used_rrt: np.ndarray


def solve(problem: TrajProblem, x_init: np.ndarray, rng: np.random.Generator | int = 0,
          init: np.ndarray | None = None, max_iterations: int | None = None) -> SolveResult:
    """Optimise trajectories from ``x_init`` to the problem's ``x_goal``.

    Args:
        problem: the per-demo problem.
        x_init: np.ndarray,  # [B, 4, 4] start camera poses
        rng: seed / generator for RRT* (obstacle mode); same seed → same result.
        init: np.ndarray | None,  # [B, T, 4, 4] initial guesses (default: straight line, or RRT* with obstacle)
        max_iterations: override of the solver's iteration limit.
    """
    x_init = np.asarray(x_init, dtype=np.float64)
    if x_init.ndim != 3 or x_init.shape[1:] != (4, 4) or not np.isfinite(x_init).all():
        raise TrajError(f"solve: `x_init` must be finite [B, 4, 4], got {x_init.shape}")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    cfg = problem.config
    B, T = x_init.shape[0], problem.T
    goal = problem.x_goal
    status: list = [TrajStatus.CONVERGED] * B
    reason = [""] * B
    X = np.empty((B, T, 4, 4))
    used_rrt = np.zeros(B, dtype=bool)
    times = np.zeros(B)
    ok, why = check_starts(problem, x_init)
    for b in np.flatnonzero(~ok):
        status[b], reason[b] = TrajStatus.INFEASIBLE_START, why[b]
    # initial guesses
    t0 = time.perf_counter()
    if init is not None:
        init = np.asarray(init, dtype=np.float64)
        if init.shape != (B, T, 4, 4):
            raise TrajError(f"solve: `init` has shape {init.shape}; expected {(B, T, 4, 4)}")
        X[:] = init
        X[:, 0], X[:, -1] = x_init, goal
    else:
        X[:] = straight_line_guess(x_init, goal, T)
        if problem.obstacle is not None:
            seeds = gen.integers(0, 2**63 - 1, size=B)
            for b in np.flatnonzero(ok):
                tb = time.perf_counter()
                g = rrt_guess(problem, x_init[b], np.random.default_rng(seeds[b]))
                times[b] += time.perf_counter() - tb
                if g is None:
                    status[b], reason[b] = TrajStatus.PLANNER_FAILED, "RRT* found no path around the inflated obstacle"
                    ok[b] = False
                else:
                    used_rrt[b] = not np.allclose(g, X[b])
                    X[b] = g
    # degenerate: start == goal → constant trajectory
    dist = (np.linalg.norm(x_init[:, :3, 3] - goal[:3, 3], axis=-1)
            + rotation_geodesic_distance(x_init[:, :3, :3], goal[:3, :3]))
    degenerate = ok & (dist <= DEGENERATE_TOL)
    X[degenerate] = goal
    X[degenerate, 0] = x_init[degenerate]
    iters = np.zeros(B, dtype=np.int64)
    cost = np.zeros(B)
    terms = {k: np.zeros(B) for k in TERM_NAMES}
    todo = np.flatnonzero(ok & ~degenerate)
    bs = cfg.solver.batch_size
    for i0 in range(0, todo.size, bs):
        idx = todo[i0:i0 + bs]
        tb = time.perf_counter()
        res = levenberg_marquardt(problem.objective_data, X[idx, :, :3, 3], X[idx, :, :3, :3], cfg.solver,
                                  max_iterations)
        times[idx] += (time.perf_counter() - tb) / idx.size
        X[idx, :, :3, 3], X[idx, :, :3, :3] = res.t, res.R
        X[idx, 0], X[idx, -1] = x_init[idx], goal  # endpoints are never variables; keep them bit-exact
        iters[idx], cost[idx] = res.iterations, res.cost
        for k in TERM_NAMES:
            terms[k][idx] = res.terms[k]
        for j, b in enumerate(idx):
            if not res.finite[j]:
                status[b], reason[b] = TrajStatus.NUMERICAL, "non-finite values in the optimisation"
            elif not res.converged[j]:
                status[b], reason[b] = TrajStatus.ITERATION_LIMIT, f"not converged in {res.iterations[j]} iterations"
    check = validate_waypoints(problem, X)
    finite = np.isfinite(X).all(axis=(1, 2, 3))
    for b in range(B):
        if not ok[b] and status[b] != TrajStatus.CONVERGED:
            continue
        if not finite[b]:
            status[b], reason[b] = TrajStatus.NUMERICAL, "non-finite waypoints"
        elif not check.ok[b] and status[b] in (TrajStatus.CONVERGED, TrajStatus.ITERATION_LIMIT):
            status[b] = TrajStatus.COLLISION
            reason[b] = (f"scene slack {check.scene_slack[b]:.4f} m, obstacle slack {check.obstacle_slack[b]:.4f} m, "
                         f"hull hit {bool(check.hull_hit[b])}, lipschitz ok {bool(check.lipschitz_ok[b])}")
    log.debug("solve: %d trajectories in %.3f s", B, time.perf_counter() - t0)
    return SolveResult(X, status, reason, iters, times, cost, terms, check, used_rrt)


def plan(problem: TrajProblem, x_init: np.ndarray, rng: np.random.Generator | int = 0) -> np.ndarray:
    """One trajectory ``[T, 4, 4]`` from ``x_init`` [4, 4]; raises :class:`TrajError` with the reason when the start
    is infeasible (e.g. inside the inflated obstacle) or the result is not a valid converged trajectory."""
    x_init = np.asarray(x_init, dtype=np.float64)
    if x_init.shape != (4, 4):
        raise TrajError(f"plan: `x_init` must be [4, 4], got {x_init.shape}")
    ok, why = check_starts(problem, x_init[None])
    if not ok[0]:
        raise TrajError(f"plan: infeasible start pose: {why[0]}")
    res = solve(problem, x_init[None], rng)
    st = res.status[0]
    if st != TrajStatus.CONVERGED and not (st == TrajStatus.ITERATION_LIMIT and problem.config.solver.accept_iteration_limit):
        raise TrajError(f"plan: trajectory failed with status '{st.value}': {res.reason[0]}")
    return res.T_world_cam[0]
