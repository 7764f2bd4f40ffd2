"""Slow references of the data stage (gsplat ``_torch_impl`` style: private, for tests and benchmarks only).

* :func:`_read_video_frames_reference` mirrors :func:`umi_aug.data.video.read_video_frames` (selective ffmpeg
  decode with crop + area resize inside ffmpeg) by decoding every frame at full size and cropping / resizing in
  OpenCV.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from umi_aug.data.video import _check_indices, centre_crop
from umi_aug.errors import DatasetError


def _read_video_frames_reference(path: str | os.PathLike, indices: Sequence[int] | np.ndarray,
                                 size: tuple[int, int] | None = None) -> np.ndarray:
    """Reference of :func:`umi_aug.data.video.read_video_frames`: decode EVERY frame at full size with
    ``imageio_ffmpeg.read_frames``, keep the requested ones, then full-height centre crop +
    ``cv2.resize(INTER_AREA)`` to ``size`` = ``(w, h)``. Returns ``[K, h, w, 3]`` uint8 RGB."""
    import imageio_ffmpeg  # lazy: optional dependency (the recon / sim extras)

    path = Path(path)
    idx = _check_indices(path, indices)
    want = set(idx.tolist())
    gen = imageio_ffmpeg.read_frames(str(path), pix_fmt="rgb24")
    meta = next(gen)
    W, H = meta["size"]
    frames = {}
    for i, raw in enumerate(gen):
        if i in want:
            frames[i] = np.frombuffer(raw, dtype=np.uint8).reshape(H, W, 3)
    missing = [i for i in idx.tolist() if i not in frames]
    if missing:
        raise DatasetError(f"{path}: frame {missing[0]} requested but the video has {i + 1} frames")
    out = []
    for i in idx.tolist():
        img = frames[i]
        if size is not None and tuple(size) != (W, H):
            x0, y0, cw, ch = centre_crop(W, H, *size)
            img = cv2.resize(img[y0:y0 + ch, x0:x0 + cw], tuple(int(s) for s in size), interpolation=cv2.INTER_AREA)
        out.append(img)
    return np.stack(out) if out else np.zeros((0, H, W, 3), np.uint8)
