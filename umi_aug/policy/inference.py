"""Deployment interface: ``Policy.predict_action(obs_dict)`` → ``{"action": absolute TCP actions for the next n
steps}`` — the policy contract of :mod:`umi_aug.policy.contract` (Diffusion Policy's ``BaseImagePolicy``).

This is what the simulator evaluation and the UR runner call. It does what UMI's ``eval_real.py`` does around
the network (``get_real_umi_obs_dict`` → ``policy.predict_action`` → ``get_real_umi_action``):

* input (environment observations, absolute; the last ``To`` frames are used, oldest first)::

      camera{j}_rgb            [T, H, W, 3] uint8 RGB (or float in [0, 1]; or [T, 3, H, W]); resized like UMI
                               (full-height centre square → S×S) when H, W ≠ S
      robot{i}_eef_pos         [T, 3] metres (TCP in the robot/table frame)
      robot{i}_eef_rot_axis_angle [T, 3] rotation vector
      robot{i}_gripper_width   [T, 1] (or [T]) metres

  A leading batch axis (``[B, T, ...]``) is accepted for all keys at once.
* poses become relative to the current (last) TCP pose; ``wrt_start`` uses the episode start pose given to
  :meth:`Policy.reset` (default: the current pose at the first call after a reset);
* output: ``{"action": [n, 7·R]}`` (or ``[B, n, 7·R]``) float64 = per arm ``[x, y, z, rx, ry, rz, gripper_width]``, absolute,
  for the next ``n`` policy steps (spaced ``task.obs_down_sample_steps`` frames apart; the first is the current
  step, as in UMI's action window).
"""

from __future__ import annotations

import copy
import os
from typing import Any, Mapping

import numpy as np
import torch
import torch.nn.functional as F

from umi_aug.errors import PolicyError
from umi_aug.policy.checkpoint import load_checkpoint
from umi_aug.policy.config import TrainConfig, shape_meta, structured_config
from umi_aug.policy.chunk_policy import ChunkPolicy
from umi_aug.policy.heads import build_policy
from umi_aug.policy.pose_repr import model_actions_to_abs, obs_pose_to_model, wrt_start_rot6d

__all__ = ["Policy", "prepare_images"]


def prepare_images(img: np.ndarray | torch.Tensor, size: int) -> torch.Tensor:
    """[..., T, H, W, 3] uint8/float or [..., T, 3, H, W] → float32 [..., T, 3, size, size] in [0, 1]
    (full-height centre square, antialiased resize, as UMI's ``get_image_transform``)."""
    x = torch.as_tensor(np.asarray(img)) if not torch.is_tensor(img) else img
    if x.dim() < 4:
        raise PolicyError(f"images must be [T, H, W, 3] or [T, 3, H, W], got {tuple(x.shape)}")
    channels_last = x.shape[-1] == 3 and x.shape[-3] != 3
    if channels_last:
        x = x.movedim(-1, -3)
    if x.shape[-3] != 3:
        raise PolicyError(f"images must have 3 (RGB) channels, got {tuple(x.shape)}")
    x = x.float().div(255.0) if x.dtype == torch.uint8 else x.float()
    H, W = x.shape[-2:]
    if (H, W) != (size, size):
        side = min(H, W)
        y0, x0 = (H - side) // 2, (W - side) // 2
        x = x[..., y0: y0 + side, x0: x0 + side]
        lead = x.shape[:-3]
        x = F.interpolate(x.reshape(-1, 3, side, side), size=(size, size), mode="bilinear", align_corners=False,
                          antialias=True).reshape(*lead, 3, size, size)
    return x


