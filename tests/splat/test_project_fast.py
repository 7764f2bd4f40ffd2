"""The numba projection with its hand-written backward (``project_gaussians(fast=True)``, :class:`ProjectGaussians`)
against the torch-autograd reference (``fast=False``) on fresh random Gaussians incl. extreme cases, against
finite differences (gradcheck on a tiny case, the KB Jacobian's tangent), and end to end through ``render``."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from umi_aug.camera import FisheyeIntrinsics
from umi_aug.geometry import make_pose, so3_exp
from umi_aug.splat import Gaussians, render
from umi_aug.splat import _project_kernels as PK
from umi_aug.splat._kernels import _kb_project_jacobian
from umi_aug.splat.project import project_gaussians
from umi_aug.splat.scenes import random_gaussians
from tests.splat._helpers import PARAMS, gopro_small, loss_weights, random_pose, rays_at, weighted_loss

def _lens(width: int = 64, height: int = 48) -> FisheyeIntrinsics:
    """UMI's GoPro KB lens (theta_max ~ 104 deg: rays past 90 deg are inside the image circle) with non-square
    pixels (fy = 1.04 fx), so that a mixed-up fx / fy shows."""
    g = gopro_small(width, height)
    return FisheyeIntrinsics(width, height, g.fx, 1.04 * g.fy, g.cx, g.cy, g.k)


OUTPUTS = ("means2d", "conics", "opacities", "colors", "depths", "cov2d")
FILTERS = ("inria", "mip", "none")


def _extreme_gaussians(rng: np.random.Generator, intr: FisheyeIntrinsics, T: np.ndarray, n: int,
                       dtype=torch.float64) -> Gaussians:
    """``n`` random Gaussians in view plus the hard cases, all in the camera ``T``'s frame mapped to the world:
    centres on / near the optical axis (r = 0, 1e-9, 1e-5, 1e-3 of z: the series branch, and 0.02: the direct
    branch), rays past 90 deg up to the lens limit and beyond it, behind the camera (incl. exactly on the back
    axis), at the camera centre, needle / pancake / tiny scales, rotations near pi (w ~ 0) and unnormalised or
    zero quaternions, low and high opacities."""
    g = random_gaussians(n, rng, intr, T, theta_max=min(intr.theta_max, 1.95), sigma_px_range=(0.5, 6.0),
                         dtype=torch.float64)
    th_max = intr.theta_max
    dirs = [rays_at(0.0, 0.0), rays_at(1e-9, 0.3), rays_at(1e-5, 2.0), rays_at(1e-3, -1.0), rays_at(0.02, 1.0),
            rays_at(math.pi / 2, 0.7), rays_at(0.5 * (math.pi / 2 + th_max), -2.5), rays_at(th_max - 1e-3, 2.9),
            rays_at(th_max + 0.05, 0.1), rays_at(math.pi - 0.01, 1.0), np.array([0.0, 0.0, -1.0])]
    k = len(dirs) * 3
    # each at its own distance (0.4, 1.3, 3.0 m, +0.1 % per direction): equal ray depths would leave their
    # compositing order to 1-ulp differences between two projections, and the images would differ where they overlap
    spread = 1.0 + 1e-3 * np.arange(len(dirs))[:, None]
    p_cam = np.concatenate([np.stack(dirs) * spread * d for d in (0.4, 1.3, 3.0)])
    p_cam = np.concatenate([p_cam, [[0.0, 0.0, 0.0], [0.0, 0.0, 0.005]]])  # at the centre / inside the near sphere
    k += 2
    means = p_cam @ T[:3, :3].T + T[:3, 3]
    log_s = np.log(rng.uniform(0.005, 0.05, (k, 3)))
    log_s[0::4, 0] -= 9.0  # needles
    log_s[1::4, 1:] -= 9.0  # pancakes (two thin axes)
    log_s[2::4] -= 6.0  # tiny: below a pixel
    q = rng.normal(size=(k, 4))
    q[0::3, 0] = rng.uniform(-1e-8, 1e-8, len(q[0::3]))  # rotations near pi
    q *= rng.uniform(0.1, 10.0, (k, 1))  # unnormalised
    q[5] = 0.0  # zero quaternion: identity
    extra = {
        "means": means, "log_scales": log_s, "quats_wxyz": q,
        "logit_opacities": rng.uniform(-6.0, 6.0, k), "sh0": rng.normal(size=(k, 3)),
        "sh_rest": 0.3 * rng.normal(size=(k, g.sh_rest.shape[1], 3)),
    }
    t = {name: torch.cat([getattr(g, name), torch.as_tensor(extra[name])]) for name in PARAMS}
    return Gaussians(**t).to(dtype)


def _loss(proj, w) -> torch.Tensor:
    return sum((getattr(proj, k) * w[k]).sum() for k in OUTPUTS)


def _weights(rng, proj) -> dict[str, torch.Tensor]:
    return {k: torch.as_tensor(rng.normal(size=tuple(getattr(proj, k).shape))) for k in OUTPUTS}


@pytest.mark.parametrize("filt", FILTERS)
def test_fast_projection_matches_reference_float64(rng, filt):
    intr = _lens()
    T = random_pose(rng)
    g = _extreme_gaussians(rng, intr, T, 150).requires_grad_(True)
    deg = int(rng.integers(0, 4))
    fast = project_gaussians(g, T, intr, deg, filt, fast=True)
    ref = project_gaussians(g, T, intr, deg, filt)
    assert torch.equal(fast.ids, ref.ids)
    assert 100 < len(ref) < g.n  # most visible, the behind / outside-the-lens / near ones culled
    for k in OUTPUTS:
        a, b = getattr(fast, k), getattr(ref, k)
        assert torch.isfinite(a).all(), k
        assert (a - b).abs().max().item() <= 1e-9 * (1.0 + b.abs().max().item()), k
    w = _weights(rng, ref)
    ga = torch.autograd.grad(_loss(fast, w), list(g))
    gb = torch.autograd.grad(_loss(ref, w), list(g))
    culled = torch.ones(g.n, dtype=torch.bool)
    culled[ref.ids] = False
    cond = _cov2d_condition(ref, g.n)
    for name, a, b in zip(PARAMS, ga, gb):
        assert torch.isfinite(a).all(), name
        assert (a[culled] == 0).all(), name  # culled Gaussians: exactly zero, as the reference
        scale = b.abs().max().item()
        assert (a - b).abs().max().item() <= 1e-6 * (1.0 + scale), (name, (a - b).abs().max().item(), scale)
        rel = ((a - b).abs() / (1.0 + b.abs())).reshape(g.n, -1).amax(dim=1)
        tol = 1e-6 + 100.0 * torch.finfo(torch.float64).eps * cond  # per Gaussian, see below
        assert (rel <= tol).all(), (name, int((rel / tol).argmax()), rel.max().item())


def _cov2d_condition(proj, n: int) -> torch.Tensor:
    """Per Gaussian: the condition number of its 2-D covariance ``[[a, b], [b, c]]`` (1 where culled). A pancake
    seen edge-on has one near 1e10; inverting it (the conic, and every gradient through it) loses ~cond × eps of
    float64, so the two paths may differ by ~1e-6 there while agreeing to ~1e-15 elsewhere (seen once:
    UMI_AUG_TEST_SEED=225065634, a log-scale gradient 1.1e-6 apart at cond 1.0e10)."""
    a, b, c = proj.cov2d.detach().unbind(-1)
    half_trace, root = 0.5 * (a + c), torch.sqrt(0.25 * (a - c) ** 2 + b ** 2)
    lam_max, lam_min = half_trace + root, (half_trace - root).clamp_min(1e-300)
    cond = torch.ones(n, dtype=torch.float64)
    cond[proj.ids] = (lam_max / lam_min).to(torch.float64)
    return cond


def test_fast_projection_float32_close_to_float64(rng):
    """float32 scene: the fast path computes in float64 inside, so its gradients agree with the float64 reference
    to float32 rounding (the float32 torch reference is the less accurate of the two)."""
    intr = _lens()
    T = random_pose(rng)
    g64 = random_gaussians(200, rng, intr, T, theta_max=1.8, sigma_px_range=(0.8, 6.0), dtype=torch.float64)
    g32 = g64.to(torch.float32)
    g64 = g32.to(torch.float64).requires_grad_(True)  # the very same values
    g32 = g32.requires_grad_(True)
    fast = project_gaussians(g32, T, intr, 3, "mip", fast=True)
    ref = project_gaussians(g64, T, intr, 3, "mip")
    assert torch.equal(fast.ids, ref.ids)
    w = _weights(rng, ref)
    ga = torch.autograd.grad(_loss(fast, {k: v.float() for k, v in w.items()}), list(g32))
    gb = torch.autograd.grad(_loss(ref, w), list(g64))
    for name, a, b in zip(PARAMS, ga, gb):
        assert a.dtype == torch.float32
        rel = ((a.double() - b).norm() / b.norm()).item()
        assert rel < 1e-5, (name, rel)


@pytest.mark.parametrize("filt", ("mip", "none"))
def test_fast_projection_gradcheck(rng, filt):
    """Central finite differences (torch gradcheck, float64) of the numba forward against its backward on a tiny
    case: one Gaussian near the optical axis (series branch), one past 90 deg, one ordinary, SH degree 3. The one
    past 90 deg (98.5 deg) projects to (10.8, 7.3) px, inside the 64x48 image (at azimuth -2.0 rad it fell at
    y = -1.1 px, and a small, faint draw was culled: a flaky test)."""
    intr = _lens()
    T = random_pose(rng)
    p_cam = np.stack([rays_at(2e-3, 0.4) * 1.2, rays_at(1.72, -2.5) * 0.9, rays_at(0.7, 1.1) * 2.0])
    n = len(p_cam)
    g = Gaussians(
        means=torch.as_tensor(p_cam @ T[:3, :3].T + T[:3, 3]),
        log_scales=torch.as_tensor(np.log(rng.uniform(0.02, 0.06, (n, 3)))),
        quats_wxyz=torch.as_tensor(rng.normal(size=(n, 4))),
        logit_opacities=torch.as_tensor(rng.uniform(-1.0, 2.0, n)),
        sh0=torch.as_tensor(rng.normal(size=(n, 3)) * 0.3),
        sh_rest=torch.as_tensor(rng.normal(size=(n, 15, 3)) * 0.2),
    )
    assert len(project_gaussians(g, T, intr, 3, filt, fast=True)) == n

    def fn(*params):
        p = project_gaussians(Gaussians(*params), T, intr, 3, filt, fast=True)
        return torch.cat([getattr(p, k).reshape(n, -1) for k in OUTPUTS], dim=1)

    inputs = tuple(t.clone().requires_grad_(True) for t in g)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("theta", [0.0, 1e-7, 3e-3, 0.0099, 0.0101, 0.6, 1.4, math.pi / 2, 1.8, 2.6])
def test_kb_jacobian_vjp_matches_finite_differences(rng, theta):
    """The derivative of the KB Jacobian (the part of d Sigma_2D / d p that autograd got from the torch graph):
    ``sum_e g_e dJ_e/dp`` against central differences of the analytic Jacobian, on / near the optical axis (both
    sides of the series-branch switch at r = 0.01 z) and past 90 deg."""
    intr = _lens()
    fx, fy = intr.fx, intr.fy
    k = intr.k
    p = rays_at(theta, float(rng.uniform(-math.pi, math.pi))) * float(rng.uniform(0.3, 3.0))
    gJ = rng.normal(size=6)
    res = PK._kb_jacobian_vjp(*p, *gJ, fx, fy, *k)
    ok, _, u, v, *J = _kb_project_jacobian(*p, fx, fy, intr.cx, intr.cy, *k)
    assert ok
    np.testing.assert_allclose(res[2:8], J, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose([res[0] + intr.cx, res[1] + intr.cy], [u, v], rtol=1e-13, atol=1e-9)
    h = 1e-6 * np.linalg.norm(p)
    fd = np.empty(3)
    dJ_fd = np.empty((3, 6))
    for axis in range(3):
        t = np.zeros(3)
        t[axis] = h
        Jp = np.array(_kb_project_jacobian(*(p + t), fx, fy, intr.cx, intr.cy, *k)[4:])
        Jm = np.array(_kb_project_jacobian(*(p - t), fx, fy, intr.cx, intr.cy, *k)[4:])
        dJ_fd[axis] = (Jp - Jm) / (2 * h)
        fd[axis] = gJ @ dJ_fd[axis]
    gp = np.array(res[8:])
    assert np.isfinite(gp).all()
    np.testing.assert_allclose(gp, fd, rtol=1e-5, atol=1e-5 * np.abs(gJ).sum() * np.abs(dJ_fd).max() + 1e-9)


@pytest.mark.parametrize("filt", FILTERS)
def test_render_fast_projection_equals_torch_projection(rng, filt):
    """End to end (float64): ``render`` with the fast projection (the default with gradients) and with the
    torch-autograd reference projection give the same image and the same gradients of every parameter; the
    step's timings name both backwards."""
    intr = _lens(48, 40)
    T = random_pose(rng)
    g = _extreme_gaussians(rng, intr, T, 60).requires_grad_(True)
    bg = torch.as_tensor(rng.uniform(size=3))
    w = loss_weights(rng, intr.height, intr.width)
    out_f = render(g, T, intr, bg, filter=filt)
    out_r = render(g, T, intr, bg, filter=filt, projection="torch")
    assert torch.allclose(out_f.rgb, out_r.rgb, rtol=0, atol=1e-10)
    ga = torch.autograd.grad(weighted_loss(out_f, w), list(g))
    gb = torch.autograd.grad(weighted_loss(out_r, w), list(g))
    for name, a, b in zip(PARAMS, ga, gb):
        assert torch.isfinite(a).all(), name
        assert (a - b).abs().max().item() <= 1e-7 * (1.0 + b.abs().max().item()), name
    assert out_f.meta["timings"]["project_backward"] > 0 and out_f.meta["timings"]["raster_backward"] > 0
    assert "project_backward" not in out_r.meta["timings"]


