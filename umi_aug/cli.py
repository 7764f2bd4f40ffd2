"""Command line: ``umi-aug demo | make-session | reconstruct | validate | intrinsics``.

``umi-aug demo`` runs every stage that exists end to end on the built-in default scene and says which stages
are not available yet. ``umi-aug validate PATH`` checks a UMI replay buffer (directory or ``.zarr.zip``).
``umi-aug make-session --out DIR`` renders a synthetic UMI session of the built-in MuJoCo scene.
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

    from umi_aug.demo.pipeline import DemoConfig, run_demo

    console = Console()
    cfg = DemoConfig(out_dir=Path(args.out), seed=args.seed, n_episodes=args.episodes, scan_frames=args.scan_frames)
    console.print(f"[bold]umi-aug demo[/bold] on the built-in MuJoCo tabletop scene (seed {cfg.seed}) → {cfg.out_dir}/")
    summary = run_demo(cfg)

    t = Table(title="what ran")
    t.add_column("item")
    t.add_column("value")
    ri, pi = summary["render_intrinsics"], summary["policy_intrinsics"]
    t.add_row("synthetic session", f"{summary['session']} ({summary['session_frames']} frames: scan + demo {summary['demo']})")
    t.add_row("camera", f"render {ri['width']}×{ri['height']} f={ri['fx']:.2f}; policy {pi['width']}² f={pi['fx']:.2f} "
              f"cx={pi['cx']:.2f} cy={pi['cy']:.2f}")
    t.add_row("lens", f"KB model valid to θ = {summary['fold_over_deg']:.1f}° (fold-over); rays up to "
              f"{summary['max_theta_seen_deg']:.1f}° rendered; cube faces {', '.join(summary['cube_faces_rendered'])} "
              f"({summary['cube_face_size']}² px)")
    t.add_row("new episodes", f"{summary['new_episodes']} optimised approaches into the demo's pre-grasp pose (frame "
              f"{summary['splice_index']}; contact at {summary['contact_index']}), original motion after; "
              f"{summary['new_frames_rendered']} new frames rendered")
    t.add_row("trajectories", f"status {summary['trajectory_status_counts']}; min clearance "
              f"{min(summary['min_clearance_mm']):.1f} mm (required ≥ {max(summary['required_clearance_mm']):.1f} mm); "
              f"solver iterations {summary['solver_iterations']}")
    t.add_row("start rotations vs demo start", ", ".join(f"{a:.0f}°" for a in summary["start_rotation_from_demo_start_deg"]))
    t.add_row("dataset", f"{summary['dataset']} ({summary['dataset_episodes']} episodes, {summary['dataset_steps']} "
              "steps; validated)")
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
        "Trajectories avoid the simulator's exact scene geometry (the reconstructed distance field is not wired in "
        "yet) and new frames come from the simulator's ground-truth scene (the 3DGS renderer is not wired in yet).\n"
        f"Pictures: {cfg.out_dir}/contact_sheet.png, trajectories.png, lens.png, session/contact_sheet.png; "
        f"summary: {cfg.out_dir}/summary.json"
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
    d.add_argument("--episodes", type=int, default=4, help="new episodes generated from the demo")
    d.add_argument("--scan-frames", type=int, default=120, help="frames of the synthetic mapping scan")
    d.set_defaults(func=_cmd_demo)

    v = sub.add_parser("validate", help="validate a UMI replay buffer (directory or .zarr.zip)")
    v.add_argument("path")
    v.set_defaults(func=_cmd_validate)

    i = sub.add_parser("intrinsics", help="show a fisheye calibration (UMI JSON or ORB-SLAM3 yaml)")
    i.add_argument("path")
    i.add_argument("--size", type=int, default=224, help="policy image size")
    i.set_defaults(func=_cmd_intrinsics)

    from umi_aug.sim.cli import add_make_session_parser  # imports neither MuJoCo nor OpenGL

    add_make_session_parser(sub)

    from umi_aug.recon.cli import add_reconstruct_parser  # imports neither pycolmap nor open3d

    add_reconstruct_parser(sub)
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
