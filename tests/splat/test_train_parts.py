"""Trainer building blocks: masked L1/SSIM (vs the direct float64 formula), Adam (vs torch.optim.Adam), MCMC
relocation formula (vs the gsplat double loop), relocation / growth invariants, hold-out split, point-cloud PLY."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from umi_aug.errors import SplatError
from umi_aug.splat.densify import (
    MAX_RELOCATION_RATIO,
    grow,
    inject_noise,
    relocate_dead,
    relocation_opacity_scale,
)
from umi_aug.splat._torch_impl import _ssim_map_reference
from umi_aug.splat.losses import (
    masked_l1,
    masked_psnr,
    masked_ssim,
    photometric_loss,
    ssim_map,
    ssim_target_stats,
)
from umi_aug.splat.optim import GaussianAdam
from umi_aug.splat.train import split_views
from umi_aug.splat.train_session import read_point_cloud


# ------------------------------------------------------------------------------------------------------ SSIM
@pytest.mark.parametrize("case", ["random", "identical", "constant", "zeros", "extreme"])
def test_ssim_matches_direct_reference(rng, case):
    H, W = int(rng.integers(5, 19)), int(rng.integers(5, 23))
    x = rng.uniform(size=(H, W, 3))
    y = np.clip(x + rng.normal(scale=0.2, size=x.shape), 0, 1)
    if case == "identical":
        y = x.copy()
    elif case == "constant":
        x, y = np.full_like(x, 0.3), np.full_like(x, 0.7)
    elif case == "zeros":
        x, y = np.zeros_like(x), np.zeros_like(x)
    elif case == "extreme":
        x = (rng.uniform(size=x.shape) > 0.5).astype(float)
        y = 1.0 - x
    ref = _ssim_map_reference(x, y)
    fast = ssim_map(torch.as_tensor(x), torch.as_tensor(y)).numpy()
    assert np.isfinite(fast).all() and np.isfinite(ref).all()
    np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-10)
    fast32 = ssim_map(torch.as_tensor(x, dtype=torch.float32), torch.as_tensor(y, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(fast32, ref, rtol=0, atol=5e-4)
    if case in ("identical", "zeros"):
        np.testing.assert_allclose(ref, 1.0, atol=1e-12)


def test_masked_pixels_get_exactly_zero_gradient(rng):
    H, W = 24, 30
    pred = torch.as_tensor(rng.uniform(size=(H, W, 3))).requires_grad_(True)
    target = torch.as_tensor(rng.uniform(size=(H, W, 3)))
    mask = torch.as_tensor(rng.uniform(size=(H, W)) > 0.5)
    loss, parts = photometric_loss(pred, target, mask, 0.2)
    loss.backward()
    g = pred.grad
    assert torch.all(g[~mask] == 0)
    assert torch.all(g[mask].abs().sum(-1) > 0)
    # changing masked-out predictions changes nothing
    pred2 = pred.detach().clone()
    pred2[~mask] = torch.as_tensor(rng.uniform(size=(int((~mask).sum()), 3)))
    loss2, _ = photometric_loss(pred2, target, mask, 0.2)
    assert float(loss2) == float(loss.detach())
    # L1 / SSIM parts are means over the masked-in pixels only
    l1 = (pred.detach() - target).abs()[mask].mean()
    assert abs(parts["l1"] - float(l1)) < 1e-12
    ssim_ref = _ssim_map_reference(torch.where(mask[..., None], pred.detach(), target).numpy(), target.numpy())
    assert abs(parts["ssim"] - ssim_ref[mask.numpy()].mean()) < 1e-10
    assert abs(float(loss.detach()) - (0.8 * parts["l1"] + 0.2 * (1 - parts["ssim"]))) < 1e-12


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cached_target_stats_give_the_same_loss_and_gradient(rng, dtype):
    """A trainer keeps each view's ssim_target_stats: the loss, its parts and the prediction's gradient equal the
    ones computed from scratch (and the SSIM map the direct float64 reference), with and without a mask."""
    H, W = int(rng.integers(9, 31)), int(rng.integers(9, 37))
    target = torch.as_tensor(rng.uniform(size=(H, W, 3)), dtype=dtype)
    stats = ssim_target_stats(target)
    assert stats.shape == (1, 6, H, W) and not stats.requires_grad
    for mask in (None, torch.as_tensor(rng.uniform(size=(H, W)) > 0.3)):
        pred = torch.as_tensor(rng.uniform(size=(H, W, 3)), dtype=dtype)
        grads, losses, parts = [], [], []
        for ts in (None, stats):
            p = pred.clone().requires_grad_(True)
            loss, part = photometric_loss(p, target, mask, 0.2, target_stats=ts)
            loss.backward()
            grads.append(p.grad)
            losses.append(float(loss.detach()))
            parts.append(part)
        tol = 1e-12 if dtype == torch.float64 else 2e-6
        assert np.isfinite(losses).all() and torch.isfinite(grads[1]).all()
        assert abs(losses[0] - losses[1]) <= tol and abs(parts[0]["ssim"] - parts[1]["ssim"]) <= tol
        torch.testing.assert_close(grads[1], grads[0], rtol=0, atol=tol)
    ref = _ssim_map_reference(pred.double().numpy(), target.double().numpy())
    np.testing.assert_allclose(ssim_map(pred, target, stats).double().numpy(), ref, rtol=0,
                               atol=1e-10 if dtype == torch.float64 else 5e-4)
    # stats of another image size or dtype are refused with one clear error
    with pytest.raises(SplatError, match="target_stats"):
        photometric_loss(pred, target, None, 0.2, target_stats=stats[:, :, :-1])
    with pytest.raises(SplatError, match="target_stats"):
        ssim_map(pred, target, stats.to(torch.float16))
    with pytest.raises(SplatError, match="ssim_target_stats"):
        ssim_target_stats(target[..., :2])


def test_trainer_keeps_view_stats_within_its_memory_budget(rng, monkeypatch):
    """train_splat's views keep their SSIM target statistics up to SSIM_STATS_CACHE_BYTES and compute the rest
    each time; kept or not, they equal ssim_target_stats of the view."""
    import umi_aug.splat.train as train_mod

    views = [train_mod.TrainView(f"v{i}", rng.integers(0, 256, (12, 16, 3), dtype=np.uint8), np.eye(4),
                                 np.ones((12, 16), bool)) for i in range(4)]
    one_view = 6 * 12 * 16 * 4  # bytes of one view's float32 statistics
    monkeypatch.setattr(train_mod, "SSIM_STATS_CACHE_BYTES", 2 * one_view)
    data = train_mod._Data(views)
    for _ in range(2):
        for i in range(4):
            st = data.ssim_stats(i)
            torch.testing.assert_close(st, ssim_target_stats(data.images[i]), rtol=0, atol=0)
    assert sorted(data._ssim_stats) == [0, 1]
    assert data.ssim_stats(0) is data.ssim_stats(0) and data.ssim_stats(3) is not data.ssim_stats(3)


def test_masked_metrics_and_errors(rng):
    t = torch.as_tensor(rng.uniform(0.2, 0.8, size=(10, 12, 3)))
    mask = torch.zeros(10, 12, dtype=torch.bool)
    mask[2:5, 3:9] = True
    p = t.clone()
    p[mask] += 0.1
    p[~mask] = 5.0  # ignored
    assert abs(masked_psnr(p, t, mask) - 20.0) < 1e-9
    assert masked_psnr(t, t, mask) == float("inf")
    assert float(masked_l1(p, t, mask)) == pytest.approx(0.1, abs=1e-12)
    assert float(masked_ssim(t, t, mask)) == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(SplatError):
        photometric_loss(p, t, torch.zeros(10, 12, dtype=torch.bool))
    with pytest.raises(SplatError):
        photometric_loss(p, t[:, :5], mask)
    with pytest.raises(SplatError):
        photometric_loss(p, t, mask, ssim_weight=1.5)


# ------------------------------------------------------------------------------------------------------ Adam
def test_adam_matches_torch(rng):
    shapes = {"a": (7, 3), "b": (7,), "c": (7, 15, 3)}
    ours = {k: torch.as_tensor(rng.normal(size=s)).requires_grad_(True) for k, s in shapes.items()}
    theirs = {k: v.detach().clone().requires_grad_(True) for k, v in ours.items()}
    lrs = {"a": 1e-2, "b": 3e-3, "c": 1e-4}
    opt = GaussianAdam(ours)
    topt = torch.optim.Adam([{"params": [theirs[k]], "lr": lrs[k]} for k in shapes], eps=1e-15)
    w = {k: torch.as_tensor(rng.normal(size=s)) for k, s in shapes.items()}
    for _ in range(5):
        for params, step in ((ours, lambda: opt.step(lrs)), (theirs, topt.step)):
            loss = sum(((p * w[k]) ** 2).sum() for k, p in params.items())
            loss.backward()
            step()
        opt.zero_grad()
        topt.zero_grad()
    for k in shapes:
        torch.testing.assert_close(ours[k], theirs[k], rtol=1e-12, atol=1e-12)
    sd = opt.state_dict()
    opt2 = GaussianAdam(ours)
    opt2.load_state_dict(sd)
    assert opt2.step_count == 5 and torch.equal(opt2.exp_avg["c"], opt.exp_avg["c"])


@pytest.mark.parametrize("k", [0, 3, 8])
def test_adam_active_prefix_equals_the_full_update(rng, k):
    """Skipping the SH coefficients above the rendered degree (zero gradient, zero moments) changes nothing: the
    parameters and both moments equal the full update's bit for bit, over steps where the active prefix grows."""
    shapes = {"means": (9, 3), "sh_rest": (9, 15, 3)}
    full = {n: torch.as_tensor(rng.normal(size=s)).requires_grad_(True) for n, s in shapes.items()}
    part = {n: v.detach().clone().requires_grad_(True) for n, v in full.items()}
    o_full, o_part = GaussianAdam(full), GaussianAdam(part)
    lrs = {"means": 1e-2, "sh_rest": 3e-3}
    for step, active in enumerate([k, k, k + 3, k + 3, 15]):
        g = {n: torch.as_tensor(rng.normal(size=s)) for n, s in shapes.items()}
        g["sh_rest"][:, active:] = 0.0  # what the renderer gives coefficients above the rendered degree
        for params, opt, act in ((full, o_full, None), (part, o_part, {"sh_rest": active})):
            for n in shapes:
                params[n].grad = g[n].clone()
            opt.step(lrs, active=act)
        for n in shapes:
            assert torch.equal(full[n], part[n]), (step, n)
            assert torch.equal(o_full.exp_avg[n], o_part.exp_avg[n]) and torch.equal(o_full.exp_avg_sq[n],
                                                                                   o_part.exp_avg_sq[n])
    assert torch.isfinite(part["sh_rest"]).all()


