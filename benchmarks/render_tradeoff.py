"""Render quality against speed (issue #34 item 4): scene budgets and early termination on the synthetic session.

    python benchmarks/render_tradeoff.py                    # all phases: scenes, timed exports, report
    python benchmarks/render_tradeoff.py --phase scenes     # train / cache the scenes, count-based metrics (any load)
    python benchmarks/render_tradeoff.py --phase time       # timed exports (run on idle cores)
    python benchmarks/render_tradeoff.py --phase report --out docs/render_tradeoff

The synthetic UMI session (``umi-aug make-session``, seed 0, one demo, made once in ``<work>/session``) is the scene:
the simulator gives ground truth at every augmented pose. Each *scene setting* (``--scenes``,
``name:max_gaussians:iterations[:opacity_reg:scale_reg]``) trains its own fisheye 3DGS from the session's scan and
demo frames (the reconstruction is built once and shared); each *early-termination threshold* (``--t-min``: a pixel
stops compositing when its transmittance would fall below it; 1e-4 is INRIA 3DGS / gsplat's) renders that scene.

Per point (scene, threshold):

* ``scenes`` phase (counts, not seconds: valid on a loaded machine): held-out PSNR/SSIM of the scene (its training
  hold-out, every 8th view, rendered at the default threshold), Gaussians, and on the new frames of one planned
  free-space episode (24 poses at the policy intrinsics, 224²): Gaussian-pixel evaluations per pixel, and PSNR of
  the threshold's render against the same scene at the default threshold (the error early termination adds).
* ``time`` phase: ``--episodes`` free-space episodes exported with the export's defaults (all fast paths, JPEG-XL
  effort 4, one process) — the same plans for every point — timed per episode (plan + render + encode + write:
  the export's loop, wall clock) = episodes/hour, the median over ``--rounds`` interleaved rounds and every earlier
  run's rounds (``--fresh`` drops those); and, once per point, the augmented frames against the simulator's
  ground truth (PSNR over the lens circle outside the gripper overlay, median of ``--gt-frames`` frames).
* ``report``: the table (Markdown), a plot of PSNR against episodes/hour with the Pareto front and its knee (the
  front's point farthest from the chord between its fastest and its best point, both axes scaled to their range on
  the front), the 2,500 episodes/hour goal, and the JSON, into ``--out``.

Writes ``<work>/render_tradeoff.json`` (phases merge into it). Scene training seconds are stated with the load
average they ran at; only the ``time`` phase's seconds are meant to be compared.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from umi_aug.runtime import configure_threads  # noqa: E402

#: Scene settings: name:max_gaussians:iterations[:opacity_reg:scale_reg] (trainer defaults 0.01 / 0.01).
SCENES = ("g5k:5000:1500", "g10k:10000:1500", "g25k:25000:1500", "g60k:60000:4000",
          "g25k_scale0.1:25000:1500:0.01:0.1", "g25k_scale0.3:25000:1500:0.01:0.3", "g25k_scale1:25000:1500:0.01:1.0",
          "g60k_scale0.3:60000:4000:0.01:0.3", "g60k_scale1:60000:4000:0.01:1.0", "g25k_opac0.05:25000:1500:0.05:0.01",
          "g25k_both:25000:1500:0.05:0.1")
#: Early-termination thresholds (minimum transmittance); 1e-4 = INRIA 3DGS / gsplat, 1/255 = one 8-bit level.
T_MINS = (1e-4, 1.0 / 255.0, 0.01)
DEFAULT_T_MIN = 1e-4
GOAL_EPISODES_PER_HOUR = 2500.0
MARKER = ".render_tradeoff_bench"


@dataclasses.dataclass(frozen=True)
class SceneSetting:
    name: str
    max_gaussians: int
    iterations: int
    opacity_reg: float = 0.01
    scale_reg: float = 0.01

    @classmethod
    def parse(cls, spec: str) -> "SceneSetting":
        parts = spec.split(":")
        if len(parts) not in (3, 5):
            raise SystemExit(f"error: --scenes {spec!r}: expected "
                             "name:max_gaussians:iterations[:opacity_reg:scale_reg]")
        try:
            regs = tuple(float(p) for p in parts[3:])
            return cls(parts[0], int(parts[1]), int(parts[2]), *regs)
        except ValueError:
            raise SystemExit(f"error: --scenes {spec!r}: Gaussians and iterations must be ints, the weights numbers")

    def augment_config(self, n_episodes: int, t_min: float):
        from umi_aug.augment import AugmentConfig, SplatStageConfig

        return AugmentConfig(mode="freespace", n_per_demo=n_episodes, seed=0, render_min_transmittance=t_min,
                             splat=SplatStageConfig(iterations=self.iterations, max_gaussians=self.max_gaussians,
                                                    scale_reg=self.scale_reg,
                                                    extra={"opacity_reg": self.opacity_reg}))


def point_key(scene: str, t_min: float) -> str:
    return f"{scene}@{t_min:.6g}"


def _load(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {"scenes": {}, "points": {}}


def _save(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, path)


def _scene_work(work: Path, s: SceneSetting) -> Path:
    """``<work>/scenes/<name>``: the shared reconstruction's stage folders copied in (same keys: skipped), so that
    only this setting's 3DGS stage is built there (a stage cache keeps one configuration per stage folder)."""
    base, dst = work / "base", work / "scenes" / s.name
    if not dst.exists():
        tmp = dst.with_name(dst.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        for stage in base.iterdir():
            if stage.is_dir() and stage.name != "splat":
                shutil.copytree(stage, tmp / stage.name)
        os.replace(tmp, dst)
    return dst


def _masked_psnr(a, b, valid) -> float:
    import numpy as np

    d = (a.astype(np.float64) - b.astype(np.float64))[valid]
    m = float(np.mean(d ** 2))
    return float("inf") if m == 0 else 10.0 * math.log10(255.0 ** 2 / m)


def _valid_pixels(assets):
    """Pixels inside the lens circle and outside the gripper overlay (what the 3DGS alone decides)."""
    import numpy as np

    from umi_aug.camera.kb import unproject

    S = assets.cfg.image_size
    uu, vv = np.meshgrid(np.arange(S), np.arange(S))
    _, in_lens = unproject(np.stack([uu.ravel(), vv.ravel()], -1).astype(np.float64), assets.policy_intrinsics)
    return in_lens.reshape(S, S) & ~assets.gripper_mask


def scene_phase(session: Path, work: Path, settings: list[SceneSetting], t_mins: list[float], n_frames: int,
                data: dict) -> None:
    import numpy as np

    from umi_aug.augment import plan_episode, prepare_session
    from umi_aug.splat.compose import render_composed, rgb_to_uint8

    base_cfg = settings[0].augment_config(1, DEFAULT_T_MIN)
    prepare_session(session, work / "base", dataclasses.replace(base_cfg, splat=dataclasses.replace(
        base_cfg.splat, iterations=0)), progress=False)  # the shared reconstruction (no 3DGS training here)
    for s in settings:
        cfg = s.augment_config(1, DEFAULT_T_MIN)
        sw = _scene_work(work, s)
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        assets = prepare_session(session, sw, cfg, progress=True)
        built = time.perf_counter() - t0
        man = json.loads((sw / "splat" / "manifest.json").read_text())
        info = assets.stages["splat"].info
        prev = data["scenes"].get(s.name, {})
        row = {"setting": dataclasses.asdict(s), "gaussians": info.get("gaussians"),
               "heldout_psnr": info.get("heldout_psnr"), "heldout_ssim": info.get("heldout_ssim"),
               "train_s": man.get("seconds"),
               "train_load_1min": prev.get("train_load_1min") if built < 1.0 else round(load0, 2)}
        d = assets.augmentable[0]
        planned = plan_episode(assets, d, 0, "freespace")
        ks = np.unique(np.linspace(0, planned.splice_index - 1, n_frames).round().astype(int))
        valid = _valid_pixels(assets)
        S = cfg.image_size
        kw = dict(background=(0.0, 0.0, 0.0), near=cfg.render_near_m, far=cfg.render_far_m)
        ref = None
        per_t = {}
        for t in sorted(t_mins):
            imgs, evals = [], 0
            for k in ks:
                out = render_composed(assets.gaussians, [], planned.episode.T_world_cam[k], assets.policy_intrinsics,
                                      min_transmittance=t, **kw)
                imgs.append(rgb_to_uint8(out.rgb))
                evals += out.meta["n_evals"]
            if t == DEFAULT_T_MIN:
                ref = imgs
            per_t[t] = (imgs, evals / len(ks) / (S * S))
        for t, (imgs, evals_px) in per_t.items():
            p = data["points"].setdefault(point_key(s.name, t), {"scene": s.name, "t_min": t})
            p["evals_per_pixel"] = evals_px
            p["psnr_vs_default_t_db"] = (None if ref is None else
                                         float(np.median([_masked_psnr(a, b, valid) for a, b in zip(imgs, ref)])))
        row["frames"] = int(len(ks))
        data["scenes"][s.name] = row
        print(f"scene {s.name}: {row['gaussians']} Gaussians, held-out {row['heldout_psnr']:.2f} dB, trained in "
              f"{row['train_s']:.0f} s at load {row['train_load_1min']}; evaluations/pixel "
              + ", ".join(f"{t:.4g}: {e:.1f}" for t, (_, e) in sorted(per_t.items())), flush=True)


def time_phase(session: Path, work: Path, settings: list[SceneSetting], t_mins: list[float], n_episodes: int,
               rounds: int, gt_frames: int, data: dict, save, fresh: bool = False) -> None:
    """Timed exports; each run's rounds are added to the points' earlier rounds (``fresh``: replaced), so that
    reruns on idle cores accumulate into one median."""
    import numpy as np

    from augment import _render_profile  # benchmarks/augment.py: where one new frame's time goes

    from umi_aug.augment import export, prepare_session
    from umi_aug.demo.pipeline import compare_with_ground_truth

    def run(s: SceneSetting, t: float, n: int, out: Path):
        if out.exists():
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        return export(session, out, s.augment_config(n, t), work_dir=_scene_work(work, s), resume=False,
                      pictures=False, progress=False)

    run(settings[0], DEFAULT_T_MIN, 1, work / "warmup.zarr.zip")  # numba compiled, caches warm; not counted
    for r in range(rounds):
        for s in settings:
            for t in t_mins:
                key = point_key(s.name, t)
                p = data["points"].setdefault(key, {"scene": s.name, "t_min": t})
                out = work / "exports" / f"{s.name}_t{t:.6g}.zarr.zip"
                out.parent.mkdir(parents=True, exist_ok=True)
                load = os.getloadavg()[0]
                summ = run(s, t, n_episodes, out)
                n = max(1, summ.n_augmented)
                if r == 0 and fresh:
                    p["rounds"] = []
                p.setdefault("rounds", []).append({"loop_s_per_ep": summ.timings_s.get("loop_s", 0.0) / n,
                                    "render_s_per_ep": summ.timings_s.get("render_s", 0.0) / n,
                                    "frames_per_ep": summ.frames_rendered / n, "episodes": summ.n_augmented,
                                    "failed": summ.n_failed, "load_1min": round(load, 2)})
                p["loop_s_per_ep"] = float(np.median([x["loop_s_per_ep"] for x in p["rounds"]]))
                p["render_s_per_ep"] = float(np.median([x["render_s_per_ep"] for x in p["rounds"]]))
                p["episodes_per_hour"] = 3600.0 / p["loop_s_per_ep"]
                assets = prepare_session(session, _scene_work(work, s), s.augment_config(n_episodes, t),
                                         progress=False)
                prof = _render_profile(assets)  # one new frame's parts (24 poses), beside this round's timing
                p.setdefault("profiles", []).append({k: prof[k] for k in ("project", "bin", "raster", "total",
                                                                          "to_uint8", "overlay", "n_evals")})
                if p.get("gt_psnr_db") is None:
                    gt = compare_with_ground_truth(session, out, assets, gt_frames,
                                                   work / "exports" / f"{s.name}_t{t:.6g}_vs_gt.png", lambda m: None)
                    p["gt_psnr_db"] = gt.get("psnr_db_median")
                save()
                gt_db = p.get("gt_psnr_db") or float("nan")
                print(f"round {r + 1}/{rounds} {key}: {p['loop_s_per_ep']:.2f} s/episode "
                      f"({p['episodes_per_hour']:.0f}/h), vs ground truth {gt_db:.2f} dB, load {load:.1f}", flush=True)


def pareto_knee(points: list[dict], x: str, y: str) -> tuple[list[dict], dict | None]:
    """The Pareto front (no other point both faster and better) sorted by speed, and its knee: the front's point
    farthest above the chord from its fastest to its best point, both axes scaled to their range on the front
    (None when the front has fewer than 3 points: the best point is then returned as the knee)."""
    pts = [p for p in points if p.get(x) is not None and p.get(y) is not None]
    front = [p for p in pts if not any((q[x] >= p[x] and q[y] > p[y]) or (q[x] > p[x] and q[y] >= p[y])
                                       for q in pts)]
    front.sort(key=lambda p: p[x])
    if len(front) < 3:
        return front, (max(front, key=lambda p: p[y]) if front else None)
    x0, x1 = front[-1][x], front[0][x]  # fastest, slowest (= best on a front)
    y0, y1 = front[-1][y], front[0][y]
    sx, sy = (x1 - x0) or 1.0, (y1 - y0) or 1.0

    def above_chord(p: dict) -> float:
        u, v = (p[x] - x0) / sx, (p[y] - y0) / sy
        return (v - u) / math.sqrt(2.0)  # signed distance from the line u = v in the scaled square

    return front, max(front, key=above_chord)


def report(data: dict, out: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    pts = [p for p in data["points"].values() if p.get("episodes_per_hour")]
    front, knee = pareto_knee(pts, "episodes_per_hour", "gt_psnr_db")
    best = max(pts, key=lambda p: p.get("gt_psnr_db") or -1.0) if pts else None
    lines = ["| scene | Gaussians | 3DGS steps | opacity / scale reg | held-out dB | train s (load) | T_min | "
             "evals/px | vs full render dB | vs GT dB | render s/ep | wall s/ep | episodes/h | front |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    known = [s.split(":")[0] for s in SCENES]
    order = known + [n for n in data["scenes"] if n not in known]
    for p in sorted(pts, key=lambda p: (order.index(p["scene"]) if p["scene"] in order else len(order), p["t_min"])):
        sc = data["scenes"].get(p["scene"], {})
        st = sc.get("setting", {})
        mark = "**knee**" if p is knee else ("yes" if p in front else "")
        vs_full = p.get("psnr_vs_default_t_db")
        lines.append(
            f"| {p['scene']} | {sc.get('gaussians')} | {st.get('iterations')} | {st.get('opacity_reg')} / "
            f"{st.get('scale_reg')} | {sc.get('heldout_psnr') or float('nan'):.2f} | {sc.get('train_s') or 0:.0f} "
            f"({sc.get('train_load_1min')}) | {p['t_min']:.3g} | {p.get('evals_per_pixel') or float('nan'):.1f} | "
            f"{'—' if vs_full is None or math.isinf(vs_full) else f'{vs_full:.1f}'} | "
            f"{p.get('gt_psnr_db') or float('nan'):.2f} | {p.get('render_s_per_ep', float('nan')):.2f} | "
            f"{p['loop_s_per_ep']:.2f} | {p['episodes_per_hour']:.0f} | {mark} |")
    table = "\n".join(lines)
    (out / "render_tradeoff.md").write_text(table + "\n")
    print(table)
    if knee is not None and best is not None:
        print(f"knee: {knee['scene']} at T_min {knee['t_min']:.3g}: {knee['episodes_per_hour']:.0f} episodes/h, "
              f"{knee['gt_psnr_db']:.2f} dB vs GT ({best['gt_psnr_db'] - knee['gt_psnr_db']:.2f} dB below the best, "
              f"{best['scene']} at {best['t_min']:.3g}: {best['episodes_per_hour']:.0f}/h); goal "
              f"{GOAL_EPISODES_PER_HOUR:.0f}/h = x{GOAL_EPISODES_PER_HOUR / knee['episodes_per_hour']:.2f} the knee")
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    names = list(data["scenes"])
    cmap = plt.get_cmap("tab20")
    for ax, ykey, label in ((axes[0], "gt_psnr_db", "augmented frames vs ground truth (dB, median)"),
                            (axes[1], "heldout", "scene held-out PSNR (dB, default T_min)")):
        for i, name in enumerate(names):
            ps = sorted((p for p in pts if p["scene"] == name), key=lambda p: p["t_min"])
            if not ps:
                continue
            ys = [p.get(ykey) if ykey != "heldout" else data["scenes"][name].get("heldout_psnr") for p in ps]
            ax.plot([p["episodes_per_hour"] for p in ps], ys, "o-", color=cmap(i % 20), label=name, ms=4)
            for p, yv in zip(ps, ys):  # the scene at the default threshold, the threshold elsewhere
                text = name if p["t_min"] == DEFAULT_T_MIN else f"T_min {p['t_min']:.2g}"
                ax.annotate(text, (p["episodes_per_hour"], yv), fontsize=6, xytext=(3, 2), textcoords="offset points")
        ax.axvline(GOAL_EPISODES_PER_HOUR, color="grey", ls="--", lw=1)
        ax.set_xlabel("free-space episodes / hour (2 cores, one process)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    if front:
        axes[0].plot([p["episodes_per_hour"] for p in front], [p["gt_psnr_db"] for p in front], "k:", lw=1,
                     label="Pareto front")
    if knee is not None:
        axes[0].plot([knee["episodes_per_hour"]], [knee["gt_psnr_db"]], "k*", ms=14, label="knee")
    axes[0].legend(fontsize=7)
    axes[0].set_title("augmented frames against the ground truth vs export speed")
    axes[1].set_title("the scene's own held-out PSNR (at the default T_min) vs export speed")
    fig.tight_layout()
    fig.savefig(out / "render_tradeoff.png", dpi=110)
    plt.close(fig)
    _save(out / "render_tradeoff.json", {**data, "knee": None if knee is None else point_key(knee["scene"],
                                                                                             knee["t_min"])})


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", default="/tmp/umi_aug_render_tradeoff")
    p.add_argument("--phase", choices=("all", "scenes", "time", "report"), default="all")
    p.add_argument("--scenes", nargs="+", default=list(SCENES))
    p.add_argument("--t-min", nargs="+", type=float, default=list(T_MINS))
    p.add_argument("--episodes", type=int, default=8, help="free-space episodes per point and round")
    p.add_argument("--rounds", type=int, default=1,
                   help="interleaved timing rounds (added to earlier runs' rounds; the median is reported)")
    p.add_argument("--fresh", action="store_true", help="drop the points' earlier timing rounds")
    p.add_argument("--frames", type=int, default=24, help="new-frame poses of the count-based metrics")
    p.add_argument("--gt-frames", type=int, default=24)
    p.add_argument("--scan-frames", type=int, default=120)
    p.add_argument("--out", default=None, help="report folder (default <work>/report)")
    args = p.parse_args()
    settings = [SceneSetting.parse(s) for s in args.scenes]
    if any(not 0.0 < t < 1.0 for t in args.t_min):
        raise SystemExit(f"error: --t-min {args.t_min}: every threshold must be in (0, 1)")
    if DEFAULT_T_MIN not in args.t_min:
        args.t_min = [DEFAULT_T_MIN, *args.t_min]  # the reference of the 'vs full render' column
    work = Path(args.work)
    from _scratch import claim_scratch_folder  # benchmarks/ (this script's folder) is on sys.path

    err = claim_scratch_folder(work, MARKER, "it keeps scenes and exports there and replaces them")
    if err:
        print(err, file=sys.stderr)
        return 2
    configure_threads()
    import logging
    logging.basicConfig(level=logging.WARNING)
    path = work / "render_tradeoff.json"
    data = _load(path)
    data.setdefault("cpus", os.cpu_count())
    if args.phase in ("all", "scenes", "time"):
        from augment import _session  # benchmarks/augment.py: the synthetic session it makes, made once

        session = _session(work / "session", args.scan_frames)
        if args.phase in ("all", "scenes"):
            scene_phase(session, work, settings, args.t_min, args.frames, data)
            _save(path, data)
        if args.phase in ("all", "time"):
            time_phase(session, work, settings, args.t_min, args.episodes, args.rounds, args.gt_frames, data,
                       lambda: _save(path, data), fresh=args.fresh)
            data["time_phase"] = {"episodes": args.episodes, "rounds": args.rounds,
                                  "date": time.strftime("%Y-%m-%d %H:%M")}
            _save(path, data)
    if args.phase in ("all", "report"):
        report(data, Path(args.out) if args.out else work / "report")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
