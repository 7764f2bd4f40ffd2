"""Numerical stability and speed of the Kannala–Brandt fisheye model (umi_aug.camera.kb / kb_torch).

Run: ``OMP_NUM_THREADS=1 python benchmarks/camera_stability.py [--n-timing 1000000] [--threads 1]``

Tables:
1. Round trips per angle case (theta = 0, 1e-12, 1e-6, 45, 89.9, 90, 100 deg, fold-over - 1e-6, fold-over, and
   pixels outside the image circle), for UMI's GoPro intrinsics at 224x224 (policy) and at 2704x2028:
   max pixel->ray->pixel error (px) and ray->pixel->ray error (rad) in float64 (numpy) and float32 (torch),
   Newton iterations (max/mean), the validity flag and whether any NaN appeared.
2. Error against iteration count: max |theta error| after 1..8 guarded-Newton updates over a dense theta sweep.
3. Error against run time: microseconds per point for 1e6 pixels / rays, and ratios to OpenCV's
   cv2.fisheye.distortPoints / projectPoints (and undistortPoints) timed in the same process.
4. The SO(3) stability rows of ``benchmarks/so3_stability.py`` when that script exists.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from umi_aug.camera import kb  # noqa: E402
from umi_aug.camera.calib_io import gopro_intrinsics_2_7k  # noqa: E402
from umi_aug.camera.intrinsics import FisheyeIntrinsics  # noqa: E402


# ---------------------------------------------------------------------------------------------- helpers
def _rays(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    theta, phi = np.broadcast_arrays(theta, phi)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1))


def _fmt(x: Any) -> str:
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else "no"
    if isinstance(x, str):
        return x
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if x == 0:
        return "0"
    return f"{x:.2e}" if (abs(x) < 1e-2 or abs(x) >= 1e4) else f"{x:.3f}"


def print_table(title: str, header: list[str], rows: list[list[Any]]) -> None:
    cells = [header] + [[_fmt(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    print(f"\n## {title}\n")
    print("| " + " | ".join(h.ljust(w) for h, w in zip(header, widths)) + " |")
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for r in cells[1:]:
        print("| " + " | ".join(c.rjust(w) for c, w in zip(r, widths)) + " |")


def _cases(intr: FisheyeIntrinsics) -> list[tuple[str, float | str]]:
    """(name, theta) pairs; theta "near"/"far" = pixels just / clearly outside the image circle (the "near" ones
    lie within float32 resolution of the circle, so float32 may call some of them valid: clamped onto the circle)."""
    return [
        ("theta = 0", 0.0),
        ("theta = 1e-12", 1e-12),
        ("theta = 1e-6", 1e-6),
        ("45 deg", math.radians(45)),
        ("89.9 deg", math.radians(89.9)),
        ("90 deg", math.pi / 2),
        ("100 deg", math.radians(100)),
        ("fold - 1e-6", intr.theta_fold - 1e-6),
        ("fold (theta_max)", intr.theta_max),
        ("outside by 1e-9..1e-6 rel", "near"),
        ("outside >1e-5 rel, corners, inf, NaN", "far"),
    ]


# ------------------------------------------------------------------------------------------ round trips
def round_trip_rows(intr: FisheyeIntrinsics, n_phi: int = 256, seed: int = 0) -> list[list[Any]]:
    import torch

    from umi_aug.camera import kb_torch as kt

    rng = np.random.default_rng(seed)
    rows = []
    for name, theta in _cases(intr):
        phi = rng.uniform(-math.pi, math.pi, n_phi)
        if isinstance(theta, str):
            if theta == "near":
                r = intr.theta_d_max * (1 + np.geomspace(1e-9, 1e-6, n_phi))
            else:
                r = intr.theta_d_max * np.concatenate([1 + np.geomspace(1e-5, 1.0, n_phi - 7), [1e6]])
            ph = phi[: r.size]
            uv = np.stack([intr.cx + intr.fx * r * np.cos(ph), intr.cy + intr.fy * r * np.sin(ph)], -1)
            if theta == "far":
                c = np.array([[0, 0], [intr.width - 1, 0], [0, intr.height - 1], [intr.width - 1, intr.height - 1]])
                c = c[np.hypot(c[:, 0] - intr.cx, c[:, 1] - intr.cy) > intr.image_circle_radius_px[0]]
                uv = np.concatenate([uv, c, [[np.nan, 0.0], [np.inf, 1.0]]])
            rays, valid, n = kb.unproject(uv, intr, return_iterations=True)
            rays32, valid32, n32 = kt.unproject(torch.as_tensor(uv, dtype=torch.float32), intr, return_iterations=True)
            nan = bool(np.isnan(rays).any() or torch.isnan(rays32).any())
            rows.append([name, "-", "-", "-", "-", int(n.max()), float(n.mean()), int(n32.max()),
                         f"{int(valid.sum())}/{valid.size} f64, {int(valid32.sum())}/{valid.size} f32", nan])
            continue
        rays_true = _rays(np.full(n_phi, theta), phi)
        # float64 numpy: ray -> pixel -> ray and pixel -> ray -> pixel
        uv, v1 = kb.project(rays_true, intr)
        rays, v2, n = kb.unproject(uv, intr, return_iterations=True)
        uv2, v3 = kb.project(rays, intr)
        e_rad64 = float(_angle(rays, rays_true).max())
        e_px64 = float(np.abs(uv2 - uv).max())
        # float32 torch
        rays32_in = torch.as_tensor(rays_true, dtype=torch.float32)
        uv32, w1 = kt.project(rays32_in, intr)
        rays32, w2, n32 = kt.unproject(uv32, intr, return_iterations=True)
        uv32b, w3 = kt.project(rays32, intr)
        e_rad32 = float(_angle(rays32.double().numpy(), rays32_in.double().numpy()).max())
        e_px32 = float((uv32b.double() - uv32.double()).abs().max())
        valid = bool(v1.all() and v2.all() and v3.all())
        valid32 = bool(w1.all() and w2.all() and w3.all())
        nan = bool(np.isnan(uv).any() or np.isnan(rays).any() or torch.isnan(rays32).any() or torch.isnan(uv32b).any())
        rows.append([name, e_px64, e_rad64, e_px32, e_rad32, int(n.max()), float(n.mean()), int(n32.max()),
                     f"{'all' if valid else 'NOT all'} f64, {'all' if valid32 else 'NOT all'} f32", nan])
    return rows


# ---------------------------------------------------------------------------------- error vs iterations
def iteration_rows(intr: FisheyeIntrinsics, n: int = 200_001) -> list[list[Any]]:
    import torch

    from umi_aug.camera import kb_torch as kt

    theta = np.linspace(0.0, intr.theta_max, n)
    td = kb.kb_theta_d(theta, intr.k)
    front = theta <= math.pi / 2
    flat = theta > intr.theta_max - 0.05  # within 0.05 rad (3 deg) of the fold-over
    rows = []
    for it in (1, 2, 3, 4, 5, 6, 8, 12, 20, 40):
        th, _, _ = kb.kb_inverse_theta(td, intr.k, intr.theta_max, max_iter=it, tol=0.0)
        err = np.abs(th - theta)
        th32, _, _ = kt.kb_inverse_theta(torch.as_tensor(td, dtype=torch.float32), intr.k, intr.theta_max, n_iter=it)
        err32 = np.abs(th32.double().numpy() - theta)
        rows.append([it, float(err[front].max()), float(err[~front & ~flat].max()), float(err[flat].max()),
                     float(err32[front].max()), float(err32[~flat].max())])
    th, _, nit = kb.kb_inverse_theta(td, intr.k, intr.theta_max)
    err = np.abs(th - theta)
    rows.append([f"converged (max {int(nit.max())}, mean {nit.mean():.2f})", float(err[front].max()),
                 float(err[~front & ~flat].max()), float(err[flat].max()), "-", "-"])
    return rows


# ---------------------------------------------------------------------------------------- run time
def _best_time(fn: Callable[[], Any], repeat: int) -> float:
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def timing_rows(intr: FisheyeIntrinsics, n_points: int, repeat: int, seed: int = 0) -> list[list[Any]]:
    import cv2
    import torch

    from umi_aug.camera import kb_torch as kt

    rng = np.random.default_rng(seed)
    # pixels uniformly over the image (~12 % outside the circle, exercised too)
    uv = rng.uniform([0, 0], [intr.width - 1, intr.height - 1], size=(n_points, 2))
    # rays in front of the camera (OpenCV's domain): theta < 89 deg
    rays = _rays(rng.uniform(0, math.radians(89), n_points), rng.uniform(-math.pi, math.pi, n_points))
    K, D = intr.K, intr.D.reshape(4, 1)
    und = (rays[:, :2] / rays[:, 2:]).reshape(-1, 1, 2)
    uv_cv_in = uv.reshape(-1, 1, 2)
    uv_front, _ = kb.project(rays, intr)

    t_cv_proj = _best_time(lambda: cv2.fisheye.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D),
                           repeat)
    t_cv_dist = _best_time(lambda: cv2.fisheye.distortPoints(und, K, D), repeat)
    t_cv_und = _best_time(lambda: cv2.fisheye.undistortPoints(uv_front.reshape(-1, 1, 2), K, D), repeat)
    del uv_cv_in

    uv32, uv64 = torch.as_tensor(uv, dtype=torch.float32), torch.as_tensor(uv)
    r32, r64 = torch.as_tensor(rays, dtype=torch.float32), torch.as_tensor(rays)
    res = [
        ("unproject", "numpy f64", _best_time(lambda: kb.unproject(uv, intr), repeat)),
        ("unproject", "torch f32", _best_time(lambda: kt.unproject(uv32, intr), repeat)),
        ("unproject", "torch f64", _best_time(lambda: kt.unproject(uv64, intr), repeat)),
        ("unproject", "torch f32, n_iter=6", _best_time(lambda: kt.unproject(uv32, intr, n_iter=6), repeat)),
        ("project", "numpy f64", _best_time(lambda: kb.project(rays, intr), repeat)),
        ("project", "torch f32", _best_time(lambda: kt.project(r32, intr), repeat)),
        ("project", "torch f64", _best_time(lambda: kt.project(r64, intr), repeat)),
        ("project_jacobian", "numpy f64", _best_time(lambda: kb.project_jacobian(rays, intr), repeat)),
        ("cv2.fisheye.projectPoints", "OpenCV f64", t_cv_proj),
        ("cv2.fisheye.distortPoints", "OpenCV f64", t_cv_dist),
        ("cv2.fisheye.undistortPoints", "OpenCV f64 (theta<89)", t_cv_und),
    ]
    rows = []
    for op, backend, t in res:
        rows.append([op, backend, 1e6 * t / n_points, t / t_cv_proj, t / t_cv_dist, t / t_cv_und])
    return rows


# ------------------------------------------------------------------------------------------- SO(3) rows
def so3_rows() -> None:
    path = Path(__file__).with_name("so3_stability.py")
    if not path.exists():
        print("\n## SO(3) stability\n\n(benchmarks/so3_stability.py not found: skipped)")
        return
    try:
        spec = importlib.util.spec_from_file_location("so3_stability", path)
        mod = importlib.util.module_from_spec(spec)
        assert spec.loader is not None
        spec.loader.exec_module(mod)
        fn = getattr(mod, "so3_stability_rows", None)
        if fn is None:
            print("\n## SO(3) stability\n\n(benchmarks/so3_stability.py has no so3_stability_rows(): skipped)")
            return
        rows = fn()
    except Exception as exc:  # report, never crash the camera benchmark
        print(f"\n## SO(3) stability\n\n(benchmarks/so3_stability.py failed: {type(exc).__name__}: {exc})")
        return
    if rows and isinstance(rows[0], dict):
        header = list(rows[0].keys())
        print_table("SO(3) stability (benchmarks/so3_stability.py)", header, [[r.get(h) for h in header] for r in rows])
    else:
        print("\n## SO(3) stability (benchmarks/so3_stability.py)\n")
        for r in rows:
            print(r)


# ------------------------------------------------------------------------------------------------ main
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-timing", type=int, default=1_000_000, help="points per timing run")
    ap.add_argument("--repeat", type=int, default=2, help="timing repeats (best is reported)")
    ap.add_argument("--threads", type=int, default=1, help="torch / OpenCV threads")
    ap.add_argument("--skip-timing", action="store_true")
    args = ap.parse_args(argv)

    import cv2
    import torch

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    full = gopro_intrinsics_2_7k()
    policy = full.umi_policy(224)
    print("# Kannala-Brandt fisheye camera: stability and speed")
    print(f"numpy {np.__version__}, torch {torch.__version__}, OpenCV {cv2.__version__}, threads {args.threads}")
    for name, intr in (("GoPro 224x224 (UMI policy, exact pixel centres)", policy), ("GoPro 2704x2028", full)):
        print(f"\n{name}: f = {intr.fx:.4f}, c = ({intr.cx:.4f}, {intr.cy:.4f}), theta_fold = {intr.theta_fold:.6f} rad"
              f" ({math.degrees(intr.theta_fold):.3f} deg), image circle r = {intr.image_circle_radius_px[0]:.2f} px")
        print_table(
            f"Round trips, {name} (256 azimuths per case)",
            ["case", "px->ray->px f64 [px]", "ray->px->ray f64 [rad]", "px->ray->px f32 [px]",
             "ray->px->ray f32 [rad]", "iters max f64", "iters mean f64", "iters max f32", "valid", "NaN"],
            round_trip_rows(intr),
        )
    print_table(
        "Error against iteration count (GoPro, 200001 theta in [0, theta_max], tol = 0)",
        ["Newton updates", "max err f64 theta<=90deg", "f64 90deg..fold-0.05", "f64 last 0.05 rad to fold",
         "f32 theta<=90deg", "f32 theta<fold-0.05"],
        iteration_rows(full),
    )
    print("\n(The last 0.05 rad before the fold-over converge linearly - theta_d' -> 0 - and are limited by the "
          "conditioning eps*theta_d/theta_d'(theta): ~1e-10 rad at fold - 1e-6, ~1e-8 rad at the fold itself.)")
    if not args.skip_timing:
        for name, intr in (("GoPro 224x224", policy), ("GoPro 2704x2028", full)):
            print_table(
                f"Run time, {name}, {args.n_timing} points (best of {args.repeat}, {args.threads} thread(s))",
                ["operation", "backend", "us/point", "x cv2.projectPoints", "x cv2.distortPoints",
                 "x cv2.undistortPoints"],
                timing_rows(intr, args.n_timing, args.repeat),
            )
    so3_rows()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
