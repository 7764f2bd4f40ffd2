"""``umi-aug make-session``: argparse wiring and the command (hooked into :mod:`umi_aug.cli`).

Importing this module imports neither MuJoCo nor OpenGL.
"""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["add_make_session_parser", "cmd_make_session"]


def add_make_session_parser(sub: "argparse._SubParsersAction") -> argparse.ArgumentParser:
    """Add the ``make-session`` sub-command to ``sub`` (the CLI's subparsers) and return its parser."""
    from umi_aug.sim.session import SessionConfig

    d = SessionConfig()
    p = sub.add_parser(
        "make-session",
        help="render a synthetic UMI session (mapping scan + demos, fisheye, with ground truth) from the "
             "built-in MuJoCo tabletop scene",
    )
    p.add_argument("--out", required=True, help="output session folder (must not exist or be empty)")
    p.add_argument("--seed", type=int, default=d.seed, help="scene layout / trajectory seed")
    p.add_argument("--demos", type=int, default=d.n_demos, help=f"demonstrations (default {d.n_demos})")
    p.add_argument("--scan-frames", type=int, default=d.scan_frames,
                   help=f"frames of the mapping sweep (default {d.scan_frames})")
    p.add_argument("--width", type=int, default=d.width, help=f"render width (default {d.width})")
    p.add_argument("--height", type=int, default=d.height, help=f"render height (default {d.height})")
    p.add_argument("--video-crf", type=int, default=d.video_crf,
                   help=f"libx264 quality of each raw_video.mp4, the frames' only copy (lower = better; default "
                        f"{d.video_crf})")
    p.add_argument("--shadows", action="store_true", help="render shadows (much slower on CPU)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing non-empty --out")
    p.set_defaults(func=cmd_make_session)
    return p


def cmd_make_session(args: argparse.Namespace) -> int:
    """Run :func:`umi_aug.sim.session.make_session` and print the summary with the 224² timing per face."""
    from rich.console import Console
    from rich.table import Table

    from umi_aug.sim.session import make_session

    console = Console()
    s = make_session(
        Path(args.out), seed=args.seed, n_demos=args.demos, scan_frames=args.scan_frames, width=args.width,
        height=args.height, video_crf=args.video_crf, shadows=args.shadows,
        overwrite=args.overwrite,
    )
    t = Table(title=f"synthetic UMI session → {s['out_dir']}")
    t.add_column("item")
    t.add_column("value")
    for name, info in s["sequences"].items():
        t.add_row(name, f"{info['frames']} frames @ {info['fps']:.3f} fps")
    for name, ev in s["demo_events"].items():
        t.add_row(f"{name} contact frame", str(ev["contact"]))
    t.add_row("dataset.zarr.zip", f"{s['dataset']['episodes']} episodes, {s['dataset']['steps']} steps (validated)")
    tm = s["timings"]
    r = s["intrinsics"]["render"]
    t.add_row(f"render {r['width']}×{r['height']} (faces {s['face_size']}²)",
              f"{tm['ms_per_frame_including_writes']:.1f} ms/frame incl. depth, segmentation and writes")
    t.add_row("total", f"{tm['total_seconds']:.1f} s")
    console.print(t)
    b = tm.get("benchmark_224")
    if b:
        bt = Table(title=f"fisheye render at {b['resolution']} (CPU, {b['frames']} frames): "
                         f"{b['ms_per_frame']:.1f} ms/frame ({b['fps']:.0f} fps), faces {b['face_size']}² px")
        bt.add_column("stage")
        bt.add_column("ms/frame", justify="right")
        for k, v in b["breakdown_ms"].items():
            bt.add_row(k, f"{v:.2f}")
        console.print(bt)
    console.print(f"Contact sheet: {s['out_dir']}/contact_sheet.png; summary: {s['out_dir']}/session.json")
    return 0
