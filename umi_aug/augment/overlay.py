"""Gripper overlay (paper §3.4): the real gripper pixels of the original frames composited onto rendered frames.

The 3DGS scene is trained with the gripper masked out, so a rendered frame shows the scene only. The overlay
copies the pixels inside the gripper mask from an original policy frame whose gripper width is closest to the
rendered frame's width (the fingers move with the width), so augmented frames look like the real UMI frames
(black gripper-jaw polygons painted by UMI's 07 script, real fingers).

Masks (policy resolution ``S x S``):
* predefined — UMI's gripper polygons plus the finger trapezoid (:func:`umi_aug.camera.masks.predefined_mask`;
  canonical coordinates, so it fits any full-height centre crop);
* estimated — pixels whose grey level barely changes over the demos' pre-contact frames (the gripper is static in
  the image while the scene moves), cleaned morphologically and restricted to components touching the bottom edge.

Compositing: ``out = a·original + (1 − a)·rendered`` with ``a = 1`` inside the mask and an outward linear ramp of
``feather_px`` pixels (distance transform), so every pixel inside the mask is exactly the original's.
"""

from __future__ import annotations

import logging
from functools import lru_cache

import cv2
import numpy as np

from umi_aug.camera.masks import predefined_mask
from umi_aug.errors import AugmentError

__all__ = ["predefined_overlay_mask", "estimate_gripper_mask", "choose_overlay_mask", "overlay_alpha",
           "composite_overlay", "source_frames_by_width"]

log = logging.getLogger(__name__)

#: Largest grey-level temporal std (0..255) a finger pixel may have (JPEG-XL noise and shading stay below it;
#: scene moving behind the fingers is far above: ~40-75 on the synthetic session).
MAX_FINGER_STD = 30.0


def predefined_overlay_mask(size: int) -> np.ndarray:
    """UMI's gripper polygons ∪ finger trapezoid at ``size x size`` → ``[S, S]`` bool."""
    return predefined_mask(size, size, mirror=False, gripper=True, finger=True)


def estimate_gripper_mask(frames: np.ndarray,  # [N, S, S, 3] uint8 frames where the gripper is static
                          std_threshold: float = 6.0, open_px: int = 1) -> np.ndarray:
    """Static-pixel estimate of the gripper region → ``[S, S]`` bool.

    A pixel is static when the temporal standard deviation of its grey level (0..255) is below
    ``std_threshold``; the static set is opened by a ``(2·open_px+1)²`` square, and only connected components
    touching the bottom image edge are kept (the gripper enters from below).

    Raises:
        AugmentError: fewer than 2 frames or a wrong shape.
    """
    f = np.asarray(frames)
    if f.ndim != 4 or f.shape[-1] != 3 or f.dtype != np.uint8 or f.shape[0] < 2:
        raise AugmentError(f"estimate_gripper_mask: need uint8 frames [N >= 2, H, W, 3], got {f.dtype} {f.shape}")
    grey = f.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    static = (grey.std(axis=0) < float(std_threshold)).astype(np.uint8)
    if open_px > 0:
        k = np.ones((2 * open_px + 1, 2 * open_px + 1), np.uint8)
        static = cv2.morphologyEx(static, cv2.MORPH_OPEN, k)
    n, labels = cv2.connectedComponents(static, connectivity=4)
    bottom = np.unique(labels[-1][static[-1] > 0])
    return np.isin(labels, bottom[bottom > 0])


