"""Gripper overlay: exact copy inside the mask, masks (predefined / estimated), source-frame choice."""

from __future__ import annotations

import numpy as np
import pytest

from umi_aug.augment.overlay import (
    choose_overlay_mask, composite_overlay, estimate_gripper_mask, overlay_alpha, predefined_overlay_mask,
    source_frames_by_width,
)
from umi_aug.errors import AugmentError


def _blob_mask(rng, s=48):
    yy, xx = np.mgrid[:s, :s]
    cx, r = rng.uniform(10, 38), rng.uniform(6, 14)
    return (xx - cx) ** 2 + (yy - (s - 1)) ** 2 < r * r  # touches the bottom edge


def test_composite_copies_exactly_the_original_inside_the_mask(rng):
    s = 48
    mask = _blob_mask(rng, s)
    rendered = rng.integers(0, 256, (3, s, s, 3), dtype=np.uint8)
    original = rng.integers(0, 256, (3, s, s, 3), dtype=np.uint8)
    for feather in (0.0, 1.5, 4.0):
        a = overlay_alpha(mask, feather)
        out = composite_overlay(rendered, original, a)
        assert np.array_equal(out[:, mask], original[:, mask])  # exactly the gripper pixels
        far = a == 0
        assert np.array_equal(out[:, far], rendered[:, far])  # untouched outside the feather
        ramp = (a > 0) & (a < 1)
        assert (ramp.any() if feather > 0 else not ramp.any())
        assert not np.any(ramp & mask)
        lo = np.minimum(rendered, original)[:, ramp]
        hi = np.maximum(rendered, original)[:, ramp]
        assert np.all((out[:, ramp] >= lo) & (out[:, ramp] <= hi))
        # the ramp stays within feather + 1 px of the mask
        import cv2

        d = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)
        assert np.all(d[a > 0] <= feather + 1.0 + 1e-6)


def test_composite_rejects_bad_shapes(rng):
    a = np.ones((8, 8), np.float32)
    with pytest.raises(AugmentError):
        composite_overlay(np.zeros((8, 8, 3), np.uint8), np.zeros((8, 9, 3), np.uint8), a)
    with pytest.raises(AugmentError):
        composite_overlay(np.zeros((8, 8, 3), np.float32), np.zeros((8, 8, 3), np.uint8), a)


def test_composite_equals_the_every_pixel_reference(rng):
    """The band-only blend gives the same bytes as blending every pixel: feathered and hard masks, random alphas
    outside [0, 1], all-0 and all-1 alphas, leading dimensions, extreme values; an alpha with NaN uses the
    reference itself."""
    from umi_aug.augment.overlay import _composite_overlay_reference

    S = 48
    mask = _blob_mask(rng, S)
    noisy = rng.uniform(-0.5, 1.5, (S, S)).astype(np.float32)
    with_nan = noisy.copy()
    with_nan[3, 4] = np.nan
    for alpha in (overlay_alpha(mask, 3.0), noisy, np.zeros((S, S), np.float32), np.ones((S, S), np.float32),
                  overlay_alpha(mask, 0.0), overlay_alpha(mask, 2.0).astype(np.float64), with_nan):
        for lead in ((), (3,), (2, 2)):
            r = rng.integers(0, 256, lead + (S, S, 3)).astype(np.uint8)
            o = rng.integers(0, 256, lead + (S, S, 3)).astype(np.uint8)
            r.reshape(-1)[:7], o.reshape(-1)[:7] = 255, 0  # extremes
            with np.errstate(invalid="ignore"):
                want = _composite_overlay_reference(r, o, alpha)
                got = composite_overlay(r, o, alpha)
            assert got.dtype == np.uint8 and got.shape == want.shape and got.tobytes() == want.tobytes()
    with pytest.raises(AugmentError, match="composite_overlay"):
        composite_overlay(np.zeros((S, S, 3), np.uint8), np.zeros((S, S - 1, 3), np.uint8), alpha)


def test_estimated_mask_recovers_a_static_region(rng):
    s, n = 48, 12
    mask = _blob_mask(rng, s)
    frames = rng.integers(0, 256, (n, s, s, 3), dtype=np.uint8)  # a moving scene: every pixel varies
    frames[:, mask] = rng.integers(0, 256, 3, dtype=np.uint8)  # the static gripper
    frames[:, :4, :4] = 17  # static but not touching the bottom edge → not the gripper
    est = estimate_gripper_mask(frames, std_threshold=6.0, open_px=0)
    assert np.array_equal(est, mask)
    with pytest.raises(AugmentError):
        estimate_gripper_mask(frames[:1])


def test_choose_mask_auto_falls_back_to_the_estimate(rng):
    s = 64
    pre = predefined_overlay_mask(s)
    assert pre[-1].any() and not pre[0].any()  # jaws/fingers at the bottom
    frames = rng.integers(0, 256, (10, s, s, 3), dtype=np.uint8)
    frames[:, pre] = 0  # a gripper exactly where UMI's polygons are → predefined fits
    m, info = choose_overlay_mask(frames, s, "auto")
    assert info["source"].startswith("predefined") and np.array_equal(m, pre)
    # fingers static but the background between them moving (a tag passing by): that background is not copied
    from umi_aug.camera.masks import predefined_mask

    jaws = predefined_mask(s, s, mirror=False, gripper=True, finger=False)
    between = pre & ~jaws  # the finger trapezoid outside UMI's jaw polygons: here all moving background
    assert between.any()
    moving = np.concatenate([frames] * 4)  # 40 frames: the sample std of moving pixels stays well above 30
    moving[:, between] = rng.integers(0, 256, (40, int(between.sum()), 3), dtype=np.uint8)
    m_mov, info_mov = choose_overlay_mask(moving, s, "auto")
    assert info_mov["source"].startswith("predefined jaws") and m_mov[jaws].all()
    assert not m_mov[between].any()
    frames2 = rng.integers(0, 256, (10, s, s, 3), dtype=np.uint8)
    other = np.zeros((s, s), bool)
    other[s // 4:, s // 2 - 3: s // 2 + 3] = True  # a tall gripper reaching above the predefined polygons
    frames2[:, other] = 40
    m2, info2 = choose_overlay_mask(frames2, s, "auto")
    assert info2["source"].startswith("estimated") and info2["coverage"] < 0.9
    assert m2[other].mean() > 0.9
    m3, info3 = choose_overlay_mask(frames2, s, "predefined")
    assert np.array_equal(m3, pre) and info3["source"] == "predefined"


def test_source_frames_closest_width_then_time():
    demo_w = np.array([0.08, 0.08, 0.08, 0.07, 0.05])
    t = np.linspace(0, 1, 5)
    idx = source_frames_by_width(demo_w, np.array([0.08, 0.08, 0.069, 0.0]), t, np.array([0.0, 0.6, 0.5, 1.0]))
    assert idx.tolist() == [0, 2, 3, 4]
    assert source_frames_by_width(demo_w, np.array([0.051])).tolist() == [4]
