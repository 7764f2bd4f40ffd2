"""FisheyeIntrinsics: validation, fold-over / image circle facts, UMI resolution conversion vs real resizes."""

from __future__ import annotations

import math
import re

import cv2
import numpy as np
import pytest

from tests.camera._kb_helpers import GOPRO_CX, GOPRO_CY, GOPRO_F, GOPRO_K, gopro, random_intrinsics, rays_at
from umi_aug.camera import kb
from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import CameraError


# ------------------------------------------------------------------------------------------ validation
@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(width=0), "width"),
        (dict(width=-5), "width"),
        (dict(width=10.5), "width"),
        (dict(width=True), "width"),
        (dict(height="480"), "height"),
        (dict(fx=0.0), "fx"),
        (dict(fy=-1.0), "fy"),
        (dict(fx=float("nan")), "fx"),
        (dict(cx=float("inf")), "cx"),
        (dict(cy=None), "cy"),
        (dict(k=(0.1, 0.2, 0.3)), "k"),
        (dict(k=(0.1, 0.2, float("nan"), 0.0)), "k[2]"),
        (dict(k="abcd"), "k"),
        (dict(theta_limit=0.0), "theta_limit"),
        (dict(theta_limit=4.0), "theta_limit"),
        (dict(theta_limit=float("nan")), "theta_limit"),
    ],
)
def test_validation_names_field(kwargs, field):
    base = dict(width=640, height=480, fx=200.0, fy=200.0, cx=320.0, cy=240.0)
    base.update(kwargs)
    with pytest.raises(CameraError, match=re.escape(field)):
        FisheyeIntrinsics(**base)


def test_types_normalised_and_frozen():
    intr = FisheyeIntrinsics(np.int64(640), 480.0, np.float32(200), 201, 320, 240, np.array([0.1, 0, 0, 0]))
    assert type(intr.width) is int and intr.height == 480 and type(intr.height) is int
    assert type(intr.fx) is float and intr.k == (0.1, 0.0, 0.0, 0.0)
    with pytest.raises(Exception):
        intr.fx = 3.0  # frozen
    assert hash(intr) == hash(FisheyeIntrinsics(640, 480, 200.0, 201.0, 320.0, 240.0, (0.1, 0, 0, 0)))


def test_K_D_dict_round_trip(rng):
    intr = random_intrinsics(rng)
    np.testing.assert_array_equal(intr.K, [[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1]])
    assert intr.D.shape == (4,) and tuple(intr.D) == intr.k
    assert FisheyeIntrinsics.from_dict(intr.to_dict()) == intr
    lim = FisheyeIntrinsics(100, 80, 30.0, 30.0, 50.0, 40.0, theta_limit=1.5)
    assert FisheyeIntrinsics.from_dict(lim.to_dict()) == lim
    with pytest.raises(CameraError, match="unknown keys"):
        FisheyeIntrinsics.from_dict({**intr.to_dict(), "skew": 0})
    d = intr.to_dict()
    del d["cx"]
    with pytest.raises(CameraError, match="cx"):
        FisheyeIntrinsics.from_dict(d)
    with pytest.raises(CameraError):
        FisheyeIntrinsics.from_dict([1, 2])


def test_check_image_shape():
    intr = FisheyeIntrinsics.equidistant(224, 224, 88.0)
    intr.check_image_shape((224, 224, 3))
    with pytest.raises(CameraError, match="224"):
        intr.check_image_shape((224, 225, 3))


# ---------------------------------------------------------------------------------------- geometry facts
def test_gopro_fold_over_and_image_circle():
    g = gopro()
    assert g.theta_fold == pytest.approx(1.815, abs=1e-3)
    assert math.degrees(g.theta_fold) == pytest.approx(104.0, abs=0.05)
    assert abs(float(kb.kb_dtheta_d(g.theta_fold, g.k))) < 1e-12  # a root of the derivative
    assert float(kb.kb_dtheta_d(g.theta_fold - 1e-3, g.k)) > 0
    assert g.theta_max == g.theta_fold
    assert g.theta_d_max == pytest.approx(1.384, abs=1e-3)
    assert g.image_circle_radius_px[0] == pytest.approx(1103.0, abs=0.5)
    assert g.fov_deg == pytest.approx(208.0, abs=0.1)
    p = g.umi_policy(224)
    assert p.image_circle_radius_px[0] == pytest.approx(121.8, abs=0.05)
    assert p.theta_fold == g.theta_fold  # distortion never changes with scaling


