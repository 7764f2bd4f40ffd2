import math

import numpy as np
import pytest

import torch  # noqa: E402

from umi_aug.geometry import (  # noqa: E402
    matrix_to_quat_wxyz,
    pose_to_pos_rotvec,
    pos_rotvec_to_pose,
    rot6d_to_mat,
    rotation_geodesic_distance,
    se3_exp,
    se3_log,
    so3_exp,
    so3_left_jacobian,
    so3_left_jacobian_inv,
    so3_log,
)
from umi_aug.geometry import se3_torch as et  # noqa: E402
from umi_aug.geometry import so3_torch as st  # noqa: E402
from tests.geometry._helpers import (  # noqa: E402
    EXTREME_ANGLES,
    random_poses,
    random_rotations,
    random_rotvecs,
    rotvec_close_mod_pi,
    rotvecs_with_angle,
)


def t64(x):
    return torch.from_numpy(np.ascontiguousarray(x))


def test_numpy_torch_agree_f64(rng):
    v = random_rotvecs(rng, 200)
    R = random_rotations(rng, 200)
    T = random_poses(rng, 200)
    T2 = random_poses(rng, 200)
    xi = np.concatenate([rng.normal(size=(200, 3)), v], axis=-1)
    d6 = rng.normal(size=(200, 6))
    pairs = [
        (st.so3_exp(t64(v)), so3_exp(v)),
        (st.so3_log(t64(R)), so3_log(R)),
        (st.rotation_geodesic_distance(t64(R), t64(T[:, :3, :3])), rotation_geodesic_distance(R, T[:, :3, :3])),
        (et.se3_exp(t64(xi)), se3_exp(xi)),
        (et.se3_log(t64(T)), se3_log(T)),
        (et.pose_to_pos_rotvec(t64(T)), pose_to_pos_rotvec(T)),
        (et.pos_rotvec_to_pose(t64(xi)), pos_rotvec_to_pose(xi)),
        (et.rot6d_to_mat(t64(d6)), rot6d_to_mat(d6)),
        (et.matrix_to_quat_wxyz(t64(R)), matrix_to_quat_wxyz(R)),
        (et.relative_pose(t64(T), t64(T2)), np.linalg.inv(T) @ T2),
        (et.absolute_pose(t64(T), t64(T2)), T @ T2),
        (et.pose_inverse(t64(T)), np.linalg.inv(T)),
    ]
    for got, ref in pairs:
        assert got.dtype == torch.float64
        np.testing.assert_allclose(got.numpy(), ref, atol=1e-12)
    np.testing.assert_allclose(et.mat_to_rot6d(t64(R)).numpy(), R[:, :2, :].reshape(-1, 6), atol=0)
    for angle in (0.0, 0.1, 0.5, 2.0, math.pi):  # both sides of the series thresholds
        phi = rotvecs_with_angle(rng, 5, angle)
        np.testing.assert_allclose(st.so3_left_jacobian(t64(phi)).numpy(), so3_left_jacobian(phi), atol=1e-13)
        np.testing.assert_allclose(st.so3_left_jacobian_inv(t64(phi)).numpy(), so3_left_jacobian_inv(phi), atol=1e-13)
        J32 = st.so3_left_jacobian_inv(t64(phi).float()) @ st.so3_left_jacobian(t64(phi).float())
        np.testing.assert_allclose(J32.double().numpy(), np.broadcast_to(np.eye(3), (5, 3, 3)), atol=2e-6)
    q = et.matrix_to_quat_wxyz(t64(R))
    np.testing.assert_allclose(et.quat_wxyz_to_matrix(q).numpy(), R, atol=1e-12)
    p = rng.normal(size=(200, 4, 3))
    np.testing.assert_allclose(
        et.transform_points(t64(T), t64(p)).numpy(), p @ np.swapaxes(T[:, :3, :3], 1, 2) + T[:, None, :3, 3], atol=1e-12
    )
    np.testing.assert_allclose(
        et.make_pose(t64(R), t64(T[:, :3, 3])).numpy()[:, :3, :3], R, atol=0
    )


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
@pytest.mark.parametrize("angle", EXTREME_ANGLES)
def test_torch_round_trip_extremes(rng, angle, dtype, tol):
    v = rotvecs_with_angle(rng, 30, angle)
    vt = t64(v).to(dtype)
    R = st.so3_exp(vt)
    assert R.dtype == dtype and torch.isfinite(R).all()
    back = st.so3_log(R)
    assert back.dtype == dtype and torch.isfinite(back).all()
    ref_angle = float(torch.linalg.norm(vt.double(), dim=-1)[0])
    assert rotvec_close_mod_pi(back.double().numpy(), vt.double().numpy(), ref_angle, 4 * tol)
    np.testing.assert_allclose(st.so3_exp(back).double().numpy(), R.double().numpy(), atol=4 * tol)
    np.testing.assert_allclose(R.double().numpy(), so3_exp(vt.double().numpy()), atol=tol)


