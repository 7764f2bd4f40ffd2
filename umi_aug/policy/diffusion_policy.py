"""Diffusion Policy (UMI's ``DiffusionUnetTimmPolicy``): observation encoder → global condition of a 1-D
conditional U-Net that predicts the noise (epsilon) of a normalised action sequence; diffusers schedulers.

Training: ``loss = MSE(ε_θ(add_noise(a, ε + 0.1·ε'), t, cond), ε)`` (DDPM-IP input perturbation, as UMI).
Sampling: ``scheduler.set_timesteps(num_inference_steps)`` then ``x ← scheduler.step(ε_θ(x, t), t, x)``.
:meth:`DiffusionUnetPolicy.predict_action` works on model-format observations (normalisable tensors, relative
poses) and returns the unnormalised 10-D action sequence, as UMI; :class:`umi_aug.policy.inference.Policy` wraps
it for environments (absolute TCP poses in and out).
"""

from __future__ import annotations

import importlib
import inspect
from dataclasses import asdict
from typing import Any, Mapping

import torch
import torch.nn.functional as F

from umi_aug.errors import PolicyError
from umi_aug.policy.chunk_policy import ChunkPolicy
from umi_aug.policy.config import PolicyConfig, SchedulerConfig
from umi_aug.policy.unet import ConditionalUnet1D

__all__ = ["DiffusionUnetPolicy", "build_noise_scheduler"]


def build_noise_scheduler(cfg: SchedulerConfig):
    """Instantiate the diffusers scheduler named by ``cfg._target_`` with the kwargs it accepts."""
    target = cfg._target_
    mod_name, _, cls_name = target.rpartition(".")
    if mod_name not in ("diffusers", "diffusers.schedulers") or not cls_name.endswith("Scheduler"):
        raise PolicyError(f"policy.noise_scheduler._target_={target!r}: expected a diffusers scheduler class, "
                          "e.g. diffusers.DDIMScheduler or diffusers.DDPMScheduler")
    try:
        cls = getattr(importlib.import_module(mod_name), cls_name)
    except (ImportError, AttributeError) as exc:
        raise PolicyError(f"policy.noise_scheduler._target_={target!r}: {exc}") from exc
    params = inspect.signature(cls.__init__).parameters
    kwargs = {k: v for k, v in asdict(cfg).items() if k != "_target_" and k in params}
    return cls(**kwargs)


class DiffusionUnetPolicy(ChunkPolicy):
    """Args:
        shape_meta: UMI-style shapes (:func:`umi_aug.policy.config.shape_meta`).
        cfg: :class:`PolicyConfig`.
    """

    def __init__(self, shape_meta: Mapping[str, Any], cfg: PolicyConfig, warn_random_init: bool = True) -> None:
        super().__init__(shape_meta, cfg, warn_random_init)
        self.model = ConditionalUnet1D(
            input_dim=self.action_dim, global_cond_dim=self.obs_feature_dim,
            diffusion_step_embed_dim=cfg.diffusion_step_embed_dim, down_dims=cfg.down_dims,
            kernel_size=cfg.kernel_size, n_groups=cfg.n_groups, cond_predict_scale=cfg.cond_predict_scale)
        if self.action_horizon % self.model.horizon_multiple:
            raise PolicyError(f"action horizon {self.action_horizon} must be a multiple of "
                              f"{self.model.horizon_multiple} for down_dims={list(cfg.down_dims)}")
        self.noise_scheduler = build_noise_scheduler(cfg.noise_scheduler)
        self.num_inference_steps = int(cfg.num_inference_steps or cfg.noise_scheduler.num_train_timesteps)
        self.input_pertub = float(cfg.input_pertub)

    # ------------------------------------------------------------------ training
    def compute_loss(self, batch: Mapping[str, Any], generator: torch.Generator | None = None) -> torch.Tensor:
        """Epsilon-prediction MSE on ``batch = {'obs': {key: [B, T, ...]}, 'action': [B, H, Da]}``."""
        cond = self.encode_obs(batch["obs"])
        nact = self.normalizer.normalize(batch["action"], "action")
        dev = nact.device
        noise = torch.randn(nact.shape, generator=generator, device="cpu").to(dev)
        noise_in = noise + self.input_pertub * torch.randn(nact.shape, generator=generator, device="cpu").to(dev)
        t = torch.randint(0, self.noise_scheduler.config.num_train_timesteps, (nact.shape[0],), generator=generator,
                          device="cpu").to(dev)
        noisy = self.noise_scheduler.add_noise(nact, noise_in, t)
        pred = self.model(noisy, t, global_cond=cond)
        return F.mse_loss(pred.float(), noise.float())

    # ------------------------------------------------------------------ inference
    @torch.no_grad()
    def conditional_sample(self, global_cond: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Run the reverse diffusion from Gaussian noise → normalised actions [B, H, Da]."""
        B = global_cond.shape[0]
        x = torch.randn((B, self.action_horizon, self.action_dim), generator=generator, device="cpu",
                        dtype=torch.float32).to(global_cond.device)
        sched = self.noise_scheduler
        sched.set_timesteps(self.num_inference_steps)
        for t in sched.timesteps:
            eps = self.model(x, t.to(x.device), global_cond=global_cond)
            x = sched.step(eps.float(), t, x, generator=generator).prev_sample
        return x

    @torch.no_grad()
    def predict_action(self, obs_dict: Mapping[str, torch.Tensor], generator: torch.Generator | None = None
                       ) -> dict[str, torch.Tensor]:
        """UMI's interface: model-format obs ``{key: [B, T, ...]}`` → ``{'action', 'action_pred'}`` both the full
        unnormalised ``[B, H, Da]`` sequence (relative pos + rot6d + gripper per arm)."""
        cond = self.encode_obs(obs_dict)
        nsample = self.conditional_sample(cond.float(), generator)
        action = self.normalizer.unnormalize(nsample, "action")
        return {"action": action, "action_pred": action}