def choose_overlay_mask(frames: np.ndarray, size: int, how: str = "auto", std_threshold: float = 6.0,
                        min_coverage: float = 0.9) -> tuple[np.ndarray, dict]:
    """The overlay mask and why it was chosen.

    Args:
        frames: ``[N, S, S, 3]`` uint8 original policy frames with a static gripper (pre-contact, open).
        size: S.
        how: ``"predefined"`` (UMI's gripper polygons ∪ finger trapezoid), ``"estimated"`` (static pixels), or
            ``"auto"``: when at least ``min_coverage`` of the static estimate lies inside UMI's polygons (they fit
            this gripper), UMI's jaw polygons ∪ the static finger pixels of the finger trapezoid
            (:func:`static_fingers`) — the whole trapezoid would also copy the scene seen between the fingers
            (e.g. a table tag) onto every rendered frame; else the estimate; the full predefined mask when the
            estimate is empty.
    Returns:
        (mask ``[S, S]`` bool, info dict: ``source``, ``coverage``, ``pixels``).
    """
    pre = predefined_overlay_mask(size)
    if how == "predefined":
        return pre, {"source": "predefined", "coverage": None, "pixels": int(pre.sum())}
    if how not in ("auto", "estimated"):
        raise AugmentError(f"choose_overlay_mask: how = {how!r}; expected predefined/estimated/auto")
    est = estimate_gripper_mask(frames, std_threshold)
    coverage = float((est & pre).sum() / max(1, est.sum()))
    if how == "auto" and not est.any():
        return pre, {"source": "predefined (the estimate is empty)", "coverage": None, "pixels": int(pre.sum())}
    if how == "estimated" or coverage < min_coverage:
        if not est.any():
            raise AugmentError("choose_overlay_mask: the static-pixel estimate is empty (no pixel below "
                               f"std {std_threshold}); use mask='predefined' or raise std_threshold")
        src = "estimated" if how == "estimated" else "estimated (predefined does not fit)"
        return est, {"source": src, "coverage": coverage, "pixels": int(est.sum())}
    jaws = predefined_mask(size, size, mirror=False, gripper=True, finger=False)
    fingers = static_fingers(frames, pre & ~jaws)
    mask = jaws | fingers
    return mask, {"source": "predefined jaws + static fingers (fits the estimate)", "coverage": coverage,
                  "pixels": int(mask.sum()), "finger_pixels": int(fingers.sum())}


def static_fingers(frames: np.ndarray,  # [N, S, S, 3] uint8 frames with an open, static gripper
                   region: np.ndarray,  # [S, S] bool the finger trapezoid outside the jaw polygons
                   max_static_std: float = MAX_FINGER_STD) -> np.ndarray:
    """The finger pixels inside UMI's finger trapezoid → ``[S, S]`` bool.

    The trapezoid holds the (static) fingers and the (moving) scene seen between them. Their grey-level temporal
    standard deviations form two groups; Otsu's threshold on the region's values separates them, capped at
    ``max_static_std`` (a region that is all moving scene gives no finger pixel). Rendering noise and shading on
    the fingers make a fixed small threshold miss them.
    """
    f = np.asarray(frames)
    grey = f.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    sd = grey.std(axis=0)
    vals = np.clip(sd[region], 0, 255).astype(np.uint8)
    if vals.size == 0:
        return np.zeros(region.shape, bool)
    thr, _ = cv2.threshold(vals.reshape(-1, 1), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    fingers = (region & (sd <= min(float(thr), max_static_std))).astype(np.uint8)
    k = np.ones((3, 3), np.uint8)
    fingers = cv2.morphologyEx(fingers, cv2.MORPH_CLOSE, k)  # fill pinholes; no opening: thin finger edges stay
    return (fingers > 0) & region


def overlay_alpha(mask: np.ndarray, feather_px: float = 2.0) -> np.ndarray:
    """``[S, S]`` float32 alpha: 1 inside ``mask``, ``1 − d/(feather_px + 1)`` at distance d (px) outside, ≥ 0."""
    m = np.asarray(mask, dtype=bool)
    a = m.astype(np.float32)
    if feather_px > 0 and m.any():
        d = cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, 5)
        a = np.where(m, 1.0, np.clip(1.0 - d / (float(feather_px) + 1.0), 0.0, 1.0)).astype(np.float32)
    return a


