"""Image pre-processing of the observation encoder, in pure torch (torchvision does not import here).

* :func:`random_crop_resize`: a random ``round(S·ratio)`` square crop per sample, resized back to S with
  antialiased bilinear interpolation (UMI: ``RandomCrop(int(224·0.95))`` + ``Resize(224, antialias=True)``).
* :func:`center_crop_resize`: the centred crop of the same side, resized back — what evaluation sees (UMI's
  ``eval_transform``: ``CenterCrop`` + ``Resize``), so an object has the same apparent size as in training.
* :func:`color_jitter`: torchvision ``ColorJitter(brightness, contrast, saturation, hue)`` semantics — factors
  drawn uniformly from ``[1-b, 1+b]``, ``[1-c, 1+c]``, ``[1-s, 1+s]``, hue shift from ``[-h, h]`` — applied in a
  random order; factors are drawn per sample (UMI's call on a (B·T) batch draws one set for the whole batch).
* :func:`random_gaussian_blur`: a Gaussian blur of standard deviation drawn uniformly from ``[0, sigma_max]``
  pixels per sample (separable, reflect padding); :func:`_random_gaussian_blur_reference` is the slow, per-image
  2-D reference beside it. Not UMI's: a lever against the look of 3DGS renders, which are softer than camera
  frames (issue #29).
* :func:`normalize_image`: CLIP / ImageNet mean-std.

The encoder applies the random crop, jitter and blur in training mode and the centre crop in evaluation mode; the T
frames of one sample share the same crop, jitter and blur.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from umi_aug.errors import PolicyError

__all__ = ["CLIP_MEAN", "CLIP_STD", "IMAGENET_MEAN", "IMAGENET_STD", "random_crop_resize", "center_crop_resize",
           "crop_side", "color_jitter", "random_gaussian_blur", "blur_sigmas",
           "normalize_image", "rgb_to_hsv", "hsv_to_rgb"]

#: OpenAI CLIP pre-processing constants (``CLIPImageProcessor`` image_mean / image_std).
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def normalize_image(img: torch.Tensor, mean: tuple[float, ...], std: tuple[float, ...]) -> torch.Tensor:
    """``(img - mean) / std`` per channel; img: [..., 3, H, W] in [0, 1]."""
    m = torch.tensor(mean, dtype=img.dtype, device=img.device)[:, None, None]
    s = torch.tensor(std, dtype=img.dtype, device=img.device)[:, None, None]
    return (img - m) / s


def crop_side(size: int, ratio: float) -> int:
    """Side in pixels of the training crop of a ``size``-pixel image (UMI: ``int(size · ratio)``, at least 1)."""
    return max(1, int(size * ratio))


def _resize_back(crops: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """[B, T, C, h, w] crops → [B, T, C, H, W] (antialiased bilinear, as UMI's ``Resize(antialias=True)``)."""
    B, T, C, h, w = crops.shape
    out = F.interpolate(crops.reshape(B * T, C, h, w), size=(H, W), mode="bilinear", align_corners=False,
                        antialias=True)
    return out.reshape(B, T, C, H, W)


def random_crop_resize(img: torch.Tensor, ratio: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """Random square crop of side :func:`crop_side` per sample (same for its T frames), resized back.

    Args:
        img: Tensor,  # [B, T, 3, H, W] in [0, 1]
    Returns:
        Tensor,  # [B, T, 3, H, W]
    """
    B, T, C, H, W = img.shape
    ch, cw = crop_side(H, ratio), crop_side(W, ratio)
    if ch == H and cw == W:
        return img
    oy = torch.randint(0, H - ch + 1, (B,), generator=generator, device="cpu")
    ox = torch.randint(0, W - cw + 1, (B,), generator=generator, device="cpu")
    crops = torch.stack([img[b, :, :, int(oy[b]): int(oy[b]) + ch, int(ox[b]): int(ox[b]) + cw] for b in range(B)])
    return _resize_back(crops, H, W)


def center_crop_resize(img: torch.Tensor, ratio: float) -> torch.Tensor:
    """The centred crop of side :func:`crop_side` (offset ``(S − side) // 2``, one of the crops
    :func:`random_crop_resize` draws), resized back: the evaluation-time twin of the training crop.

    Args:
        img: Tensor,  # [B, T, 3, H, W] in [0, 1]
    Returns:
        Tensor,  # [B, T, 3, H, W]
    """
    H, W = img.shape[-2:]
    ch, cw = crop_side(H, ratio), crop_side(W, ratio)
    if ch == H and cw == W:
        return img
    oy, ox = (H - ch) // 2, (W - cw) // 2
    return _resize_back(img[..., oy: oy + ch, ox: ox + cw], H, W)


def _gray(img: torch.Tensor) -> torch.Tensor:  # [..., 3, H, W] → [..., 1, H, W] (ITU-R 601-2 luma)
    return (0.299 * img[..., 0:1, :, :] + 0.587 * img[..., 1:2, :, :] + 0.114 * img[..., 2:3, :, :])


def rgb_to_hsv(img: torch.Tensor) -> torch.Tensor:
    """[..., 3, H, W] RGB in [0, 1] → HSV with hue in [0, 1)."""
    r, g, b = img.unbind(-3)
    maxc, _ = img.max(dim=-3)
    minc, _ = img.min(dim=-3)
    eqc = maxc == minc
    cr = maxc - minc
    ones = torch.ones_like(maxc)
    s = cr / torch.where(eqc, ones, maxc)
    cr_div = torch.where(eqc, ones, cr)
    rc, gc, bc = (maxc - r) / cr_div, (maxc - g) / cr_div, (maxc - b) / cr_div
    hr = (maxc == r) * (bc - gc)
    hg = ((maxc == g) & (maxc != r)) * (2.0 + rc - bc)
    hb = ((maxc != g) & (maxc != r)) * (4.0 + gc - rc)
    h = torch.fmod((hr + hg + hb) / 6.0 + 1.0, 1.0)
    return torch.stack([h, s, maxc], dim=-3)


def hsv_to_rgb(img: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rgb_to_hsv` (h in turns, s and v in [0, 1]): channel ``c = v − v·s·clamp(min(k, 4 − k),
    0, 1)`` with ``k = (n + 6h) mod 6``, n = 5, 3, 1 for R, G, B — the sector-free form of the same piecewise-linear
    map, a few elementwise passes where :func:`_hsv_to_rgb_reference` builds 18 candidate planes (issue #29: the
    colour jitter was a third of a CPU training step)."""
    h, s, v = img.unbind(-3)
    h6 = h * 6.0
    vs = v * s
    out = []
    for n in (5.0, 3.0, 1.0):
        k = torch.remainder(h6 + n, 6.0)
        out.append(v - vs * torch.minimum(k, 4.0 - k).clamp(0.0, 1.0))
    return torch.stack(out, dim=-3)


def _hsv_to_rgb_reference(img: torch.Tensor) -> torch.Tensor:
    """Reference of :func:`hsv_to_rgb`, sector by sector as torchvision's ``_hsv2rgb`` writes it."""
    h, s, v = img.unbind(-3)
    i = torch.floor(h * 6.0)
    f = h * 6.0 - i
    i = i.to(torch.int64) % 6
    p = (v * (1.0 - s)).clamp(0.0, 1.0)
    q = (v * (1.0 - s * f)).clamp(0.0, 1.0)
    t = (v * (1.0 - s * (1.0 - f))).clamp(0.0, 1.0)
    mask = i.unsqueeze(-3) == torch.arange(6, device=i.device).view(-1, 1, 1)
    a1 = torch.stack((v, q, p, p, t, v), dim=-3)
    a2 = torch.stack((t, v, v, q, p, p), dim=-3)
    a3 = torch.stack((p, p, t, v, v, q), dim=-3)
    a4 = torch.stack((a1, a2, a3), dim=-4)
    return torch.einsum("...ijk,...xijk->...xjk", mask.to(img.dtype), a4)


def color_jitter(img: torch.Tensor, brightness: float, contrast: float, saturation: float, hue: float,
                 generator: torch.Generator | None = None) -> torch.Tensor:
    """Colour jitter with per-sample factors shared by the sample's T frames.

    Args:
        img: Tensor,  # [B, T, 3, H, W] in [0, 1]
        brightness, contrast, saturation: max relative change (factor in [1-x, 1+x], clipped at 0)
        hue: max hue shift in turns (≤ 0.5)
    Returns:
        Tensor,  # [B, T, 3, H, W] in [0, 1]
    """
    B = img.shape[0]
    shape = (B, 1, 1, 1, 1)

    def factor(x: float) -> torch.Tensor:
        u = torch.rand(B, generator=generator) * 2.0 - 1.0
        return (1.0 + x * u).clamp_min(0.0).to(img.device, img.dtype).view(shape)

    ops = []
    if brightness > 0:
        fb = factor(brightness)
        ops.append(lambda x: (x * fb).clamp(0.0, 1.0))
    if contrast > 0:
        fc = factor(contrast)
        ops.append(lambda x: (fc * x + (1 - fc) * _gray(x).mean(dim=(-3, -2, -1), keepdim=True)).clamp(0.0, 1.0))
    if saturation > 0:
        fs = factor(saturation)
        ops.append(lambda x: (fs * x + (1 - fs) * _gray(x)).clamp(0.0, 1.0))
    if hue > 0:
        fh = ((torch.rand(B, generator=generator) * 2.0 - 1.0) * hue).to(img.device, img.dtype).view(B, 1, 1, 1)

        def shift_hue(x: torch.Tensor) -> torch.Tensor:
            hsv = rgb_to_hsv(x)
            hsv = torch.stack([torch.remainder(hsv[..., 0, :, :] + fh, 1.0), hsv[..., 1, :, :], hsv[..., 2, :, :]],
                              dim=-3)
            return hsv_to_rgb(hsv)
        ops.append(shift_hue)
    for k in torch.randperm(len(ops), generator=generator).tolist():
        img = ops[k](img)
    return img


def blur_sigmas(batch: int, sigma_max: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """[B] blur standard deviations (pixels), uniform in ``[0, sigma_max]`` (the draws of
    :func:`random_gaussian_blur`)."""
    return torch.rand(batch, generator=generator) * float(sigma_max)


def _gaussian_kernels(sigmas: torch.Tensor, radius: int) -> torch.Tensor:
    """[B, 2r+1] normalised 1-D Gaussian kernels; sigma 0 (or below 1e-3) gives the identity (a unit impulse)."""
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    s = sigmas.to(torch.float64).clamp_min(1e-3)[:, None]
    k = torch.exp(-0.5 * (x[None] / s) ** 2)
    return k / k.sum(dim=1, keepdim=True)


def random_gaussian_blur(img: torch.Tensor, sigma_max: float, generator: torch.Generator | None = None,
                         sigmas: torch.Tensor | None = None) -> torch.Tensor:
    """Blur each sample (its T frames alike) with a Gaussian of std ``sigma`` pixels, ``sigma`` ~ U[0, sigma_max]
    (:func:`blur_sigmas`; or the given ``sigmas`` [B]); separable, reflect padding.

    Args:
        img: Tensor,  # [B, T, C, H, W] in [0, 1]
    Returns:
        Tensor,  # [B, T, C, H, W], same dtype
    """
    B, T, C, H, W = img.shape
    if sigmas is None:
        sigmas = blur_sigmas(B, sigma_max, generator)
    radius = max(1, int(math.ceil(3.0 * float(sigma_max))))
    if radius >= min(H, W):
        raise PolicyError(f"random_gaussian_blur: sigma_max {sigma_max} px needs a {2 * radius + 1}-pixel kernel, "
                         f"more than the {H}x{W} image")
    k = _gaussian_kernels(sigmas, radius).to(img.dtype)  # [B, K]
    w = k.repeat_interleave(T * C, dim=0)  # one kernel per (sample, frame, channel) plane
    x = img.reshape(1, B * T * C, H, W)
    x = F.conv2d(F.pad(x, (radius, radius, 0, 0), mode="reflect"), w[:, None, None, :], groups=B * T * C)
    x = F.conv2d(F.pad(x, (0, 0, radius, radius), mode="reflect"), w[:, None, :, None], groups=B * T * C)
    return x.reshape(B, T, C, H, W)


def _random_gaussian_blur_reference(img: torch.Tensor, sigmas: torch.Tensor, radius: int) -> torch.Tensor:
    """Slow reference of :func:`random_gaussian_blur`: each plane convolved with its full 2-D Gaussian kernel,
    pixel by pixel, reflect-padded (float64)."""
    B, T, C, H, W = img.shape
    out = torch.empty(img.shape, dtype=torch.float64)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    for b in range(B):
        s = max(float(sigmas[b]), 1e-3)
        g = torch.exp(-0.5 * (x / s) ** 2)
        k2 = torch.outer(g, g)
        k2 = k2 / k2.sum()
        for t in range(T):
            for c in range(C):
                p = F.pad(img[b, t, c].to(torch.float64)[None, None], (radius,) * 4, mode="reflect")[0, 0]
                for i in range(H):
                    for j in range(W):
                        out[b, t, c, i, j] = (p[i:i + 2 * radius + 1, j:j + 2 * radius + 1] * k2).sum()
    return out
