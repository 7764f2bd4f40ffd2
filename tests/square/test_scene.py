"""Square scene model (umi_aug.square.scene): cached build, composition at a demo's nut pose, errors."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

if importlib.util.find_spec("robosuite") is None or importlib.util.find_spec("mujoco") is None:
    pytest.skip("robosuite / mujoco (robomimic + sim extras) not installed", allow_module_level=True)

from umi_aug.errors import AugmentError, SplatError  # noqa: E402
from umi_aug.square.scene import (SquareSceneConfig, build_square_scene, demo_gaussians,  # noqa: E402
                                          load_scene_gaussians, scene_parts, train_demo_scene)

#: A tiny recipe (32² scan, a few dozen steps): enough for the nut to be where it belongs, not for fidelity.
TINY = SquareSceneConfig(image_size=32, n_scan_views=8, static_iterations=30, static_max_gaussians=1500,
                         n_nut_views=8, nut_image_size=32, nut_iterations=60, nut_max_gaussians=500, sh_degree=0)


@pytest.fixture(scope="module")
def env():
    from umi_aug.errors import SimError
    from umi_aug.square.env import SquareEnv  # imports MuJoCo through umi_aug.sim.gl (offscreen backend)

    try:
        e = SquareEnv(image_size=None)
    except SimError as exc:  # pragma: no cover - machine without offscreen GL
        pytest.skip(str(exc))
    yield e
    e.close()


@pytest.fixture(scope="module")
def states(env):
    out = []
    for seed in (0, 1):
        env.reset(seed=seed)
        out.append(env.get_state())
    return out


@pytest.fixture(scope="module")
def built(env, states, tmp_path_factory):
    work = tmp_path_factory.mktemp("square_scene")
    return work, build_square_scene(work, env, states[0], TINY, progress=False)


def test_build_outputs_and_cache_reuse(built, env, states, monkeypatch):
    work, scene = built
    assert scene.static_ply.is_file() and scene.nut_ply.is_file()
    assert scene.scan_T_world_cam.shape == (TINY.n_scan_views, 4, 4)
    for part in ("static", "nut"):
        r = scene.report[part]
        assert r["gaussians"] > 0 and r["views"] > 0 and np.isfinite(r["heldout_psnr"]) and r["train_seconds"] > 0
        assert (work / part / "train" / "contact_sheet.png").is_file()
    np.testing.assert_allclose(scene.T_world_nut_ref, _nut_pose(env, states[0]), atol=1e-12)
    import umi_aug.splat.train as train_mod

    def no_training(*a, **k):
        raise AssertionError("retrained although the stages are up to date")

    monkeypatch.setattr(train_mod, "train_splat", no_training)
    again = build_square_scene(work, env.env_meta, states[0], TINY, progress=False)  # env_meta: same key, no env
    assert again.key == scene.key and again.static_ply == scene.static_ply
    assert again.report == scene.report
    with pytest.raises(AssertionError, match="retrained"):  # another config does train (the guard is live)
        build_square_scene(work / "other", env, states[0], SquareSceneConfig(**{**TINY.__dict__, "seed": 1}),
                           progress=False)


def _nut_pose(env, state):
    from umi_aug.square.scan import body_pose, data_at_state

    return body_pose(env.model, data_at_state(env.model, state))


def test_composition_puts_the_nut_where_the_simulator_has_it(built, env, states):
    """At ANOTHER demo's nut pose: the composed nut Gaussians sit on the simulator's nut, and a render of
    static + nut matches the simulator's nut pixels better than the static scene alone."""
    import torch

    from umi_aug.geometry import look_at_rotation
    from umi_aug.splat.compose import render_composed, rgb_to_uint8
    from umi_aug.splat.renderer import render
    from umi_aug.square.camera import wrist_intrinsics
    from umi_aug.square.scan import ScanRenderer, hidden_geom_ids

    _, scene = built
    s1 = states[1]
    T_nut = _nut_pose(env, s1)
    assert np.linalg.norm(T_nut[:3, 3] - scene.T_world_nut_ref[:3, 3]) > 0.01  # a different nut pose
    static, nut = load_scene_gaussians(scene)
    g = demo_gaussians(scene, T_nut)
    assert g.n == static.n + nut.n
    w = torch.sigmoid(g.logit_opacities[static.n:]).double()
    centroid = (g.means[static.n:].double() * w[:, None]).sum(0) / w.sum()
    # the nut body origin is the ring's centre; the handle shifts the centroid along nut +x by 1-3 cm
    off = T_nut[:3, :3].T @ (centroid.numpy() - T_nut[:3, 3])
    assert abs(off[1]) < 0.01 and abs(off[2]) < 0.01 and 0.0 < off[0] < 0.04, off
    # renders from above the nut vs the simulator (robot hidden)
    intr = wrist_intrinsics(TINY.image_size)
    T_cam = np.eye(4)  # 22 cm above the nut, 3 cm to the side, looking at it
    T_cam[:3, 3] = T_nut[:3, 3] + np.array([0.03, 0.0, 0.22])
    T_cam[:3, :3] = look_at_rotation(T_cam[:3, 3], T_nut[:3, 3], np.array([1.0, 0.0, 0.0]))
    with ScanRenderer(env.model, "scene", intr) as r:
        gt = r.render(s1, T_cam[None])
    nut_px = np.isin(gt.geom_id[0], np.setdiff1d(np.arange(env.model.ngeom), hidden_geom_ids(env.model, "nut")))
    assert nut_px.sum() > 10
    st, placed = scene_parts(scene, T_nut)
    comp = rgb_to_uint8(render_composed(st, placed, T_cam, intr).rgb).astype(float)
    ref = rgb_to_uint8(render(g, T_cam, intr).rgb).astype(float)
    alone = rgb_to_uint8(render(static, T_cam, intr).rgb).astype(float)
    assert np.abs(comp - ref).max() <= 2  # composition == concatenated reference
    err_comp = np.abs(comp - gt.rgb[0])[nut_px].mean()
    err_alone = np.abs(alone - gt.rgb[0])[nut_px].mean()
    assert err_comp < 0.7 * err_alone, (err_comp, err_alone)


