"""Compile the splatting kernels before their first use, in a background process.

The numba kernels of :mod:`umi_aug.splat` are compiled on their first call and kept in numba's on-disk cache
(``cache=True``: ``__pycache__`` next to the source, or ``NUMBA_CACHE_DIR``). On a machine whose cache is cold (a
fresh install, a new checkout, a CI runner) the first 3DGS training step and the first render wait for that
compilation. :func:`start_background_compile` runs :func:`compile_kernels` in a child process at low priority
while the pipeline's first stages (the session's rendering, SfM) leave a core idle; the child writes the cache,
and the parent loads the kernels from it when it gets there. If the parent reaches a kernel first it simply
compiles it itself, so nothing depends on the child finishing (or succeeding).

:func:`compile_kernels` calls every kernel through the public API with the dtypes and array layouts the
pipeline uses (float32 scenes; a training step with the fast projection and its backward; an inference render
with an obstacle set composed in).
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

from umi_aug.runtime import start_background_helper

__all__ = ["compile_kernels", "kernel_cache_is_warm", "start_background_compile"]


def compile_kernels() -> None:
    """Call every numba kernel of the CPU splatting path once, on a tiny random scene (float32)."""
    # lazy, start-up: numpy, torch
    import numpy as np
    import torch

    # lazy, start-up: cv2, torch
    from umi_aug.camera import gopro_intrinsics_2_7k
    from umi_aug.splat.compose import PlacedGaussians, render_composed
    from umi_aug.splat.scenes import look_at_pose, random_gaussians
    from umi_aug.splat.train import SplatTrainConfig, TrainView, train_splat

    rng = np.random.default_rng(0)
    intr = gopro_intrinsics_2_7k().scaled(32, 24)
    poses = [look_at_pose(np.array([0.4 * np.cos(a), 0.4 * np.sin(a), 0.3]), np.zeros(3)) for a in (0.0, 0.7, 1.4)]
    views = [TrainView(f"warmup/{i}", rng.integers(0, 256, (24, 32, 3), dtype=np.uint8), T, np.ones((24, 32), bool))
             for i, T in enumerate(poses)]
    cfg = SplatTrainConfig(iterations=2, max_gaussians=64, holdout_every=3, eval_every=1, checkpoint_every=10,
                           refine_start=1, refine_every=1, sh_increase_every=1)
    train_splat(views, intr, rng.uniform(-0.1, 0.1, (48, 3)), None, cfg, None, progress=False)
    scene = random_gaussians(64, rng, intr, poses[0], dtype=torch.float32)
    obstacle = random_gaussians(16, rng, intr, poses[0], dtype=torch.float32)
    with torch.no_grad():
        render_composed(scene, [PlacedGaussians(obstacle, np.eye(4), "warmup")], poses[0], intr)


#: Kernels whose cache index files show that the cache is warm (the last ones :func:`compile_kernels` reaches).
_PROBE_KERNELS = ("project_bwd_kernel", "raster_bwd_kernel", "raster_fwd_kernel", "project_kernel",
                  "raster_fwd_fused_kernel")
_child: subprocess.Popen | None = None


def kernel_cache_is_warm() -> bool:
    """Whether numba's cache holds an index for each probe kernel (where numba keeps it: ``NUMBA_CACHE_DIR`` or the
    package's ``__pycache__``). An index of an older source makes numba compile anyway: then this says warm and
    the first run compiles in the foreground, as without this module."""
    env_dir = os.environ.get("NUMBA_CACHE_DIR")
    roots = [Path(env_dir)] if env_dir else [Path(__file__).resolve().parent / "__pycache__"]
    for name in _PROBE_KERNELS:
        if not any(next(iter(r.rglob(f"*.{name}-*.nbi")), None) for r in roots if r.is_dir()):
            return False
    return True


def start_background_compile(force: bool = False) -> subprocess.Popen | None:
    """Start :func:`compile_kernels` in a child process (``nice`` 10, 1 thread, output discarded) unless the
    kernel cache is already warm or a child of this process is still running; returns the child, or None (nothing
    else depends on it). ``force``: start it even when the cache looks warm. ``UMI_AUG_NO_WARMUP=1`` turns it
    off."""
    global _child
    if os.environ.get("UMI_AUG_NO_WARMUP", "") not in ("", "0"):
        return None
    if _child is not None and _child.poll() is None:
        return _child
    if not force and kernel_cache_is_warm():
        return None
    _child = start_background_helper("umi_aug.splat.warmup", [])
    return _child


if __name__ == "__main__":  # pragma: no cover - the child process of start_background_compile
    compile_kernels()
