"""Optional GPU backend: gsplat's 3DGUT path with the OpenCV-fisheye (= Kannala–Brandt k1..k4) camera (issue #4
item 6). The CPU renderer (:func:`umi_aug.splat.render`) stays the default and the reference.

Written against gsplat 1.5.3's ``gsplat.rasterization`` and run on an H100 (torch 2.11 + CUDA 13.0, gsplat
JIT-built; ``benchmarks/gsplat_check.py`` measures it against the CPU renderer, results in
``docs/gsplat_check.md``):

``rasterization(means [N,3], quats [N,4] (wxyz), scales [N,3] (activated), opacities [N] (activated),
colors [N,K,3] (SH when sh_degree is set, else [N,D] colours), viewmats [C,4,4] (world -> camera),
Ks [C,3,3], width, height, near_plane, far_plane, eps2d, sh_degree, packed, backgrounds [C,D], render_mode,
rasterize_mode, camera_model="fisheye", with_ut=True, with_eval3d=True, radial_coeffs [C,4]) -> (colors
[C,H,W,X], alphas [C,H,W,1], meta)``; UT / eval3d require ``packed=False``, and the eval3d rasteriser takes
exactly 3 channels (a C++ ``assert(channels == 3)`` that aborts the process: ``render_mode="RGB+ED"`` is not
usable). :func:`render_gsplat` therefore rasterises twice: the SH colours, then each Gaussian's ray distance
``|p|`` as a 3-channel colour, normalised by alpha, which is exactly the CPU renderer's ``ray_depth``.

Conventions converted here, in one place (:func:`gsplat_rasterization_kwargs`):

* activations: the PLY stores log-scales and logit opacities; gsplat takes ``exp`` / ``sigmoid`` values;
  quaternions are passed normalised (zero norm -> identity, as our renderer treats them; gsplat's CUDA backward
  ignores the normalisation, gsplat #153); SH as ``cat(sh0, sh_rest)`` ``[N, K, 3]`` (same real-SH basis and
  signs as INRIA and :mod:`umi_aug.splat.sh`);
* pose: ``viewmats = T_world_cam^-1`` (OpenCV camera frame on both sides);
* pixels: gsplat samples pixel ``(i, j)`` at ``(j + 0.5, i + 0.5)`` (COLMAP convention), we put pixel centres at
  integers (OpenCV), so ``Ks`` carries ``cx + 0.5``, ``cy + 0.5``;
* filter: ``"inria"`` -> ``eps2d=0.3`` classic, ``"mip"`` -> ``eps2d=0.1`` antialiased, ``"none"`` -> ``eps2d=0``
  (with eval3d the response is evaluated in 3D and ``eps2d`` only affects the tile bounds);
* near/far: ours are spheres around the camera centre (ray distance of the mean), gsplat's planes ``z = near``,
  ``z = far``: a plane culls every Gaussian near 90 deg off-axis (an H100 run lost a Gaussian at 89 deg, 0.5 m).
  The conversion drops the Gaussians outside ``[near, far]`` itself and gives gsplat the plane
  ``GSPLAT_NEAR_PLANE`` (or ``near`` when smaller), ``far_plane = far``.

Known differences from the CPU renderer (measured on an H100 in ``docs/gsplat_check.md``: small unfiltered
Gaussians agree to 40-44 dB, the ``inria``-filtered room scene to 21-25 dB): 3DGUT evaluates each Gaussian's
maximum response along the pixel ray instead of the EWA 2D footprint and does not apply our filter's dilation;
gsplat's UT camera rejects Gaussians with ``z <= 0`` (little content past 90 deg: the GoPro's 90..104 deg rim is
mostly background); it sorts by camera ``z`` (ours by ray distance); it renders nothing beyond the inscribed circle
of its canvas (hence :func:`gsplat_canvas_pad`); and it takes its fold-over limit from the polynomial itself (ours
from ``intr.theta_max``).
"""

from __future__ import annotations

import importlib
from typing import Any, Literal, Sequence

import numpy as np
import torch

from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import SplatError
from umi_aug.splat._constants import DEFAULT_FAR, DEFAULT_FILTER, DEFAULT_NEAR, FILTER_DILATION
from umi_aug.splat.gaussians import Gaussians

__all__ = ["GSPLAT_VERSION", "GSPLAT_NEAR_PLANE", "BACKENDS", "gsplat_rasterization_kwargs", "gsplat_depth_pass_kwargs",
           "gsplat_canvas_pad", "render_gsplat",
           "render_with_backend", "gsplat_available"]

