"""CPU fisheye Gaussian splatting: :func:`render` (fast numba path) and the rasteriser autograd function.

Pipeline (gsplat's split): projection (numba for inference; with gradients the numba
:class:`umi_aug.splat.project.ProjectGaussians` with its hand-written backward, or the torch-autograd reference) ->
binning (depth sort of the visible Gaussians by ray distance, stable counting sort into 16x16 tiles, exact
ellipse/tile test) -> rasterisation (numba, parallel over tiles; hand-written backward that replays each pixel
from its last contributor using the stored final transmittance) exposed as :class:`RasterizeGaussians`
(``torch.autograd.Function``). The dense float64 torch reference lives in :mod:`umi_aug.splat._torch_impl`.

Outputs follow the project conventions: RGB float ``[H, W, 3]``, ``alpha = 1 - T_final`` ``[H, W]`` and
``ray_depth`` ``[H, W]`` = alpha-normalised expected distance along the pixel ray (metres; 0 where nothing
was composited).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, Literal, Sequence

import numba
import numpy as np
import torch

from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import SplatError
from umi_aug.splat import _kernels as K
from umi_aug.splat._constants import DEFAULT_FAR, DEFAULT_FILTER, DEFAULT_NEAR, TILE_SIZE, TRANSMITTANCE_THRESHOLD
from umi_aug.splat.gaussians import Gaussians
from umi_aug.splat.project import camera_from_pose, check_filter, project_gaussians

__all__ = [
    "RenderOutput", "Binning", "RasterizeGaussians", "render", "bin_gaussians", "rasterize_packed", "project_numba",
    "compose_background_numpy", "restrict_binning", "tiles_covering",
]

Tensor = torch.Tensor

#: Iterations handed to one thread at a time by the rasteriser's parallel loops (over its workers, each of which
#: takes an interleaved share of the tiles: ``_kernels.raster_fwd_kernel``).
PARALLEL_CHUNK = 1
#: Below this much work (Gaussians, intersections, pixels) a kernel runs on one thread: waking the thread pool
#: costs more than it saves, and on busy shared cores it can stall for milliseconds.
SERIAL_WORK = 50_000


@contextlib.contextmanager
def _parallel(work: int, chunk: int):
    """Run the enclosed numba parallel loops with ``chunk`` iterations per hand-out, single-threaded when
    ``work < SERIAL_WORK``."""
    n = numba.get_num_threads()
    serial = work < SERIAL_WORK and n > 1
    if serial:
        numba.set_num_threads(1)
    try:
        with numba.parallel_chunksize(chunk):
            yield
    finally:
        if serial:
            numba.set_num_threads(n)


@dataclass
class RenderOutput:
    """Result of :func:`render`.

    Attributes:
        rgb: Tensor,  # [H, W, 3] colour, background composited
        alpha: Tensor,  # [H, W] 1 - final transmittance
        ray_depth: Tensor,  # [H, W] expected distance along the ray (metres), alpha-normalised, 0 if alpha = 0
        meta: dict with ``ids`` (visible Gaussian rows, [V]), ``means2d`` ([V, 2]; in the autograd path a
            non-leaf tensor of the graph, call ``retain_grad()`` on it before ``backward`` for densification),
            ``n_visible``, ``n_isects`` ((tile, Gaussian) pairs), ``n_evals`` ((Gaussian, pixel) pairs
            evaluated by the forward), ``tiles`` ((tiles_x, tiles_y)), ``timings`` (seconds per stage).
    """

    rgb: Tensor
    alpha: Tensor
    ray_depth: Tensor
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass
class Binning:
    """Tile lists of one frame (numpy; ``rows`` index the packed per-Gaussian array).

    Attributes:
        rows: [V] int64 visible rows in depth order (ray distance, ties by row).
        offsets: [V+1] int64 intersections of ``rows[i]`` are ``offsets[i]..offsets[i+1]`` (Gaussian-major).
        tile_start: [n_tiles+1] int64 tile ``t`` owns ``sorted_row[tile_start[t]:tile_start[t+1]]``.
        sorted_row: [M] int64 packed rows, per tile in depth order.
        pos_of_isect: [M] int64 position in ``sorted_row`` of Gaussian-major intersection ``e``.
    """

    rows: np.ndarray
    offsets: np.ndarray
    tile_start: np.ndarray
    sorted_row: np.ndarray
    pos_of_isect: np.ndarray
    width: int
    height: int
    tiles_x: int
    tiles_y: int

    @property
    def n_isects(self) -> int:
        return int(self.sorted_row.shape[0])


def bin_gaussians(
    packed: np.ndarray, rows: np.ndarray, depth: np.ndarray, width: int, height: int,
    counts: np.ndarray | None = None,
) -> Binning:
    """Sort ``rows`` of ``packed`` by ``depth`` and build the per-tile lists.

    Tile counts and tile ids are computed in the (ascending) order of ``rows`` so that ``packed`` is read
    sequentially; only the small intersection records are scattered into depth order.

    Args:
        packed: [G, 16] per-Gaussian array (see :mod:`umi_aug.splat._kernels`), columns 10..15 filled.
        rows: [V] int64 rows to render.
        depth: [V] float64 sort key (ray distance, > 0) of ``rows``.
        width, height: image size.
        counts: [V] tiles per row when already known (the numba projection computes them).
    """
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    depth = np.ascontiguousarray(depth, dtype=np.float64)
    V = rows.shape[0]
    order = K.radix_argsort_f64(depth) if V else np.zeros(0, dtype=np.int64)
    if counts is None:
        counts = np.zeros(V, dtype=np.int64)
        with _parallel(4 * V, 256):
            K.count_tiles_kernel(packed, rows, width, height, counts)
    else:
        counts = np.ascontiguousarray(counts, dtype=np.int64)
    offsets = np.zeros(V + 1, dtype=np.int64)
    np.cumsum(counts[order], out=offsets[1:])
    start_of = np.empty(V, dtype=np.int64)
    start_of[order] = offsets[:-1]
    m = int(offsets[-1])
    isect_tile = np.empty(m, dtype=np.int64)
    isect_row = np.empty(m, dtype=np.int64)
    with _parallel(4 * V, 256):
        K.fill_tiles_kernel(packed, rows, start_of, counts, width, height, tiles_x, isect_tile, isect_row)
    n_tiles = tiles_x * tiles_y
    tile_start = np.empty(n_tiles + 1, dtype=np.int64)
    sorted_row = np.empty(m, dtype=np.int64)
    pos = np.empty(m, dtype=np.int64)
    K.sort_by_tile_kernel(isect_tile, isect_row, n_tiles, tile_start, sorted_row, pos)
    return Binning(rows[order], offsets, tile_start, sorted_row, pos, width, height, tiles_x, tiles_y)


def tiles_covering(mask: np.ndarray) -> np.ndarray:
    """``[tiles_y, tiles_x]`` bool: the 16x16 tiles holding at least one True pixel of ``mask [H, W]``."""
    m = np.asarray(mask, dtype=bool)
    if m.ndim != 2:
        raise SplatError(f"tiles_covering: mask must be [H, W], got shape {m.shape}")
    H, W = m.shape
    ty, tx = -(-H // TILE_SIZE), -(-W // TILE_SIZE)
    padded = np.zeros((ty * TILE_SIZE, tx * TILE_SIZE), dtype=bool)
    padded[:H, :W] = m
    return padded.reshape(ty, TILE_SIZE, tx, TILE_SIZE).any(axis=(1, 3))


def restrict_binning(binning: Binning, tiles: np.ndarray) -> Binning:
    """``binning`` with only the intersections of the ``tiles [tiles_y, tiles_x]`` (bool) kept: rasterising it gives
    exactly the full render's values in those tiles (each tile is composited on its own) and nothing elsewhere
    (transmittance 1). Forward only: the result has no ``pos_of_isect`` for the backward."""
    keep = np.asarray(tiles, dtype=bool)
    if keep.shape != (binning.tiles_y, binning.tiles_x):
        raise SplatError(f"tiles: expected a bool mask of shape {(binning.tiles_y, binning.tiles_x)} "
                         f"(tiles_y, tiles_x), got {keep.shape}")
    per_tile = np.diff(binning.tile_start)
    kept = per_tile * keep.reshape(-1)
    tile_start = np.zeros_like(binning.tile_start)
    np.cumsum(kept, out=tile_start[1:])
    sorted_row = binning.sorted_row[np.repeat(keep.reshape(-1), per_tile)]
    return dataclasses.replace(binning, tile_start=tile_start, sorted_row=sorted_row,
                               pos_of_isect=np.zeros(0, dtype=np.int64))


def _pixel_coords(binning: Binning, dtype) -> tuple[np.ndarray, np.ndarray]:
    """Tile-local pixel coordinates (the kernels work relative to each tile's origin)."""
    return np.arange(TILE_SIZE, dtype=dtype), np.arange(TILE_SIZE, dtype=dtype)


def check_min_transmittance(min_transmittance: float) -> float:
    """``min_transmittance`` as a float; raises :class:`SplatError` unless it is finite and in (0, 1)."""
    try:
        v = float(min_transmittance)
    except (TypeError, ValueError):
        raise SplatError(f"min_transmittance must be a number in (0, 1), got {min_transmittance!r}") from None
    if not 0.0 < v < 1.0:
        raise SplatError(f"min_transmittance must be in (0, 1) (a pixel stops compositing when its transmittance "
                         f"would fall below it; default {TRANSMITTANCE_THRESHOLD}), got {min_transmittance!r}")
    return v


def active_pixels(pixels: np.ndarray | Tensor | None, height: int, width: int) -> np.ndarray:
    """``pixels`` as the rasteriser's C-contiguous ``[H, W]`` bool mask (None: every pixel); raises
    :class:`SplatError` naming the shape or dtype it got otherwise."""
    if pixels is None:
        return np.ones((height, width), dtype=bool)
    m = pixels.detach().cpu().numpy() if isinstance(pixels, Tensor) else np.asarray(pixels)
    if m.dtype != np.bool_ or m.shape != (height, width):
        raise SplatError(f"pixels: expected a bool mask of shape {(height, width)} (H, W), got {m.dtype} "
                         f"{m.shape}")
    return np.ascontiguousarray(m)


def rasterize_packed(packed: np.ndarray, binning: Binning, uv64: np.ndarray, fused: bool = False,
                     min_transmittance: float = TRANSMITTANCE_THRESHOLD,
                     pixels: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Forward rasterisation in the dtype of ``packed`` (``uv64 [G, 2]``: the means in float64).

    ``min_transmittance``: a pixel stops at the first Gaussian that would bring its transmittance below this
    (early termination; the default is the INRIA/gsplat 1e-4). Raising it skips the faint tail of each pixel's
    compositing (inference only: the backward assumes the default).

    ``fused``: inference only — float32 ``packed`` runs the kernel compiled with fused multiply-adds
    (``K.raster_fwd_fused_kernel``, ~x1.16; results within rounding of the plain one); float64 (the tests'
    reference comparisons) always runs the plain kernel. A forward whose backward will run must stay unfused: the
    backward re-evaluates every pair with the plain kernel's instructions.

    ``pixels``: ``[H, W]`` bool, the pixels to composite (None: all). The others are left empty (``rgb`` and
    ``depth`` 0, ``T`` 1, ``last`` -1) at no cost where a whole tile is left out; the pixels composited are
    exactly what an all-pixel call gives. The backward needs nothing more: a pixel with nothing composited
    passes no gradient.

    Returns ``rgb`` [H, W, 3] (no background), ``depth`` [H, W] (not normalised), ``T`` [H, W], ``last``
    [H, W] int32 and ``evals`` [n_tiles]."""
    H, W = binning.height, binning.width
    dt = packed.dtype
    out = {
        "rgb": np.empty((H, W, 3), dtype=dt),
        "depth": np.empty((H, W), dtype=dt),
        "T": np.empty((H, W), dtype=dt),
        "last": np.empty((H, W), dtype=np.int32),
        "evals": np.zeros(binning.tiles_x * binning.tiles_y, dtype=np.int64),
    }
    xs, ys = _pixel_coords(binning, dt)
    with _parallel(16 * binning.n_isects + H * W, PARALLEL_CHUNK):
        (K.raster_fwd_fused_kernel if fused and dt == np.float32 else K.raster_fwd_kernel)(
            packed, uv64, binning.tile_start, binning.sorted_row, W, H, binning.tiles_x, xs, ys,
            K.raster_constants(dt, min_transmittance), active_pixels(pixels, H, W), out["rgb"], out["depth"], out["T"],
            out["last"], out["evals"], numba.get_num_threads(),
        )
    return out


def rasterize_packed_backward(
    packed: np.ndarray, binning: Binning, final_T: np.ndarray, last: np.ndarray,
    g_rgb: np.ndarray, g_depth: np.ndarray, g_T: np.ndarray, uv64: np.ndarray,
) -> np.ndarray:
    """Gradients ``[G, 10]`` (float64) w.r.t. the packed columns 0..9 of every row (zero for rows not binned);
    ``final_T``, ``last`` come from the forward, ``uv64 [G, 2]`` are the float64 means it used."""
    dt = packed.dtype
    xs, ys = _pixel_coords(binning, dt)
    isect_grad = np.empty((binning.n_isects, K.GRAD_COLS), dtype=dt)
    with _parallel(32 * binning.n_isects + binning.width * binning.height, PARALLEL_CHUNK):
        K.raster_bwd_kernel(
            packed, uv64, binning.tile_start, binning.sorted_row, binning.width, binning.height, binning.tiles_x,
            xs, ys, K.raster_constants(dt), final_T, last,
            np.ascontiguousarray(g_rgb, dtype=dt), np.ascontiguousarray(g_depth, dtype=dt),
            np.ascontiguousarray(g_T, dtype=dt), isect_grad, numba.get_num_threads(),
        )
    out = np.zeros((packed.shape[0], K.GRAD_COLS), dtype=np.float64)
    with _parallel(binning.n_isects, 256):
        K.reduce_grads_kernel(isect_grad, binning.pos_of_isect, binning.offsets, binning.rows, out)
    return out


def _pack(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, depths: Tensor, dtype) -> np.ndarray:
    """The rasteriser's rows ``[V, PACKED_COLS]`` in ``dtype`` (the projection's outputs, then each footprint):
    :func:`K.pack_kernel`; reference :func:`_pack_reference`."""
    parts = [t.detach().cpu().numpy() for t in (means2d, conics, opacities, colors, depths)]
    if any(p.dtype != dtype for p in parts):
        return _pack_reference(means2d, conics, opacities, colors, depths, dtype)
    packed = np.empty((means2d.shape[0], K.PACKED_COLS), dtype=dtype)
    with _parallel(4 * packed.shape[0], 256):
        K.pack_kernel(*parts, packed)
    return packed


def _pack_reference(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, depths: Tensor,
                    dtype) -> np.ndarray:
    """:func:`_pack` in numpy: a zero fill, the columns copied (cast to ``dtype``), then
    :func:`K.footprint_kernel` (``tests/splat/test_kernels.py``)."""
    V = means2d.shape[0]
    packed = np.zeros((V, K.PACKED_COLS), dtype=dtype)
    packed[:, 0:2] = means2d.detach().cpu().numpy()
    packed[:, 2:5] = conics.detach().cpu().numpy()
    packed[:, 5] = opacities.detach().cpu().numpy()
    packed[:, 6:9] = colors.detach().cpu().numpy()
    packed[:, 9] = depths.detach().cpu().numpy()
    with _parallel(4 * V, 256):
        K.footprint_kernel(packed)
    return packed


class RasterizeGaussians(torch.autograd.Function):
    """Differentiable tile rasteriser (numba forward and hand-written backward).

    ``forward(means2d [V, 2], conics [V, 3], opacities [V], colors [V, 3], depths [V], width, height, stats,
    pixels)`` returns ``(rgb_acc [H, W, 3], depth_acc [H, W], T_final [H, W])`` without background; the working
    dtype is the inputs' (float32 or float64). Gradients flow to all five inputs. ``pixels``: as in
    :func:`rasterize_packed` (the pixels left out are empty and pass no gradient).
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, width: int, height: int, stats: dict | None = None,
                pixels: np.ndarray | None = None):
        dt = np.float64 if means2d.dtype == torch.float64 else np.float32
        packed = _pack(means2d, conics, opacities, colors, depths, dt)
        rows = np.arange(packed.shape[0], dtype=np.int64)
        binning = bin_gaussians(packed, rows, depths.detach().cpu().numpy().astype(np.float64), width, height)
        uv64 = means2d.detach().cpu().numpy().astype(np.float64)
        out = rasterize_packed(packed, binning, uv64, pixels=pixels)
        ctx.packed, ctx.binning, ctx.uv64 = packed, binning, uv64
        ctx.grad_dtype = means2d.dtype
        ctx.final_T, ctx.last = out["T"].copy(), out["last"]  # the returned T may be modified by the caller
        ctx.timings = stats.get("timings") if stats is not None else None
        if stats is not None:
            stats["n_isects"] = binning.n_isects
            stats["n_evals"] = int(out["evals"].sum())
            stats["tiles"] = (binning.tiles_x, binning.tiles_y)
        tt = lambda a: torch.from_numpy(a).to(means2d.dtype)  # noqa: E731
        return tt(out["rgb"]), tt(out["depth"]), tt(out["T"])

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_T):
        t0 = time.perf_counter()
        zeros = lambda shape: np.zeros(shape, dtype=ctx.packed.dtype)  # noqa: E731
        H, W = ctx.binning.height, ctx.binning.width
        g_rgb = zeros((H, W, 3)) if g_rgb is None else g_rgb.detach().cpu().numpy()
        g_depth = zeros((H, W)) if g_depth is None else g_depth.detach().cpu().numpy()
        g_T = zeros((H, W)) if g_T is None else g_T.detach().cpu().numpy()
        grad = rasterize_packed_backward(
            ctx.packed, ctx.binning, ctx.final_T, ctx.last, g_rgb, g_depth, g_T, ctx.uv64
        )
        gt = torch.from_numpy(grad).to(ctx.grad_dtype)
        if ctx.timings is not None:
            ctx.timings["raster_backward"] = ctx.timings.get("raster_backward", 0.0) + time.perf_counter() - t0
        return gt[:, 0:2], gt[:, 2:5], gt[:, 5], gt[:, 6:9], gt[:, 9], None, None, None, None


