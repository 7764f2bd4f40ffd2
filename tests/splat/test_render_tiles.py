"""Rendering a subset of tiles (``render(tiles=...)``, :func:`restrict_binning`): the kept tiles equal the full
render bit for bit, the rest is background, on fresh random scenes and masks (none, all, scattered, partial
border tiles, Gaussians behind the camera and past 90 degrees); errors for a wrong mask or the gradient path."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from umi_aug.errors import SplatError
from umi_aug.splat import render
from umi_aug.splat.renderer import tiles_covering
from umi_aug.splat.scenes import random_gaussians, room_camera_pose, room_gaussians
from tests.splat._helpers import gopro_small, random_kb_intrinsics, random_pose

TS = 16


def _masks(rng, ty: int, tx: int):
    yield np.zeros((ty, tx), bool)
    yield np.ones((ty, tx), bool)
    for p in (0.05, 0.3, 0.7):
        yield rng.uniform(size=(ty, tx)) < p
    m = np.zeros((ty, tx), bool)
    m[-1, :] = m[:, -1] = True  # the partial border tiles of a size that is not a multiple of 16
    yield m


def _check(full, part, tiles, bg, H, W):
    keep = np.kron(tiles, np.ones((TS, TS), bool))[:H, :W]
    for name in ("rgb", "alpha", "ray_depth"):
        a, b = getattr(full, name).numpy(), getattr(part, name).numpy()
        assert np.isfinite(b).all(), name
        assert np.array_equal(a[keep], b[keep]), name  # bit for bit
    assert (part.alpha.numpy()[~keep] == 0).all()
    np.testing.assert_array_equal(part.rgb.numpy()[~keep], np.broadcast_to(bg, part.rgb.numpy()[~keep].shape))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tiles_equal_the_full_render(rng, dtype):
    for intr in (gopro_small(70, 45), random_kb_intrinsics(rng, 64, 48)):
        H, W = intr.height, intr.width
        ty, tx = -(-H // TS), -(-W // TS)
        T = random_pose(rng)
        # theta_max 2.0 rad: many Gaussians past 90 degrees; some behind the camera are culled by the projection
        g = random_gaussians(300, rng, intr, T, theta_max=2.0, dtype=dtype)
        bg = rng.uniform(0, 1, 3).astype(np.float64)
        full = render(g, T, intr, bg)
        assert full.meta["n_visible"] > 50
        for tiles in _masks(rng, ty, tx):
            part = render(g, T, intr, bg, tiles=tiles)
            _check(full, part, tiles, bg.astype(full.rgb.numpy().dtype), H, W)


def test_tiles_of_a_dense_scene_and_tiles_covering(rng):
    intr = gopro_small(64, 64)
    g = room_gaussians(3000, rng, dtype=torch.float32)
    T = room_camera_pose(int(rng.integers(0, 4)))
    full = render(g, T, intr)
    mask = np.zeros((64, 64), bool)
    mask[rng.integers(0, 64, 5), rng.integers(0, 64, 5)] = True
    tiles = tiles_covering(mask)
    assert tiles.shape == (4, 4) and tiles.sum() <= 5
    assert all(tiles[y // TS, x // TS] for y, x in zip(*np.nonzero(mask)))
    part = render(g, T, intr, tiles=tiles)
    _check(full, part, tiles, np.zeros(3, np.float32), 64, 64)
    assert part.meta["n_evals"] < full.meta["n_evals"]


def test_tiles_errors(rng):
    intr = gopro_small(32, 24)
    g = random_gaussians(20, rng, intr, random_pose(rng))
    with pytest.raises(SplatError, match=r"tiles: expected a bool mask of shape \(2, 2\)"):
        render(g, np.eye(4), intr, tiles=np.ones((3, 2), bool))
    with pytest.raises(SplatError, match="inference only"):
        render(g, np.eye(4), intr, tiles=np.ones((2, 2), bool), projection="torch")
    with pytest.raises(SplatError, match="mask must be"):
        tiles_covering(np.ones(5, bool))
