"""Stage cache (skip when up to date, rerun when the config or an input changes) and config validation."""

from __future__ import annotations

import json

import pytest

from umi_aug.augment.cache import read_manifest, run_stage
from umi_aug.augment.config import AugmentConfig, config_hash
from umi_aug.errors import AugmentError


def _fn(calls, text):
    def fn(out):
        calls.append(text)
        (out / "a.txt").write_text(text)
        return {"a": "a.txt"}, ["a.txt"], {"n": len(calls)}
    return fn


def test_stage_runs_once_then_skips_and_reruns_on_change(tmp_path):
    calls = []
    r1 = run_stage("s", tmp_path, {"x": 1}, {"in": "k0"}, _fn(calls, "one"))
    assert not r1.skipped and calls == ["one"] and r1.path("a").read_text() == "one"
    r2 = run_stage("s", tmp_path, {"x": 1}, {"in": "k0"}, _fn(calls, "two"))
    assert r2.skipped and r2.key == r1.key and calls == ["one"] and r2.path("a").read_text() == "one"
    r3 = run_stage("s", tmp_path, {"x": 2}, {"in": "k0"}, _fn(calls, "three"))  # config changed
    assert not r3.skipped and r3.key != r1.key and r3.path("a").read_text() == "three"
    r4 = run_stage("s", tmp_path, {"x": 2}, {"in": "k1"}, _fn(calls, "four"))  # an input changed
    assert not r4.skipped and r4.key != r3.key
    (tmp_path / "s" / "a.txt").unlink()  # an output vanished → rerun
    r5 = run_stage("s", tmp_path, {"x": 2}, {"in": "k1"}, _fn(calls, "five"))
    assert not r5.skipped and calls[-1] == "five"
    assert read_manifest(tmp_path / "s")["key"] == r5.key


def test_stage_without_manifest_keeps_partial_outputs(tmp_path):
    def interrupted(out):
        (out / "partial.bin").write_text("resume me")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):  # an interrupted run of the same key (its pending.json names it)
        run_stage("s", tmp_path, {}, {}, interrupted)

    def fn(out):
        assert (out / "partial.bin").read_text() == "resume me"  # an interrupted run's files are kept
        (out / "a.txt").write_text("x")
        return {}, ["a.txt"], {}

    run_stage("s", tmp_path, {}, {}, fn)


def test_stage_missing_output_raises(tmp_path):
    with pytest.raises(AugmentError, match="not written"):
        run_stage("s", tmp_path, {}, {}, lambda out: ({}, ["nope.txt"], {}))
    assert read_manifest(tmp_path / "s") is None


def test_config_hash_and_validation():
    a, b = AugmentConfig(), AugmentConfig(seed=1)
    assert config_hash(a) == config_hash(AugmentConfig()) != config_hash(b)
    assert json.dumps(config_hash(a))
    assert AugmentConfig(mode="both").modes == ("freespace", "obstacle")
    for bad in (dict(mode="nope"), dict(n_per_demo=-1), dict(cone_radius_m=0.0), dict(executor="dask"),
                dict(image_size=0)):
        with pytest.raises(AugmentError):
            AugmentConfig(**bad)


def test_obstacle_fit_iterations_in_the_keys_only_when_changed():
    """``ObstacleConfig.fit_iterations`` at its default hashes like the settings before it existed (earlier work
    folders and exports keep their keys); another value changes the key; the default is the fit's own default."""
    import dataclasses

    from umi_aug.augment.config import OBSTACLE_FIT_ITERATIONS, ObstacleConfig, obstacle_key
    from umi_aug.splat.obstacle_gaussians import ObstacleGaussianConfig

    assert OBSTACLE_FIT_ITERATIONS == ObstacleGaussianConfig().fit_iterations
    o = ObstacleConfig()
    before = {f.name: getattr(o, f.name) for f in dataclasses.fields(o) if f.name != "fit_iterations"}
    assert config_hash(obstacle_key(o)) == config_hash(before)
    assert config_hash(obstacle_key(ObstacleConfig(fit_iterations=50))) != config_hash(before)
    for bad in (0, -3, 2.5, True):
        with pytest.raises(AugmentError, match="fit_iterations"):
            AugmentConfig(obstacle=ObstacleConfig(fit_iterations=bad))


