"""Augmentation pipeline benchmark (issues #9, #17): episodes/hour end to end, the per-stage split, the speed-ups of
issue #17 against their reference paths, JPEG-XL settings (time, bytes, PSNR), on-the-fly Dataset samples/s with 0
and 2 DataLoader workers, and error against run time for a few quality settings (3DGS Gaussian budget / training
steps -> PSNR of augmented frames against the simulator's ground truth vs episodes/hour).

    python benchmarks/augment.py                       # makes a synthetic session in /tmp/umi_aug_bench_augment
    python benchmarks/augment.py --settings base:25000:1500 --rounds 2 --dataset-samples 0
    python benchmarks/augment.py --session DIR --episodes 16 --settings small:10000:800 base:25000:1500

One-time stages (reconstruction, 3DGS training) are reported separately from the per-episode cost; the
episodes/hour figure is the per-episode steady state (plan + render + encode + write: the export's job loop, wall
clock) on this machine. The speed-up table exports the same episodes with each set of fast paths
(``export(fast_paths=...)``), interleaved over ``--rounds`` so that a shared machine's changing load hits every
variant alike; ratios to the reference of the same round are the numbers to quote, and each variant's dataset is
checked byte for byte against the reference's. The machine's load average is printed with the tables.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from umi_aug.runtime import configure_threads  # noqa: E402


def _session(path: Path, scan_frames: int) -> Path:
    from umi_aug.sim.session import make_session

    if not (path / "dataset.zarr.zip").is_file():
        make_session(path, seed=0, n_demos=1, scan_frames=scan_frames, benchmark_frames=0, overwrite=True)
    return path


def _dataset_rate(session: Path, assets, workers: int, n: int) -> float:
    import torch

    from umi_aug.policy.augmented_dataset import AugmentedUmiDataset
    from umi_aug.policy.config import TaskConfig
    from umi_aug.policy.dataset import UmiPolicyDataset

    task = TaskConfig(image_size=assets.cfg.image_size, val_ratio=0.0)
    original = UmiPolicyDataset(session / "dataset.zarr.zip", task, "train")
    ds = AugmentedUmiDataset(original, assets, ("freespace",), ratio=0.9, n_aug_per_demo=n, seed=1)
    idx = list(range(len(original), len(original) + n))
    loader = torch.utils.data.DataLoader(torch.utils.data.Subset(ds, idx), batch_size=8, num_workers=workers,
                                         multiprocessing_context="spawn" if workers else None)
    t0 = time.perf_counter()
    count = sum(len(b["action"]) for b in loader)
    return count / (time.perf_counter() - t0)


#: Speed-up variants of the export: name -> (``fast_paths``, ``AugmentConfig.jpegxl_effort``), timed against the
#: reference (no fast path, libjxl's default effort 7: the export before issue #17).
VARIANTS: dict[str, tuple[tuple[str, ...], int | None]] = {
    "reference": ((), None), "overlay_cache": (("overlay_cache",), None), "encode_ahead": (("encode_ahead",), None),
    "obstacle_tiles": (("obstacle_tiles",), None), "overlay_pixels": (("overlay_pixels",), None),
    "all fast paths": (("overlay_cache", "encode_ahead", "obstacle_tiles", "overlay_pixels"), None),
    "all + effort 4 (default)": (("overlay_cache", "encode_ahead", "obstacle_tiles", "overlay_pixels"), 4)}
#: JPEG-XL settings compared with UMI's (level 99; name -> imagecodecs.jpegxl_encode keywords).
CODECS: dict[str, dict] = {"L99 (UMI)": {"level": 99}, "L99 effort 4": {"level": 99, "effort": 4},
                           "L99 effort 2": {"level": 99, "effort": 2}, "L99 effort 1": {"level": 99, "effort": 1},
                           "L95": {"level": 95}, "L90": {"level": 90}}


def _stored(path: Path) -> dict[str, bytes]:
    return {str(q.relative_to(path)): q.read_bytes() for q in sorted(path.rglob("*")) if q.is_file()}


def _per_ep(s, key: str) -> float:
    return s.timings_s.get(key, 0.0) / max(1, s.n_augmented)


def _cpu_s() -> float:
    """CPU seconds of this process so far, all threads (user + system): a measure of the work done that a shared
    machine's load does not stretch, unlike wall time (but that overlap does not shorten either)."""
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _image_psnr(a: Path, b: Path) -> float:
    """PSNR (dB) between the decoded ``camera0_rgb`` of two exports of the same episodes."""
    import numpy as np

    from umi_aug.data import ReplayBuffer

    with ReplayBuffer.open(a) as x, ReplayBuffer.open(b) as y:
        fa, fb = x["camera0_rgb"][:], y["camera0_rgb"][:]
    if fa.shape != fb.shape:
        return float("nan")
    m = float(np.mean((fa.astype(np.float64) - fb.astype(np.float64)) ** 2))
    return float("inf") if m == 0 else 10 * np.log10(255.0 ** 2 / m)