def test_equidistant_has_no_fold_over():
    e = FisheyeIntrinsics.equidistant(640, 480, 150.0)
    assert math.isinf(e.theta_fold)
    assert e.theta_max == pytest.approx(math.pi, abs=1e-8) and e.theta_max < math.pi
    assert (e.cx, e.cy) == (319.5, 239.5)
    assert e.k == (0.0, 0.0, 0.0, 0.0)
    # rays past 90 deg are valid, straight back is not
    _, valid = kb.project(rays_at(np.radians([150.0, 179.0, 180.0]), [0.2, 0.2, 0.2]), e)
    assert valid.tolist() == [True, True, False]
    e2 = FisheyeIntrinsics.equidistant(640, 480, 150.0, theta_limit=math.radians(95))
    assert e2.fov_deg == pytest.approx(190.0)


def test_theta_fold_random_polynomials_vs_dense_scan(rng):
    for _ in range(30):
        k = tuple(rng.uniform(-1, 1, 4) * [0.3, 0.1, 0.03, 0.01])
        intr = FisheyeIntrinsics(10, 10, 5.0, 5.0, 5.0, 5.0, k)
        grid = np.linspace(0, math.pi, 200001)
        d = kb.kb_dtheta_d(grid, k)
        bad = np.flatnonzero(d <= 0)
        if bad.size == 0:
            assert math.isinf(intr.theta_fold) or intr.theta_fold <= math.pi
            if math.isinf(intr.theta_fold):
                continue
        ref = grid[bad[0]] if bad.size else intr.theta_fold
        assert intr.theta_fold == pytest.approx(ref, abs=2e-5)
        assert abs(float(kb.kb_dtheta_d(intr.theta_fold, k))) < 1e-9
        # theta_d increases up to the fold
        td = kb.kb_theta_d(np.linspace(0, intr.theta_max, 5001), k)
        assert (np.diff(td) > 0).all()


def test_tangential_fold_is_found():
    """A derivative that touches zero without changing sign (double root) still limits theta_max."""
    # d theta_d/d theta = (1 - s/s0)^2 with s = theta^2, s0 = 1.5^2  ->  3 k1 = -2/s0, 5 k2 = 1/s0^2
    s0 = 1.5**2
    k = (-2.0 / s0 / 3.0, 1.0 / s0**2 / 5.0, 0.0, 0.0)
    intr = FisheyeIntrinsics(10, 10, 5.0, 5.0, 5.0, 5.0, k)
    assert intr.theta_fold == pytest.approx(1.5, abs=1e-6)


# ------------------------------------------------------------------------------------- resolution changes
def test_umi_formula_exact():
    g = gopro()
    p = g.umi_policy(224, pixel_centre="umi")
    s = 224 / 2028
    assert p.fx == GOPRO_F * s and p.fy == GOPRO_F * s
    assert p.cx == (GOPRO_CX - 2704 / 2) * s + 224 / 2
    assert p.cy == GOPRO_CY * s
    assert (p.fx, p.cx, p.cy) == pytest.approx((88.02, 112.27, 111.72), abs=0.005)
    assert p.k == GOPRO_K and (p.width, p.height) == (224, 224)
    q = g.scaled(960, 720, pixel_centre="umi")
    assert q.fx == GOPRO_F * 720 / 2028 and q.cx == (GOPRO_CX - 1352) * 720 / 2028 + 480


def test_exact_vs_umi_half_pixel():
    g = gopro()
    e, u = g.umi_policy(224), g.umi_policy(224, pixel_centre="umi")
    s = 224 / 2028
    assert e.fx == u.fx
    # crop x0 = (2704 - 2028) // 2 = 338, then c' = (c + 0.5) s - 0.5
    assert e.cx == pytest.approx((GOPRO_CX - 338 + 0.5) * s - 0.5, abs=1e-12)
    assert e.cy == pytest.approx((GOPRO_CY + 0.5) * s - 0.5, abs=1e-12)
    assert u.cy - e.cy == pytest.approx(0.5 - 0.5 * s, abs=1e-9)  # UMI's half-pixel offset
    assert g.crop_geometry(224, 224) == (338, 0, 2028, 2028)
    with pytest.raises(CameraError):
        g.scaled(224, 224, pixel_centre="corner")


def _render_dots(h: int, w: int, centres: np.ndarray, sigma: float) -> np.ndarray:
    """Float32 image with Gaussian dots at sub-pixel ``centres [N, 2]`` (u, v) (pixel centres at integers)."""
    img = np.zeros((h, w), np.float32)
    rad = int(math.ceil(5 * sigma))
    for u, v in centres:
        u0, v0 = int(round(u)), int(round(v))
        ys = np.arange(max(v0 - rad, 0), min(v0 + rad + 1, h))
        xs = np.arange(max(u0 - rad, 0), min(u0 + rad + 1, w))
        g = np.exp(-((xs[None, :] - u) ** 2 + (ys[:, None] - v) ** 2) / (2 * sigma**2))
        img[np.ix_(ys, xs)] += g.astype(np.float32)
    return img


