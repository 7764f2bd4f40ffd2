"""Policy stage: Diffusion Policy with a CLIP ViT-B/16 encoder trained on UMI zarr data (paper §3.4).

* :class:`DiffusionUnetPolicy` — encoder + 1-D conditional U-Net + diffusers scheduler (UMI's interface:
  ``compute_loss(batch)``, ``predict_action(obs) -> {'action', 'action_pred'}`` in the model's relative 10-D
  representation).
* :class:`RegressionChunkPolicy` — the same encoder with an MLP that regresses the chunk (``policy.action_head:
  regression``); both are :class:`ChunkPolicy`, built from a config by :func:`build_policy`.
* :class:`Policy` — deployment wrapper: ``Policy.from_checkpoint(path).predict_action(env_obs)`` →
  ``{"action": absolute TCP actions [n, 7]}`` (pos, rotvec, gripper).
* :class:`PolicyLike` — the one policy contract evaluation and deployment call (:mod:`umi_aug.policy.contract`:
  Diffusion Policy's ``reset()`` / ``predict_action(obs_dict) -> {"action": chunk}``).
* :class:`UmiPolicyDataset` — UMI sampling from a replay buffer; :class:`TrainWorkspace` — the training loop that
  ``train/train.py`` runs; typed configs in :mod:`umi_aug.policy.config`.

Needs the ``policy`` extra (diffusers, transformers, hydra-core); importing this package imports neither torch
nor those (the classes load on first use).
"""

from umi_aug.policy.config import (
    AugConfig, DataloaderConfig, DeviceConfig, EncoderConfig, PolicyConfig, SchedulerConfig, TaskConfig,
    TrainConfig, TrainingConfig, check_aug, check_config, shape_meta, structured_config,
)
from umi_aug.policy.contract import ACTION_KEY, PolicyLike, SeedablePolicy, action_chunk

__all__ = [
    "TrainConfig", "TaskConfig", "PolicyConfig", "EncoderConfig", "SchedulerConfig", "AugConfig", "DeviceConfig",
    "DataloaderConfig", "TrainingConfig", "structured_config", "check_config", "check_aug", "shape_meta",
    "ConditionalUnet1D", "LinearNormalizer", "ObsEncoder", "DiffusionUnetPolicy",
    "RegressionChunkPolicy", "ChunkPolicy", "build_policy", "UmiPolicyDataset", "AugmentedUmiDataset",
    "TrainWorkspace", "Policy", "save_checkpoint", "load_checkpoint",
    "abs_actions_to_model", "model_actions_to_abs", "PolicyLike", "SeedablePolicy", "ACTION_KEY", "action_chunk",
]

_LAZY = {
    "ConditionalUnet1D": "umi_aug.policy.unet",
    "LinearNormalizer": "umi_aug.policy.normalizer",
    "ObsEncoder": "umi_aug.policy.encoders",
    "DiffusionUnetPolicy": "umi_aug.policy.diffusion_policy",
    "RegressionChunkPolicy": "umi_aug.policy.regression_policy",
    "ChunkPolicy": "umi_aug.policy.chunk_policy",
    "build_policy": "umi_aug.policy.heads",
    "UmiPolicyDataset": "umi_aug.policy.dataset",
    "AugmentedUmiDataset": "umi_aug.policy.augmented_dataset",
    "TrainWorkspace": "umi_aug.policy.workspace",
    "Policy": "umi_aug.policy.inference",
    "save_checkpoint": "umi_aug.policy.checkpoint",
    "load_checkpoint": "umi_aug.policy.checkpoint",
    "abs_actions_to_model": "umi_aug.policy.pose_repr",
    "model_actions_to_abs": "umi_aug.policy.pose_repr",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'umi_aug.policy' has no attribute {name!r}")
