"""Fisheye 3DGS training on the synthetic UMI session: held-out PSNR / SSIM against training time and iterations
(the error-vs-run-time table). Target (issue #4): held-out PSNR >= 30 dB in <= 15 min on 2 cores.

Run: ``python benchmarks/train.py [--session DIR] [--settings NAME:ITERS:MAX_GAUSSIANS:WIDTH ...] [--threads 2]``

* Session: ``--session`` reuses a folder; otherwise ``umi_aug.sim.session.make_session`` writes one into
  ``--work`` (``--scan-frames`` scan frames, 1 demo, 320x240; reused on the next run). Training views: every scan
  frame + every 4th demo frame up to the contact frame (from ``session.json``); every 8th view held out.
* Initial points: ``--init gt`` = the session's ground-truth scene point cloud (stand-in for an SfM cloud with
  colours; subsampled to the budget), ``--init random`` = random points around the cameras, or a PLY path (e.g.
  ``recon/scene_cloud.ply``).
* Each setting trains from scratch in this process (same seed); the table lists every evaluation; then a summary
  with the time to reach 25 / 28 / 30 dB, the per-stage split of a step and the step time relative to the first
  setting (the in-process reference). The machine is shared: the load average is printed with every setting.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

from umi_aug.runtime import configure_threads  # noqa: E402

DEFAULT_SETTINGS = ("base:3000:60000:0", "budget-25k:3000:25000:0", "half-res:3000:30000:160")
THRESHOLDS_DB = (25.0, 28.0, 30.0)


def _session(args) -> Path:
    if args.session:
        return Path(args.session)
    path = Path(args.work) / f"session_scan{args.scan_frames}"
    if (path / "session.json").is_file():
        return path
    from umi_aug.sim.session import make_session

    print(f"making the synthetic session in {path} ({args.scan_frames} scan frames, 1 demo) ...", flush=True)
    make_session(path, seed=0, scan_frames=args.scan_frames, n_demos=1, benchmark_frames=0,
                 progress=False)
    return path


def _first_reach(history, db: float):
    for h in history:
        if h["heldout_psnr"] is not None and h["heldout_psnr"] >= db:
            return h
    return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--session", default=None)
    ap.add_argument("--work", default="/tmp/umi_aug_bench_train")
    ap.add_argument("--scan-frames", type=int, default=160)
    ap.add_argument("--settings", nargs="+", default=list(DEFAULT_SETTINGS),
                    help="NAME:ITERATIONS:MAX_GAUSSIANS:WIDTH (WIDTH 0 = the frames' size)")
    ap.add_argument("--init", default="gt", help="gt | random | PATH.ply")
    ap.add_argument("--eval-every", type=int, default=500)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    configure_threads(args.threads)
    import logging

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    logging.getLogger("numba").setLevel(logging.WARNING)
    import numba
    import torch

    torch.set_num_threads(args.threads)
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    from umi_aug.splat.train import SplatTrainConfig
    from umi_aug.splat.train_session import train_splat_from_session

    sess = _session(args)
    meta = json.loads((sess / "session.json").read_text())
    contact = {k: int(v["contact"]) for k, v in meta.get("demo_events", {}).items()}
    init = None if args.init == "random" else (
        sess / "ground_truth" / "scene" / "scene_points.ply" if args.init == "gt" else Path(args.init))
    print(f"session {sess}: {meta['sequences']}, contact frames {contact}; init = {args.init}")
    print(f"python {platform.python_version()}, torch {torch.__version__}, threads {args.threads}, "
          f"cpus {os.cpu_count()}, load average at start {os.getloadavg()}")

    results = []
    for spec in args.settings:
        name, iters, budget, width = spec.split(":")
        cfg = replace(SplatTrainConfig(), iterations=int(iters), max_gaussians=int(budget), seed=args.seed,
                      eval_every=args.eval_every, checkpoint_every=int(iters))
        out = Path(args.work) / f"run_{name}"
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        r = train_splat_from_session(sess, out, cfg, init_cloud=init, image_size=int(width) or None,
                                     contact=contact, resume=False, progress=False)
        wall = time.perf_counter() - t0
        load1 = os.getloadavg()[0]
        results.append((name, cfg, int(width), r, wall, (load0, load1)))
        print(f"\n== {name}: {iters} iterations, budget {budget}, width {width or 'native'}; "
              f"wall {wall:.0f} s incl. evaluation; load average {load0:.1f} -> {load1:.1f}; out {out}")
        print(f"{'iter':>6} {'train s':>8} {'#Gauss':>7} {'held PSNR':>9} {'held SSIM':>9} {'train PSNR':>10}")
        for h in r.history:
            print(f"{h['iteration']:>6} {h['seconds']:>8.0f} {h['n_gaussians']:>7} {h['heldout_psnr']:>9.2f} "
                  f"{h['heldout_ssim']:>9.4f} {h['train_psnr']:>10.2f}")

    print("\n== error against run time (held-out PSNR, masked pixels; seconds = training time)")
    head = " ".join(f"{'t@' + str(int(d)) + 'dB':>8}" for d in THRESHOLDS_DB)
    print(f"{'setting':<14} {'final dB':>8} {'SSIM':>6} {'train s':>8} {'s/step':>7} {'ratio':>6} {head}  stage split "
          f"(fraction of step)")
    ref = None
    for name, cfg, width, r, wall, load in results:
        last = r.history[-1]
        per_step = last["seconds"] / max(last["iteration"], 1)
        ref = ref or per_step
        reach = []
        for d in THRESHOLDS_DB:
            h = _first_reach(r.history, d)
            reach.append(f"{h['seconds']:>7.0f}s" if h else f"{'-':>8}")
        tot = sum(r.timings[k] for k in ("render", "loss", "backward", "step", "densify")) or 1.0
        split = ", ".join(f"{k} {r.timings[k] / tot:.2f}" for k in ("render", "loss", "backward", "step", "densify"))
        split += f" (render = project {r.timings['project'] / tot:.2f} + raster {r.timings['raster'] / tot:.2f})"
        print(f"{name:<14} {r.heldout_psnr:>8.2f} {r.heldout_ssim:>6.3f} {last['seconds']:>8.0f} {per_step:>7.3f} "
              f"{per_step / ref:>6.2f} {' '.join(reach)}  {split}")
    print(f"load average at end {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
