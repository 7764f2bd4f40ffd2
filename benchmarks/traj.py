"""Trajectory-stage benchmark (issue #6): speed, success, clearance, endpoint error, error vs run time.

Run (2 shared CPU cores; set the thread variables BEFORE Python starts numpy)::

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/traj.py            # 1000 problems per mode
    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/traj.py --n 128    # quick look

Setup: the fixed analytic tabletop scene of :mod:`umi_aug.traj.synthetic` (table, mug + handle, plate, two
distractors), its mug-handle demo (59.94 fps, contact after 2.2 s), 160 scan views + the demo as render views;
starts sampled in the paper's cone (θ = 50°, r = 0.15 m), T = 64 waypoints. Obstacle mode adds a 12 cm box
between the start region and the mug (inflated 1 cm): every straight-line guess and the demo itself pass through
it, so every problem needs RRT*.

Tables (printed, never asserted):
1. pipeline per mode at batch 64 and batch 1: ms per trajectory (median / p95) for the solve (start checks +
   initial guess incl. RRT* + LM) and in total (+ retiming, splicing, validation). At batch 64 every trajectory
   of a batch gets the batch's wall time / 64 (amortised), so the p95 there is over batches;
   LM iterations; success rate over all problems and over problems with a feasible start; status counts;
   min clearance over every emitted trajectory (and how many are below the margin); max endpoint error.
2. error vs run time: LM from the same initial guesses with iteration budgets, vs a long-run reference (LM,
   300 iterations, ftol 1e-12): cost gap (relative, median / p95 / max), constraint violation (largest shortfall
   of the required clearance at the waypoints, and the fraction of trajectories violating it), ms per trajectory.
3. cross-check of the LM optimum against an independent optimiser (scipy L-BFGS-B, preconditioned) on a few
   problems.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

for _v, _n in (("OPENBLAS_NUM_THREADS", "1"), ("OMP_NUM_THREADS", "1"), ("MKL_NUM_THREADS", "1")):
    os.environ.setdefault(_v, _n)

import numpy as np  # noqa: E402
import scipy  # noqa: E402

from umi_aug.traj import (  # noqa: E402
    ConvexObstacle,
    SolverConfig,
    TrajProblem,
    TrajScene,
    TrajStatus,
    plot_trajectories,
    solve,
)
from umi_aug.traj.generate import finish_batch  # noqa: E402
from umi_aug.traj._ref import _solve_scipy_reference as solve_scipy_reference  # noqa: E402
from umi_aug.traj.plan import validate_waypoints  # noqa: E402
from umi_aug.traj.solver import levenberg_marquardt  # noqa: E402
from umi_aug.traj.synthetic import SyntheticTabletop  # noqa: E402

THETA = np.radians(50.0)
RADIUS = 0.15


def format_table(rows: list[dict], columns: list[str]) -> str:
    """Plain-text table: one row per dict, the given columns (floats with 4 significant digits)."""
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    cells = [[fmt(r.get(c, "")) for c in columns] for r in rows]
    w = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    line = "  ".join(c.ljust(w[i]) for i, c in enumerate(columns))
    sep = "  ".join("-" * w[i] for i in range(len(columns)))
    body = ["  ".join(row[i].ljust(w[i]) for i in range(len(columns))) for row in cells]
    return "\n".join([line, sep, *body])


def build(mode: str) -> TrajProblem:
    st = SyntheticTabletop.build(seed=0)
    obstacle = ConvexObstacle(st.obstacle_points, 0.01) if mode == "obstacle" else None
    return TrajProblem(st.demo, TrajScene(st.sdf, st.render_views, obstacle))


def pipeline(pb: TrajProblem, x: np.ndarray, batch: int, seed: int) -> dict:
    """Solve + finish in chunks of ``batch``; per-trajectory timings and outcomes."""
    solve_ms, total_ms, iters, statuses, clear, end_err, feasible, kept = [], [], [], [], [], [], [], []
    rng = np.random.default_rng(seed)
    t_all = time.perf_counter()
    for i0 in range(0, len(x), batch):
        xb = x[i0:i0 + batch]
        t0 = time.perf_counter()
        res = solve(pb, xb, rng)
        t1 = time.perf_counter()
        eps, reps = finish_batch(pb, xb, res)
        t2 = time.perf_counter()
        kept.extend(e for e in eps if e is not None and len(kept) < 50)
        for b, rep in enumerate(reps):
            statuses.append(rep.status)
            feasible.append(res.status[b] != TrajStatus.INFEASIBLE_START)
            iters.append(rep.iterations)
            solve_ms.append((t1 - t0) / len(xb) * 1e3)
            total_ms.append((t2 - t0) / len(xb) * 1e3)
            if rep.status == "converged":
                clear.append(rep.min_clearance)
                end_err.append(max(rep.start_error, rep.goal_error))
    return dict(solve_ms=np.array(solve_ms), total_ms=np.array(total_ms), iters=np.array(iters),
                status=np.array(statuses), feasible=np.array(feasible), clearance=np.array(clear),
                endpoint_error=np.array(end_err), wall_s=time.perf_counter() - t_all, episodes=kept)


def pipeline_row(mode: str, batch: int, r: dict, margin: float) -> dict:
    ok = r["status"] == "converged"
    counts = {s: int(np.sum(r["status"] == s)) for s in sorted(set(r["status"]))}
    return {
        "mode": mode, "batch": batch, "n": len(ok),
        "solve_ms_p50": float(np.median(r["solve_ms"])), "solve_ms_p95": float(np.percentile(r["solve_ms"], 95)),
        "total_ms_p50": float(np.median(r["total_ms"])), "total_ms_p95": float(np.percentile(r["total_ms"], 95)),
        "wall_ms_per_traj": r["wall_s"] / len(ok) * 1e3,
        "iters_p50": float(np.median(r["iters"][ok])) if ok.any() else float("nan"),
        "iters_p95": float(np.percentile(r["iters"][ok], 95)) if ok.any() else float("nan"),
        "success": float(ok.mean()), "success_feasible": float(ok[r["feasible"]].mean()) if r["feasible"].any() else float("nan"),
        "min_clear_mm": float(r["clearance"].min() * 1e3) if ok.any() else float("nan"),
        "below_margin": int(np.sum(r["clearance"] < margin)),
        "endpoint_err": float(r["endpoint_error"].max()) if ok.any() else float("nan"),
        "statuses": " ".join(f"{k}:{v}" for k, v in counts.items()),
    }


def budgets_table(pb: TrajProblem, x: np.ndarray, budgets: list[int], seed: int, batch: int = 64) -> list[dict]:
    """Error vs run time of the LM from fixed initial guesses."""
    init_res = solve(pb, x, np.random.default_rng(seed), max_iterations=0)
    keep = np.array([s in (TrajStatus.CONVERGED, TrajStatus.ITERATION_LIMIT, TrajStatus.COLLISION)
                     for s in init_res.status])  # feasible start and an initial guess
    X0 = init_res.T_world_cam[keep]
    data = pb.objective_data

    def run(cfg: SolverConfig, max_it: int | None):
        t, R, costs, its = [], [], [], []
        t0 = time.perf_counter()
        for i0 in range(0, len(X0), batch):
            Xb = X0[i0:i0 + batch]
            r = levenberg_marquardt(data, Xb[:, :, :3, 3], Xb[:, :, :3, :3], cfg, max_it)
            t.append(r.t)
            R.append(r.R)
            costs.append(r.cost)
            its.append(r.iterations)
        ms = (time.perf_counter() - t0) / len(X0) * 1e3
        X = X0.copy()
        X[:, :, :3, 3] = np.concatenate(t)
        X[:, :, :3, :3] = np.concatenate(R)
        return X, np.concatenate(costs), np.concatenate(its), ms

    ref_cfg = SolverConfig(max_iterations=300, ftol=1e-12, xtol=1e-14)
    Xref, cref, itref, msref = run(ref_cfg, None)
    rows = []
    for label, cfg, mi in ([(f"{b} it", pb.config.solver, b) for b in budgets]
                           + [("default (converged)", pb.config.solver, None), ("reference (300 it, ftol 1e-12)", ref_cfg, None)]):
        X, c, its, ms = (Xref, cref, itref, msref) if label.startswith("reference") else run(cfg, mi)
        gap = (c - cref) / np.maximum(cref, 1e-300)
        chk = validate_waypoints(pb, X)
        shortfall = np.maximum(0.0, -np.minimum(chk.scene_slack, chk.obstacle_slack))
        viol = ~chk.ok
        rows.append({"budget": label, "n": len(X0), "ms_per_traj": ms, "iters_mean": float(its.mean()),
                     "gap_p50": float(np.median(gap)), "gap_p95": float(np.percentile(gap, 95)),
                     "gap_max": float(gap.max()), "gap_min": float(gap.min()),
                     "violation_max_mm": float(shortfall.max() * 1e3), "violating_frac": float(viol.mean())})
    return rows


def scipy_table(pb: TrajProblem, x: np.ndarray, seed: int) -> list[dict]:
    init = solve(pb, x, np.random.default_rng(seed), max_iterations=0)
    X0 = init.T_world_cam
    rows = []
    r = levenberg_marquardt(pb.objective_data, X0[:, :, :3, 3], X0[:, :, :3, :3], pb.config.solver)
    for b in range(len(X0)):
        t0 = time.perf_counter()
        _, cs, nit = solve_scipy_reference(pb.objective_data, X0[b])
        rows.append({"problem": b, "lm_cost": float(r.cost[b]), "lm_iters": int(r.iterations[b]),
                     "lbfgs_cost": cs, "lbfgs_iters": nit, "lbfgs_s": time.perf_counter() - t0,
                     "lm_minus_lbfgs_rel": (float(r.cost[b]) - cs) / cs})
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1000, help="problems per mode")
    ap.add_argument("--n-batch1", type=int, default=None, help="problems for the batch-1 timing (default: n)")
    ap.add_argument("--n-budget", type=int, default=None, help="problems for the error-vs-time table (default: n)")
    ap.add_argument("--budgets", type=int, nargs="+", default=[3, 5, 10, 20])
    ap.add_argument("--n-scipy", type=int, default=6)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--modes", nargs="+", default=["free", "obstacle"])
    ap.add_argument("--plot-dir", default=None, help="write traj_<mode>.png (first 50 emitted episodes) here")
    args = ap.parse_args(argv)
    print(f"# traj benchmark  python {platform.python_version()}  numpy {np.__version__}  scipy {scipy.__version__}  "
          f"cpus {os.cpu_count()} (affinity {len(os.sched_getaffinity(0))})  "
          f"OMP={os.environ.get('OMP_NUM_THREADS')} OPENBLAS={os.environ.get('OPENBLAS_NUM_THREADS')}")
    print(f"# theta = 50 deg, r = {RADIUS} m, T = 64, n = {args.n} problems per mode, seed {args.seed}\n")
    rows, budget_rows, scipy_rows = [], {}, {}
    for mode in args.modes:
        pb = build(mode)
        x = pb.sample_starts(args.n, args.seed, THETA, RADIUS)
        solve(pb, x[:2], 0)  # warm caches (scene grid, band indices) outside the timings
        r64 = pipeline(pb, x, 64, args.seed)
        rows.append(pipeline_row(mode, 64, r64, pb.config.margin))
        if args.plot_dir:
            out = plot_trajectories(os.path.join(args.plot_dir, f"traj_{mode}.png"), pb, r64["episodes"],
                                    title=f"{mode}: {len(r64['episodes'])} of {args.n} augmented (θ = 50°, r = {RADIUS} m)")
            print(f"# wrote {out}")
        n1 = args.n_batch1 or args.n
        r1 = pipeline(pb, x[:n1], 1, args.seed)
        rows.append(pipeline_row(mode, 1, r1, pb.config.margin))
        print(format_table(rows[-2:], ["mode", "batch", "n", "solve_ms_p50", "solve_ms_p95", "total_ms_p50",
                                       "total_ms_p95", "iters_p50", "success", "success_feasible"]), flush=True)
        nb = args.n_budget or args.n
        budget_rows[mode] = budgets_table(pb, x[:nb], args.budgets, args.seed)
        scipy_rows[mode] = scipy_table(pb, x[: args.n_scipy], args.seed)
        print(flush=True)
    print("\n## 1. pipeline (ms per trajectory; batch 64 = amortised over the batch)")
    print(format_table(rows, ["mode", "batch", "n", "solve_ms_p50", "solve_ms_p95", "total_ms_p50", "total_ms_p95",
                              "wall_ms_per_traj", "iters_p50", "iters_p95"]))
    print()
    print(format_table(rows, ["mode", "batch", "success", "success_feasible", "min_clear_mm", "below_margin",
                              "endpoint_err", "statuses"]))
    for mode, br in budget_rows.items():
        print(f"\n## 2. error vs run time, {mode} (LM from the same initial guesses, batch 64)")
        print(format_table(br, ["budget", "n", "ms_per_traj", "iters_mean", "gap_p50", "gap_p95", "gap_max", "gap_min",
                                "violation_max_mm", "violating_frac"]))
    for mode, sr in scipy_rows.items():
        print(f"\n## 3. LM vs scipy L-BFGS-B (preconditioned), {mode}")
        print(format_table(sr, ["problem", "lm_cost", "lm_iters", "lbfgs_cost", "lbfgs_iters", "lbfgs_s",
                                "lm_minus_lbfgs_rel"]))


if __name__ == "__main__":
    main(sys.argv[1:])
