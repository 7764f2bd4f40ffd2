"""UMI predefined masks: canonical coordinates, resolution invariance, symmetry, drawing."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from umi_aug.camera.masks import (
    REFERENCE_HEIGHT,
    REFERENCE_WIDTH,
    canonical_to_pixel,
    draw_predefined_mask,
    finger_polygon,
    gripper_polygons,
    mirror_crop_slices,
    mirror_polygons,
    pixel_to_canonical,
    predefined_mask,
)
from umi_aug.errors import CameraError


def _center_square(mask: np.ndarray) -> np.ndarray:
    """Full-height centre square (what UMI's resize-to-height + centre crop keeps)."""
    h, w = mask.shape
    x0 = (w - h) // 2
    return mask[:, x0 : x0 + h]


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.logical_and(a, b).sum() / max(np.logical_or(a, b).sum(), 1))


def test_canonical_roundtrip_and_values(rng):
    h, w = 1080, 1920
    xy = rng.uniform([-100, -100], [w + 100, h + 100], size=(7, 5, 2))
    c = pixel_to_canonical(xy, h, w)
    np.testing.assert_allclose(canonical_to_pixel(c, h, w), xy, atol=1e-9)
    # centre → 0; one image height → 1
    np.testing.assert_allclose(pixel_to_canonical([w / 2, h / 2], h, w), [0.0, 0.0])
    np.testing.assert_allclose(pixel_to_canonical([w / 2 + h, h / 2 - h], h, w), [1.0, -1.0])
    # reference polygon pixels come back exactly at the reference resolution
    left_mirror_px = canonical_to_pixel(mirror_polygons()[0], REFERENCE_HEIGHT, REFERENCE_WIDTH)
    np.testing.assert_allclose(left_mirror_px[0], [540, 1700], atol=1e-9)


def test_polygon_shapes_and_right_is_mirrored():
    m, g, f = mirror_polygons(), gripper_polygons(), finger_polygon()
    assert m.shape == (2, 6, 2) and g.shape == (2, 6, 2) and f.shape == (1, 4, 2)
    for p in (m, g):
        np.testing.assert_allclose(p[1, :, 0], -p[0, :, 0])
        np.testing.assert_allclose(p[1, :, 1], p[0, :, 1])
        assert np.all(p[0, :, 0] <= 1e-12)  # left polygons live in the left half
    # finger trapezoid: height 0.37, widths 0.25 / 1.4, centred, touching the bottom edge (y = 0.5)
    ys = f[0, :, 1]
    assert np.isclose(ys.max() - ys.min(), 0.37) and np.isclose(ys.max(), 0.5)
    top = f[0][np.isclose(ys, ys.min())]
    bot = f[0][np.isclose(ys, ys.max())]
    assert np.isclose(np.ptp(top[:, 0]), 0.25) and np.isclose(np.ptp(bot[:, 0]), 1.4)
    assert np.isclose(f[0, :, 0].mean(), 0.0)


@pytest.mark.parametrize(
    "kw", [dict(mirror=True, gripper=True, finger=False), dict(mirror=False, gripper=False, finger=True)]
)
def test_masks_agree_across_resolutions(kw):
    direct = predefined_mask(224, 224, **kw)
    assert direct.shape == (224, 224) and direct.dtype == bool
    for h, w in ((2028, 2704), (1080, 1920)):
        full = predefined_mask(h, w, **kw).astype(np.float32)
        sq = _center_square(full)
        small = cv2.resize(sq, (224, 224), interpolation=cv2.INTER_AREA) > 0.5
        iou = _iou(small, direct)
        assert iou > 0.97, (h, w, iou)


def test_left_right_symmetry():
    for h, w in ((2028, 2704), (224, 224), (1080, 1920)):
        m = predefined_mask(h, w, mirror=True, gripper=True, finger=True)
        # canonical x -> -x is u -> W - u; with integer pixel centres that is column j -> W - j
        # (cannot be exact on the pixel grid: compare the mask with its flip, allowing a 1-px boundary band)
        flipped = m[:, ::-1]
        assert _iou(m, flipped) > 0.97, (h, w)


