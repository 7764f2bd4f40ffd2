"""End-to-end trainer tests on a procedural scene rendered by our own renderer: the fit improves, resume equals an
uninterrupted run, outputs are written (PLY round-trip), a finished run returns at once; session loading."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from umi_aug.errors import SplatError
from umi_aug.splat import Gaussians, read_ply, render
from umi_aug.splat.scenes import look_at_pose
from umi_aug.splat.train import SplatTrainConfig, TrainView, train_splat
from tests.splat._helpers import gopro_small

SIZE = 48


def _scene(rng, n=250) -> Gaussians:
    """Coloured blobs in a 0.6 m cube around the origin."""
    pts = rng.uniform(-0.3, 0.3, (n, 3))
    g = Gaussians.from_points(pts, rng.uniform(0.05, 0.95, (n, 3)), rng.uniform(0.02, 0.05, n), 0.8, sh_degree=1)
    return g


def _views(rng, gt: Gaussians, n_views=8) -> tuple[list[TrainView], object]:
    intr = gopro_small(SIZE, SIZE)
    views = []
    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    for k in range(n_views):
        a = 2 * math.pi * k / n_views
        pos = np.array([1.1 * math.cos(a), 1.1 * math.sin(a), 0.4 + 0.1 * math.sin(3 * a)])
        T = look_at_pose(pos, np.zeros(3))
        rgb = render(gt, T, intr, background=(0.1, 0.1, 0.1)).rgb.clamp(0, 1).numpy()
        img = (rgb * 255 + 0.5).astype(np.uint8)
        mask = np.hypot(xx - intr.cx, yy - intr.cy) < 0.45 * SIZE
        mask &= ~((yy > 0.8 * SIZE) & (np.abs(xx - SIZE / 2) < 6))  # a "gripper" corner
        views.append(TrainView(f"v{k:02d}", img, T, mask))
    return views, intr


CFG = SplatTrainConfig(iterations=100, max_gaussians=400, sh_degree=1, sh_increase_every=50, refine_start=20,
                       refine_every=20, eval_every=50, checkpoint_every=50, lr_means=1e-3, init_scale=1.0,
                       background=(0.1, 0.1, 0.1), train_eval_views=7, sheet_views=2)


@pytest.fixture
def problem(rng):
    gt = _scene(rng)
    views, intr = _views(rng, gt)
    init = rng.uniform(-0.35, 0.35, (200, 3))
    return views, intr, init


def test_fit_improves_and_writes_outputs(problem, tmp_path, rng):
    views, intr, init = problem
    cfg = replace(CFG, seed=int(rng.integers(1000)))
    res = train_splat(views, intr, init, None, cfg, tmp_path / "run", progress=False)
    h0, h1 = res.history[0], res.history[-1]
    assert h1["iteration"] == 100 and [h["iteration"] for h in res.history] == [0, 50, 100]
    assert h1["train_psnr"] > h0["train_psnr"] + 6.0, res.history
    assert h1["heldout_psnr"] > h0["heldout_psnr"] + 3.0, res.history
    assert math.isfinite(res.heldout_ssim) and res.heldout_ssim > h0["heldout_ssim"]
    assert res.gaussians.n <= cfg.max_gaussians and res.gaussians.n > 200
    res.gaussians.validate()
    for name in ("scene.ply", "checkpoint.pt", "metrics.json", "contact_sheet.png", "curve.png"):
        assert (tmp_path / "run" / name).is_file(), name
    assert res.ply_path == tmp_path / "run" / "scene.ply"
    assert read_ply(res.ply_path) == res.gaussians
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["heldout_psnr"] == pytest.approx(res.heldout_psnr) and m["n_heldout_views"] == 1
    sheet = cv2.imread(str(tmp_path / "run" / "contact_sheet.png"))
    assert sheet.shape == (SIZE, 3 * SIZE, 3)  # one held-out view: GT | render | error
    # a finished run returns at once with the same result
    again = train_splat(views, intr, init, None, cfg, tmp_path / "run", progress=False)
    assert again.gaussians == res.gaussians and again.heldout_psnr == pytest.approx(res.heldout_psnr)


def test_resume_equals_uninterrupted(problem, tmp_path, rng):
    views, intr, init = problem
    cfg = replace(CFG, iterations=40, eval_every=20, checkpoint_every=1000, seed=int(rng.integers(1000)))
    full = train_splat(views, intr, init, None, cfg, tmp_path / "a", progress=False)
    part = train_splat(views, intr, init, None, cfg, tmp_path / "b", progress=False, stop_at=27)
    assert part.ply_path is None and not (tmp_path / "b" / "scene.ply").exists()
    assert (tmp_path / "b" / "checkpoint.pt").is_file()
    resumed = train_splat(views, intr, init, None, cfg, tmp_path / "b", progress=False)
    assert resumed.gaussians == full.gaussians
    strip = lambda h: [{k: v for k, v in r.items() if "seconds" not in k and k != "loss"} for r in h]  # noqa: E731
    assert strip(resumed.history) == strip(full.history)
    assert [r["loss"] for r in resumed.history[1:]] == [r["loss"] for r in full.history[1:]]
    # a different config must not silently resume
    with pytest.raises(SplatError, match="other settings"):
        train_splat(views, intr, init, None, replace(cfg, lr_sh0=1e-2), tmp_path / "b", progress=False)
    # resume=False starts over and reproduces the same run (same seed -> same result)
    again = train_splat(views, intr, init, None, cfg, tmp_path / "b", progress=False, resume=False)
    assert again.gaussians == full.gaussians


def test_evaluating_only_at_the_end_trains_the_same_scene(problem, tmp_path, rng):
    """``eval_every = 0`` and ``eval_at_start = False`` (a dataset scene's settings) leave one evaluation, after the
    last step, and the same trained Gaussians as evaluating at 0, 20 and 40 (evaluations draw no random numbers);
    switching them on a checkpoint still resumes."""
    views, intr, init = problem
    cfg = replace(CFG, iterations=40, eval_every=20, checkpoint_every=1000, seed=int(rng.integers(1000)))
    full = train_splat(views, intr, init, None, cfg, tmp_path / "a", progress=False)
    assert [h["iteration"] for h in full.history] == [0, 20, 40]
    once = replace(cfg, eval_every=0, eval_at_start=False)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "curve.png").write_bytes(b"an earlier run's curve")
    end = train_splat(views, intr, init, None, once, tmp_path / "b", progress=False)
    assert [h["iteration"] for h in end.history] == [40]
    assert end.gaussians == full.gaussians
    assert end.heldout_psnr == full.heldout_psnr and end.heldout_ssim == full.heldout_ssim
    # one evaluation is no curve: curve.png is not drawn (a stale one is removed); the contact sheet is
    assert not (tmp_path / "b" / "curve.png").exists() and (tmp_path / "b" / "contact_sheet.png").is_file()
    assert (tmp_path / "a" / "curve.png").is_file()
    part = train_splat(views, intr, init, None, once, tmp_path / "c", progress=False, stop_at=13)
    assert part.history == []
    resumed = train_splat(views, intr, init, None, cfg, tmp_path / "c", progress=False)
    assert resumed.gaussians == full.gaussians and [h["iteration"] for h in resumed.history] == [20, 40]
    with pytest.raises(SplatError, match="eval_every"):
        train_splat(views, intr, init, cfg=replace(CFG, eval_every=-1), progress=False)


def test_bad_inputs(problem):
    views, intr, init = problem
    with pytest.raises(SplatError, match="image"):
        bad = [TrainView("x", views[0].image[:10], views[0].T_world_cam, views[0].loss_mask)]
        train_splat(bad, intr, init, progress=False)
    with pytest.raises(SplatError, match="loss_mask"):
        train_splat([TrainView("x", views[0].image, views[0].T_world_cam, np.zeros((SIZE, SIZE), bool))], intr,
                    init, progress=False)
    with pytest.raises(SplatError, match="init_xyz"):
        train_splat(views, intr, np.full((3, 3), np.nan), progress=False)
    with pytest.raises(SplatError, match="holdout_every"):
        train_splat(views, intr, init, cfg=replace(CFG, holdout_every=1), progress=False)


def test_session_views_and_masks(tmp_path, rng):
    """A hand-made session folder in UMI's layout (raw_video.mp4 + CSV with a lost row) -> views, masks, resized
    intrinsics."""
    pytest.importorskip("imageio_ffmpeg")
    from umi_aug.camera import gopro_intrinsics_2_7k, save_umi_intrinsics_json
    from umi_aug.data import CameraTrajectory, write_camera_trajectory_csv
    from umi_aug.data.video import VideoWriter
    from umi_aug.splat.train_session import loss_mask, session_views

    intr = gopro_intrinsics_2_7k().scaled(64, 48)
    root = tmp_path / "sess"
    (root / "calibration").mkdir(parents=True)
    save_umi_intrinsics_json(intr, root / "calibration" / "gopro_intrinsics_64x48.json")
    for seq, csv, n in (("mapping", "mapping_camera_trajectory.csv", 3), ("demo_a", "camera_trajectory.csv", 6)):
        d = root / "demos" / seq
        d.mkdir(parents=True)
        with VideoWriter(d / "raw_video.mp4", 64, 48, 60.0) as wr:
            for k in range(n):
                wr.write(rng.integers(0, 256, (48, 64, 3)).astype(np.uint8))
        T = np.repeat(np.eye(4)[None], n, 0)
        T[:, 0, 3] = np.arange(n) * 0.1
        lost = np.zeros(n, bool)
        lost[1] = True
        write_camera_trajectory_csv(root / "demos" / seq / csv, CameraTrajectory(
            np.arange(n), np.arange(n) / 60.0, np.where(lost, 1, 2), lost, np.zeros(n, bool), T))
    views, vi = session_views(root, contact={"demo_a": 4}, demo_stride=2)
    assert [v.name for v in views] == ["mapping/000000", "mapping/000002", "demo_a/000000", "demo_a/000002",
                                       "demo_a/000004"]
    assert vi == intr
    np.testing.assert_allclose(views[3].T_world_cam[0, 3], 0.2)
    m = loss_mask(intr)
    assert views[0].loss_mask.shape == (48, 64) and np.array_equal(views[0].loss_mask, m)
    assert not m[-1, 32] and m[24, 32] and not m[0, 0]  # gripper/finger bottom centre, corner outside circle
    views_small, vs = session_views(root, image_size=32)
    assert (vs.width, vs.height) == (32, 24) and views_small[0].image.shape == (24, 32, 3)
    assert [v.name for v in views_small] == ["mapping/000000", "mapping/000002"]  # no contact known: no demo
    # end to end from the session folder, through the CLI (random init, a few steps)
    import argparse

    from umi_aug.splat.cli import add_train_splat_parser

    ap = argparse.ArgumentParser()
    add_train_splat_parser(ap.add_subparsers(dest="command"))
    args = ap.parse_args(["train-splat", str(root), "--out", str(tmp_path / "out"), "--iterations", "3",
                          "--max-gaussians", "300", "--contact", "demo_a=4", "--image-size", "32", "--no-progress"])
    assert args.func(args) == 0
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["n_train_views"] + m["n_heldout_views"] == 4 and m["image_size"] == [32, 24]
    assert m["n_gaussians"] == 300 and read_ply(tmp_path / "out" / "scene.ply").n == 300
    with pytest.raises(SplatError, match="DEMO=FRAME"):
        args = ap.parse_args(["train-splat", str(root), "--out", str(tmp_path / "o2"), "--contact", "demo_a"])
        args.func(args)


def test_coarse_to_fine_trains_coarse_steps_at_the_coarse_size(problem, tmp_path, rng, monkeypatch):
    """``coarse_downscale=2``: the first ``coarse_fraction`` of the steps render at half size with the halved
    intrinsics, the rest and every evaluation at full size; the fit still improves like a full-resolution one."""
    import torch

    import umi_aug.splat.renderer as renderer

    views, intr, init = problem
    cfg = replace(CFG, coarse_downscale=2, coarse_fraction=0.3, seed=int(rng.integers(1000)))
    assert cfg.coarse_stop_step == 30
    calls: list[tuple[bool, int, int]] = []
    real_render = renderer.render

    def spy(g, T, intr_, *a, **k):
        calls.append((torch.is_grad_enabled(), intr_.width, intr_.height))
        return real_render(g, T, intr_, *a, **k)

    monkeypatch.setattr(renderer, "render", spy)
    res = train_splat(views, intr, init, None, cfg, tmp_path / "c2f", progress=False)
    train_sizes = [(w, h) for grad, w, h in calls if grad]
    assert train_sizes == [(SIZE // 2, SIZE // 2)] * 30 + [(SIZE, SIZE)] * 70
    assert all((w, h) == (SIZE, SIZE) for grad, w, h in calls if not grad)
    h0, h1 = res.history[0], res.history[-1]
    assert h1["train_psnr"] > h0["train_psnr"] + 6.0 and h1["heldout_psnr"] > h0["heldout_psnr"] + 3.0, res.history
    assert all(math.isfinite(h["loss"]) for h in res.history[1:])


def test_downscaled_views_are_block_means_with_conservative_masks(problem):
    from umi_aug.splat.train import _Data

    views, intr, _ = problem
    data = _Data(views)
    coarse, c_intr = data.downscaled(intr, 2)
    assert (c_intr.width, c_intr.height) == (SIZE // 2, SIZE // 2)
    assert c_intr.cx == pytest.approx((intr.cx + 0.5) / 2 - 0.5) and c_intr.fx == pytest.approx(intr.fx / 2)
    for v, img, m in zip(views, coarse.images, coarse.masks):
        area = cv2.resize(v.image.astype(np.float32) / 255.0, (SIZE // 2, SIZE // 2), interpolation=cv2.INTER_AREA)
        np.testing.assert_allclose(img.numpy(), area, atol=1e-6)
        full = v.loss_mask
        want = full[0::2, 0::2] & full[1::2, 0::2] & full[0::2, 1::2] & full[1::2, 1::2]
        assert np.array_equal(m.numpy(), want) and m.any() and not np.array_equal(m.numpy(), full[::2, ::2])
    with pytest.raises(SplatError, match=r"coarse_downscale = 5: the image size 48x48"):
        data.downscaled(intr, 5)


def test_coarse_settings_are_checked_and_old_checkpoints_resume(problem, tmp_path):
    import torch

    views, intr, init = problem
    for bad in ({"coarse_downscale": 0}, {"coarse_downscale": 1.5}, {"coarse_fraction": 1.2}):
        with pytest.raises(SplatError, match=next(iter(bad))):
            train_splat(views, intr, init, cfg=replace(CFG, **bad), progress=False)
    # a checkpoint written before the coarse settings existed resumes with their defaults (full resolution)
    cfg = replace(CFG, iterations=30, eval_every=15, checkpoint_every=1000)
    train_splat(views, intr, init, None, cfg, tmp_path / "old", progress=False, stop_at=10)
    path = tmp_path / "old" / "checkpoint.pt"
    ck = torch.load(path, weights_only=False)
    for key in ("coarse_downscale", "coarse_fraction"):
        del ck["cfg"][key]
    torch.save(ck, path)
    res = train_splat(views, intr, init, None, cfg, tmp_path / "old", progress=False)
    assert res.history[-1]["iteration"] == 30
    with pytest.raises(SplatError, match="coarse_downscale"):  # but not into a coarse run
        ck["iteration"] = 10
        torch.save(ck, path)
        train_splat(views, intr, init, None, replace(cfg, coarse_downscale=2), tmp_path / "old", progress=False)


def test_evaluation_ssim_equals_masked_ssim(problem):
    """The trainer's held-out SSIM (the fused loss's, with the view's kept target statistics) is
    :func:`masked_ssim`'s mean within float32 rounding, and its PSNR :func:`masked_psnr`'s exactly."""
    from umi_aug.splat.losses import masked_psnr, masked_ssim
    from umi_aug.splat.train import _Data, _evaluate, _render

    views, intr, init = problem
    g = _scene(np.random.default_rng(5), n=120)
    g = Gaussians(**{k: v.float() for k, v in g.tensors().items()})
    data = _Data(views)
    idx = [0, 3, 5]
    psnr, ssim = _evaluate(g, data, idx, intr, CFG, 1)
    ref_p, ref_s = [], []
    for i in idx:
        rgb = _render(g, data, i, intr, CFG, 1).rgb.clamp(0.0, 1.0)
        ref_p.append(masked_psnr(rgb, data.images[i], data.masks[i]))
        ref_s.append(float(masked_ssim(rgb, data.images[i], data.masks[i])))
    assert psnr == float(np.mean(ref_p))
    assert math.isfinite(ssim) and 0.0 < ssim < 1.0 and abs(ssim - float(np.mean(ref_s))) < 1e-5
