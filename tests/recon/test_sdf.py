"""Voxel SDF vs its brute-force reference (same sign rule), conservativeness, gradients, speed, failures."""

import math

import numpy as np
import pytest

from umi_aug.errors import ReconError
from umi_aug.geometry.sdf import SignedDistanceField, check_sdf_output
from umi_aug.recon.cloud import SceneCloud
from umi_aug.recon.sdf_grid import VoxelSDF, build_scene_sdf, choose_voxel_size, reachable_region
from umi_aug.recon._ref import _reference_sdf, _reference_unsigned_sdf


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


def test_many_queries_at_once(field):
    """200k queries in one call (chunked inside) are finite and match the same queries asked in small batches.
    Their rate is ``benchmarks/recon.py``'s (no unit test times anything)."""
    _, sdf = field
    q = np.random.default_rng(4).uniform(LO - 0.1, HI + 0.1, (200_000, 3))
    d, g = sdf.distance_and_gradient(q)
    assert np.isfinite(d).all() and np.isfinite(g).all()
    d2, g2 = zip(*(sdf.distance_and_gradient(q[a:a + 997]) for a in range(0, len(q), 997)))
    np.testing.assert_array_equal(d, np.concatenate(d2))
    np.testing.assert_array_equal(g, np.concatenate(g2))


@pytest.mark.parametrize("seed,n_points", [(0, 9000), (1, 50), (2, 51), (3, 300)])
def test_unsigned_field_matches_folded_signed_field(seed, n_points):
    """``signed=False`` (one nearest point, no vote) against the signed field folded to its magnitude (every vote
    taken) on fresh random clouds, from the fewest points a cloud may have (50) to thousands, with
    inflation; and its node values against brute-force distances. Equal to rounding: 1e-15 m."""
    rng = np.random.default_rng(seed)
    base = _scene_cloud(seed)
    pick = rng.choice(len(base.points), min(n_points, len(base.points)), replace=False)
    pts = base.points[pick] + rng.normal(0, 0.01, (len(pick), 3))
    nrm = rng.normal(size=(len(pick), 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    cloud = SceneCloud(pts, np.zeros((len(pts), 3), np.uint8), nrm)
    inflation = float(rng.uniform(0.0, 0.02))
    fast = build_scene_sdf(cloud, LO, HI, voxel=0.013, inflation=inflation, signed=False)
    ref = _reference_unsigned_sdf(cloud, LO, HI, 0.013, inflation)
    assert fast.shape == ref.shape and fast.inflation == ref.inflation
    np.testing.assert_array_equal(fast.origin, ref.origin)
    assert np.isfinite(fast.values).all()
    np.testing.assert_allclose(fast.values, ref.values, rtol=0, atol=1e-15)
    n = np.array(fast.shape)
    nodes = LO + 0.013 * np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, 3)
    sub = rng.choice(len(nodes), 2000, replace=False)
    brute = np.sqrt(((nodes[sub, None, :] - pts[None]) ** 2).sum(-1)).min(1) - math.sqrt(3.0) / 2.0 * 0.013
    np.testing.assert_allclose(fast.values.reshape(-1)[sub], brute, rtol=0, atol=1e-12)
    q = rng.uniform(LO - 0.05, HI + 0.05, (500, 3))
    d_fast, g_fast = fast.distance_and_gradient(q)
    d_ref, g_ref = ref.distance_and_gradient(q)
    np.testing.assert_allclose(d_fast, d_ref, rtol=0, atol=1e-14)
    np.testing.assert_allclose(g_fast, g_ref, rtol=0, atol=1e-11)


def test_unsigned_field_ignores_rays():
    """Visibility carving only decides signs: the unsigned field is the same with and without rays."""
    cloud = _scene_cloud(4, 2000, 800)
    cam = np.tile([0.0, 0.0, 0.6], (50, 1))
    rays = (cam, cloud.points[:50])
    a = build_scene_sdf(cloud, LO, HI, voxel=0.02, signed=False)
    b = build_scene_sdf(cloud, LO, HI, voxel=0.02, signed=False, rays=rays)
    np.testing.assert_array_equal(a.values, b.values)
    assert (a.values >= -math.sqrt(3.0) / 2.0 * 0.02 - 1e-15).all()


def test_save_load_round_trip_uncompressed(tmp_path, field):
    """``VoxelSDF.save`` writes a plain (stored, not deflated) ``.npz`` that loads to the same field."""
    import zipfile

    _, sdf = field
    path = sdf.save(tmp_path / "f.npz")
    with zipfile.ZipFile(path) as z:
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_STORED}
    back = VoxelSDF.load(path)
    np.testing.assert_array_equal(back.values, sdf.values)
    np.testing.assert_array_equal(back.origin, sdf.origin)
    assert (back.voxel, back.inflation) == (sdf.voxel, sdf.inflation)
