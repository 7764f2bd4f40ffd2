"""Per-key affine normaliser ``y = x · scale + offset`` (UMI/DP ``LinearNormalizer``), stored as buffers so it
travels inside the policy's ``state_dict``.

UMI's choices (``UmiDataset.get_normalizer``): action pos and gripper → range [-1, 1], rot6d → identity; obs
``*pos`` / ``*gripper_width`` → range, ``*rot_axis_angle*`` (rot6d) → identity; images → identity (the encoder
does its own image normalisation). Range normalisers treat a dimension whose range is < ``RANGE_EPS`` as
constant: it is shifted to 0 with unit scale (as UMI does), so ``unnormalize(normalize(x)) == x`` always holds.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
import torch
from torch import nn

from umi_aug.errors import PolicyError

__all__ = ["LinearNormalizer", "range_params", "identity_params", "RANGE_EPS"]

#: A dimension whose range is below this is treated as constant (UMI's ``range_eps``).
RANGE_EPS: float = 1e-7


def range_params(x: np.ndarray, out_min: float = -1.0, out_max: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """``(scale, offset)`` mapping the per-dimension [min, max] of ``x`` [N, D] onto [out_min, out_max]."""
    x = np.asarray(x, dtype=np.float64).reshape(-1, np.shape(x)[-1])
    if x.shape[0] == 0:
        raise PolicyError("range normaliser: no samples to fit (is the training split empty?)")
    lo, hi = x.min(axis=0), x.max(axis=0)
    rng = hi - lo
    const = rng < RANGE_EPS
    rng = np.where(const, out_max - out_min, rng)
    scale = (out_max - out_min) / rng
    offset = out_min - scale * lo
    offset = np.where(const, (out_max + out_min) / 2 - lo, offset)
    return scale, offset


def identity_params(dim: int) -> tuple[np.ndarray, np.ndarray]:
    return np.ones(dim), np.zeros(dim)


class LinearNormalizer(nn.Module):
    """``{key: (scale [D], offset [D])}`` buffers; ``normalize``/``unnormalize`` act on the last axis."""

    def __init__(self) -> None:
        super().__init__()
        self._keys: list[str] = []

    def set(self, key: str, scale: np.ndarray | torch.Tensor, offset: np.ndarray | torch.Tensor) -> None:
        scale = torch.as_tensor(np.asarray(scale, dtype=np.float32))
        offset = torch.as_tensor(np.asarray(offset, dtype=np.float32))
        if scale.shape != offset.shape or scale.dim() != 1 or not torch.isfinite(scale).all() or (scale == 0).any():
            raise PolicyError(f"LinearNormalizer[{key!r}]: scale/offset must be finite 1-D of one shape with scale != 0,"
                              f" got {tuple(scale.shape)} / {tuple(offset.shape)}")
        name = self._buf(key)
        self.register_buffer(name + "_scale", scale)
        self.register_buffer(name + "_offset", offset)
        if key not in self._keys:
            self._keys.append(key)

    @staticmethod
    def _buf(key: str) -> str:
        return "p_" + key.replace(".", "__")

    def keys(self) -> list[str]:
        return list(self._keys)

    def __contains__(self, key: object) -> bool:
        return key in self._keys

    def params(self, key: str) -> tuple[torch.Tensor, torch.Tensor]:
        if key not in self._keys:
            raise PolicyError(f"LinearNormalizer: no key {key!r}; have {self._keys}")
        name = self._buf(key)
        return getattr(self, name + "_scale"), getattr(self, name + "_offset")

    def normalize(self, x: torch.Tensor | Mapping[str, torch.Tensor], key: str | None = None):
        """Normalise one tensor (``key`` given) or every key of a dict that the normaliser knows (others pass)."""
        if key is None and isinstance(x, Mapping):
            return {k: (self.normalize(v, k) if k in self._keys else v) for k, v in x.items()}
        scale, offset = self.params(key)  # type: ignore[arg-type]
        return x * scale.to(x.dtype) + offset.to(x.dtype)

    def unnormalize(self, y: torch.Tensor, key: str) -> torch.Tensor:
        scale, offset = self.params(key)
        return (y - offset.to(y.dtype)) / scale.to(y.dtype)

    # state_dict round trip: buffers are registered lazily, so load_state_dict must create them first
    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                              error_msgs):  # noqa: D401 - torch hook
        for k in list(state_dict):
            if k.startswith(prefix + "p_") and k.endswith("_scale"):
                name = k[len(prefix):-len("_scale")]
                key = name[2:].replace("__", ".")
                off = state_dict.get(prefix + name + "_offset")
                if off is not None and key not in self._keys:
                    self.set(key, state_dict[k].detach().cpu().numpy(), off.detach().cpu().numpy())
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                                      error_msgs)

    def extra_repr(self) -> str:
        return ", ".join(f"{k}: {tuple(self.params(k)[0].shape)}" for k in self._keys)
