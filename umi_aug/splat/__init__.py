"""Fisheye 3D Gaussian Splatting on the CPU (paper §3.1 "Fisheye 3D Gaussians", §3.3).

* :class:`Gaussians`: the standard 3DGS parameterisation (means, log-scales, wxyz quaternions, logit
  opacities, SH up to degree 3); :func:`read_ply` / :func:`write_ply` in the INRIA layout.
* :func:`render`: exact Kannala–Brandt EWA splatting (Jacobian of the full KB model, ray-distance ordering so
  Gaussians beyond 90 deg render, culling at the fold-over angle), 16x16-tile numba rasteriser, differentiable
  through a hand-written backward (:class:`RasterizeGaussians`) plus torch autograd for the projection.
* :func:`render_reference`: the dense float64 torch oracle.
* :mod:`umi_aug.splat.scenes`: procedural Gaussian scenes for tests and benchmarks.

Importing this package imports torch; the renderers (numba, the ``splat`` extra) load on first access to
:func:`render`, :class:`RasterizeGaussians`, :class:`RenderOutput` or :func:`render_reference`, so the scene
model and PLY I/O work without numba. Kernels compile on first use and are cached on disk.
"""

from typing import Any

from umi_aug.splat._constants import DEFAULT_FILTER, FILTER_DILATION
from umi_aug.splat.gaussians import Gaussians
from umi_aug.splat.ply import read_ply, write_ply
from umi_aug.splat.project import Projected, project_gaussians
from umi_aug.splat.sh import eval_sh, rgb_to_sh, sh_basis

_LAZY = {
    "render": "umi_aug.splat.renderer",
    "RasterizeGaussians": "umi_aug.splat.renderer",
    "RenderOutput": "umi_aug.splat.renderer",
    "render_reference": "umi_aug.splat._torch_impl",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = [
    "DEFAULT_FILTER",
    "FILTER_DILATION",
    "Gaussians",
    "Projected",
    "RasterizeGaussians",
    "RenderOutput",
    "eval_sh",
    "project_gaussians",
    "read_ply",
    "render",
    "render_reference",
    "rgb_to_sh",
    "sh_basis",
    "write_ply",
]
