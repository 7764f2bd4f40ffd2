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
    from umi_aug.umi_compat.dataset import _cached_splat_settings

    from umi_aug.augment.config import SESSION_SPLAT_SCALE_REG

    cached = _cached_splat_settings(tmp_path / "work")
    assert cached["iterations"] == 0 and cached["scale_reg"] == SESSION_SPLAT_SCALE_REG  # a session's default


def test_cached_splat_settings_of_a_cache_from_before_scale_reg(tmp_path):
    """A stage cache trained before ``SplatStageConfig.scale_reg`` / ``coarse_downscale`` existed (its settings have
    no such keys) was trained with the trainer's 0.01 at full size: those values are what a dataset reusing the cache
    asks for (the same stage key, no retraining); no manifest, no settings."""
    import json

    from umi_aug.augment.config import TRAINER_SCALE_REG
    from umi_aug.umi_compat.dataset import _cached_splat_settings

    assert _cached_splat_settings(tmp_path / "work") == {}
    (tmp_path / "work" / "splat").mkdir(parents=True)
    (tmp_path / "work" / "splat" / "manifest.json").write_text(json.dumps(
        {"settings": {"splat": {"iterations": 1500, "max_gaussians": 25000, "sh_degree": 3}}}))
    assert _cached_splat_settings(tmp_path / "work") == {"iterations": 1500, "max_gaussians": 25000,
                                                         "scale_reg": TRAINER_SCALE_REG, "coarse_downscale": 1}
    # a coarse-to-fine scene (a plain dataset's default) reports its factor, so the dataset reuses it
    (tmp_path / "work" / "splat" / "manifest.json").write_text(json.dumps(
        {"settings": {"splat": {"iterations": 1200, "max_gaussians": 30000, "scale_reg": 0.5,
                                "coarse_downscale": 2}}}))
    assert _cached_splat_settings(tmp_path / "work") == {"iterations": 1200, "max_gaussians": 30000,
                                                         "scale_reg": 0.5, "coarse_downscale": 2}