def test_render_min_transmittance_setting():
    """The export's early-termination threshold: defaults to the renderer's (INRIA / gsplat 1e-4), refused out of
    (0, 1) in one line naming the field, and part of the export's run key when it is not the default (a resumed
    export never mixes frames rendered with two thresholds)."""
    from umi_aug.augment.exporter import _run_key
    from umi_aug.splat._constants import TRANSMITTANCE_THRESHOLD

    from umi_aug.augment.config import DEFAULT_RENDER_MIN_TRANSMITTANCE

    assert AugmentConfig().render_min_transmittance == DEFAULT_RENDER_MIN_TRANSMITTANCE == TRANSMITTANCE_THRESHOLD
    for bad in (0.0, 1.0, -1e-3, float("nan"), True, "0.01"):
        with pytest.raises(AugmentError, match="render_min_transmittance"):
            AugmentConfig(render_min_transmittance=bad)
    keys = {_run_key(AugmentConfig(render_min_transmittance=t), "fp") for t in (1e-4, 1.0 / 255.0, 0.01)}
    assert len(keys) == 3


def test_render_min_transmittance_reaches_the_new_frames(aug_assets):
    """``render_view`` (the new frames of the export, the on-the-fly Dataset and square) renders with the config's
    threshold: the same pixels as ``render_composed`` at that threshold, other pixels than the default where
    pixels terminate early."""
    import dataclasses

    import numpy as np

    from umi_aug.augment.render import render_view
    from umi_aug.splat.compose import render_composed, rgb_to_uint8

    d = aug_assets.augmentable[0]
    T = aug_assets.demo(d).T_world_cam[0]
    cfg = aug_assets.cfg
    views = {}
    for t in (1e-4, 0.3):
        handle = dataclasses.replace(aug_assets, cfg=dataclasses.replace(cfg, render_min_transmittance=t))
        handle.memo = aug_assets.memo  # the loaded scene, shared
        views[t] = render_view(handle, T)
        want = render_composed(aug_assets.gaussians, [], T, aug_assets.policy_intrinsics, background=(0.0, 0.0, 0.0),
                               near=cfg.render_near_m, far=cfg.render_far_m, min_transmittance=t)
        assert np.array_equal(views[t], rgb_to_uint8(want.rgb))
    assert not np.array_equal(views[1e-4], views[0.3])


def test_splat_stage_scale_reg_reaches_the_trainer():
    """``SplatStageConfig.scale_reg`` is passed to ``SplatTrainConfig`` (an ``extra`` entry of the same name wins),
    is part of the stage's hashed config, and is refused when negative or not a finite number."""
    from umi_aug.augment import SplatStageConfig
    from umi_aug.splat.train import SplatTrainConfig

    sc = SplatStageConfig(iterations=10, max_gaussians=100, scale_reg=0.5)
    tcfg = SplatTrainConfig(seed=0, **sc.train_kwargs())
    assert (tcfg.scale_reg, tcfg.iterations, tcfg.max_gaussians) == (0.5, 10, 100)
    assert SplatTrainConfig(**SplatStageConfig(scale_reg=0.5, extra={"scale_reg": 0.2}).train_kwargs()).scale_reg == 0.2
    assert config_hash(SplatStageConfig(scale_reg=0.5)) != config_hash(SplatStageConfig(scale_reg=0.01))
    # the keys: scale_reg at the trainer's 0.01 hashes like the settings before the field existed (stage caches and
    # exports trained that way keep their keys); any other value changes the key
    import dataclasses

    from umi_aug.augment.config import TRAINER_SCALE_REG, splat_key

    assert SplatTrainConfig().scale_reg == TRAINER_SCALE_REG
    old = SplatStageConfig(scale_reg=TRAINER_SCALE_REG)
    before = {f.name: getattr(old, f.name) for f in dataclasses.fields(old)
              if f.name not in ("scale_reg", "coarse_downscale")}
    assert config_hash(splat_key(old)) == config_hash(before)
    assert config_hash(splat_key(SplatStageConfig(scale_reg=1.0))) != config_hash(before)
    for bad in (-0.1, float("nan"), float("inf"), True, "1"):
        with pytest.raises(AugmentError, match="scale_reg"):
            AugmentConfig(splat=SplatStageConfig(scale_reg=bad))
    # coarse-to-fine: full size (1) hashes like the settings before the field existed; 2 is a new key, reaches the
    # trainer, and must divide the image side
    assert SplatStageConfig().coarse_downscale == 1 and SplatTrainConfig().coarse_downscale == 1
    assert "coarse_downscale" not in splat_key(SplatStageConfig(scale_reg=TRAINER_SCALE_REG))
    assert config_hash(splat_key(SplatStageConfig(scale_reg=TRAINER_SCALE_REG, coarse_downscale=2))) != \
        config_hash(before)
    assert SplatTrainConfig(**SplatStageConfig(coarse_downscale=2).train_kwargs()).coarse_stop_step > 0
    for bad in (0, 3, 2.0, True):
        with pytest.raises(AugmentError, match="coarse_downscale"):
            AugmentConfig(image_size=224, splat=SplatStageConfig(coarse_downscale=bad))
