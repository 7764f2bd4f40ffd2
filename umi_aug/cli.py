"""Command line: ``umi-aug demo | augment | make-session | reconstruct | train-splat | validate | repair | intrinsics |
square-demos | square-convert | square-init-configs``.

``umi-aug demo`` runs the whole method end to end on the built-in default scene (synthetic session →
reconstruction → fisheye 3DGS → augmented episodes → UMI zarr → check against ground-truth renders).
``umi-aug augment SESSION`` is the offline export on any UMI session. ``umi-aug validate PATH`` checks a UMI replay buffer (directory or ``.zarr.zip``).
``umi-aug repair PATH --out NEW`` writes a repaired copy of a buffer left by an interrupted append (PATH is only read).
``umi-aug make-session --out DIR`` renders a synthetic UMI session of the built-in MuJoCo scene.
``umi-aug intrinsics FILE`` prints a calibration (UMI/OpenICC JSON or ORB-SLAM3 yaml) and its 224² policy view.

The commands import what they run inside their functions (and the sub-command modules ``*/cli.py`` likewise):
building the parser, as ``umi-aug --help`` does, loads no library beyond the standard one.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from umi_aug.errors import UmiAugError
from umi_aug.runtime import configure_threads, interruption, terminate_like_ctrl_c


def _cmd_demo(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from umi_aug.augment.export_report import summary_table
    from umi_aug.demo.pipeline import DemoConfig, run_demo

    console = Console()
    cfg = DemoConfig(out_dir=Path(args.out), seed=args.seed, n_episodes=args.episodes, mode=args.mode,
                     scan_frames=args.scan_frames, splat_iterations=args.splat_iterations)
    console.print(f"[bold]umi-aug demo[/bold] on the built-in MuJoCo tabletop scene (seed {cfg.seed}) → {cfg.out_dir}/")
    summary = run_demo(cfg, say=lambda msg: console.print(f"[cyan]›[/cyan] {msg}"))

    from umi_aug.augment import ExportSummary

    console.print(summary_table(ExportSummary(**summary["export"])))
    t = Table(title="demo: what came out")
    t.add_column("item")
    t.add_column("value")
    sp, gt = summary["splat"], summary["ground_truth_check"]
    t.add_row("dataset", f"{summary['dataset']}: {summary['dataset_episodes']} episodes "
              f"({summary['export']['n_original']} original + {summary['export']['n_augmented']} augmented), "
              f"{summary['dataset_steps']} steps, validated")
    if sp.get("heldout_psnr") is not None:
        t.add_row("3DGS scene", f"{sp.get('gaussians', '?')} Gaussians; held-out scan views PSNR "
                  f"{sp['heldout_psnr']:.2f} dB, SSIM {sp.get('heldout_ssim', float('nan')):.3f}")
    if gt:
        t.add_row("augmented vs ground truth", f"{gt['frames']} free-space frames: PSNR median "
                  f"{gt['psnr_db_median']:.2f} dB (min {gt['psnr_db_min']:.2f}; lens pixels, gripper overlay "
                  f"excluded) → {gt['picture']}")
    for k, v in summary["timings"].items():
        t.add_row(k, f"{v:.1f}")
    console.print(t)

    s = Table(title="stages")
    s.add_column("stage")
    s.add_column("status")
    s.add_column("what")
    for row in summary["stages"]:
        colour = {"ran": "green", "not yet available": "yellow"}.get(row["status"], "cyan")
        s.add_row(row["stage"], f"[{colour}]{row['status']}[/{colour}]", row["what"])
    console.print(s)
    pics = ", ".join(str(v) for v in summary["export"]["pictures"].values())
    console.print(f"Pictures: {pics}, {cfg.out_dir}/lens.png; summary: {cfg.out_dir}/summary.json")
    return 0


def _cmd_validate(args: argparse.Namespace) -> int:
    from umi_aug.augment.export_store import interrupted_export_message
    from umi_aug.data import validate_replay_buffer
    from umi_aug.errors import DatasetError

    path = Path(args.path)
    partial = path.with_name(path.name + ".partial")  # a .zarr.zip export is written from it at the end
    stopped = (interrupted_export_message(path) if path.exists() else
               interrupted_export_message(partial, shown=path) if partial.is_dir() else None)
    if stopped:  # before the layout checks: an interrupted append is the export's to resume, not to repair
        raise DatasetError(stopped)
    report = validate_replay_buffer(path, deep=args.deep, progress=args.deep, umi=True)
    print(f"{args.path}: OK — {report.n_episodes} episodes, {report.n_steps} steps"
          + (", every chunk decoded" if args.deep else ", chunk listing complete (--deep decodes every chunk)"))
    for key, info in report.keys.items():
        print(f"  {key}: {info}")
    for w in report.warnings:
        print(f"  warning: {w}")
    return 0


def _cmd_repair(args: argparse.Namespace) -> int:
    from umi_aug.data.repair import repair_copy

    r = repair_copy(Path(args.path), Path(args.out))
    for note in r.notes:
        print(f"  {note}")
    what = f"repaired copy written ({len(r.notes)} change(s) above)" if r.notes else \
        "copy written; nothing needed a repair"
    print(f"{r.out}: {what} — {r.n_episodes} episodes, {r.n_steps} steps; {args.path} unchanged")
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
    for w in _intrinsics_warnings(intr, path):
        print(f"warning: {w}")
    return 0


#: A fisheye's "valid FOV" above this means the model never folds over (its k do not bound the view): GoPro
#: lenses see about 155 deg, UMI's 2.7k calibration folds at 104 deg from the axis (FOV 208 deg).
FOV_WARN_DEG = 270.0


def _intrinsics_warnings(intr, path: Path) -> list[str]:
    """The session check's warnings for suspicious-but-legal intrinsics (principal point outside the image,
    focal length, k1), and a field of view no lens has."""
    from umi_aug.augment.preflight import intrinsics_warnings

    out = intrinsics_warnings(intr, str(path))
    if intr.fov_deg > FOV_WARN_DEG:
        out.append(f"{path}: valid FOV = {intr.fov_deg:.2f}° is more than a fisheye lens sees (GoPro: about 155°; "
                   f"UMI's calibration folds over at 104° from the axis): the distortion coefficients k = "
                   f"{tuple(round(x, 6) for x in intr.k)} never fold over — a calibration of another camera model?")
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="umi-aug", description=__doc__.split("\n")[0])
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="run all available stages end to end on the built-in default scene")
    d.add_argument("--out", default="umi_aug_demo", help="output folder (default: ./umi_aug_demo)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--episodes", type=int, default=4, help="augmented episodes per mode")
    d.add_argument("--mode", choices=("freespace", "obstacle", "both"), default="both")
    d.add_argument("--scan-frames", type=int, default=120, help="frames of the synthetic mapping scan")
    d.add_argument("--splat-iterations", type=int, default=1500, help="3DGS training steps")
    d.set_defaults(func=_cmd_demo)

    v = sub.add_parser("validate", help="validate a UMI replay buffer (directory or .zarr.zip)")
    v.add_argument("path")
    v.add_argument("--deep", action="store_true", help="decode every chunk (images included), with a progress bar")
    v.set_defaults(func=_cmd_validate)

    r = sub.add_parser("repair", help="write a repaired copy of a replay buffer left by an interrupted append "
                                      "(the input is only read)")
    r.add_argument("path", help="the damaged replay buffer (directory or .zarr.zip); never modified")
    r.add_argument("--out", required=True, help="the new copy (must not exist; a .zip name writes a .zarr.zip)")
    r.set_defaults(func=_cmd_repair)

    i = sub.add_parser("intrinsics", help="show a fisheye calibration (UMI JSON or ORB-SLAM3 yaml)")
    i.add_argument("path")
    i.add_argument("--size", type=int, default=224, help="policy image size")
    i.set_defaults(func=_cmd_intrinsics)

    from umi_aug.sim.cli import add_make_session_parser  # imports neither MuJoCo nor OpenGL

    add_make_session_parser(sub)

    from umi_aug.recon.cli import add_reconstruct_parser  # imports neither pycolmap nor open3d

    add_reconstruct_parser(sub)

    from umi_aug.splat.cli import add_train_splat_parser

    add_train_splat_parser(sub)

    from umi_aug.augment.cli import add_augment_parser

    add_augment_parser(sub).set_defaults(func=_cmd_augment)

    from umi_aug.square.cli import add_square_parsers  # imports neither robosuite nor MuJoCo

    add_square_parsers(sub)
    return p


def _cmd_augment(args: argparse.Namespace) -> int:
    """``umi-aug augment``: the export of any input kind, the square benchmark's demo folders included (their kind
    is registered by importing :mod:`umi_aug.square.source`)."""
    from umi_aug.augment.cli import cmd_augment
    import umi_aug.square.source  # noqa: F401  lazy (torch, the augment stages): registers the kind "square"

    return cmd_augment(args)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``umi-aug`` command. Exit code 0 on success, 2 on bad input (one clear message)."""
    args = build_parser().parse_args(argv)
    # umi-aug's own INFO lines; other libraries' only from WARNING up (PyOpenGL's shutdown notes…) unless -v
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not args.verbose:
        logging.getLogger("umi_aug").setLevel(logging.INFO)
    configure_threads()
    args.argv = list(sys.argv[1:] if argv is None else argv)  # as typed (augment records it to name its resume)
    try:
        with terminate_like_ctrl_c():  # SIGTERM (kill, timeout) ends like Ctrl-C: one line, resumable
            return int(args.func(args))
    except UmiAugError as exc:
        print(f"umi-aug {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # Ctrl-C / SIGTERM: one line, no traceback; outputs are resumable
        how, code = interruption(exc)
        print(f"umi-aug {args.command}: interrupted ({how}); nothing half-written is kept — rerun the same "
              f"command to resume", file=sys.stderr)
        return code
    except OSError as exc:  # the environment (disk full, read-only, permissions): one line naming the path
        if args.verbose:
            raise
        where = f": {exc.filename}" if exc.filename else ""
        print(f"umi-aug {args.command}: error: {exc.strerror or exc}{where} (-v shows the traceback)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
