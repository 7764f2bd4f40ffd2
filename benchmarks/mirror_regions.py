"""UMI's side mirrors at the splice (issue #34 item 6): originals vs augmented mirror regions of one or more exports.

For every augmented episode of each export: the last rendered frame (splice − 1) against the first replayed
original frame (splice), inside the two mirror polygons and, for context, in the rest of the lit image. A mirror
that shows the 3DGS render (``--mirrors scene``) jumps there from the scene ahead to the real reflection; one whose
pixels come from the overlay's original frame (``--mirrors source``) does not. Prints a table (mean absolute change,
0..255 levels) and writes a picture of the first episodes' mirror crops at the splice.

    umi-aug augment ../shared/realdata/umi_cup_in_the_wild_ep0/dataset.zarr.zip -n 2 --mode freespace \
        --work /tmp/mirrors/work --mirrors scene --out /tmp/mirrors/scene.zarr.zip
    umi-aug augment ... --mirrors source --out /tmp/mirrors/source.zarr.zip      # same --work: the scene is reused
    python benchmarks/mirror_regions.py /tmp/mirrors/scene.zarr.zip /tmp/mirrors/source.zarr.zip \
        --out docs/mirrors/real_episode_splice.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from umi_aug.augment.export_store import read_episode_records  # noqa: E402
from umi_aug.augment.mirrors import mirror_mask  # noqa: E402
from umi_aug.camera.masks import predefined_mask  # noqa: E402
from umi_aug.data import ReplayBuffer  # noqa: E402
from umi_aug.io_utils import atomic_path  # noqa: E402

ZOOM = 3


def splice_pairs(path: Path) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Per augmented episode with a replayed tail: (episode, frame splice − 1, frame splice), uint8 [S, S, 3]."""
    rec = read_episode_records(path)
    out = []
    with ReplayBuffer.open(path) as buf:
        img = buf["camera0_rgb"]
        for e in np.flatnonzero(rec["aug_mode"] > 0):
            s = int(rec["aug_splice_index"][e])
            sl = buf.get_episode_slice(int(e))
            if 0 < s < sl.stop - sl.start:
                out.append((int(e), np.asarray(img[sl.start + s - 1]), np.asarray(img[sl.start + s])))
    return out


def mirror_boxes(size: int, lit: np.ndarray) -> list[tuple[slice, slice]]:
    """Row/column slices of the left and the right mirror polygon's bounding boxes, the part inside ``lit``
    ([S, S] bool: pixels inside the lens circle)."""
    m = mirror_mask(size) & lit
    ys, _ = np.nonzero(m)
    rows = slice(ys.min(), ys.max() + 1)  # one row range for both, so their crops sit side by side
    boxes = []
    for half in (slice(0, size // 2), slice(size // 2, size)):
        part = np.zeros_like(m)
        part[:, half] = m[:, half]
        _, xs = np.nonzero(part)
        boxes.append((rows, slice(xs.min(), xs.max() + 1)))
    return boxes


def seams(pairs, size: int) -> tuple[float, float]:
    """Mean |frame(splice) − frame(splice − 1)| (levels) inside the mirrors and in the rest of the lit image
    (outside the gripper and mirror polygons)."""
    m = mirror_mask(size)
    rest = ~m & ~predefined_mask(size, size, mirror=False, gripper=True, finger=True)
    dm, dr = [], []
    for _, a, b in pairs:
        lit = (a.max(-1) > 16) | (b.max(-1) > 16)
        d = np.abs(a.astype(np.float32) - b.astype(np.float32)).mean(-1)
        dm.append(d[m & lit].mean())
        dr.append(d[rest & lit].mean())
    return float(np.mean(dm)), float(np.mean(dr))


def picture(rows: list[tuple[str, list]], size: int, out: Path, n_episodes: int) -> None:
    """One row per (export, episode): left mirror at splice − 1 | at splice || right mirror at splice − 1 | at
    splice."""
    first = rows[0][1][0]
    boxes = mirror_boxes(size, (first[1].max(-1) > 16) | (first[2].max(-1) > 16))
    tiles = []
    for name, pairs in rows:
        for e, a, b in pairs[:n_episodes]:
            crops = []
            for ys, xs in boxes:
                crops += [a[ys, xs], b[ys, xs], np.full((ys.stop - ys.start, 2, 3), 255, np.uint8)]
            row = np.concatenate(crops[:-1], 1)
            row = cv2.resize(row, None, fx=ZOOM, fy=ZOOM, interpolation=cv2.INTER_NEAREST)
            label = np.full((22, row.shape[1], 3), 255, np.uint8)
            cv2.putText(label, f"{name} ep {e}: L mirror splice-1 | splice   R mirror splice-1 | splice", (4, 16),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
            tiles.append(np.concatenate([label, row], 0))
    width = max(t.shape[1] for t in tiles)
    sheet = np.concatenate([np.pad(t, ((0, 4), (0, width - t.shape[1]), (0, 0)), constant_values=255) for t in tiles])
    out.parent.mkdir(parents=True, exist_ok=True)
    ok, png = cv2.imencode(".png", sheet[:, :, ::-1])
    with atomic_path(out) as tmp:
        Path(tmp).write_bytes(png.tobytes())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("exports", nargs="+", type=Path, help="umi-aug exports (.zarr.zip or directory)")
    ap.add_argument("--out", type=Path, default=Path("mirror_regions.png"), help="picture (PNG)")
    ap.add_argument("--episodes", type=int, default=2, help="episodes per export in the picture")
    args = ap.parse_args()
    rows = []
    print(f"{'export':40s} {'episodes':>8s} {'mirror seam':>12s} {'rest seam':>10s}")
    size = None
    for p in args.exports:
        pairs = splice_pairs(p)
        if not pairs:
            sys.exit(f"error: {p}: no augmented episode with a replayed tail")
        size = pairs[0][1].shape[0]
        dm, dr = seams(pairs, size)
        print(f"{p.name:40s} {len(pairs):8d} {dm:12.1f} {dr:10.1f}")
        rows.append((p.name.split(".")[0], pairs))
    picture(rows, size, args.out, args.episodes)
    print(f"picture: {args.out}")


if __name__ == "__main__":
    main()
