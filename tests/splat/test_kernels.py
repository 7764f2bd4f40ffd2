"""numba building blocks: KB projection/Jacobian, projection vs the torch projection, tile binning vs brute
force, radix sort, the float32 exp."""

from __future__ import annotations

import math

import numpy as np
import pytest

import numba  # noqa: E402,F401  (the splat extra; a missing install must fail, not skip)

from numba import njit  # noqa: E402

from umi_aug.camera import kb  # noqa: E402
from umi_aug.splat import _kernels as K  # noqa: E402
from umi_aug.splat.project import project_gaussians  # noqa: E402
from umi_aug.splat.renderer import bin_gaussians, project_numba  # noqa: E402
from umi_aug.splat.scenes import random_gaussians  # noqa: E402
from tests.splat._helpers import random_kb_intrinsics, random_pose, rays_at  # noqa: E402


def test_kb_projection_and_jacobian_match_camera_stage(rng):
    intr = random_kb_intrinsics(rng)
    special = np.array([0.0, 1e-9, 1e-3, math.pi / 2, 1.7, intr.theta_max])
    theta = np.concatenate([rng.uniform(0, intr.theta_max, 300), special[special <= intr.theta_max]])
    pts = np.stack([rays_at(t, p) for t, p in zip(theta, rng.uniform(-math.pi, math.pi, theta.size))])
    pts *= rng.uniform(0.01, 10, (theta.size, 1))
    uv, ok = kb.project(pts, intr)
    J, _ = kb.project_jacobian(pts, intr)
    for i, p in enumerate(pts):
        r = K._kb_project_jacobian(*p, intr.fx, intr.fy, intr.cx, intr.cy, *intr.k)
        assert r[0] and ok[i]
        assert r[1] == pytest.approx(theta[i], abs=1e-12)
        np.testing.assert_allclose(r[2:4], uv[i], rtol=0, atol=1e-10)
        np.testing.assert_allclose(np.array(r[4:]).reshape(2, 3), J[i], rtol=1e-10, atol=1e-10 * intr.fx)
    assert not K._kb_project_jacobian(0.0, 0.0, 0.0, intr.fx, intr.fy, intr.cx, intr.cy, *intr.k)[0]
    assert not K._kb_project_jacobian(np.nan, 0.0, 1.0, intr.fx, intr.fy, intr.cx, intr.cy, *intr.k)[0]


