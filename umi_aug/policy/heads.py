"""Build the chunk policy a config names (``policy.action_head``): diffusion (the paper's) or regression."""

from __future__ import annotations

from typing import Any, Mapping

from umi_aug.policy.chunk_policy import ChunkPolicy
from umi_aug.policy.config import PolicyConfig
from umi_aug.policy.diffusion_policy import DiffusionUnetPolicy
from umi_aug.policy.regression_policy import RegressionChunkPolicy

__all__ = ["build_policy"]

_HEADS = {"diffusion": DiffusionUnetPolicy, "regression": RegressionChunkPolicy}


def build_policy(shape_meta: Mapping[str, Any], cfg: PolicyConfig, warn_random_init: bool = True) -> ChunkPolicy:
    """The :class:`ChunkPolicy` of ``cfg.action_head`` (values checked by :func:`umi_aug.policy.config.check_config`)."""
    return _HEADS[cfg.action_head](shape_meta, cfg, warn_random_init)
