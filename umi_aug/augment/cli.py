"""``umi-aug augment SESSION --mode … -n … --out PATH``: the offline export from the command line (wired in
umi_aug/cli.py). The command imports the pipeline inside :func:`cmd_augment`: building the parser loads none of it."""

from __future__ import annotations

import argparse
import dataclasses

from umi_aug.augment.splat_defaults import DATASET_SPLAT_ITERATIONS, DATASET_SPLAT_MAX_GAUSSIANS

__all__ = ["add_augment_parser", "cmd_augment", "config_from_args", "dataset_input_from_args", "check_args",
           "source_settings_from_args"]

#: ``--tcp-offset``: UMI's gripper has 0.205 m; a camera→TCP distance outside this range is a typo (mm, a sign)
#: that used to fail only minutes later ("no splice frame", "points near the reachable region").
DEFAULT_TCP_OFFSET_M = 0.205
TCP_OFFSET_RANGE_M = (0.02, 0.5)
#: flags of the "plain dataset / square demo folder input" group → the input kinds they apply to
#: (:func:`umi_aug.augment.sources.source_kind`)
INPUT_FLAGS = {"--episodes": ("dataset", "square"), "--scene-group": ("dataset",), "--scene-map": ("dataset",),
               "--tcp-offset": ("dataset",), "--no-embodiment": ("square",)}


def add_augment_parser(sub: "argparse._SubParsersAction") -> argparse.ArgumentParser:
    """Add the ``augment`` sub-command (imports nothing heavy)."""
    p = sub.add_parser("augment", help="augmented UMI dataset (original + new episodes) from a session or dataset")
    p.add_argument("session", help="UMI session folder (demos/mapping, demos/demo_*, calibration/, dataset.zarr.zip), "
                   "a plain UMI dataset (*.zarr.zip / zarr directory: scenes built from its own frames), or a "
                   "square demo folder (`umi-aug square-demos` output: simulator scene model, Panda-feasible paths)")
    p.add_argument("--mode", choices=("freespace", "obstacle", "both"), default="freespace")
    p.add_argument("-n", "--n-per-demo", type=int, default=4, help="augmented episodes per demo and mode")
    p.add_argument("--out", required=True, help="output dataset (*.zarr.zip, or a zarr directory)")
    p.add_argument("--work", default=None, help="stage cache folder (default <out>.work)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--image-size", type=int, default=224, help="policy image side (the session dataset's)")
    p.add_argument("--cone-deg", type=float, default=50.0, help="start cone half-angle θ (degrees)")
    p.add_argument("--cone-radius", type=float, default=0.15, help="start sphere radius r (metres)")
    p.add_argument("--splat-iterations", type=int, default=None,
                   help="3DGS training steps (0 = untrained init; default 1500 for a session's scan, "
                        f"{DATASET_SPLAT_ITERATIONS} for a plain dataset's episode frames, with a short schedule's "
                        "learning rates and growth: docs/real_scale.md section 1f)")
    p.add_argument("--splat-max-gaussians", type=int, default=None,
                   help=f"3DGS Gaussian budget (default 25000 for a session, {DATASET_SPLAT_MAX_GAUSSIANS} for a dataset)")
    p.add_argument("--splat-coarse-downscale", type=int, default=None, metavar="F",
                   help="3DGS coarse-to-fine: the first half of the steps on frames downscaled by F (1 = full size; "
                        "default 1 for a session, 2 for a plain dataset)")
    p.add_argument("--sfm-mode", choices=("known_poses", "full"), default="known_poses")
    p.add_argument("--obstacle", action="append", default=None, metavar="ASSET",
                   help="obstacle asset (box/cylinder/bottle/mug or a mesh path); repeatable")
    p.add_argument("--mask", choices=("auto", "predefined", "estimated"), default="auto", help="gripper overlay mask")
    p.add_argument("--mirrors", choices=("auto", "source", "scene"), default="auto",
                   help="UMI's side mirrors in augmented frames: source = the pixels of the overlay's original frame "
                        "(black / swapped / reflection, as the dataset has them), scene = the 3DGS render; auto = "
                        "source unless the frames show no mirror there")
    p.add_argument("--max-attempts", type=int, default=8, help="resamples per episode before it counts as failed")
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local: this process (1 worker) or spawned processes; ray: a Ray cluster")
    p.add_argument("--workers", type=int, default=1,
                   help="tasks in parallel: episodes, and a plain dataset's scene builds (ahead of their episodes)")
    p.add_argument("--ray-address", default=None,
                   help="existing Ray cluster, e.g. auto or ray://HOST:10001 (default: start a local one); "
                        "--work must then be on a filesystem every node mounts at the same path")
    p.add_argument("--no-original", action="store_true", help="do not copy the original episodes")
    p.add_argument("--rerender-originals", action="store_true",
                   help="also write each augmented demo once more with its approach (the frames before the splice) "
                        "rendered by the scene model at its own poses, labels unchanged: the policy sees the same "
                        "approach in the camera's and the renders' look (aug_mode 3; docs/square_learning.md §2e)")
    p.add_argument("--jpegxl-effort", default="4", metavar="1..9|default",
                   help="libjxl encoder effort of the new frames (4: ~3x faster than libjxl's default 7 with the "
                        "same PSNR; 'default': the library's own, as UMI's writer)")
    p.add_argument("--restart", action="store_true", help="discard a previous/interrupted export at --out instead of resuming (only one "
                   "umi-aug wrote: inputs and other folders are refused)")
    p.add_argument("--no-pictures", action="store_true")
    g = p.add_argument_group("plain dataset / square demo folder input")
    g.add_argument("--episodes", default=None, metavar="A:B",
                   help="episodes to augment, e.g. 0:50 or 0,3,7:9 (default all; the others are copied unchanged)")
    g.add_argument("--no-embodiment", action="store_true",
                   help="square demos: skip the simulated Panda's feasibility check of each trajectory")
    g.add_argument("--scene-group", default=None, metavar="N|auto",
                   help="N consecutive episodes share one scene (default 1: a scene per episode); 'auto': episodes "
                        "recorded in one place share a scene (found from frames at nearby poses whose matches agree "
                        "with the poses; up to 4 per scene; evidence in <work>/scene_groups.json)")
    g.add_argument("--scene-map", default=None, metavar="JSON",
                   help='JSON file {"scene": [episode, ...]} or [[episode, ...], ...] of episodes sharing a scene')
    g.add_argument("--tcp-offset", type=float, default=None,
                   help=f"UMI's tcp_offset (m, gripper tip to mount) of the camera→TCP transform (default "
                        f"{DEFAULT_TCP_OFFSET_M}; {TCP_OFFSET_RANGE_M[0]}..{TCP_OFFSET_RANGE_M[1]})")
    p.set_defaults(func=cmd_augment)
    return p


