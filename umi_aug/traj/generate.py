"""The driver: sample starts, solve in batches, retime and splice, validate, resample failures.

:func:`generate` returns exactly ``n`` valid augmented episodes or raises :class:`TrajError` after a bounded
number of rounds (it never hangs: every round is bounded — LM iterations, RRT* iterations, retiming stretches —
and the number of rounds is capped). Deterministic: the same seed gives the same episodes.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from umi_aug.errors import TrajError
from umi_aug.traj.constants import MAX_ROUNDS, OVERSAMPLE
from umi_aug.traj.plan import SolveResult, solve, validate_waypoints
from umi_aug.traj.problem import TrajProblem
from umi_aug.traj.report import TrajReport, render_prior_distance
from umi_aug.traj.solver import TrajStatus
from umi_aug.traj.splice import AugmentedEpisode, time_and_splice

__all__ = ["GenerateResult", "generate", "finish_batch"]

log = logging.getLogger(__name__)


@dataclass
class GenerateResult:
    """Output of :func:`generate`.

    Attributes:
        episodes: list[AugmentedEpisode]  # exactly n, in sampling order
        reports: list[TrajReport]  # one per emitted episode (same order)
        attempts: list[TrajReport]  # every sampled problem, including failures
        status_counts: dict[str, int]
        rounds: int
        wall_time_s: float
    """

    episodes: list
    reports: list
    attempts: list = field(default_factory=list)
    status_counts: dict = field(default_factory=dict)
    rounds: int = 0
    wall_time_s: float = 0.0


def finish_batch(problem: TrajProblem, x_init: np.ndarray, res: SolveResult, index0: int = 0
                 ) -> tuple[list[AugmentedEpisode | None], list[TrajReport]]:
    """Retime + splice every solved trajectory, validate the emitted frames, and build the reports.

    A trajectory is emitted only when it converged (or hit the iteration limit with
    ``accept_iteration_limit``), its frames keep every sphere at the required clearance, no sphere chord between
    frames touches the inflated hull, the retimed motion is within the speed/accel bounds, and all values are
    finite.
    """
    cfg = problem.config
    eps: list[AugmentedEpisode | None] = []
    reps: list[TrajReport] = []
    for b in range(x_init.shape[0]):
        st = res.status[b]
        rep = TrajReport(index=index0 + b, status=st.value, reason=res.reason[b], iterations=int(res.iterations[b]),
                         solve_time_s=float(res.solve_time_s[b]), cost=float(res.cost[b]),
                         terms={k: float(v[b]) for k, v in res.terms.items()}, used_rrt=bool(res.used_rrt[b]))
        emit_ok = st == TrajStatus.CONVERGED or (st == TrajStatus.ITERATION_LIMIT and cfg.solver.accept_iteration_limit)
        if not emit_ok:
            eps.append(None)
            reps.append(rep)
            continue
        t0 = time.perf_counter()
        ep, timing = time_and_splice(problem.demo, res.T_world_cam[b], cfg.timing)
        n = ep.splice_index
        pre = ep.T_world_cam[: n + 1]
        chk = validate_waypoints(problem, pre[None], ep.progress[None])
        rep.min_clearance = float(chk.min_clearance[0])
        rep.required_clearance = float(problem.required_clearance(ep.progress).min())
        rep.max_speed, rep.max_accel = timing.max_speed, timing.max_accel
        rep.max_ang_speed, rep.max_ang_accel = timing.max_ang_speed, timing.max_ang_accel
        rep.max_jerk, rep.rms_jerk = timing.max_jerk, timing.rms_jerk
        rd = render_prior_distance(problem, pre)
        rep.render_distance_mean, rep.render_distance_max = float(rd.mean()), float(rd.max())
        rep.start_error = float(np.abs(pre[0] - x_init[b]).max())
        rep.goal_error = float(np.abs(pre[-1] - problem.x_goal).max())
        rep.splice_velocity_jump = timing.splice_velocity_jump
        rep.splice_ang_velocity_jump = timing.splice_ang_velocity_jump
        rep.blend_max_offset, rep.duration_s, rep.n_frames = timing.blend_max_offset, timing.duration_s, len(ep.timestamps)
        finite = all(np.isfinite(a).all() for a in (ep.T_world_cam, ep.actions, ep.timestamps, ep.gripper_width))
        if not finite:
            rep.status, rep.reason = TrajStatus.NUMERICAL.value, "non-finite values after retiming"
        elif not chk.ok[0]:
            rep.status = TrajStatus.COLLISION.value
            rep.reason = (f"retimed frames: scene slack {chk.scene_slack[0]:.4f} m, obstacle slack "
                          f"{chk.obstacle_slack[0]:.4f} m, hull hit {bool(chk.hull_hit[0])}")
        elif not timing.within_bounds:
            rep.status = TrajStatus.TIMING_FAILED.value
            rep.reason = (f"speed {timing.max_speed:.3f} m/s, accel {timing.max_accel:.3f} m/s², ang speed "
                          f"{timing.max_ang_speed:.3f} rad/s, ang accel {timing.max_ang_accel:.3f} rad/s² after "
                          f"{timing.stretch_steps} stretches")
        rep.total_time_s = rep.solve_time_s + (time.perf_counter() - t0)
        ok = rep.status in (TrajStatus.CONVERGED.value, TrajStatus.ITERATION_LIMIT.value)
        eps.append(ep if ok else None)
        reps.append(rep)
    return eps, reps


def generate(problem: TrajProblem, n: int, seed: int, half_angle: float, radius: float,
             pivot: np.ndarray | None = None, max_extra_rotation: float = 0.0, max_rounds: int = MAX_ROUNDS,
             oversample: float = OVERSAMPLE) -> GenerateResult:
    """Generate exactly ``n`` augmented episodes from the problem's demo.

    Each round samples ``ceil(missing · oversample)`` start poses in the θ-cone (``half_angle`` radians, sphere
    radius ``radius`` metres; see :meth:`TrajProblem.sample_starts`), solves them in batches, retimes, splices and
    validates them; failures are reported (``attempts``) and replaced in the next round.

    Raises:
        TrajError: fewer than ``n`` valid episodes after ``max_rounds`` rounds (the message gives the status
            counts, e.g. an obstacle blocking every path shows as ``planner_failed``/``collision``).
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise TrajError(f"generate: n = {n!r}; expected an int >= 1")
    if max_rounds < 1 or oversample < 1.0:
        raise TrajError(f"generate: max_rounds = {max_rounds}, oversample = {oversample}; expected >= 1")
    t_start = time.perf_counter()
    episodes: list[AugmentedEpisode] = []
    reports: list[TrajReport] = []
    attempts: list[TrajReport] = []
    rounds = 0
    for rnd in range(max_rounds):
        missing = n - len(episodes)
        if missing <= 0:
            break
        rounds += 1
        rng = np.random.default_rng([int(seed), rnd])
        m = max(1, math.ceil(missing * oversample))
        x_init = problem.sample_starts(m, rng, half_angle, radius, pivot, max_extra_rotation)
        res = solve(problem, x_init, rng)
        eps, reps = finish_batch(problem, x_init, res, index0=len(attempts))
        attempts.extend(reps)
        for ep, rep in zip(eps, reps):
            if ep is not None and len(episodes) < n:
                episodes.append(ep)
                reports.append(rep)
        log.info("generate: round %d: %d/%d valid (%d/%d total)", rnd, sum(e is not None for e in eps), m,
                 len(episodes), n)
    counts = dict(Counter(r.status for r in attempts))
    if len(episodes) < n:
        raise TrajError(f"generate: only {len(episodes)} of {n} valid trajectories after {rounds} rounds "
                        f"({len(attempts)} sampled problems; status counts {counts}). Typical causes: the added "
                        f"obstacle blocks every path to the pre-contact pose (planner_failed / collision), the cone "
                        f"puts starts inside the scene (infeasible_start), or the speed bounds are too tight "
                        f"(timing_failed).")
    return GenerateResult(episodes, reports, attempts, counts, rounds, time.perf_counter() - t_start)
