"""The 3DGS learning-rate and growth schedule of a plain dataset's scene, on the real UMI episode (issue #34 item 1):
held-out quality against 3DGS time for short schedules, the scene's other stages built once and shared.

    python benchmarks/splat_schedule.py                       # every setting below
    python benchmarks/splat_schedule.py --settings "before (1200 steps, the trainer's schedule)" default
    python benchmarks/splat_schedule.py --seeds 0 1 2 --settings default "default, 500 steps"

The triangulation, distance field and contacts of ``umi-aug augment <dataset>``'s defaults are built once (stage
cache in ``<work>/stages``); each setting then trains the 3DGS again from the same initial Gaussians (only the
``splat`` stage's key changes) and reports the held-out PSNR / SSIM (every 8th real pre-contact frame, masked), the
Gaussians at the end and the 3DGS training seconds, with the ratio to the first setting's seconds in the same run.
Settings name their changes to the dataset defaults (600 steps, first half at half size, 30k Gaussians, and
``DATASET_SPLAT_SCHEDULE`` in ``umi_aug/augment/splat_defaults.py``); ``trainer`` = the trainer's own rates and growth
(``SplatTrainConfig``'s defaults: 3DGS-MCMC's, made for 30k-step runs), on which the other "trainer + ..." rows
change one thing at a time. Quality does not depend on the load; the seconds do: compare them within one run.

``--seeds`` trains every setting once per root seed (``AugmentConfig.seed``: the 3DGS's view order, relocation and
noise, and the background shell's points); the held-out PSNR moves by a few tenths of a dB with the seed alone, so the
last table pairs each setting with the first by seed. Rows are written as they are trained.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _scratch import claim_scratch_folder, real_episode_missing  # noqa: E402
from real_scene_cost import REAL, configs, seed_paired_table  # noqa: E402
from umi_aug.runtime import configure_threads  # noqa: E402

_TRAINER = {"splat.trainer_schedule": True}
_GROW = {"refine_start": 100, "refine_every": 50, "growth_factor": 1.1}

#: name → ``real_scene_cost.configs`` overrides (``splat.extra`` is laid over the schedule the row starts from).
SETTINGS: dict[str, dict[str, object]] = {
    "before (1200 steps, the trainer's schedule)": {**_TRAINER, "splat.iterations": 1200},
    "trainer, 600 steps": {**_TRAINER, "splat.iterations": 600},
    "trainer + 2x rates (means, scales, opacities, colour)": {
        **_TRAINER, "splat.iterations": 600,
        "splat.extra": {"lr_means": 3.2e-4, "lr_scales": 1e-2, "lr_opacities": 0.1, "lr_sh0": 5e-3}},
    "trainer + 3x position rate": {**_TRAINER, "splat.iterations": 600, "splat.extra": {"lr_means": 4.8e-4}},
    "trainer + position rate decays to 10 % (1 %)": {**_TRAINER, "splat.iterations": 600,
                                                      "splat.extra": {"lr_means_final": 0.1}},
    "trainer + 4x colour rate": {**_TRAINER, "splat.iterations": 600, "splat.extra": {"lr_sh0": 1e-2}},
    "trainer + 8x colour rate": {**_TRAINER, "splat.iterations": 600, "splat.extra": {"lr_sh0": 2e-2}},
    "trainer + 2x scale rate": {**_TRAINER, "splat.iterations": 600, "splat.extra": {"lr_scales": 1e-2}},
    "trainer + half opacity rate": {**_TRAINER, "splat.iterations": 600, "splat.extra": {"lr_opacities": 0.025}},
    "trainer + growth from 100 every 50 by 1.1x": {**_TRAINER, "splat.iterations": 600, "splat.extra": _GROW},
    "trainer + 4x colour, 2x scale": {**_TRAINER, "splat.iterations": 600,
                                      "splat.extra": {"lr_sh0": 1e-2, "lr_scales": 1e-2}},
    "trainer + 4x colour, 2x scale, growth": {**_TRAINER, "splat.iterations": 600,
                                              "splat.extra": {"lr_sh0": 1e-2, "lr_scales": 1e-2, **_GROW}},
    "trainer + 4x colour, 4x higher-degree colour": {**_TRAINER, "splat.iterations": 600,
                                                     "splat.extra": {"lr_sh0": 1e-2, "lr_sh_rest": 5e-4}},
    "trainer + 4x colour, 2x scale, growth, 450 steps": {
        **_TRAINER, "splat.iterations": 450, "splat.extra": {"lr_sh0": 1e-2, "lr_scales": 1e-2, **_GROW}},
    "trainer + 4x colour, 3x scale, growth": {**_TRAINER, "splat.iterations": 600,
                                              "splat.extra": {"lr_sh0": 1e-2, "lr_scales": 1.5e-2, **_GROW}},
    "trainer + 4x colour, 2x scale, growth, 2x position and opacity": {
        **_TRAINER, "splat.iterations": 600,
        "splat.extra": {"lr_sh0": 1e-2, "lr_scales": 1e-2, "lr_means": 3.2e-4, "lr_opacities": 0.1, **_GROW}},
    "trainer + 4x colour, 2x scale, growth, 800 steps": {
        **_TRAINER, "splat.iterations": 800, "splat.extra": {"lr_sh0": 1e-2, "lr_scales": 1e-2, **_GROW}},
    "trainer + 4x colour, 2x scale, growth from 50 by 1.2x": {
        **_TRAINER, "splat.iterations": 600,
        "splat.extra": {"lr_sh0": 1e-2, "lr_scales": 1e-2, "refine_start": 50, "refine_every": 50,
                        "growth_factor": 1.2}},
    "default": {},
    "default, 400 steps": {"splat.iterations": 400},
    "default, 500 steps": {"splat.iterations": 500},
    "default, 550 steps": {"splat.iterations": 550},
    "default, coarse for 3/4 of the steps": {"splat.extra": {"coarse_fraction": 0.75}},
    "default, coarse for 2/3 of the steps": {"splat.extra": {"coarse_fraction": 2 / 3}},
    "default, 20k Gaussians (30k)": {"splat.max_gaussians": 20_000},
    "default, 500 steps, growth from step 50 (100)": {"splat.iterations": 500, "splat.extra": {"refine_start": 50}},
    "default, 500 steps, growth from step 50, coarse for 2/3": {
        "splat.iterations": 500, "splat.extra": {"refine_start": 50, "coarse_fraction": 2 / 3}},
    "default, 450 steps, growth from step 50": {"splat.iterations": 450, "splat.extra": {"refine_start": 50}},
}


def train_setting(dataset: Path, stages: Path, overrides: dict[str, object], seed: int = 0) -> dict:
    """The setting's scene with root seed ``seed`` (its 3DGS trained unless cached with the same key): quality,
    Gaussians, 3DGS seconds."""
    from umi_aug.augment.dataset_source import prepare_dataset

    cfg, inp = configs(overrides, seed)
    t0 = time.perf_counter()
    assets = prepare_dataset(dataset, stages, cfg, inp, renders=True, progress=False)
    g = assets.group_of[0]
    splat = assets.stages[f"{g}/splat"]
    return {"wall_s": time.perf_counter() - t0, "cached": bool(splat.skipped), "psnr": splat.info["heldout_psnr"],
            "ssim": splat.info["heldout_ssim"], "gaussians": splat.info["gaussians"],
            "splat_train_s": splat.info["train_seconds"], "iterations": cfg.splat.iterations,
            "extra": dict(cfg.splat.extra)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default=str(REAL))
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--work", default="/tmp/umi_aug_splat_schedule", help="scratch folder (stage cache, rows)")
    ap.add_argument("--threads", type=int, default=None, help="threads (default: the machine's cores)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0],
                    help="root seeds: every setting is trained once per seed (default: 0)")
    args = ap.parse_args()
    configure_threads(args.threads)
    from rich.console import Console
    from rich.table import Table

    from umi_aug.io_utils import atomic_write_text

    ds, work = Path(args.dataset), Path(args.work)
    error = real_episode_missing(ds) or claim_scratch_folder(work, ".splat_schedule", "it keeps its stage cache there")
    if error:
        print(error, file=sys.stderr)
        return 2
    console, rows = Console(width=200), []
    out = work / "splat_schedule.json"
    for seed in args.seeds:  # seed-major: a run cut short still holds every setting of its first seeds
        for name in args.settings:
            r = {"setting": name, "seed": seed, "overrides": SETTINGS[name],
                 **train_setting(ds, work / "stages", SETTINGS[name], seed)}
            rows.append(r)
            console.print(f"{name}, seed {seed}: {r['psnr']:.2f} dB, {r['splat_train_s']:.1f} s"
                          + (" (cached)" if r["cached"] else ""))
            atomic_write_text(out, json.dumps(rows, indent=2, default=float) + "\n")  # each row as it comes
    ref = {r["seed"]: r["splat_train_s"] for r in rows if r["setting"] == rows[0]["setting"]}
    t = Table(title="the real episode's 3DGS per schedule (held-out every 8th frame; seconds: this run, this load)")
    for c in ("setting", "seed", "steps", "PSNR dB", "SSIM", "Gaussians", "3DGS s", f"x {rows[0]['setting'][:24]}"):
        t.add_column(c, justify="right")
    for r in rows:
        t.add_row(r["setting"], str(r["seed"]), str(r["iterations"]), f"{r['psnr']:.2f}", f"{r['ssim']:.3f}",
                  str(r["gaussians"]), f"{r['splat_train_s']:.1f}" + (" (cached)" if r["cached"] else ""),
                  f"{r['splat_train_s'] / ref[r['seed']]:.2f}")
    console.print(t)
    if len(args.seeds) > 1:
        console.print(seed_paired_table(rows, rows[0]["setting"], seconds=lambda r: r["splat_train_s"],
                                        seconds_name="3DGS s"))
    console.print(f"rows: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