def test_coefficients_above_the_rendered_degree_get_exactly_zero_gradient(rng):
    """What makes :meth:`GaussianAdam.step`'s ``active`` prefix exact: a degree-3 scene rendered at degree 1 gives
    the 12 coefficients of degrees 2-3 an exactly zero gradient, and a non-zero one to the 3 of degree 1."""
    from umi_aug.splat import Gaussians, render
    from umi_aug.splat.scenes import look_at_pose
    from tests.splat._helpers import gopro_small

    n = 60
    g = Gaussians.from_points(rng.uniform(-0.2, 0.2, (n, 3)), rng.uniform(0.1, 0.9, (n, 3)),
                              rng.uniform(0.03, 0.06, n), 0.7, sh_degree=3, dtype=torch.float32)
    sh_rest = torch.as_tensor(rng.normal(0, 0.1, (n, 15, 3)), dtype=torch.float32).requires_grad_(True)
    g = Gaussians(g.means, g.log_scales, g.quats_wxyz, g.logit_opacities, g.sh0, sh_rest)
    intr = gopro_small(40, 40)
    rgb = render(g, look_at_pose(np.array([0.8, 0.3, 0.4]), np.zeros(3)), intr, torch.zeros(3), 1).rgb
    (rgb * torch.as_tensor(rng.normal(size=rgb.shape), dtype=rgb.dtype)).sum().backward()
    assert sh_rest.grad is not None and torch.isfinite(sh_rest.grad).all()
    assert torch.count_nonzero(sh_rest.grad[:, 3:]) == 0
    assert torch.count_nonzero(sh_rest.grad[:, :3]) > 0


