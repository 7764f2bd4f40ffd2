"""Command line: ``umi-aug demo | validate | intrinsics``.

``umi-aug demo`` runs every stage that exists end to end on the built-in default scene and says which stages
are not available yet. ``umi-aug validate PATH`` checks a UMI replay buffer (directory or ``.zarr.zip``).
``umi-aug intrinsics FILE`` prints a calibration (UMI/OpenICC JSON or ORB-SLAM3 yaml) and its 224² policy view.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from umi_aug.errors import UmiAugError
from umi_aug.runtime import configure_threads


def _cmd_demo(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from umi_aug.demo.foundation import DemoConfig, run_demo

    console = Console()
    cfg = DemoConfig(out_dir=Path(args.out), seed=args.seed, n_episodes=args.episodes, n_frames=args.frames)
    console.print(f"[bold]umi-aug demo[/bold] on the built-in analytic room → {cfg.out_dir}/")
    summary = run_demo(cfg)

    t = Table(title="what ran")
    t.add_column("item")
    t.add_column("value")
    intr = summary["intrinsics_224"]
    t.add_row("policy camera", f"{intr['width']}×{intr['height']} fx={intr['fx']:.2f} cx={intr['cx']:.2f} cy={intr['cy']:.2f}")
    t.add_row(
        "lens",
        f"KB model valid to θ = {summary['fold_over_deg']:.1f}° (fold-over); the {intr['width']}² crop sees rays up to "
        f"{summary['max_theta_seen_deg']:.1f}°, {100 * summary['fraction_pixels_in_image_circle']:.1f}% of pixels in the image circle",
    )
    t.add_row("cube faces rendered", f"{', '.join(summary['cube_faces_rendered'])} ({summary['cube_face_size']}² px)")
    t.add_row("episodes", f"{summary['episodes']} × {summary['frames_per_episode']} frames")
    t.add_row("start rotations vs reference", ", ".join(f"{a:.0f}°" for a in summary["start_rotation_from_reference_deg"]))
    t.add_row("dataset", f"{summary['dataset']} ({summary['dataset_steps']} steps, validated, read back; "
              f"JPEG-XL mean abs error {summary['jpegxl_mean_abs_error']:.2f}/255)")
    for k, v in summary["timings"].items():
        t.add_row(k, f"{v:.3f}")
    console.print(t)

    s = Table(title="stages")
    s.add_column("stage")
    s.add_column("status")
    s.add_column("what")
    for row in summary["stages"]:
        colour = {"ran": "green", "not yet available": "yellow"}.get(row["status"], "cyan")
        s.add_row(row["stage"], f"[{colour}]{row['status']}[/{colour}]", row["what"])
    console.print(s)
    console.print(
        "Paths are straight-line initial guesses (trajectory optimisation is not available yet) and frames come "
        "from the analytic room (the 3DGS renderer is not available yet).\n"
        f"Pictures: {cfg.out_dir}/lens.png, cone.png, contact_sheet.png; summary: {cfg.out_dir}/summary.json"
    )
    return 0


def _cmd_validate(args: argparse.Namespace) -> int:
    from umi_aug.data import validate_replay_buffer

    report = validate_replay_buffer(Path(args.path))
    print(f"{args.path}: OK — {report.n_episodes} episodes, {report.n_steps} steps")
    for key, info in report.keys.items():
        print(f"  {key}: {info}")
    for w in report.warnings:
        print(f"  warning: {w}")
    return 0


def _cmd_intrinsics(args: argparse.Namespace) -> int:
    from umi_aug.camera.calib_io import load_orbslam3_yaml, load_umi_intrinsics_json

    path = Path(args.path)
    intr = load_orbslam3_yaml(path) if path.suffix in (".yaml", ".yml") else load_umi_intrinsics_json(path)
    import numpy as np

    for name, it in (("file", intr), (f"policy {args.size}²", intr.umi_policy(args.size))):
        print(f"{name}: {it.width}×{it.height} fx={it.fx:.4f} fy={it.fy:.4f} cx={it.cx:.4f} cy={it.cy:.4f} "
              f"k={tuple(round(x, 8) for x in it.k)} fold-over={np.degrees(it.theta_fold):.2f}° "
              f"valid FOV={it.fov_deg:.2f}°")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="umi-aug", description=__doc__.split("\n")[0])
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="run all available stages end to end on the built-in default scene")
    d.add_argument("--out", default="umi_aug_demo", help="output folder (default: ./umi_aug_demo)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--episodes", type=int, default=6, help="generated episodes")
    d.add_argument("--frames", type=int, default=30, help="frames per episode")
    d.set_defaults(func=_cmd_demo)

    v = sub.add_parser("validate", help="validate a UMI replay buffer (directory or .zarr.zip)")
    v.add_argument("path")
    v.set_defaults(func=_cmd_validate)

    i = sub.add_parser("intrinsics", help="show a fisheye calibration (UMI JSON or ORB-SLAM3 yaml)")
    i.add_argument("path")
    i.add_argument("--size", type=int, default=224, help="policy image size")
    i.set_defaults(func=_cmd_intrinsics)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``umi-aug`` command. Exit code 0 on success, 2 on bad input (one clear message)."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    configure_threads()
    try:
        return int(args.func(args))
    except UmiAugError as exc:
        print(f"umi-aug {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
