"""Simulated fisheye data source: true-fisheye MuJoCo rendering and a built-in synthetic UMI session.

Importing this package does no work and does not import MuJoCo; the submodules choose the GL backend
(:mod:`umi_aug.sim.gl`) when they first need it. Public entry points:

- :class:`umi_aug.sim.fisheye_renderer.FisheyeRenderer` — KB fisheye RGB / ray depth / segmentation of any model.
- :func:`umi_aug.sim.scene.build_tabletop_scene` — the built-in tabletop MJCF (seeded layout).
- :func:`umi_aug.sim.session.make_session` — a synthetic UMI session folder (scan + demos + ground truth).
- :func:`umi_aug.sim.camera_frames.opencv_to_mujoco_camera` — the one OpenCV↔MuJoCo camera-axis conversion.
"""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "FisheyeRenderer": "umi_aug.sim.fisheye_renderer",
    "FisheyeFrame": "umi_aug.sim.fisheye_renderer",
    "RasterOptions": "umi_aug.sim.raster",
    "PinholeRasterizer": "umi_aug.sim.raster",
    "opencv_to_mujoco_camera": "umi_aug.sim.camera_frames",
    "mujoco_to_opencv_camera": "umi_aug.sim.camera_frames",
    "build_tabletop_scene": "umi_aug.sim.scene",
    "TabletopScene": "umi_aug.sim.scene",
    "SceneLayout": "umi_aug.sim.scene",
    "make_session": "umi_aug.sim.session",
    "SessionConfig": "umi_aug.sim.session",
    "import_mujoco": "umi_aug.sim.gl",
    "select_gl_backend": "umi_aug.sim.gl",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'umi_aug.sim' has no attribute {name!r}")