# ---------------------------------------------------------------------------------------------- relocation
def _relocation_loop(o: float, s: float, r: int) -> tuple[float, float]:
    """gsplat's compute_relocation written as its double loop (float64)."""
    new_o = 1.0 - (1.0 - o) ** (1.0 / r)
    denom = 0.0
    for i in range(1, r + 1):
        for k in range(i):
            denom += math.comb(i - 1, k) * ((-1.0) ** k / math.sqrt(k + 1)) * new_o ** (k + 1)
    return new_o, s * o / denom


def test_relocation_formula_matches_loop(rng):
    n = 40
    o = np.concatenate([rng.uniform(0.005, 0.999, n - 4), [0.005, 0.5, 0.99, 1 - 1e-6]])
    s = rng.uniform(0.001, 0.2, (n, 3))
    r = np.concatenate([rng.integers(1, MAX_RELOCATION_RATIO + 1, n - 4), [1, MAX_RELOCATION_RATIO, 2, 7]])
    new_o, new_s = relocation_opacity_scale(torch.as_tensor(o), torch.as_tensor(s), torch.as_tensor(r))
    for i in range(n):
        eo, es = _relocation_loop(o[i], 1.0, int(r[i]))
        assert abs(float(new_o[i]) - eo) <= 1e-12
        np.testing.assert_allclose(new_s[i].numpy(), es * s[i], rtol=1e-8)
        # r copies of opacity o' composite to the original opacity
        assert abs(1 - (1 - float(new_o[i])) ** int(r[i]) - o[i]) < 1e-9
    assert torch.isfinite(new_s).all()
    # one copy: unchanged
    o1, s1 = relocation_opacity_scale(torch.as_tensor(o), torch.as_tensor(s), torch.ones(n, dtype=torch.long))
    np.testing.assert_allclose(o1.numpy(), o, rtol=1e-12)
    np.testing.assert_allclose(s1.numpy(), s, rtol=1e-9)


