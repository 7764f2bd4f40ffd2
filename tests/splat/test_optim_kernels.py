"""The trainer's per-step update in numba (``splat/_optim_kernels.py``) against its torch references, on fresh random
inputs: ``GaussianAdam.step`` against ``GaussianAdam._step_torch`` and ``inject_noise`` against
``_inject_noise_torch``, in float64 (to rounding) and float32 (as close to the float64 result as torch's own float32
path), with the active SH prefix, strided gradients, zero and tiny gradients, quaternions of zero and huge norm,
saturated opacities and large scales; the random stream drawn is the reference's."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from umi_aug.splat.densify import _inject_noise_torch, inject_noise
from umi_aug.splat.optim import GaussianAdam

SHAPES = {"means": (3,), "log_scales": (3,), "quats_wxyz": (4,), "logit_opacities": (), "sh0": (1, 3),
          "sh_rest": (15, 3)}


def _params(rng, n: int, dtype) -> dict[str, torch.Tensor]:
    p = {k: torch.as_tensor(rng.normal(size=(n, *s)), dtype=dtype) for k, s in SHAPES.items()}
    p["log_scales"] = p["log_scales"] * 2.0 - 4.0
    q = p["quats_wxyz"]
    q[0] = 0.0  # zero norm: used as it is
    q[1] = torch.tensor([1e-31, 0.0, 0.0, 0.0], dtype=dtype) if dtype == torch.float64 else 0.0
    q[2] *= 1e12  # huge norm
    q[3] = torch.tensor([1e-7, -1.0, 0.0, 0.0], dtype=dtype)  # a rotation by nearly pi about x
    p["logit_opacities"][:4] = torch.tensor([-60.0, 60.0, -8.0, 0.0], dtype=dtype)  # saturated both ways
    p["log_scales"][4] = torch.tensor([5.0, -20.0, 0.0], dtype=dtype)
    return {k: v.requires_grad_(True) for k, v in p.items()}


def _grads(rng, params, k_active: int, strided: bool) -> dict[str, torch.Tensor]:
    out = {}
    for name, p in params.items():
        g = torch.as_tensor(rng.normal(size=p.shape), dtype=p.dtype) * 10.0 ** rng.uniform(-3, 1)
        g[0] = 0.0  # a Gaussian without gradient
        g[1] = 1e-30  # denormal-range squares in float32
        if name == "sh_rest":
            g[:, k_active:] = 0.0  # above the rendered degree (the renderer's zeros)
        if strided and p.ndim == 2:
            g = torch.cat([g, g], dim=1)[:, ::2]  # a non-contiguous gradient (the kernel copies it)
            assert not g.is_contiguous()
        out[name] = g
    return out


def _run_adam(params, grads_per_step, actives, lrs, use_kernel: bool):
    opt = GaussianAdam(params)
    for grads, act in zip(grads_per_step, actives):
        for name, p in params.items():
            p.grad = grads[name].clone()
        (opt.step if use_kernel else opt._step_torch)(lrs, active=None if act is None else {"sh_rest": act})
        opt.zero_grad()
    return opt


@pytest.mark.parametrize("strided", [False, True])
def test_adam_kernel_matches_the_torch_reference(rng, strided):
    n = int(rng.integers(5, 300))
    lrs = {k: float(10.0 ** rng.uniform(-5, -1)) for k in SHAPES}
    actives = [0, 0, 3, None, 8, 15]
    steps = [None] * len(actives)
    for dtype, rtol in ((torch.float64, 1e-12), (torch.float32, None)):
        base = _params(rng, n, dtype)
        grads = [_grads(rng, base, 15 if a is None else a, strided) for a in steps]
        fast = {k: v.detach().clone().requires_grad_(True) for k, v in base.items()}
        ref = {k: v.detach().clone().requires_grad_(True) for k, v in base.items()}
        o_fast = _run_adam(fast, grads, actives, lrs, True)
        o_ref = _run_adam(ref, grads, actives, lrs, False)
        if dtype == torch.float64:
            for k in SHAPES:
                torch.testing.assert_close(fast[k], ref[k], rtol=rtol, atol=1e-14)
                torch.testing.assert_close(o_fast.exp_avg_sq[k], o_ref.exp_avg_sq[k], rtol=rtol, atol=0.0)
            continue
        # float32: within a few float32 roundings per step of the float64 run, as torch's float32 run is, and no
        # further from it overall than that run
        hi = {k: v.detach().double().requires_grad_(True) for k, v in base.items()}
        _run_adam(hi, [{k: g.double() for k, g in gs.items()} for gs in grads], actives, lrs, False)
        for k in SHAPES:
            f, r, h = fast[k].detach().double(), ref[k].detach().double(), hi[k].detach()
            assert torch.isfinite(f).all(), k
            tol = len(actives) * 2 * torch.finfo(torch.float32).eps * (h.abs() + base[k].detach().double().abs()
                                                                       + lrs[k])
            assert ((f - h).abs() <= tol).all() and ((r - h).abs() <= tol).all(), k
            assert float((f - h).abs().max()) <= 2.0 * float((r - h).abs().max()) + 1e-12, k


def test_adam_skips_what_the_reference_skips(rng):
    """A parameter without gradient and the SH coefficients above the active prefix stay as they are."""
    params = _params(rng, 20, torch.float32)
    before = {k: v.detach().clone() for k, v in params.items()}
    opt = GaussianAdam(params)
    for name in ("means", "sh_rest"):
        params[name].grad = torch.ones_like(params[name])
    opt.step({k: 1e-2 for k in SHAPES}, active={"sh_rest": 3})
    assert not torch.equal(params["means"], before["means"])
    assert torch.equal(params["sh_rest"][:, 3:], before["sh_rest"][:, 3:])
    assert not torch.equal(params["sh_rest"][:, :3], before["sh_rest"][:, :3])
    for name in ("log_scales", "quats_wxyz", "logit_opacities", "sh0"):
        assert torch.equal(params[name], before[name]) and not opt.exp_avg[name].any()


def test_adam_non_contiguous_parameter_falls_back_to_torch(rng):
    p = torch.as_tensor(rng.normal(size=(6, 8)), dtype=torch.float32)[:, ::2].requires_grad_(True)
    q = p.detach().clone().requires_grad_(True)
    a, b = GaussianAdam({"x": p}), GaussianAdam({"x": q})
    g = torch.as_tensor(rng.normal(size=(6, 4)), dtype=torch.float32)
    p.grad, q.grad = g.clone(), g.clone()
    a.step({"x": 1e-2})
    b._step_torch({"x": 1e-2})
    assert torch.equal(p, q)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_noise_kernel_matches_the_torch_reference(rng, dtype):
    for n in (1, 7, int(rng.integers(50, 400))):
        base = _params(rng, max(n, 5), dtype)
        base = {k: v.detach()[:n].clone() for k, v in base.items()}
        scale = float(10.0 ** rng.uniform(-2, 3))
        fast = {k: v.clone() for k, v in base.items()}
        ref = {k: v.clone() for k, v in base.items()}
        seed = int(rng.integers(1 << 30))
        g1, g2 = torch.Generator().manual_seed(seed), torch.Generator().manual_seed(seed)
        inject_noise(fast, scale, g1)
        _inject_noise_torch(ref, scale, g2)
        assert torch.equal(g1.get_state(), g2.get_state())  # the same numbers drawn
        assert torch.isfinite(fast["means"]).all()
        moved = (ref["means"] - base["means"]).abs()
        if dtype == torch.float64:
            atol = 1e-12 * float(moved.max()) + 1e-300
            torch.testing.assert_close(fast["means"], ref["means"], rtol=1e-12, atol=atol)
        else:  # each computed once in float64 here, in float32 steps there: within a few float32 roundings
            tol = 8 * torch.finfo(torch.float32).eps * (base["means"].abs() + moved) + 1e-30
            assert ((fast["means"] - ref["means"]).abs() <= tol).all()
        for k in SHAPES:
            if k != "means":
                assert torch.equal(fast[k], base[k])


def test_noise_kernel_moves_by_the_covariance(rng):
    """A mutant check of the reference comparison: one Gaussian, identity rotation, opacity ~0: the move is
    ``diag(s^2) eps * scale`` exactly as the formula says (it fails if R or s^2 were left out)."""
    p = {"means": torch.zeros(1, 3, dtype=torch.float64), "logit_opacities": torch.tensor([-50.0], dtype=torch.float64),
         "quats_wxyz": torch.tensor([[2.0, 0.0, 0.0, 0.0]], dtype=torch.float64),
         "log_scales": torch.tensor([[0.0, np.log(2.0), np.log(3.0)]], dtype=torch.float64)}
    gen = torch.Generator().manual_seed(5)
    eps = torch.randn((1, 3), generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    inject_noise(p, 0.5, gen)
    gate = 1.0 / (1.0 + np.exp(-100.0 * (1.0 - 1.0 / (1.0 + np.exp(50.0)) - 0.995)))
    expect = eps[0].numpy() * np.array([1.0, 4.0, 9.0]) * 0.5 * gate
    np.testing.assert_allclose(p["means"][0].numpy(), expect, rtol=1e-12)
