"""Per-scene cost and quality on the real UMI episode (issue #34 item 1): each setting builds the episode's whole scene
from an empty stage cache — known-pose triangulation (``scene``), distance field + contacts (``sdf``), fisheye 3DGS
(``splat``), overlay mask — and reports each stage's seconds and the 3DGS's held-out PSNR/SSIM (every 8th real
pre-contact frame, masked), so error stands against run time for every setting.

    python benchmarks/real_scene_cost.py                                  # every setting below
    python benchmarks/real_scene_cost.py --settings default "before (every 2nd frame, 600 steps, full size)"
    python benchmarks/real_scene_cost.py --seeds 0 1 2 \
        --settings default "pose pairs within 0.25 m, 45 deg (none; the default before session 38)"

``--seeds`` builds every setting once per root seed (``AugmentConfig.seed``: the 3DGS's view order, relocation and
noise, the background shell's points): the held-out PSNR moves by a few tenths of a dB with the seed alone, so a
setting's effect on quality is read from the seed-paired differences to the first setting, which the last table
shows (mean and range over the seeds) once there is more than one seed.

Each setting is one change to the defaults of ``umi-aug augment <dataset>`` (every 4th pre-grasp frame
triangulated, matched with its sequential neighbours and the loop grid; 550 3DGS steps with the first half at half
size, 30k Gaussians and the short schedule ``DATASET_SPLAT_SCHEDULE``, ``umi_aug/augment/splat_defaults.py``). Rows
recorded earlier name changes to the defaults of their time: before session 42, 600 3DGS steps (so "3DGS 500 steps
(600)" is 500 steps); before session 38 the triangulation also matched every
two frames within 0.25 m and 45° (pose pairs); before 2026-11-29, 1,200 steps at the trainer's rates and growth;
before 2026-11-27 (session 19), every 2nd frame and 600 full-size steps. ``splat.extra`` is laid over the schedule.
The last five columns split a 3DGS step (ms per step, averaged over the run): the whole step, the rasteriser and the
projection (forward + backward each), the optimiser and the loss's forward (its backward is inside the step's
autograd); the scene column's parts are the triangulation's SIFT extraction, matching and known-pose mapping.

Timings are wall seconds on this machine as it is: run on idle cores (nothing else running) and compare settings
within one run. Goal (#34): a whole scene in <= 45 s on 2 cores at >= 27 dB held-out.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _scratch import claim_scratch_folder, real_episode_missing  # noqa: E402
from umi_aug.runtime import configure_threads  # noqa: E402

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata" / "umi_cup_in_the_wild_ep0" / \
    "dataset.zarr.zip"

#: name → overrides: ``sfm.<field>`` (recon.sfm), ``splat.<field>`` (the 3DGS stage), ``inp.<field>`` (DatasetInput).
SETTINGS: dict[str, dict[str, object]] = {
    "default": {},
    "3DGS schedule before (1200 steps, the trainer's rates and growth)": {"splat.iterations": 1200,
                                                                          "splat.trainer_schedule": True},
    "3DGS 500 steps (600)": {"splat.iterations": 500},
    "3DGS 600 steps (550; the default before session 42)": {"splat.iterations": 600},
    "3DGS 800 steps (600)": {"splat.iterations": 800},
    "before (every 2nd frame, 600 steps, full size)": {"inp.sfm_stride": 2, "inp.sfm_pose_pairs": True,
                                                       "splat.iterations": 600, "splat.coarse_downscale": 1,
                                                       "splat.trainer_schedule": True},
    "features 1024": {"sfm.max_num_features": 1024},
    "no x2 upscale for SIFT": {"inp.sfm_upscale": 1},
    "every 2nd frame to SfM (4th)": {"inp.sfm_stride": 2},
    "overlap 3, no loop grid": {"sfm.overlap": 3, "sfm.loop_stride": 0},
    "overlap 3 (6)": {"sfm.overlap": 3},
    "pose pairs within 0.12 m, 30 deg (none)": {"inp.sfm_pose_pairs": True, "sfm.pose_pair_max_dist_m": 0.12,
                                                "sfm.pose_pair_max_angle_deg": 30.0},
    "pose pairs within 0.25 m, 45 deg (none; the default before session 38)": {"inp.sfm_pose_pairs": True},
    "matches verified by the known poses (COLMAP's two-view RANSAC)": {"inp.sfm_known_pose_verification": True},
    "3DGS 300 steps (600)": {"splat.iterations": 300},
    "3DGS full size (first half at 1/2)": {"splat.coarse_downscale": 1},
    "3DGS coarse for 3/4 of the steps": {"splat.extra": {"coarse_fraction": 0.75}},
    "3DGS 15k Gaussians (30k)": {"splat.max_gaussians": 15_000},
    "no background shell": {"inp.background_points": 0},
    "3DGS scale_reg 1.0 (0.01)": {"splat.scale_reg": 1.0},
    # the same scene (exact: tests/splat/test_render_pixels.py), only the time differs
    "3DGS renders every pixel (only the loss mask's)": {"splat.extra": {"loss_pixels_only": False}},
}

#: The 3DGS step's parts (``SplatTrainResult.timings`` keys) the table shows, in ms per training step.
STEP_PARTS = {"step ms": ("render", "loss", "backward", "step", "densify"),
              "raster ms": ("raster", "raster_backward"), "project ms": ("project", "project_backward"),
              "optimiser ms": ("step",), "loss fwd ms": ("loss",)}
#: The triangulation's parts (``SfmResult.timings_s``): SIFT extraction, matching, known-pose triangulation.
SFM_PARTS = ("extract", "match", "map")


def configs(overrides: dict[str, object], seed: int = 0):
    """``(AugmentConfig, DatasetInput)`` of ``umi-aug augment <dataset>``'s defaults with ``overrides``, its root seed
    ``seed``."""
    from umi_aug.augment.config import DATASET_SPLAT_SCHEDULE, AugmentConfig, dataset_splat_stage
    from umi_aug.augment.dataset_source import DatasetInput

    base = AugmentConfig()
    sfm = dataclasses.replace(base.recon.sfm, mode="known_poses")
    splat = dataset_splat_stage()
    inp = DatasetInput()
    for key, value in overrides.items():
        part, name = key.split(".", 1)
        if part == "sfm":
            sfm = dataclasses.replace(sfm, **{name: value})
        elif key == "splat.extra":  # laid over the dataset's schedule
            splat = dataclasses.replace(splat, extra={**splat.extra, **value})
        elif key == "splat.trainer_schedule":  # the trainer's own rates and growth instead of the dataset's
            splat = dataclasses.replace(splat, extra={k: v for k, v in splat.extra.items()
                                                      if k not in dict(DATASET_SPLAT_SCHEDULE)})
        elif part == "splat":
            splat = dataclasses.replace(splat, **{name: value})
        elif part == "inp":
            inp = dataclasses.replace(inp, **{name: value})
        else:
            raise SystemExit(f"error: setting key {key!r}: expected sfm.*, splat.* or inp.*")
    cfg = dataclasses.replace(base, mode="freespace", splat=splat, recon=dataclasses.replace(base.recon, sfm=sfm),
                              seed=int(seed))
    return cfg, inp


def real_episode_assets(dataset: Path, work: Path):
    """The real episode's demo-0 assets with ``umi-aug augment``'s defaults, its stages built once (cached in
    ``work``): ``(assets, None)``, or ``(None, error line)`` when the episode is not there."""
    from _scratch import real_episode_missing

    from umi_aug.augment.dataset_source import prepare_dataset

    error = real_episode_missing(dataset)
    if error:
        return None, error
    cfg, inp = configs({})
    return prepare_dataset(dataset, work, cfg, inp, progress=False).for_demo(0), None


def build_scene(dataset: Path, work: Path, overrides: dict[str, object], seed: int = 0) -> dict:
    """One scene from an empty cache (root seed ``seed``); per-stage seconds, SfM/cloud sizes and the 3DGS held-out
    quality."""
    from umi_aug.augment.dataset_source import prepare_dataset

    cfg, inp = configs(overrides, seed)
    shutil.rmtree(work, ignore_errors=True)
    t0 = time.perf_counter()
    assets = prepare_dataset(dataset, work, cfg, inp, renders=True, progress=False)
    total = time.perf_counter() - t0
    g = assets.group_of[0]
    st = {k.split("/", 1)[1]: v for k, v in assets.stages.items() if k.startswith(f"{g}/")}
    scene, splat = st["scene"].info, st["splat"].info
    contact = st["contact"].info["demos"][0]
    metrics = st["splat"].dir / "metrics.json"
    m = json.loads(metrics.read_text()) if metrics.is_file() else {}
    steps = max(int(m.get("config", {}).get("iterations", 0)), 1)
    profile = {name: round(1e3 * sum(m.get("timings", {}).get(k, 0.0) for k in keys) / steps, 2)
               for name, keys in STEP_PARTS.items()}
    return {"total_s": total, "contact": contact["contact_index"], "splice": contact["splice_index"],
            "stages_s": {k: round(v.seconds, 2) for k, v in st.items()},
            "registered": scene["sfm"]["registered"], "frames": scene["sfm"]["frames"],
            "points3D": scene["sfm"]["points3D"], "cloud": scene["cloud"]["points"],
            "sfm_s": {k: round(float(scene["sfm"].get("timings_s", {}).get(k, float("nan"))), 2) for k in SFM_PARTS},
            "psnr": splat["heldout_psnr"], "ssim": splat["heldout_ssim"], "gaussians": splat["gaussians"],
            "splat_train_s": splat["train_seconds"], "splat_step_profile": profile}


def _scene_seconds(row: dict) -> float:
    return row["stages_s"].get("scene", 0.0)


def seed_paired(rows: list[dict], reference: str, seconds=_scene_seconds) -> list[dict]:
    """Per setting, over the seeds where both it and ``reference`` built: mean PSNR / ``seconds(row)`` (default: the
    triangulation's) and the seed-paired PSNR differences ``setting - reference`` (their mean, min and max)."""
    ok = {(r["setting"], r["seed"]): r for r in rows if "failed" not in r}
    out = []
    for name in dict.fromkeys(r["setting"] for r in rows):
        seeds = [sd for (n, sd) in ok if n == name and (reference, sd) in ok]
        if not seeds:
            continue
        diff = [ok[(name, sd)]["psnr"] - ok[(reference, sd)]["psnr"] for sd in seeds]
        out.append({"setting": name, "seeds": seeds,
                    "psnr_mean": sum(ok[(name, sd)]["psnr"] for sd in seeds) / len(seeds),
                    "seconds_mean": sum(seconds(ok[(name, sd)]) for sd in seeds) / len(seeds),
                    "diff_mean": sum(diff) / len(diff), "diff_min": min(diff), "diff_max": max(diff)})
    return out


def seed_paired_table(rows: list[dict], reference: str, seconds=_scene_seconds, seconds_name: str = "scene s"):
    """:func:`seed_paired` as a table (``seconds_name``: the column of ``seconds``' mean)."""
    from rich.table import Table

    t = Table(title=f"held-out PSNR against {reference!r}, paired by seed")
    for c in ("setting", "seeds", f"{seconds_name} (mean)", "PSNR dB (mean)", "- reference dB (mean)", "(min / max)"):
        t.add_column(c, justify="right")
    for p in seed_paired(rows, reference, seconds):
        t.add_row(p["setting"], " ".join(map(str, p["seeds"])), f"{p['seconds_mean']:.1f}", f"{p['psnr_mean']:.2f}",
                  f"{p['diff_mean']:+.2f}", f"{p['diff_min']:+.2f} / {p['diff_max']:+.2f}")
    return t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default=str(REAL))
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--work", default="/tmp/umi_aug_real_scene_cost", help="scratch folder (emptied per setting)")
    ap.add_argument("--out", default=None, help="JSON of the rows (default: <work>/real_scene_cost.json)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0],
                    help="root seeds: every setting is built once per seed (default: 0)")
    args = ap.parse_args()
    configure_threads()
    from rich.console import Console
    from rich.table import Table

    from umi_aug.errors import UmiAugError
    from umi_aug.io_utils import atomic_write_text

    ds = Path(args.dataset)
    work = Path(args.work)
    error = real_episode_missing(ds) or claim_scratch_folder(work, ".real_scene_cost", "it is emptied per setting")
    if error:
        print(error, file=sys.stderr)
        return 2
    console, rows = Console(width=200), []
    out = Path(args.out) if args.out else work / "real_scene_cost.json"
    for seed in args.seeds:  # seed-major: a run cut short still holds every setting of its first seeds
        for name in args.settings:
            t0 = time.perf_counter()
            try:  # (COLMAP's glog is kept quiet by recon.sfm)
                r = build_scene(ds, work / "stages", SETTINGS[name], seed)
            except UmiAugError as exc:  # a setting can break a stage (e.g. too sparse a cloud for the contact frame)
                r = {"total_s": time.perf_counter() - t0, "failed": str(exc)}
                console.print(f"{name}, seed {seed}: FAILED after {r['total_s']:.1f} s: {exc}")
            else:
                console.print(f"{name}, seed {seed}: {r['total_s']:.1f} s, {r['psnr']:.2f} dB")
            rows.append({"setting": name, "seed": seed, "overrides": SETTINGS[name], **r})
            atomic_write_text(out, json.dumps(rows, indent=2, default=float) + "\n")  # each row as it comes
    t = Table(title="one real episode's scene from an empty cache (seconds, held-out PSNR/SSIM every 8th frame)")
    for c in ("setting", "seed", "total s", "scene s", "(SIFT / match / map s)", "sdf s", "contact s", "splat s",
              "mask s", "SfM frames", "points", "contact/splice", "PSNR dB", "SSIM", "Gaussians", *STEP_PARTS):
        t.add_column(c, justify="right")
    for r in rows:
        if "failed" in r:
            t.add_row(r["setting"], str(r["seed"]), f"{r['total_s']:.1f}", *(["-"] * 9),
                      "failed: " + r["failed"][-60:], "-", "-", *(["-"] * len(STEP_PARTS)))
            continue
        s = r["stages_s"]
        sfm = " / ".join(f"{r['sfm_s'][k]:.1f}" for k in SFM_PARTS)
        t.add_row(r["setting"], str(r["seed"]), f"{r['total_s']:.1f}", f"{s.get('scene', 0.0):.1f}", sfm,
                  *(f"{s.get(k, 0.0):.1f}" for k in ("sdf", "contact", "splat", "gripper_mask")),
                  f"{r['registered']}/{r['frames']}", str(r["points3D"]), f"{r['contact']}/{r['splice']}",
                  f"{r['psnr']:.2f}", f"{r['ssim']:.3f}",
                  str(r["gaussians"]), *(f"{r['splat_step_profile'][k]:.1f}" for k in STEP_PARTS))
    console.print(t)
    if len(args.seeds) > 1:
        console.print(seed_paired_table(rows, args.settings[0]))
    console.print(f"rows: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
