"""Scene + obstacle composition vs the concatenate-and-render reference, exact SH rotation, render cache."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

import numba  # noqa: F401  (the splat extra; a missing install must fail, not skip)

from umi_aug.errors import SplatError
from umi_aug.geometry import make_pose, pose_inverse, so3_exp
from umi_aug.splat import Gaussians, eval_sh, render
from umi_aug.splat.compose import (
    PlacedGaussians,
    RenderCache,
    render_cache_key,
    render_composed,
    rgb_to_uint8,
    sh_rotation_matrices,
    transform_gaussians,
)
from umi_aug.splat.scenes import random_gaussians
from tests.splat._helpers import gopro_small, random_kb_intrinsics, random_pose

FILTERS = ["inria", "mip", "none"]


def _obstacle(rng, intr, T_wc, n=25, theta_range=(0.0, 2.0), dtype=torch.float64) -> PlacedGaussians:
    """An obstacle set seen by the camera (ray angles up to ``theta_range[1]``, i.e. past 90 deg), expressed in a
    random object frame at a random rigid pose."""
    g_world = random_gaussians(n, rng, intr, T_wc, theta_max=theta_range[1], depth_range=(0.3, 2.0), dtype=dtype)
    if theta_range[0] > 0:  # push every mean beyond theta_range[0] (e.g. behind the camera)
        p_cam = (g_world.means - torch.as_tensor(T_wc[:3, 3], dtype=dtype)) @ torch.as_tensor(T_wc[:3, :3], dtype=dtype)
        p_cam[:, :2] *= 0.05
        p_cam[:, 2] = -p_cam[:, 2].abs() - 0.3
        g_world.means = p_cam @ torch.as_tensor(T_wc[:3, :3], dtype=dtype).T + torch.as_tensor(T_wc[:3, 3], dtype=dtype)
    T_wo = random_pose(rng)
    g_obj = transform_gaussians(g_world, pose_inverse(T_wo))
    return PlacedGaussians(g_obj, T_wo, f"obj{int(rng.integers(1 << 30))}")


def _reference(scene, obstacles, T, intr, bg, **kw):
    parts = [scene] + [transform_gaussians(o.gaussians, o.T_world_obj) for o in obstacles]
    return render(Gaussians.cat(parts), T, intr, bg, **kw)


@pytest.mark.parametrize("filt", FILTERS)
def test_composed_matches_concatenated_reference_float64(rng, filt):
    for which in ("gopro", "random"):
        intr = gopro_small() if which == "gopro" else random_kb_intrinsics(rng)
        T = random_pose(rng)
        scene = random_gaussians(60, rng, intr, T, theta_max=2.0)
        obstacles = [_obstacle(rng, intr, T), _obstacle(rng, intr, T, n=15),
                     _obstacle(rng, intr, T, n=10, theta_range=(2.2, 2.0))]  # the last one: behind the camera
        bg = rng.uniform(0, 1, 3)
        out = render_composed(scene, obstacles, T, intr, bg, filter=filt)
        ref = _reference(scene, obstacles, T, intr, bg, filter=filt)
        assert out.meta["parts"][1]["n_visible"] > 5
        if which == "gopro":  # theta_max ~104 deg: the set behind the camera is culled
            assert out.meta["parts"][3]["n_visible"] == 0
        assert torch.equal(out.meta["ids"].sort().values, ref.meta["ids"].sort().values)
        for name in ("rgb", "alpha", "ray_depth"):
            a, b = getattr(out, name), getattr(ref, name)
            assert torch.isfinite(a).all()
            assert (a - b).abs().max().item() < 1e-9, name


def test_composed_float32_close_to_reference(rng):
    intr = gopro_small()
    T = random_pose(rng)
    scene = random_gaussians(80, rng, intr, T, theta_max=2.0, dtype=torch.float32)
    obstacles = [_obstacle(rng, intr, T, dtype=torch.float32), _obstacle(rng, intr, T, dtype=torch.float32)]
    bg = rng.uniform(0, 1, 3)
    out = render_composed(scene, obstacles, T, intr, bg)
    ref = _reference(scene.to(torch.float64), [PlacedGaussians(o.gaussians.to(torch.float64), o.T_world_obj, o.key)
                                               for o in obstacles], T, intr, bg)
    assert out.rgb.dtype == torch.float32 and torch.isfinite(out.rgb).all()
    err = (out.rgb.double() - ref.rgb).abs().amax(-1)
    # float32 may take the other branch at the 1/255 alpha threshold on rare pixels (as in test_render)
    assert (err > 1e-4).float().mean().item() < 0.01
    assert err.median().item() < 1e-5


def test_no_obstacles_is_plain_render_bitwise(rng):
    intr = gopro_small()
    T = random_pose(rng)
    scene = random_gaussians(70, rng, intr, T, theta_max=2.0, dtype=torch.float32)
    out = render_composed(scene, [], T, intr, (0.1, 0.2, 0.3))
    ref = render(scene, T, intr, (0.1, 0.2, 0.3))
    assert torch.equal(out.rgb, ref.rgb) and torch.equal(out.alpha, ref.alpha)
    assert torch.equal(out.ray_depth, ref.ray_depth)


def test_composition_never_builds_the_scene_copy(rng, monkeypatch):
    intr = gopro_small()
    T = random_pose(rng)
    scene = random_gaussians(50, rng, intr, T)
    before = {k: v.clone() for k, v in scene.tensors().items()}
    ptrs = {k: v.data_ptr() for k, v in scene.tensors().items()}
    obstacles = [_obstacle(rng, intr, T)]

    def boom(*a, **k):
        raise AssertionError("the composition must not concatenate/transform Gaussians")

    monkeypatch.setattr(Gaussians, "cat", staticmethod(boom))
    monkeypatch.setattr("umi_aug.splat.compose.transform_gaussians", boom)
    out = render_composed(scene, obstacles, T, intr)
    assert out.meta["n_visible"] > 0
    for k, v in scene.tensors().items():
        assert v.data_ptr() == ptrs[k] and torch.equal(v, before[k])


def test_sh_rotation_is_exact(rng):
    for _ in range(3):
        R = so3_exp(rng.normal(size=3) * 2.0)
        sh = torch.as_tensor(rng.normal(size=(7, 16, 3)))
        mats = sh_rotation_matrices(R, 3)
        for l, M in enumerate(mats, start=1):
            assert M.shape == (2 * l + 1, 2 * l + 1)
            np.testing.assert_allclose(M @ M.T, np.eye(2 * l + 1), atol=1e-12)  # orthogonal (real SH basis)
        sh_w = sh.clone()
        for l, M in enumerate(mats, start=1):
            a, b = l * l, (l + 1) * (l + 1)
            sh_w[:, a:b] = torch.einsum("jk,nkc->njc", torch.as_tensor(M), sh[:, a:b])
        d = torch.as_tensor(rng.normal(size=(7, 3)))
        d = d / d.norm(dim=-1, keepdim=True)
        c_world = eval_sh(3, sh_w, d)
        c_obj = eval_sh(3, sh, d @ torch.as_tensor(R))  # R^T d
        assert (c_world - c_obj).abs().max().item() < 1e-12
    assert sh_rotation_matrices(np.eye(3), 0) == []


def test_transform_gaussians_geometry_and_round_trip(rng):
    intr = gopro_small()
    g = random_gaussians(20, rng, intr, None)
    g.quats_wxyz[0] = 0.0  # zero norm = identity rotation (renderer convention)
    T = make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3))
    w = transform_gaussians(g, T)
    np.testing.assert_allclose(w.means.numpy(), g.means.numpy() @ T[:3, :3].T + T[:3, 3], atol=1e-12)
    from umi_aug.geometry.se3_torch import quat_wxyz_to_matrix

    Rw = quat_wxyz_to_matrix(w.quats_wxyz).numpy()
    Rl = quat_wxyz_to_matrix(g.quats_wxyz).numpy()
    np.testing.assert_allclose(Rw, T[:3, :3] @ Rl, atol=1e-12)
    assert torch.equal(w.log_scales, g.log_scales) and torch.equal(w.sh0, g.sh0)
    back = transform_gaussians(w, pose_inverse(T))
    np.testing.assert_allclose(back.sh_rest.numpy(), g.sh_rest.numpy(), atol=1e-12)
    np.testing.assert_allclose(back.means.numpy(), g.means.numpy(), atol=1e-12)


def test_compose_errors(rng):
    intr = gopro_small()
    g = random_gaussians(5, rng, intr, None)
    with pytest.raises(SplatError, match="rigid"):
        PlacedGaussians(g, np.diag([2.0, 1, 1, 1]), "scaled")
    with pytest.raises(SplatError, match="key"):
        PlacedGaussians(g, np.eye(4), "")
    with pytest.raises(SplatError, match="shape"):
        PlacedGaussians(g, np.eye(3), "x")
    with pytest.raises(SplatError, match="unsupported keyword"):
        render_composed(g, [], np.eye(4), intr, projection="torch")
    with pytest.raises(SplatError, match="PlacedGaussians"):
        render_composed(g, [g], np.eye(4), intr)
    with pytest.raises(SplatError, match="non-finite"):
        render_composed(g, [], np.full((4, 4), np.nan), intr)


# ------------------------------------------------------------------------------------------------ render cache
def _cache_inputs(rng):
    intr = gopro_small(32, 24)
    T = random_pose(rng)
    scene = random_gaussians(40, rng, intr, T, dtype=torch.float32)
    ob = _obstacle(rng, intr, T, n=10, dtype=torch.float32)
    return intr, T, scene, ob


def test_cache_hits_misses_and_content(rng):
    intr, T, scene, ob = _cache_inputs(rng)
    cache = RenderCache()
    img = cache.render_rgb(scene, "s", T, intr, [ob], (0.2, 0.3, 0.4))
    assert img.dtype == np.uint8 and img.shape == (24, 32, 3) and not img.flags.writeable
    expect = rgb_to_uint8(render_composed(scene, [ob], T, intr, (0.2, 0.3, 0.4)).rgb)
    np.testing.assert_array_equal(img, expect)
    again = cache.render_rgb(scene, "s", T.copy(), intr, [ob], (0.2, 0.3, 0.4))
    assert again is img
    st = cache.stats
    assert (st["hits"], st["misses"], st["entries"], st["bytes"]) == (1, 1, 1, img.nbytes)
    cache.render_rgb(scene, "s", T, intr, [], (0.2, 0.3, 0.4))  # no obstacle: another key
    assert cache.stats["misses"] == 2


def test_cache_lru_eviction_by_bytes(rng):
    intr, T, scene, _ = _cache_inputs(rng)
    nb = 24 * 32 * 3
    cache = RenderCache(max_bytes=int(2.5 * nb))
    poses = [T.copy() for _ in range(3)]
    for i, P in enumerate(poses):
        P[0, 3] += 0.01 * i
    cache.render_rgb(scene, "s", poses[0], intr)
    cache.render_rgb(scene, "s", poses[1], intr)
    cache.render_rgb(scene, "s", poses[0], intr)  # touch 0: 1 is now least recently used
    cache.render_rgb(scene, "s", poses[2], intr)  # evicts 1
    st = cache.stats
    assert st["entries"] == 2 and st["bytes"] == 2 * nb and st["evictions"] == 1 and st["hits"] == 1
    cache.render_rgb(scene, "s", poses[0], intr)
    assert cache.stats["hits"] == 2
    cache.render_rgb(scene, "s", poses[1], intr)
    assert cache.stats["misses"] == 4
    tiny = RenderCache(max_bytes=nb - 1)  # an image larger than the budget is returned but not kept
    tiny.render_rgb(scene, "s", T, intr)
    assert tiny.stats["entries"] == 0 and tiny.stats["bytes"] == 0


def test_cache_disk_store_shared_between_instances(rng, tmp_path, caplog):
    intr, T, scene, ob = _cache_inputs(rng)
    a = RenderCache(disk_dir=tmp_path)
    img = a.render_rgb(scene, "s", T, intr, [ob])
    files = sorted(tmp_path.iterdir())
    assert len(files) == 1 and files[0].suffix == ".npy"  # no temporary left behind
    b = pickle.loads(pickle.dumps(a))  # what a DataLoader worker gets: settings, no memory entries
    assert len(b) == 0 and b.disk_dir == tmp_path
    img_b = b.render_rgb(scene, "s", T, intr, [ob])
    np.testing.assert_array_equal(img_b, img)
    assert b.stats["disk_hits"] == 1 and b.stats["misses"] == 0
    files[0].write_bytes(b"garbage")  # a corrupt entry is re-rendered and rewritten
    c = RenderCache(disk_dir=tmp_path)
    img_c = c.render_rgb(scene, "s", T, intr, [ob])
    np.testing.assert_array_equal(img_c, img)
    assert c.stats["misses"] == 1 and "unreadable" in caplog.text
    np.testing.assert_array_equal(np.load(files[0]), img)


def test_cache_keys_deterministic_and_discriminating(rng):
    intr, T, scene, ob = _cache_inputs(rng)
    k0 = render_cache_key("s", T, intr, [ob], None)
    assert k0 == render_cache_key("s", torch.as_tensor(T.copy()), intr, [ob], None)
    Tz = T.copy()
    Tz[3, :3] = -0.0
    assert render_cache_key("s", Tz, intr, [ob]) == k0
    T2 = T.copy()
    T2[1, 3] += 1e-9
    ob2 = PlacedGaussians(ob.gaussians, ob.T_world_obj @ make_pose(np.eye(3), [0.0, 0.0, 1e-6]), ob.key)
    others = {
        render_cache_key("t", T, intr, [ob]),
        render_cache_key("s", T2, intr, [ob]),
        render_cache_key("s", T, gopro_small(32, 25), [ob]),
        render_cache_key("s", T, intr, []),
        render_cache_key("s", T, intr, [ob2]),
        render_cache_key("s", T, intr, [PlacedGaussians(ob.gaussians, ob.T_world_obj, "other")]),
        render_cache_key("s", T, intr, [ob], (0.0, 0.0, 0.0)),
        render_cache_key("s", T, intr, [ob], None, {"filter": "mip"}),
    }
    assert k0 not in others and len(others) == 8
    c1 = RenderCache(render_kwargs={"filter": "mip"})
    assert c1.key("s", T, intr, [ob]) == render_cache_key("s", T, intr, [ob], None, {"filter": "mip"})
    with pytest.raises(SplatError, match="render_kwargs"):
        RenderCache(render_kwargs={"projection": "torch"})


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_composed_pixels_equal_the_full_composed_render(rng, dtype):
    """``render_composed(pixels=)`` (the export leaves out what the gripper overlay covers): the kept pixels bit for
    bit, the rest the background; obstacles past 90 degrees and behind the camera included."""
    from tests.splat.test_render_pixels import _check, _masks

    intr = random_kb_intrinsics(rng, 64, 48)
    T = random_pose(rng)
    scene = random_gaussians(150, rng, intr, T, theta_max=2.0, dtype=dtype)
    obstacles = [_obstacle(rng, intr, T, dtype=dtype), _obstacle(rng, intr, T, n=10, theta_range=(2.2, 2.0),
                                                                 dtype=dtype)]
    bg = rng.uniform(0, 1, 3)
    full = render_composed(scene, obstacles, T, intr, bg)
    for keep in _masks(rng, 48, 64):
        part = render_composed(scene, obstacles, T, intr, bg, pixels=keep)
        _check(full, part, keep, bg)
    with pytest.raises(SplatError, match=r"pixels: expected a bool mask of shape \(48, 64\)"):
        render_composed(scene, obstacles, T, intr, bg, pixels=np.ones((64, 48), bool))
