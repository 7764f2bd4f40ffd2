"""What every action head shares: the observation encoder, the fitted normaliser and UMI's interface.

A chunk policy maps model-format observations ``{key: [B, T, ...]}`` (normalisable tensors, relative poses) to a
normalised action chunk ``[B, H, Da]`` (relative pos + rot6d + gripper per arm); subclasses say how
(:class:`umi_aug.policy.diffusion_policy.DiffusionUnetPolicy`: a denoised U-Net sample;
:class:`umi_aug.policy.regression_policy.RegressionChunkPolicy`: one MLP forward pass). Both train with
``compute_loss(batch)`` and answer ``predict_action(obs_dict) -> {'action', 'action_pred'}`` (unnormalised), so the
workspace, checkpoints, EMA and :class:`umi_aug.policy.inference.Policy` treat them alike.
"""

from __future__ import annotations

from typing import Any, Mapping

import torch
from torch import nn

from umi_aug.errors import PolicyError
from umi_aug.policy.config import PolicyConfig
from umi_aug.policy.encoders import ObsEncoder
from umi_aug.policy.normalizer import LinearNormalizer

__all__ = ["ChunkPolicy"]


class ChunkPolicy(nn.Module):
    """Args:
        shape_meta: UMI-style shapes (:func:`umi_aug.policy.config.shape_meta`).
        cfg: :class:`PolicyConfig`.
        warn_random_init: log when the image backbone starts from random weights.
    """

    def __init__(self, shape_meta: Mapping[str, Any], cfg: PolicyConfig, warn_random_init: bool = True) -> None:
        super().__init__()
        act = shape_meta["action"]
        self.shape_meta = shape_meta
        self.cfg = cfg
        self.action_dim = int(act["shape"][0])
        self.action_horizon = int(act["horizon"])
        self.obs_encoder = ObsEncoder(shape_meta, cfg.encoder, warn_random_init)
        self.obs_feature_dim = self.obs_encoder.output_dim
        self.normalizer = LinearNormalizer()

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def set_normalizer(self, normalizer: LinearNormalizer) -> None:
        self.normalizer.load_state_dict(normalizer.state_dict())
        self.normalizer.to(self.device)

    def _check_normalizer(self) -> None:
        if "action" not in self.normalizer:
            raise PolicyError("the policy has no fitted normaliser; call set_normalizer(dataset.fit_normalizer())")

    def encode_obs(self, obs_dict: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Model-format observations → the global condition ``[B, obs_feature_dim]`` (normalised, encoded)."""
        self._check_normalizer()
        return self.obs_encoder(self.normalizer.normalize(dict(obs_dict)))

    def compute_loss(self, batch: Mapping[str, Any], generator: torch.Generator | None = None) -> torch.Tensor:
        raise NotImplementedError

    def forward(self, batch: Mapping[str, Any]) -> torch.Tensor:
        return self.compute_loss(batch)