def config_from_args(args: argparse.Namespace):
    """The :class:`AugmentConfig` of parsed arguments."""
    from umi_aug.augment.config import (AugmentConfig, ObstacleConfig, OverlayConfig, SplatStageConfig,
                                        dataset_splat_stage)
    from umi_aug.augment.sources import source_kind

    base = AugmentConfig()
    given = {"iterations": args.splat_iterations, "max_gaussians": args.splat_max_gaussians,
             "coarse_downscale": getattr(args, "splat_coarse_downscale", None)}
    if source_kind(args.session) == "dataset":
        splat = dataset_splat_stage(**given)
    else:
        splat = SplatStageConfig(**{k: (getattr(base.splat, k) if v is None else v) for k, v in given.items()},
                                 scale_reg=base.splat.scale_reg)
    return AugmentConfig(
        mode=args.mode, n_per_demo=args.n_per_demo, seed=args.seed, image_size=args.image_size,
        cone_half_angle_deg=args.cone_deg, cone_radius_m=args.cone_radius, max_attempts=args.max_attempts,
        splat=splat,
        recon=dataclasses.replace(base.recon, sfm=dataclasses.replace(base.recon.sfm, mode=args.sfm_mode)),
        obstacle=ObstacleConfig(assets=tuple(args.obstacle)) if args.obstacle else ObstacleConfig(),
        overlay=OverlayConfig(mask=args.mask, mirrors=args.mirrors), include_original=not args.no_original,
        executor=args.executor, workers=args.workers, ray_address=args.ray_address,
        jpegxl_effort=_effort_arg(getattr(args, "jpegxl_effort", "4")),
        rerender_originals=bool(getattr(args, "rerender_originals", False)))


def _effort_arg(value: str | int | None) -> int | None:
    """``--jpegxl-effort``: an int 1..9, or ``default``/``none`` (libjxl's own)."""
    from umi_aug.errors import AugmentError

    if value is None or str(value).strip().lower() in ("default", "none"):
        return None
    try:
        return int(value)
    except ValueError:
        raise AugmentError(f"--jpegxl-effort {value!r}: expected an int in 1..9 or 'default'") from None


