"""Kannala–Brandt model in torch: agreement with numpy, dtype, autograd (incl. r = 0), Newton modes."""

from __future__ import annotations

import math

import numpy as np
import pytest

import torch  # noqa: E402

from tests.camera._kb_helpers import (  # noqa: E402
    angle_between,
    gopro,
    gopro_224,
    intrinsics_zoo,
    random_intrinsics,
    rays_at,
    special_thetas,
)
from umi_aug.camera import kb  # noqa: E402
from umi_aug.camera import kb_torch as kt  # noqa: E402


def _t(a: np.ndarray, dtype=torch.float64) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a), dtype=dtype)


def _test_points(rng: np.random.Generator, intr) -> np.ndarray:
    """Random valid + invalid points, the optical axis, tiny r and theta > 90 deg."""
    theta = np.concatenate([rng.uniform(0, intr.theta_max, 400), special_thetas(intr), [2.5, math.pi]])
    pts = rays_at(theta, rng.uniform(-math.pi, math.pi, theta.size)) * rng.uniform(0.1, 5, theta.size)[:, None]
    extra = np.array([[0.0, 0.0, 0.0], [np.nan, 0, 1], [0.0, 0.0, 2.0], [1e-12, -1e-12, 1.0]])
    return np.concatenate([pts, extra])


@pytest.mark.parametrize("which", range(6))
def test_project_agrees_with_numpy(rng, which):
    intr = intrinsics_zoo(rng)[which]
    pts = _test_points(rng, intr)
    uv, valid = kb.project(pts, intr)
    uv_t, valid_t = kt.project(_t(pts), intr)
    assert uv_t.dtype == torch.float64
    assert np.array_equal(valid_t.numpy(), valid)
    np.testing.assert_allclose(uv_t.numpy(), uv, rtol=0, atol=1e-10)
    J, vj = kb.project_jacobian(pts, intr)
    J_t, vj_t = kt.project_jacobian(_t(pts), intr)
    assert np.array_equal(vj_t.numpy(), vj)
    np.testing.assert_allclose(J_t.numpy(), J, rtol=0, atol=1e-10 * intr.fx)


@pytest.mark.parametrize("which", range(6))
def test_unproject_agrees_with_numpy(rng, which):
    intr = intrinsics_zoo(rng)[which]
    uv = rng.uniform([-20, -20], [intr.width + 20, intr.height + 20], size=(3000, 2))
    uv = np.concatenate([uv, [[intr.cx, intr.cy], [np.nan, 1.0], [np.inf, 0.0]]])
    rays, valid, n = kb.unproject(uv, intr, return_iterations=True)
    rays_t, valid_t, n_t = kt.unproject(_t(uv), intr, return_iterations=True)
    assert rays_t.dtype == torch.float64 and n_t.dtype == torch.int32
    assert np.array_equal(valid_t.numpy(), valid)
    assert angle_between(rays_t.numpy(), rays).max() <= 1e-10
    assert np.abs(rays_t.numpy() - rays).max() <= 1e-10
    assert np.abs(n_t.numpy() - n).max() <= 2  # same algorithm; last-ulp differences may shift a stop
    assert torch.isfinite(rays_t).all()


def test_float32_preserved_and_accurate(rng):
    intr = gopro_224()
    uv = rng.uniform(0, 224, size=(5000, 2))
    rays32, valid32 = kt.unproject(_t(uv, torch.float32), intr)
    assert rays32.dtype == torch.float32
    rays, valid = kb.unproject(uv, intr)
    inner = valid & (np.hypot(uv[:, 0] - intr.cx, uv[:, 1] - intr.cy) < 0.98 * intr.image_circle_radius_px[0])
    assert np.array_equal(valid32.numpy()[inner], valid[inner])
    assert angle_between(rays32.double().numpy()[inner], rays[inner]).max() < 2e-6
    uv32, v32 = kt.project(rays32, intr)
    assert uv32.dtype == torch.float32
    assert np.abs(uv32.double().numpy() - uv)[inner].max() < 1e-3


def test_fixed_iteration_mode_matches_adaptive(rng):
    intr = gopro()
    theta = rng.uniform(0, math.pi / 2, 2000)
    uv, _ = kb.project(rays_at(theta, rng.uniform(-math.pi, math.pi, theta.size)), intr)
    r_fixed, v1 = kt.unproject(_t(uv), intr, n_iter=8)
    r_adapt, v2 = kt.unproject(_t(uv), intr)
    assert v1.all() and v2.all()
    assert (r_fixed - r_adapt).abs().max() < 1e-14
    # float32: 5 updates reach float32 rounding
    r32, _ = kt.unproject(_t(uv, torch.float32), intr, n_iter=5)
    assert angle_between(r32.double().numpy(), r_adapt.numpy()).max() < 1e-6


