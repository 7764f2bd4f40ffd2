"""Fisheye 3DGS training on the synthetic UMI session: held-out PSNR / SSIM against training time and iterations
(the error-vs-run-time table), the fast projection (numba forward + hand-written backward) against the
torch-autograd reference projection in the same run. Targets: issue #4 held-out PSNR >= 30 dB in <= 15 min on 2
cores; issue #17 part 3: 30 dB in <= 2 min.

Run: ``python benchmarks/train.py [--session DIR] [--settings NAME:ITERS:MAX_GAUSSIANS:WIDTH ...]
[--projections fast torch] [--chunk N] [--threads 2]``

* Session: ``--session`` reuses a folder; otherwise ``umi_aug.sim.session.make_session`` writes one into
  ``--work`` (``--scan-frames`` scan frames, 1 demo, 320x240; reused on the next run). Training views: every scan
  frame + every 4th demo frame up to the contact frame (from ``session.json``); every 8th view held out.
* Initial points: ``--init gt`` = the session's ground-truth scene point cloud (stand-in for an SfM cloud with
  colours; subsampled to the budget), ``--init random`` = random points around the cameras, or a PLY path (e.g.
  ``recon/scene_cloud.ply``).
* Each setting trains from scratch once per projection (``fast`` = :class:`umi_aug.splat.project.ProjectGaussians`,
  ``torch`` = the autograd reference; same seed). The runs are interleaved: ``--chunk`` iterations of one, then
  of the other (resumed from their checkpoints; the first in each round alternates), so both see the same machine
  load. Tables: every evaluation (training seconds = wall time of the steps, evaluation excluded; CPU seconds =
  the process's CPU time over the same steps, all threads), the two projections side by side, the time to reach
  25 / 28 / 30 dB, the per-stage split of a step (projection and rasteriser forward / backward) and the step-time
  ratio. The machine is shared: the load average is printed per chunk and summarised per run.
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

DEFAULT_SETTINGS = ("half-res:1500:30000:160",)
THRESHOLDS_DB = (25.0, 28.0, 30.0)
STAGES = ("project", "project_backward", "raster", "raster_backward", "loss", "other_backward", "step", "densify")


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


def _cache_session_views() -> None:
    """Load each session's views once: the interleaved runs resume ``train_splat_from_session`` every chunk, and
    decoding the session's videos again each time would only load the shared machine."""
    import umi_aug.splat.train_session as ts

    load, cache = ts.session_views, {}

    def cached(session_dir, **kw):
        key = (str(session_dir), json.dumps(kw, sort_keys=True, default=str))
        if key not in cache:
            cache[key] = load(session_dir, **kw)
        return cache[key]

    ts.session_views = cached


def _first_reach(history, db: float):
    for h in history:
        if h["heldout_psnr"] is not None and h["heldout_psnr"] >= db:
            return h
    return None


def _split(timings: dict) -> dict[str, float]:
    """Seconds per stage: ``backward`` minus the two measured backwards is what autograd spends elsewhere (the
    reference projection's backward, loss and regularisers)."""
    t = {k: float(timings.get(k, 0.0)) for k in ("project", "raster", "project_backward", "raster_backward", "loss",
                                                  "step", "densify")}
    t["other_backward"] = float(timings["backward"]) - t["project_backward"] - t["raster_backward"]
    t["render_other"] = float(timings["render"]) - t["project"] - t["raster"]
    return t