def _speedups(session: Path, work: Path, cfg, rounds: int) -> dict:
    """Export the same episodes with every variant, ``rounds`` times interleaved; per variant the median of each
    round's stage seconds per episode, episodes/hour and the ratio to that round's reference. Variants with the
    reference's codec effort are checked byte for byte against it; the others by the PSNR of their decoded
    frames against the reference's."""
    import dataclasses

    from umi_aug.augment import export

    # warm-up: plans cached, numba compiled, the scene loaded — none of it counted below
    export(session, work / "tp_warmup.zarr", cfg, work_dir=work / "work", resume=False, pictures=False,
           progress=False)
    runs: dict[str, list] = {v: [] for v in VARIANTS}
    load = [os.getloadavg()[0]]
    for r in range(rounds):
        ref_bytes = None
        for vi, (name, (fast, effort)) in enumerate(VARIANTS.items()):
            out = work / f"tp_{vi}.zarr"
            cpu0 = _cpu_s()
            s = export(session, out, dataclasses.replace(cfg, jpegxl_effort=effort), work_dir=work / "work",
                       resume=False, pictures=False, progress=False, fast_paths=fast)
            cpu = (_cpu_s() - cpu0) / max(1, s.n_augmented)
            stored = _stored(out)
            if ref_bytes is None:
                ref_bytes, ref_out = stored, out
            psnr_ref = None
            if effort == VARIANTS["reference"][1]:
                identical = stored.keys() == ref_bytes.keys() and all(stored[k] == ref_bytes[k] for k in stored)
            else:  # other codec bytes by design: how far the decoded frames are from the reference's
                identical, psnr_ref = None, _image_psnr(out, ref_out)
            runs[name].append({"render": _per_ep(s, "render_s"), "plan": _per_ep(s, "plan_s"),
                               "encode": _per_ep(s, "encode_s"), "write": _per_ep(s, "write_s"),
                               "wall": _per_ep(s, "loop_s"), "cpu": cpu, "identical": identical,
                               "psnr_ref": psnr_ref,
                               "n": s.n_augmented})
            load.append(os.getloadavg()[0])
            same = identical if psnr_ref is None else f"other effort, {psnr_ref:.1f} dB vs reference"
            print(f"  round {r + 1}/{rounds} {name:>24}: {runs[name][-1]['wall']:.2f} s/episode wall, "
                  f"{cpu:.2f} CPU s/episode, byte-identical to reference: {same}", flush=True)
    import numpy as np

    table = {}
    for name, rs in runs.items():
        med = {k: float(np.median([x[k] for x in rs])) for k in ("render", "plan", "encode", "write", "wall", "cpu")}
        ratio = float(np.median([ref["wall"] / x["wall"] for ref, x in zip(runs["reference"], rs)]))
        table[name] = {**med, "episodes_per_hour": 3600.0 / med["wall"], "speedup_vs_reference": ratio,
                       "byte_identical": None if rs[0]["identical"] is None else all(x["identical"] for x in rs),
                       "psnr_vs_reference_db": (None if rs[0]["psnr_ref"] is None
                                                else min(x["psnr_ref"] for x in rs)), "rounds": rs}
    return {"variants": table, "load_1min": load}