def test_grad_at_exact_zero_rotation():
    v = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    J = torch.autograd.functional.jacobian(st.so3_exp, v)  # [3, 3, 3(i)]
    gens = torch.stack([st.hat(e) for e in torch.eye(3, dtype=torch.float64)])
    assert torch.isfinite(J).all()
    torch.testing.assert_close(J.permute(2, 0, 1), gens, atol=0, rtol=0)
    # d log / d R at identity: rotvec ≈ vee(R − Rᵀ)/2, so d log(exp(v))/dv = I
    R0 = torch.eye(3, dtype=torch.float64, requires_grad=True)
    Jl = torch.autograd.functional.jacobian(st.so3_log, R0)  # [3, 3, 3]
    assert torch.isfinite(Jl).all()
    torch.testing.assert_close(torch.einsum("kij,nij->kn", Jl, gens), torch.eye(3, dtype=torch.float64))
    for f32 in (torch.float32, torch.float64):
        z = torch.zeros(2, 3, dtype=f32, requires_grad=True)
        xi0 = torch.zeros(6, dtype=f32, requires_grad=True)
        (st.so3_log(st.so3_exp(z)).sum() + et.se3_log(et.se3_exp(xi0)).sum()).backward()
        assert torch.isfinite(xi0.grad).all()
        assert torch.isfinite(z.grad).all()
        torch.testing.assert_close(z.grad, torch.ones_like(z))
        R1 = torch.eye(3, dtype=f32, requires_grad=True)
        (g,) = torch.autograd.grad(st.rotation_geodesic_distance(R1, torch.eye(3, dtype=f32)), R1)
        assert torch.isfinite(g).all()  # |angle| is not differentiable at 0: the safe norm gives 0


@pytest.mark.parametrize("angle", [math.pi - 1e-3, math.pi - 1e-6, math.pi - 1e-9, math.pi])
def test_grad_finite_near_pi(rng, angle):
    for dtype in (torch.float32, torch.float64):
        v = t64(rotvecs_with_angle(rng, 8, angle)).to(dtype).requires_grad_()
        out = st.so3_log(st.so3_exp(v))
        (out * torch.randn_like(out)).sum().backward()
        assert torch.isfinite(v.grad).all()
        R = st.so3_exp(v.detach()).requires_grad_()
        xi = et.se3_log(et.make_pose(R, torch.ones(8, 3, dtype=dtype)))
        (xi.sum() + st.rotation_geodesic_distance(R, torch.eye(3, dtype=dtype)).sum()).backward()
        assert torch.isfinite(R.grad).all()


def test_gradcheck(rng):
    gc = torch.autograd.gradcheck
    v = t64(random_rotvecs(rng, 4, max_angle=3.0)).requires_grad_()
    assert gc(st.so3_exp, (v,))
    assert gc(st.so3_exp, (t64(rotvecs_with_angle(rng, 2, 1e-6)).requires_grad_(),))
    for angle in (0.5, 2.5):  # generic branch and symmetric-part branch, both away from π
        R = t64(so3_exp(rotvecs_with_angle(rng, 3, angle))).requires_grad_()
        assert gc(st.so3_log, (R,))
    T = t64(random_poses(rng, 3))
    T[:, :3, :3] = t64(so3_exp(random_rotvecs(rng, 3, max_angle=2.8)))
    assert gc(et.se3_log, (T.requires_grad_(),))
    assert gc(et.se3_exp, (t64(rng.normal(size=(3, 6))).requires_grad_(),))
    assert gc(et.rot6d_to_mat, (t64(rng.normal(size=(4, 6))).requires_grad_(),))
    assert gc(et.matrix_to_quat_wxyz, (t64(random_rotations(rng, 3)).requires_grad_(),))


def test_torch_degenerate_inputs_finite():
    z = torch.zeros(3, 6, dtype=torch.float32, requires_grad=True)
    R = et.rot6d_to_mat(z)
    R.sum().backward()
    assert torch.isfinite(R).all() and torch.isfinite(z.grad).all()
    torch.testing.assert_close(R[0] @ R[0].T, torch.eye(3))
    q = et.quat_wxyz_to_matrix(torch.zeros(4))
    torch.testing.assert_close(q, torch.eye(3))


def test_torch_batched_shapes_and_errors():
    from umi_aug.errors import GeometryError

    v = torch.zeros(2, 5, 3)
    assert st.so3_exp(v).shape == (2, 5, 3, 3)
    assert et.pos_rotvec_to_pose(torch.zeros(2, 5, 6)).shape == (2, 5, 4, 4)
    assert st.so3_exp(torch.zeros(3, dtype=torch.int64)).dtype == torch.get_default_dtype()
    with pytest.raises(GeometryError, match="rotvec"):
        st.so3_exp(torch.zeros(2, 4))
    with pytest.raises(GeometryError, match="T_base"):
        et.relative_pose(torch.zeros(3, 3), torch.eye(4))


def test_torch_module_not_imported_by_package():
    import subprocess
    import sys

    code = "import sys, umi_aug.geometry; sys.exit(1 if 'torch' in sys.modules else 0)"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0
