"""Gaussian model container and spherical harmonics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from umi_aug.errors import SplatError
from umi_aug.splat import Gaussians, eval_sh, rgb_to_sh, sh_basis
from umi_aug.splat.scenes import random_gaussians
from tests.splat._helpers import gopro_small


def _fibonacci_sphere(n: int) -> torch.Tensor:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    phi = math.pi * (1 + 5**0.5) * i
    return torch.as_tensor(np.stack([r * np.cos(phi), r * np.sin(phi), z], -1))


def test_sh_basis_is_orthonormal():
    d = _fibonacci_sphere(200_000)
    Y = sh_basis(3, d)
    gram = (Y.T @ Y) * (4 * math.pi / d.shape[0])
    np.testing.assert_allclose(gram.numpy(), np.eye(16), atol=2e-4)


def test_sh_known_values_and_degree_truncation(rng):
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    Y = sh_basis(1, d)
    c0, c1 = 0.28209479177387814, 0.4886025119029199
    np.testing.assert_allclose(Y.numpy(), [[c0, 0, c1, 0], [c0, 0, 0, -c1], [c0, -c1, 0, 0]], atol=1e-15)
    sh = torch.as_tensor(rng.normal(size=(3, 16, 3)))
    for deg in range(4):
        k = (deg + 1) ** 2
        ref = (sh_basis(deg, d)[..., None] * sh[:, :k]).sum(-2)
        np.testing.assert_allclose(eval_sh(deg, sh, d).numpy(), ref.numpy(), rtol=1e-14)
    rgb = torch.tensor([[0.2, 0.5, 0.9]], dtype=torch.float64)
    np.testing.assert_allclose((eval_sh(0, rgb_to_sh(rgb)[:, None, :], d[:1]) + 0.5).numpy(), rgb.numpy())
    with pytest.raises(SplatError):
        sh_basis(4, d)
    with pytest.raises(SplatError):
        eval_sh(3, sh[:, :9], d)


def test_gaussians_container(rng):
    g = random_gaussians(10, rng, gopro_small(), sh_degree=2)
    assert g.n == 10 and len(g) == 10 and g.sh_degree == 2 and g.sh.shape == (10, 9, 3)
    h = Gaussians.cat([g, g.with_sh_degree(0), g.with_sh_degree(3)])
    assert h.n == 30 and h.sh_degree == 3
    assert torch.equal(h.sh_rest[10:20], torch.zeros(10, 15, 3, dtype=torch.float64))
    assert g.select(np.arange(10) < 3).n == 3
    assert g.to(torch.float32).dtype == torch.float32
    assert g.clone() == g and g.detach() == g
    g.requires_grad_(True)
    assert all(t.requires_grad for t in g)
    p = Gaussians.from_points(rng.normal(size=(7, 3)), rng.uniform(size=(7, 3)), 0.01, opacity=0.1)
    assert p.sh_degree == 3 and torch.allclose(p.opacities, torch.full((7,), 0.1))
    with pytest.raises(SplatError, match="means"):
        Gaussians(torch.zeros(3, 2), *[t for t in list(g.detach())[1:]])
    with pytest.raises(SplatError, match="sh_rest"):
        Gaussians(*list(g.detach())[:5], torch.zeros(10, 5, 3, dtype=torch.float64))
    bad = g.detach().clone()
    bad.log_scales[4, 1] = float("nan")
    with pytest.raises(SplatError, match="log_scales.*row 4"):
        bad.validate()
    assert Gaussians.empty(2).sh_degree == 2