class Policy:
    """A trained policy ready for closed-loop control.

    Args:
        model: the :class:`ChunkPolicy` (usually the EMA weights).
        cfg: the training config it was trained with.
        device: torch device for inference.
    """

    def __init__(self, model: ChunkPolicy, cfg: TrainConfig, device: str | torch.device = "cpu") -> None:
        self.device = torch.device(device)
        self.model = model.to(self.device).eval()
        self.cfg = cfg
        self.task = cfg.task
        self.shape_meta = shape_meta(cfg.task)
        self.n_action_steps = int(cfg.policy.n_action_steps)
        self._start_pose: np.ndarray | None = None

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike, device: str | torch.device = "cpu", use_ema: bool = True
                        ) -> "Policy":
        """Rebuild the policy from a training checkpoint (EMA weights when present and ``use_ema``)."""
        payload = load_checkpoint(path)
        cfg = structured_config(payload["cfg"])
        build_cfg = copy.deepcopy(cfg)
        build_cfg.policy.encoder.pretrained_path = None  # the weights come from the checkpoint
        model = build_policy(shape_meta(cfg.task), build_cfg.policy, warn_random_init=False)
        sd = payload["state_dicts"]
        state = sd["ema_model"] if use_ema and "ema_model" in sd else sd["model"]
        try:
            model.load_state_dict(state)
        except RuntimeError as exc:
            raise PolicyError(f"checkpoint {path}: weights do not fit the model its config describes: {exc}") from exc
        return cls(model, cfg, device)

    def reset(self, episode_start_pose: np.ndarray | None = None) -> None:
        """Start a new episode. ``episode_start_pose``: pos + rotvec, [6] (one arm), [R, 6] or, for batched
        observations, [B, R, 6]; None = the current pose at the next :meth:`predict_action` call."""
        if episode_start_pose is None:
            self._start_pose = None
            return
        sp = np.asarray(episode_start_pose, np.float64)
        sp = sp.reshape((1,) * (3 - sp.ndim) + sp.shape) if sp.ndim < 3 else sp
        if sp.ndim != 3 or sp.shape[1:] != (self.task.n_robots, 6) or not np.isfinite(sp).all():
            raise PolicyError(f"reset: episode_start_pose must be finite [6], [R, 6] or [B, R, 6] with "
                              f"R={self.task.n_robots}, got {np.shape(episode_start_pose)}")
        self._start_pose = sp

    # ------------------------------------------------------------------ conversion
    def obs_to_model(self, obs: Mapping[str, Any]) -> tuple[dict[str, torch.Tensor], np.ndarray, bool]:
        """Environment obs → model obs tensors ``{key: [B, To, ...]}``, current poses [B, R, 6], batched flag."""
        t = self.task
        key0 = "robot0_eef_pos"
        if key0 not in obs:
            raise PolicyError(f"predict_action: observation {key0!r} missing; got {sorted(obs)}")
        batched = np.asarray(obs[key0]).ndim == 3
        To = t.low_dim_obs_horizon
        out: dict[str, np.ndarray] = {}
        arms = []
        for i in range(t.n_robots):
            p = f"robot{i}_"
            for k in ("eef_pos", "eef_rot_axis_angle", "gripper_width"):
                if p + k not in obs:
                    raise PolicyError(f"predict_action: observation {p + k!r} missing; got {sorted(obs)}")
            pos = np.asarray(obs[p + "eef_pos"], np.float64)
            rot = np.asarray(obs[p + "eef_rot_axis_angle"], np.float64)
            grip = np.asarray(obs[p + "gripper_width"], np.float64)
            if not batched:
                pos, rot, grip = pos[None], rot[None], grip[None]
            if grip.ndim == 2:
                grip = grip[..., None]
            if pos.shape[1] < 1 or pos.shape[-1] != 3 or rot.shape != pos.shape or grip.shape[:2] != pos.shape[:2]:
                raise PolicyError(f"predict_action: robot{i} pose arrays must be [T, 3] / [T, 3] / [T, 1] "
                                  f"(optionally batched), got {pos.shape}, {rot.shape}, {grip.shape}")
            idx = np.clip(np.arange(pos.shape[1] - To, pos.shape[1]), 0, None)  # pad by repeating the oldest
            arms.append((pos[:, idx], rot[:, idx], grip[:, idx]))
        cur = np.stack([np.concatenate([pos[:, -1], rot[:, -1]], axis=-1) for pos, rot, _ in arms], axis=1)  # [B,R,6]
        if t.use_wrt_start and self._start_pose is None:
            self._start_pose = cur.copy()
        for i, (pos, rot, grip) in enumerate(arms):
            p = f"robot{i}_"
            mp, mr = obs_pose_to_model(pos, rot, t.obs_pose_repr)
            out[p + "eef_pos"], out[p + "eef_rot_axis_angle"], out[p + "gripper_width"] = mp, mr, grip
            if t.use_wrt_start:
                sp = self._start_pose  # [1 or B, R, 6]
                start = np.broadcast_to(sp[:, i], (cur.shape[0], 6))
                out[p + "eef_rot_axis_angle_wrt_start"] = wrt_start_rot6d(pos, rot, start)
        cur_arr = cur
        tensors = {k: torch.as_tensor(v, dtype=torch.float32, device=self.device) for k, v in out.items()}
        for j in range(t.n_cameras):
            k = f"camera{j}_rgb"
            if k not in obs:
                raise PolicyError(f"predict_action: observation {k!r} missing; got {sorted(obs)}")
            img = prepare_images(obs[k], t.image_size)
            if not batched:
                img = img[None]
            Ti = t.img_obs_horizon
            idx = torch.clamp(torch.arange(img.shape[1] - Ti, img.shape[1]), min=0)
            tensors[k] = img[:, idx].to(self.device)
        return tensors, cur_arr, batched

    @torch.no_grad()
    def predict_action(self, obs_dict: Mapping[str, Any], n_steps: int | None = None,
                       generator: torch.Generator | None = None) -> dict[str, np.ndarray]:
        """``{"action": absolute TCP actions [n, 7·R]}`` (``[B, n, 7·R]`` for batched obs): per arm pos (m), rotvec
        (rad), gripper width (m), for the next ``n_steps`` (default ``policy.n_action_steps``) steps.

        ``generator`` (CPU ``torch.Generator``) makes the sampling noise reproducible."""
        n = self.n_action_steps if n_steps is None else int(n_steps)
        if not 1 <= n <= self.task.action_horizon:
            raise PolicyError(f"predict_action: n_steps={n} must be in [1, {self.task.action_horizon}]")
        model_obs, cur, batched = self.obs_to_model(obs_dict)
        action10 = self.model.predict_action(model_obs, generator=generator)["action"].float().cpu().numpy()
        base = cur[:, 0] if self.task.n_robots == 1 else cur  # [B, 6] or [B, R, 6]
        act = model_actions_to_abs(action10.astype(np.float64), base, self.task.action_pose_repr)[:, :n]
        return {"action": act if batched else act[0]}