def composite_overlay(rendered: np.ndarray,  # [..., S, S, 3] uint8
                      original: np.ndarray,  # [..., S, S, 3] uint8
                      alpha: np.ndarray,  # [S, S] float in [0, 1]
                      ) -> np.ndarray:
    """``a·original + (1 − a)·rendered``, rounded; exactly ``original`` where a = 1, ``rendered`` where a = 0.

    Blended only inside the mask's feathered band (``0 < a < 1``: a few per cent of the pixels); elsewhere the
    pixels are copied. The same bytes as :func:`_composite_overlay_reference`, which blends every pixel and is used
    as is for an alpha with NaN (``tests/augment/test_overlay.py``)."""
    a32 = np.ascontiguousarray(alpha, dtype=np.float32)
    r, o = np.asarray(rendered), np.asarray(original)
    if (r.shape != o.shape or r.dtype != np.uint8 or o.dtype != np.uint8 or r.ndim < 3
            or r.shape[-3:-1] != a32.shape or not np.isfinite(a32).all()):
        return _composite_overlay_reference(rendered, original, alpha)  # its checks and error message
    full, band, ab = _band(a32.tobytes(), a32.shape)
    lead = r.shape[:-3]
    P = a32.size
    rf, of = r.reshape(-1, P, 3), o.reshape(-1, P, 3)
    out = rf.copy()
    out[:, full] = of[:, full]
    ob, rb = of[:, band].astype(np.float32), rf[:, band].astype(np.float32)
    out[:, band] = np.rint(ab * ob + (1.0 - ab) * rb).astype(np.uint8)
    return out.reshape(lead + r.shape[-3:])


@lru_cache(maxsize=8)
def _band(alpha_bytes: bytes, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flat pixel indices where ``alpha >= 1`` and where ``0 < alpha < 1``, and the band's alphas ``[B, 1]``."""
    a = np.frombuffer(alpha_bytes, np.float32).reshape(shape)
    flat = a.reshape(-1)
    full = np.flatnonzero(flat >= 1.0)
    band = np.flatnonzero((flat > 0.0) & (flat < 1.0))
    return full, band, flat[band][:, None]


def _composite_overlay_reference(rendered: np.ndarray, original: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """:func:`composite_overlay` blending every pixel (the slow, obviously correct reference)."""
    r = np.asarray(rendered)
    o = np.asarray(original)
    if r.shape != o.shape or r.dtype != np.uint8 or o.dtype != np.uint8 or r.shape[-3:-1] != alpha.shape:
        raise AugmentError(f"composite_overlay: rendered {r.dtype}{r.shape}, original {o.dtype}{o.shape}, "
                           f"alpha {alpha.shape}: need equal uint8 [..., S, S, 3] and alpha [S, S]")
    a = alpha.astype(np.float32)[..., None]
    out = np.rint(a * o.astype(np.float32) + (1.0 - a) * r.astype(np.float32)).astype(np.uint8)
    full, none = alpha >= 1.0, alpha <= 0.0
    out[..., full, :] = o[..., full, :]
    out[..., none, :] = r[..., none, :]
    return out


def source_frames_by_width(demo_width: np.ndarray,  # [M] metres, candidate original frames' widths
                           width: np.ndarray,  # [K] metres, widths of the frames to overlay
                           demo_time: np.ndarray | None = None,  # [M] normalised time in [0, 1] (tie-break)
                           time: np.ndarray | None = None,  # [K] normalised time in [0, 1]
                           ) -> np.ndarray:
    """Index ``[K]`` into the candidates: closest gripper width; ties (within 0.5 mm) → closest normalised time."""
    dw = np.abs(np.asarray(width, np.float64)[:, None] - np.asarray(demo_width, np.float64)[None, :])  # [K, M]
    if demo_time is None or time is None:
        return np.argmin(dw, axis=1)
    dq = np.floor(dw / 5e-4)  # quantised width error, then time
    dt = np.abs(np.asarray(time, np.float64)[:, None] - np.asarray(demo_time, np.float64)[None, :])
    return np.argmin(dq * 10.0 + np.minimum(dt, 1.0) * 0.999, axis=1)
