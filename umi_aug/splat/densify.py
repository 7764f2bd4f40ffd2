"""Budgeted densification: 3DGS-MCMC (Kheradmand et al. 2024; gsplat ``MCMCStrategy``).

* **Relocation** (:func:`relocate_dead`): Gaussians with opacity ``<= min_opacity`` are "dead"; each is moved onto
  an alive Gaussian sampled with probability proportional to opacity. A Gaussian sampled ``r - 1`` times ends up
  as ``r`` copies whose opacity ``o' = 1 - (1 - o)^(1/r)`` and scale ``s' = s o / sum_i sum_k C(i-1, k) (-1)^k
  o'^(k+1) / sqrt(k+1)`` keep the rendered contribution (:func:`relocation_opacity_scale`). The moved rows and
  their sources restart their Adam moments.
* **Growth** (:func:`grow`): every refinement adds ``min(cap, growth_factor * N) - N`` copies of Gaussians
  sampled by opacity (same correction), so the count rises geometrically to the budget ``max_gaussians`` and never
  exceeds it.
* **Noise** (:func:`inject_noise`): every step, means get ``Sigma (noise_scale * eps)`` with ``eps ~ N(0, I)``,
  gated by ``sigmoid(-k (o - (1 - x0)))`` so that only near-transparent Gaussians wander (SGLD exploration).

All randomness comes from the ``torch.Generator`` passed in (same seed -> same result). The correction is computed
in float64 (the alternating binomial sum cancels badly in float32 for large ``r``).
"""

from __future__ import annotations

import math

import torch

from umi_aug.geometry.se3_torch import quat_wxyz_to_matrix
from umi_aug.splat import _optim_kernels as OK
from umi_aug.splat.optim import GaussianAdam

__all__ = ["MAX_RELOCATION_RATIO", "relocation_opacity_scale", "relocate_dead", "grow", "inject_noise"]

Tensor = torch.Tensor

#: Copies of one Gaussian made in one relocation are capped at this (gsplat ``n_max = 51``).
MAX_RELOCATION_RATIO: int = 51
#: Gate of the position noise: ``1 / (1 + exp(-NOISE_GATE_K (1 - o - NOISE_GATE_X0)))``.
NOISE_GATE_K: float = 100.0
NOISE_GATE_X0: float = 0.995
_OPACITY_EPS = float(torch.finfo(torch.float32).eps)


def _relocation_table(n_max: int = MAX_RELOCATION_RATIO) -> Tensor:
    """``A[r, k] = sum_{i=k+1..r} C(i-1, k) (-1)^k / sqrt(k+1)`` (float64, ``[n_max + 1, n_max]``)."""
    A = torch.zeros(n_max + 1, n_max, dtype=torch.float64)
    for r in range(1, n_max + 1):
        for k in range(r):
            A[r, k] = sum(math.comb(i - 1, k) for i in range(k + 1, r + 1)) * (-1.0) ** k / math.sqrt(k + 1)
    return A


_TABLE = _relocation_table()


def relocation_opacity_scale(opacities: Tensor, scales: Tensor, ratios: Tensor) -> tuple[Tensor, Tensor]:
    """Opacity and scales of each of ``ratios`` copies of a Gaussian (3DGS-MCMC eq. 9, gsplat ``compute_relocation``).

    Args:
        opacities: Tensor,  # [K] in (0, 1)
        scales: Tensor,  # [K, 3] standard deviations, metres
        ratios: Tensor,  # [K] int, number of copies (clamped to [1, MAX_RELOCATION_RATIO])
    Returns:
        ``(new_opacities [K], new_scales [K, 3])`` in the dtype of the inputs.
    """
    o = opacities.double()
    r = ratios.long().clamp(1, MAX_RELOCATION_RATIO)
    new_o = 1.0 - (1.0 - o) ** (1.0 / r.double())
    powers = new_o[:, None] ** torch.arange(1, MAX_RELOCATION_RATIO + 1, dtype=torch.float64)[None, :]
    denom = (_TABLE[r] * powers).sum(-1)
    coeff = o / denom
    return new_o.to(opacities.dtype), (coeff[:, None] * scales.double()).to(scales.dtype)


