"""Forward rendering: fast numba path vs the dense float64 reference, analytic checks, fisheye geometry
(beyond 90 deg, fold-over culling, ray-distance order), extreme Gaussians (no NaN), API errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import numba  # noqa: E402,F401  (the splat extra; a missing install must fail, not skip)

from umi_aug.camera import FisheyeIntrinsics, kb  # noqa: E402
from umi_aug.errors import SplatError  # noqa: E402
from umi_aug.splat import Gaussians, render  # noqa: E402
from umi_aug.splat._torch_impl import _render_reference  # noqa: E402
from umi_aug.splat.scenes import random_gaussians, room_camera_pose, room_gaussians  # noqa: E402
from tests.splat._helpers import gopro_small, random_kb_intrinsics, random_pose, rays_at, single_gaussian  # noqa: E402

FILTERS = ["inria", "mip", "none"]


def _scene(rng, intr, n=60, dtype=torch.float64, **kw):
    T = random_pose(rng)
    g = random_gaussians(n, rng, intr, T, theta_max=kw.pop("theta_max", 2.0), dtype=dtype, **kw)
    bg = rng.uniform(0, 1, 3)
    return g, T, bg


@pytest.mark.parametrize("filt", FILTERS)
@pytest.mark.parametrize("which_intr", ["gopro", "random"])
def test_fast_matches_reference_float64(rng, filt, which_intr):
    intr = gopro_small() if which_intr == "gopro" else random_kb_intrinsics(rng)
    for _ in range(2):
        g, T, bg = _scene(rng, intr)
        out = render(g, T, intr, bg, filter=filt)
        ref = _render_reference(g, T, intr, bg, filter=filt)
        assert out.meta["n_visible"] > 10
        for name in ("rgb", "alpha", "ray_depth"):
            a, b = getattr(out, name), getattr(ref, name)
            assert a.dtype == torch.float64 and torch.isfinite(a).all()
            assert (a - b).abs().max().item() < 1e-9, name


@pytest.mark.parametrize("filt", FILTERS)
def test_fast_matches_reference_float32(rng, filt):
    """float32 fast path vs float64 reference: max abs error < 1e-4 everywhere except pixels where a
    (Gaussian, pixel) alpha sits within 1e-4 (relative) of the 1/255 threshold (or T of 1e-4), where the two
    precisions may legitimately take different branches; those must be rare."""
    intr = gopro_small()
    n_amb = n_px = 0
    for _ in range(3):
        g, T, bg = _scene(rng, intr, n=80, dtype=torch.float32)
        out = render(g, T, intr, bg, filter=filt)
        ref = _render_reference(g, T, intr, bg, filter=filt)
        amb = ref.meta["near_threshold"]
        n_amb += int(amb.sum())
        n_px += amb.numel()
        assert out.rgb.dtype == torch.float32
        err = (out.rgb.double() - ref.rgb).abs().amax(-1)
        assert err[~amb].max().item() < 1e-4
        assert (out.alpha.double() - ref.alpha).abs()[~amb].max().item() < 1e-4
        # ray depth (metres, ~0.5-3): relative
        rd = (out.ray_depth.double() - ref.ray_depth).abs() / ref.ray_depth.clamp_min(1e-3)
        assert rd[~amb & (ref.alpha > 0.01)].max().item() < 1e-4
    assert n_amb <= 0.01 * n_px


def test_fused_inference_rasteriser_matches_the_plain_one(rng):
    """The float32 inference forward (``fused=True``: fused multiply-adds) against the plain forward that
    training's backward replays, on fresh random scenes (rays up to 115 deg off axis, GoPro and random KB lenses):
    the same pairs visited, colour / depth / transmittance within rounding, no NaN. (render() itself, which uses
    the fused kernel for float32 scenes, is checked against the dense reference above; float64 stays plain.)"""
    from umi_aug.splat.renderer import bin_gaussians, project_numba, rasterize_packed

    dtype = torch.float32
    tol = {"rgb": 2e-6, "depth": 5e-6, "T": 1e-6}
    n_last = n_px = 0
    for k in range(4):
        intr = gopro_small() if k % 2 else random_kb_intrinsics(rng)
        g, T, _ = _scene(rng, intr, n=150, dtype=dtype)
        packed, uv64, depth64, valid, counts = project_numba(g, torch.as_tensor(T), intr, g.sh_degree, "inria",
                                                             0.0, 1e6)
        rows = np.flatnonzero(valid)
        b = bin_gaussians(packed, rows, depth64[rows], intr.width, intr.height, counts[rows])
        plain, fused = rasterize_packed(packed, b, uv64), rasterize_packed(packed, b, uv64, fused=True)
        assert np.array_equal(plain["evals"], fused["evals"]) and plain["evals"].sum() > 1000
        for name, t in tol.items():
            assert np.isfinite(fused[name]).all() and fused[name].dtype == plain[name].dtype
            assert np.abs(fused[name] - plain[name]).max() <= t, name
        n_last += int((plain["last"] != fused["last"]).sum())  # a branch taken differently at a threshold
        n_px += plain["last"].size
    assert n_last <= 1e-3 * n_px


def _min_transmittance_draw(rng) -> float:
    """An early-termination threshold, log-uniform from the default 1e-4 to 0.3 (a visibly faint tail cut)."""
    return float(10.0 ** rng.uniform(-4.0, math.log10(0.3)))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_early_termination_matches_reference(rng, dtype):
    """``render(min_transmittance=t)`` (numba; float32: the fused inference kernel) against the dense reference
    stopping at the same ``t``, on fresh random scenes dense enough that pixels terminate (GoPro and random KB
    lenses, rays up to 115 deg): float64 within 1e-9, float32 within 1e-4 off the reference's ambiguous pixels;
    the final transmittance never below ``t``; fewer Gaussian-pixel evaluations than at the default; no NaN."""
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    n_changed = n_amb = n_px = 0
    for k in range(3):
        intr = gopro_small() if k % 2 else random_kb_intrinsics(rng)
        g, T, bg = _scene(rng, intr, n=200, dtype=dtype, opacity_range=(0.5, 0.97), sigma_px_range=(2.0, 8.0))
        t_min = _min_transmittance_draw(rng) if k else 0.3
        out = render(g, T, intr, bg, min_transmittance=t_min)
        default = render(g, T, intr, bg)
        ref = _render_reference(g, T, intr, bg, min_transmittance=t_min)
        amb = ref.meta["near_threshold"]
        n_amb += int(amb.sum())
        n_px += amb.numel()
        for name in ("rgb", "alpha"):
            a, b = getattr(out, name), getattr(ref, name)
            assert a.dtype == dtype and torch.isfinite(a).all(), name
            err = (a.double() - b).abs()
            err = err.amax(-1) if err.ndim == 3 else err
            assert err[~amb].max().item() < tol, name
        assert (1.0 - out.alpha.double()).min().item() >= t_min * (1 - 1e-6)
        assert out.meta["n_evals"] <= default.meta["n_evals"]
        n_changed += int(((out.rgb - default.rgb).abs().amax(-1) > 1e-6).sum())
    assert n_changed > 0, "no pixel terminated early: the scenes do not test the threshold"
    assert n_amb <= 0.01 * n_px


def test_early_termination_through_render_composed(rng):
    """``render_composed(..., min_transmittance=t)`` equals ``render`` of the same set with ``t`` (no obstacles)."""
    from umi_aug.splat.compose import render_composed

    intr = gopro_small()
    g, T, bg = _scene(rng, intr, n=120, dtype=torch.float32, opacity_range=(0.5, 0.97))
    t_min = _min_transmittance_draw(rng)
    a = render_composed(g, [], T, intr, bg, min_transmittance=t_min)
    b = render(g, T, intr, bg, min_transmittance=t_min)
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.alpha, b.alpha)
    assert a.meta["n_evals"] == b.meta["n_evals"]


def test_min_transmittance_errors(rng):
    """Out-of-range thresholds are refused in one line naming the value; the differentiable path keeps the
    default (its backward assumes it)."""
    from umi_aug.splat.compose import render_composed

    intr = gopro_small(32, 24)
    g = random_gaussians(5, rng, intr)
    for bad in (0.0, 1.0, -0.1, float("nan"), "x"):
        with pytest.raises(SplatError, match="min_transmittance"):
            render(g, np.eye(4), intr, min_transmittance=bad)
        with pytest.raises(SplatError, match="min_transmittance"):
            render_composed(g, [], np.eye(4), intr, min_transmittance=bad)
    g_grad = Gaussians(*(t.clone().requires_grad_(True) for t in g))
    with pytest.raises(SplatError, match="inference only"):
        render(g_grad, np.eye(4), intr, min_transmittance=0.01)
    render(g_grad, np.eye(4), intr, min_transmittance=1e-4)  # the default is fine with gradients


def test_torch_projection_path_matches_numba_path(rng):
    intr = random_kb_intrinsics(rng)
    g, T, bg = _scene(rng, intr, n=50)
    a = render(g, T, intr, bg, projection="numba")
    b = render(g, T, intr, bg, projection="torch")
    assert torch.equal(a.meta["ids"].sort().values, b.meta["ids"].sort().values)
    for name in ("rgb", "alpha", "ray_depth"):
        assert (getattr(a, name) - getattr(b, name)).abs().max().item() < 1e-10


def test_isotropic_gaussian_on_axis_is_the_analytic_footprint():
    """On the optical axis J = diag(f/z): the splat of an isotropic Gaussian (sigma, distance z) is the 2D
    Gaussian with sigma_px = f sigma / z (+ the filter), peak = opacity at the principal point."""
    intr = FisheyeIntrinsics.equidistant(41, 33, 30.0)  # principal point (20, 16), on a pixel
    z, sigma, o, c = 2.0, 0.2, 0.7, np.array([0.9, 0.4, 0.2])
    for filt, lam in (("none", 0.0), ("inria", 0.3)):
        g = single_gaussian([0, 0, z], [sigma] * 3, opacity=o, rgb=c)
        out = render(g, np.eye(4), intr, filter=filt)
        s2 = (30.0 * sigma / z) ** 2 + lam
        v, u = np.mgrid[0:33, 0:41]
        a = o * np.exp(-0.5 * ((u - 20.0) ** 2 + (v - 16.0) ** 2) / s2)
        a = np.where(a >= 1 / 255, np.minimum(a, 0.99), 0.0)
        # the equidistant model bends the footprint slightly away from the axis: compare near the centre
        near = ((u - 20) ** 2 + (v - 16) ** 2) <= 9
        np.testing.assert_allclose(out.alpha.numpy()[near], a[near], rtol=2e-3)
        assert out.alpha[16, 20].item() == pytest.approx(o, rel=1e-12)
        np.testing.assert_allclose(out.rgb[16, 20].numpy(), o * c, rtol=1e-12)
        assert out.ray_depth[16, 20].item() == pytest.approx(z, rel=1e-12)
        np.testing.assert_allclose(out.alpha.numpy(), _render_reference(g, np.eye(4), intr, filter=filt).alpha.numpy(),
                                   atol=1e-12)
    # exact: sigma small enough that the footprint lies inside the small-angle region -> matches to 1e-6
    g = single_gaussian([0, 0, 10.0], [0.1] * 3, opacity=0.5)
    out = render(g, np.eye(4), intr, filter="none")
    a = 0.5 * np.exp(-0.5 * ((u - 20.0) ** 2 + (v - 16.0) ** 2) / 0.09)
    a = np.where(a >= 1 / 255, a, 0.0)
    np.testing.assert_allclose(out.alpha.numpy(), a, atol=2e-4)


@pytest.mark.parametrize("theta_deg", [60.0, 95.0, 100.0, 103.0])
def test_gaussian_far_off_axis_lands_on_the_kb_pixel(rng, theta_deg):
    """A small round splat at 100 deg (z < 0) renders centred on the KB projection of its mean."""
    intr = gopro_intrinsics_big()
    phi = float(rng.uniform(-0.35, 0.35)) + (math.pi if rng.uniform() < 0.5 else 0.0)  # along the long axis
    dist = 1.5
    mean = rays_at(math.radians(theta_deg), phi) * dist
    uv, ok = kb.project(mean, intr)
    assert ok
    J, _ = kb.project_jacobian(mean, intr)
    sigma = 1.5 / np.linalg.svd(J, compute_uv=False).max()  # <= 1.5 px (+ the 0.3 px^2 filter) on screen
    g = single_gaussian(mean, [sigma] * 3, opacity=0.9)
    out = render(g, np.eye(4), intr, filter="inria")
    a = out.alpha.numpy()
    assert a.sum() > 1.0
    v, u = np.mgrid[0 : intr.height, 0 : intr.width]
    cu, cv = (a * u).sum() / a.sum(), (a * v).sum() / a.sum()
    assert abs(cu - uv[0]) < 0.1 and abs(cv - uv[1]) < 0.1
    iu, iv = int(round(uv[0])), int(round(uv[1]))
    assert a[iv, iu] > 0.3
    assert out.ray_depth[iv, iu].item() == pytest.approx(dist, rel=1e-9)
    np.testing.assert_allclose(a, _render_reference(g, np.eye(4), intr, filter="inria").alpha.numpy(), atol=1e-10)


def gopro_intrinsics_big() -> FisheyeIntrinsics:
    # full GoPro image circle inside the frame: scale 2704x2028 to 160x120 keeps theta up to ~104 deg visible
    return gopro_small(160, 120)


def test_beyond_fold_over_and_inside_near_sphere_are_culled():
    intr = gopro_small()
    beyond = rays_at(intr.theta_max + 0.02, 0.3) * 1.0
    inside = rays_at(0.2, 0.1) * 0.005
    for mean in (beyond, inside):
        out = render(single_gaussian(mean, [0.3] * 3), np.eye(4), intr)
        assert out.meta["n_visible"] == 0 and out.alpha.abs().max().item() == 0.0
    out = render(single_gaussian(inside, [0.3] * 3), np.eye(4), intr, near=0.001)
    assert out.meta["n_visible"] == 1


def test_occlusion_uses_ray_distance_beyond_90_degrees():
    """Two Gaussians on the same ray at 97 deg (z < 0): the nearer one (by ray distance) must be in front.
    Sorting by camera z would put the farther one (more negative z) first."""
    intr = gopro_intrinsics_big()
    d = rays_at(math.radians(97.0), 0.4)
    near_g = single_gaussian(d * 0.8, [0.05] * 3, opacity=0.95, rgb=(1.0, 0.0, 0.0))
    far_g = single_gaussian(d * 1.6, [0.1] * 3, opacity=0.95, rgb=(0.0, 0.0, 1.0))
    g = Gaussians.cat([far_g, near_g])
    out = render(g, np.eye(4), intr, filter="none")
    uv, _ = kb.project(d, intr)
    u, v = int(round(uv[0])), int(round(uv[1]))
    r, _, b = out.rgb[v, u].tolist()
    assert r > 0.9 and b < 0.1
    assert out.ray_depth[v, u].item() < 1.0
    np.testing.assert_allclose(out.rgb.numpy(), _render_reference(g, np.eye(4), intr, filter="none").rgb.numpy(),
                               atol=1e-10)


def _extreme_scene(dtype) -> Gaussians:
    intr = gopro_small()
    rows = [
        (rays_at(math.radians(100), 0.7) * 1.0, [0.05, 0.05, 0.05], 0.8),  # 100 deg off axis
        (np.zeros(3), [0.1, 0.1, 0.1], 0.8),  # at the camera centre
        (np.array([1e-9, -1e-9, 1e-9]), [0.1, 0.1, 0.1], 0.8),  # 1 nm from it
        (np.array([0.0, 0.0, -1.0]), [0.2, 0.2, 0.2], 0.8),  # straight behind
        (rays_at(math.radians(150), 2.0) * 0.5, [0.3, 0.3, 0.3], 0.8),  # behind, beyond the fold-over
        (np.array([0.0, 0.0, 1.0]), [0.1, 0.1, 0.1], 0.8),  # exactly on the optical axis (r = 0)
        (np.array([0.1, 0.05, 1.0]), [0.3, 1e-7, 1e-7], 0.8),  # needle
        (np.array([-0.2, 0.1, 1.0]), [0.1, 1e-7, 1e-4], 0.8),  # 1e6 scale ratio
        (np.array([0.05, 0.1, 0.9]), [0.02, 0.02, 2e-8], 0.8),  # disc seen edge-on? (random rotation)
        (np.array([0.0, -0.1, 1.2]), [0.2, 0.2, 0.2], 0.0),  # zero opacity
        (np.array([0.1, 0.1, 0.8]), [1e-12, 1e-12, 1e-12], 0.9),  # vanishing
        (np.array([0.1, -0.1, 0.5]), [50.0, 50.0, 50.0], 0.9),  # enormous, camera inside it
        (rays_at(intr.theta_max - 1e-9, 1.0) * 2.0, [0.1, 0.1, 0.1], 0.8),  # at the fold-over
    ]
    rng = np.random.default_rng(0)
    n = len(rows)
    quats = rng.normal(size=(n, 4))
    quats[1] = 0.0  # zero quaternion -> identity
    op = np.array([r[2] for r in rows])
    return Gaussians.from_numpy(
        {
            "means": np.stack([r[0] for r in rows]),
            "log_scales": np.log(np.array([r[1] for r in rows])),
            "quats_wxyz": quats,
            "logit_opacities": np.where(op > 0, np.log(np.maximum(op, 1e-300) / (1 - op)), -1e4),
            "sh0": rng.normal(size=(n, 3)),
            "sh_rest": rng.normal(size=(n, 15, 3)) * 0.2,
        },
        dtype=dtype,
    )


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("filt", FILTERS)
def test_extreme_gaussians_no_nan(dtype, filt):
    intr = gopro_small()
    g = _extreme_scene(dtype).requires_grad_(True)
    for projection in ("auto", "numba"):
        with torch.set_grad_enabled(projection == "auto"):
            out = render(g, np.eye(4), intr, (0.1, 0.2, 0.3), filter=filt, projection=projection)
        for t in (out.rgb, out.alpha, out.ray_depth):
            assert torch.isfinite(t).all()
        assert out.alpha.max().item() > 0.5
    out = render(g, np.eye(4), intr, (0.1, 0.2, 0.3), filter=filt)
    loss = out.rgb.sum() + out.alpha.sum() + out.ray_depth.sum()
    grads = torch.autograd.grad(loss, list(g))
    for gr in grads:
        assert torch.isfinite(gr).all()
    ids = set(out.meta["ids"].tolist())
    assert 0 in ids and 5 in ids  # 100 deg and on-axis render
    assert not ids & {1, 2, 3, 4, 9}  # centre, 1 nm, behind, beyond the fold-over, zero opacity: culled
    for i in (1, 2, 3, 4, 9):
        assert all(gr[i].abs().max().item() == 0.0 for gr in grads)
    if dtype == torch.float64:
        ref = _render_reference(g, np.eye(4), intr, (0.1, 0.2, 0.3), filter=filt)
        tol = 1e-9 if filt != "none" else 1e-6
        assert (out.rgb - ref.rgb).abs().max().item() < tol
        rl = ref.rgb.sum() + ref.alpha.sum() + ref.ray_depth.sum()
        for a, b in zip(grads, torch.autograd.grad(rl, list(g))):
            assert torch.isfinite(b).all()
            assert (a - b).abs().max().item() <= 1e-6 * (1.0 + b.abs().max().item())


def test_background_alpha_depth_semantics(rng):
    intr = gopro_small(32, 24)
    empty = Gaussians.empty(3, torch.float64)
    bg_img = torch.as_tensor(rng.uniform(size=(24, 32, 3)))
    out = render(empty, np.eye(4), intr, bg_img)
    assert torch.equal(out.rgb, bg_img) and out.alpha.abs().max() == 0 and out.ray_depth.abs().max() == 0
    g = random_gaussians(40, rng, intr, sigma_px_range=(2, 6))
    out = render(g, np.eye(4), intr, (1.0, 1.0, 1.0))
    black = render(g, np.eye(4), intr)
    np.testing.assert_allclose(out.rgb.numpy(), black.rgb.numpy() + (1 - out.alpha.numpy())[..., None], atol=1e-12)
    assert (out.alpha <= 1 - 1e-4 + 1e-12).all()  # compositing stops before T < 1e-4
    d = out.ray_depth[out.alpha > 0]
    assert d.min() >= 0.5 - 1e-9 and d.max() <= 3.0 + 1e-9


def test_room_scene_renders_and_sh_degree_matters(rng):
    intr = gopro_small(64, 64)
    g = room_gaussians(3000, rng, dtype=torch.float32)
    T = room_camera_pose(0)
    out = render(g, T, intr)
    assert out.alpha.mean() > 0.5 and torch.isfinite(out.rgb).all()
    assert out.meta["n_isects"] >= out.meta["n_visible"] > 100 and out.meta["n_evals"] > 0
    d0 = render(g, T, intr, sh_degree=0)
    assert (d0.rgb - out.rgb).abs().max() > 1e-3
    g0 = g.with_sh_degree(0)
    assert torch.equal(render(g0, T, intr).rgb, d0.rgb)


def test_input_errors(rng):
    intr = gopro_small(32, 24)
    g = random_gaussians(5, rng, intr)
    with pytest.raises(SplatError, match="filter"):
        render(g, np.eye(4), intr, filter="gauss")
    with pytest.raises(SplatError, match=r"T_world_cam must have shape \[4, 4\]"):
        render(g, np.eye(3), intr)
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(SplatError, match="non-finite"):
        render(g, bad, intr)
    with pytest.raises(SplatError, match="background"):
        render(g, np.eye(4), intr, np.zeros((5, 5, 3)))
    with pytest.raises(SplatError, match="FisheyeIntrinsics"):
        render(g, np.eye(4), intr.K)
    with pytest.raises(SplatError, match="near"):
        render(g, np.eye(4), intr, near=2.0, far=1.0)
    with pytest.raises(SplatError, match="sh_degree"):
        render(g, np.eye(4), intr, sh_degree=4)
    with pytest.raises(SplatError, match="float32 and float64"):
        render(g.to(torch.float16), np.eye(4), intr)
