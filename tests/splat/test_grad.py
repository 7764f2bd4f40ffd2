"""Gradients of the fast path (torch-autograd projection + hand-written numba rasteriser backward) against the
dense float64 reference's autograd and against central finite differences, for every parameter."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import numba  # noqa: E402,F401  (the splat extra; a missing install must fail, not skip)

from umi_aug.splat import RasterizeGaussians, render  # noqa: E402
from umi_aug.splat._torch_impl import _render_reference  # noqa: E402
from umi_aug.splat.scenes import random_gaussians  # noqa: E402
from tests.splat._helpers import PARAMS, gopro_small, loss_weights, random_kb_intrinsics, random_pose, weighted_loss  # noqa: E402

FILTERS = ["inria", "mip", "none"]


def _setup(rng, intr, n, dtype=torch.float64, **kw):
    T = random_pose(rng)
    g = random_gaussians(n, rng, intr, T, theta_max=kw.pop("theta_max", 1.95), dtype=dtype, **kw)
    return g.requires_grad_(True), T


@pytest.mark.parametrize("filt", FILTERS)
def test_grads_match_reference_autograd(rng, filt):
    intr = random_kb_intrinsics(rng, 48, 40) if filt != "inria" else gopro_small(48, 40)
    g, T = _setup(rng, intr, 40)
    pose = torch.as_tensor(T).requires_grad_(True)
    bg = torch.as_tensor(rng.uniform(size=3)).requires_grad_(True)
    w = loss_weights(rng, intr.height, intr.width)
    inputs = [*g, pose, bg]
    out = render(g, pose, intr, bg, filter=filt)
    assert "projected" in out.meta  # autograd path
    fast = torch.autograd.grad(weighted_loss(out, w), inputs)
    ref = torch.autograd.grad(weighted_loss(_render_reference(g, pose, intr, bg, filter=filt), w), inputs)
    for name, a, b in zip([*PARAMS, "pose", "background"], fast, ref):
        scale = b.abs().max().item()
        assert scale > 0, name
        assert (a - b).abs().max().item() <= 1e-9 * (1 + scale), name


def test_grads_match_finite_differences(rng):
    intr = random_kb_intrinsics(rng, 32, 24)
    g, T = _setup(rng, intr, 6, sigma_px_range=(1.0, 4.0))
    w = loss_weights(rng, intr.height, intr.width)
    bg = rng.uniform(size=3)
    for filt in ("mip", "none"):
        analytic = torch.autograd.grad(weighted_loss(render(g, T, intr, bg, filter=filt), w), list(g))
        h = 1e-7
        with torch.no_grad():
            for name, t, ga in zip(PARAMS, g, analytic):
                flat = t.view(-1)
                fd = torch.empty_like(flat)
                for i in range(flat.numel()):
                    old = flat[i].item()
                    flat[i] = old + h
                    lp = weighted_loss(render(g, T, intr, bg, filter=filt), w).item()
                    flat[i] = old - h
                    lm = weighted_loss(render(g, T, intr, bg, filter=filt), w).item()
                    flat[i] = old
                    fd[i] = (lp - lm) / (2 * h)
                err = (fd - ga.view(-1)).abs()
                tol = 2e-5 * (1.0 + ga.abs().max().item())
                assert err.max().item() <= tol, (filt, name, int(err.argmax()), err.max().item())


def test_float32_grads_close_to_float64_reference(rng):
    intr = gopro_small(48, 40)
    g64, T = _setup(rng, intr, 40, sigma_px_range=(1.0, 5.0))
    g32 = g64.detach().to(torch.float32).requires_grad_(True)
    w = loss_weights(rng, intr.height, intr.width)
    fast = torch.autograd.grad(weighted_loss(render(g32, T, intr), [x.float() for x in w]), list(g32))
    ref = torch.autograd.grad(weighted_loss(_render_reference(g64, T, intr), w), list(g64))
    for name, a, b in zip(PARAMS, fast, ref):
        assert a.dtype == torch.float32
        rel = (a.double() - b).norm() / b.norm()
        assert rel.item() < 1e-3, (name, rel.item())


def test_rasterizer_function_gradcheck(rng):
    """torch.autograd.gradcheck of the numba forward/backward on screen-space inputs (float64)."""
    V, W, H = 8, 20, 16
    means2d = torch.as_tensor(rng.uniform([2, 2], [W - 3, H - 3], (V, 2))).requires_grad_(True)
    L = rng.normal(size=(V, 2, 2)) + 2.5 * np.eye(2)
    cov = L @ L.transpose(0, 2, 1)
    conic = np.linalg.inv(cov)
    conics = torch.as_tensor(np.stack([conic[:, 0, 0], conic[:, 0, 1], conic[:, 1, 1]], 1)).requires_grad_(True)
    opac = torch.as_tensor(rng.uniform(0.2, 0.95, V)).requires_grad_(True)
    colors = torch.as_tensor(rng.uniform(size=(V, 3))).requires_grad_(True)
    depths = torch.as_tensor(rng.uniform(1, 3, V)).requires_grad_(True)

    def fn(m, c, o, col, d):
        return RasterizeGaussians.apply(m, c, o, col, d, W, H, None)

    assert torch.autograd.gradcheck(fn, (means2d, conics, opac, colors, depths), eps=1e-7, atol=1e-6, rtol=1e-4)


def test_means2d_gradient_available_for_densification(rng):
    intr = gopro_small(32, 24)
    g, T = _setup(rng, intr, 20)
    out = render(g, T, intr)
    m2d = out.meta["means2d"]
    m2d.retain_grad()
    out.rgb.sum().backward()
    assert m2d.grad is not None and m2d.grad.shape == (out.meta["n_visible"], 2)
    assert torch.isfinite(m2d.grad).all() and m2d.grad.abs().sum() > 0
    assert g.means.grad is not None and torch.isfinite(g.means.grad).all()


def test_no_grad_uses_numba_projection(rng):
    intr = gopro_small(32, 24)
    g, T = _setup(rng, intr, 10)
    with torch.no_grad():
        out = render(g, T, intr)
    assert "projected" not in out.meta and not out.rgb.requires_grad