def _sample_and_correct(params: dict[str, Tensor], candidates: Tensor, n: int, gen: torch.Generator,
                        min_opacity: float) -> Tensor:
    """Sample ``n`` rows of ``candidates`` by opacity, apply the copy correction to the sampled rows in place;
    return the sampled rows ``[n]``."""
    with torch.no_grad():
        op = torch.sigmoid(params["logit_opacities"])
        probs = op[candidates].double()
        sampled = candidates[torch.multinomial(probs, n, replacement=True, generator=gen)]
        counts = torch.bincount(sampled, minlength=op.shape[0])
        new_o, new_s = relocation_opacity_scale(op[sampled], torch.exp(params["log_scales"][sampled]),
                                                counts[sampled] + 1)
        new_o = new_o.clamp(min_opacity, 1.0 - _OPACITY_EPS)
        params["logit_opacities"][sampled] = torch.logit(new_o)
        params["log_scales"][sampled] = torch.log(new_s)
    return sampled


def relocate_dead(params: dict[str, Tensor], opt: GaussianAdam, gen: torch.Generator, min_opacity: float) -> int:
    """Move every dead Gaussian (opacity ``<= min_opacity``) onto a live one (in place); returns how many moved."""
    with torch.no_grad():
        op = torch.sigmoid(params["logit_opacities"])
        dead = torch.nonzero(op <= min_opacity).squeeze(-1)
        alive = torch.nonzero(op > min_opacity).squeeze(-1)
        n = int(dead.numel())
        if n == 0 or alive.numel() == 0:
            return 0
        sampled = _sample_and_correct(params, alive, n, gen, min_opacity)
        for t in params.values():
            t[dead] = t[sampled]
        opt.reset_rows(torch.cat([dead, sampled]))
    return n


def grow(params: dict[str, Tensor], opt: GaussianAdam, gen: torch.Generator, max_gaussians: int,
         growth_factor: float, min_opacity: float) -> int:
    """Add ``min(max_gaussians, floor(growth_factor N)) - N`` Gaussians (copies of opacity-sampled ones, corrected);
    replaces the tensors in ``params`` (new leaves) and extends ``opt``. Returns how many were added."""
    n_cur = int(params["means"].shape[0])
    n_new = max(0, min(int(max_gaussians), int(growth_factor * n_cur)) - n_cur)
    if n_new == 0:
        return 0
    with torch.no_grad():
        sampled = _sample_and_correct(params, torch.arange(n_cur), n_new, gen, min_opacity)
        for name in list(params):
            t = params[name].detach()
            params[name] = torch.cat([t, t[sampled]], dim=0).requires_grad_(True)
        opt.params = params
        opt.reset_rows(sampled)
        opt.append_rows(n_new)
    return n_new


def inject_noise(params: dict[str, Tensor], scale: float, gen: torch.Generator) -> None:
    """SGLD position noise (in place): ``means += Sigma eps * scale * gate(opacity)``, ``Sigma`` the world
    covariance (m^2), ``scale`` = ``noise_lr * lr_means``. One numba pass over the Gaussians
    (:func:`umi_aug.splat._optim_kernels.position_noise_kernel`) with ``eps`` drawn from ``gen`` as
    :func:`_inject_noise_torch` (the reference) draws it."""
    names = ("means", "logit_opacities", "quats_wxyz", "log_scales")
    ts = [params[k] for k in names]
    dt = ts[0].dtype
    if not all(t.device.type == "cpu" and t.dtype == dt and t.is_contiguous() for t in ts) or dt not in (
            torch.float32, torch.float64):
        _inject_noise_torch(params, scale, gen)
        return
    with torch.no_grad():
        eps = torch.randn(ts[0].shape, generator=gen, dtype=dt)
        means, logit_op, quats, log_scales = (t.detach().numpy() for t in ts)
        OK.position_noise_kernel(means, logit_op, quats, log_scales, eps.numpy(), float(scale), NOISE_GATE_K,
                                 NOISE_GATE_X0)


def _inject_noise_torch(params: dict[str, Tensor], scale: float, gen: torch.Generator) -> None:
    """:func:`inject_noise` with torch operations (the reference of ``tests/splat/test_optim_kernels.py``)."""
    with torch.no_grad():
        means = params["means"]
        op = torch.sigmoid(params["logit_opacities"])
        gate = torch.sigmoid(NOISE_GATE_K * ((1.0 - op) - NOISE_GATE_X0))
        R = quat_wxyz_to_matrix(params["quats_wxyz"])
        s2 = torch.exp(2.0 * params["log_scales"])
        eps = torch.randn(means.shape, generator=gen, dtype=means.dtype)
        # Sigma eps = R diag(s^2) R^T eps
        local = torch.einsum("nji,nj->ni", R, eps) * s2
        noise = torch.einsum("nij,nj->ni", R, local)
        means.add_(noise * (gate * scale)[:, None])
