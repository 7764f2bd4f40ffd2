"""COLMAP's feature extraction on several cores with the bytes of one thread.

COLMAP's own extraction pool stores keypoints in the order its threads finish, so a multi-threaded database
differed run to run (and a Ray worker's scene from the one-process one). Here the frames are split into
contiguous blocks in input order, one thread per block runs ``pycolmap.extract_features`` single-threaded into its
own database (the call releases the GIL), and ``pycolmap.Database.merge`` joins them in order, keeping the image
ids: the same keypoints and descriptors under the same ids as one thread (tests/recon/test_colmap_blocks.py). Each
block adds its own camera row with the same parameters (the callers read each image's camera; intrinsics are
never refined). On the real episode (38 frames at 448²) extraction took 9.7 s on one thread and 5.2 s in two
blocks, 2 idle cores, and the triangulated cloud was the same bytes.

Matching is not split: COLMAP's FAISS matcher already keeps two cores busy from one COLMAP thread (7.7 s of CPU
in 4.3 s for 208 pairs), and two blocks in two processes took as long as one.
"""

from __future__ import annotations

import functools
import threading
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from umi_aug.errors import ReconError

__all__ = ["block_bounds", "extract_in_blocks"]

#: Fewest frames per block: a block's database and merge cost more than a few frames' extraction saves.
MIN_FRAMES_PER_BLOCK: int = 4


def block_bounds(n: int, blocks: int, min_per_block: int = 1) -> list[tuple[int, int]]:
    """Contiguous ``[start, stop)`` ranges covering ``0..n-1`` in order: at most ``blocks`` of them, each with at
    least ``min_per_block`` items (one range when ``n`` is too small to split; none when ``n`` is 0)."""
    if n <= 0:
        return []
    k = max(1, min(int(blocks), n // max(1, int(min_per_block))))
    b = np.linspace(0, n, k + 1).round().astype(int)
    return [(int(b[i]), int(b[i + 1])) for i in range(k)]


def _run_in_threads(fns: Sequence[Callable[[], None]]) -> None:
    """Run each function in its own thread; re-raise the first error (in block order) after all have finished."""
    errors: list[BaseException | None] = [None] * len(fns)

    def run(i: int) -> None:
        try:
            fns[i]()
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread below
            errors[i] = exc

    threads = [threading.Thread(target=run, args=(i,), name=f"colmap-block-{i}") for i in range(len(fns))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for exc in errors:
        if exc is not None:
            raise exc


def _merge(pc, first: Path, second: Path, out: Path) -> None:
    a, b, m = (pc.Database.open(str(p)) for p in (first, second, out))
    try:
        pc.Database.merge(a, b, m)
    finally:
        for d in (a, b, m):
            d.close()


def extract_in_blocks(pc, db: Path, image_dir: Path, names: Sequence[str], reader, extraction,
                      workers: int) -> None:
    """``pycolmap.extract_features`` of ``names`` into the new database ``db``, one thread per block of frames.

    Args:
        pc: the pycolmap module.
        db: the database to create (must not exist).
        image_dir: folder the names are relative to.
        names: image names in the order their ids are assigned (1, 2, ...).
        reader: ``pycolmap.ImageReaderOptions`` (one camera per block, ``CameraMode.SINGLE``).
        extraction: ``pycolmap.FeatureExtractionOptions``; its ``num_threads`` must be 1 (checked).
        workers: blocks run at the same time (1: one call, as plain COLMAP).
    """
    if extraction.num_threads != 1:
        raise ReconError(f"extract_in_blocks: extraction.num_threads must be 1 (one thread per block), got "
                         f"{extraction.num_threads}")
    names = list(names)
    if not names:
        raise ReconError(f"extract_in_blocks: no image names to extract into {db}")
    bounds = block_bounds(len(names), workers, MIN_FRAMES_PER_BLOCK)
    parts = [db] if len(bounds) == 1 else [db.with_name(f"{db.stem}.extract{k}.db") for k in range(len(bounds))]

    def extract(k: int) -> None:
        a, b = bounds[k]
        pc.extract_features(parts[k], image_dir, image_names=names[a:b], camera_mode=pc.CameraMode.SINGLE,
                            reader_options=reader, extraction_options=extraction, device=pc.Device.cpu)

    _run_in_threads([functools.partial(extract, k) for k in range(len(bounds))])
    done = parts[0]
    for k in range(1, len(parts)):
        out = db if k == len(parts) - 1 else db.with_name(f"{db.stem}.merged{k}.db")
        _merge(pc, done, parts[k], out)
        for p in (done, parts[k]):
            p.unlink()
        done = out