@pytest.mark.parametrize("filt", ["inria", "mip", "none"])
def test_numba_projection_matches_torch_projection(rng, filt):
    intr = random_kb_intrinsics(rng)
    T = random_pose(rng)
    g = random_gaussians(200, rng, intr, T, theta_max=2.2, opacity_range=(0.001, 0.99))
    packed, uv, depth, valid, counts = project_numba(g, T, intr, 3, filt)
    proj = project_gaussians(g, T, intr, 3, filt)
    ids = np.flatnonzero(valid)
    separate = np.zeros(ids.size, dtype=np.int64)
    K.count_tiles_kernel(packed, ids, intr.width, intr.height, separate)
    assert np.array_equal(counts[ids], separate) and not counts[~valid].any()
    assert np.array_equal(ids, proj.ids.numpy())
    assert 50 < ids.size < 200  # some culled (beyond the fold-over, low opacity, off-image)
    np.testing.assert_allclose(uv[ids], proj.means2d.detach().numpy(), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(packed[ids, 2:5], proj.conics.detach().numpy(), rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(packed[ids, 5], proj.opacities.detach().numpy(), rtol=1e-12)
    np.testing.assert_allclose(packed[ids, 6:9], proj.colors.detach().numpy(), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(depth[ids], proj.depths.detach().numpy(), rtol=1e-14)


def test_tile_lists_contain_every_contributing_pair(rng):
    """Brute force: every (Gaussian, pixel) pair with q <= lim (alpha >= 1/255) is in the pixel's tile list,
    and the ellipse/tile test never keeps more tiles than the bounding box."""
    W, H = 83, 57
    V = 60
    L = rng.normal(size=(V, 2, 2)) * rng.uniform(0.5, 8, (V, 1, 1))
    L[:10, 1] *= 1e-3  # needles
    cov = L @ L.transpose(0, 2, 1) + 1e-4 * np.eye(2)
    packed = np.zeros((V, K.PACKED_COLS))
    mu = rng.uniform([-10, -10], [W + 10, H + 10], (V, 2))
    inv = np.linalg.inv(cov)
    packed[:, 0:2] = mu
    packed[:, 2], packed[:, 3], packed[:, 4] = inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]
    packed[:, 5] = rng.uniform(0.01, 1.0, V)
    K.footprint_kernel(packed)
    rows = np.arange(V)
    b = bin_gaussians(packed, rows, rng.uniform(1, 2, V), W, H)
    lists = [set(b.sorted_row[b.tile_start[t]:b.tile_start[t + 1]].tolist()) for t in range(b.tiles_x * b.tiles_y)]
    v, u = np.mgrid[0:H, 0:W]
    n_pairs = 0
    for g in range(V):
        d = np.stack([u - mu[g, 0], v - mu[g, 1]], -1)
        q = np.einsum("...i,ij,...j->...", d, inv[g], d)
        lim = 2 * np.log(packed[g, 5] * 255)
        ys, xs = np.nonzero(q <= lim)
        n_pairs += ys.size
        for y, x in zip(ys, xs):
            assert g in lists[(y // 16) * b.tiles_x + x // 16]
    assert n_pairs > 1000
    # per Gaussian: tiles kept <= tiles of its bounding box
    for i in range(V):
        g = b.rows[i]
        kept = b.offsets[i + 1] - b.offsets[i]
        tx0, tx1, ty0, ty1 = K._tile_rect(packed, g, W, H)
        assert kept <= max(0, (tx1 - tx0 + 1) * (ty1 - ty0 + 1))
    # depth order inside every tile
    depth = np.empty(V)
    depth[b.rows] = np.arange(V)
    for t in range(len(lists)):
        seg = depth[b.sorted_row[b.tile_start[t]:b.tile_start[t + 1]]]
        assert np.all(np.diff(seg) > 0)


def test_radix_argsort_is_a_stable_sort(rng):
    keys = np.concatenate([rng.uniform(0, 5, 3000), np.full(50, 1.5), [0.0, 1e-300, 1e300, 7.0, 7.0]])
    rng.shuffle(keys)
    idx = K.radix_argsort_f64(keys)
    assert np.array_equal(idx, np.argsort(keys, kind="stable"))
    assert K.radix_argsort_f64(np.zeros(0)).size == 0


@njit(cache=True)
def _fexp_array(x, out):
    for i in range(x.shape[0]):
        out[i] = K.fexp(x[i])


def test_float32_exp_accuracy():
    x = np.concatenate([np.linspace(K.FEXP_MIN, 0, 400_001), [-0.0, -1e-30, 1e-3]]).astype(np.float32)
    out = np.empty_like(x)
    _fexp_array(x, out)
    ref = np.exp(np.minimum(x.astype(np.float64), 0.0))
    assert np.max(np.abs(out / ref - 1)) < 2.5e-7
    # below the range (and NaN): clamped to exp(FEXP_MIN), far below any alpha that passes 1/255
    low = np.array([-16.5, -87.0, -1e30, -np.inf, np.nan], dtype=np.float32)
    out = np.empty_like(low)
    _fexp_array(low, out)
    assert np.all(out == out[0]) and out[0] == pytest.approx(math.exp(K.FEXP_MIN), rel=1e-6)
    assert out[0] < 1.0 / 255 / 1000


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_pack_kernel_equals_numpy(rng, dtype):
    """The rasteriser's rows from the projection's outputs: ``pack_kernel`` gives the bytes of the zero fill,
    column copies and ``footprint_kernel`` it replaces (degenerate and negative conics, opacities under the alpha
    threshold, NaN; no row; contiguous outputs and strided column views of one buffer)."""
    import torch

    from umi_aug.splat.renderer import _pack, _pack_reference

    tdt = torch.float32 if dtype == np.float32 else torch.float64
    for V in (0, 1, int(rng.integers(50, 400))):
        L = rng.normal(size=(V, 2, 2)) * rng.uniform(0.3, 20.0, (V, 1, 1))
        inv = np.linalg.inv(L @ L.transpose(0, 2, 1) + 1e-3 * np.eye(2))
        conic = np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
        conic[1::7, 1] = np.sqrt(np.abs(conic[1::7, 0] * conic[1::7, 2])) * 1.5  # det < 0
        conic[2::11, 0] = -1.0
        conic[3::13, 2] = np.nan
        opacity = rng.uniform(0.0, 1.0, V)
        opacity[::5] = 1e-4  # under the alpha threshold: no footprint
        cols = [rng.uniform(-50.0, 300.0, (V, 2)), conic, opacity, rng.random((V, 3)), rng.uniform(0.05, 5.0, V)]
        separate = [torch.from_numpy(np.ascontiguousarray(c)).to(tdt) for c in cols]
        buf = torch.from_numpy(np.concatenate([c.reshape(V, w) for c, w in zip(cols, (2, 3, 1, 3, 1))], axis=1)).to(tdt)
        strided = [buf[:, 0:2], buf[:, 2:5], buf[:, 5], buf[:, 6:9], buf[:, 9]]
        for parts in (separate, strided):
            want = _pack_reference(*parts, dtype)
            got = _pack(*parts, dtype)
            assert got.dtype == want.dtype and got.shape == (V, K.PACKED_COLS) and got.tobytes() == want.tobytes()
