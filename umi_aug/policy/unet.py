"""1-D temporal conditional U-Net with FiLM conditioning: the Diffusion Policy CNN (``ConditionalUnet1D``).

Architecture (own code following the DP paper and ``model/diffusion/conditional_unet1d.py``'s structure):

* diffusion step → sinusoidal embedding (dim ``dsed``) → Linear(dsed, 4·dsed) → Mish → Linear(4·dsed, dsed);
  condition vector = [step embedding, global_cond] (dim ``dsed + global_cond_dim``).
* Encoder: for each (c_in, c_out) in ``[input_dim] + down_dims``: two conditional residual blocks, then a
  stride-2 Conv1d down-sampling except at the last level; the output of each level is kept as a skip.
* Middle: two conditional residual blocks at ``down_dims[-1]``.
* Decoder: for the levels in reverse (all but the first): concat the skip, two residual blocks, ConvTranspose1d
  up-sampling (×2). Final: Conv1d block + 1×1 Conv1d back to ``input_dim``.
* Conditional residual block: Conv1d→GroupNorm→Mish, FiLM from the condition (Mish→Linear→(scale, bias) when
  ``cond_predict_scale`` else bias only), Conv1d→GroupNorm→Mish, plus a 1×1 residual projection.

The horizon must be divisible by ``2 ** (len(down_dims) - 1)``.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from umi_aug.errors import PolicyError

__all__ = ["ConditionalUnet1D", "SinusoidalPosEmb", "ConditionalResidualBlock1D"]


class SinusoidalPosEmb(nn.Module):
    """``[sin(t·ω_k), cos(t·ω_k)]`` with ``ω_k = 10000^(-k/(half-1))``, k < half = dim/2."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        if dim < 4 or dim % 2:
            raise PolicyError(f"SinusoidalPosEmb: dim must be even and >= 4, got {dim}")
        self.dim = dim

    def forward(self, t: torch.Tensor) -> torch.Tensor:  # [B] → [B, dim]
        half = self.dim // 2
        freq = torch.exp(torch.arange(half, device=t.device, dtype=torch.float32) * (-math.log(10000.0) / (half - 1)))
        arg = t.float()[:, None] * freq[None, :]
        return torch.cat([arg.sin(), arg.cos()], dim=-1)


class Conv1dBlock(nn.Sequential):
    """Conv1d (same padding) → GroupNorm → Mish."""

    def __init__(self, c_in: int, c_out: int, kernel_size: int, n_groups: int) -> None:
        super().__init__(nn.Conv1d(c_in, c_out, kernel_size, padding=kernel_size // 2),
                         nn.GroupNorm(n_groups, c_out), nn.Mish())


class ConditionalResidualBlock1D(nn.Module):
    """Two Conv1d blocks with FiLM modulation of the first one's output by the condition vector."""

    def __init__(self, c_in: int, c_out: int, cond_dim: int, kernel_size: int = 3, n_groups: int = 8,
                 cond_predict_scale: bool = False) -> None:
        super().__init__()
        self.blocks = nn.ModuleList([Conv1dBlock(c_in, c_out, kernel_size, n_groups),
                                     Conv1dBlock(c_out, c_out, kernel_size, n_groups)])
        self.out_channels = c_out
        self.cond_predict_scale = cond_predict_scale
        self.cond_encoder = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, c_out * 2 if cond_predict_scale else c_out))
        self.residual_conv = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """x: [B, c_in, T], cond: [B, cond_dim] → [B, c_out, T]."""
        out = self.blocks[0](x)
        embed = self.cond_encoder(cond)[..., None]  # [B, c_out(·2), 1]
        if self.cond_predict_scale:
            scale, bias = embed[:, : self.out_channels], embed[:, self.out_channels:]
            out = scale * out + bias
        else:
            out = out + embed
        out = self.blocks[1](out)
        return out + self.residual_conv(x)