def test_pose_gradient_falls_back_to_reference(rng):
    intr = gopro_small(32, 24)
    T = torch.as_tensor(random_pose(rng)).requires_grad_(True)
    g = random_gaussians(20, rng, intr, T.detach().numpy(), dtype=torch.float64).requires_grad_(True)
    out = render(g, T, intr)
    (gT,) = torch.autograd.grad(out.rgb.sum(), [T])
    assert torch.isfinite(gT).all() and gT.abs().max() > 0
    assert "project_backward" not in out.meta["timings"]


def test_trainer_fast_projection_matches_reference(rng):
    """A few trainer steps with the fast and with the reference projection (float32 scene) stay together: same
    loss to float32 rounding (the two projections differ only by rounding), both finite."""
    from umi_aug.splat.train import SplatTrainConfig, TrainView, train_splat

    intr = gopro_small(32, 32)
    gt = random_gaussians(80, rng, intr, np.eye(4), dtype=torch.float32)
    views = []
    for k in range(3):
        T = make_pose(so3_exp(rng.normal(size=3) * 0.1), rng.normal(size=3) * 0.05)
        img = (render(gt, T, intr).rgb.clamp(0, 1).numpy() * 255).astype(np.uint8)
        views.append(TrainView(f"v{k}", img, T, np.ones((32, 32), dtype=bool)))
    init = gt.means.numpy() + rng.normal(scale=0.01, size=(80, 3))
    cfg = SplatTrainConfig(iterations=6, max_gaussians=100, holdout_every=0, eval_every=3, checkpoint_every=6,
                           sh_degree=1, refine_start=2, refine_every=2)
    runs = [train_splat(views, intr, init, None, replace(cfg, fast_projection=f), progress=False)
            for f in (True, False)]
    la = [h["loss"] for h in runs[0].history[1:]]
    lb = [h["loss"] for h in runs[1].history[1:]]
    assert np.isfinite(la).all() and np.isfinite(lb).all()
    np.testing.assert_allclose(la, lb, rtol=1e-3)
    assert runs[0].timings["project_backward"] > 0 and runs[1].timings["project_backward"] == 0


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_gather_visible_kernel_equals_numpy(rng, dtype):
    """The forward's visible rows, split into the six output groups in the scene's dtype: the numba pass gives the
    same bytes as numpy's fancy index + ``astype`` (values that round up and down in float32, huge, tiny, signed
    zeros; no visible row)."""
    from umi_aug.splat.project import ProjectGaussians, _gather_visible_numpy

    n = int(rng.integers(300, 900))
    # magnitudes from float32 denormals to 1e30
    out = rng.normal(size=(n, PK.PROJ_COLS)) * 10.0 ** rng.integers(-45, 30, size=(n, PK.PROJ_COLS))
    out[::7, 3] = -0.0
    out[::11, 5] = 1.0 + 2.0 ** -30  # rounds to 1.0 in float32
    for ids in (np.flatnonzero(rng.random(n) < 0.7), np.arange(n), np.zeros(0, dtype=np.int64)):
        want = _gather_visible_numpy(out, ids, dtype)
        got = [np.empty(w.shape, dtype=dtype) for w in want]
        PK.gather_visible_kernel(out, ids, *got)
        assert len(got) == len(ProjectGaussians.COLUMNS)
        for g, w in zip(got, want):
            assert g.dtype == w.dtype and g.shape == w.shape and g.tobytes() == w.tobytes()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_grad_out_kernel_equals_numpy(rng, dtype):
    """The backward's output gradients gathered into the kernel's float64 layout: the numba pass gives the bytes of
    the numpy zero fill + casting copies it replaces, for the renderer's strided column views of one buffer,
    separate contiguous tensors, outputs without a gradient (None: zeros), NaN/inf/signed zeros/denormals kept."""
    from umi_aug.splat.project import ProjectGaussians, _grad_out, _grad_out_reference

    V = int(rng.integers(1, 700))
    base = torch.from_numpy(rng.normal(size=(V, 13)) * 10.0 ** rng.integers(-45, 30, size=(V, 13))).to(dtype)
    base[::5, 1] = float("nan")
    base[::7, 3] = -0.0
    base[::9, 9] = float("-inf")
    strided = [base[:, a:b] if b - a > 1 else base[:, a] for a, b in ProjectGaussians.COLUMNS]
    separate = [x.clone() for x in strided]
    for grads in (strided, separate, strided[:5] + [None], [None, separate[1], None, strided[3], None, None],
                  [None] * 5 + [separate[5]]):
        want = _grad_out_reference(grads, V)
        got = _grad_out(grads, V, np.float32 if dtype == torch.float32 else np.float64)
        assert got.dtype == np.float64 and got.shape == (V, PK.PROJ_COLS) and got.tobytes() == want.tobytes()
