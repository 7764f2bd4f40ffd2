"""The 3D Gaussian scene in the standard 3DGS parameterisation (INRIA layout, gsplat names).

Frames and units: means in the world frame (metres); ``log_scales`` are natural logs of the per-axis standard
deviations (metres); ``quats_wxyz`` rotate the Gaussian's local axes into the world (scalar first, normalised
at render time, zero norm = identity); ``logit_opacities`` pass through a sigmoid; colour is real spherical
harmonics (``sh0`` = DC, ``sh_rest`` = degrees 1..3, coefficient-major ``[N, K-1, 3]``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Iterator, Mapping, Sequence

import numpy as np
import torch

from umi_aug.errors import SplatError
from umi_aug.splat._constants import MAX_SH_DEGREE, SH_COEFFS
from umi_aug.splat.sh import rgb_to_sh

__all__ = ["Gaussians"]

Tensor = torch.Tensor

_NAMES = ("means", "log_scales", "quats_wxyz", "logit_opacities", "sh0", "sh_rest")


def _sh_degree_of(n_rest: int) -> int:
    for deg, k in enumerate(SH_COEFFS):
        if k - 1 == n_rest:
            return deg
    raise SplatError(
        f"Gaussians.sh_rest must hold (d+1)^2 - 1 coefficients for a degree d <= {MAX_SH_DEGREE} "
        f"(0, 3, 8 or 15), got {n_rest}"
    )


@dataclass
class Gaussians:
    """A set of 3D Gaussians (torch tensors; any float dtype/device, all the same).

    Attributes:
        means: Tensor,  # [N, 3] world frame, metres
        log_scales: Tensor,  # [N, 3] log of the standard deviations along the local axes (metres)
        quats_wxyz: Tensor,  # [N, 4] rotation local -> world, (w, x, y, z), need not be normalised
        logit_opacities: Tensor,  # [N] opacity = sigmoid(logit)
        sh0: Tensor,  # [N, 3] DC SH coefficient per RGB channel
        sh_rest: Tensor,  # [N, K-1, 3] higher SH coefficients, K = (sh_degree + 1)^2 (K-1 = 0 allowed)
    """

    means: Tensor
    log_scales: Tensor
    quats_wxyz: Tensor
    logit_opacities: Tensor
    sh0: Tensor
    sh_rest: Tensor

    def __post_init__(self) -> None:
        self._check_shapes()

    # ----------------------------------------------------------------------------------------------- checks
    def _check_shapes(self) -> None:
        for name in _NAMES:
            v = getattr(self, name)
            if not isinstance(v, torch.Tensor):
                raise SplatError(f"Gaussians.{name} must be a torch.Tensor, got {type(v).__name__}")
            if not v.is_floating_point():
                raise SplatError(f"Gaussians.{name} must be floating point, got {v.dtype}")
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        expect = {
            "means": (n, 3),
            "log_scales": (n, 3),
            "quats_wxyz": (n, 4),
            "logit_opacities": (n,),
            "sh0": (n, 3),
        }
        if self.means.ndim != 2 or self.means.shape[1] != 3:
            raise SplatError(f"Gaussians.means must have shape [N, 3], got {tuple(self.means.shape)}")
        for name, shape in expect.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise SplatError(f"Gaussians.{name} must have shape {list(shape)} (N = {n}), got {list(got)}")
        r = self.sh_rest
        if r.ndim != 3 or r.shape[0] != n or r.shape[2] != 3:
            raise SplatError(f"Gaussians.sh_rest must have shape [N, K-1, 3] (N = {n}), got {list(r.shape)}")
        _sh_degree_of(r.shape[1])
        dt, dev = self.means.dtype, self.means.device
        for name in _NAMES:
            v = getattr(self, name)
            if v.dtype != dt or v.device != dev:
                raise SplatError(
                    f"Gaussians.{name} has dtype/device {v.dtype}/{v.device}, expected {dt}/{dev} like means"
                )

    def validate(self) -> "Gaussians":
        """Raise :class:`SplatError` naming the field and the first offending row if any value is non-finite;
        returns ``self``."""
        self._check_shapes()
        for name in _NAMES:
            v = getattr(self, name).detach()
            bad = ~torch.isfinite(v.reshape(v.shape[0], -1)).all(dim=1) if v.numel() else torch.zeros(0, dtype=bool)
            if bool(bad.any()):
                i = int(torch.nonzero(bad)[0, 0])
                raise SplatError(f"Gaussians.{name}: non-finite value in row {i}: {v[i].tolist()}")
        return self

    # ------------------------------------------------------------------------------------------- properties
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def n(self) -> int:
        return len(self)

    @property
    def sh_degree(self) -> int:
        """Largest SH degree stored (0..3)."""
        return _sh_degree_of(self.sh_rest.shape[1])

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def scales(self) -> Tensor:
        """``exp(log_scales)`` ``[N, 3]`` metres."""
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:
        """``sigmoid(logit_opacities)`` ``[N]``."""
        return torch.sigmoid(self.logit_opacities)

    @property
    def sh(self) -> Tensor:
        """All SH coefficients ``[N, K, 3]`` (DC first)."""
        return torch.cat([self.sh0[:, None, :], self.sh_rest], dim=1)

    def tensors(self) -> dict[str, Tensor]:
        """The six parameter tensors by name (same objects, not copies)."""
        return {name: getattr(self, name) for name in _NAMES}

    def __iter__(self) -> Iterator[Tensor]:
        return iter(self.tensors().values())

    # --------------------------------------------------------------------------------------- conversions
    def _map(self, fn) -> "Gaussians":
        return Gaussians(**{name: fn(getattr(self, name)) for name in _NAMES})

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> "Gaussians":
        return self._map(lambda t: t.to(dtype=dtype or t.dtype, device=device or t.device))

    def detach(self) -> "Gaussians":
        return self._map(lambda t: t.detach())

    def clone(self) -> "Gaussians":
        return self._map(lambda t: t.clone())

    def requires_grad_(self, requires_grad: bool = True) -> "Gaussians":
        for t in self:
            t.requires_grad_(requires_grad)
        return self

    def select(self, index: Tensor | np.ndarray | slice | Sequence[int]) -> "Gaussians":
        """Subset (boolean mask or integer indices) along N."""
        if isinstance(index, np.ndarray):
            index = torch.as_tensor(index, device=self.device)
        return self._map(lambda t: t[index])

    def with_sh_degree(self, degree: int) -> "Gaussians":
        """Copy with ``sh_rest`` truncated (or zero-padded) to ``degree``."""
        if not 0 <= int(degree) <= MAX_SH_DEGREE:
            raise SplatError(f"SH degree must be in [0, {MAX_SH_DEGREE}], got {degree!r}")
        k = SH_COEFFS[int(degree)] - 1
        r = self.sh_rest
        if r.shape[1] >= k:
            rest = r[:, :k]
        else:
            rest = torch.cat([r, r.new_zeros(r.shape[0], k - r.shape[1], 3)], dim=1)
        return Gaussians(self.means, self.log_scales, self.quats_wxyz, self.logit_opacities, self.sh0, rest)

    @staticmethod
    def cat(parts: Sequence["Gaussians"]) -> "Gaussians":
        """Concatenate along N (the SH degree of the result is the largest; lower ones are zero-padded)."""
        if not parts:
            raise SplatError("Gaussians.cat needs at least one set")
        deg = max(p.sh_degree for p in parts)
        parts = [p.with_sh_degree(deg) for p in parts]
        return Gaussians(**{name: torch.cat([getattr(p, name) for p in parts], dim=0) for name in _NAMES})

    def numpy(self) -> dict[str, np.ndarray]:
        """Detached numpy copies keyed by field name."""
        return {name: getattr(self, name).detach().cpu().numpy() for name in _NAMES}

    @classmethod
    def from_numpy(
        cls, arrays: Mapping[str, np.ndarray], dtype: torch.dtype = torch.float32, device: str = "cpu"
    ) -> "Gaussians":
        """Build from numpy arrays keyed by field name (``sh_rest`` may be missing: degree 0)."""
        missing = [n for n in _NAMES[:5] if n not in arrays]
        if missing:
            raise SplatError(f"Gaussians.from_numpy: missing arrays {missing}")
        vals = dict(arrays)
        if "sh_rest" not in vals:
            vals["sh_rest"] = np.zeros((np.shape(vals["means"])[0], 0, 3))
        return cls(**{n: torch.as_tensor(np.asarray(vals[n]), dtype=dtype, device=device) for n in _NAMES})

    @classmethod
    def empty(cls, sh_degree: int = 0, dtype: torch.dtype = torch.float32) -> "Gaussians":
        k = SH_COEFFS[sh_degree]
        z = lambda *s: torch.zeros(s, dtype=dtype)  # noqa: E731
        return cls(z(0, 3), z(0, 3), z(0, 4), z(0), z(0, 3), z(0, k - 1, 3))

    @classmethod
    def from_points(
        cls,
        points: np.ndarray,  # [N, 3] world, metres
        colors: np.ndarray,  # [N, 3] RGB in [0, 1]
        scale: np.ndarray | float,  # [N] or scalar, metres (isotropic initial standard deviation)
        opacity: float = 0.1,
        sh_degree: int = 3,
        dtype: torch.dtype = torch.float32,
    ) -> "Gaussians":
        """Isotropic Gaussians at points with DC colour (the usual SfM / random initialisation)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        n = pts.shape[0]
        rgb = np.asarray(colors, dtype=np.float64).reshape(n, 3)
        s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (n,))
        if not (0.0 < opacity < 1.0):
            raise SplatError(f"Gaussians.from_points: opacity must be in (0, 1), got {opacity!r}")
        if np.any(s <= 0) or not np.all(np.isfinite(s)):
            raise SplatError("Gaussians.from_points: scale must be positive and finite")
        quats = np.zeros((n, 4))
        quats[:, 0] = 1.0
        arrays = {
            "means": pts,
            "log_scales": np.repeat(np.log(s)[:, None], 3, axis=1),
            "quats_wxyz": quats,
            "logit_opacities": np.full(n, np.log(opacity / (1.0 - opacity))),
            "sh0": rgb_to_sh(torch.as_tensor(rgb)).numpy(),
            "sh_rest": np.zeros((n, SH_COEFFS[sh_degree] - 1, 3)),
        }
        return cls.from_numpy(arrays, dtype=dtype)

    def __repr__(self) -> str:
        return f"Gaussians(n={self.n}, sh_degree={self.sh_degree}, dtype={self.dtype}, device={self.device})"

    def __eq__(self, other: object) -> bool:  # exact (bitwise for finite values) equality
        if not isinstance(other, Gaussians):
            return NotImplemented
        return all(
            getattr(self, f.name).shape == getattr(other, f.name).shape
            and torch.equal(getattr(self, f.name), getattr(other, f.name))
            for f in fields(self)
        )

    __hash__ = None  # type: ignore[assignment]
