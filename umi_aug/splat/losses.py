"""Photometric losses and metrics of the splat trainer (INRIA 3DGS: ``(1 - lambda) L1 + lambda (1 - SSIM)``).

Masking: a pixel with ``mask = False`` (gripper, mirrors, outside the fisheye image circle) must not influence
the loss. The prediction is composited with the target there (``where(mask, pred, target)``) *before* the SSIM
windows are taken, so masked pixels get exactly zero gradient and windows straddling the mask edge compare only
true pixels against the target; L1 and the SSIM map are then averaged over the masked-in pixels only.

SSIM: 11x11 Gaussian window (sigma 1.5), ``C1 = 0.01^2``, ``C2 = 0.03^2`` (data range 1), zero padding at the
image border (INRIA ``utils/loss_utils.py``), separable convolution.
:func:`umi_aug.splat._torch_impl._ssim_map_reference` is the direct float64 formula (explicit windows) the fast
version is tested against. A trainer that sees the same target many times passes its window statistics
(:func:`ssim_target_stats`, computed once per view), so that each step blurs only the three maps that depend on the
prediction (9 of 15 channels, forward and backward).

:func:`photometric_loss_fused` is the trainer's fast twin of :func:`photometric_loss` (its reference): the same loss
with its gradient in closed form from numba kernels (:mod:`umi_aug.splat._loss_kernels`), for a target that is data.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from umi_aug.errors import SplatError

__all__ = [
    "SSIM_WINDOW", "SSIM_SIGMA", "gaussian_window_1d", "ssim_map", "ssim_target_stats", "masked_ssim",
    "masked_l1", "masked_psnr", "photometric_loss", "photometric_loss_fused",
]

Tensor = torch.Tensor

#: SSIM window edge (pixels) and Gaussian standard deviation (pixels).
SSIM_WINDOW: int = 11
SSIM_SIGMA: float = 1.5
#: SSIM stabilisers for data range 1.
SSIM_C1: float = 0.01**2
SSIM_C2: float = 0.03**2


def gaussian_window_1d(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA, dtype=torch.float32) -> Tensor:
    """Normalised 1D Gaussian ``[size]`` (the 2D window is its outer product)."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    w = torch.exp(-(x * x) / (2.0 * sigma * sigma))
    return (w / w.sum()).to(dtype)


def _check_pair(pred: Tensor, target: Tensor, mask: Tensor | None) -> None:
    if pred.ndim != 3 or pred.shape[-1] != 3 or pred.shape != target.shape:
        raise SplatError(f"loss: pred and target must both be [H, W, 3], got {list(pred.shape)} and "
                         f"{list(target.shape)}")
    if mask is not None and tuple(mask.shape) != tuple(pred.shape[:2]):
        raise SplatError(f"loss: mask must be [H, W] = {list(pred.shape[:2])}, got {list(mask.shape)}")


