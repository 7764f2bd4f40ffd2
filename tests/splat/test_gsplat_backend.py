"""gsplat backend: the pure conversion (CPU) and the clear error without gsplat/CUDA. The GPU path itself is not
exercised here (no GPU in CI)."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest
import torch

from umi_aug.camera import kb
from umi_aug.errors import SplatError
from umi_aug.splat import render
from umi_aug.splat.gsplat_backend import gsplat_rasterization_kwargs, render_gsplat, render_with_backend
from umi_aug.splat.scenes import random_gaussians
from tests.splat._helpers import gopro_small, random_kb_intrinsics, random_pose


def _kb_project_gsplat_convention(p_world: np.ndarray, kw: dict) -> np.ndarray:
    """OpenCV-fisheye projection written from gsplat's side: world -> camera with ``viewmats``, then
    ``theta_d = theta (1 + k1 theta^2 + ...)`` and ``K`` (pixel centres at +0.5)."""
    V = kw["viewmats"][0].double().numpy()
    K = kw["Ks"][0].double().numpy()
    k1, k2, k3, k4 = kw["radial_coeffs"][0].double().numpy()
    p = p_world @ V[:3, :3].T + V[:3, 3]
    r = np.hypot(p[:, 0], p[:, 1])
    th = np.arctan2(r, p[:, 2])
    th_d = th * (1 + k1 * th**2 + k2 * th**4 + k3 * th**6 + k4 * th**8)
    s = np.where(r > 0, th_d / np.where(r > 0, r, 1.0), 1.0)
    return np.stack([K[0, 0] * s * p[:, 0] + K[0, 2], K[1, 1] * s * p[:, 1] + K[1, 2]], axis=-1)


def test_conversion_shapes_values_and_camera(rng):
    intr = random_kb_intrinsics(rng)
    T = random_pose(rng)
    g = random_gaussians(30, rng, intr, T, theta_max=1.2, sh_degree=3)
    g.quats_wxyz[0] = 0.0  # zero norm -> identity, as our renderer treats it
    g.quats_wxyz[1] *= 7.0
    kw = gsplat_rasterization_kwargs(g, T, intr, filter="mip", near=0.05)
    N = g.n
    assert kw["means"].shape == (N, 3) and kw["quats"].shape == (N, 4) and kw["scales"].shape == (N, 3)
    assert kw["opacities"].shape == (N,) and kw["colors"].shape == (N, 16, 3)
    assert kw["viewmats"].shape == (1, 4, 4) and kw["Ks"].shape == (1, 3, 3) and kw["radial_coeffs"].shape == (1, 4)
    assert all(t.dtype == torch.float32 for t in kw.values() if isinstance(t, torch.Tensor))
    np.testing.assert_allclose(kw["scales"].numpy(), np.exp(g.log_scales.numpy()), rtol=1e-6)
    np.testing.assert_allclose(kw["opacities"].numpy(), 1 / (1 + np.exp(-g.logit_opacities.numpy())), rtol=1e-6)
    q = kw["quats"].double().numpy()
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(q[0], [1.0, 0.0, 0.0, 0.0])
    q_in = g.quats_wxyz.numpy()[1:]
    np.testing.assert_allclose(q[1:], q_in / np.linalg.norm(q_in, axis=1, keepdims=True), atol=1e-6)
    np.testing.assert_allclose(kw["colors"][:, 0].numpy(), g.sh0.numpy(), rtol=1e-6)
    np.testing.assert_allclose(kw["colors"][:, 1:].numpy(), g.sh_rest.numpy(), rtol=1e-6)
    np.testing.assert_allclose(kw["viewmats"][0].double().numpy() @ T, np.eye(4), atol=1e-6)
    np.testing.assert_allclose(kw["radial_coeffs"][0].numpy(), intr.k, rtol=1e-6)
    assert (kw["width"], kw["height"], kw["sh_degree"]) == (intr.width, intr.height, 3)
    assert kw["camera_model"] == "fisheye" and kw["with_ut"] and kw["with_eval3d"] and kw["packed"] is False
    assert (kw["eps2d"], kw["rasterize_mode"], kw["near_plane"]) == (pytest.approx(0.1), "antialiased", 0.05)
    # the same world points land on the same pixels through gsplat's camera (pixel centres at +0.5) and ours
    p_world = g.means.numpy()
    uv_ours, ok = kb.project((p_world - T[:3, 3]) @ T[:3, :3], intr)
    uv_gs = _kb_project_gsplat_convention(p_world, kw)
    np.testing.assert_allclose(uv_gs[ok] - 0.5, uv_ours[ok], atol=1e-3)
    assert gsplat_rasterization_kwargs(g, T, intr, sh_degree=1)["sh_degree"] == 1
    assert gsplat_rasterization_kwargs(g.with_sh_degree(0), T, intr)["colors"].shape == (N, 1, 3)


def test_conversion_differentiable_option(rng):
    intr = gopro_small()
    g = random_gaussians(5, rng, intr, None).requires_grad_()
    kw = gsplat_rasterization_kwargs(g, np.eye(4), intr, differentiable=True, dtype=torch.float64)
    (kw["means"].sum() + kw["scales"].sum() + kw["opacities"].sum() + kw["quats"].sum() + kw["colors"].sum()).backward()
    assert all(t.grad is not None and torch.isfinite(t.grad).all() for t in g)
    kw = gsplat_rasterization_kwargs(g, np.eye(4), intr)
    assert not kw["means"].requires_grad


def test_conversion_errors(rng):
    intr = gopro_small()
    g = random_gaussians(5, rng, intr, None)
    with pytest.raises(SplatError, match="filter"):
        gsplat_rasterization_kwargs(g, np.eye(4), intr, filter="box")
    with pytest.raises(SplatError, match="sh_degree"):
        gsplat_rasterization_kwargs(g, np.eye(4), intr, sh_degree=4)
    with pytest.raises(SplatError, match="pose"):
        gsplat_rasterization_kwargs(g, np.eye(3), intr)


def test_render_gsplat_clear_error_without_gsplat_or_cuda(rng, monkeypatch):
    intr = gopro_small()
    g = random_gaussians(5, rng, intr, None)
    monkeypatch.setitem(sys.modules, "gsplat", None)  # import gsplat -> ImportError
    with pytest.raises(SplatError, match="gsplat is not installed"):
        render_gsplat(g, np.eye(4), intr)
    with pytest.raises(SplatError, match="gsplat is not installed"):
        render_with_backend(g, np.eye(4), intr, backend="gsplat")
    fake = types.ModuleType("gsplat")
    fake.rasterization = lambda **kw: pytest.fail("must not be called without CUDA")
    monkeypatch.setitem(sys.modules, "gsplat", fake)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SplatError, match="CUDA"):
        render_gsplat(g, np.eye(4), intr)


def test_backend_switch_cpu_is_render(rng):
    intr = gopro_small()
    T = random_pose(rng)
    g = random_gaussians(30, rng, intr, T)
    a = render_with_backend(g, T, intr, (0.1, 0.2, 0.3), filter="none")
    b = render(g, T, intr, (0.1, 0.2, 0.3), filter="none")
    assert torch.equal(a.rgb, b.rgb)
    with pytest.raises(SplatError, match="backend"):
        render_with_backend(g, T, intr, backend="vulkan")