def _centroids(img: np.ndarray, guesses: np.ndarray, rad: int) -> np.ndarray:
    out = []
    for u, v in guesses:
        u0, v0 = int(round(u)), int(round(v))
        ys = np.arange(v0 - rad, v0 + rad + 1)
        xs = np.arange(u0 - rad, u0 + rad + 1)
        patch = img[np.ix_(ys, xs)].astype(np.float64)
        m = patch.sum()
        out.append([(patch.sum(0) * xs).sum() / m, (patch.sum(1) * ys).sum() / m])
    return np.array(out)


@pytest.mark.parametrize("out_size", [(224, 224), (480, 360), (150, 200)])
def test_exact_scaling_matches_crop_and_inter_area(rng, out_size):
    """Render dots at the projections of random rays, crop + cv2.resize(INTER_AREA), and find the dots where the
    scaled intrinsics project the same rays: < 0.05 px for "exact"; UMI's formula is off by ~(1 - s)/2 px."""
    w, h = 1352, 1014
    src = FisheyeIntrinsics(w, h, 398.4, 398.4, 677.2 + rng.uniform(-3, 3), 505.7 + rng.uniform(-3, 3), GOPRO_K)
    ow, oh = out_size
    x0, y0, cw, ch = src.crop_geometry(ow, oh)
    assert y0 == 0 and ch == h and 0 <= x0 and x0 + cw <= w
    dst = src.scaled(ow, oh)
    s = oh / h
    sigma_out = 1.6
    # rays whose dots land well inside the output frame and inside the image circle
    rays = rays_at(rng.uniform(0, math.radians(60), 400), rng.uniform(-math.pi, math.pi, 400))
    uv_dst, ok = kb.project(rays, dst)
    margin = 6 * sigma_out + 2
    ok &= (uv_dst[:, 0] > margin) & (uv_dst[:, 0] < ow - 1 - margin)
    ok &= (uv_dst[:, 1] > margin) & (uv_dst[:, 1] < oh - 1 - margin)
    rays, uv_dst = rays[ok], uv_dst[ok]
    # keep dots far apart (no overlap of a neighbour's tail into a centroid window)
    keep = [0]
    for i in range(1, len(uv_dst)):
        if np.min(np.linalg.norm(uv_dst[keep] - uv_dst[i], axis=1)) > 14 * sigma_out:
            keep.append(i)
        if len(keep) == 12:
            break
    rays, uv_dst = rays[keep], uv_dst[keep]
    assert len(rays) >= 3
    uv_src, _ = kb.project(rays, src)
    img = _render_dots(h, w, uv_src, sigma_out / s)
    out = cv2.resize(img[y0:y0 + ch, x0:x0 + cw], (ow, oh), interpolation=cv2.INTER_AREA)
    found = _centroids(out, uv_dst, rad=int(5 * sigma_out))
    err_exact = np.abs(found - uv_dst).max()
    assert err_exact < 0.05, err_exact
    uv_umi, _ = kb.project(rays, src.scaled(ow, oh, pixel_centre="umi"))
    err_umi = np.abs(found - uv_umi).max()
    assert err_umi > 0.5 * (0.5 - 0.5 * s), err_umi  # the half-pixel convention error is real


def test_scaled_pad_and_upscale():
    src = FisheyeIntrinsics(640, 480, 200.0, 200.0, 319.5, 239.5, (0.01, 0, 0, 0), theta_limit=1.6)
    # wider output than the input aspect: padding on both sides (x0 < 0)
    x0, _, cw, _ = src.crop_geometry(1000, 480)
    assert cw == 1000 and x0 == -180
    p = src.scaled(1000, 480)
    assert p.fx == 200.0 and p.cx == pytest.approx(319.5 + 180) and p.cy == 239.5
    up = src.scaled(1280, 960)
    assert up.fx == 400.0 and up.cx == pytest.approx((319.5 + 0.5) * 2 - 0.5) and up.theta_limit == 1.6
    # a centred principal point stays centred under "exact" scaling
    c = src.umi_policy(224)
    assert (c.cx, c.cy) == pytest.approx((111.5, 111.5))
    with pytest.raises(CameraError):
        src.scaled(0, 10)