def project_numba(
    gaussians: Gaussians,
    T_world_cam: Tensor | np.ndarray,
    intr: FisheyeIntrinsics,
    sh_degree: int,
    filter: str = DEFAULT_FILTER,
    near: float = DEFAULT_NEAR,
    far: float = DEFAULT_FAR,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Projection of the inference path (numba, float64 inside, no gradients): same semantics as
    :func:`umi_aug.splat.project.project_gaussians`.

    Returns:
        ``packed [N, 16]`` in the scene's dtype (see :mod:`umi_aug.splat._kernels`), ``uv [N, 2]`` float64,
        ``ray_depth [N]`` float64, ``valid [N]`` bool (rows not culled) and ``tile_counts [N]`` int64.
    """
    dilation, compensate = check_filter(filter)
    np_dt = np.float64 if gaussians.dtype == torch.float64 else np.float32
    pose = torch.as_tensor(T_world_cam).detach()
    R_cw, t_cw, campos = (x.numpy() for x in camera_from_pose(pose, torch.float64))
    arr = {k: np.ascontiguousarray(v.detach().cpu().numpy()) for k, v in gaussians.tensors().items()}
    N = gaussians.n
    packed = np.empty((N, K.PACKED_COLS), dtype=np_dt)
    uv64 = np.empty((N, 2), dtype=np.float64)
    depth64 = np.empty(N, dtype=np.float64)
    valid = np.empty(N, dtype=np.bool_)
    counts = np.empty(N, dtype=np.int64)
    cam = np.array([intr.fx, intr.fy, intr.cx, intr.cy, *intr.k, intr.theta_max], dtype=np.float64)
    with _parallel(8 * N, 256):
        K.project_kernel(
            arr["means"], arr["log_scales"], arr["quats_wxyz"], arr["logit_opacities"], arr["sh0"],
            arr["sh_rest"], int(sh_degree), R_cw, t_cw, campos, cam, float(near), float(far), float(dilation),
            bool(compensate), intr.width, intr.height, packed, uv64, depth64, valid, counts,
        )
    return packed, uv64, depth64, valid, counts


def _background(background, dtype: torch.dtype, H: int, W: int) -> Tensor:
    if background is None:
        return torch.zeros(3, dtype=dtype)
    bg = torch.as_tensor(background).to(dtype)
    if bg.shape not in ((3,), (H, W, 3)):
        raise SplatError(f"background must have shape [3] or [H, W, 3] = [{H}, {W}, 3], got {list(bg.shape)}")
    if not bool(torch.isfinite(bg.detach()).all()):
        raise SplatError("background has non-finite values")
    return bg


def _compose(rgb_acc: Tensor, depth_acc: Tensor, T: Tensor, bg: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    rgb = rgb_acc + T[..., None] * bg
    alpha = 1.0 - T
    ray_depth = depth_acc / torch.clamp_min(alpha, 1e-10)
    return rgb, alpha, ray_depth


def compose_background_numpy(out: dict[str, np.ndarray], bg: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Finish a :func:`rasterize_packed` result in place: background under the remaining transmittance,
    ``alpha = 1 - T``, alpha-normalised ray depth → ``(rgb [H, W, 3], alpha [H, W], ray_depth [H, W])`` tensors.
    Numpy, single-threaded: on small images torch's thread pool only adds wake-up latency."""
    bg_np = bg.detach().cpu().numpy().astype(out["rgb"].dtype)
    T_np = out["T"]
    rgb_np = out["rgb"]
    rgb_np += T_np[..., None] * bg_np
    alpha_np = 1.0 - T_np
    depth_np = out["depth"]
    np.divide(depth_np, np.maximum(alpha_np, 1e-10), out=depth_np)
    return torch.from_numpy(rgb_np), torch.from_numpy(alpha_np), torch.from_numpy(depth_np)


def render(
    gaussians: Gaussians,
    T_world_cam: Tensor | np.ndarray,  # [4, 4] camera pose (OpenCV camera frame), metres
    intr: FisheyeIntrinsics,
    background: Tensor | np.ndarray | Sequence[float] | None = None,  # [3] or [H, W, 3]
    sh_degree: int | None = None,
    *,
    filter: Literal["inria", "mip", "none"] = DEFAULT_FILTER,
    near: float = DEFAULT_NEAR,
    far: float = DEFAULT_FAR,
    projection: Literal["auto", "numba", "torch"] = "auto",
    tiles: np.ndarray | None = None,
    min_transmittance: float = TRANSMITTANCE_THRESHOLD,
    pixels: np.ndarray | Tensor | None = None,
) -> RenderOutput:
    """Render a fisheye image of ``gaussians`` from ``T_world_cam`` (CPU, numba).

    Differentiable with respect to every Gaussian parameter (and the pose and background if they require
    grad) whenever autograd is on and something requires grad: the projection then runs as
    :class:`umi_aug.splat.project.ProjectGaussians` (numba forward and backward; the torch-autograd reference
    when the pose requires grad or ``projection="torch"``) and the rasteriser as :class:`RasterizeGaussians`.
    Otherwise (``projection="auto"``) the numba inference projection and (float32) the fused-multiply-add
    rasteriser (:func:`rasterize_packed` ``fused=True``) run. The working dtype is the scene's (float32: fast path; float64:
    used by the tests).

    Args:
        gaussians: the scene.
        T_world_cam: camera pose ``[4, 4]``.
        intr: KB fisheye intrinsics; the image is ``intr.height x intr.width``.
        background: RGB behind the Gaussians (default black).
        sh_degree: SH degree to evaluate (default/maximum: the scene's).
        filter: screen-space low-pass: ``"inria"`` (+0.3 px^2), ``"mip"`` (+0.1 px^2, opacity compensated),
            ``"none"``.
        near, far: Gaussians whose centre is closer than ``near`` or farther than ``far`` (metres, along the
            ray) are culled.
        projection: ``"auto"``, or force ``"numba"`` (the inference projection, no gradients) / ``"torch"`` (the
            torch-autograd reference projection).
        tiles: ``[tiles_y, tiles_x]`` bool (16x16-pixel tiles, e.g. :func:`tiles_covering`): rasterise only these
            tiles — their pixels equal the full render's exactly, every other pixel is the background
            (``alpha`` 0). Inference only (no gradients, numba projection).
        min_transmittance: early termination: a pixel stops at the first Gaussian that would bring its
            transmittance below this (default 1e-4, as INRIA 3DGS and gsplat). A larger value skips the faint
            tail of each pixel (fewer evaluations; the skipped Gaussians' colour is missing, at most this
            fraction of the pixel). Inference only (the default when gradients are needed).
        pixels: ``[H, W]`` bool: composite only these pixels (e.g. a loss mask); every other pixel is the
            background (``alpha`` 0) and passes no gradient. The pixels composited, and every gradient of a loss
            that does not read the others (:func:`umi_aug.splat.losses.photometric_loss` with that mask), are
            exactly the full render's; a 16x16 tile without such a pixel costs nothing in the rasteriser.

    Returns:
        :class:`RenderOutput`.
    """
    if not isinstance(gaussians, Gaussians):
        raise SplatError(f"render expects a Gaussians, got {type(gaussians).__name__}")
    if not isinstance(intr, FisheyeIntrinsics):
        raise SplatError(f"render expects FisheyeIntrinsics, got {type(intr).__name__}")
    if projection not in ("auto", "numba", "torch"):
        raise SplatError(f"projection must be 'auto', 'numba' or 'torch', got {projection!r}")
    check_filter(filter)
    if not (0.0 <= near < far):
        raise SplatError(f"need 0 <= near < far, got near={near!r}, far={far!r}")
    dtype = gaussians.dtype
    if dtype not in (torch.float32, torch.float64):
        raise SplatError(f"render supports float32 and float64 scenes, got {dtype}")
    H, W = intr.height, intr.width
    bg = _background(background, dtype, H, W)
    deg = gaussians.sh_degree if sh_degree is None else int(sh_degree)
    if not 0 <= deg <= 3:
        raise SplatError(f"sh_degree must be in [0, 3], got {sh_degree!r}")
    deg = min(deg, gaussians.sh_degree)
    pose_t = torch.as_tensor(T_world_cam)
    needs_grad = torch.is_grad_enabled() and (
        any(t.requires_grad for t in gaussians) or pose_t.requires_grad or bg.requires_grad
    )
    use_torch = projection == "torch" or (projection == "auto" and needs_grad)
    if tiles is not None and use_torch:
        raise SplatError("render(tiles=...) renders part of the image for inference only: call it without "
                         "gradients and with projection 'auto' or 'numba'")
    t_min = check_min_transmittance(min_transmittance)
    if use_torch and t_min != TRANSMITTANCE_THRESHOLD:
        raise SplatError(f"render(min_transmittance={min_transmittance!r}) is inference only: the differentiable "
                         f"path stops at the default {TRANSMITTANCE_THRESHOLD}; call it without gradients")
    active = None if pixels is None else active_pixels(pixels, H, W)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if use_torch:
        proj = project_gaussians(gaussians, pose_t, intr, deg, filter, near, far, fast=projection == "auto",
                                 timings=timings)
        timings["project"] = time.perf_counter() - t0
        stats: dict[str, Any] = {"timings": timings}  # the backward adds timings["raster_backward"] (seconds)
        rgb_acc, depth_acc, T = RasterizeGaussians.apply(
            proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths, W, H, stats, active
        )
        timings["raster"] = time.perf_counter() - t0 - timings["project"]
        rgb, alpha, ray_depth = _compose(rgb_acc, depth_acc, T, bg)
        meta = {"ids": proj.ids, "means2d": proj.means2d, "projected": proj, "n_visible": len(proj), **stats}
    else:
        packed, uv64, depth64, valid, counts = project_numba(gaussians, pose_t, intr, deg, filter, near, far)
        rows = np.flatnonzero(valid)
        t1 = time.perf_counter()
        timings["project"] = t1 - t0
        binning = bin_gaussians(packed, rows, depth64[rows], W, H, counts[rows])
        if tiles is not None:
            binning = restrict_binning(binning, tiles)
        t2 = time.perf_counter()
        timings["bin"] = t2 - t1
        out = rasterize_packed(packed, binning, uv64, fused=True, min_transmittance=t_min, pixels=active)
        timings["raster"] = time.perf_counter() - t2
        rgb, alpha, ray_depth = compose_background_numpy(out, bg)
        ids = torch.from_numpy(rows)
        meta = {
            "ids": ids,
            "means2d": torch.from_numpy(uv64[rows]).to(dtype),
            "n_visible": int(rows.size),
            "n_isects": binning.n_isects,
            "n_evals": int(out["evals"].sum()),
            "tiles": (binning.tiles_x, binning.tiles_y),
        }
    timings["total"] = time.perf_counter() - t0
    meta["timings"] = timings
    return RenderOutput(rgb=rgb, alpha=alpha, ray_depth=ray_depth, meta=meta)