def _profile_steps(run_dir: Path, sess: Path, width: int, contact: dict, n_views: int) -> None:
    """CPU milliseconds per stage of one training step on the trained scene in ``run_dir`` (its checkpoint), the
    two projections interleaved on the same ``n_views`` random training views, learning rates 0 (the scene does not
    change). The stage clocks of the renderer are switched to this process's CPU time for the measurement, so the
    split does not depend on how the shared machine schedules us."""
    import types

    import numpy as np
    import torch

    import umi_aug.splat.project as project_mod
    import umi_aug.splat.renderer as renderer_mod
    from umi_aug.splat.gaussians import Gaussians
    from umi_aug.splat.losses import photometric_loss
    from umi_aug.splat.optim import GaussianAdam
    from umi_aug.splat.train_session import session_views

    views, intr = session_views(sess, image_size=width or None, contact=contact)
    ck = torch.load(run_dir / "checkpoint.pt", map_location="cpu", weights_only=False)
    params = {k: v.clone().requires_grad_(True) for k, v in ck["params"].items()}
    opt = GaussianAdam(params)
    zero_lr = {k: 0.0 for k in params}
    data = [(torch.from_numpy(v.image.astype(np.float32) / 255.0), torch.from_numpy(v.loss_mask), v.T_world_cam)
            for v in views]
    clock = time.process_time

    def step(i: int, projection: str) -> dict[str, float]:
        img, mask, T = data[i]
        t0 = clock()
        r = renderer_mod.render(Gaussians(**params), T, intr, torch.zeros(3), 3, projection=projection)
        t1 = clock()
        loss, _ = photometric_loss(r.rgb, img, mask, 0.2)
        loss = loss + 0.01 * torch.sigmoid(params["logit_opacities"]).mean() + 0.01 * torch.exp(
            params["log_scales"]).mean()
        t2 = clock()
        loss.backward()
        t3 = clock()
        opt.step(zero_lr)
        opt.zero_grad()
        t4 = clock()
        tm = r.meta["timings"]
        pb, rb = tm.get("project_backward", 0.0), tm.get("raster_backward", 0.0)
        return {"project": tm["project"], "project_backward": pb, "raster": tm["raster"], "raster_backward": rb,
                "loss": t2 - t1, "other_backward": t3 - t2 - pb - rb, "step": t4 - t3, "total": t4 - t0}

    shim = types.SimpleNamespace(perf_counter=clock)
    saved = renderer_mod.time, project_mod.time
    renderer_mod.time = project_mod.time = shim
    try:
        idx = np.random.default_rng(0).choice(len(views), n_views, replace=False)
        step(int(idx[0]), "auto"), step(int(idx[0]), "torch")  # warm-up
        res: dict[str, list] = {"torch": [], "auto": []}
        for j, i in enumerate(idx):
            for proj in (("torch", "auto") if j % 2 else ("auto", "torch")):
                res[proj].append(step(int(i), proj))
    finally:
        renderer_mod.time, project_mod.time = saved
    keys = list(res["torch"][0])
    print(f"\n== CPU ms per step (median of {n_views} views, interleaved; {params['means'].shape[0]} Gaussians at "
          f"{intr.width}x{intr.height}, scene of {run_dir.name}; load average {os.getloadavg()[0]:.1f})")
    print(f"{'proj':>6} " + " ".join(f"{k:>16}" for k in keys))
    med = {p: {k: 1e3 * float(np.median([x[k] for x in v])) for k in keys} for p, v in res.items()}
    for p, name in (("torch", "torch"), ("auto", "fast")):
        print(f"{name:>6} " + " ".join(f"{med[p][k]:>9.1f} ({med[p][k] / med[p]['total']:.2f})" for k in keys))
    t, f = med["torch"], med["auto"]
    share_t = (t["project"] + t["other_backward"] - f["other_backward"]) / t["total"]
    share_f = (f["project"] + f["project_backward"]) / f["total"]
    print(f"step-time ratio torch / fast (CPU): {t['total'] / f['total']:.2f}; projection (forward + backward) share "
          f"of the step: torch {share_t:.2f} (its backward = other_backward minus the fast run's), fast {share_f:.2f}")

