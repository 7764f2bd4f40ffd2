"""Square scene model: static scene + nut asset composed per demo vs a 3DGS trained per demo (issue #15 item 1).

Run (CPU setting used for the docs; ~15-25 min on 2 shared cores)::

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 nice -n 10 python benchmarks/square_scene.py \
        --work /tmp/square_scene_bench --demos 3 --poses 12 --picture docs/square_scene_fidelity.png

Reference demo = the first state (its wrist camera and nut centre the static scan; its nut pose is the asset's);
evaluated demos = the next ``--demos`` states (other nut poses: the composition has to move the nut). States come
from ``--shards`` (``square_demos/shards/seed_*.npz``, ``states[0]``) when present, else from
``SquareEnv.reset(seed)`` with seeds 0, 1, ... (how the demos were generated).

Per evaluated demo, ``--poses`` wrist-camera poses: half are cone start poses
(:func:`umi_aug.geometry.sample_cone_start_poses` around the demo's initial camera pose, pivot 0.15 m ahead on its
optical axis, θ = 50°, r = 0.15 m: the study's augmentation cone), half lie on the straight path
(:func:`umi_aug.geometry.interpolate_pose`, fraction U(0.2, 1)) from such a start to the expert's pre-grasp camera
pose (:func:`umi_aug.square.expert.expert_pregrasp_pose` → camera via ``T_CAM_TCP``). Ground truth = the
simulator's fisheye render of the demo's initial state with the robot hidden (``scan`` kind ``"scene"``). Models:

* ``composed``: static 3DGS + nut asset at the demo's nut pose (:func:`render_composed`);
* ``per_demo``: a 3DGS trained on a scan of that demo's own scene (:func:`train_demo_scene`);
* ``static_only``: the static 3DGS without the nut (shows what the nut asset adds).

``--static-iterations / --static-gaussians / --static-scan-views`` give the static scene (trained ONCE for all
demos) its own budget, to compare at equal total cost instead of equal per-model settings.

Metrics: PSNR / SSIM inside the fisheye image circle (median and 5th percentile over all frames), and PSNR over
the nut's pixels (GT nut geoms, dilated 2 px). Cost: training seconds (static + nut once, vs once per demo) and
render milliseconds per frame (interleaved rounds, this process). Writes ``<work>/square_scene_fidelity.json`` and
the picture (rows = poses: GT | composed | per-demo | |GT − composed| | |GT − per-demo|, ×2 nearest).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import numpy as np  # noqa: E402


def _states(env, shards: Path, n: int) -> list[np.ndarray]:
    from umi_aug.square.writers import load_episode

    files = sorted(shards.glob("seed_*.npz")) if shards.is_dir() else []
    if len(files) >= n:
        return [load_episode(f).states[0] for f in files[:n]]
    out = []
    for s in range(n):
        env.reset(seed=s)
        out.append(env.get_state())
    return out


def eval_poses(model, state0: np.ndarray, n: int, seed: int) -> np.ndarray:
    """``[n, 4, 4]`` wrist-camera poses: ceil(n/2) cone starts, the rest on straight paths to the pre-grasp pose."""
    from umi_aug.geometry import interpolate_pose, pose_inverse, sample_cone_start_poses
    from umi_aug.square.camera import T_CAM_TCP, camera_pose_cv
    from umi_aug.square.expert import expert_pregrasp_pose
    from umi_aug.square.scan import body_pose, data_at_state

    rng = np.random.default_rng(seed)
    data = data_at_state(model, state0)
    T_ref = camera_pose_cv(model, data)
    pivot = T_ref[:3, 3] + 0.15 * T_ref[:3, 2]
    n_cone = (n + 1) // 2
    starts = sample_cone_start_poses(T_ref, pivot, math.radians(50.0), n_cone, rng, radius=0.15)
    table_z = float(data.site_xpos[_site(model, "table_top")][2])
    T_pre = expert_pregrasp_pose(body_pose(model, data), table_z) @ pose_inverse(T_CAM_TCP)
    path = [interpolate_pose(starts[i % n_cone], T_pre, float(rng.uniform(0.2, 1.0))) for i in range(n - n_cone)]
    return np.concatenate([starts, np.asarray(path).reshape(-1, 4, 4)])


def _site(model, name: str) -> int:
    from umi_aug.sim.gl import import_mujoco

    mj = import_mujoco()
    return mj.mj_name2id(model, mj.mjtObj.mjOBJ_SITE, name)


def _dilate(m: np.ndarray, r: int) -> np.ndarray:
    out = m.copy()
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            out |= np.roll(np.roll(m, dy, 0), dx, 1)
    return out


def _metrics(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray, nut: np.ndarray) -> dict[str, float]:
    import torch

    from umi_aug.splat.losses import masked_psnr, masked_ssim

    p = torch.from_numpy(pred.astype(np.float32) / 255.0)
    t = torch.from_numpy(gt.astype(np.float32) / 255.0)
    v = torch.from_numpy(valid)
    out = {"psnr": masked_psnr(p, t, v), "ssim": float(masked_ssim(p, t, v))}
    out["nut_psnr"] = masked_psnr(p, t, torch.from_numpy(nut)) if nut.any() else float("nan")
    return out


def _stats(v: list[float]) -> dict[str, float]:
    a = np.asarray([x for x in v if np.isfinite(x)], dtype=np.float64)
    if a.size == 0:
        return {"median": float("nan"), "p5": float("nan"), "mean": float("nan"), "n": 0}
    return {"median": float(np.median(a)), "p5": float(np.percentile(a, 5)), "mean": float(a.mean()), "n": int(a.size)}


def _picture(rows: list[tuple[np.ndarray, ...]], path: Path) -> None:
    from PIL import Image, ImageDraw

    tiles = []
    for gt, comp, per in rows:
        d1 = np.clip(np.abs(gt.astype(np.int16) - comp.astype(np.int16)) * 3, 0, 255).astype(np.uint8)
        d2 = np.clip(np.abs(gt.astype(np.int16) - per.astype(np.int16)) * 3, 0, 255).astype(np.uint8)
        tiles.append(np.concatenate([gt, comp, per, d1, d2], axis=1))
    img = np.concatenate(tiles, axis=0).repeat(2, 0).repeat(2, 1)
    head = 16
    canvas = Image.new("RGB", (img.shape[1], img.shape[0] + head), (255, 255, 255))
    canvas.paste(Image.fromarray(img), (0, head))
    w = img.shape[1] // 5
    dr = ImageDraw.Draw(canvas)
    for i, t in enumerate(["GT (robot hidden)", "composed", "per-demo", "|GT-composed| x3", "|GT-per-demo| x3"]):
        dr.text((i * w + 3, 2), t, fill=(0, 0, 0))
    path.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/square_scene_bench"))
    ap.add_argument("--shards", type=Path, default=ROOT / "square_demos" / "shards")
    ap.add_argument("--demos", type=int, default=3, help="evaluated demos (besides the reference)")
    ap.add_argument("--poses", type=int, default=12, help="poses per evaluated demo")
    ap.add_argument("--size", type=int, default=84)
    ap.add_argument("--scan-views", type=int, default=40)
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--gaussians", type=int, default=12000)
    ap.add_argument("--nut-iterations", type=int, default=800)
    ap.add_argument("--nut-gaussians", type=int, default=3000)
    ap.add_argument("--nut-size", type=int, default=None, help="orbit image size (default: density-matched)")
    ap.add_argument("--nut-oversample", type=float, default=1.5)
    ap.add_argument("--static-iterations", type=int, default=None, help="static scene only (default: --iterations)")
    ap.add_argument("--static-gaussians", type=int, default=None, help="static scene only (default: --gaussians)")
    ap.add_argument("--static-scan-views", type=int, default=None, help="static scan only (default: --scan-views)")
    ap.add_argument("--timing-rounds", type=int, default=5)
    ap.add_argument("--picture", type=Path, default=None)
    ap.add_argument("--picture-rows", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)

    from umi_aug.runtime import configure_threads
    from umi_aug.splat.compose import render_composed, rgb_to_uint8
    from umi_aug.splat.ply import read_ply
    from umi_aug.splat.renderer import render
    from umi_aug.square.camera import wrist_intrinsics
    from umi_aug.square.env import SquareEnv
    from umi_aug.square.scan import ScanRenderer, body_pose, data_at_state, hidden_geom_ids
    from umi_aug.square.scene import (SquareSceneConfig, build_square_scene, scene_parts, train_demo_scene)

    configure_threads(int(os.environ.get("NUMBA_NUM_THREADS", "1")))
    load0 = open("/proc/loadavg").read().split()[:3]
    print(f"load average at start: {' '.join(load0)}", flush=True)
    cfg = SquareSceneConfig(image_size=a.size, n_scan_views=a.scan_views, static_iterations=a.iterations,
                            static_max_gaussians=a.gaussians, nut_iterations=a.nut_iterations,
                            nut_max_gaussians=a.nut_gaussians, nut_image_size=a.nut_size,
                            nut_oversample=a.nut_oversample, seed=a.seed)
    from dataclasses import replace

    cfg_static = replace(cfg, static_iterations=a.static_iterations or a.iterations,
                         static_max_gaussians=a.static_gaussians or a.gaussians,
                         n_scan_views=a.static_scan_views or a.scan_views)  # the amortised model may be larger
    env = SquareEnv(image_size=None)
    model = env.model
    states = _states(env, a.shards, a.demos + 1)
    prog = not a.no_progress

    t0 = time.perf_counter()
    scene = build_square_scene(a.work, env, states[0], cfg_static, progress=prog)
    build_wall = time.perf_counter() - t0
    per_demo = []
    for s in states[1:]:
        per_demo.append(train_demo_scene(a.work, env, s, cfg, progress=prog))

    intr = wrist_intrinsics(a.size)
    nut_geoms = set(range(model.ngeom)) - set(hidden_geom_ids(model, "nut").tolist())
    frames = []
    times = {"composed": [], "per_demo": []}
    demo_rows = []
    with ScanRenderer(model, "scene", intr) as gt_r:
        valid = gt_r.renderer.valid_mask
        for d, (s, pd) in enumerate(zip(states[1:], per_demo)):
            poses = eval_poses(model, s, a.poses, a.seed + 1000 + d)
            gt = gt_r.render(s, poses)
            T_nut = body_pose(model, data_at_state(model, s))
            dR = scene.T_world_nut_ref[:3, :3].T @ T_nut[:3, :3]
            demo_rows.append({"demo": d + 1, "nut_offset_m": float(np.linalg.norm(T_nut[:3, 3] -
                                                                                   scene.T_world_nut_ref[:3, 3])),
                              "nut_yaw_vs_reference_deg": float(np.degrees(np.arctan2(dR[1, 0], dR[0, 0])))})
            static, placed = scene_parts(scene, T_nut)
            g_demo = read_ply(pd.ply)
            for i, T in enumerate(poses):
                comp = rgb_to_uint8(render_composed(static, placed, T, intr, background=(0.0, 0.0, 0.0)).rgb)
                per = rgb_to_uint8(render(g_demo, T, intr, (0.0, 0.0, 0.0)).rgb)
                stat = rgb_to_uint8(render(static, T, intr, (0.0, 0.0, 0.0)).rgb)
                nut = _dilate(np.isin(gt.geom_id[i], list(nut_geoms)), 2) & valid
                rec = {"demo": d + 1, "pose": i, "kind": "cone" if i < (a.poses + 1) // 2 else "path",
                       "nut_pixels": int(nut.sum())}
                for name, img in (("composed", comp), ("per_demo", per), ("static_only", stat)):
                    rec[name] = _metrics(img, gt.rgb[i], valid, nut)
                frames.append((rec, gt.rgb[i], comp, per))
            # interleaved timing rounds (same poses, same process)
            for _ in range(a.timing_rounds):
                for T in poses[:4]:
                    tc = time.perf_counter()
                    render_composed(static, placed, T, intr, background=(0.0, 0.0, 0.0))
                    times["composed"].append(time.perf_counter() - tc)
                    tc = time.perf_counter()
                    render(g_demo, T, intr, (0.0, 0.0, 0.0))
                    times["per_demo"].append(time.perf_counter() - tc)
    env.close()

    recs = [f[0] for f in frames]
    summary = {}
    for name in ("composed", "per_demo", "static_only"):
        summary[name] = {m: _stats([r[name][m] for r in recs]) for m in ("psnr", "ssim", "nut_psnr")}
    rep = scene.report
    cost = {
        "composed_train_s": {"static": rep["static"]["train_seconds"], "nut": rep["nut"]["train_seconds"],
                             "total_once": rep["static"]["train_seconds"] + rep["nut"]["train_seconds"]},
        "per_demo_train_s": [p.report["train_seconds"] for p in per_demo],
        "render_ms": {k: 1000.0 * float(np.median(v)) for k, v in times.items()},
        "gaussians": {"static": rep["static"]["gaussians"], "nut": rep["nut"]["gaussians"],
                      "per_demo": [p.report["gaussians"] for p in per_demo]},
        "build_wall_s_this_run": build_wall,
    }
    load1 = open("/proc/loadavg").read().split()[:3]
    for row in demo_rows:
        row["composed_nut_psnr_median"] = _stats([r["composed"]["nut_psnr"] for r in recs if r["demo"] == row["demo"]])[
            "median"]
        row["per_demo_nut_psnr_median"] = _stats([r["per_demo"]["nut_psnr"] for r in recs if r["demo"] == row["demo"]])[
            "median"]
    out = {"config": {**cfg.__dict__, "demos": a.demos, "poses": a.poses}, "config_static": cfg_static.__dict__,
           "summary": summary, "cost": cost,
           "demos": demo_rows,
           "heldout": {"static": rep["static"], "nut": rep["nut"], "per_demo": [p.report for p in per_demo]},
           "frames": recs, "loadavg_start": load0, "loadavg_end": load1,
           "command": " ".join(["python", "benchmarks/square_scene.py", *(argv if argv is not None else sys.argv[1:])])}
    a.work.mkdir(parents=True, exist_ok=True)
    (a.work / "square_scene_fidelity.json").write_text(json.dumps(out, indent=1, default=float) + "\n")

    print(f"\n{len(recs)} frames ({a.demos} demos x {a.poses} poses), {a.size}x{a.size}, inside the image circle")
    print(f"{'model':<12} {'PSNR med':>9} {'PSNR p5':>8} {'SSIM med':>9} {'SSIM p5':>8} {'nut PSNR med':>13} "
          f"{'nut p5':>7}")
    for name, s in summary.items():
        print(f"{name:<12} {s['psnr']['median']:9.2f} {s['psnr']['p5']:8.2f} {s['ssim']['median']:9.4f} "
              f"{s['ssim']['p5']:8.4f} {s['nut_psnr']['median']:13.2f} {s['nut_psnr']['p5']:7.2f}")
    ct = cost["composed_train_s"]
    print(f"train s: composed static {ct['static']:.0f} + nut {ct['nut']:.0f}"
          f" (once); per-demo {', '.join(f'{t:.0f}' for t in cost['per_demo_train_s'])} (each demo)")
    print(f"render ms/frame (median, interleaved): composed {cost['render_ms']['composed']:.1f}, "
          f"per-demo {cost['render_ms']['per_demo']:.1f}")
    held = ", ".join(f"{p.report['heldout_psnr']:.2f}" for p in per_demo)
    print(f"held-out PSNR: static {rep['static']['heldout_psnr']:.2f}, nut {rep['nut']['heldout_psnr']:.2f}, per-demo "
          f"{held}")
    for row in demo_rows:
        print(f"demo {row['demo']}: nut {100 * row['nut_offset_m']:.1f} cm / "
              f"{row['nut_yaw_vs_reference_deg']:+.0f} deg from the reference; nut PSNR composed {row['composed_nut_psnr_median']:.2f}, per-demo "
              f"{row['per_demo_nut_psnr_median']:.2f}")
    print(f"load average: start {' '.join(load0)}, end {' '.join(load1)}")
    if a.picture is not None:
        pick = np.linspace(0, len(frames) - 1, min(a.picture_rows, len(frames))).round().astype(int)
        _picture([frames[i][1:] for i in pick], a.picture)
        print(f"picture: {a.picture}")
    print(f"json: {a.work / 'square_scene_fidelity.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
