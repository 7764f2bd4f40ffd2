"""Fisheye 3D Gaussian Splatting on the CPU (paper §3.1 "Fisheye 3D Gaussians", §3.3).

* :class:`Gaussians`: the standard 3DGS parameterisation (means, log-scales, wxyz quaternions, logit
  opacities, SH up to degree 3); :func:`read_ply` / :func:`write_ply` in the INRIA layout.
* :func:`render`: exact Kannala–Brandt EWA splatting (Jacobian of the full KB model, ray-distance ordering so
  Gaussians beyond 90 deg render, culling at the fold-over angle), 16x16-tile numba rasteriser, differentiable
  through a hand-written backward (:class:`RasterizeGaussians`) plus torch autograd for the projection.
* :mod:`umi_aug.splat._torch_impl`: the slow references (the dense float64 torch oracle of :func:`render`).
* :mod:`umi_aug.splat.scenes`: procedural Gaussian scenes for tests and benchmarks.

* :func:`render_composed` / :class:`RenderCache`: a scene plus rigidly placed obstacle Gaussian sets, without
  copying the scene per frame; :func:`umi_aug.splat.obstacle_gaussians.obstacle_gaussians`: Gaussians of an
  obstacle mesh (cached per asset).
* :func:`train_splat` / :func:`train_splat_from_session`: the fisheye 3DGS trainer.
* :func:`render_with_backend`: ``"cpu"`` (default, the reference) or ``"gsplat"`` (CUDA, optional).

Importing this package is cheap: every name loads its module on first access (torch with the scene model,
numba with the renderers — the ``splat`` extra). Kernels compile on first use and are cached on disk.
"""

from typing import Any

_LAZY = {
    "DEFAULT_FILTER": "_constants", "FILTER_DILATION": "_constants",
    "Gaussians": "gaussians",
    "read_ply": "ply", "write_ply": "ply",
    "Projected": "project", "project_gaussians": "project",
    "eval_sh": "sh", "rgb_to_sh": "sh", "sh_basis": "sh",
    "render": "renderer", "RasterizeGaussians": "renderer", "RenderOutput": "renderer",
    "render_composed": "compose", "PlacedGaussians": "compose", "RenderCache": "compose",
    "render_with_backend": "gsplat_backend",
    "SplatTrainConfig": "train", "TrainView": "train", "SplatTrainResult": "train", "train_splat": "train",
    "train_splat_from_session": "train_session",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(f"umi_aug.splat.{_LAZY[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = sorted(_LAZY)
