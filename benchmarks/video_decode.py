"""Decoding frames of a GoPro-sized raw_video.mp4: the selective one-pass decoder (umi_aug.data.video) against the
decode-everything reference, per (frames kept, output size). Prints a table; asserts nothing.

    python benchmarks/video_decode.py [--frames 120] [--width 2704 --height 2028]

The video is synthetic (smooth moving texture, libx264 crf 8, yuv420p) at the GoPro's 2.7K size.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def _make(path: Path, n: int, w: int, h: int) -> float:
    from umi_aug.data.video import VideoWriter

    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    t = time.perf_counter()
    with VideoWriter(path, w, h, 59.94) as wr:
        for i in range(n):
            img = np.stack([128 + 100 * np.sin(xx / 37.0 + i / 5), 128 + 100 * np.cos(yy / 23.0 - i / 7),
                            128 + 80 * np.sin((xx + yy) / 51.0)], -1)
            wr.write(img.astype(np.uint8))
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--width", type=int, default=2704)
    ap.add_argument("--height", type=int, default=2028)
    a = ap.parse_args()
    from umi_aug.data._ref import _read_video_frames_reference
    from umi_aug.data.video import read_video_frames

    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "raw_video.mp4"
        s = _make(p, a.frames, a.width, a.height)
        print(f"wrote {a.frames} frames {a.width}x{a.height} in {s:.1f} s ({p.stat().st_size / 1e6:.1f} MB)")
        sw = 960
        sh = int(round(sw * a.height / a.width))
        cases = [("every 4th", np.arange(0, a.frames, 4), (sw, sh)), ("every 2nd", np.arange(0, a.frames, 2), (sw, sh)),
                 ("every 8th", np.arange(0, a.frames, 8), (224, 224)), ("first 10%", np.arange(a.frames // 10), None)]
        print("| frames kept | size | selective s | reference s | speed-up | max |diff| |")
        print("|---|---|---:|---:|---:|---:|")
        for name, idx, size in cases:
            t = time.perf_counter()
            fast = read_video_frames(p, idx, size)
            tf = time.perf_counter() - t
            t = time.perf_counter()
            ref = _read_video_frames_reference(p, idx, size)
            tr = time.perf_counter() - t
            d = int(np.abs(fast.astype(np.int16) - ref).max())
            sz = "native" if size is None else f"{size[0]}x{size[1]}"
            print(f"| {name} ({len(idx)}) | {sz} | {tf:.2f} | {tr:.2f} | {tr / tf:.1f}x | {d} |")


if __name__ == "__main__":
    main()
