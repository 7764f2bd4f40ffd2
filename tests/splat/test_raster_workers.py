"""The rasteriser's tiles shared among its workers (``_kernels.raster_fwd_kernel`` / ``raster_bwd_kernel``: worker k of
n takes tiles k, k + n, ...) give the same bytes as the reference that hands numba one tile per ``prange`` iteration
(``_raster_fwd_kernel_per_tile`` / ``_raster_bwd_kernel_per_tile``), for any worker count and thread count, on fresh
random scenes: float32 and float64, Gaussians past 90 degrees and behind the camera, image sizes that are not a
multiple of the tile, pixel masks, fewer tiles than workers, no Gaussian at all."""

from __future__ import annotations

from dataclasses import replace

import numba
import numpy as np
import pytest
import torch

from umi_aug.splat import _kernels as K
from umi_aug.splat._constants import DEFAULT_FILTER
from umi_aug.splat.renderer import _pixel_coords, active_pixels, bin_gaussians, project_numba
from umi_aug.splat.scenes import random_gaussians
from tests.splat._helpers import gopro_small, random_kb_intrinsics, random_pose


def _inputs(rng, intr, n: int, dtype):
    T = random_pose(rng)
    # theta_max 2.0 rad: many Gaussians past 90 degrees; some behind the camera are culled by the projection
    g = random_gaussians(n, rng, intr, T, theta_max=2.0, dtype=dtype)
    packed, uv64, depth64, valid, counts = project_numba(g, torch.as_tensor(T), intr, g.sh_degree, DEFAULT_FILTER)
    rows = np.flatnonzero(valid)
    b = bin_gaussians(packed, rows, depth64[rows], intr.width, intr.height, counts[rows])
    xs, ys = _pixel_coords(b, packed.dtype)
    return packed, uv64, b, xs, ys


def _forward(kernel, packed, uv64, b, xs, ys, active, *extra):
    H, W, dt = b.height, b.width, packed.dtype
    out = (np.full((H, W, 3), np.nan, dt), np.full((H, W), np.nan, dt), np.full((H, W), np.nan, dt),
           np.full((H, W), -7, np.int32), np.full(b.tiles_x * b.tiles_y, -7, np.int64))
    kernel(packed, uv64, b.tile_start, b.sorted_row, W, H, b.tiles_x, xs, ys, K.raster_constants(dt), active, *out,
           *extra)
    return out


def _backward(kernel, packed, uv64, b, xs, ys, fwd, grads, *extra):
    out = np.full((b.n_isects, K.GRAD_COLS), np.nan, packed.dtype)
    kernel(packed, uv64, b.tile_start, b.sorted_row, b.width, b.height, b.tiles_x, xs, ys,
           K.raster_constants(packed.dtype), fwd[2], fwd[3], *grads, out, *extra)
    return out


def _same(a, b) -> bool:
    return all(np.array_equal(x, y) and not np.isnan(x).any() for x, y in zip(a, b))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_workers_give_the_per_tile_kernels_bytes(rng, dtype):
    threads = numba.get_num_threads()
    cases = [(gopro_small(70, 45), 300), (random_kb_intrinsics(rng, 64, 48), 400), (gopro_small(40, 24), 150),
             (gopro_small(16, 16), 60), (gopro_small(70, 45), 0)]
    try:
        for intr, n in cases:
            packed, uv64, b, xs, ys = _inputs(rng, intr, n, dtype)
            H, W = intr.height, intr.width
            for active in (np.ones((H, W), bool), rng.uniform(size=(H, W)) < 0.5,
                           active_pixels(np.pad(np.ones((H, W // 2), bool), ((0, 0), (0, W - W // 2))), H, W)):
                ref = _forward(K._raster_fwd_kernel_per_tile, packed, uv64, b, xs, ys, active)
                dt = packed.dtype
                grads = (rng.normal(size=(H, W, 3)).astype(dt), rng.normal(size=(H, W)).astype(dt),
                         rng.normal(size=(H, W)).astype(dt))
                g_ref = _backward(K._raster_bwd_kernel_per_tile, packed, uv64, b, xs, ys, ref, grads)
                assert np.isfinite(g_ref).all()
                # more workers than tiles, one, two, an odd count; on 1 thread and on the machine's threads
                for n_threads in sorted({1, threads}):
                    numba.set_num_threads(n_threads)
                    for n_workers in (1, 2, 3, 7, b.tiles_x * b.tiles_y + 5):
                        got = _forward(K.raster_fwd_kernel, packed, uv64, b, xs, ys, active, n_workers)
                        assert _same(got, ref), (intr.width, n, n_threads, n_workers)
                        g = _backward(K.raster_bwd_kernel, packed, uv64, b, xs, ys, got, grads, n_workers)
                        assert np.array_equal(g, g_ref), (intr.width, n, n_threads, n_workers)
                    numba.set_num_threads(threads)
                if dtype == torch.float32:  # the inference kernel (fused multiply-adds) against itself per tile
                    fused = _forward(K.raster_fwd_fused_kernel, packed, uv64, b, xs, ys, active, 2)
                    np.testing.assert_allclose(fused[0], ref[0], atol=1e-5)
                    assert np.isfinite(fused[0]).all()
    finally:
        numba.set_num_threads(threads)


def test_a_mutant_schedule_that_skips_the_last_tile_is_caught(rng):
    """The comparison above can fail: a worker split that leaves out the last tile differs from the reference."""
    intr = gopro_small(70, 45)
    packed, uv64, b, xs, ys = _inputs(rng, intr, 300, torch.float32)
    active = np.ones((intr.height, intr.width), bool)
    ref = _forward(K._raster_fwd_kernel_per_tile, packed, uv64, b, xs, ys, active)
    b_short = replace(b, tile_start=b.tile_start[:-1].copy())  # one tile fewer
    got = _forward(K.raster_fwd_kernel, packed, uv64, b_short, xs, ys, active, 2)
    assert not _same(got, ref)
