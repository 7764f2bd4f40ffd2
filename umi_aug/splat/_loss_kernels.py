"""numba kernels of the trainer's fused photometric loss (:func:`umi_aug.splat.losses.photometric_loss_fused`).

One call computes the masked ``(1 - w) L1 + w (1 - SSIM)`` and its gradient with respect to the prediction, in
closed form, instead of torch's graph of depthwise convolutions (forward and backward: ~11 ms per 224² view on 2
cores, 2.8 ms fused; ``benchmarks/splat_loss.py``). Definitions, as :func:`umi_aug.splat.losses.photometric_loss` (the
reference it is tested against):

* ``x = where(mask, pred, target)`` (the composite), ``y = target``, per channel;
* ``mu_x = G * x``, ``e_xx = G * x^2``, ``e_xy = G * (x y)`` with the separable 11-tap Gaussian ``G`` and zero
  padding; ``mu_y``, ``e_yy`` come in as the target's window statistics;
* ``S = A1 A2 / (B1 B2)``, ``A1 = 2 mu_x mu_y + C1``, ``A2 = 2 (e_xy - mu_x mu_y) + C2``,
  ``B1 = mu_x^2 + mu_y^2 + C1``, ``B2 = (e_xx - mu_x^2) + (e_yy - mu_y^2) + C2``;
* ``L1 = sum_mask |x - y| / (3 N)``, ``SSIM = sum_mask S / (3 N)``, ``N`` = pixels in the mask.

Gradient: with ``P_mu = m dS/dmu_x``, ``P_xx = m dS/de_xx = -m S / B2``, ``P_xy = m dS/de_xy = 2 m A1 / (B1 B2)`` and
``dS/dmu_x = 2 mu_y (A2 - A1) / (B1 B2) - 2 mu_x S (1 / B1 - 1 / B2)``, the adjoint of the zero-padded symmetric blur
is the same blur, so ``dSSIM/dx = (G * P_mu + 2 x (G * P_xx) + y (G * P_xy)) / (3 N)``;
``dL1/dx = m sign(x - y) / (3 N)``; the prediction's gradient is the composite's where ``mask`` (zero elsewhere).

Maps are ``[C, H, W]`` (channel-major, so that the blur's inner loop runs along contiguous rows); sums are
accumulated per row in float64. No fastmath: the kernel runs in the inputs' dtype (float32 in training, float64 in
the reference comparisons) and keeps IEEE semantics.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from umi_aug.runtime import quiet_numba_threading_warning
from umi_aug.splat._numba_cache import install as install_kernel_cache

quiet_numba_threading_warning()
install_kernel_cache()  # before the first @njit(cache=True): stamped with every kernel source


@njit(cache=True, parallel=True, fastmath=False)
def blur_maps_kernel(maps, g, tmp, out):  # pragma: no cover - compiled
    """Separable zero-padded blur of ``maps [K, H, W]`` with the odd 1-D kernel ``g [T]`` into ``out [K, H, W]``
    (``tmp``: scratch of the same shape; horizontal pass, then vertical)."""
    K, H, W = maps.shape
    T = g.shape[0]
    r = T // 2
    for kh in prange(K * H):  # horizontal: tap by tap along the row (contiguous, vectorised)
        k = kh // H
        i = kh - k * H
        src = maps[k, i]
        dst = tmp[k, i]
        for j in range(W):
            dst[j] = 0.0
        for t in range(T):
            gt = g[t]
            j0 = max(0, r - t)
            s0 = j0 + t - r
            # unsigned indices: numba then drops its negative-index wrap-around and LLVM vectorises (4.5x)
            for q in range(min(W, W + r - t) - j0):
                dst[np.uintp(j0 + q)] += gt * src[np.uintp(s0 + q)]
    for kh in prange(K * H):  # vertical: row by row of the window
        k = kh // H
        i = kh - k * H
        dst = out[k, i]
        for j in range(W):
            dst[j] = 0.0
        for t in range(max(0, r - i), min(T, H + r - i)):
            gt = g[t]
            srow = tmp[k, i + t - r]
            for j in range(W):
                dst[j] += gt * srow[j]


@njit(cache=True, parallel=True, fastmath=False)
def composite_maps_kernel(pred, target, m, x, maps):  # pragma: no cover - compiled
    """``x = where(m, pred, target)`` and ``maps [9, H, W]`` = ``x``, ``x^2``, ``x target`` (3 channels each)."""
    C, H, W = pred.shape
    for i in prange(H):
        for c in range(C):
            for j in range(W):
                v = pred[c, i, j] if m[i, j] else target[c, i, j]
                x[c, i, j] = v
                maps[c, i, j] = v
                maps[C + c, i, j] = v * v
                maps[2 * C + c, i, j] = v * target[c, i, j]


@njit(cache=True, parallel=True, fastmath=False)
def ssim_partials_kernel(x, y, m, blurred, target_stats, c1, c2, partials, row_l1, row_ssim):  # pragma: no cover
    """Per pixel and channel: the SSIM value's masked sum per row (``row_ssim [H]``), the masked L1's (``row_l1``),
    and ``partials [9, H, W]`` = ``P_mu, P_xx, P_xy`` (3 channels each, see the module docstring).

    ``x, y [3, H, W]`` composite and target, ``m [H, W]`` mask (bool), ``blurred [9, H, W]`` = blurs of ``x``,
    ``x^2``, ``x y``, ``target_stats [6, H, W]`` = ``mu_y``, ``e_yy``."""
    C, H, W = x.shape
    for i in prange(H):
        s_acc = 0.0
        l_acc = 0.0
        for c in range(C):
            for j in range(W):
                if not m[i, j]:
                    partials[c, i, j] = 0.0
                    partials[C + c, i, j] = 0.0
                    partials[2 * C + c, i, j] = 0.0
                    continue
                mu_x = blurred[c, i, j]
                mu_y = target_stats[c, i, j]
                sxx = blurred[C + c, i, j] - mu_x * mu_x
                syy = target_stats[C + c, i, j] - mu_y * mu_y
                sxy = blurred[2 * C + c, i, j] - mu_x * mu_y
                a1 = 2.0 * mu_x * mu_y + c1
                a2 = 2.0 * sxy + c2
                b1 = mu_x * mu_x + mu_y * mu_y + c1
                b2 = sxx + syy + c2
                den = b1 * b2
                s = a1 * a2 / den
                s_acc += s
                l_acc += abs(x[c, i, j] - y[c, i, j])
                partials[c, i, j] = 2.0 * mu_y * (a2 - a1) / den - 2.0 * mu_x * s * (1.0 / b1 - 1.0 / b2)
                partials[C + c, i, j] = -s / b2
                partials[2 * C + c, i, j] = 2.0 * a1 / den
        row_ssim[i] = s_acc
        row_l1[i] = l_acc


@njit(cache=True, parallel=True, fastmath=False)
def loss_grad_kernel(x, y, m, blurred_partials, k_ssim, k_l1, grad):  # pragma: no cover - compiled
    """``grad [3, H, W]`` of ``k_l1 * sum_mask |x - y| + k_ssim * sum_mask S`` with respect to the prediction
    (``blurred_partials [9, H, W]``: the partials blurred; zero outside the mask, where ``x`` is the target)."""
    C, H, W = x.shape
    for i in prange(H):
        for c in range(C):
            for j in range(W):
                if not m[i, j]:
                    grad[c, i, j] = 0.0
                    continue
                d = x[c, i, j] - y[c, i, j]
                sgn = 1.0 if d > 0 else (-1.0 if d < 0 else 0.0)
                dssim = (blurred_partials[c, i, j] + 2.0 * x[c, i, j] * blurred_partials[C + c, i, j]
                         + y[c, i, j] * blurred_partials[2 * C + c, i, j])
                grad[c, i, j] = k_ssim * dssim + k_l1 * sgn


def fused_loss_and_grad(pred: np.ndarray, target: np.ndarray, mask: np.ndarray, target_stats: np.ndarray,
                        window: np.ndarray, ssim_weight: float, c1: float, c2: float
                        ) -> tuple[float, float, float, np.ndarray]:
    """``(loss, l1, ssim, grad)`` of the masked photometric loss (module docstring).

    Args:
        pred, target: np.ndarray,  # [3, H, W] float32 or float64, C-contiguous, the same dtype
        mask: np.ndarray,  # [H, W] bool, at least one True (checked by the caller)
        target_stats: np.ndarray,  # [6, H, W] blurred target and target^2, the dtype of pred
        window: np.ndarray,  # [T] 1-D Gaussian, odd T, the dtype of pred
        ssim_weight: ``w``; ``c1``, ``c2``: SSIM stabilisers.
    Returns:
        loss, l1, ssim (floats) and ``grad`` [3, H, W] (d loss / d pred, the dtype of pred).
    """
    C, H, W = pred.shape
    dt = pred.dtype
    y = target
    n = float(np.count_nonzero(mask))
    x = np.empty_like(pred)
    maps = np.empty((3 * C, H, W), dt)
    composite_maps_kernel(pred, target, mask, x, maps)
    tmp = np.empty_like(maps)
    blurred = np.empty_like(maps)
    blur_maps_kernel(maps, window, tmp, blurred)
    partials = maps  # reused: the products are no longer needed
    row_l1 = np.empty(H, np.float64)
    row_ssim = np.empty(H, np.float64)
    ssim_partials_kernel(x, y, mask, blurred, target_stats, dt.type(c1), dt.type(c2), partials, row_l1, row_ssim)
    l1 = float(row_l1.sum()) / (3.0 * n)
    ssim = float(row_ssim.sum()) / (3.0 * n)
    w = float(ssim_weight)
    loss = (1.0 - w) * l1 + w * (1.0 - ssim)
    grad = np.empty((C, H, W), dt)
    if w > 0:
        blur_maps_kernel(partials, window, tmp, blurred)
    else:
        blurred[:] = 0.0
    loss_grad_kernel(x, y, mask, blurred, dt.type(-w / (3.0 * n)), dt.type((1.0 - w) / (3.0 * n)), grad)
    return loss, l1, ssim, grad
