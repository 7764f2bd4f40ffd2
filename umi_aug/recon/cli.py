"""``umi-aug reconstruct SESSION``: the reconstruction stage from the command line (wired in umi_aug/cli.py)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

__all__ = ["add_reconstruct_parser", "cmd_reconstruct"]


def add_reconstruct_parser(sub: "argparse._SubParsersAction") -> argparse.ArgumentParser:
    """Add the ``reconstruct`` sub-command (imports neither pycolmap nor open3d)."""
    p = sub.add_parser("reconstruct", help="SfM scene cloud, scene SDF and contact frames of a UMI session")
    p.add_argument("session", help="session folder (demos/mapping, demos/demo_*, calibration/)")
    p.add_argument("--out", default=None, help="output folder (default <session>/recon)")
    p.add_argument("--mode", choices=("known_poses", "full"), default="known_poses",
                   help="triangulate with the session's SLAM poses, or full SfM + Sim(3) alignment")
    p.add_argument("--features", type=int, default=2048, help="SIFT features per frame")
    p.add_argument("--cone-deg", type=float, default=45.0, help="start-pose cone half-angle bounding the SDF")
    p.add_argument("--voxel-mm", type=float, default=None, help="SDF voxel (default: chosen from the region)")
    p.add_argument("--contact-threshold-mm", type=float, default=30.0)
    p.add_argument("--contact", action="append", default=[], metavar="DEMO=FRAME",
                   help="override a demo's contact frame (repeatable)")
    p.set_defaults(func=cmd_reconstruct)
    return p


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from umi_aug.errors import ReconError
    from umi_aug.recon.pipeline import ReconConfig, reconstruct_session
    from umi_aug.recon.sfm import SfmConfig

    def need(ok: bool, flag: str, value, want: str) -> None:  # every flag before any work (SfM takes minutes)
        if not ok:
            raise ReconError(f"{flag} {value}: {want}")

    need(args.voxel_mm is None or 0.5 <= args.voxel_mm <= 200.0, "--voxel-mm", args.voxel_mm,
         "must be in [0.5, 200] mm (the SDF voxel; omit it to choose one from the region)")
    need(args.features >= 64, "--features", args.features, "must be >= 64 (SIFT features per frame)")
    need(0.0 < args.cone_deg <= 180.0, "--cone-deg", args.cone_deg, "must be in (0, 180] degrees")
    need(0.0 < args.contact_threshold_mm <= 1000.0, "--contact-threshold-mm", args.contact_threshold_mm,
         "must be in (0, 1000] mm")
    if args.out and Path(args.out).exists() and not Path(args.out).is_dir():
        raise ReconError(f"--out {args.out}: is a file, not a folder: choose another --out")
    overrides = {}
    for item in args.contact:
        name, _, frame = item.partition("=")
        if not frame.strip().lstrip("-").isdigit():
            raise ReconError(f"--contact {item!r}: expected DEMO=FRAME (an integer frame index)")
        overrides[name] = int(frame)
    cfg = ReconConfig(sfm=SfmConfig(mode=args.mode, max_num_features=args.features),
                      cone_half_angle_deg=args.cone_deg,
                      voxel_m=None if args.voxel_mm is None else args.voxel_mm / 1000.0,
                      contact_threshold_m=args.contact_threshold_mm / 1000.0, contact_overrides=overrides)
    out = Path(args.out) if args.out else Path(args.session) / "recon"
    o = reconstruct_session(args.session, out, cfg)
    r = o.report
    print(f"SfM {r['sfm']['mode']}: {r['sfm']['registered']}/{r['sfm']['frames']} frames registered, "
          f"{r['sfm']['points3D']} points, {r['sfm']['mean_reproj_error_px']:.2f} px; Sim(3) residual "
          f"{r['sim3']['residual_rms_m'] * 1000:.1f} mm; cloud {r['cloud']['points']} points; SDF "
          f"{r['sdf']['shape']} at {r['sdf']['voxel_m'] * 1000:.1f} mm")
    for c in r["contacts"]:
        print(f"  {c['episode']}: contact frame {c['contact_index']} (proximity {c['proximity_index']})"
              + (f" — {c['message']}" if c["message"] else ""))
    print(json.dumps(o.paths))
    return 0