def _random_params(rng, n: int, dead_frac: float = 0.3) -> dict[str, torch.Tensor]:
    op = rng.uniform(0.01, 0.95, n)
    op[rng.uniform(size=n) < dead_frac] = rng.uniform(1e-5, 0.005)
    p = {
        "means": rng.normal(size=(n, 3)),
        "log_scales": np.log(rng.uniform(0.005, 0.05, (n, 3))),
        "quats_wxyz": rng.normal(size=(n, 4)),
        "logit_opacities": np.log(op / (1 - op)),
        "sh0": rng.normal(size=(n, 3)),
        "sh_rest": rng.normal(size=(n, 15, 3)),
    }
    return {k: torch.as_tensor(v, dtype=torch.float32).requires_grad_(True) for k, v in p.items()}


def test_relocate_dead_invariants(rng):
    params = _random_params(rng, 200)
    opt = GaussianAdam(params)
    for t in params.values():
        t.grad = torch.ones_like(t)
    opt.step({k: 1e-3 for k in params})
    before = {k: v.detach().clone() for k, v in params.items()}
    dead_before = torch.sigmoid(before["logit_opacities"]) <= 0.005
    gen = torch.Generator().manual_seed(int(rng.integers(1 << 31)))
    n = relocate_dead(params, opt, gen, 0.005)
    assert n == int(dead_before.sum()) > 0
    assert params["means"].shape[0] == 200
    opt.check()
    op = torch.sigmoid(params["logit_opacities"].detach())
    assert bool((op >= 0.005 * (1 - 1e-5)).all())
    for k, v in params.items():
        assert torch.isfinite(v).all(), k
        assert v.is_leaf and v.requires_grad
    # every dead row now holds a copy of an alive row (means identical to some previously alive mean)
    alive_means = before["means"][~dead_before]
    for i in torch.nonzero(dead_before).squeeze(-1):
        assert (params["means"][i].detach() == alive_means).all(-1).any()
        assert torch.all(opt.exp_avg["means"][i] == 0) and torch.all(opt.exp_avg_sq["sh_rest"][i] == 0)
    # untouched rows keep parameters and moments
    changed = torch.zeros(200, dtype=torch.bool)
    changed |= dead_before
    changed |= (params["logit_opacities"].detach() != before["logit_opacities"])
    keep = ~changed
    assert keep.any()
    assert torch.equal(params["sh0"].detach()[keep], before["sh0"][keep])
    assert torch.all(opt.exp_avg["sh0"][keep] != 0)


def test_grow_never_exceeds_budget(rng):
    params = _random_params(rng, 50, dead_frac=0.0)
    opt = GaussianAdam(params)
    gen = torch.Generator().manual_seed(int(rng.integers(1 << 31)))
    budget = int(rng.integers(60, 120))
    sizes = []
    for _ in range(30):
        relocate_dead(params, opt, gen, 0.005)
        grow(params, opt, gen, budget, 1.05, 0.005)
        n = params["means"].shape[0]
        sizes.append(n)
        assert n <= budget
        opt.check()
        assert opt.params is params
        for k, v in params.items():
            assert v.shape[0] == n and torch.isfinite(v).all() and v.is_leaf and v.requires_grad, k
    assert sizes[-1] == budget and sizes == sorted(sizes)
    assert grow(params, opt, gen, budget, 1.05, 0.005) == 0


