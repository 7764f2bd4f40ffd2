"""A square study dataset's new frames rendered again by ANOTHER scene model: what a change of the scene model
(e.g. the nut asset's orbit views) does to the trained policy, without planning the augmented episodes again.

Run: ``python benchmarks/square_rescene_variant.py --ours square_study/cpu_abs/data/ours_n50.zarr.zip
--work <a copy of the study's work folder> --scene nut_oversample=1.5 n_nut_views=48 --out DIR/ours_X_n50.zarr.zip``
(then ``--ours DIR/ours_X_n50.zarr.zip --rerender --out DIR/ours_rerender_X_n50.zarr.zip`` with the same scene)

Every episode of ``--ours`` is kept with its records and labels; each augmented episode's new frames (``0 ..
splice-1``) are rendered by the scene model that ``--scene`` (:class:`umi_aug.square.scene.SquareSceneConfig`
fields; only the stages they change are retrained in ``--work``) gives, at the episode's own poses, with the
gripper overlay of the demo frames the export chose (the closest gripper width:
:func:`umi_aug.augment.render.overlay_sources`' rule), so each frame is the one the export makes with that scene
model; the replayed tails and the original
demos are copied as stored (:func:`umi_aug.square.variants.write_variant`'s frame replacement, as its
``gt_render``). ``--rerender`` instead keeps every episode of ``--ours`` as stored and adds each demo re-rendered
by the scene model (the ``ours_rerender`` variant of ``--ours``).
Prints the frames written and seconds; the policy trained on the output is compared with the one trained on
``--ours`` (``docs/square_learning.md`` §2e).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.square_demo_rerender import _value  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ours", type=Path, required=True, help="a study's ours_n* dataset")
    ap.add_argument("--demos-dir", type=Path, default=ROOT / "square_demos")
    ap.add_argument("--work", type=Path, required=True, help="stage cache (a copy of the study's work folder)")
    ap.add_argument("--scene", nargs="*", default=[], metavar="KEY=VALUE", help="SquareSceneConfig fields")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--rerender", action="store_true",
                    help="keep --ours as stored and add each demo re-rendered (ours_rerender)")
    ap.add_argument("--image-size", type=int, default=84)
    args = ap.parse_args()

    from umi_aug.augment.config import AugmentConfig
    from umi_aug.augment.export_store import read_episode_records
    from umi_aug.augment.overlay import composite_overlay
    from umi_aug.augment.render import overlay_source_rows, render_view
    from umi_aug.square.source import SquareInput, prepare_square, spartn_render_function
    from umi_aug.square.variants import write_variant

    scene = {k: _value(v) for k, v in (kv.split("=", 1) for kv in args.scene)}
    n_demos = int((read_episode_records(args.ours)["aug_id"] == -1).sum())
    cfg = AugmentConfig(mode="freespace", image_size=args.image_size, include_original=True, workers=1)
    assets = prepare_square(args.demos_dir, args.work, cfg, SquareInput(episodes=tuple(range(n_demos)), scene=scene))
    t0 = time.perf_counter()
    def render_new(episode: int, info: dict) -> np.ndarray:
        h = assets.for_demo(int(info["source"]))
        if "n_new" in info:  # an augmented episode: the gripper of the demo frames the export overlays
            n, d = int(info["n_new"]), h.demos[int(info["source"])]
            rows = overlay_source_rows(d.gripper_width, d.contact_index, info["gripper_width"], n, np.arange(n))
            rendered = np.stack([render_view(h, T) for T in info["T_world_cam"][:n]])
            return composite_overlay(rendered, h.original_frames(int(info["source"]), rows), h.overlay_alpha)
        return spartn_render_function(assets)(episode, info)  # a demo re-rendered (--rerender)

    variant = "ours_rerender" if args.rerender else "gt_render"
    summary = write_variant(variant, args.ours, args.out, n_demos, render_new=render_new,
                            label=f"{'ours_rerender' if args.rerender else 'ours'} rescene {scene}")
    summary["seconds"] = round(time.perf_counter() - t0, 1)
    summary["nut_asset"] = assets.square["scene"].report.get("nut", {})
    print(json.dumps(summary, indent=1, default=str))


if __name__ == "__main__":
    main()