def test_bad_inputs_are_one_clear_error_and_keep_the_cache(built, env, states):
    work, scene = built
    with pytest.raises(AugmentError, match=r"state0 has shape \[44\].*= 45 values"):
        build_square_scene(work, env, states[0][:-1], TINY, progress=False)
    assert scene.static_ply.is_file() and scene.nut_ply.is_file()  # nothing cleared
    with pytest.raises(AugmentError, match="n_scan_views"):
        build_square_scene(work, env, states[0], SquareSceneConfig(**{**TINY.__dict__, "n_scan_views": 1}))
    with pytest.raises(AugmentError, match="env_meta dict or an MJCF string"):
        build_square_scene(work / "x", 42, states[0], TINY)
    T = np.eye(4)
    T[0, 0] = 2.0
    with pytest.raises(SplatError, match="rigid"):
        demo_gaussians(scene, T)


def test_per_demo_scene_trains_on_the_demo_scene(built, env, states, monkeypatch):
    work, _ = built
    d = train_demo_scene(work, env, states[1], TINY, progress=False)
    assert d.ply.is_file() and d.scan_T_world_cam.shape == (TINY.n_scan_views, 4, 4)
    assert d.report["gaussians"] > 0 and np.isfinite(d.report["heldout_psnr"])
    import umi_aug.splat.train as train_mod

    monkeypatch.setattr(train_mod, "train_splat", lambda *a, **k: (_ for _ in ()).throw(AssertionError("retrained")))
    assert train_demo_scene(work, env, states[1], TINY, progress=False).key == d.key


def test_nut_orbit_size_follows_the_policy_lens_density():
    from umi_aug.square.camera import wrist_intrinsics

    for size in (84, 224):
        c = SquareSceneConfig(image_size=size)
        expect = wrist_intrinsics(size).fx * np.radians(c.nut_fov_deg) * c.nut_oversample
        assert abs(c.nut_size - expect) <= 0.5 and c.nut_size >= 16
    assert SquareSceneConfig(nut_image_size=50).nut_size == 50
    with pytest.raises(AugmentError, match="nut_oversample"):
        SquareSceneConfig(nut_oversample=0.0).check()