def _render_profile(assets, n_frames: int = 24) -> dict:
    """Where a new frame's time goes: the renderer's own stages (summed over ``n_frames`` poses of one planned
    episode) and the Gaussian-pixel evaluations per second of the rasteriser."""
    import numpy as np

    from umi_aug.augment import plan_episode
    from umi_aug.augment.overlay import composite_overlay, overlay_alpha
    from umi_aug.augment.render import overlay_originals, overlay_sources
    from umi_aug.splat.compose import render_composed, rgb_to_uint8

    d = assets.augmentable[0]
    planned = plan_episode(assets, d, 0, "freespace")
    ks = np.unique(np.linspace(0, planned.splice_index - 1, n_frames).round().astype(int))
    cfg, intr = assets.cfg, assets.policy_intrinsics
    acc = {"project": 0.0, "bin": 0.0, "raster": 0.0, "total": 0.0, "to_uint8": 0.0, "overlay": 0.0,
           "n_visible": 0, "n_isects": 0, "n_evals": 0}
    alpha = overlay_alpha(assets.gripper_mask, cfg.overlay.feather_px)
    originals = overlay_originals(assets, d, overlay_sources(assets, planned, ks))
    for k, orig in zip(ks, originals):
        out = render_composed(assets.gaussians, [], planned.episode.T_world_cam[k], intr, background=(0.0, 0.0, 0.0),
                              near=cfg.render_near_m, far=cfg.render_far_m,
                              min_transmittance=cfg.render_min_transmittance)
        for key in ("project", "bin", "raster", "total"):
            acc[key] += out.meta["timings"][key]
        for key in ("n_visible", "n_isects", "n_evals"):
            acc[key] += out.meta[key]
        t0 = time.perf_counter()
        img = rgb_to_uint8(out.rgb)
        t1 = time.perf_counter()
        composite_overlay(img[None], orig[None], alpha)
        t2 = time.perf_counter()
        acc["to_uint8"] += t1 - t0
        acc["overlay"] += t2 - t1
    n = len(ks)
    res = {k: v / n for k, v in acc.items()}
    res["frames"] = n
    res["gaussians"] = assets.gaussians.n
    res["evals_per_s"] = acc["n_evals"] / max(1e-9, acc["raster"])
    return res


