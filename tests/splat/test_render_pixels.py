"""Rendering only some pixels (``render(pixels=...)``, the trainer's ``loss_pixels_only``): the pixels kept equal the
full render bit for bit and the rest is empty, on fresh random scenes and masks (none, all, one pixel, scattered,
whole tiles, partial border tiles, Gaussians behind the camera and past 90 degrees); every gradient of a loss masked
the same way equals the full render's exactly; a trainer run is the same run either way; errors for a bad mask."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from umi_aug.errors import SplatError
from umi_aug.splat import render
from umi_aug.splat.losses import photometric_loss
from umi_aug.splat._constants import DEFAULT_FAR, DEFAULT_FILTER, DEFAULT_NEAR
from umi_aug.splat.renderer import bin_gaussians, project_numba, rasterize_packed
from umi_aug.splat.scenes import random_gaussians
from umi_aug.splat.train import SplatTrainConfig, TrainView, train_splat
from tests.splat._helpers import gopro_small, random_kb_intrinsics, random_pose


def _masks(rng, H: int, W: int):
    yield np.zeros((H, W), bool)
    yield np.ones((H, W), bool)
    one = np.zeros((H, W), bool)
    one[rng.integers(0, H), rng.integers(0, W)] = True  # a single pixel
    yield one
    for p in (0.05, 0.5, 0.95):
        yield rng.uniform(size=(H, W)) < p
    yy, xx = np.mgrid[0:H, 0:W]
    yield np.hypot(xx - W / 2, yy - H / 2) < 0.4 * max(H, W)  # an image circle: whole tiles out at the corners
    band = np.ones((H, W), bool)
    band[:, : int(rng.integers(16, W))] = False  # whole tiles out, and a cut through a tile
    yield band
    edge = np.zeros((H, W), bool)
    edge[-1, :] = edge[:, -1] = True  # the partial border tiles of a size that is not a multiple of 16
    yield edge


def _check(full, part, keep, bg):
    for name in ("rgb", "alpha", "ray_depth"):
        a, b = getattr(full, name).detach().numpy(), getattr(part, name).detach().numpy()
        assert np.isfinite(b).all(), name
        assert np.array_equal(a[keep], b[keep]), name  # bit for bit
    assert (part.alpha.detach().numpy()[~keep] == 0).all() and (part.ray_depth.detach().numpy()[~keep] == 0).all()
    rgb = part.rgb.detach().numpy()[~keep]
    np.testing.assert_array_equal(rgb, np.broadcast_to(bg.astype(rgb.dtype), rgb.shape))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_pixels_equal_the_full_render_with_and_without_gradients(rng, dtype):
    for intr in (gopro_small(70, 45), random_kb_intrinsics(rng, 64, 48)):
        H, W = intr.height, intr.width
        T = random_pose(rng)
        # theta_max 2.0 rad: many Gaussians past 90 degrees; some behind the camera are culled by the projection
        g = random_gaussians(300, rng, intr, T, theta_max=2.0, dtype=dtype)
        bg = rng.uniform(0, 1, 3)
        for grad in (False, True):
            gg = g.requires_grad_(grad)
            full = render(gg, T, intr, bg)
            assert full.meta["n_visible"] > 50 and ("projected" in full.meta) == grad
            for keep in _masks(rng, H, W):
                part = render(gg, T, intr, bg, pixels=keep)
                _check(full, part, keep, bg)
                assert part.meta["n_evals"] <= full.meta["n_evals"]  # fewer once a tile has no kept pixel
            assert render(gg, T, intr, bg, pixels=torch.from_numpy(keep)).meta["n_evals"] == part.meta["n_evals"]


def test_a_tile_without_a_kept_pixel_costs_no_evaluation(rng):
    intr = gopro_small(64, 48)
    T = random_pose(rng)
    g = random_gaussians(400, rng, intr, T, theta_max=1.5, dtype=torch.float32)
    keep = np.zeros((48, 64), bool)
    keep[16:32, 32:48] = True  # exactly tile (1, 2)
    keep[40, 5] = True  # one pixel of tile (2, 0)
    out = render(g, T, intr, pixels=keep)
    evals = out.meta["n_evals"]
    packed, uv64, depth64, valid, counts = project_numba(g, torch.as_tensor(T), intr, g.sh_degree, DEFAULT_FILTER,
                                                         DEFAULT_NEAR, DEFAULT_FAR)  # as render projects
    rows = np.flatnonzero(valid)
    b = bin_gaussians(packed, rows, depth64[rows], 64, 48, counts[rows])
    per_tile = rasterize_packed(packed, b, uv64, pixels=keep)["evals"].reshape(3, 4)
    assert per_tile.sum() == evals
    assert (per_tile[[0, 0, 0, 0, 1, 1, 1, 2, 2, 2], [0, 1, 2, 3, 0, 1, 3, 1, 2, 3]] == 0).all()
    assert per_tile[1, 2] > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gradients_of_a_masked_loss_equal_the_full_renders(rng, dtype):
    """The trainer's use: ``photometric_loss`` composites the target outside the mask before it reads anything, so
    rendering only the mask's pixels must give the same loss and the same gradient of every parameter, exactly."""
    intr = random_kb_intrinsics(rng, 48, 40)
    H, W = intr.height, intr.width
    T = random_pose(rng)
    g = random_gaussians(200, rng, intr, T, theta_max=1.95, dtype=dtype).requires_grad_(True)
    target = torch.as_tensor(rng.uniform(0, 1, (H, W, 3)), dtype=dtype)
    bg = torch.as_tensor(rng.uniform(0, 1, 3), dtype=dtype)
    for keep in list(_masks(rng, H, W))[1:]:  # the loss needs a pixel
        mask = torch.from_numpy(keep)
        res = []
        for pixels in (None, keep):
            out = render(g, T, intr, bg, pixels=pixels)
            loss, _ = photometric_loss(out.rgb, target, mask)
            res.append((loss.detach(), torch.autograd.grad(loss, list(g))))
        (l_full, g_full), (l_part, g_part) = res
        assert torch.equal(l_full, l_part) and math.isfinite(float(l_full))
        for a, b in zip(g_full, g_part):
            assert torch.isfinite(b).all() and torch.equal(a, b)
        if keep.all():
            assert all(a.abs().max() > 0 for a in g_full)  # something to compare


