"""Deterministic action-chunk regression: the observation encoder's global condition → an MLP → the normalised
``[H, Da]`` chunk in one forward pass (robomimic's BC head, ACT's chunking and L1 loss without its CVAE).

For a deterministic, unimodal demonstrator (the scripted square expert) there is nothing for a diffusion head's
sampling to choose between; regression trains on the labels themselves instead of on noise at 50 levels, and
inference costs one pass instead of ``num_inference_steps`` U-Net passes. Selected by ``policy.action_head:
regression`` (``configs/policy/small_regression.yaml``); issue #29 part 3 measures it against diffusion.
"""

from __future__ import annotations

from typing import Any, Mapping

import torch
import torch.nn.functional as F
from torch import nn

from umi_aug.policy.chunk_policy import ChunkPolicy
from umi_aug.policy.config import PolicyConfig

__all__ = ["RegressionChunkPolicy", "regression_loss"]


def regression_loss(pred: torch.Tensor, target: torch.Tensor, kind: str) -> torch.Tensor:
    """Mean ``|pred − target|`` (``kind='l1'``) or squared error (``'mse'``) over every element (normalised units)."""
    if kind == "l1":
        return F.l1_loss(pred.float(), target.float())
    return F.mse_loss(pred.float(), target.float())


class RegressionChunkPolicy(ChunkPolicy):
    """Args:
        shape_meta: UMI-style shapes (:func:`umi_aug.policy.config.shape_meta`).
        cfg: :class:`PolicyConfig` (``head_hidden_dims``, ``regression_loss``; the U-Net/scheduler fields unused).
    """

    def __init__(self, shape_meta: Mapping[str, Any], cfg: PolicyConfig, warn_random_init: bool = True) -> None:
        super().__init__(shape_meta, cfg, warn_random_init)
        dims = [self.obs_feature_dim, *[int(d) for d in cfg.head_hidden_dims]]
        layers: list[nn.Module] = []
        for d_in, d_out in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(d_in, d_out), nn.ReLU()]
        layers.append(nn.Linear(dims[-1], self.action_horizon * self.action_dim))
        self.head = nn.Sequential(*layers)
        self.loss_kind = str(cfg.regression_loss)

    def predict_normalized(self, global_cond: torch.Tensor) -> torch.Tensor:
        """Global condition ``[B, F]`` → normalised action chunk ``[B, H, Da]``."""
        return self.head(global_cond).reshape(-1, self.action_horizon, self.action_dim)

    def compute_loss(self, batch: Mapping[str, Any], generator: torch.Generator | None = None) -> torch.Tensor:
        """L1 (or MSE) between the predicted and the labelled normalised chunk; ``generator`` is unused (no noise)."""
        cond = self.encode_obs(batch["obs"])
        nact = self.normalizer.normalize(batch["action"], "action")
        return regression_loss(self.predict_normalized(cond), nact, self.loss_kind)

    @torch.no_grad()
    def predict_action(self, obs_dict: Mapping[str, torch.Tensor], generator: torch.Generator | None = None
                       ) -> dict[str, torch.Tensor]:
        """UMI's interface: model-format obs ``{key: [B, T, ...]}`` → ``{'action', 'action_pred'}``, the unnormalised
        ``[B, H, Da]`` chunk (deterministic: ``generator`` is accepted for the interface and unused)."""
        nchunk = self.predict_normalized(self.encode_obs(obs_dict).float())
        action = self.normalizer.unnormalize(nchunk, "action")
        return {"action": action, "action_pred": action}