class ConditionalUnet1D(nn.Module):
    """Noise-prediction network ε(x_t, t, global_cond) over action sequences.

    Args:
        input_dim: action dimension (10 per arm: pos 3 + rot6d 6 + gripper 1).
        global_cond_dim: length of the observation feature vector (None = unconditional).
        diffusion_step_embed_dim: sinusoidal step-embedding size (UMI 128, DP 256).
        down_dims: channels per level (UMI [256, 512, 1024]).
        kernel_size, n_groups: Conv1d kernel and GroupNorm groups (UMI 5, 8).
        cond_predict_scale: FiLM with scale and bias (True in UMI) or bias only.
    """

    def __init__(self, input_dim: int, global_cond_dim: int | None = None, diffusion_step_embed_dim: int = 256,
                 down_dims: tuple[int, ...] | list[int] = (256, 512, 1024), kernel_size: int = 3, n_groups: int = 8,
                 cond_predict_scale: bool = False) -> None:
        super().__init__()
        down_dims = [int(d) for d in down_dims]
        if not down_dims or any(d % n_groups for d in down_dims):
            raise PolicyError(f"ConditionalUnet1D: down_dims {down_dims} must be non-empty and divisible by "
                              f"n_groups={n_groups}")
        dsed = int(diffusion_step_embed_dim)
        self.input_dim = int(input_dim)
        self.global_cond_dim = global_cond_dim
        self.n_levels = len(down_dims)
        self.diffusion_step_encoder = nn.Sequential(
            SinusoidalPosEmb(dsed), nn.Linear(dsed, dsed * 4), nn.Mish(), nn.Linear(dsed * 4, dsed))
        cond_dim = dsed + (int(global_cond_dim) if global_cond_dim else 0)
        dims = [self.input_dim] + down_dims
        in_out = list(zip(dims[:-1], dims[1:]))

        def block(a: int, b: int) -> ConditionalResidualBlock1D:
            return ConditionalResidualBlock1D(a, b, cond_dim, kernel_size, n_groups, cond_predict_scale)

        self.down_modules = nn.ModuleList()
        for level, (c_in, c_out) in enumerate(in_out):
            last = level == len(in_out) - 1
            self.down_modules.append(nn.ModuleList([
                block(c_in, c_out), block(c_out, c_out),
                nn.Identity() if last else nn.Conv1d(c_out, c_out, 3, stride=2, padding=1)]))
        mid = down_dims[-1]
        self.mid_modules = nn.ModuleList([block(mid, mid), block(mid, mid)])
        self.up_modules = nn.ModuleList()
        for c_in, c_out in reversed(in_out[1:]):
            self.up_modules.append(nn.ModuleList([
                block(c_out * 2, c_in), block(c_in, c_in), nn.ConvTranspose1d(c_in, c_in, 4, stride=2, padding=1)]))
        start = down_dims[0]
        self.final_conv = nn.Sequential(Conv1dBlock(start, start, kernel_size, n_groups),
                                        nn.Conv1d(start, self.input_dim, 1))

    @property
    def horizon_multiple(self) -> int:
        """The horizon must be a multiple of this (one halving per level but the last)."""
        return 2 ** (self.n_levels - 1)

    def forward(self, sample: torch.Tensor, timestep: torch.Tensor | int | float,
                global_cond: torch.Tensor | None = None) -> torch.Tensor:
        """Predict the noise of ``sample``.

        Args:
            sample: Tensor,  # [B, T, input_dim] noisy (normalised) actions
            timestep: Tensor,  # [B] or [] or a number: diffusion step(s)
            global_cond: Tensor,  # [B, global_cond_dim] observation features
        Returns:
            Tensor,  # [B, T, input_dim]
        """
        if sample.dim() != 3 or sample.shape[-1] != self.input_dim:
            raise PolicyError(f"ConditionalUnet1D: `sample` must be [B, T, {self.input_dim}], got {tuple(sample.shape)}")
        B, T = sample.shape[:2]
        if T % self.horizon_multiple:
            raise PolicyError(f"ConditionalUnet1D: horizon T={T} must be a multiple of {self.horizon_multiple}")
        if self.global_cond_dim and (global_cond is None or tuple(global_cond.shape) != (B, self.global_cond_dim)):
            raise PolicyError(f"ConditionalUnet1D: `global_cond` must be [{B}, {self.global_cond_dim}], got "
                              f"{None if global_cond is None else tuple(global_cond.shape)}")
        t = timestep if torch.is_tensor(timestep) else torch.tensor([timestep], device=sample.device)
        t = t.to(sample.device).reshape(-1).expand(B)
        cond = self.diffusion_step_encoder(t).to(sample.dtype)
        if self.global_cond_dim:
            cond = torch.cat([cond, global_cond.to(cond.dtype)], dim=-1)
        x = sample.transpose(1, 2)  # [B, C, T]
        skips = []
        for res1, res2, down in self.down_modules:
            x = res2(res1(x, cond), cond)
            skips.append(x)
            x = down(x)
        for res in self.mid_modules:
            x = res(x, cond)
        for res1, res2, up in self.up_modules:
            x = torch.cat([x, skips.pop()], dim=1)
            x = up(res2(res1(x, cond), cond))
        x = self.final_conv(x)
        return x.transpose(1, 2)
