"""Real UMI data benchmark (issue #13): the fisheye 3DGS of one real demonstration (UMI "cup in the wild",
episode 0, ``../shared/realdata``) — held-out PSNR/SSIM on every 8th real pre-contact frame (masked) against
training time, for several initialisations — and, optionally, the augmentation end to end.

    python benchmarks/real_umi.py --iterations 600 --variants random sfm sfm+bg
    python benchmarks/real_umi.py --iterations 0 --augment 4          # only the export -n 4 --mode both

Variants: ``random`` = the issue reporter's setting (random points around the cameras); ``sfm`` = the episode's own
known-pose triangulation (frames upscaled x2 for SIFT) topped up with random points; ``sfm+bg`` = that plus a
far-background shell of Gaussians (:func:`umi_aug.augment.dataset_source.background_shell_points`).
Timings are the trainer's own clock (evaluation excluded) on this machine, whatever its load: compare variants
within one run.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from umi_aug.runtime import configure_threads  # noqa: E402

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata" / "umi_cup_in_the_wild_ep0" / \
    "dataset.zarr.zip"


def train_variant(assets, variant: str, iterations: int, max_gaussians: int, eval_every: int, out: Path,
                  seed: int = 0) -> dict:
    """Train one initialisation variant on the episode's pre-splice frames; return its history."""
    import numpy as np

    from umi_aug.augment.dataset_source import EpisodePoses, background_shell_points, dataset_views
    from umi_aug.splat.train import SplatTrainConfig, train_splat
    from umi_aug.splat.train_session import random_init_points, read_point_cloud, top_up_init_points

    d = assets.demos[0]
    g = assets.group_of[0]
    views, intr = dataset_views(Path(assets.paths["dataset"]), {0: EpisodePoses(d.name, d.T_world_cam, d.gripper_width)},
                                {0: int(d.contact_index)}, assets.cfg.image_size)
    Tv = np.stack([v.T_world_cam for v in views])
    rng = np.random.default_rng([seed, 0x1A17])
    if variant == "random":
        xyz, rgb = random_init_points(Tv, min(30_000, max_gaussians), rng), None
    else:
        xyz, rgb = read_point_cloud(assets.group_paths[g]["cloud"])
        if variant == "sfm+bg":
            bg = background_shell_points(Tv, max_gaussians // 8, 8.0, rng)
            med = float(np.median(np.stack([v.image for v in views[::8]]))) / 255.0
            xyz, rgb = np.concatenate([xyz, bg]), np.concatenate([rgb, np.full((len(bg), 3), med)])
        xyz, rgb = top_up_init_points(xyz, rgb, max_gaussians // 2, Tv, rng)
    cfg = SplatTrainConfig(iterations=iterations, max_gaussians=max_gaussians, holdout_every=8, seed=seed,
                           eval_every=eval_every, checkpoint_every=max(eval_every, 100))
    t0 = time.perf_counter()
    res = train_splat(views, intr, xyz, rgb, cfg, out / variant, resume=True, progress=False)
    return {"variant": variant, "views": len(views), "heldout_views": len(views[::8]), "init_points": len(xyz),
            "psnr": res.heldout_psnr, "ssim": res.heldout_ssim, "wall_s": time.perf_counter() - t0,
            "history": [{k: h[k] for k in ("iteration", "seconds", "heldout_psnr", "heldout_ssim", "n_gaussians")}
                        for h in res.history]}


def docs_pictures(pictures: dict, docs: Path, width: int = 1100) -> list[str]:
    """Small JPEG copies (at most ``width`` px wide) of the export's contact sheet and trajectory plot."""
    import cv2

    out = []
    for k, v in pictures.items():
        name = "real_contact_sheet.jpg" if k == "contact_sheet" else "real_trajectories.jpg"
        img = cv2.imread(str(v))
        if img is None:
            continue
        if img.shape[1] > width:
            img = cv2.resize(img, (width, round(img.shape[0] * width / img.shape[1])), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(docs / name), img, [cv2.IMWRITE_JPEG_QUALITY, 80])
        out.append(str(docs / name))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", default=str(REAL))
    ap.add_argument("--work", default="/tmp/umi_aug_bench_real")
    ap.add_argument("--stages", default=None, help="stage cache (default <work>/stages; e.g. an export's .work)")
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--max-gaussians", type=int, default=30_000)
    ap.add_argument("--eval-every", type=int, default=100)
    ap.add_argument("--variants", nargs="*", default=["random", "sfm", "sfm+bg"])
    ap.add_argument("--augment", type=int, default=0,
                    help="also run the export with -n N --mode both, with umi-aug augment's defaults for a dataset "
                         "(3DGS steps, budget, regulariser, coarse-to-fine; --augment-iterations overrides the steps)")
    ap.add_argument("--augment-iterations", type=int, default=None, help="3DGS steps of the export's scene")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--docs", action="store_true", help="write small JPEG copies of the pictures to docs/real_*.jpg")
    args = ap.parse_args()
    configure_threads(args.threads)
    logging.basicConfig(level=logging.WARNING)
    from rich.console import Console
    from rich.table import Table

    from umi_aug.augment.config import AugmentConfig
    from umi_aug.augment.dataset_source import DatasetInput, prepare_dataset

    ds = Path(args.dataset)
    if not ds.exists():
        print(f"{ds}: the real demonstration is not here (../shared/realdata is absent); nothing to benchmark")
        return 2
    work = Path(args.work)
    console = Console()
    t0 = time.perf_counter()
    assets = prepare_dataset(ds, Path(args.stages) if args.stages else work / "stages", AugmentConfig(), DatasetInput(), renders=False, progress=False)
    scene_s = time.perf_counter() - t0
    info = assets.stages[f"{assets.group_of[0]}/scene"].info
    console.print(f"scene stage: {scene_s:.1f} s (cached: {assets.stages[f'{assets.group_of[0]}/scene'].skipped}); "
                  f"SfM {info['sfm']['registered']}/{info['sfm']['frames']} frames, {info['sfm']['points3D']} "
                  f"points → cloud {info['cloud']['points']}; splice frame {assets.demos[0].contact_index}")
    rows = []
    if args.iterations > 0:
        for v in args.variants:
            rows.append(train_variant(assets, v, args.iterations, args.max_gaussians, args.eval_every,
                                      work / "splat"))
            console.print(f"{v}: {rows[-1]['psnr']:.2f} dB / SSIM {rows[-1]['ssim']:.3f}")
        t = Table(title=f"fisheye 3DGS on the real episode: held-out every 8th frame (masked), {args.iterations} "
                        f"steps, {args.max_gaussians} Gaussians max")
        for c in ("variant", "step", "train s", "PSNR dB", "SSIM", "Gaussians"):
            t.add_column(c, justify="right")
        for r in rows:
            for h in r["history"]:
                t.add_row(r["variant"], str(h["iteration"]), f"{h['seconds']:.0f}", f"{h['heldout_psnr']:.2f}",
                          f"{h['heldout_ssim']:.3f}", str(h["n_gaussians"]))
        console.print(t)
    aug = None
    if args.augment > 0:
        from umi_aug.augment.export_report import summary_table
        from umi_aug.augment.exporter import export

        from umi_aug.augment.config import dataset_splat_stage

        cfg = AugmentConfig(mode="both", n_per_demo=args.augment,
                            splat=dataset_splat_stage(iterations=args.augment_iterations))
        t1 = time.perf_counter()
        s = export(ds, work / "augmented.zarr.zip", cfg, work_dir=work / "export_work", resume=False)
        aug = {"wall_s": time.perf_counter() - t1, "n_augmented": s.n_augmented, "n_failed": s.n_failed,
               "pictures": s.pictures, "stages": s.stages}
        console.print(summary_table(s))
        if args.docs:
            aug["docs"] = docs_pictures(s.pictures, Path(__file__).resolve().parents[1] / "docs")
    out = work / "real_umi.json"
    out.write_text(json.dumps({"scene_s": scene_s, "scene": info, "variants": rows, "augment": aug}, indent=2,
                              default=float) + "\n")
    console.print(f"results: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