def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--session", default=None)
    ap.add_argument("--work", default="/tmp/umi_aug_bench_train")
    ap.add_argument("--scan-frames", type=int, default=160)
    ap.add_argument("--settings", nargs="+", default=list(DEFAULT_SETTINGS),
                    help="NAME:ITERATIONS:MAX_GAUSSIANS:WIDTH (WIDTH 0 = the frames' size)")
    ap.add_argument("--projections", nargs="+", default=["torch", "fast"], choices=["torch", "fast"],
                    help="projections to train with (interleaved); the first is the reference of the ratios")
    ap.add_argument("--chunk", type=int, default=100, help="iterations per turn of the interleaved runs")
    ap.add_argument("--init", default="gt", help="gt | random | PATH.ply")
    ap.add_argument("--eval-every", type=int, default=100)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--profile-views", type=int, default=12,
                    help="after training: CPU split of a step on this many views per projection (0 = skip)")
    ap.add_argument("--profile-only", default=None, metavar="RUN_DIR:WIDTH",
                    help="only the CPU split, on the checkpoint in RUN_DIR (WIDTH 0 = native)")
    args = ap.parse_args()
    configure_threads(args.threads)
    import logging

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    import numba
    import torch

    torch.set_num_threads(args.threads)
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    from umi_aug.splat.train import SplatTrainConfig
    from umi_aug.splat.train_session import train_splat_from_session

    _cache_session_views()
    sess = _session(args)
    meta = json.loads((sess / "session.json").read_text())
    contact = {k: int(v["contact"]) for k, v in meta.get("demo_events", {}).items()}
    init = None if args.init == "random" else (
        sess / "ground_truth" / "scene" / "scene_points.ply" if args.init == "gt" else Path(args.init))
    print(f"session {sess}: {meta['sequences']}, contact frames {contact}; init = {args.init}")
    if args.profile_only:
        run_dir, width = args.profile_only.rsplit(":", 1)
        _profile_steps(Path(run_dir), sess, int(width), contact, args.profile_views)
        return 0
    print(f"python {platform.python_version()}, torch {torch.__version__}, numba {numba.__version__}, "
          f"threads {args.threads} (numba {numba.get_num_threads()}), cpus {os.cpu_count()}, "
          f"load average at start {os.getloadavg()}")

    results = []
    for spec in args.settings:
        name, iters, budget, width = spec.split(":")
        iters = int(iters)
        runs = {}
        for proj in args.projections:
            cfg = replace(SplatTrainConfig(), iterations=iters, max_gaussians=int(budget), seed=args.seed,
                          eval_every=args.eval_every, checkpoint_every=iters, fast_projection=proj == "fast")
            runs[proj] = {"cfg": cfg, "out": Path(args.work) / f"run_{name}_{proj}", "wall": 0.0, "loads": [],
                          "result": None}
        print(f"\n== {name}: {iters} iterations, budget {budget}, width {width or 'native'}; "
              f"interleaved in chunks of {args.chunk}")
        stops = list(range(args.chunk, iters, args.chunk)) + [iters]
        for r_i, stop in enumerate(stops):
            order = args.projections if r_i % 2 == 0 else args.projections[::-1]
            for proj in order:
                run = runs[proj]
                t0 = time.perf_counter()
                run["result"] = train_splat_from_session(
                    sess, run["out"], run["cfg"], init_cloud=init, image_size=int(width) or None, contact=contact,
                    resume=r_i > 0, progress=False, stop_at=stop)
                run["wall"] += time.perf_counter() - t0
                run["loads"].append(os.getloadavg()[0])
                h = run["result"].history[-1]
                print(f"  {proj:>5} to it {stop:>5}: {h['seconds']:7.1f} s train, {h['cpu_seconds']:7.1f} CPU s, "
                      f"held-out {h['heldout_psnr']:.2f} dB (it {h['iteration']}); load {os.getloadavg()[0]:.1f}",
                      flush=True)
        results.append((name, iters, budget, width, runs))
        for proj, run in runs.items():
            r, loads = run["result"], run["loads"]
            print(f"\n-- {name} / {proj}: wall {run['wall']:.0f} s incl. evaluation and resumes; load average "
                  f"{min(loads):.1f}..{max(loads):.1f} (mean {sum(loads) / len(loads):.1f}); out {run['out']}")
            print(f"{'iter':>6} {'train s':>8} {'CPU s':>8} {'#Gauss':>7} {'held PSNR':>9} {'held SSIM':>9} "
                  f"{'train PSNR':>10}")
            for h in r.history:
                print(f"{h['iteration']:>6} {h['seconds']:>8.1f} {h.get('cpu_seconds', float('nan')):>8.1f} "
                      f"{h['n_gaussians']:>7} {h['heldout_psnr']:>9.2f} {h['heldout_ssim']:>9.4f} "
                      f"{h['train_psnr']:>10.2f}")
        if len(runs) == 2:
            (pa, ra), (pb, rb) = runs.items()
            print(f"\n-- {name}: side by side ({pa} | {pb}); ratio = {pa} train s / {pb} train s")
            print(f"{'iter':>6} {pa + ' s':>9} {pb + ' s':>9} {'ratio':>6} {pa + ' CPU s':>11} {pb + ' CPU s':>11} "
                  f"{pa + ' dB':>9} {pb + ' dB':>9}")
            for ha, hb in zip(ra["result"].history, rb["result"].history):
                ratio = ha["seconds"] / hb["seconds"] if hb["seconds"] > 0 else float("nan")
                print(f"{ha['iteration']:>6} {ha['seconds']:>9.1f} {hb['seconds']:>9.1f} {ratio:>6.2f} "
                      f"{ha['cpu_seconds']:>11.1f} {hb['cpu_seconds']:>11.1f} {ha['heldout_psnr']:>9.2f} "
                      f"{hb['heldout_psnr']:>9.2f}")

    print("\n== error against run time (held-out PSNR, masked pixels; train s = wall time of the steps, CPU s = "
          "process CPU time of the steps)")
    head = " ".join(f"{'t@' + str(int(d)) + 'dB':>13}" for d in THRESHOLDS_DB)
    print(f"{'setting':<14} {'proj':>5} {'final dB':>8} {'SSIM':>6} {'train s':>8} {'CPU s':>7} {'s/step':>7} "
          f"{'ratio':>6} {head}   (t@: train s / CPU s)")
    for name, iters, budget, width, runs in results:
        ref = None
        for proj, run in runs.items():
            r = run["result"]
            last = r.history[-1]
            per_step = last["seconds"] / max(last["iteration"], 1)
            ref = ref or per_step
            reach = []
            for d in THRESHOLDS_DB:
                h = _first_reach(r.history, d)
                reach.append(f"{h['seconds']:>6.0f}/{h['cpu_seconds']:<6.0f}" if h else f"{'-':>13}")
            print(f"{name:<14} {proj:>5} {r.heldout_psnr:>8.2f} {r.heldout_ssim:>6.3f} {last['seconds']:>8.0f} "
                  f"{last['cpu_seconds']:>7.0f} {per_step:>7.3f} {ref / per_step:>6.2f} {' '.join(reach)}")
    print("\n== step split (fraction of the training seconds; other_backward = autograd outside the two numba "
          "backwards: the reference projection's backward, loss, regularisers)")
    print(f"{'setting':<14} {'proj':>5} " + " ".join(f"{k:>16}" for k in STAGES) + f" {'s/step':>7}")
    for name, iters, budget, width, runs in results:
        for proj, run in runs.items():
            r = run["result"]
            t = _split(r.timings)
            tot = sum(r.timings[k] for k in ("render", "loss", "backward", "step", "densify")) or 1.0
            steps = max(r.history[-1]["iteration"], 1)
            cells = " ".join(f"{t[k] / tot:>7.3f} {1e3 * t[k] / steps:>6.1f}ms" for k in STAGES)
            print(f"{name:<14} {proj:>5} {cells} {tot / steps:>7.3f}")
    if args.profile_views > 0:
        for name, iters, budget, width, runs in results:
            last = list(runs.values())[-1]
            _profile_steps(last["out"], sess, int(width), contact, args.profile_views)
    print(f"load average at end {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
