"""The trainer's fused photometric loss (numba, gradient in closed form) against its reference, the torch-autograd
``photometric_loss``, on fresh random inputs: the loss, its L1 / SSIM parts and the prediction's gradient, with and
without a mask, ssim weights 0 / 0.2 / 1, images smaller than the 11x11 window, constant images (zero variance),
values at 0 and 1, a single masked-in pixel; float64 to rounding, float32 within float32 noise."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from umi_aug.errors import SplatError
from umi_aug.splat.losses import photometric_loss, photometric_loss_fused, ssim_target_stats


def _both(pred, target, mask, w, stats):
    out = []
    for fn in (photometric_loss, photometric_loss_fused):
        p = pred.clone().requires_grad_(True)
        loss, parts = fn(p, target, mask, w, target_stats=stats)
        loss.backward()
        out.append((float(loss.detach()), parts, p.grad))
    return out


def _cases(rng, dtype):
    H, W = int(rng.integers(12, 70)), int(rng.integers(12, 70))
    u = lambda *s: torch.as_tensor(rng.uniform(size=s), dtype=dtype)  # noqa: E731
    yield "random", u(H, W, 3), u(H, W, 3), torch.as_tensor(rng.uniform(size=(H, W)) > 0.3)
    yield "no mask", u(H, W, 3), u(H, W, 3), None
    h, w = int(rng.integers(1, 11)), int(rng.integers(1, 11))  # smaller than the window both ways
    yield "tiny", u(h, w, 3), u(h, w, 3), torch.as_tensor(rng.uniform(size=(h, w)) > 0.2) | (torch.arange(h * w)
                                                                                                .view(h, w) == 0)
    yield "constant", torch.full((H, W, 3), 0.5, dtype=dtype), torch.full((H, W, 3), 0.25, dtype=dtype), None
    yield "identical", (t := u(H, W, 3)), t.clone(), None  # x = y: L1's gradient is 0 (torch's sign(0))
    yield "saturated", torch.as_tensor(rng.integers(0, 2, (H, W, 3)), dtype=dtype), u(H, W, 3), None
    one = torch.zeros(H, W, dtype=torch.bool)
    one[int(rng.integers(H)), int(rng.integers(W))] = True
    yield "one pixel", u(H, W, 3), u(H, W, 3), one


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("w", [0.2, 0.0, 1.0])
def test_fused_loss_equals_the_reference(rng, dtype, w):
    for name, pred, target, mask in _cases(rng, dtype):
        stats = ssim_target_stats(target) if rng.uniform() < 0.5 else None
        (l_ref, p_ref, g_ref), (l_fast, p_fast, g_fast) = _both(pred, target, mask, w, stats)
        assert np.isfinite([l_fast, p_fast["l1"], p_fast["ssim"]]).all() and torch.isfinite(g_fast).all(), name
        assert g_fast.shape == pred.shape and g_fast.dtype == dtype, name
        tol = 1e-12 if dtype == torch.float64 else 2e-6
        assert abs(l_fast - l_ref) <= tol, (name, l_fast, l_ref)
        assert abs(p_fast["l1"] - p_ref["l1"]) <= tol and abs(p_fast["ssim"] - p_ref["ssim"]) <= tol, name
        # gradients are O(1 / (3 N)) (N pixels in the mask); near x = y they vanish, so the tolerance has that floor
        n = pred.shape[0] * pred.shape[1] if mask is None else int(mask.sum())
        scale = max(float(g_ref.abs().max()), 1.0 / (3 * n))
        if dtype == torch.float64:
            torch.testing.assert_close(g_fast, g_ref, rtol=0, atol=1e-12 * scale, msg=lambda m: f"{name}: {m}")
        else:  # float32: no further from the float64 gradient than the torch float32 reference is (rounding only)
            s64 = None if stats is None else ssim_target_stats(target.double())
            (_, _, g64), _ = _both(pred.double(), target.double(), mask, w, s64)
            err_fast = float((g_fast.double() - g64).abs().max())
            err_ref = float((g_ref.double() - g64).abs().max())
            assert err_fast <= 2.0 * err_ref + 1e-5 * scale, (name, err_fast, err_ref, scale)
        if mask is not None:
            assert torch.all(g_fast[~mask] == 0), name


def test_fused_loss_refuses_what_it_cannot_compute(rng):
    pred = torch.as_tensor(rng.uniform(size=(10, 12, 3)), dtype=torch.float32)
    target = torch.as_tensor(rng.uniform(size=(10, 12, 3)), dtype=torch.float32)
    with pytest.raises(SplatError, match="mask selects no pixel"):
        photometric_loss_fused(pred, target, torch.zeros(10, 12, dtype=torch.bool))
    with pytest.raises(SplatError, match="must both be"):
        photometric_loss_fused(pred, target[:, :5])
    with pytest.raises(SplatError, match="ssim_weight"):
        photometric_loss_fused(pred, target, None, 1.5)
    with pytest.raises(SplatError, match="one dtype"):
        photometric_loss_fused(pred, target.double())
    with pytest.raises(SplatError, match="the target must be data"):
        photometric_loss_fused(pred, target.clone().requires_grad_(True))
    with pytest.raises(SplatError, match="target_stats"):
        photometric_loss_fused(pred, target, None, 0.2, target_stats=ssim_target_stats(target)[:, :, :-1])
