"""numba forward and hand-written backward of the training projection (:class:`umi_aug.splat.project.ProjectGaussians`).

Same formulas, culling and outputs as the torch-autograd reference :func:`umi_aug.splat.project.project_gaussians`
(float64 inside whatever the scene's dtype): ``p = R_cw mu + t_cw``; ``(u, v), J = KB(p), dKB/dp``;
``A, B = rows of J R_cw R(q) diag(exp(log_s))``; ``Sigma_2D = [[A.A, A.B], [A.B, B.B]] + lambda I`` with
``det0 = |A x B|^2`` (Cauchy–Binet); conic; ``sigmoid(logit) [x sqrt(det0 / det)]``; SH colour along
``(mu - campos) / |mu - campos|``, clamped at 0.

The backward recomputes each visible Gaussian's forward and runs the reverse pass by hand. The only non-trivial
part is ``d J / d p`` (the EWA covariance depends on the projection Jacobian): :func:`_kb_jacobian_vjp`
propagates a tangent through the KB Jacobian (forward-mode, both branches of :mod:`umi_aug.camera.kb`: the series
branch near the optical axis, exact at ``r = 0``, and the direct branch, finite past 90 deg), once per axis, from
one evaluation of the primal.

Output columns of :func:`project_fwd_kernel` (and the gradient columns of :func:`project_bwd_kernel`)::

    (u, v, conic_a, conic_b, conic_c, opacity, r, g, b, ray_depth, sxx, sxy, syy)
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from umi_aug.camera.kb import SMALL_T
from umi_aug.splat._kernels import _kb_project_jacobian
from umi_aug.splat._constants import (
    ALPHA_THRESHOLD,
    BBOX_MARGIN_PX,
    BBOX_MARGIN_REL,
    LOG_INV_ALPHA_THRESHOLD,
    MIN_DET_2D_ABS,
    MIN_DET_2D_REL,
    SH_C0,
    SH_C1,
    SH_C2,
    SH_C3,
)
from umi_aug.splat._numba_cache import install as install_kernel_cache

install_kernel_cache()  # before the first @njit(cache=True): stamped with every kernel source

#: Columns of the projection output / its gradient (see the module docstring).
PROJ_COLS = 13
#: Gaussians per parallel work item (scratch buffers are allocated once per block).
BLOCK = 256
#: ``|q|^2`` at or below which a quaternion is not normalised (torch ``safe_norm(q, 1e-30)``).
QUAT_EPS2 = 1e-30

_C2_0, _C2_1, _C2_2, _C2_3, _C2_4 = SH_C2
_C3_0, _C3_1, _C3_2, _C3_3, _C3_4, _C3_5, _C3_6 = SH_C3


@njit(cache=True, fastmath=False)
def _kb_jacobian_vjp(px, py, pz, g00, g01, g02, g10, g11, g12, fx, fy, k1, k2, k3, k4):  # pragma: no cover
    """KB projection Jacobian ``J = d(u, v)/dp`` at ``p`` and the vector-Jacobian product of ``J`` itself:
    ``gp_k = sum_e g_e dJ_e/dp_k`` (the second derivatives of the projection the EWA covariance needs).

    ``p`` (camera frame, metres) must be valid (finite, non-zero); ``g`` is dL/dJ in the order of ``J``. The primal
    is evaluated once, then a tangent (forward mode) per axis ``k``: same branches and formulas as
    :func:`umi_aug.splat._kernels._kb_project_jacobian` (series branch near the optical axis, exact at ``r = 0``;
    direct branch, finite past 90 deg). Returns ``u, v`` (pixels minus the principal point),
    ``j00, j01, j02, j10, j11, j12`` (pixels per metre) and ``gp0, gp1, gp2``.
    """
    m = max(abs(px), max(abs(py), abs(pz)))
    qx, qy, qz = px / m, py / m, pz / m
    n = math.sqrt(qx * qx + qy * qy + qz * qz)
    x, y, z = qx / n, qy / n, qz / n
    norm = m * n
    r2 = x * x + y * y
    r = math.sqrt(r2)
    series = z > 0.0 and r <= SMALL_T * z
    # primal (both branches' locals defined; only the taken branch's are used)
    z2 = z3 = q = a = da = dda = P = dP = ddP = G = E = dG = 0.0
    theta = rd = rho2 = t2 = td = dtd = ddtd = num = A = 0.0
    if series:  # q = r^2/z^2, a = atan(t)/t, G = a P(q a^2)
        z2 = z * z
        z3 = z2 * z
        q = r2 / z2
        a = 1.0 + q * (-1.0 / 3.0 + q * (1.0 / 5.0 + q * (-1.0 / 7.0 + q * (1.0 / 9.0))))
        da = -1.0 / 3.0 + q * (2.0 / 5.0 + q * (-3.0 / 7.0 + q * (4.0 / 9.0)))
        dda = 2.0 / 5.0 + q * (-6.0 / 7.0 + q * (12.0 / 9.0))
        w = q * a * a
        P = 1.0 + w * (k1 + w * (k2 + w * (k3 + w * k4)))
        dP = k1 + w * (2.0 * k2 + w * (3.0 * k3 + w * 4.0 * k4))
        ddP = 2.0 * k2 + w * (6.0 * k3 + w * 12.0 * k4)
        G = a * P
        E = a * a + 2.0 * q * a * da
        dG = da * P + a * dP * E
        s = G / z
        B = 2.0 * dG / z3
        s_z = -(G + 2.0 * q * dG) / z2
        cxx, cxy, cyy = x * x, x * y, y * y
    else:
        theta = math.atan2(r, z)
        rd = r if r > 0.0 else 1.0  # on the axis behind the camera: held at 1 like the reference
        rho2 = r2 + z * z
        t2 = theta * theta
        td = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        dtd = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
        ddtd = theta * (6.0 * k1 + t2 * (20.0 * k2 + t2 * (42.0 * k3 + t2 * 72.0 * k4)))
        s = td / rd
        num = dtd * z / rho2 - s
        A = num / (rd * rd)
        s_z = -dtd / rho2
        B = A * r2
        if r2 > 0.0:
            cxx, cxy, cyy = x * x / r2, x * y / r2, y * y / r2
        else:
            cxx, cxy, cyy = 0.0, 0.0, 0.0
    inv = 1.0 / norm
    u = fx * s * x
    v = fy * s * y
    j00 = fx * (s + cxx * B) * inv
    j01 = fx * cxy * B * inv
    j02 = fx * x * s_z * inv
    j10 = fy * cxy * B * inv
    j11 = fy * (s + cyy * B) * inv
    j12 = fy * y * s_z * inv
    gp0 = gp1 = gp2 = 0.0
    for k in range(3):  # tangent along the axis k
        tx = 1.0 if k == 0 else 0.0
        ty = 1.0 if k == 1 else 0.0
        tz = 1.0 if k == 2 else 0.0
        dnorm = x * tx + y * ty + z * tz
        dx, dy, dz = (tx - x * dnorm) / norm, (ty - y * dnorm) / norm, (tz - z * dnorm) / norm
        dr2 = 2.0 * (x * dx + y * dy)
        if series:
            dq = dr2 / z2 - 2.0 * r2 * dz / z3
            a_t = da * dq
            da_t = dda * dq
            w_t = dq * a * a + 2.0 * q * a * a_t
            P_t = dP * w_t
            dP_t = ddP * w_t
            G_t = a_t * P + a * P_t
            E_t = 2.0 * a * a_t + 2.0 * (dq * a * da + q * a_t * da + q * a * da_t)
            dG_t = da_t * P + da * P_t + a_t * dP * E + a * dP_t * E + a * dP * E_t
            s_t = G_t / z - G * dz / z2
            B_t = 2.0 * dG_t / z3 - 6.0 * dG * dz / (z2 * z2)
            s_z_t = -(G_t + 2.0 * dq * dG + 2.0 * q * dG_t) / z2 + 2.0 * (G + 2.0 * q * dG) * dz / z3
            cxx_t, cxy_t, cyy_t = 2.0 * x * dx, dx * y + x * dy, 2.0 * y * dy
        else:
            rd_t = (x * dx + y * dy) / r if r > 0.0 else 0.0
            rho2_t = dr2 + 2.0 * z * dz
            th_t = (z * rd_t - r * dz) / rho2 if r > 0.0 else 0.0
            td_t = dtd * th_t
            dtd_t = ddtd * th_t
            s_t = td_t / rd - td * rd_t / (rd * rd)
            num_t = dtd_t * z / rho2 + dtd * dz / rho2 - dtd * z * rho2_t / (rho2 * rho2) - s_t
            A_t = num_t / (rd * rd) - 2.0 * num * rd_t / (rd * rd * rd)
            s_z_t = -dtd_t / rho2 + dtd * rho2_t / (rho2 * rho2)
            B_t = A_t * r2 + A * dr2
            if r2 > 0.0:
                cxx_t = 2.0 * x * dx / r2 - cxx * dr2 / r2
                cxy_t = (dx * y + x * dy) / r2 - cxy * dr2 / r2
                cyy_t = 2.0 * y * dy / r2 - cyy * dr2 / r2
            else:
                cxx_t, cxy_t, cyy_t = 2.0 * x * dx, dx * y + x * dy, 2.0 * y * dy
        inv_t = -dnorm * inv * inv
        acc = g00 * fx * ((s_t + cxx_t * B + cxx * B_t) * inv + (s + cxx * B) * inv_t)
        acc += (g01 * fx + g10 * fy) * ((cxy_t * B + cxy * B_t) * inv + cxy * B * inv_t)
        acc += g02 * fx * ((dx * s_z + x * s_z_t) * inv + x * s_z * inv_t)
        acc += g11 * fy * ((s_t + cyy_t * B + cyy * B_t) * inv + (s + cyy * B) * inv_t)
        acc += g12 * fy * ((dy * s_z + y * s_z_t) * inv + y * s_z * inv_t)
        if k == 0:
            gp0 = acc
        elif k == 1:
            gp1 = acc
        else:
            gp2 = acc
    return u, v, j00, j01, j02, j10, j11, j12, gp0, gp1, gp2


@njit(cache=True, fastmath=False)
def _rotation(qw, qx, qy, qz):  # pragma: no cover - compiled
    """Normalised quaternion (as ``quat_wxyz_to_matrix``: not normalised when ``|q|^2 <= QUAT_EPS2``), its norm
    (1 when not normalised) and the rotation matrix entries ``r00 .. r22``."""
    n2 = qw * qw + qx * qx + qy * qy + qz * qz
    qn = math.sqrt(n2) if n2 > QUAT_EPS2 else 1.0
    w, x, y, z = qw / qn, qx / qn, qy / qn, qz / qn
    return (w, x, y, z, qn,
            1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
            2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
            2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))


@njit(cache=True, fastmath=False)
def _sh_degree(sh_degree, n_rest):  # pragma: no cover - compiled
    deg = min(sh_degree, 3)
    if deg >= 3 and n_rest < 15:
        deg = 2
    if deg >= 2 and n_rest < 8:
        deg = 1
    if deg >= 1 and n_rest < 3:
        deg = 0
    return deg


@njit(cache=True, fastmath=False)
def _sh_basis(x, y, z, Y):  # pragma: no cover - compiled
    """Real SH basis (16 values, INRIA constants and signs) of the unit direction ``(x, y, z)`` into ``Y``."""
    xx, yy, zz = x * x, y * y, z * z
    Y[0] = SH_C0
    Y[1], Y[2], Y[3] = -SH_C1 * y, SH_C1 * z, -SH_C1 * x
    Y[4], Y[5], Y[6] = _C2_0 * x * y, _C2_1 * y * z, _C2_2 * (2.0 * zz - xx - yy)
    Y[7], Y[8] = _C2_3 * x * z, _C2_4 * (xx - yy)
    Y[9] = _C3_0 * y * (3.0 * xx - yy)
    Y[10] = _C3_1 * x * y * z
    Y[11] = _C3_2 * y * (4.0 * zz - xx - yy)
    Y[12] = _C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
    Y[13] = _C3_4 * x * (4.0 * zz - xx - yy)
    Y[14] = _C3_5 * z * (xx - yy)
    Y[15] = _C3_6 * x * (xx - 3.0 * yy)


@njit(cache=True, fastmath=False)
def _sh_basis_vjp(x, y, z, gY, deg):  # pragma: no cover - compiled
    """``sum_k gY[k] dY_k/d(x, y, z)`` for the first ``(deg + 1)^2`` basis functions (x, y, z independent)."""
    gx = 0.0
    gy = 0.0
    gz = 0.0
    if deg >= 1:
        gy -= SH_C1 * gY[1]
        gz += SH_C1 * gY[2]
        gx -= SH_C1 * gY[3]
    if deg >= 2:
        gx += _C2_0 * y * gY[4] - 2.0 * _C2_2 * x * gY[6] + _C2_3 * z * gY[7] + 2.0 * _C2_4 * x * gY[8]
        gy += _C2_0 * x * gY[4] + _C2_1 * z * gY[5] - 2.0 * _C2_2 * y * gY[6] - 2.0 * _C2_4 * y * gY[8]
        gz += _C2_1 * y * gY[5] + 4.0 * _C2_2 * z * gY[6] + _C2_3 * x * gY[7]
    if deg >= 3:
        xx, yy, zz = x * x, y * y, z * z
        gx += (_C3_0 * 6.0 * x * y * gY[9] + _C3_1 * y * z * gY[10] - _C3_2 * 2.0 * x * y * gY[11]
               - _C3_3 * 6.0 * x * z * gY[12] + _C3_4 * (4.0 * zz - 3.0 * xx - yy) * gY[13]
               + _C3_5 * 2.0 * x * z * gY[14] + _C3_6 * (3.0 * xx - 3.0 * yy) * gY[15])
        gy += (_C3_0 * (3.0 * xx - 3.0 * yy) * gY[9] + _C3_1 * x * z * gY[10]
               + _C3_2 * (4.0 * zz - xx - 3.0 * yy) * gY[11] - _C3_3 * 6.0 * y * z * gY[12]
               - _C3_4 * 2.0 * x * y * gY[13] - _C3_5 * 2.0 * y * z * gY[14] - _C3_6 * 6.0 * x * y * gY[15])
        gz += (_C3_1 * x * y * gY[10] + _C3_2 * 8.0 * y * z * gY[11] + _C3_3 * (6.0 * zz - 3.0 * xx - 3.0 * yy) * gY[12]
               + _C3_4 * 8.0 * x * z * gY[13] + _C3_5 * (xx - yy) * gY[14])
    return gx, gy, gz


@njit(cache=True, fastmath=False)
def _view_dir(mx, my, mz, campos):  # pragma: no cover - compiled
    """Unit direction camera centre -> mean (world) and the distance (``(0, 0, 1), 0`` at the centre)."""
    vx, vy, vz = mx - campos[0], my - campos[1], mz - campos[2]
    n2 = vx * vx + vy * vy + vz * vz
    if n2 > 0.0:
        dn = math.sqrt(n2)
        return vx / dn, vy / dn, vz / dn, dn
    return 0.0, 0.0, 1.0, 0.0


@njit(cache=True, fastmath=False)
def _cov_rows(j, Rcw, rot, sc, M, AB):  # pragma: no cover - compiled
    """``M = R_cw R diag(s)`` (3x3, into ``M``) and the rows ``A = J[0] M``, ``B = J[1] M`` (into ``AB[0:3]``,
    ``AB[3:6]``); ``j`` = J row-major (6), ``rot`` = R row-major (9), ``sc`` = scales (3)."""
    for k in range(3):
        for c in range(3):
            M[k, c] = (Rcw[k, 0] * rot[c] + Rcw[k, 1] * rot[3 + c] + Rcw[k, 2] * rot[6 + c]) * sc[c]
    for c in range(3):
        AB[c] = j[0] * M[0, c] + j[1] * M[1, c] + j[2] * M[2, c]
        AB[3 + c] = j[3] * M[0, c] + j[4] * M[1, c] + j[5] * M[2, c]


@njit(parallel=True, cache=True, fastmath=False)
def project_fwd_kernel(
    means, log_scales, quats, logit_op, sh0, sh_rest, sh_degree, Rcw, tcw, campos, cam, near, far, dilation,
    compensate, theta_slack, width, height, out, valid,
):  # pragma: no cover - compiled
    """Project, cull and shade every Gaussian (float64 inside; inputs of any float dtype).

    ``cam = (fx, fy, cx, cy, k1, k2, k3, k4, theta_max)``; ``theta_slack`` = the reference's ray-angle slack
    for the scene's dtype. Writes ``out [N, PROJ_COLS]`` (rows of culled Gaussians undefined) and ``valid [N]``.
    Culls as :func:`umi_aug.splat.project.project_gaussians`: near/far sphere, ray angle beyond ``theta_max``,
    near-singular ``Sigma_2D``, opacity below the alpha threshold, opacity-aware bounding box off the image.
    """
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    k1, k2, k3, k4, theta_max = cam[4], cam[5], cam[6], cam[7], cam[8]
    deg = _sh_degree(sh_degree, sh_rest.shape[1])
    n_coef = (deg + 1) * (deg + 1)
    N = means.shape[0]
    for blk in prange((N + BLOCK - 1) // BLOCK):
        j = np.empty(6)
        rot = np.empty(9)
        sc = np.empty(3)
        M = np.empty((3, 3))
        AB = np.empty(6)
        Y = np.empty(16)
        for i in range(blk * BLOCK, min(N, (blk + 1) * BLOCK)):
            valid[i] = False
            mx, my, mz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
            px = Rcw[0, 0] * mx + Rcw[0, 1] * my + Rcw[0, 2] * mz + tcw[0]
            py = Rcw[1, 0] * mx + Rcw[1, 1] * my + Rcw[1, 2] * mz + tcw[1]
            pz = Rcw[2, 0] * mx + Rcw[2, 1] * my + Rcw[2, 2] * mz + tcw[2]
            ok, theta, u, v, j00, j01, j02, j10, j11, j12 = _kb_project_jacobian(
                px, py, pz, fx, fy, cx, cy, k1, k2, k3, k4)
            j[0], j[1], j[2], j[3], j[4], j[5] = j00, j01, j02, j10, j11, j12
            depth = math.sqrt(px * px + py * py + pz * pz)
            if not (ok and theta <= theta_max + theta_slack and depth > near and depth < far):
                continue
            rt = _rotation(np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]),
                           np.float64(quats[i, 3]))
            for e in range(9):
                rot[e] = rt[5 + e]
            for c in range(3):
                sc[c] = math.exp(np.float64(log_scales[i, c]))
            _cov_rows(j, Rcw, rot, sc, M, AB)
            a0, a1, a2, b0, b1, b2 = AB[0], AB[1], AB[2], AB[3], AB[4], AB[5]
            sxx0 = a0 * a0 + a1 * a1 + a2 * a2
            sxy = a0 * b0 + a1 * b1 + a2 * b2
            syy0 = b0 * b0 + b1 * b1 + b2 * b2
            m01 = a0 * b1 - a1 * b0
            m02 = a0 * b2 - a2 * b0
            m12 = a1 * b2 - a2 * b1
            det0 = m01 * m01 + m02 * m02 + m12 * m12
            sxx = sxx0 + dilation
            syy = syy0 + dilation
            det = det0 + dilation * (sxx0 + syy0) + dilation * dilation
            half_tr = 0.5 * (sxx + syy)
            if not (det > MIN_DET_2D_ABS and det > MIN_DET_2D_REL * half_tr * half_tr and math.isfinite(det)):
                continue
            op = 1.0 / (1.0 + math.exp(-np.float64(logit_op[i])))
            if compensate:
                op = op * math.sqrt(det0 / det) if det0 > 0.0 else 0.0
            if not (op >= ALPHA_THRESHOLD):
                continue
            lim = 2.0 * (math.log(op) + LOG_INV_ALPHA_THRESHOLD)
            hx = math.sqrt(max(lim * sxx, 0.0)) * (1.0 + BBOX_MARGIN_REL) + BBOX_MARGIN_PX
            hy = math.sqrt(max(lim * syy, 0.0)) * (1.0 + BBOX_MARGIN_REL) + BBOX_MARGIN_PX
            if not (u + hx >= 0.0 and u - hx <= width - 1.0 and v + hy >= 0.0 and v - hy <= height - 1.0):
                continue
            dx_, dy_, dz_, _ = _view_dir(mx, my, mz, campos)
            _sh_basis(dx_, dy_, dz_, Y)
            for ch in range(3):
                col = Y[0] * np.float64(sh0[i, ch])
                for k in range(1, n_coef):
                    col += Y[k] * np.float64(sh_rest[i, k - 1, ch])
                col += 0.5
                out[i, 6 + ch] = col if col > 0.0 else 0.0
            out[i, 0] = u
            out[i, 1] = v
            out[i, 2] = syy / det
            out[i, 3] = -sxy / det
            out[i, 4] = sxx / det
            out[i, 5] = op
            out[i, 9] = depth
            out[i, 10] = sxx
            out[i, 11] = sxy
            out[i, 12] = syy
            valid[i] = True


@njit(parallel=True, cache=True, fastmath=False)
def project_bwd_kernel(
    ids, means, log_scales, quats, logit_op, sh0, sh_rest, sh_degree, Rcw, tcw, campos, cam, dilation,
    compensate, grad_out, g_means, g_log_scales, g_quats, g_logit, g_sh0, g_sh_rest,
):  # pragma: no cover - compiled
    """Vector-Jacobian product of :func:`project_fwd_kernel` for the visible rows ``ids [V]``.

    ``grad_out [V, PROJ_COLS]``: dL/d(outputs) of row ``ids[k]``. Writes rows ``ids`` of ``g_means [N, 3]``,
    ``g_log_scales [N, 3]``, ``g_quats [N, 4]``, ``g_logit [N]``, ``g_sh0 [N, 3]``, ``g_sh_rest [N, K-1, 3]``
    (other rows untouched: the caller zero-fills). Race-free (each id once).
    """
    fx, fy, k1, k2, k3, k4 = cam[0], cam[1], cam[4], cam[5], cam[6], cam[7]
    deg = _sh_degree(sh_degree, sh_rest.shape[1])
    n_coef = (deg + 1) * (deg + 1)
    V = ids.shape[0]
    for blk in prange((V + BLOCK - 1) // BLOCK):
        j = np.empty(6)
        rot = np.empty(9)
        sc = np.empty(3)
        M = np.empty((3, 3))
        AB = np.empty(6)
        gAB = np.empty(6)
        gJ = np.empty(6)
        gR = np.empty(9)
        gp = np.empty(3)
        Y = np.empty(16)
        gY = np.empty(16)
        for kk in range(blk * BLOCK, min(V, (blk + 1) * BLOCK)):
            i = ids[kk]
            g = grad_out[kk]
            # ---- recompute the forward
            mx, my, mz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
            px = Rcw[0, 0] * mx + Rcw[0, 1] * my + Rcw[0, 2] * mz + tcw[0]
            py = Rcw[1, 0] * mx + Rcw[1, 1] * my + Rcw[1, 2] * mz + tcw[1]
            pz = Rcw[2, 0] * mx + Rcw[2, 1] * my + Rcw[2, 2] * mz + tcw[2]
            depth = math.sqrt(px * px + py * py + pz * pz)
            _, _, _, _, j00, j01, j02, j10, j11, j12 = _kb_project_jacobian(
                px, py, pz, fx, fy, 0.0, 0.0, k1, k2, k3, k4)
            j[0], j[1], j[2], j[3], j[4], j[5] = j00, j01, j02, j10, j11, j12
            rt = _rotation(np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]),
                           np.float64(quats[i, 3]))
            qw, qx, qy, qz, qn = rt[0], rt[1], rt[2], rt[3], rt[4]
            for e in range(9):
                rot[e] = rt[5 + e]
            for c in range(3):
                sc[c] = math.exp(np.float64(log_scales[i, c]))
            _cov_rows(j, Rcw, rot, sc, M, AB)
            a0, a1, a2, b0, b1, b2 = AB[0], AB[1], AB[2], AB[3], AB[4], AB[5]
            sxx0 = a0 * a0 + a1 * a1 + a2 * a2
            sxy = a0 * b0 + a1 * b1 + a2 * b2
            syy0 = b0 * b0 + b1 * b1 + b2 * b2
            m01 = a0 * b1 - a1 * b0
            m02 = a0 * b2 - a2 * b0
            m12 = a1 * b2 - a2 * b1
            det0 = m01 * m01 + m02 * m02 + m12 * m12
            sxx = sxx0 + dilation
            syy = syy0 + dilation
            det = det0 + dilation * (sxx0 + syy0) + dilation * dilation
            sig = 1.0 / (1.0 + math.exp(-np.float64(logit_op[i])))
            # ---- conic, 2D covariance output and opacity
            gsxx = np.float64(g[10]) + np.float64(g[4]) / det
            gsxy = np.float64(g[11]) - np.float64(g[3]) / det
            gsyy = np.float64(g[12]) + np.float64(g[2]) / det
            gdet = -(np.float64(g[2]) * syy - np.float64(g[3]) * sxy + np.float64(g[4]) * sxx) / (det * det)
            gop = np.float64(g[5])
            gdet0 = 0.0
            if compensate:
                ratio = det0 / det
                sq = math.sqrt(ratio)
                gsig = gop * sq
                gratio = gop * sig * 0.5 / sq
                gdet0 += gratio / det
                gdet -= gratio * det0 / (det * det)
            else:
                gsig = gop
            g_logit[i] = gsig * sig * (1.0 - sig)
            gdet0 += gdet
            gsxx0 = gsxx + dilation * gdet
            gsyy0 = gsyy + dilation * gdet
            gm01, gm02, gm12 = 2.0 * m01 * gdet0, 2.0 * m02 * gdet0, 2.0 * m12 * gdet0
            gAB[0] = 2.0 * a0 * gsxx0 + b0 * gsxy + gm01 * b1 + gm02 * b2
            gAB[1] = 2.0 * a1 * gsxx0 + b1 * gsxy - gm01 * b0 + gm12 * b2
            gAB[2] = 2.0 * a2 * gsxx0 + b2 * gsxy - gm02 * b0 - gm12 * b1
            gAB[3] = 2.0 * b0 * gsyy0 + a0 * gsxy - gm01 * a1 - gm02 * a2
            gAB[4] = 2.0 * b1 * gsyy0 + a1 * gsxy + gm01 * a0 - gm12 * a2
            gAB[5] = 2.0 * b2 * gsyy0 + a2 * gsxy + gm02 * a0 + gm12 * a1
            # ---- A = J[0] M, B = J[1] M  ->  dL/dJ, dL/dM -> scales, rotation
            for k in range(3):
                gJ[k] = gAB[0] * M[k, 0] + gAB[1] * M[k, 1] + gAB[2] * M[k, 2]
                gJ[3 + k] = gAB[3] * M[k, 0] + gAB[4] * M[k, 1] + gAB[5] * M[k, 2]
            gR[:] = 0.0
            for c in range(3):
                gs = 0.0
                for k in range(3):
                    gM = j[k] * gAB[c] + j[3 + k] * gAB[3 + c]
                    gs += gM * M[k, c]
                    gMs = gM * sc[c]
                    gR[c] += Rcw[k, 0] * gMs
                    gR[3 + c] += Rcw[k, 1] * gMs
                    gR[6 + c] += Rcw[k, 2] * gMs
                g_log_scales[i, c] = gs  # d/dlog s = s d/ds and M already carries s
            gw = 2.0 * (-qz * gR[1] + qy * gR[2] + qz * gR[3] - qx * gR[5] - qy * gR[6] + qx * gR[7])
            gx = 2.0 * (qy * gR[1] + qz * gR[2] + qy * gR[3] - 2.0 * qx * gR[4] - qw * gR[5] + qz * gR[6]
                        + qw * gR[7] - 2.0 * qx * gR[8])
            gy = 2.0 * (-2.0 * qy * gR[0] + qx * gR[1] + qw * gR[2] + qx * gR[3] + qz * gR[5] - qw * gR[6]
                        + qz * gR[7] - 2.0 * qy * gR[8])
            gz = 2.0 * (-2.0 * qz * gR[0] - qw * gR[1] + qx * gR[2] + qw * gR[3] - 2.0 * qz * gR[4] + qy * gR[5]
                        + qx * gR[6] + qy * gR[7])
            dotq = qw * gw + qx * gx + qy * gy + qz * gz
            if qn != 1.0:
                g_quats[i, 0] = (gw - qw * dotq) / qn
                g_quats[i, 1] = (gx - qx * dotq) / qn
                g_quats[i, 2] = (gy - qy * dotq) / qn
                g_quats[i, 3] = (gz - qz * dotq) / qn
            else:
                n2 = qw * qw + qx * qx + qy * qy + qz * qz
                proj = dotq if n2 > QUAT_EPS2 else 0.0
                g_quats[i, 0] = gw - qw * proj
                g_quats[i, 1] = gx - qx * proj
                g_quats[i, 2] = gy - qy * proj
                g_quats[i, 3] = gz - qz * proj
            # ---- camera-frame point: uv (J^T), ray depth, and the KB Jacobian's own derivative
            gu, gv = np.float64(g[0]), np.float64(g[1])
            gdep = np.float64(g[9])
            vjp = _kb_jacobian_vjp(px, py, pz, gJ[0], gJ[1], gJ[2], gJ[3], gJ[4], gJ[5], fx, fy, k1, k2, k3, k4)
            for k in range(3):
                gp[k] = gu * j[k] + gv * j[3 + k] + vjp[8 + k]
            gp[0] += gdep * px / depth
            gp[1] += gdep * py / depth
            gp[2] += gdep * pz / depth
            gmx = Rcw[0, 0] * gp[0] + Rcw[1, 0] * gp[1] + Rcw[2, 0] * gp[2]
            gmy = Rcw[0, 1] * gp[0] + Rcw[1, 1] * gp[1] + Rcw[2, 1] * gp[2]
            gmz = Rcw[0, 2] * gp[0] + Rcw[1, 2] * gp[1] + Rcw[2, 2] * gp[2]
            # ---- SH colour (clamp at 0 passes the gradient where colour >= 0, like torch.clamp_min)
            dx_, dy_, dz_, dn = _view_dir(mx, my, mz, campos)
            _sh_basis(dx_, dy_, dz_, Y)
            gY[:] = 0.0
            for ch in range(3):
                col = Y[0] * np.float64(sh0[i, ch])
                for k in range(1, n_coef):
                    col += Y[k] * np.float64(sh_rest[i, k - 1, ch])
                gc = np.float64(g[6 + ch]) if col + 0.5 >= 0.0 else 0.0
                g_sh0[i, ch] = Y[0] * gc
                for k in range(1, n_coef):
                    g_sh_rest[i, k - 1, ch] = Y[k] * gc
                    gY[k] += np.float64(sh_rest[i, k - 1, ch]) * gc
            if dn > 0.0 and deg > 0:
                gdx, gdy, gdz = _sh_basis_vjp(dx_, dy_, dz_, gY, deg)
                dot = dx_ * gdx + dy_ * gdy + dz_ * gdz
                gmx += (gdx - dx_ * dot) / dn
                gmy += (gdy - dy_ * dot) / dn
                gmz += (gdz - dz_ * dot) / dn
            g_means[i, 0] = gmx
            g_means[i, 1] = gmy
            g_means[i, 2] = gmz


@njit(cache=True, inline="always")
def _put_grad(out, k, col, g):  # pragma: no cover - compiled
    """Row ``k`` of ``g [V, w]`` (float32 or float64) into ``out[k, col:col + w]`` as float64; zeros when ``g``
    has no rows (an output that got no gradient)."""
    w = g.shape[1]
    if g.shape[0] == 0:
        for c in range(w):
            out[k, col + c] = 0.0
    else:
        for c in range(w):
            out[k, col + c] = g[k, c]


@njit(parallel=True, cache=True, fastmath=False)
def gather_grad_out_kernel(g_uv, g_conic, g_opacity, g_color, g_depth, g_cov2d, out):  # pragma: no cover
    """The gradients of the six differentiable outputs, ``[V, w]`` each in the scene's dtype (any strides; a
    ``[0, w]`` array for an output that got no gradient), into ``out [V, PROJ_COLS]`` float64, the layout
    :func:`project_bwd_kernel` reads: the same values as numpy's ``out[:, a:b] = g`` (float32 to float64 is
    exact), in one parallel pass instead of a zero fill and six strided casting copies."""
    for k in prange(out.shape[0]):
        _put_grad(out, k, 0, g_uv)
        _put_grad(out, k, 2, g_conic)
        _put_grad(out, k, 5, g_opacity)
        _put_grad(out, k, 6, g_color)
        _put_grad(out, k, 9, g_depth)
        _put_grad(out, k, 10, g_cov2d)


@njit(parallel=True, cache=True, fastmath=False)
def gather_visible_kernel(out, ids, uv, conic, opacity, color, depth, cov2d):  # pragma: no cover - compiled
    """Rows ``ids [V]`` of :func:`project_fwd_kernel`'s ``out [N, PROJ_COLS]`` (float64) into its six
    differentiable outputs, each ``[V, ...]`` in the scene's dtype: ``uv [V, 2]``, ``conic [V, 3]``, ``opacity
    [V]``, ``color [V, 3]``, ``depth [V]``, ``cov2d [V, 3]`` (float64 to float32 rounds to nearest, as numpy's
    ``astype``: the same bits as ``out[ids][:, a:b].astype(dtype)``, one parallel pass instead of seven)."""
    for k in prange(ids.shape[0]):
        i = ids[k]
        uv[k, 0] = out[i, 0]
        uv[k, 1] = out[i, 1]
        for c in range(3):
            conic[k, c] = out[i, 2 + c]
            color[k, c] = out[i, 6 + c]
            cov2d[k, c] = out[i, 10 + c]
        opacity[k] = out[i, 5]
        depth[k] = out[i, 9]
