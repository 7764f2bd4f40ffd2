"""Cost of composing obstacle Gaussians into a scene render (umi_aug.splat.compose), and the render cache.

Run: ``python benchmarks/compose.py [--sizes 100000 300000] [--res 224] [--obstacle-gaussians 6000]
[--obstacles 2] [--repeats 9] [--threads 2] [--picture docs/splat_composition.png [--fit]]``

Scene: the procedural tabletop room (:func:`umi_aug.splat.scenes.room_gaussians`, float32, SH degree 3) seen by
the UMI GoPro at ``res``², obstacles = :func:`umi_aug.splat.obstacle_gaussians.obstacle_gaussians` of the procedural
``mug`` / ``bottle`` / ``box`` (surface initialisation; ``--fit`` also runs the short fit for the picture), placed on
the table in view. All timings in this process, median of ``repeats`` (the machine's cores may be shared: see the
load printed first). Rows (ratio = time / plain render of the scene alone, same process):

* ``plain``: :func:`umi_aug.splat.render` of the scene alone (the reference time);
* ``composed``: :func:`render_composed` of scene + obstacles (no scene copy);
* ``prebuilt``: ``render`` of scene + transformed obstacles concatenated once outside the timing (the lower bound:
  the cost of the extra Gaussians themselves);
* ``concat``: what one would do without composition: ``transform_gaussians`` per obstacle + ``Gaussians.cat`` +
  ``render`` (builds the full set every frame);
* ``cache hit``: :meth:`RenderCache.render_rgb` of an already rendered frame (memory), ``cache miss``: a new pose.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

from umi_aug.runtime import configure_threads  # noqa: E402


def _median_time(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def _placements(n: int) -> list:
    import numpy as np

    from umi_aug.geometry import make_pose, so3_exp

    spots = [(0.06, 0.05), (-0.10, 0.12), (0.14, -0.02), (-0.05, -0.08)]
    return [make_pose(so3_exp(np.array([0.0, 0.0, 0.7 * i + 0.3])), np.array([*spots[i % 4], 0.0]))
            for i in range(n)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 300_000])
    ap.add_argument("--res", type=int, default=224)
    ap.add_argument("--obstacles", type=int, default=2)
    ap.add_argument("--obstacle-gaussians", type=int, default=6000)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--picture", type=Path, default=None, help="write scene | scene + obstacles as a PNG")
    ap.add_argument("--fit", action="store_true", help="fit the obstacle Gaussians (picture only; ~30 s each)")
    ap.add_argument("--cache-dir", type=Path, default=None, help="obstacle Gaussian cache folder")
    args = ap.parse_args(argv)
    n_threads = configure_threads(args.threads)

    import numpy as np
    import torch

    from umi_aug.camera import gopro_intrinsics_2_7k
    from umi_aug.recon.obstacles import procedural_asset
    from umi_aug.splat import Gaussians, render
    from umi_aug.splat.compose import PlacedGaussians, RenderCache, render_composed, rgb_to_uint8, transform_gaussians
    from umi_aug.splat.obstacle_gaussians import obstacle_gaussians, obstacle_gaussians_key
    from umi_aug.splat.scenes import room_camera_pose, room_gaussians

    print(f"threads {n_threads}, load average {os.getloadavg()[0]:.2f} (cores: {os.cpu_count()})")
    intr = gopro_intrinsics_2_7k().umi_policy(args.res)
    T = room_camera_pose(0)
    names = ["mug", "bottle", "box"]
    assets = [procedural_asset(names[i % 3]) for i in range(args.obstacles)]

    def placed(fit: bool) -> list[PlacedGaussians]:
        out = []
        for a, Two in zip(assets, _placements(len(assets))):
            g = obstacle_gaussians(a, cache_dir=args.cache_dir, fit=fit, n_gaussians=args.obstacle_gaussians)
            out.append(PlacedGaussians(g, Two, obstacle_gaussians_key(a, fit=fit, n_gaussians=args.obstacle_gaussians)))
        return out

    obstacles = placed(False)
    print(f"\nres {args.res}², {len(obstacles)} obstacles x {args.obstacle_gaussians} Gaussians, median of "
          f"{args.repeats}\n")
    print(f"{'scene N':>9} | {'plain':>9} | {'prebuilt':>9} {'ratio':>6} | {'composed':>9} {'ratio':>6} | "
          f"{'concat':>9} {'ratio':>6} | "
          f"{'cache hit':>9} {'ratio':>7} | {'miss':>9} | {'max |Δ| vs concat':>17}")
    for n in args.sizes:
        scene = room_gaussians(n, np.random.default_rng(0), dtype=torch.float32)
        for _ in range(2):  # warm-up (numba compile, caches)
            render(scene, T, intr)
            render_composed(scene, obstacles, T, intr)

        def concat():
            parts = [scene] + [transform_gaussians(o.gaussians, o.T_world_obj) for o in obstacles]
            return render(Gaussians.cat(parts), T, intr)

        t_plain = _median_time(lambda: render(scene, T, intr), args.repeats)
        full = Gaussians.cat([scene] + [transform_gaussians(o.gaussians, o.T_world_obj) for o in obstacles])
        t_pre = _median_time(lambda: render(full, T, intr), args.repeats)
        t_comp = _median_time(lambda: render_composed(scene, obstacles, T, intr), args.repeats)
        t_cat = _median_time(concat, args.repeats)
        cache = RenderCache()
        cache.render_rgb(scene, "room", T, intr, obstacles)
        t_hit = _median_time(lambda: cache.render_rgb(scene, "room", T, intr, obstacles), args.repeats)
        poses = []
        for i in range(args.repeats):
            P = T.copy()
            P[0, 3] += 1e-3 * (i + 1)
            poses.append(P)
        it = iter(poses)
        t_miss = _median_time(lambda: cache.render_rgb(scene, "room", next(it), intr, obstacles), args.repeats)
        err = (render_composed(scene, obstacles, T, intr).rgb - concat().rgb).abs().max().item()
        ms = lambda s: f"{s * 1e3:7.1f}ms"  # noqa: E731
        print(f"{n:>9} | {ms(t_plain)} | {ms(t_pre)} {t_pre / t_plain:6.2f} | {ms(t_comp)} {t_comp / t_plain:6.2f} | "
              f"{ms(t_cat)} {t_cat / t_plain:6.2f} | "
              f"{ms(t_hit)} {t_hit / t_plain:7.4f} | {ms(t_miss)} | {err:17.2e}")

    if args.picture is not None:
        import cv2

        scene = room_gaussians(args.sizes[0], np.random.default_rng(0), dtype=torch.float32)
        obs = placed(args.fit) if args.fit else obstacles
        bg = (0.05, 0.05, 0.05)
        a = rgb_to_uint8(render(scene, T, intr, bg).rgb)
        b = rgb_to_uint8(render_composed(scene, obs, T, intr, bg).rgb)
        T2 = room_camera_pose(1)
        c = rgb_to_uint8(render_composed(scene, obs, T2, intr, bg).rgb)
        sheet = np.concatenate([a, b, c], axis=1)
        args.picture.parent.mkdir(parents=True, exist_ok=True)
        from umi_aug.io_utils import atomic_path

        with atomic_path(args.picture) as tmp:
            ok, buf = cv2.imencode(".png", sheet[..., ::-1])
            tmp.write_bytes(buf.tobytes())
        print(f"\nwrote {args.picture} (scene | scene + {len(obs)} obstacles | other view)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