def test_gripper_covers_bottom_corners_not_centre():
    for h, w in ((2028, 2704), (1080, 1920), (224, 224)):
        m = predefined_mask(h, w, mirror=False, gripper=True)
        # the polygons reach canonical x = ±2/3 (the 4:3 frame's edges): on 16:9 frames they cover the
        # bottom corners of the full-height centre square (what the policy sees), not the frame's corners
        x0 = max((w - round(h * REFERENCE_WIDTH / REFERENCE_HEIGHT)) // 2, 0)
        assert m[h - 1, x0] and m[h - 1, w - 1 - x0]
        sq = _center_square(m)
        assert sq[h - 1, 0] and sq[h - 1, h - 1]
        assert not m[h // 2, w // 2]
        assert not m[: h // 3].any()  # the top third is never masked
        mm = predefined_mask(h, w, mirror=True, gripper=False)
        assert mm.any() and not mm[h // 2, w // 2]
        assert not mm[h - 1, 0] or w > h  # the mirrors sit left/right of centre, above the bottom edge


def test_mirror_crop_slices_contains_mirror():
    for h, w in ((2028, 2704), (1080, 1920)):
        rs, cs = mirror_crop_slices(h, w)
        assert rs.start == int(np.round(pixel_to_canonical([0, 1120], 2028, 2704)[1] * h + h / 2))
        assert 0 <= rs.start < rs.stop <= h and 0 <= cs.start < cs.stop <= w
        m = predefined_mask(h, w, mirror=True, gripper=False)
        assert m[rs, cs].mean() > 0.9, (h, w)  # the box lies on the mirror
        rs_r, cs_r = mirror_crop_slices(h, w, left=False)
        assert rs_r == rs and abs((w - cs_r.stop) - cs.start) <= 1
    assert mirror_crop_slices(2028, 2704) == (slice(1120, 1480), slice(290, 650))
    # at 224² the mirror box pokes out of the square: clipped to the image (UMI would return a negative start)
    assert mirror_crop_slices(224, 224) == (slice(124, 163), slice(0, 34))
    assert mirror_crop_slices(224, 224, left=False)[1] == slice(190, 224)


@pytest.mark.parametrize("use_aa", [False, True])
def test_draw_color_and_input_untouched(rng, use_aa):
    img = rng.integers(1, 255, size=(224, 224, 3), dtype=np.uint8)
    before = img.copy()
    color = (255, 0, 128)
    out = draw_predefined_mask(img, color=color, mirror=True, gripper=True, use_aa=use_aa)
    np.testing.assert_array_equal(img, before)
    assert out.shape == img.shape and out.dtype == img.dtype and out is not img
    m = predefined_mask(224, 224, mirror=True, gripper=True)
    # the interior of the mask (eroded, away from AA edges) has exactly the colour
    core = cv2.erode(m.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert core.sum() > 100
    np.testing.assert_array_equal(out[core], np.broadcast_to(np.array(color, np.uint8), out[core].shape))
    # far from the mask nothing changed
    far = ~cv2.dilate(m.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    np.testing.assert_array_equal(out[far], img[far])


def test_bad_sizes_raise():
    for h, w in ((0, 10), (10, -1), (2.5, 10), (True, 10)):
        with pytest.raises(CameraError):
            predefined_mask(h, w)  # type: ignore[arg-type]
    with pytest.raises(CameraError):
        mirror_crop_slices(0, 5)
    with pytest.raises(CameraError):
        draw_predefined_mask(np.zeros((4, 4, 2), np.uint8))
    with pytest.raises(CameraError):
        draw_predefined_mask(np.zeros((4,), np.uint8))
    with pytest.raises(CameraError):
        draw_predefined_mask(np.zeros((4, 4, 3), np.uint8), color=(1, 2))
    with pytest.raises(CameraError):
        pixel_to_canonical(np.zeros((3, 3)), 10, 10)
