"""The regression action head (``policy.action_head: regression``): it learns, its training loss is the error of
what it predicts, it round-trips through a checkpoint into :class:`Policy`, and its settings are checked."""


import numpy as np
import pytest
import torch

from tests.policy.helpers import tiny_config
from tests.policy.test_training import _obs_window
from umi_aug.errors import PolicyError
from umi_aug.policy.chunk_policy import ChunkPolicy
from umi_aug.policy.config import check_config, shape_meta
from umi_aug.policy.dataset import UmiPolicyDataset
from umi_aug.policy.diffusion_policy import DiffusionUnetPolicy
from umi_aug.policy.heads import build_policy
from umi_aug.policy.inference import Policy
from umi_aug.policy.regression_policy import RegressionChunkPolicy
from umi_aug.policy.workspace import TrainWorkspace, iter_jsonl


def _regression_config(dataset_path, tmp_path, loss="l1"):
    cfg = tiny_config(dataset_path, tmp_path)
    cfg.policy.action_head, cfg.policy.head_hidden_dims, cfg.policy.regression_loss = "regression", [64, 64], loss
    return cfg


def test_build_policy_follows_action_head(dataset_path, tmp_path):
    cfg = tiny_config(dataset_path, tmp_path)
    meta = shape_meta(cfg.task)
    assert type(build_policy(meta, cfg.policy, warn_random_init=False)) is DiffusionUnetPolicy
    cfg = _regression_config(dataset_path, tmp_path)
    model = build_policy(meta, cfg.policy, warn_random_init=False)
    assert type(model) is RegressionChunkPolicy and isinstance(model, ChunkPolicy)
    assert not hasattr(model, "model")  # no U-Net is built for the regression head
    assert model.head[-1].out_features == meta["action"]["horizon"] * meta["action"]["shape"][0]


@pytest.mark.parametrize("loss", ["l1", "mse"])
def test_training_loss_is_the_error_of_the_prediction(dataset_path, tmp_path, loss):
    """In eval mode (no crop jitter, no colour jitter), compute_loss(batch) is exactly the L1/MSE between the
    normalised chunk predict_action returns and the normalised label: training fits what inference outputs."""
    cfg = _regression_config(dataset_path, tmp_path, loss)
    ds = UmiPolicyDataset(dataset_path, cfg.task, "train")
    torch.manual_seed(0)
    model = build_policy(ds.shape_meta, cfg.policy, warn_random_init=False)
    model.set_normalizer(ds.fit_normalizer())
    model.eval()
    batch = torch.utils.data.default_collate([ds[i] for i in range(0, len(ds), 3)])
    with torch.no_grad():
        got = float(model.compute_loss(batch))
        pred = model.predict_action(batch["obs"])["action"]
    npred = model.normalizer.normalize(pred, "action").double()
    nlab = model.normalizer.normalize(batch["action"], "action").double()
    diff = npred - nlab
    want = float(diff.abs().mean() if loss == "l1" else (diff ** 2).mean())
    assert np.isfinite(got) and got == pytest.approx(want, rel=1e-5, abs=1e-7)


def test_regression_head_learns_and_round_trips(dataset_path, tmp_path):
    cfg = _regression_config(dataset_path, tmp_path)
    t = cfg.training
    t.num_epochs, t.max_steps, t.val_every, t.sample_every, t.checkpoint_every = 100, 60, 0, 0, 60
    t.lr_scheduler, t.use_ema = "constant", False
    cfg.dataloader.batch_size = 32
    out = TrainWorkspace(cfg).run()
    assert out["global_step"] == 60
    losses = [r["train_loss"] for r in iter_jsonl(tmp_path / "run" / "logs.jsonl") if "train_loss" in r]
    assert len(losses) == 60 and all(np.isfinite(losses))
    first, last = np.mean(losses[:10]), np.mean(losses[-10:])
    assert last < 0.6 * first, (first, last)  # measured 0.44 → 0.13

    obs, start = _obs_window(dataset_path, 20)
    p1, p2 = Policy.from_checkpoint(out["checkpoint"]), Policy.from_checkpoint(out["checkpoint"])
    assert isinstance(p1.model, RegressionChunkPolicy)
    p1.reset(start)
    p2.reset(start)
    a1 = p1.predict_action(obs, generator=torch.Generator().manual_seed(1))["action"]
    a2 = p2.predict_action(obs, generator=torch.Generator().manual_seed(2))["action"]
    assert a1.shape == (8, 7) and np.isfinite(a1).all()
    np.testing.assert_array_equal(a1, a2)  # deterministic: no sampling noise, whatever the generator


def test_regression_settings_are_checked(dataset_path, tmp_path):
    cfg = _regression_config(dataset_path, tmp_path)
    cfg.task.action_horizon, cfg.policy.n_action_steps = 5, 4  # 5: odd, no U-Net takes it; an MLP head does
    check_config(cfg)
    cfg.policy.action_head = "diffusion"
    with pytest.raises(PolicyError, match="task.action_horizon"):
        check_config(cfg)
    cfg = _regression_config(dataset_path, tmp_path)
    cfg.policy.encoder.blur_sigma_max = 5.0
    with pytest.raises(PolicyError, match=r"policy.encoder.blur_sigma_max"):
        check_config(cfg)
    for field, value, match in [("action_head", "transformer", "policy.action_head"),
                                ("regression_loss", "huber", "policy.regression_loss"),
                                ("head_hidden_dims", [64, 0], "policy.head_hidden_dims")]:
        cfg = _regression_config(dataset_path, tmp_path)
        setattr(cfg.policy, field, value)
        with pytest.raises(PolicyError, match=match):
            check_config(cfg)
    for field, value in [("resnet_pool", "max"), ("spatial_softmax_keypoints", 0)]:
        cfg = _regression_config(dataset_path, tmp_path)
        setattr(cfg.policy.encoder, field, value)
        with pytest.raises(PolicyError, match=f"policy.encoder.{field}"):
            check_config(cfg)
