"""Cheap shape checks and dtype handling for the torch geometry API (no value-dependent branching)."""

from __future__ import annotations

from typing import Sequence

import torch

from umi_aug.errors import GeometryError
from umi_aug.geometry._checks import fmt_trailing
from umi_aug.geometry._constants import JAC_SERIES_ANGLE, JAC_SERIES_ANGLE_F32, NORM_EPS


def as_tensor(x, name: str, func: str, trailing: Sequence[int] = ()) -> torch.Tensor:
    """Tensor with a floating dtype (non-float input → default dtype) and the expected trailing shape."""
    if not isinstance(x, torch.Tensor):
        x = torch.as_tensor(x)
    if not x.is_floating_point():
        x = x.to(torch.get_default_dtype())
    k = len(trailing)
    if x.dim() < k or tuple(x.shape[x.dim() - k:]) != tuple(trailing):
        raise GeometryError(f"{func}: `{name}` has shape {tuple(x.shape)}; expected {fmt_trailing(trailing)}")
    return x


def jac_threshold(dtype: torch.dtype) -> float:
    return JAC_SERIES_ANGLE if dtype == torch.float64 else JAC_SERIES_ANGLE_F32


def norm_eps(dtype: torch.dtype) -> float:
    return NORM_EPS if dtype == torch.float64 else 1e-6


def safe_norm(v: torch.Tensor, eps2: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(‖v‖ with zero gradient where ‖v‖² <= eps2, mask ‖v‖² > eps2) — never NaN in backward."""
    n2 = (v * v).sum(-1)
    pos = n2 > eps2
    n = torch.where(pos, torch.sqrt(torch.where(pos, n2, torch.ones_like(n2))), torch.zeros_like(n2))
    return n, pos
