"""Voxel SDF vs its brute-force reference (same sign rule), conservativeness, gradients, speed, failures."""

import math
import time

import numpy as np
import pytest

from umi_aug.errors import ReconError
from umi_aug.geometry.sdf import SignedDistanceField, check_sdf_output
from umi_aug.recon.cloud import SceneCloud
from umi_aug.recon.sdf_grid import VoxelSDF, build_scene_sdf, choose_voxel_size, reachable_region
from umi_aug.recon._ref import _reference_sdf


def _scene_cloud(seed=0, n_plane=6000, n_ball=3000):
    """Table plane z = 0 (normals +z) and a ball of radius 0.08 at (0, 0, 0.08) (normals outward)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.3, 0.3, (n_plane, 2))
    xy = xy[np.linalg.norm(xy, axis=1) > 0.02]
    P = np.column_stack([xy, np.zeros(len(xy))])
    Np = np.tile([0.0, 0.0, 1.0], (len(P), 1))
    d = rng.normal(size=(n_ball, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    B = np.array([0, 0, 0.08]) + 0.08 * d
    keep = B[:, 2] > 0.0
    pts = np.concatenate([P, B[keep]])
    nrm = np.concatenate([Np, d[keep]])
    return SceneCloud(pts, np.zeros((len(pts), 3), np.uint8), nrm)


LO, HI = np.array([-0.2, -0.2, -0.05]), np.array([0.2, 0.2, 0.25])


@pytest.fixture(scope="module")
def field():
    cloud = _scene_cloud()
    return cloud, build_scene_sdf(cloud, LO, HI, voxel=0.01)


def test_protocol_and_shapes(field):
    _, sdf = field
    assert isinstance(sdf, SignedDistanceField)
    q = np.random.default_rng(1).uniform(LO, HI, (4, 5, 3))
    d, g = sdf.distance_and_gradient(q)
    check_sdf_output(d, g, q.shape, "VoxelSDF")


def test_grid_vs_reference_lower_bound_and_error(field):
    cloud, sdf = field
    h = sdf.voxel
    q = np.random.default_rng(2).uniform(LO, HI, (1500, 3))
    d, g = sdf.distance_and_gradient(q)
    rd, rg = _reference_sdf(q, cloud, h)
    # the guarantee holds where the sign rule is consistent over the query's cell: check the 8 corners
    lo = sdf.bounds[0]
    i0 = np.floor((q - lo) / h)
    corners = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], float)
    cq = (lo + (i0[:, None, :] + corners[None]) * h).reshape(-1, 3)
    cs = np.sign(_reference_sdf(cq, cloud, h)[0]).reshape(-1, 8)
    consistent = np.all(cs == np.sign(rd)[:, None], axis=1)
    away = (np.abs(rd) > 2 * h) & consistent
    assert away.mean() > 0.5 and consistent.mean() > 0.9
    # conservative: never above the reference; within √3·h below it (interpolation + offset)
    assert np.all(d[away] <= rd[away] + 1e-12)
    assert np.all(d[away] >= rd[away] - math.sqrt(3) * h - 1e-12)
    # sign agrees with the reference except within a couple of voxels of the surface
    assert np.mean(np.sign(d[away]) == np.sign(rd[away])) == 1.0
    # gradient: the interpolant's gradient follows the reference direction
    far = np.abs(rd) > 3 * h
    cos = np.sum(g[far] * rg[far], axis=1) / np.linalg.norm(g[far], axis=1)
    assert np.mean(cos > 0.9) > 0.95
    assert np.mean(np.abs(np.linalg.norm(g[far], axis=1) - 1) < 0.2) > 0.95


def test_gradient_is_the_interpolants_derivative(field):
    _, sdf = field
    q = np.random.default_rng(3).uniform(LO + 0.02, HI - 0.02, (200, 3))
    _, g = sdf.distance_and_gradient(q)
    eps = 1e-6
    fd = np.stack([(sdf.distance_and_gradient(q + eps * e)[0] - sdf.distance_and_gradient(q - eps * e)[0]) / (2 * eps)
                   for e in np.eye(3)], axis=1)
    assert np.median(np.abs(fd - g)) < 1e-6


def test_inflation_outside_grid_and_io(field, tmp_path):
    _, sdf = field
    q = np.array([[0.1, 0.1, 0.2], [0.0, 0.0, 0.6], [0.5, 0.0, 0.1]])
    d, g = sdf.distance_and_gradient(q)
    d2, _ = sdf.inflated(0.02).distance_and_gradient(q)
    np.testing.assert_allclose(d2, d - 0.02)
    # outside the grid: 1-Lipschitz extension, gradient points back
    dc, _ = sdf.distance_and_gradient(np.clip(q, *sdf.bounds))
    np.testing.assert_allclose(d[1:], dc[1:] - np.linalg.norm(q[1:] - np.clip(q[1:], *sdf.bounds), axis=1))
    assert np.isfinite(g).all() and g[1, 2] < 0 and g[2, 0] < 0
    p = sdf.save(tmp_path / "sdf.npz")
    back = VoxelSDF.load(p)
    np.testing.assert_array_equal(back.values, sdf.values)
    assert back.voxel == sdf.voxel and not list(tmp_path.glob("*.tmp-*"))
    with pytest.raises(ReconError):
        sdf.distance_and_gradient(np.array([[np.nan, 0.0, 0.0]]))
    # an empty or cut-off file (a copy that did not finish): one ReconError naming the file, not numpy's EOFError
    for name, data in (("empty.npz", b""), ("cut.npz", p.read_bytes()[:200])):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(ReconError, match=name):
            VoxelSDF.load(tmp_path / name)


def test_carving_makes_seen_space_free():
    cloud = _scene_cloud()
    # flip every normal: the vote alone now calls free space occupied; carving from a camera above fixes it
    bad = SceneCloud(cloud.points, cloud.colors, -cloud.normals)
    cam = np.tile([0.0, 0.0, 0.24], (len(bad.points), 1))
    sel = bad.points[:, 2] < 1e-9  # rays to the plane points
    sdf = build_scene_sdf(bad, LO, HI, voxel=0.01, rays=(cam[sel], bad.points[sel]))
    d, _ = sdf.distance_and_gradient(np.array([[0.12, 0.0, 0.12], [0.0, 0.0, 0.22]]))
    assert np.all(d > 0)
    d0, _ = build_scene_sdf(bad, LO, HI, voxel=0.01).distance_and_gradient(np.array([[0.12, 0.0, 0.12]]))
    assert d0[0] < 0


def test_region_and_voxel_choice():
    T = np.tile(np.eye(4), (30, 1, 1))
    T[:, :3, 3] = np.linspace([0.0, -0.1, 0.45], [0.0, 0.2, 0.15], 30)
    lo, hi = reachable_region(T, 25, math.radians(45))
    assert np.all(lo < T[:26, :3, 3].min(0)) and np.all(hi > T[:26, :3, 3].max(0))
    h = choose_voxel_size(lo, hi, max_voxels=1_000_000)
    n = np.ceil((hi - lo) / h) + 1
    assert 0.004 <= h <= 0.03 and np.prod(n) <= 1.1e6
    with pytest.raises(ReconError):
        choose_voxel_size(hi, lo)


def test_empty_or_tiny_cloud_raises():
    for n in (0, 10):
        c = SceneCloud(np.zeros((n, 3)), np.zeros((n, 3), np.uint8), np.zeros((n, 3)))
        with pytest.raises(ReconError, match="points"):
            build_scene_sdf(c, LO, HI)


def test_queries_per_second(field):
    _, sdf = field
    q = np.random.default_rng(4).uniform(LO, HI, (200_000, 3))
    t = time.perf_counter()
    sdf.distance_and_gradient(q)
    dt = time.perf_counter() - t
    print(f"\nVoxelSDF {sdf.shape}: {len(q) / dt / 1e6:.2f} M queries/s (value + gradient)")
    assert len(q) / dt > 2e5