#: The gsplat release whose API this module targets.
GSPLAT_VERSION: str = "1.5.3"
#: gsplat's ``near_plane`` (metres, camera z): tiny, because our spherical near/far cull is applied before gsplat.
GSPLAT_NEAR_PLANE: float = 1e-5
#: Render backends selectable by :func:`render_with_backend`.
BACKENDS: tuple[str, ...] = ("cpu", "gsplat")
#: gsplat's (eps2d, rasterize_mode) for each of our screen-space filters.
_GSPLAT_FILTER: dict[str, tuple[float, str]] = {
    "inria": (FILTER_DILATION["inria"], "classic"),
    "mip": (FILTER_DILATION["mip"], "antialiased"),
    "none": (0.0, "classic"),
}


def _pose64(T: Any) -> np.ndarray:
    if isinstance(T, torch.Tensor):
        T = T.detach().cpu().numpy()
    a = np.asarray(T, dtype=np.float64)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise SplatError(f"T_world_cam must be a finite [4, 4] pose, got shape {list(a.shape)}")
    return a


def gsplat_canvas_pad(intr: FisheyeIntrinsics) -> int:
    """Pixels of empty canvas :func:`gsplat_rasterization_kwargs` adds on every side of the image (``pad_canvas``).

    gsplat 1.5.3's OpenCV-fisheye camera renders nothing farther from the principal point than the nearest image
    edge (measured on an H100: UMI's GoPro at 224² or 448² is empty past 81.5 deg, where the corners of the
    square crop see up to 104 deg). Rendering a canvas padded so that this inscribed circle reaches the farthest
    image corner, then cropping, removes the cut. Returns ``ceil(r_corner - d_edge) + 1`` (pixels), ``r_corner``
    the farthest corner's and ``d_edge`` the nearest edge's distance from the principal point.
    """
    W, H, cx, cy = intr.width, intr.height, intr.cx, intr.cy
    corners = np.array([[-0.5, -0.5], [W - 0.5, -0.5], [-0.5, H - 0.5], [W - 0.5, H - 0.5]])
    r_corner = float(np.max(np.hypot(corners[:, 0] - cx, corners[:, 1] - cy)))
    d_edge = float(min(cx + 0.5, W - 0.5 - cx, cy + 0.5, H - 0.5 - cy))
    return int(np.ceil(r_corner - d_edge)) + 1