def test_autograd_jacobian_matches_analytic(rng):
    intr = random_intrinsics(rng)
    g = gopro()
    cases = [
        (intr, np.array([0.0, 0.0, 1.7])),  # r = 0 exactly
        (intr, np.array([1e-300, 0.0, 1.0])),
        (intr, np.array([1e-9, -2e-9, 0.8])),  # tiny r
        (intr, np.array([kb.SMALL_T * 0.999, 0.0, 1.0])),
        (intr, np.array([kb.SMALL_T * 1.001, 0.0, 1.0])),
        (g, rays_at(math.radians(100), 0.7) * 3.0),  # theta > 90 deg
        (g, rays_at(math.radians(90), -2.0)),
    ]
    for intr_i, p in cases:
        pt = _t(p).requires_grad_(True)
        Ja = torch.autograd.functional.jacobian(lambda q: kt.project(q, intr_i)[0], pt)
        J, valid = kb.project_jacobian(p, intr_i)
        assert valid
        assert torch.isfinite(Ja).all()
        np.testing.assert_allclose(Ja.numpy(), J, rtol=0, atol=1e-9 * intr_i.fx)
    # batched random points
    pts = _test_points(rng, g)
    pts = pts[kb.project(pts, g)[1]]
    Ja = torch.func.vmap(torch.func.jacrev(lambda q: kt.project(q, g)[0]))(_t(pts))
    J, _ = kb.project_jacobian(pts, g)
    np.testing.assert_allclose(Ja.numpy(), J, rtol=0, atol=1e-8 * g.fx)


def test_gradients_finite_everywhere():
    intr = gopro()
    pts = _t(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [np.nan, 1.0, 1.0], [0.0, 0.0, -1.0], [1e-8, 0, 1]]))
    pts.requires_grad_(True)
    uv, _ = kt.project(pts, intr)
    uv.sum().backward()
    assert torch.isfinite(pts.grad).all()
    uv = _t(np.array([[intr.cx, intr.cy], [0.0, 0.0], [np.inf, 1.0], [intr.cx + 1e-9, intr.cy], [1e300, 1e300]]))
    uv.requires_grad_(True)
    rays, valid = kt.unproject(uv, intr)
    assert valid.tolist() == [True, False, False, True, False]
    rays.sum().backward()
    assert torch.isfinite(uv.grad).all()
    assert (uv.grad[[1, 2, 4]] == 0).all()


def test_unproject_gradient_inverts_projection_jacobian(rng):
    """project(unproject(uv)) = uv  =>  J_project(ray) @ d ray / d uv = I (2x2), incl. theta > 90 deg."""
    intr = gopro()
    theta = np.concatenate([rng.uniform(0.05, math.radians(100), 50), [0.0, 1e-7]])
    uv, _ = kb.project(rays_at(theta, rng.uniform(-math.pi, math.pi, theta.size)), intr)
    # under vmap the loop needs a fixed iteration count (no data-dependent control flow)
    Ju = torch.func.vmap(torch.func.jacrev(lambda q: kt.unproject(q, intr, n_iter=40)[0]))(_t(uv))  # [N, 3, 2]
    rays, _ = kb.unproject(uv, intr)
    Jp, _ = kb.project_jacobian(rays, intr)  # [N, 2, 3]
    prod = np.einsum("nij,njk->nik", Jp, Ju.numpy())
    np.testing.assert_allclose(prod, np.broadcast_to(np.eye(2), prod.shape), rtol=0, atol=1e-9)


def test_gradcheck_small():
    intr = random_intrinsics(np.random.default_rng(0))
    p = torch.tensor([[0.1, -0.2, 1.0], [0.5, 0.3, -0.1], [1e-6, 0.0, 1.0]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda q: kt.project(q, intr)[0], (p,))
    uv = torch.tensor([[intr.cx + 10.3, intr.cy - 40.1], [intr.cx + 1e-3, intr.cy]], dtype=torch.float64,
                      requires_grad=True)
    assert torch.autograd.gradcheck(lambda q: kt.unproject(q, intr)[0], (uv,))


def test_batched_and_integer_inputs(rng):
    intr = random_intrinsics(rng)
    pts = torch.randn(2, 5, 3, dtype=torch.float64)
    uv, valid = kt.project(pts, intr)
    assert uv.shape == (2, 5, 2) and valid.shape == (2, 5)
    rays, v = kt.unproject(uv, intr)
    assert rays.shape == (2, 5, 3)
    J, _ = kt.project_jacobian(pts, intr)
    assert J.shape == (2, 5, 2, 3)
    uv_int = torch.tensor([[int(intr.cx), int(intr.cy)]])
    rays, v = kt.unproject(uv_int, intr)
    assert rays.dtype == torch.get_default_dtype() and v.all()


def test_fused_project_with_jacobian_matches_separate_calls(rng):
    """The fused projection + Jacobian used by the splatter equals project() and project_jacobian()."""
    from umi_aug.camera import gopro_intrinsics_2_7k
    from umi_aug.camera import kb_torch

    intr = gopro_intrinsics_2_7k().umi_policy(224)
    pts = torch.as_tensor(rng.normal(size=(500, 3)))
    pts[:5] = torch.tensor([[0.0, 0, 1], [0, 0, -1], [0, 0, 0], [1e-9, 0, 1], [1, 0, -0.2]], dtype=pts.dtype)
    uv, J, valid = kb_torch.project_with_jacobian(pts, intr)
    uv_ref, valid_ref = kb_torch.project(pts, intr)
    J_ref, valid_j = kb_torch.project_jacobian(pts, intr)
    assert torch.equal(valid, valid_ref) and torch.equal(valid, valid_j)
    torch.testing.assert_close(uv[valid], uv_ref[valid], rtol=0, atol=1e-12)
    torch.testing.assert_close(J, J_ref, rtol=0, atol=0)
    assert torch.isfinite(uv).all() and torch.isfinite(J).all()