def _codec_study(session: Path, work: Path, cfg, n_episodes: int, gt_frames: int) -> list[dict]:
    """JPEG-XL settings on the new frames of ``n_episodes`` free-space episodes: encode ms/frame (1 thread), bytes,
    PSNR against the uncompressed render and against UMI's level 99, and PSNR against the simulator's ground truth
    of a copy of the export whose new-frame chunks hold that setting's bytes (read by the dataset's own codec)."""
    import dataclasses
    import shutil

    import imagecodecs
    import numpy as np

    from umi_aug.augment import export, plan_episode, prepare_session, read_episode_records
    from umi_aug.augment.encode import write_encoded
    from umi_aug.augment.render import render_episode_frames
    from umi_aug.data import ReplayBuffer
    from umi_aug.demo.pipeline import compare_with_ground_truth

    c = dataclasses.replace(cfg, n_per_demo=n_episodes)
    base = work / "codec_base.zarr"
    export(session, base, c, work_dir=work / "work", resume=False, pictures=False, progress=False)
    assets = prepare_session(session, work / "work", c, progress=False)
    rec = read_episode_records(base)
    with ReplayBuffer.open(base) as buf:
        eps = [(int(e), buf.get_episode_slice(int(e)).start) for e in np.flatnonzero(rec["aug_mode"] == 1)]
    raw = {}
    for e, _ in eps:
        planned = plan_episode(assets, int(rec["aug_source_episode"][e]), int(rec["aug_id"][e]), "freespace")
        raw[e] = render_episode_frames(assets, planned, range(planned.splice_index))

    def psnr(x, y):
        m = float(np.mean((x.astype(np.float64) - y.astype(np.float64)) ** 2))
        return float("inf") if m == 0 else 10 * np.log10(255.0 ** 2 / m)

    frames = np.concatenate(list(raw.values()))
    ref_dec = None
    rows = []
    for name, kw in CODECS.items():
        t0 = time.perf_counter()
        enc = [imagecodecs.jpegxl_encode(f, numthreads=1, **kw) for f in frames]
        ms = 1000 * (time.perf_counter() - t0) / len(frames)
        dec = np.stack([imagecodecs.jpegxl_decode(b) for b in enc])
        if ref_dec is None:
            ref_dec = dec
        copy = work / "codec_copy.zarr"
        if copy.exists():
            shutil.rmtree(copy)
        shutil.copytree(base, copy)
        with ReplayBuffer.open(copy, mode="a") as buf:
            arr, i = buf["camera0_rgb"], 0
            for e, start in eps:
                n = len(raw[e])
                write_encoded(arr, start, enc[i:i + n])
                i += n
        with ReplayBuffer.open(copy) as buf:  # the dataset's reader: same shapes, the new pixels
            back = np.concatenate([buf["camera0_rgb"][s:s + len(raw[e])] for e, s in eps])
        assert back.shape == frames.shape and np.array_equal(back, dec)
        gt = compare_with_ground_truth(session, copy, assets, gt_frames, work / f"codec_vs_gt_{name.split()[0]}.png",
                                       lambda m: None)
        rows.append({"codec": name, "kwargs": kw, "encode_ms_per_frame": ms,
                     "bytes_per_frame": float(np.mean([len(b) for b in enc])),
                     "psnr_vs_render_db": psnr(dec, frames), "psnr_vs_L99_db": psnr(dec, ref_dec),
                     "gt_psnr_db": gt.get("psnr_db_median"), "frames": len(frames)})
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--session", default=None, help="UMI session (default: a synthetic one, made once)")
    p.add_argument("--work", default="/tmp/umi_aug_bench_augment")
    p.add_argument("--scan-frames", type=int, default=120)
    p.add_argument("--episodes", type=int, default=8, help="augmented episodes per setting / speed-up variant")
    p.add_argument("--settings", nargs="+", default=["small:10000:600", "base:25000:1500", "large:60000:3000"],
                   help="name:max_gaussians:iterations")
    p.add_argument("--speedup-setting", default="base", help="setting whose scene the speed-up table uses")
    p.add_argument("--speedup-mode", default="freespace", choices=("freespace", "obstacle", "both"),
                   help="episodes of the speed-up table (both: --episodes of each mode)")
    p.add_argument("--rounds", type=int, default=2, help="interleaved rounds of the speed-up variants (0: skip)")
    p.add_argument("--codec-episodes", type=int, default=2, help="episodes of the JPEG-XL study (0: skip)")
    p.add_argument("--gt-frames", type=int, default=24)
    p.add_argument("--dataset-samples", type=int, default=32, help="on-the-fly Dataset samples (0: skip)")
    args = p.parse_args()
    configure_threads()
    logging.basicConfig(level=logging.WARNING)
    from rich.console import Console
    from rich.table import Table

    from umi_aug.augment import AugmentConfig, SplatStageConfig, export, prepare_session
    from umi_aug.demo.pipeline import compare_with_ground_truth

    console = Console(width=200)
    work = Path(args.work)
    session = Path(args.session) if args.session else _session(work / "session", args.scan_frames)
    load0 = os.getloadavg()
    rows, cfgs = [], {}
    for spec in args.settings:
        name, budget, iters = spec.split(":")
        cfg = AugmentConfig(mode="freespace", n_per_demo=args.episodes, seed=0,
                            splat=SplatStageConfig(iterations=int(iters), max_gaussians=int(budget)))
        cfgs[name] = cfg
        out = work / f"export_{name}.zarr.zip"
        if out.exists():
            out.unlink()
        t0 = time.perf_counter()
        s = export(session, out, cfg, work_dir=work / "work", resume=False, pictures=False, progress=False)
        wall = time.perf_counter() - t0
        assets = prepare_session(session, work / "work", cfg, progress=False)
        gt = compare_with_ground_truth(session, out, assets, args.gt_frames, work / f"render_vs_gt_{name}.png",
                                       lambda m: None)
        splat = assets.stages["splat"].info
        rows.append({"setting": name, "gaussians": int(budget), "iterations": int(iters),
                     "one_time_s": round(sum(v["seconds"] for v in s.stages.values()), 1),
                     "heldout_psnr": splat.get("heldout_psnr"), "gt_psnr": gt.get("psnr_db_median"),
                     "plan_s_per_ep": _per_ep(s, "plan_s"), "render_s_per_ep": _per_ep(s, "render_s"),
                     "encode_s_per_ep": _per_ep(s, "encode_s"), "write_s_per_ep": _per_ep(s, "write_s"),
                     "loop_s_per_ep": _per_ep(s, "loop_s"),
                     "frames_per_ep": s.frames_rendered / max(1, s.n_augmented),
                     "episodes_per_hour": 3600.0 / _per_ep(s, "loop_s") if s.n_augmented else float("nan"),
                     "failed": s.n_failed, "resampled": s.n_resampled, "wall_s": round(wall, 1)})
        last_assets = assets

    t = Table(title=f"augmentation end to end ({args.episodes} free-space episodes per setting, 224², "
                    f"{os.cpu_count()} CPUs, all fast paths; load average {load0[0]:.1f})")
    for col in ("setting", "Gaussians", "3DGS steps", "one-time s", "held-out dB", "vs GT dB", "plan s/ep",
                "render s/ep", "encode s/ep (threads)", "write s/ep", "wall s/ep", "new frames/ep", "episodes/hour",
                "failed", "resampled"):
        t.add_column(col, justify="right")
    for r in rows:
        t.add_row(r["setting"], str(r["gaussians"]), str(r["iterations"]), f"{r['one_time_s']:.0f}",
                  f"{r['heldout_psnr'] or float('nan'):.2f}", f"{r['gt_psnr'] or float('nan'):.2f}",
                  f"{r['plan_s_per_ep']:.2f}", f"{r['render_s_per_ep']:.2f}", f"{r['encode_s_per_ep']:.2f}",
                  f"{r['write_s_per_ep']:.2f}", f"{r['loop_s_per_ep']:.2f}", f"{r['frames_per_ep']:.0f}",
                  f"{r['episodes_per_hour']:.0f}", str(r["failed"]), str(r["resampled"]))
    console.print(t)
    result: dict = {"rows": rows, "load_1min_start": load0[0]}

    name = args.speedup_setting if args.speedup_setting in cfgs else next(iter(cfgs))
    if args.rounds > 0:
        console.print(f"speed-ups on the '{name}' scene ({args.episodes} episodes x {len(VARIANTS)} variants x "
                      f"{args.rounds} rounds, interleaved):")
        sp = _speedups(session, work, dataclasses.replace(cfgs[name], mode=args.speedup_mode), args.rounds)
        prof = _render_profile(prepare_session(session, work / "work", cfgs[name], progress=False))
        ld = sp["load_1min"]
        t = Table(title=f"export speed-ups vs the reference path ('{name}' scene, 224², {args.episodes} episodes, "
                        f"median of {args.rounds} interleaved rounds; load average {min(ld):.1f}-{max(ld):.1f} "
                        f"on {os.cpu_count()} CPUs)")
        for col in ("variant", "render s/ep", "encode s/ep (threads)", "write s/ep (main)", "wall s/ep",
                    "CPU s/ep", "episodes/hour", "x reference (same round)", "dataset byte-identical"):
            t.add_column(col, justify="right")
        for v, r in sp["variants"].items():
            t.add_row(v, f"{r['render']:.2f}", f"{r['encode']:.2f}", f"{r['write']:.2f}", f"{r['wall']:.2f}",
                      f"{r['cpu']:.2f}", f"{r['episodes_per_hour']:.0f}", f"{r['speedup_vs_reference']:.2f}",
                      str(r["byte_identical"]) if r["byte_identical"] is not None
                      else f"other effort: {r['psnr_vs_reference_db']:.1f} dB vs reference")
        console.print(t)
        t = Table(title=f"one new frame ({prof['gaussians']} Gaussians, mean of {prof['frames']} poses)")
        for col in ("project ms", "bin ms", "raster ms", "render total ms", "to uint8 ms", "overlay ms",
                    "visible", "tile isects", "Gaussian-pixel evals", "evals/s (raster)"):
            t.add_column(col, justify="right")
        t.add_row(*(f"{1000 * prof[k]:.1f}" for k in ("project", "bin", "raster", "total", "to_uint8", "overlay")),
                  f"{prof['n_visible']:.0f}", f"{prof['n_isects']:.0f}", f"{prof['n_evals'] / 1e6:.2f} M",
                  f"{prof['evals_per_s'] / 1e6:.0f} M")
        console.print(t)
        result.update({"speedups": sp, "render_profile": prof})

    if args.codec_episodes > 0:
        codecs = _codec_study(session, work, cfgs[name], args.codec_episodes, args.gt_frames)
        t = Table(title=f"JPEG-XL settings on {codecs[0]['frames']} new 224² frames ({args.codec_episodes} "
                        f"episodes; UMI writes level 99; 1 encode thread; load average {os.getloadavg()[0]:.1f})")
        for col in ("setting", "encode ms/frame", "x L99", "KB/frame", "PSNR vs render dB", "PSNR vs L99 dB",
                    "vs GT dB (median)"):
            t.add_column(col, justify="right")
        for r in codecs:
            t.add_row(r["codec"], f"{r['encode_ms_per_frame']:.1f}",
                      f"{codecs[0]['encode_ms_per_frame'] / r['encode_ms_per_frame']:.2f}",
                      f"{r['bytes_per_frame'] / 1024:.1f}", f"{r['psnr_vs_render_db']:.2f}",
                      f"{r['psnr_vs_L99_db']:.2f}", f"{r['gt_psnr_db'] or float('nan'):.2f}")
        console.print(t)
        result["codecs"] = codecs

    if args.dataset_samples > 0:
        d = Table(title=f"on-the-fly AugmentedUmiDataset ({rows[-1]['setting']} scene, batch 8, "
                        f"{args.dataset_samples} augmented samples)")
        d.add_column("DataLoader workers", justify="right")
        d.add_column("samples/s", justify="right")
        rates = {}
        for workers in (0, 2):
            rates[workers] = _dataset_rate(session, last_assets, workers, args.dataset_samples)
            d.add_row(str(workers), f"{rates[workers]:.1f}")
        console.print(d)
        result["dataset_samples_per_s"] = rates
    result["load_1min_end"] = os.getloadavg()[0]
    (work / "augment_benchmark.json").write_text(json.dumps(result, indent=2, default=str))


if __name__ == "__main__":
    main()