def check_args(args: argparse.Namespace) -> None:
    """Every flag checked before any work: ranges (named as typed), and the input-specific flags refused on an
    input they do not apply to (they were silently ignored). Raises :class:`AugmentError` (one line)."""
    from umi_aug.augment.sources import source_kind
    from umi_aug.errors import AugmentError

    kind = source_kind(args.session)
    given = {"--episodes": args.episodes is not None, "--scene-group": args.scene_group is not None,
             "--scene-map": args.scene_map is not None, "--tcp-offset": args.tcp_offset is not None,
             "--no-embodiment": bool(args.no_embodiment)}
    wrong = [f for f, on in given.items() if on and kind not in INPUT_FLAGS[f]]
    if wrong:
        what = {"session": "a UMI session folder (all its demos are augmented)", "dataset": "a plain UMI dataset",
                "square": "a square demo folder"}[kind]
        names = {"dataset": "a plain dataset", "square": "a square demo folder"}
        applies = "; ".join(f"{f} applies to {' or '.join(names[k] for k in INPUT_FLAGS[f])} input" for f in wrong)
        raise AugmentError(f"{', '.join(wrong)}: {args.session} is {what}; {applies}: drop "
                           f"{'it' if len(wrong) == 1 else 'them'}")

    def need(ok: bool, flag: str, value, want: str) -> None:
        if not ok:
            raise AugmentError(f"{flag} {value}: {want}")

    need(args.n_per_demo >= 1, "-n/--n-per-demo", args.n_per_demo, "must be >= 1")
    need(args.image_size >= 8, "--image-size", args.image_size, "must be >= 8 pixels (the dataset's frame side)")
    need(0.0 < args.cone_deg <= 180.0, "--cone-deg", args.cone_deg, "must be in (0, 180] degrees")
    need(0.0 < args.cone_radius < 10.0, "--cone-radius", args.cone_radius, "must be in (0, 10) metres")
    need(args.splat_iterations is None or args.splat_iterations >= 0, "--splat-iterations", args.splat_iterations,
         "must be >= 0 (0 = the untrained initial scene)")
    need(args.splat_max_gaussians is None or args.splat_max_gaussians >= 1, "--splat-max-gaussians",
         args.splat_max_gaussians, "must be >= 1")
    coarse = getattr(args, "splat_coarse_downscale", None)
    need(coarse is None or (coarse >= 1 and args.image_size % coarse == 0), "--splat-coarse-downscale", coarse,
         f"must be >= 1 and divide --image-size {args.image_size} (1 = full size)")
    need(args.max_attempts >= 1, "--max-attempts", args.max_attempts, "must be >= 1")
    need(args.workers >= 1, "--workers", args.workers, "must be >= 1")
    need(args.scene_group is None or _scene_group_arg(args.scene_group) is not None, "--scene-group",
         args.scene_group, "expected an int >= 1 or 'auto'")
    lo, hi = TCP_OFFSET_RANGE_M
    need(args.tcp_offset is None or lo <= args.tcp_offset <= hi, "--tcp-offset", args.tcp_offset,
         f"must be in [{lo}, {hi}] m (UMI's gripper: {DEFAULT_TCP_OFFSET_M} m, the distance from the camera to the "
         "fingertips' TCP along its axis)")
    effort = _effort_arg(args.jpegxl_effort)
    need(effort is None or 1 <= effort <= 9, "--jpegxl-effort", args.jpegxl_effort, "expected an int in 1..9 or "
         "'default'")


def _scene_group_arg(value) -> int | str | None:
    """``--scene-group``: ``"auto"`` or an int >= 1 (None: neither)."""
    from umi_aug.augment.dataset_source import parse_scene_group

    return parse_scene_group(value)


def dataset_input_from_args(args: argparse.Namespace):
    """The :class:`~umi_aug.augment.dataset_source.DatasetInput` of parsed arguments (used for a plain dataset)."""
    from umi_aug.augment.dataset_source import DatasetInput, load_scene_map, parse_episodes
    from umi_aug.errors import AugmentError

    raw = getattr(args, "scene_group", None)
    scene_group = 1 if raw is None else _scene_group_arg(raw)
    tcp_offset = getattr(args, "tcp_offset", None)
    if scene_group is None:
        raise AugmentError(f"--scene-group {raw!r}: expected an int >= 1 or 'auto'")
    return DatasetInput(tcp_offset_m=float(DEFAULT_TCP_OFFSET_M if tcp_offset is None else tcp_offset),
                        episodes=parse_episodes(getattr(args, "episodes", None)),
                        scene_group=scene_group,
                        scene_map=load_scene_map(args.scene_map) if getattr(args, "scene_map", None) else None)


def source_settings_from_args(kind: str, args: argparse.Namespace):
    """The input settings of a ``kind`` input (:func:`umi_aug.augment.sources.source_kind`) from its flags: a plain
    dataset's :class:`~umi_aug.augment.dataset_source.DatasetInput`, a registered kind's own (its ``from_cli``:
    a square folder's ``SquareInput``), None for a session (it has none)."""
    from umi_aug.augment.sources import settings_from_cli

    if kind == "dataset":
        return dataset_input_from_args(args)
    return settings_from_cli(kind, args)


def cmd_augment(args: argparse.Namespace) -> int:
    from rich.console import Console

    from umi_aug.augment.export_report import summary_table
    from umi_aug.augment.exporter import export
    from umi_aug.augment.sources import open_source, source_kind

    check_args(args)  # before any work: a bad flag costs nothing
    cfg = config_from_args(args)
    source = open_source(args.session, source_settings_from_args(source_kind(args.session), args))
    argv = getattr(args, "argv", None)  # the command as typed, without --restart: the one that resumes this export
    command = (["umi-aug", *[a for a in argv if not (a.startswith("--re") and "--restart".startswith(a))]]
               if argv else None)  # argparse takes any unique prefix (--re, --rest, ...) for --restart
    s = export(args.session, args.out, cfg, resume=not args.restart, work_dir=args.work,
               pictures=not args.no_pictures, source=source, command=command)
    console = Console()
    console.print(summary_table(s))
    for k, v in s.pictures.items():
        console.print(f"{k}: {v}")
    return 0 if s.n_failed == 0 else 3