def test_training_with_loss_pixels_only_is_the_same_run(rng, tmp_path):
    size = 48
    intr = gopro_small(size, size)
    gt = random_gaussians(250, rng, intr, np.eye(4), theta_max=1.2, dtype=torch.float32)
    yy, xx = np.mgrid[0:size, 0:size]
    views = []
    for k in range(6):
        a = 0.15 * k
        T = np.eye(4)
        T[:3, :3] = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        img = (render(gt, T, intr).rgb.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
        mask = np.hypot(xx - size / 2, yy - size / 2) < 0.45 * size
        mask[:, :16] = False  # whole tiles out, as the gripper and mirrors of a UMI frame
        mask[40:, 20:30] = False
        views.append(TrainView(f"v{k}", img, T, mask))
    init = rng.uniform(-0.3, 0.3, (150, 3)) + [0.0, 0.0, 1.0]
    cfg = SplatTrainConfig(iterations=30, max_gaussians=300, sh_degree=1, sh_increase_every=15, refine_start=5,
                           refine_every=10, eval_every=15, checkpoint_every=1000, holdout_every=3,
                           seed=int(rng.integers(1000)), coarse_downscale=2, coarse_fraction=0.4)
    only = train_splat(views, intr, init, None, cfg, tmp_path / "only", progress=False)
    every = train_splat(views, intr, init, None, replace(cfg, loss_pixels_only=False), tmp_path / "every",
                        progress=False)
    assert only.gaussians == every.gaussians
    strip = lambda h: [{k: v for k, v in r.items() if "seconds" not in k} for r in h]  # noqa: E731
    np.testing.assert_equal(strip(only.history), strip(every.history))  # bit for bit (the first loss is nan in both)
    assert math.isfinite(only.heldout_psnr)


def test_pixels_errors(rng):
    intr = gopro_small(32, 24)
    g = random_gaussians(20, rng, intr, random_pose(rng))
    with pytest.raises(SplatError, match=r"pixels: expected a bool mask of shape \(24, 32\)"):
        render(g, np.eye(4), intr, pixels=np.ones((32, 24), bool))
    with pytest.raises(SplatError, match=r"pixels: expected a bool mask .* got float64"):
        render(g, np.eye(4), intr, pixels=np.ones((24, 32)))
