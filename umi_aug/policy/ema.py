"""Exponential moving average of the policy weights (Diffusion Policy's ``EMAModel`` schedule).

``decay(step) = clip(1 - (1 + s / inv_gamma) ** -power, min_value, max_value)`` with
``s = step - update_after_step - 1`` (0 for s ≤ 0); UMI uses power 0.75, max 0.9999. Parameters that do not
require grad and all buffers (e.g. the normaliser) are copied, not averaged.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["EMA"]


class EMA:
    def __init__(self, averaged_model: nn.Module, update_after_step: int = 0, inv_gamma: float = 1.0,
                 power: float = 0.75, min_value: float = 0.0, max_value: float = 0.9999) -> None:
        self.averaged_model = averaged_model.eval().requires_grad_(False)
        self.update_after_step = int(update_after_step)
        self.inv_gamma, self.power = float(inv_gamma), float(power)
        self.min_value, self.max_value = float(min_value), float(max_value)
        self.optimization_step = 0
        self.decay = 0.0

    def get_decay(self, step: int) -> float:
        s = max(0, step - self.update_after_step - 1)
        if s <= 0:
            return 0.0
        value = 1.0 - (1.0 + s / self.inv_gamma) ** -self.power
        return max(self.min_value, min(value, self.max_value))

    @torch.no_grad()
    def step(self, model: nn.Module) -> None:
        self.decay = self.get_decay(self.optimization_step)
        for p_ema, p in zip(self.averaged_model.parameters(), model.parameters()):
            if not p.requires_grad:
                p_ema.copy_(p)
            else:
                p_ema.mul_(self.decay).add_(p.detach().to(p_ema.dtype), alpha=1.0 - self.decay)
        for b_ema, b in zip(self.averaged_model.buffers(), model.buffers()):
            b_ema.copy_(b)
        self.optimization_step += 1

    def state_dict(self) -> dict:
        return {"optimization_step": self.optimization_step, "decay": self.decay}

    def load_state_dict(self, state: dict) -> None:
        self.optimization_step = int(state["optimization_step"])
        self.decay = float(state["decay"])