def _blur(x: Tensor, w: Tensor) -> Tensor:
    """Separable zero-padded Gaussian blur of ``x [1, C, H, W]`` (depthwise convolutions: one group per map, much
    faster on the CPU than a batch of single-channel maps)."""
    k, c = w.shape[0], x.shape[1]
    x = F.conv2d(x, w.view(1, 1, 1, k).expand(c, 1, 1, k), padding=(0, k // 2), groups=c)
    return F.conv2d(x, w.view(1, 1, k, 1).expand(c, 1, k, 1), padding=(k // 2, 0), groups=c)


def ssim_target_stats(target: Tensor) -> Tensor:
    """Window statistics of a target image ``[H, W, 3]``: ``[1, 6, H, W]`` = the blurred ``y`` and ``y^2`` (3
    channels each), what :func:`ssim_map` takes as ``target_stats``. Not differentiable (the target is data)."""
    if target.ndim != 3 or target.shape[-1] != 3:
        raise SplatError(f"ssim_target_stats: target must be [H, W, 3], got {list(target.shape)}")
    with torch.no_grad():
        return _target_stats(target)


def _target_stats(target: Tensor) -> Tensor:
    y = target.permute(2, 0, 1)[None]
    return _blur(torch.cat([y, y * y], dim=1), gaussian_window_1d(dtype=target.dtype))


def _check_target_stats(target_stats: Tensor, target: Tensor) -> None:
    H, W = target.shape[:2]
    if tuple(target_stats.shape) != (1, 6, H, W) or target_stats.dtype != target.dtype:
        raise SplatError(f"target_stats must be ssim_target_stats(target): [1, 6, {H}, {W}] {target.dtype}, got "
                         f"{list(target_stats.shape)} {target_stats.dtype}")


def ssim_map(pred: Tensor, target: Tensor, target_stats: Tensor | None = None) -> Tensor:
    """Per-pixel SSIM ``[H, W, 3]`` of two ``[H, W, 3]`` images in [0, 1] (differentiable, separable conv).

    ``target_stats``: :func:`ssim_target_stats` of ``target`` when already known (the same values; saves blurring
    the target's maps again)."""
    _check_pair(pred, target, None)
    w = gaussian_window_1d(dtype=pred.dtype)
    x = pred.permute(2, 0, 1)[None]  # [1, 3, H, W]
    y = target.permute(2, 0, 1)[None]
    if target_stats is None:
        target_stats = _target_stats(target)  # differentiable, for a target that requires grad
    else:
        _check_target_stats(target_stats, target)
    mu_x, e_xx, e_xy = _blur(torch.cat([x, x * x, x * y], dim=1), w).split(3, dim=1)  # [1, 3, H, W] each
    mu_y, e_yy = target_stats.split(3, dim=1)
    sxx = e_xx - mu_x * mu_x
    syy = e_yy - mu_y * mu_y
    sxy = e_xy - mu_x * mu_y
    num = (2.0 * mu_x * mu_y + SSIM_C1) * (2.0 * sxy + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sxx + syy + SSIM_C2)
    return (num / den)[0].permute(1, 2, 0)


def _composite(pred: Tensor, target: Tensor, mask: Tensor | None) -> Tensor:
    return pred if mask is None else torch.where(mask[..., None], pred, target)


def _masked_mean(x: Tensor, mask: Tensor | None) -> Tensor:
    """Mean of ``x [H, W, 3]`` over the pixels with ``mask`` (all pixels when None)."""
    if mask is None:
        return x.mean()
    n = mask.sum()
    if int(n) == 0:
        raise SplatError("loss: the mask selects no pixel")
    return (x * mask[..., None].to(x.dtype)).sum() / (3.0 * n.to(x.dtype))


def masked_ssim(pred: Tensor, target: Tensor, mask: Tensor | None = None,
                target_stats: Tensor | None = None) -> Tensor:
    """Mean SSIM over the masked-in pixels (``mask [H, W]`` bool; prediction composited with the target outside;
    ``target_stats`` as in :func:`ssim_map`)."""
    _check_pair(pred, target, mask)
    return _masked_mean(ssim_map(_composite(pred, target, mask), target, target_stats), mask)


def masked_l1(pred: Tensor, target: Tensor, mask: Tensor | None = None) -> Tensor:
    """Mean absolute error over the masked-in pixels and the 3 channels."""
    _check_pair(pred, target, mask)
    return _masked_mean((_composite(pred, target, mask) - target).abs(), mask)


def masked_psnr(pred: Tensor | np.ndarray, target: Tensor | np.ndarray,
                mask: Tensor | np.ndarray | None = None) -> float:
    """PSNR in dB (data range 1) over the masked-in pixels; ``pred`` is clamped to [0, 1] first."""
    p = torch.as_tensor(pred).double().clamp(0.0, 1.0)
    t = torch.as_tensor(target).double()
    m = None if mask is None else torch.as_tensor(mask, dtype=torch.bool)
    _check_pair(p, t, m)
    mse = float(_masked_mean((p - t) ** 2, m))
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def photometric_loss(pred: Tensor, target: Tensor, mask: Tensor | None = None,
                     ssim_weight: float = 0.2, target_stats: Tensor | None = None) -> tuple[Tensor, dict[str, float]]:
    """``(1 - w) L1 + w (1 - SSIM)`` on the masked-in pixels (INRIA 3DGS with ``w = 0.2``).

    Args:
        pred: Tensor,  # [H, W, 3] rendered RGB
        target: Tensor,  # [H, W, 3] ground truth in [0, 1]
        mask: Tensor | None,  # [H, W] bool, True = pixel used
        ssim_weight: ``w`` in [0, 1].
        target_stats: Tensor | None,  # [1, 6, H, W] ssim_target_stats(target), when the caller keeps it per view
    Returns:
        The scalar loss and ``{"l1": ..., "ssim": ...}`` (floats, for logging).
    """
    if not 0.0 <= ssim_weight <= 1.0:
        raise SplatError(f"ssim_weight must be in [0, 1], got {ssim_weight!r}")
    _check_pair(pred, target, mask)
    comp = _composite(pred, target, mask)
    l1 = _masked_mean((comp - target).abs(), mask)
    if ssim_weight > 0:
        ssim = _masked_mean(ssim_map(comp, target, target_stats), mask)
        loss = (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - ssim)
    else:
        ssim = torch.zeros((), dtype=pred.dtype)
        loss = l1
    return loss, {"l1": float(l1.detach()), "ssim": float(ssim.detach())}


class _FusedPhotometricLoss(torch.autograd.Function):
    """The loss of :func:`photometric_loss_fused`; its gradient (computed in the forward) is saved for backward."""

    @staticmethod
    def forward(ctx, pred: Tensor, target_chw: np.ndarray, mask: np.ndarray, target_stats: np.ndarray,
                window: np.ndarray, ssim_weight: float, parts: dict) -> Tensor:
        from umi_aug.splat._loss_kernels import fused_loss_and_grad  # lazy, start-up: numba

        pred_chw = np.ascontiguousarray(pred.detach().numpy().transpose(2, 0, 1))
        loss, l1, ssim, grad = fused_loss_and_grad(pred_chw, target_chw, mask, target_stats, window, ssim_weight,
                                                   SSIM_C1, SSIM_C2)
        parts["l1"], parts["ssim"] = l1, (ssim if ssim_weight > 0 else 0.0)
        ctx.save_for_backward(torch.from_numpy(grad).permute(1, 2, 0))
        return torch.tensor(loss, dtype=pred.dtype)

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        (grad,) = ctx.saved_tensors
        return grad * grad_out, None, None, None, None, None, None


def photometric_loss_fused(pred: Tensor, target: Tensor, mask: Tensor | None = None, ssim_weight: float = 0.2,
                           target_stats: Tensor | None = None) -> tuple[Tensor, dict[str, float]]:
    """:func:`photometric_loss` with the same arguments and values, differentiable with respect to ``pred`` only
    (the target is data), computed with its gradient in one pass of numba kernels: on 2 cores about a fifth of
    the reference's time at 224² (3.7 against 20 ms, ``benchmarks/splat_loss.py``). CPU tensors, float32 or float64."""
    if not 0.0 <= ssim_weight <= 1.0:
        raise SplatError(f"ssim_weight must be in [0, 1], got {ssim_weight!r}")
    _check_pair(pred, target, mask)
    if pred.dtype not in (torch.float32, torch.float64) or target.dtype != pred.dtype or pred.device.type != "cpu":
        raise SplatError(f"photometric_loss_fused: pred and target must be CPU float32/float64 of one dtype, got "
                         f"{pred.dtype} on {pred.device} and {target.dtype}")
    if target.requires_grad:
        raise SplatError("photometric_loss_fused: the target must be data (use photometric_loss for a target that "
                         "requires grad)")
    H, W = pred.shape[:2]
    m = np.ones((H, W), dtype=bool) if mask is None else np.ascontiguousarray(mask.detach().numpy(), dtype=bool)
    if not m.any():
        raise SplatError("loss: the mask selects no pixel")
    if target_stats is None:  # (without SSIM its value is not used: no need to blur the target)
        target_stats = ssim_target_stats(target) if ssim_weight > 0 else torch.zeros((1, 6, H, W), dtype=pred.dtype)
    else:
        _check_target_stats(target_stats, target)
    tgt = np.ascontiguousarray(target.detach().numpy().transpose(2, 0, 1))
    stats = np.ascontiguousarray(target_stats.detach().numpy()[0])
    window = gaussian_window_1d(dtype=pred.dtype).numpy()
    parts: dict[str, float] = {}
    loss = _FusedPhotometricLoss.apply(pred, tgt, m, stats, window, float(ssim_weight), parts)
    return loss, parts
