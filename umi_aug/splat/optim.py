"""Adam over the Gaussian parameter tensors, with row-wise state surgery for densification / relocation.

``torch.optim.Adam`` keys its state by tensor object, which makes growing or relocating Gaussians (new tensors,
rows copied or reset) clumsy; this small optimiser keeps ``exp_avg`` / ``exp_avg_sq`` per parameter name, so
:mod:`umi_aug.splat.densify` can reset rows (:meth:`GaussianAdam.reset_rows`) and append rows
(:meth:`GaussianAdam.append_rows`) and the state round-trips through a checkpoint (:meth:`state_dict`).
Update rule: PyTorch's Adam (``betas = (0.9, 0.999)``, ``eps = 1e-15`` as in 3DGS, bias-corrected, one shared
step count). :meth:`GaussianAdam.step` runs it as one numba pass per parameter (:mod:`umi_aug.splat._optim_kernels`);
:meth:`GaussianAdam._step_torch` is the torch reference it is tested against.
"""

from __future__ import annotations

from typing import Mapping

import torch

from umi_aug.errors import SplatError
from umi_aug.splat import _optim_kernels as OK

__all__ = ["GaussianAdam"]

Tensor = torch.Tensor


def _kernel_can_update(p: Tensor, g: Tensor, m: Tensor, v: Tensor) -> bool:
    """Whether the numba kernel can update ``p`` in place: CPU float32/float64, one dtype, contiguous (the gradient
    may be strided: it is copied), at least one row."""
    return (p.device.type == "cpu" and p.dtype in (torch.float32, torch.float64) and p.shape[0] > 0
            and all(t.device.type == "cpu" and t.dtype == p.dtype and t.shape == p.shape for t in (g, m, v))
            and p.is_contiguous() and m.is_contiguous() and v.is_contiguous())


class GaussianAdam:
    """Adam over named ``[N, ...]`` parameter tensors (all with the same N).

    Args:
        params: name -> leaf tensor with ``requires_grad`` (replaced in place by the densifier when N changes).
        betas, eps: Adam constants.
    """

    def __init__(self, params: dict[str, Tensor], betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15):
        self.params = params
        self.betas = (float(betas[0]), float(betas[1]))
        self.eps = float(eps)
        self.step_count = 0
        self.exp_avg = {k: torch.zeros_like(v.detach()) for k, v in params.items()}
        self.exp_avg_sq = {k: torch.zeros_like(v.detach()) for k, v in params.items()}

    @torch.no_grad()
    def step(self, lrs: Mapping[str, float], active: Mapping[str, int] | None = None) -> None:
        """One Adam update of every parameter with a gradient (``lrs``: name -> learning rate).

        ``active``: name -> how many leading entries along dim 1 can have a gradient (``sh_rest``'s coefficients up
        to the rendered SH degree); the entries after them are skipped. Only for entries whose gradient and both
        moments are zero (a coefficient never rendered so far), which Adam leaves unchanged: the result is the same
        as the full update, for a fraction of the work (``sh_rest`` is 45 of a Gaussian's 59 numbers).
        """
        self.step_count += 1
        b1, b2 = self.betas
        bc1 = 1.0 - b1**self.step_count
        bc2 = 1.0 - b2**self.step_count
        for name, p in self.params.items():
            g = p.grad
            if g is None:
                continue
            m, v = self.exp_avg[name], self.exp_avg_sq[name]
            if not _kernel_can_update(p, g, m, v):
                self._update_torch(name, p, lrs, active, bc1, bc2)
                continue
            n = p.shape[0]
            k = None if active is None else active.get(name)
            cols = p[:1].numel()  # numbers per Gaussian
            if k is not None and p.ndim >= 2 and k < p.shape[1]:
                if k <= 0:
                    continue
                cols = cols // p.shape[1] * k  # the leading k entries along dim 1 are the leading columns
            OK.adam_rows_kernel(p.detach().view(n, -1).numpy(), g.detach().contiguous().view(n, -1).numpy(),
                                m.view(n, -1).numpy(), v.view(n, -1).numpy(), cols, float(lrs[name]) / bc1, b1, b2,
                                bc2, self.eps)

    @torch.no_grad()
    def _step_torch(self, lrs: Mapping[str, float], active: Mapping[str, int] | None = None) -> None:
        """:meth:`step` with torch operations (the reference of ``tests/splat/test_optim_kernels.py``)."""
        self.step_count += 1
        b1, b2 = self.betas
        bc1 = 1.0 - b1**self.step_count
        bc2 = 1.0 - b2**self.step_count
        for name, p in self.params.items():
            if p.grad is not None:
                self._update_torch(name, p, lrs, active, bc1, bc2)

    @torch.no_grad()
    def _update_torch(self, name: str, p: Tensor, lrs: Mapping[str, float], active: Mapping[str, int] | None,
                      bc1: float, bc2: float) -> None:
        """Adam on parameter ``name`` with torch operations (bias corrections ``bc1``, ``bc2`` of this step)."""
        b1, b2 = self.betas
        g = p.grad
        m, v = self.exp_avg[name], self.exp_avg_sq[name]
        k = None if active is None else active.get(name)
        if k is not None and p.ndim >= 2 and k < p.shape[1]:
            if k <= 0:
                return
            p, g, m, v = p[:, :k], g[:, :k], m[:, :k], v[:, :k]  # views: updated in place
        m.mul_(b1).add_(g, alpha=1.0 - b1)
        v.mul_(b2).addcmul_(g, g, value=1.0 - b2)
        denom = (v / bc2).sqrt_().add_(self.eps)
        p.addcdiv_(m, denom, value=-float(lrs[name]) / bc1)

    def zero_grad(self) -> None:
        for p in self.params.values():
            p.grad = None

    @torch.no_grad()
    def reset_rows(self, rows: Tensor) -> None:
        """Zero the moments of Gaussians ``rows [K]`` (they restart like fresh parameters)."""
        for name in self.params:
            self.exp_avg[name][rows] = 0
            self.exp_avg_sq[name][rows] = 0

    def append_rows(self, n: int) -> None:
        """Extend every moment by ``n`` zero rows (after the parameters were grown by ``n``)."""
        for name in self.params:
            for st in (self.exp_avg, self.exp_avg_sq):
                t = st[name]
                st[name] = torch.cat([t, t.new_zeros((n, *t.shape[1:]))], dim=0)
        self.check()

    def check(self) -> None:
        """Raise :class:`SplatError` unless every moment has its parameter's shape."""
        for name, p in self.params.items():
            for label, st in (("exp_avg", self.exp_avg), ("exp_avg_sq", self.exp_avg_sq)):
                if st[name].shape != p.shape:
                    raise SplatError(f"GaussianAdam: {label}[{name!r}] has shape {list(st[name].shape)} but the "
                                     f"parameter has {list(p.shape)}")

    def state_dict(self) -> dict:
        return {"step_count": self.step_count, "betas": self.betas, "eps": self.eps,
                "exp_avg": {k: v.clone() for k, v in self.exp_avg.items()},
                "exp_avg_sq": {k: v.clone() for k, v in self.exp_avg_sq.items()}}

    def load_state_dict(self, state: Mapping) -> None:
        self.step_count = int(state["step_count"])
        self.betas = tuple(state["betas"])  # type: ignore[assignment]
        self.eps = float(state["eps"])
        self.exp_avg = {k: v.clone() for k, v in state["exp_avg"].items()}
        self.exp_avg_sq = {k: v.clone() for k, v in state["exp_avg_sq"].items()}
        self.check()
