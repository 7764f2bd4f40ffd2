"""What the rasteriser's (Gaussian, pixel) evaluations do on a real augmented episode (issue #17, part 1).

    python benchmarks/raster_occupancy.py                          # the scene of benchmarks/augment.py's 'base'
    python benchmarks/raster_occupancy.py --work DIR --max-gaussians 25000 --iterations 1500 --frames 24

The export is bound by the rasteriser (docs/throughput.md). This asks whether its work could be cut without
changing the image: every visited (Gaussian, pixel) pair of ``--frames`` new frames of one planned free-space
episode is classified as the forward kernel (``umi_aug.splat._kernels.raster_fwd_kernel``) would treat it — the
pixel already finished (transmittance below the stop threshold), outside the footprint (``power > 0``), alpha
below 1/255, the Gaussian that finishes the pixel, or composited — and the composited ones are binned by the
pixel's transmittance before them. Culling levers (tighter footprints, skipping finished pixels or rows) can only
remove the first three classes; a higher stop threshold only the low-transmittance bins. The counting loop below
re-walks the kernel's tile lists with the kernel's own footprint helpers (single-threaded, counters only, no
compositing outputs); the same frames are then timed with the real rasteriser, its plain forward (training's) and
its fused-multiply-add forward (inference) interleaved.

Needs the work folder of ``benchmarks/augment.py`` (its session and the 3DGS stage of the chosen setting; a missing
stage is trained first, ~2.5 min for 'base').
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from numba import njit  # noqa: E402

from umi_aug.splat._kernels import _TS, _gather_tile, _pixel_range, _row_span, fexp  # noqa: E402

#: counter slots of :func:`_count_tile_work`
CLASSES = ("finished pixel", "outside footprint", "alpha < 1/255", "finishes the pixel", "composited")
T_BINS = (0.1, 0.01, 1.0 / 255.0, 1e-3)  # composited evaluations by the transmittance before them: > 0.1, ...


@njit(cache=False)
def _count_tile_work(packed, uv64, tile_start, sorted_row, width, height, tiles_x, cst, counts):  # pragma: no cover
    """Add to ``counts`` (int64 [10]): slots 0..4 the classes of :data:`CLASSES`, 5..9 the composited evaluations
    by transmittance bin (:data:`T_BINS`, last slot: below the smallest). Arithmetic in ``packed``'s dtype, as
    the kernel's."""
    max_alpha, a_thr, t_thr, one, half, zero = cst[0], cst[1], cst[2], cst[3], cst[4], cst[5]
    px = np.arange(_TS).astype(packed.dtype)  # tile-local pixel coordinates
    for t in range(tile_start.shape[0] - 1):
        ty = t // tiles_x
        x0, y0 = (t - ty * tiles_x) * _TS, ty * _TS
        tw, th = min(x0 + _TS, width) - x0, min(y0 + _TS, height) - y0
        T = np.full(_TS * _TS, one)
        done = np.zeros(_TS * _TS, dtype=np.bool_)
        tp = _gather_tile(packed, uv64, sorted_row, tile_start[t], tile_start[t + 1], x0, y0)
        for j in range(tp.shape[0]):
            if tp[j, 10] < 0.0:
                continue
            mx, my = np.float64(tp[j, 0]), np.float64(tp[j, 1])
            ya, yb = _pixel_range(my, np.float64(tp[j, 11]), 0, th - 1)
            for y in range(ya, yb + 1):
                xa, xb = _row_span(mx, my, np.float64(tp[j, 10]), np.float64(tp[j, 12]), np.float64(tp[j, 13]),
                                   np.float64(tp[j, 14]), np.float64(y), 0, tw - 1)
                dy = px[y] - tp[j, 1]
                gdy = tp[j, 12] * dy * dy
                bdy = tp[j, 13] * dy
                for x in range(xa, xb + 1):
                    p = y * _TS + x
                    e = px[x] - tp[j, 0] + bdy
                    power = -half * (tp[j, 2] * e * e + gdy)
                    alpha = min(max_alpha, tp[j, 5] * fexp(min(power, zero)))
                    if done[p]:
                        counts[0] += 1
                    elif power > zero:
                        counts[1] += 1
                    elif alpha < a_thr:
                        counts[2] += 1
                    elif T[p] * (one - alpha) < t_thr:
                        done[p] = True
                        counts[3] += 1
                    else:
                        k = 0
                        while k < len(T_BINS) and T[p] <= T_BINS[k]:
                            k += 1
                        counts[5 + k] += 1
                        T[p] *= one - alpha
                        counts[4] += 1


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", default="/tmp/umi_aug_bench_augment", help="benchmarks/augment.py's --work folder")
    p.add_argument("--max-gaussians", type=int, default=25000)
    p.add_argument("--iterations", type=int, default=1500)
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--repeats", type=int, default=5, help="timed passes of each rasteriser over the frames")
    args = p.parse_args()
    from umi_aug.runtime import configure_threads

    configure_threads()
    import torch
    from rich.console import Console
    from rich.table import Table

    import umi_aug.splat._kernels as K
    from umi_aug.augment import AugmentConfig, SplatStageConfig, plan_episode, prepare_session
    from umi_aug.splat.renderer import bin_gaussians, project_numba, rasterize_packed

    work = Path(args.work)
    cfg = AugmentConfig(mode="freespace", n_per_demo=1, seed=0,
                        splat=SplatStageConfig(iterations=args.iterations, max_gaussians=args.max_gaussians))
    assets = prepare_session(work / "session", work / "work", cfg, progress=True)
    planned = plan_episode(assets, assets.augmentable[0], 0, "freespace")
    ks = np.unique(np.linspace(0, planned.splice_index - 1, args.frames).round().astype(int))
    intr, g = assets.policy_intrinsics, assets.gaussians
    frames = []
    for k in ks:
        packed, uv64, depth64, valid, n_tiles = project_numba(
            g, torch.as_tensor(planned.episode.T_world_cam[k]), intr, g.sh_degree, "inria", cfg.render_near_m,
            cfg.render_far_m)
        rows = np.flatnonzero(valid)
        frames.append((packed, uv64, bin_gaussians(packed, rows, depth64[rows], intr.width, intr.height,
                                                   n_tiles[rows])))
    counts = np.zeros(10, dtype=np.int64)
    for packed, uv64, b in frames:
        _count_tile_work(packed, uv64, b.tile_start, b.sorted_row, b.width, b.height, b.tiles_x,
                         K.raster_constants(packed.dtype), counts)
    kernel_evals = sum(int(rasterize_packed(packed, b, uv64)["evals"].sum()) for packed, uv64, b in frames)
    # the plain forward (training's, replayed by the backward) and the fused one (inference), interleaved
    seconds = {False: [], True: []}
    max_diff = max(float(np.abs(rasterize_packed(packed, b, uv64, fused=True)["rgb"]
                                - rasterize_packed(packed, b, uv64)["rgb"]).max()) for packed, uv64, b in frames)
    for _ in range(args.repeats):
        for fused in (False, True):
            t0 = time.perf_counter()
            for packed, uv64, b in frames:
                rasterize_packed(packed, b, uv64, fused=fused)
            seconds[fused].append((time.perf_counter() - t0) / len(frames))
    raster_s = float(np.median(seconds[True]))

    n, total = len(frames), int(counts[:5].sum())
    if total != kernel_evals:
        raise SystemExit(f"the counting loop visited {total} pairs, the kernel {kernel_evals}: out of step")
    console = Console(width=160)
    t = Table(title=f"(Gaussian, pixel) evaluations of one new frame ({g.n} Gaussians, {intr.width}x{intr.height}, "
                    f"mean of {n} poses of one episode; {total / n / 1e6:.2f} M per frame, inference rasteriser "
                    f"{raster_s * 1e3:.1f} ms = {total / n / raster_s / 1e6:.0f} M/s on this machine)")
    for col in ("evaluation", "M per frame", "share"):
        t.add_column(col, justify="right")
    for name, c in zip(CLASSES, counts[:5]):
        t.add_row(name, f"{c / n / 1e6:.3f}", f"{c / total:.3f}")
    edges = ("> 0.1", "0.01-0.1", "1/255-0.01", "1e-3-1/255", "< 1e-3")
    for name, c in zip(edges, counts[5:]):
        t.add_row(f"  composited at transmittance {name}", f"{c / n / 1e6:.3f}", f"{c / total:.3f}")
    console.print(t)
    per_px = counts[4] / n / (intr.width * intr.height)
    console.print(f"composited Gaussians per pixel: {per_px:.1f}")
    plain = float(np.median(seconds[False]))
    console.print(f"rasteriser per frame, median of {args.repeats} interleaved passes: plain (training's) "
                  f"{plain * 1e3:.2f} ms, fused multiply-add (inference) {raster_s * 1e3:.2f} ms = x{plain / raster_s:.2f}; "
                  f"max |rgb difference| {max_diff:.1e}")


if __name__ == "__main__":
    main()
