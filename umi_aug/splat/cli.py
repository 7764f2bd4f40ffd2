"""``umi-aug train-splat SESSION --out DIR``: train the fisheye 3DGS scene of a UMI session (CPU).

Wired into the ``umi-aug`` command by umi_aug/cli.py (``add_train_splat_parser(sub)``)."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

__all__ = ["add_train_splat_parser", "cmd_train_splat"]


def add_train_splat_parser(sub: "argparse._SubParsersAction") -> argparse.ArgumentParser:
    """Add the ``train-splat`` sub-command (imports neither torch nor numba until run)."""
    p = sub.add_parser("train-splat", help="train a fisheye 3D Gaussian Splatting scene on a UMI session (CPU)")
    p.add_argument("session", help="session folder (demos/mapping, demos/demo_*, calibration/)")
    p.add_argument("--out", required=True, help="output folder (scene.ply, checkpoint.pt, metrics.json, PNGs)")
    p.add_argument("--iterations", type=int, default=None, help="training steps (default: SplatTrainConfig's)")
    p.add_argument("--max-gaussians", type=int, default=None, help="Gaussian budget (default: SplatTrainConfig's)")
    p.add_argument("--init-cloud", default=None,
                   help="PLY point cloud with colours for the initial Gaussians (e.g. recon/scene_cloud.ply); "
                        "default: random points around the cameras")
    p.add_argument("--image-size", type=int, default=None, help="train at this width (default: the frames' size)")
    p.add_argument("--recon-report", default=None,
                   help="recon_report.json with the demos' contact frames (default <session>/recon/recon_report.json)")
    p.add_argument("--contact", action="append", default=[], metavar="DEMO=FRAME",
                   help="a demo's contact frame (its frames up to it are used; repeatable)")
    p.add_argument("--demo-stride", type=int, default=4, help="use every n-th pre-contact demo frame")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--restart", action="store_true", help="ignore an existing checkpoint in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_train_splat)
    return p


def cmd_train_splat(args: argparse.Namespace) -> int:
    from umi_aug.errors import SplatError
    from umi_aug.splat.train import SplatTrainConfig
    from umi_aug.splat.train_session import train_splat_from_session

    contact = {}
    for item in args.contact:
        name, _, frame = item.partition("=")
        if not frame.strip().lstrip("-").isdigit():
            raise SplatError(f"--contact {item!r}: expected DEMO=FRAME (an integer frame index)")
        contact[name] = int(frame)
    over = {"seed": args.seed}
    if args.iterations is not None:
        over["iterations"] = args.iterations
    if args.max_gaussians is not None:
        over["max_gaussians"] = args.max_gaussians
    cfg = replace(SplatTrainConfig(), **over)
    r = train_splat_from_session(args.session, args.out, cfg, init_cloud=args.init_cloud, image_size=args.image_size,
                                 contact=contact, recon_report=args.recon_report, demo_stride=args.demo_stride,
                                 resume=not args.restart, progress=not args.no_progress)
    last = r.history[-1]
    print(f"{r.gaussians.n} Gaussians after {last['iteration']} iterations ({last['seconds']:.0f} s training): "
          f"held-out PSNR {r.heldout_psnr:.2f} dB, SSIM {r.heldout_ssim:.4f}; train PSNR {last['train_psnr']:.2f} dB")
    print(json.dumps({"ply": str(r.ply_path), "out": str(r.out_dir)}))
    return 0
