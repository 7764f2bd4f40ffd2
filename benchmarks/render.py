"""Speed of the CPU fisheye Gaussian splatting renderer (umi_aug.splat) and what the screen-space filter does.

Run: ``python benchmarks/render.py [--sizes 10000 100000 300000] [--res 224] [--repeats 15] [--threads 2]``

Scene: the procedural tabletop room of :func:`umi_aug.splat.scenes.room_gaussians` (flat surface Gaussians with
the overlap of a trained scene, SH degree 3, float32), seen by UMI's GoPro (KB fisheye, 2704x2028 calibration
scaled to the policy's ``res x res`` crop) from a wrist-camera pose 35 cm above the table. Numbers are timed in
this process on whatever cores it gets (the project machines have 2, shared): median and best of ``repeats``.

Tables:
1. Forward (inference path: numba projection + binning + rasteriser) and forward+backward (training path:
   torch-autograd projection + numba rasteriser with the hand-written backward; loss = sum(w * rgb)) for each
   scene size: frames/s, (Gaussian, pixel) evaluations/s, stage times, visible Gaussians, tile intersections,
   evaluations per pixel.
2. Ratio to the dense float64 torch reference renderer (:func:`umi_aug.splat._torch_impl._render_reference`), measured in the
   same run on a subset (``--ref-gaussians`` random Gaussians of each scene at ``--ref-res``², because the dense
   reference costs O(pixels x Gaussians)): time of both on that identical input, and the reference's time
   extrapolated to the full problem (pixels x visible Gaussians at its measured pair rate).
3. Screen-space filter (``--filter-study``): PSNR of each filter at ``res``² against (a) the no-filter render and
   (b) an anti-aliased ground truth = the no-filter render at 4x resolution, 4x4 box-averaged.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# Idle OpenMP workers sleep instead of spinning (both numba's and torch's libgomp read this when they load):
# on 2 cores shared with other processes, spinning workers steal the core a straggler thread needs and every
# fork-join of the renderer stalls (measured here: 100k Gaussians median 64 -> 42 ms/frame under load ~2).
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

from umi_aug.runtime import configure_threads  # noqa: E402


def _fmt_t(s: float) -> str:
    return f"{s * 1e3:.1f} ms" if s < 10 else f"{s:.1f} s"


def _time(fn, repeats: int) -> tuple[float, float, object]:
    """Median and best wall time of ``repeats`` calls, and the last result."""
    ts, _, out = _time_cpu(fn, repeats)
    return statistics.median(ts), min(ts), out


def _time_cpu(fn, repeats: int) -> tuple[list[float], list[float], object]:
    """Wall and process-CPU (all threads) seconds per call."""
    ts, cs = [], []
    out = None
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
    return ts, cs, out


def _table(headers: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(headers)]
    line = lambda cells: "| " + " | ".join(c.rjust(w) for c, w in zip(cells, widths)) + " |"  # noqa: E731
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(headers), sep, *(line(r) for r in rows)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 300_000])
    ap.add_argument("--res", type=int, default=224)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--bwd-repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--filter", default="inria", choices=["inria", "mip", "none"])
    ap.add_argument("--ref-gaussians", type=int, default=2000)
    ap.add_argument("--ref-res", type=int, default=64)
    ap.add_argument("--filter-study", action="store_true", help="also run table 3")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    n_threads = configure_threads(args.threads)
    import numba
    import numpy as np
    import torch

    from umi_aug.camera import gopro_intrinsics_2_7k
    from umi_aug.splat import render
    from umi_aug.splat._torch_impl import _render_reference as render_reference
    from umi_aug.splat.scenes import room_camera_pose, room_gaussians

    torch.set_num_threads(n_threads)
    numba.set_num_threads(min(n_threads, numba.config.NUMBA_NUM_THREADS))
    intr = gopro_intrinsics_2_7k().umi_policy(args.res)
    T = room_camera_pose(0)
    rng = np.random.default_rng(args.seed)
    H, W = intr.height, intr.width
    load0 = os.getloadavg()[0]
    print(f"# camera: GoPro KB fisheye {W}x{H} (theta_max {math.degrees(intr.theta_max):.1f} deg), filter "
          f"{args.filter!r}, SH degree 3, float32; median (best) of {args.repeats} forward / {args.bwd_repeats} "
          "forward+backward runs after one warm-up")

    # warm-up / compile
    warm = room_gaussians(2000, np.random.default_rng(1))
    t0 = time.perf_counter()
    render(warm, T, intr, filter=args.filter)
    wg = warm.clone().requires_grad_(True)
    render(wg, T, intr, filter=args.filter).rgb.sum().backward()
    print(f"# first call (numba compile or cache load): {_fmt_t(time.perf_counter() - t0)}")
    print(f"# {platform.machine()}, {len(os.sched_getaffinity(0))} usable CPUs, numba {numba.__version__} "
          f"({numba.threading_layer()} layer, {numba.get_num_threads()} threads), torch {torch.__version__} "
          f"({torch.get_num_threads()} threads), OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}; load average "
          f"before: {load0:.2f}")

    rows1, rows2 = [], []
    w_img = torch.as_tensor(rng.uniform(size=(H, W, 3)), dtype=torch.float32)
    for n in args.sizes:
        g = room_gaussians(n, np.random.default_rng(args.seed + n))
        render(g, T, intr, filter=args.filter)  # warm caches
        with torch.no_grad():
            ts, cs, out = _time_cpu(lambda: render(g, T, intr, filter=args.filter), args.repeats)
        med, best, cpu = statistics.median(ts), min(ts), statistics.median(cs)
        m = out.meta
        stages = {k: [] for k in ("project", "bin", "raster")}
        for _ in range(5):
            o = render(g, T, intr, filter=args.filter)
            for k in stages:
                stages[k].append(o.meta["timings"][k])
        st = "/".join(f"{statistics.median(v) * 1e3:.1f}" for v in stages.values())
        evals = m["n_evals"]
        rows1.append([
            f"{n:,}", "forward", f"{1 / med:.1f} ({1 / best:.1f})", f"{cpu * 1e3:.1f}", f"{n_threads / cpu:.1f}",
            f"{evals / med / 1e6:.0f} M", st, f"{m['n_visible']:,}", f"{m['n_isects']:,}", f"{evals / (H * W):.1f}",
        ])
        # one thread: immune to the fork-join stalls of a shared machine; 2 processes x 1 thread (batch
        # rendering of many frames) give ~2x this frame rate when both cores are free
        numba.set_num_threads(1)
        torch.set_num_threads(1)
        with torch.no_grad():
            ts1, cs1, _ = _time_cpu(lambda: render(g, T, intr, filter=args.filter), max(3, args.repeats // 2))
        numba.set_num_threads(min(n_threads, numba.config.NUMBA_NUM_THREADS))
        torch.set_num_threads(n_threads)
        med1, best1 = statistics.median(ts1), min(ts1)
        rows1.append([
            f"{n:,}", "fwd, 1 thread", f"{1 / med1:.1f} ({1 / best1:.1f})", f"{statistics.median(cs1) * 1e3:.1f}",
            "-", f"{evals / med1 / 1e6:.0f} M", "-", "", "", "",
        ])
        gg = g.clone().requires_grad_(True)

        def fwd_bwd():
            o = render(gg, T, intr, filter=args.filter)
            (o.rgb * w_img).sum().backward()
            return o

        ts, cs, ob = _time_cpu(fwd_bwd, args.bwd_repeats)
        med_b, best_b, cpu_b = statistics.median(ts), min(ts), statistics.median(cs)
        rows1.append([
            f"{n:,}", "fwd+bwd", f"{1 / med_b:.1f} ({1 / best_b:.1f})", f"{cpu_b * 1e3:.1f}",
            f"{n_threads / cpu_b:.1f}", f"{evals / med_b / 1e6:.0f} M",
            f"proj {ob.meta['timings']['project'] * 1e3:.0f} / raster {ob.meta['timings']['raster'] * 1e3:.0f}",
            f"{ob.meta['n_visible']:,}", f"{ob.meta['n_isects']:,}", f"{evals / (H * W):.1f}",
        ])

        # reference on a subset: same input for both renderers
        k = min(args.ref_gaussians, n)
        sub = g.select(torch.as_tensor(np.sort(rng.choice(n, size=k, replace=False))))
        intr_s = gopro_intrinsics_2_7k().umi_policy(args.ref_res)
        with torch.no_grad():
            render_reference(sub, T, intr_s, filter=args.filter)  # warm-up
            _, tr, ref = _time(lambda: render_reference(sub, T, intr_s, filter=args.filter), 2)
            _, tf, fo = _time(lambda: render(sub, T, intr_s, filter=args.filter), 5)
        err = (fo.rgb.double() - ref.rgb).abs().max().item()
        sg = sub.clone().requires_grad_(True)
        w_s = torch.as_tensor(rng.uniform(size=(args.ref_res, args.ref_res, 3)))

        def ref_fb():
            o = render_reference(sg, T, intr_s, filter=args.filter)
            (o.rgb * w_s).sum().backward()

        def fast_fb():
            o = render(sg, T, intr_s, filter=args.filter)
            (o.rgb * w_s.float()).sum().backward()

        _, trb, _ = _time(ref_fb, 2)
        _, tfb, _ = _time(fast_fb, 3)
        pairs_ref = args.ref_res**2 * max(ref.meta["n_visible"], 1)
        rate = pairs_ref / tr
        full_pairs = H * W * m["n_visible"]
        t_ref_full = full_pairs / rate
        rows2.append([
            f"{n:,}", f"{k:,} @ {args.ref_res}^2", f"{ref.meta['n_visible']:,}", _fmt_t(tr), _fmt_t(tf),
            f"{tr / tf:.0f}x", _fmt_t(trb), _fmt_t(tfb), f"{trb / tfb:.0f}x", f"{err:.1e}",
            f"{rate / 1e6:.1f} M/s", _fmt_t(t_ref_full), f"{t_ref_full / med:,.0f}x",
        ])
        print(f"# done {n:,} (load average {os.getloadavg()[0]:.2f})", flush=True)

    print()
    print(f"## 1. Render speed at {W}x{H}: wall-clock frames/s median (best) on this shared machine; CPU ms/frame"
          f" (process time, all threads, median) and {n_threads}/CPU = frames/s if the {n_threads} cores were ours;"
          " evals/s at the median wall time; stage times median wall ms (project/bin/raster)")
    print(_table(["Gaussians", "pass", "frames/s", "CPU ms", f"{n_threads}/CPU f/s", "evals/s", "stages (ms)",
                  "visible", "tile isects", "evals/px"], rows1))
    print()
    print("## 2. Ratio to the dense float64 torch reference, measured in the same run on a random subset at a smaller"
          " size (identical input for both; best of 2 / 5 runs);\n##    last three columns: reference pair rate and its"
          " time extrapolated to the full forward problem (pixels x visible Gaussians), vs the fast forward median")
    print(_table(["scene", "subset", "visible", "ref fwd", "fast fwd", "ratio", "ref f+b", "fast f+b", "ratio",
                  "max|diff|", "ref pairs/s", "ref full fwd (est.)", "ratio (est.)"], rows2))

    if args.filter_study:
        n = 100_000 if 100_000 in args.sizes else args.sizes[0]
        g = room_gaussians(n, np.random.default_rng(args.seed + n))
        hi = gopro_intrinsics_2_7k().umi_policy(4 * args.res)
        with torch.no_grad():
            gt_hi = render(g, T, hi, filter="none").rgb
            gt = gt_hi.reshape(H, 4, W, 4, 3).mean(dim=(1, 3)).double()
            imgs = {f: render(g, T, intr, filter=f).rgb.double() for f in ("none", "inria", "mip")}

        def psnr(a, b):
            mse = ((a.clamp(0, 1) - b.clamp(0, 1)) ** 2).mean().item()
            return float("inf") if mse == 0 else -10 * math.log10(mse)

        rows3 = [[f, f"{psnr(imgs[f], imgs['none']):.2f}", f"{psnr(imgs[f], gt):.2f}"] for f in imgs]
        print()
        print(f"## 3. Screen-space filter, {n:,}-Gaussian room at {W}x{H}: PSNR (dB) vs the no-filter render and vs"
              " the 4x-supersampled no-filter render box-averaged to the same size")
        print(_table(["filter", "vs no filter", "vs 4x supersampled"], rows3))
    print(f"\n# load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
