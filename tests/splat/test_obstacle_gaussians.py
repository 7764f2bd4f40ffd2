"""Obstacle Gaussians from meshes: surface initialisation, colours, per-asset cache, silhouette coverage, fit."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import numba  # noqa: F401  (the splat extra; a missing install must fail, not skip)
import trimesh

from umi_aug.camera.kb import unproject
from umi_aug.geometry.se3_torch import quat_wxyz_to_matrix
from umi_aug.recon.obstacles import ObstacleAsset, procedural_asset
from umi_aug.splat import render
from umi_aug.splat.compose import PlacedGaussians, render_composed
from umi_aug.splat.obstacle_gaussians import (
    ObstacleGaussianConfig,
    init_obstacle_gaussians,
    obstacle_gaussians,
    obstacle_gaussians_key,
    orbit_intrinsics,
    orbit_poses,
)


def _dc_rgb(g) -> np.ndarray:
    return (g.sh0.double() * 0.28209479177387814 + 0.5).numpy()


def mesh_mask(mesh, T_world_cam: np.ndarray, intr) -> np.ndarray:
    """[H, W] bool: pixel rays that hit the mesh (plain Moller-Trumbore over every triangle, float64)."""
    vv, uu = np.mgrid[0 : intr.height, 0 : intr.width]
    rays, ok = unproject(np.stack([uu, vv], -1).reshape(-1, 2).astype(np.float64), intr)
    d = rays @ T_world_cam[:3, :3].T
    o = T_world_cam[:3, 3]
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    hit = np.zeros(len(d), dtype=bool)
    for s in range(0, len(d), 256):
        dd = d[s : s + 256, None, :]
        p = np.cross(dd, e2[None])
        det = (e1[None] * p).sum(-1)
        inv = 1.0 / np.where(np.abs(det) > 1e-14, det, np.inf)
        tv = o - v0
        u = (tv[None] * p).sum(-1) * inv
        q = np.cross(tv, e1)
        v = (dd * q[None]).sum(-1) * inv
        t = (e2[None] * q[None]).sum(-1) * inv
        hit[s : s + 256] = ((u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)).any(-1)
    return (hit & ok).reshape(intr.height, intr.width)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def test_init_lies_on_the_surface_with_sane_frames(rng):
    n = 3000
    seed = int(rng.integers(1 << 30))
    # box 8 x 8 x 20 cm, bottom at z = 0
    box = procedural_asset("box")
    g = init_obstacle_gaussians(box, n, seed)
    assert g.n == n and g.dtype == torch.float32 and g.sh_degree == 0
    p = g.means.double().numpy()
    r = np.abs(np.stack([p[:, 0] / 0.04, p[:, 1] / 0.04, (p[:, 2] - 0.10) / 0.10], -1))
    assert np.abs(r.max(-1) - 1.0).max() < 1e-5  # on the box surface
    axis = r.argmax(-1)
    normal = np.zeros_like(p)
    normal[np.arange(n), axis] = np.sign(np.stack([p[:, 0], p[:, 1], p[:, 2] - 0.1], -1)[np.arange(n), axis])
    R = quat_wxyz_to_matrix(g.quats_wxyz.double()).numpy()
    np.testing.assert_allclose(np.abs((R[:, :, 2] * normal).sum(-1)), 1.0, atol=1e-5)  # local z = face normal
    s = g.scales.double().numpy()
    cfg = ObstacleGaussianConfig()
    spacing = math.sqrt(box.mesh.area / n)
    np.testing.assert_allclose(s[:, :2], cfg.tangent_scale * spacing, rtol=1e-5)
    np.testing.assert_allclose(s[:, 2], cfg.normal_scale * cfg.tangent_scale * spacing, rtol=1e-5)
    assert np.allclose(g.opacities.numpy(), cfg.opacity)
    # cylinder r 4 cm, 22 cm: on the side (radius 0.04, polygonal: >= 0.04 cos(pi/32)) or on a cap
    cyl = procedural_asset("cylinder")
    p = init_obstacle_gaussians(cyl, n, seed).means.double().numpy()
    rad = np.hypot(p[:, 0], p[:, 1])
    cap = (np.abs(p[:, 2]) < 1e-6) | (np.abs(p[:, 2] - 0.22) < 1e-6)
    side = (rad <= 0.04 + 1e-6) & (rad >= 0.04 * math.cos(math.pi / 32) - 1e-6)
    assert (cap | side).all() and (rad[cap] <= 0.04 + 1e-6).all()
    assert 0.05 < cap.mean() < 0.4  # area-uniform: caps are 2 pi r^2 / (2 pi r^2 + 2 pi r h) = 15 %


def test_colours_from_mesh_or_default(rng):
    mesh = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    side_rgb = rng.integers(0, 256, (6, 3))  # one colour per side (+x, -x, +y, -y, +z, -z), both its triangles
    nrm = np.asarray(mesh.face_normals)
    side = np.argmax(np.abs(nrm), 1) * 2 + (nrm[np.arange(len(nrm)), np.argmax(np.abs(nrm), 1)] < 0)
    fc = np.concatenate([side_rgb[side], np.full((len(side), 1), 255)], 1).astype(np.uint8)
    mesh.visual.face_colors = fc
    asset = ObstacleAsset("painted", mesh)
    g = init_obstacle_gaussians(asset, 500, 1)
    p = g.means.double().numpy()
    ax = np.argmax(np.abs(p), 1)
    expect = side_rgb[ax * 2 + (p[np.arange(len(p)), ax] < 0)] / 255.0
    np.testing.assert_allclose(_dc_rgb(g), expect, atol=1e-5)
    plain = init_obstacle_gaussians(procedural_asset("box"), 50, 0)
    c = _dc_rgb(plain)
    assert np.ptp(c, axis=0).max() < 1e-6 and np.ptp(c[0]) > 0.1  # one saturated default colour
    np.testing.assert_allclose(_dc_rgb(init_obstacle_gaussians(procedural_asset("box"), 50, 3))[0], c[0], atol=1e-6)


def test_cache_hit_returns_identical_gaussians(rng, tmp_path):
    asset = procedural_asset("bottle")
    seed = int(rng.integers(100))
    a = obstacle_gaussians(asset, cache_dir=tmp_path, fit=False, n_gaussians=400, seed=seed)
    files = sorted(tmp_path.iterdir())
    assert [f.name for f in files] == [obstacle_gaussians_key(asset, fit=False, n_gaussians=400, seed=seed) + ".ply"]
    b = obstacle_gaussians(asset, cache_dir=tmp_path, fit=False, n_gaussians=400, seed=seed)
    assert a == b
    assert a == obstacle_gaussians(asset, fit=False, n_gaussians=400, seed=seed)  # no cache: same content
    obstacle_gaussians(asset, cache_dir=tmp_path, fit=False, n_gaussians=400, seed=seed + 1)
    obstacle_gaussians(procedural_asset("bottle", scale=1.1), cache_dir=tmp_path, fit=False, n_gaussians=400,
                       seed=seed)
    assert len(list(tmp_path.iterdir())) == 3  # other seed, other mesh: other files
    files[0].write_bytes(b"not a ply")
    assert obstacle_gaussians(asset, cache_dir=tmp_path, fit=False, n_gaussians=400, seed=seed) == a
    k = obstacle_gaussians_key(procedural_asset("box"), fit=False)
    assert k == obstacle_gaussians_key(procedural_asset("box"), fit=False) and k.startswith("box-")
    assert obstacle_gaussians_key(ObstacleAsset("robosuite/bottle", asset.mesh)).startswith("robosuite_bottle-")


@pytest.mark.parametrize("name", ["box", "mug"])
def test_initialised_gaussians_cover_the_mesh_silhouette(rng, name):
    asset = procedural_asset(name)
    g = obstacle_gaussians(asset, fit=False, n_gaussians=3000, seed=int(rng.integers(100)))
    cfg = ObstacleGaussianConfig(image_size=64, n_views=6)
    intr = orbit_intrinsics(cfg)
    for T in orbit_poses(asset, cfg)[:: 2]:
        gt = mesh_mask(asset.mesh, T, intr)
        assert gt.mean() > 0.03
        m = render(g, T, intr).alpha.numpy() > 0.5
        assert _iou(m, gt) > 0.75, name
    # placed in a scene through the composition: same silhouette at the placed pose
    T_wo = np.eye(4)
    T_wo[:3, 3] = rng.uniform(-1, 1, 3)
    T_wc = T_wo @ orbit_poses(asset, cfg)[1]
    out = render_composed(g.with_sh_degree(0), [PlacedGaussians(g, T_wo, "ob")], T_wc, intr)
    assert out.meta["parts"][1]["n_visible"] > 100


def test_orbit_poses_look_at_the_object():
    asset = procedural_asset("mug")
    cfg = ObstacleGaussianConfig(n_views=9)
    P = orbit_poses(asset, cfg)
    c = asset.mesh.bounds.mean(0)
    assert P.shape == (9, 4, 4)
    to_c = c - P[:, :3, 3]
    np.testing.assert_allclose(np.einsum("vi,vi->v", P[:, :3, 2], to_c / np.linalg.norm(to_c, axis=1)[:, None]), 1,
                               atol=1e-9)
    assert len({round(float(z), 6) for z in P[:, 2, 3]}) == 3  # three rings


@pytest.mark.slow
def test_fit_improves_on_the_initialisation(rng, tmp_path):
    """The short fit (MuJoCo orbit renders + the splat trainer) reproduces the shaded renders better than the
    unshaded initialisation and keeps the silhouette."""
    from umi_aug.splat.obstacle_gaussians import FIT_BACKGROUND, render_orbit_views

    asset = procedural_asset("box")
    cfg = ObstacleGaussianConfig(image_size=48, n_views=8, fit_iterations=200)
    intr = orbit_intrinsics(cfg)
    init = obstacle_gaussians(asset, fit=False, n_gaussians=1200, seed=0, config=cfg)
    fitted = obstacle_gaussians(asset, cache_dir=tmp_path, fit=True, n_gaussians=1200, seed=0, config=cfg)
    assert fitted.n == 1200 and fitted.sh_degree == cfg.fit_sh_degree
    fitted.validate()
    P = orbit_poses(asset, cfg)[[1, 4]]
    imgs, masks = render_orbit_views(asset, P, intr, _dc_rgb(init)[0])

    def psnr(g, i):
        x = render(g, P[i], intr, FIT_BACKGROUND).rgb.numpy().clip(0, 1)  # the orbit views are on white
        return -10 * math.log10(float(((x - imgs[i] / 255.0) ** 2).mean()))

    for i in range(len(P)):
        assert psnr(fitted, i) > psnr(init, i) + 2.0
        assert _iou(render(fitted, P[i], intr).alpha.numpy() > 0.5, masks[i]) > 0.8
    again = obstacle_gaussians(asset, cache_dir=tmp_path, fit=True, n_gaussians=1200, seed=0, config=cfg)
    assert again == fitted
