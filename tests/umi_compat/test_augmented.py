"""Issue #30: on-the-fly augmentation through UMI's construction path (``hydra.utils.instantiate`` of task/umi.yaml's
dataset block + ``aug=freespace``) on the small synthetic session shared with tests/augment (64² images)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.umi_compat.conftest import umi_task_dataset_kwargs


@pytest.mark.slow
def test_freespace_augmentation_through_umis_construction_path(aug_session, tmp_path):
    import hydra
    from omegaconf import OmegaConf

    kw = umi_task_dataset_kwargs(aug_session / "dataset.zarr.zip", size=64)
    node = OmegaConf.create({"_target_": "umi_aug.umi_compat.UmiAugDataset", **kw, "aug": "freespace",
                             "work_dir": str(tmp_path / "work"), "splat_iterations": 0, "aug_ratio": 0.5})
    ds = hydra.utils.instantiate(node)
    n_orig = len(ds) - ds.n_augmented
    assert ds.n_augmented == n_orig > 0  # ratio 0.5: as many augmented slots as original samples
    sm = kw["shape_meta"]
    first = []
    for j in range(3):
        s = ds[n_orig + j]
        assert {k: tuple(v.shape) for k, v in s["obs"].items()} == {
            k: (m["horizon"], *m["shape"]) for k, m in sm["obs"].items()}
        assert all(v.dtype == torch.float32 for v in s["obs"].values()) and tuple(s["action"].shape) == (16, 10)
        np.testing.assert_allclose(s["obs"]["robot0_eef_pos"][-1].numpy(), 0.0, atol=1e-6)  # relative to T_cur
        first.append(s["action"])
    again = [ds[n_orig + j]["action"] for j in range(3)]  # a second pass: new draws, no set_epoch
    assert any(not torch.equal(a, b) for a, b in zip(first, again))
    val = ds.get_validation_dataset()
    assert type(val) is type(ds) and val.n_augmented == 0
    sd = ds.get_normalizer().state_dict()
    assert {"params_dict.action.scale", "params_dict.camera0_rgb.input_stats.std"} <= set(sd)
    # the stage cache records the 3DGS settings it was built with: a second dataset takes them from there
    from umi_aug.umi_compat.dataset import _cached_splat_stage

    from umi_aug.augment.config import SESSION_SPLAT_SCALE_REG

    cached = _cached_splat_stage(tmp_path / "work")
    assert cached.iterations == 0 and cached.scale_reg == SESSION_SPLAT_SCALE_REG  # a session's default


def test_cached_splat_stage_is_the_stage_the_cache_was_keyed_with(tmp_path):
    """A dataset reusing a stage cache asks for the stage its scene was trained with, every setting included: a cache
    trained before ``SplatStageConfig.scale_reg`` / ``coarse_downscale`` existed (no such keys) stands for the
    trainer's 0.01 at full size; a plain dataset's scene groups (``scenes/<group>/splat``) carry the short schedule
    in ``extra``. Rebuilt from the manifest, the stage hashes to the manifest's own settings (no retraining). No
    manifest, no stage."""
    import json

    from umi_aug.augment.config import TRAINER_SCALE_REG, dataset_splat_stage, splat_key
    from umi_aug.umi_compat.dataset import _cached_splat_stage

    def write(stage_dir, splat):
        stage_dir.mkdir(parents=True, exist_ok=True)
        (stage_dir / "manifest.json").write_text(json.dumps({"settings": {"splat": splat}}))

    assert _cached_splat_stage(tmp_path / "work") is None
    old = {"iterations": 1500, "max_gaussians": 25000, "sh_degree": 3, "holdout_every": 8, "image_size": None,
           "extra": {}}
    write(tmp_path / "work" / "splat", old)
    st = _cached_splat_stage(tmp_path / "work")
    assert (st.iterations, st.max_gaussians, st.scale_reg, st.coarse_downscale) == (1500, 25000, TRAINER_SCALE_REG, 1)
    assert splat_key(st) == old
    # a plain dataset's scene, as `umi-aug augment <dataset>` trains it, found under its scene group
    plain = tmp_path / "plain"
    key = json.loads(json.dumps(splat_key(dataset_splat_stage())))  # as the manifest stores it
    write(plain / "scenes" / "g0" / "splat", key)
    st = _cached_splat_stage(plain)
    assert st == dataset_splat_stage() and splat_key(st) == key and st.extra and st.coarse_downscale == 2
    write(plain / "scenes" / "g1" / "splat", {**key, "iterations": 7})  # a second group's other settings: g0's
    assert _cached_splat_stage(plain) == dataset_splat_stage()