def gsplat_rasterization_kwargs(
    gaussians: Gaussians,
    T_world_cam: torch.Tensor | np.ndarray,  # [4, 4] camera pose (OpenCV camera frame), metres
    intr: FisheyeIntrinsics,
    sh_degree: int | None = None,
    *,
    filter: Literal["inria", "mip", "none"] = DEFAULT_FILTER,
    near: float = DEFAULT_NEAR,
    far: float = DEFAULT_FAR,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
    differentiable: bool = False,
    pad_canvas: bool = True,
) -> dict[str, Any]:
    """Pure conversion of our scene + KB camera into the keyword arguments of gsplat 1.5.3 ``rasterization``
    (3DGUT, OpenCV fisheye). Runs on any device (CPU in the tests); no gsplat import.

    Returns:
        dict with ``means [N',3]`` (the N' Gaussians whose mean is between ``near`` and ``far`` from the camera
        centre; the other tensors likewise), ``quats [N,4]`` (unit wxyz), ``scales [N,3]`` (metres), ``opacities [N]``,
        ``colors [N,K,3]`` (SH, K = (sh_degree+1)^2 of the scene), ``viewmats [1,4,4]`` (world -> camera),
        ``Ks [1,3,3]`` (principal point + 0.5, gsplat's pixel convention), ``radial_coeffs [1,4]`` (k1..k4),
        ``width``, ``height``, ``sh_degree``, ``near_plane``, ``far_plane``, ``eps2d``, ``rasterize_mode``,
        ``camera_model="fisheye"``, ``with_ut=True``, ``with_eval3d=True``, ``packed=False``,
        ``render_mode="RGB"`` (gsplat's eval3d path renders 3 channels only); all tensors in ``dtype`` on
        ``device``. With ``differentiable=True`` the Gaussian tensors stay in the autograd graph of the scene's
        parameters (for a gsplat training step).
        With ``pad_canvas`` (default) ``width``/``height``/``Ks`` describe the image padded by
        :func:`gsplat_canvas_pad` pixels on every side (gsplat's inscribed-circle cut): crop the result with
        ``[pad:pad + height, pad:pad + width]``.
    """
    if not isinstance(gaussians, Gaussians):
        raise SplatError(f"gsplat conversion expects Gaussians, got {type(gaussians).__name__}")
    if not isinstance(intr, FisheyeIntrinsics):
        raise SplatError(f"gsplat conversion expects FisheyeIntrinsics, got {type(intr).__name__}")
    if filter not in _GSPLAT_FILTER:
        raise SplatError(f"unknown filter {filter!r}; expected one of {sorted(_GSPLAT_FILTER)}")
    if not (0.0 <= near < far):
        raise SplatError(f"need 0 <= near < far, got near={near!r}, far={far!r}")
    deg = gaussians.sh_degree if sh_degree is None else int(sh_degree)
    if not 0 <= deg <= 3:
        raise SplatError(f"sh_degree must be in [0, 3], got {sh_degree!r}")
    deg = min(deg, gaussians.sh_degree)
    dev = torch.device(device) if device is not None else gaussians.device
    g = gaussians if differentiable else gaussians.detach()
    q = g.quats_wxyz.to(torch.float64)
    n = torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    ident = torch.zeros_like(q)
    ident[:, 0] = 1.0
    quats = torch.where(n > 0, q / torch.where(n > 0, n, torch.ones_like(n)), ident)
    T = _pose64(T_world_cam)
    viewmat = np.eye(4)
    viewmat[:3, :3] = T[:3, :3].T
    viewmat[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    # our spherical near/far cull (ray distance of the mean), as the CPU renderer applies it
    R_cw = torch.as_tensor(viewmat[:3, :3], dtype=torch.float64, device=g.device)
    t_cw = torch.as_tensor(viewmat[:3, 3], dtype=torch.float64, device=g.device)
    dist = torch.linalg.vector_norm(g.means.detach().to(torch.float64) @ R_cw.T + t_cw, dim=-1)
    keep = (dist >= near) & (dist <= far)
    if not bool(keep.all()):
        g, quats = g.select(keep), quats[keep]
    pad = gsplat_canvas_pad(intr) if pad_canvas else 0
    K = np.array([[intr.fx, 0.0, intr.cx + 0.5 + pad], [0.0, intr.fy, intr.cy + 0.5 + pad], [0.0, 0.0, 1.0]])
    eps2d, mode = _GSPLAT_FILTER[filter]
    to = lambda t: torch.as_tensor(t).to(device=dev, dtype=dtype).contiguous()  # noqa: E731
    return {
        "means": to(g.means),
        "quats": to(quats),
        "scales": to(torch.exp(g.log_scales.to(torch.float64))),
        "opacities": to(torch.sigmoid(g.logit_opacities.to(torch.float64))),
        "colors": to(g.sh),
        "viewmats": to(viewmat[None]),
        "Ks": to(K[None]),
        "radial_coeffs": to(np.asarray(intr.k, dtype=np.float64)[None]),
        "width": int(intr.width) + 2 * pad,
        "height": int(intr.height) + 2 * pad,
        "sh_degree": int(deg),
        "near_plane": float(min(near, GSPLAT_NEAR_PLANE)) if near > 0 else GSPLAT_NEAR_PLANE,
        "far_plane": float(far),
        "eps2d": float(eps2d),
        "rasterize_mode": mode,
        "camera_model": "fisheye",
        "with_ut": True,
        "with_eval3d": True,
        "packed": False,
        "render_mode": "RGB",
    }


def gsplat_depth_pass_kwargs(kw: dict[str, Any]) -> dict[str, Any]:
    """The second pass of :func:`render_gsplat`: ``kw`` (from :func:`gsplat_rasterization_kwargs`) with each
    Gaussian's colour replaced by its distance from the camera centre, ``|R_cw mu + t_cw|`` (metres, the CPU
    renderer's per-Gaussian ray depth) in all 3 channels, and no SH. Rasterised, channel 0 divided by alpha is
    the expected ray depth. One camera only (``viewmats [1, 4, 4]``)."""
    V = kw["viewmats"]
    if V.shape[0] != 1:
        raise SplatError(f"the depth pass takes one camera, got viewmats of shape {list(V.shape)}")
    p = kw["means"] @ V[0, :3, :3].T + V[0, :3, 3]
    dist = torch.linalg.vector_norm(p, dim=-1)
    return dict(kw, colors=dist[:, None].expand(-1, 3).contiguous(), sh_degree=None)


def gsplat_available() -> tuple[bool, str]:
    """``(True, "")`` when gsplat imports and CUDA is available, else ``(False, reason)``."""
    try:
        importlib.import_module("gsplat")
    except ImportError as exc:
        return False, (f"gsplat is not installed ({exc}); install gsplat=={GSPLAT_VERSION} with a CUDA build of "
                       f"torch, or use backend='cpu'")
    if not torch.cuda.is_available():
        return False, "gsplat needs a CUDA device but torch.cuda.is_available() is False; use backend='cpu'"
    return True, ""


def render_gsplat(
    gaussians: Gaussians,
    T_world_cam: torch.Tensor | np.ndarray,  # [4, 4]
    intr: FisheyeIntrinsics,
    background: torch.Tensor | np.ndarray | Sequence[float] | None = None,  # [3] or [H, W, 3]
    sh_degree: int | None = None,
    *,
    filter: Literal["inria", "mip", "none"] = DEFAULT_FILTER,
    near: float = DEFAULT_NEAR,
    far: float = DEFAULT_FAR,
    device: str = "cuda",
    pad_canvas: bool = True,
):
    """Render with gsplat's 3DGUT fisheye path on CUDA (see the module docstring for how it differs from the CPU
    renderer, and ``docs/gsplat_check.md`` for how much).

    Same inputs and :class:`umi_aug.splat.renderer.RenderOutput` as :func:`umi_aug.splat.render` (tensors on the
    CPU, float32; differentiable when inputs require grad is NOT supported here: the scene is detached; a
    training step calls ``gsplat.rasterization`` on :func:`gsplat_rasterization_kwargs` with
    ``differentiable=True``). Two rasterisations: colour, then ray depth (:func:`gsplat_depth_pass_kwargs`).

    Raises:
        SplatError: gsplat missing, no CUDA, or gsplat failed (its message included).
    """
    from umi_aug.splat.renderer import RenderOutput, _background  # lazy, start-up: numba, scipy

    ok, why = gsplat_available()
    if not ok:
        raise SplatError(f"render_gsplat: {why}")
    gsplat = importlib.import_module("gsplat")
    kw = gsplat_rasterization_kwargs(gaussians, T_world_cam, intr, sh_degree, filter=filter, near=near, far=far,
                                     device=device, pad_canvas=pad_canvas)
    pad = gsplat_canvas_pad(intr) if pad_canvas else 0
    H, W = intr.height, intr.width
    bg = _background(background, torch.float32, H, W)
    try:
        with torch.no_grad():
            colors, alphas, _ = gsplat.rasterization(**kw)
            depth_acc, _, _ = gsplat.rasterization(**gsplat_depth_pass_kwargs(kw))
    except Exception as exc:  # gsplat raises AssertionError/RuntimeError with its own messages
        raise SplatError(f"render_gsplat: gsplat {getattr(gsplat, '__version__', '?')}.rasterization failed: "
                         f"{type(exc).__name__}: {exc}") from exc
    crop = (slice(pad, pad + H), slice(pad, pad + W))
    rgb = colors[0][crop].float().cpu()
    alpha = alphas[0, ..., 0][crop].float().cpu()
    rgb = rgb + (1.0 - alpha)[..., None] * bg
    acc = depth_acc[0, ..., 0][crop].float().cpu()
    ray_depth = torch.where(alpha > 0, acc / alpha.clamp_min(1e-10), torch.zeros_like(acc))
    return RenderOutput(rgb=rgb, alpha=alpha, ray_depth=ray_depth,
                        meta={"backend": "gsplat", "gsplat_version": getattr(gsplat, "__version__", "?")})


def render_with_backend(
    gaussians: Gaussians,
    T_world_cam: torch.Tensor | np.ndarray,  # [4, 4]
    intr: FisheyeIntrinsics,
    background: torch.Tensor | np.ndarray | Sequence[float] | None = None,
    sh_degree: int | None = None,
    *,
    backend: Literal["cpu", "gsplat"] = "cpu",
    **kwargs: Any,
):
    """The one backend switch: ``"cpu"`` -> :func:`umi_aug.splat.render` (default, reference), ``"gsplat"`` ->
    :func:`render_gsplat` (CUDA only). ``kwargs`` go to the chosen renderer."""
    if backend == "cpu":
        from umi_aug.splat.renderer import render  # lazy, start-up: numba, scipy

        return render(gaussians, T_world_cam, intr, background, sh_degree, **kwargs)
    if backend == "gsplat":
        return render_gsplat(gaussians, T_world_cam, intr, background, sh_degree, **kwargs)
    raise SplatError(f"backend must be one of {BACKENDS}, got {backend!r}")