def test_inject_noise_moves_only_transparent(rng):
    params = _random_params(rng, 100, dead_frac=0.0)
    with torch.no_grad():
        params["logit_opacities"][:50] = -8.0  # opacity ~3e-4: moves
        params["logit_opacities"][50:] = 2.0  # 0.88: frozen by the gate
    before = params["means"].detach().clone()
    inject_noise(params, 5e5 * 1.6e-4, torch.Generator().manual_seed(3))
    d = (params["means"].detach() - before).norm(dim=-1)
    assert bool((d[:50] > 0).all()) and float(d[50:].max()) < 1e-6 * float(d[:50].min() + 1e-12) + 1e-12
    p2 = {k: v.detach().clone() for k, v in params.items()}
    p2["means"] = before.clone()
    inject_noise(p2, 5e5 * 1.6e-4, torch.Generator().manual_seed(3))
    assert torch.equal(p2["means"], params["means"].detach())


# ------------------------------------------------------------------------------------------ split / cloud IO
def test_split_views():
    train, held = split_views(17, 8)
    assert held == [0, 8, 16] and train == [i for i in range(17) if i not in (0, 8, 16)]
    assert split_views(5, 0) == ([0, 1, 2, 3, 4], [])
    assert split_views(1, 8) == ([0], [])


def test_read_point_cloud_from_sim_and_recon(tmp_path, rng):
    from umi_aug.recon.cloud import SceneCloud, write_ply as recon_write
    from umi_aug.sim.pointcloud import write_ply as sim_write

    pts = rng.normal(size=(30, 3))
    cols = rng.integers(0, 256, (30, 3)).astype(np.uint8)
    sim_write(tmp_path / "a.ply", pts, cols, rng.normal(size=(30, 3)), rng.integers(0, 9, 30))
    xyz, rgb = read_point_cloud(tmp_path / "a.ply")
    np.testing.assert_allclose(xyz, pts.astype(np.float32), rtol=0, atol=0)
    np.testing.assert_allclose(rgb, cols / 255.0)
    recon_write(tmp_path / "b.ply", SceneCloud(pts, cols, np.zeros((30, 3))))
    xyz, rgb = read_point_cloud(tmp_path / "b.ply")
    np.testing.assert_allclose(xyz, pts.astype(np.float32), rtol=0, atol=0)
    sim_write(tmp_path / "c.ply", pts)
    xyz, rgb = read_point_cloud(tmp_path / "c.ply")
    assert rgb is None and xyz.shape == (30, 3)
    (tmp_path / "d.ply").write_bytes(b"not a ply")
    with pytest.raises(SplatError):
        read_point_cloud(tmp_path / "d.ply")


def test_sparse_cloud_is_topped_up_with_random_points(rng):
    from umi_aug.splat.train_session import random_init_points, top_up_init_points

    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, :3, 3] = rng.normal(scale=0.2, size=(5, 3))
    xyz = rng.normal(size=(40, 3))
    rgb = rng.uniform(size=(40, 3))
    out_xyz, out_rgb = top_up_init_points(xyz, rgb, 100, T, rng)
    assert out_xyz.shape == (100, 3) and out_rgb.shape == (100, 3)
    np.testing.assert_array_equal(out_xyz[:40], xyz)  # the cloud is kept, in order, with its colours
    np.testing.assert_array_equal(out_rgb[:40], rgb)
    assert np.isfinite(out_xyz).all() and ((out_rgb >= 0) & (out_rgb <= 1)).all()
    # the added points lie in the random-initialisation cube around the cameras
    ref = random_init_points(T, 10_000, np.random.default_rng(0))
    lo, hi = ref.min(0), ref.max(0)
    assert ((out_xyz[40:] >= lo - 1e-2) & (out_xyz[40:] <= hi + 1e-2)).all()
    # a cloud already large enough (and no colours) is returned as is, with random colours
    same_xyz, same_rgb = top_up_init_points(xyz, None, 10, T, rng)
    np.testing.assert_array_equal(same_xyz, xyz)
    assert same_rgb.shape == (40, 3)
