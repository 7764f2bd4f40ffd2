"""Timing of fisheye rendering (ms/frame, CPU) with the per-face breakdown (render vs remap)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.sim.fisheye_renderer import FisheyeRenderer
from umi_aug.sim.raster import RasterOptions

__all__ = ["benchmark_fisheye_render"]


def benchmark_fisheye_render(
    model,
    data,
    intr: FisheyeIntrinsics,
    T_world_cam: np.ndarray,
    options: RasterOptions | None = None,
    face_size: int | None = None,
    warmup: int = 3,
    segmentation: bool = False,
) -> dict[str, Any]:
    """Render every pose of ``T_world_cam`` once (after ``warmup`` untimed frames) and report timings.

    Args:
        model, data: MuJoCo model and data (state as it should be rendered).
        intr: output fisheye intrinsics (e.g. ``gopro_intrinsics_2_7k().umi_policy(224)``).
        T_world_cam: np.ndarray,  # [N, 4, 4] camera poses, OpenCV axes
        options: raster options (shadows off by default).
        face_size: cube-face size (default: matched to the lens).
        warmup: untimed frames first (GL/texture upload).
        segmentation: include the segmentation pass.

    Returns:
        ``{"resolution": "WxH", "face_size", "faces", "frames", "ms_per_frame", "fps", "breakdown_ms":
        {stage: ms/frame}}`` where the breakdown has ``render/<face>`` (render + readback), ``remap/rgb``,
        ``remap/depth``, ``update_scene`` and totals.
    """
    poses = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    with FisheyeRenderer(model, intr, face_size=face_size, options=options) as r:
        for k in range(min(warmup, len(poses))):
            r.render(poses[k], data, segmentation=segmentation)
        r.reset_timings()
        t0 = time.perf_counter()
        for T in poses:
            r.render(T, data, segmentation=segmentation)
        wall = time.perf_counter() - t0
        rep = r.timing_report()
        faces = list(r.faces_needed)
        fs = r.face_size
    ms = 1000.0 * wall / max(len(poses), 1)
    return {
        "resolution": f"{intr.width}x{intr.height}",
        "face_size": fs,
        "faces": faces,
        "frames": len(poses),
        "ms_per_frame": ms,
        "fps": 1000.0 / ms if ms > 0 else float("inf"),
        "breakdown_ms": {k: v for k, v in rep.items() if k != "frames"},
    }
