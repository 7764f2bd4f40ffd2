"""numba kernels of the CPU splatting fast path: KB projection, tile binning, forward and backward rasterisation.

All kernels are ``@njit(cache=True)``; the heavy ones are ``parallel=True`` (``prange`` over Gaussians or over
16x16 tiles). The dense float64 torch reference in :mod:`umi_aug.splat._torch_impl` is the oracle they are
tested against.

Data layout (one row per Gaussian, 64 bytes in float32 = one cache line)::

    packed[g] = (u, v, conic_a, conic_b, conic_c, opacity, r, g, b, ray_depth,      # columns 0..9: the data
                 lim, hy, gamma, beta, 1/a, hx)                                    # columns 10..15: footprint

``(u, v)`` is the projected mean in pixels (pixel centres at integers), ``conic = Sigma_2D^-1 = [[a, b], [b, c]]``,
``opacity`` includes the Mip compensation, ``lim = 2 ln(opacity / ALPHA_THRESHOLD)`` bounds the footprint
(``alpha >= ALPHA_THRESHOLD`` only where ``d^T conic d <= lim``), ``hx``, ``hy`` its half-extents in pixels.
The rasteriser evaluates the quadratic form in the completed-square form
``q = a (dx + beta dy)^2 + gamma dy^2`` (``beta = b/a = -Sxy/Syy``, ``gamma = (ac - b^2)/a = 1/Syy``), which
has no cancellation, so needle-thin footprints (10^6 axis ratios) keep their shape in float32; each row's pixel
span is ``|dx + beta dy| <= sqrt((lim - gamma dy^2) / a)``. The numba projection derives columns 10..15 from
the float64 covariance (determinant by Cauchy–Binet); :func:`footprint_kernel` derives them from a conic.

``exp`` in float32 kernels is :func:`fexp` (table of 2^(-k/16) + cubic, relative error < 2e-7, short
dependency chain; libm's expf was a third of the rasteriser's time); float64 kernels use ``np.exp``.

The rasteriser works in the dtype of ``packed`` (float32 for speed, float64 for the reference comparisons); its
constants come in the ``cst`` array of that dtype so that float32 arithmetic stays float32. No fastmath in the
rasteriser that training uses (:func:`raster_fwd_kernel`, :func:`raster_bwd_kernel`): the backward re-evaluates every
(Gaussian, pixel) pair with the same instructions as the forward, so the skip decisions (alpha < 1/255) and the
transmittance it reconstructs are bit-identical. Inference, which is never replayed, uses
:func:`raster_fwd_fused_kernel`: the same tile loop (:func:`_raster_fwd_tile`, inlined) with fused multiply-adds only. (The projection,
which is never replayed, uses a fastmath subset without ``nnan``/``ninf``, so its NaN/inf culling still holds.)

Every function here that is not inlined states ``fastmath=False``. numba compiles a helper once per signature, on its
first call, with the fastmath flags of the caller that made that call when the helper states none, and caches that
code on disk. Before session 40 the helpers stated none, so whichever kernel compiled first decided their code for
every kernel after it: a process that ran the fused inference kernels first (a render, a test) left contracted
helpers (``_kb_project_jacobian``, the spans, the tile gather) in ``__pycache__``, and training then linked them. The
real episode's 3DGS came out at 27.35 dB held-out with such a cache and 27.30 dB compiled fresh, the same code.
Helpers marked ``inline="always"`` are compiled inside each caller with its flags, as intended
(``tests/splat/test_kernel_flags.py``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange, types
from numba.extending import overload

from umi_aug.camera.kb import MIN_POINT_NORM, SMALL_T, THETA_MAX_SLACK
from umi_aug.runtime import quiet_numba_threading_warning
from umi_aug.splat._constants import (
    ALPHA_THRESHOLD,
    BBOX_MARGIN_PX,
    BBOX_MARGIN_REL,
    LOG_INV_ALPHA_THRESHOLD,
    MAX_ALPHA,
    MIN_DET_2D_ABS,
    MIN_DET_2D_REL,
    SH_C0,
    SH_C1,
    SH_C2,
    SH_C3,
    TILE_SIZE,
    TRANSMITTANCE_THRESHOLD,
)
from umi_aug.splat._numba_cache import install as install_kernel_cache

quiet_numba_threading_warning()
install_kernel_cache()  # before the first @njit(cache=True): stamped with every kernel source

#: Number of columns of the packed per-Gaussian array.
PACKED_COLS = 16
#: Number of per-Gaussian gradient columns: d/d(u, v, a, b, c, opacity, r, g, b, ray_depth).
GRAD_COLS = 10

_TS = TILE_SIZE
_C2_0, _C2_1, _C2_2, _C2_3, _C2_4 = SH_C2
_C3_0, _C3_1, _C3_2, _C3_3, _C3_4, _C3_5, _C3_6 = SH_C3


#: float32 ``exp`` on ``[FEXP_MIN, 0]``: ``exp(x) = 2^(-k/16) * p(r)`` with ``k = round(-16 x / ln 2)``,
#: ``|r| <= ln2/32`` and a cubic ``p`` (relative error < 2e-7, four dependent multiply-adds after the table
#: look-up). Arguments below ``FEXP_MIN`` (and NaN) are clamped to it: ``exp(-16) < 1.2e-7`` is far below any
#: alpha that passes the 1/255 threshold, so no compositing decision changes.
FEXP_MIN = -16.0
_FEXP_STEPS = 16
_LN2_16_HI = 0.0433197021484375  # ln(2)/16 split for Cody-Waite reduction (hi: 14 significant bits, k*hi exact)
_LN2_16_LO = 1.996636559080389e-06
_FEXP_TABLE = np.array([2.0 ** (-k / _FEXP_STEPS) for k in range(int(-FEXP_MIN * _FEXP_STEPS / math.log(2)) + 2)],
                       dtype=np.float32)


def fexp(x):  # pragma: no cover - replaced by the overload inside numba
    """``exp(x)`` for ``x <= 0`` (python fallback; compiled versions below)."""
    return np.exp(x)


@overload(fexp, inline="always")
def _fexp_overload(x):  # pragma: no cover - compiled
    if x == types.float32:
        def impl(x):
            if not (x > np.float32(FEXP_MIN)):
                x = np.float32(FEXP_MIN)
            if x > np.float32(0.0):
                x = np.float32(0.0)
            k = np.int32(x * np.float32(-_FEXP_STEPS / math.log(2.0)) + np.float32(0.5))  # round(-x 16/ln2) >= 0
            kf = np.float32(k)
            r = (x + kf * np.float32(_LN2_16_HI)) + kf * np.float32(_LN2_16_LO)
            p = np.float32(1.0) + r * (np.float32(1.0) + r * (np.float32(0.5) + r * np.float32(1.0 / 6.0)))
            return _FEXP_TABLE[k] * p
        return impl
    return lambda x: np.exp(x)


def raster_constants(dtype, min_transmittance: float = TRANSMITTANCE_THRESHOLD) -> np.ndarray:
    """The ``cst`` array of the rasteriser in its working dtype (``min_transmittance``: where a pixel stops)."""
    return np.array([MAX_ALPHA, ALPHA_THRESHOLD, min_transmittance, 1.0, 0.5, 0.0], dtype=dtype)


# ------------------------------------------------------------------------------------------------------------
# Kannala–Brandt projection and Jacobian of one camera-frame point (float64; same formulas as camera.kb)
# ------------------------------------------------------------------------------------------------------------
@njit(cache=True, fastmath=False)
def _kb_project_jacobian(px, py, pz, fx, fy, cx, cy, k1, k2, k3, k4):
    """Returns ``ok, theta, u, v, j00, j01, j02, j10, j11, j12`` (``d(u,v)/d(x,y,z)``, exact at ``r = 0``)."""
    m = max(abs(px), max(abs(py), abs(pz)))
    if not (m > MIN_POINT_NORM) or not math.isfinite(m):
        return False, 0.0, cx, cy, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    qx, qy, qz = px / m, py / m, pz / m
    n = math.sqrt(qx * qx + qy * qy + qz * qz)
    x, y, z = qx / n, qy / n, qz / n
    norm = m * n
    r2 = x * x + y * y
    r = math.sqrt(r2)
    theta = math.atan2(r, z)
    if z > 0.0 and r <= SMALL_T * z:
        # series branch: q = r^2/z^2, a = atan(t)/t, G(q) = a P(q a^2); exact r -> 0 limit
        q = r2 / (z * z)
        a = 1.0 + q * (-1.0 / 3.0 + q * (1.0 / 5.0 + q * (-1.0 / 7.0 + q * (1.0 / 9.0))))
        da = -1.0 / 3.0 + q * (2.0 / 5.0 + q * (-3.0 / 7.0 + q * (4.0 / 9.0)))
        w = q * a * a
        P = 1.0 + w * (k1 + w * (k2 + w * (k3 + w * k4)))
        dP = k1 + w * (2.0 * k2 + w * (3.0 * k3 + w * 4.0 * k4))
        G = a * P
        s = G / z
        dG = da * P + a * dP * (a * a + 2.0 * q * a * da)
        B = 2.0 * dG / (z * z * z)
        s_z = -(G + 2.0 * q * dG) / (z * z)
        cxx, cxy, cyy = x * x, x * y, y * y
    else:
        rd = r if r > 0.0 else 1.0
        t2 = theta * theta
        td = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        dtd = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
        s = td / rd
        rho2 = r2 + z * z
        A = (dtd * z / rho2 - td / rd) / (rd * rd)
        s_z = -dtd / rho2
        B = A * r2
        r2s = r2 if r2 > 0.0 else 1.0
        cxx, cxy, cyy = x * x / r2s, x * y / r2s, y * y / r2s
    u = fx * s * x + cx
    v = fy * s * y + cy
    j00 = fx * (s + cxx * B) / norm
    j01 = fx * cxy * B / norm
    j02 = fx * x * s_z / norm
    j10 = fy * cxy * B / norm
    j11 = fy * (s + cyy * B) / norm
    j12 = fy * y * s_z / norm
    return True, theta, u, v, j00, j01, j02, j10, j11, j12


@njit(parallel=True, cache=True, fastmath={"nsz", "arcp", "contract", "afn"})
def project_kernel(
    means, log_scales, quats, logit_op, sh0, sh_rest, sh_degree,
    Rcw, tcw, campos, cam, near, far, dilation, compensate, width, height,
    packed, uv_out, depth_out, valid_out, counts_out,
):  # pragma: no cover - compiled
    """EWA projection of every Gaussian through the full KB model, culling and SH colour.

    ``cam = (fx, fy, cx, cy, k1, k2, k3, k4, theta_max)``. Writes ``packed [N, 16]`` (any float dtype),
    ``uv_out [N, 2]`` float64 projected means, ``depth_out [N]`` float64 ray distance (for sorting),
    ``valid_out [N]`` bool and ``counts_out [N]`` the number of tiles each footprint reaches (as
    :func:`count_tiles_kernel`, fused here to save a parallel region).
    """
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    k1, k2, k3, k4, theta_max = cam[4], cam[5], cam[6], cam[7], cam[8]
    n_rest = sh_rest.shape[1]
    dummy = np.empty(0, dtype=np.int64)
    for i in prange(means.shape[0]):
        valid_out[i] = False
        counts_out[i] = 0
        depth_out[i] = 0.0
        uv_out[i, 0] = 0.0
        uv_out[i, 1] = 0.0
        for col in range(packed.shape[1]):
            packed[i, col] = 0.0
        mx, my, mz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
        px = Rcw[0, 0] * mx + Rcw[0, 1] * my + Rcw[0, 2] * mz + tcw[0]
        py = Rcw[1, 0] * mx + Rcw[1, 1] * my + Rcw[1, 2] * mz + tcw[1]
        pz = Rcw[2, 0] * mx + Rcw[2, 1] * my + Rcw[2, 2] * mz + tcw[2]
        depth = math.sqrt(px * px + py * py + pz * pz)
        if not (depth > near and depth < far):
            continue
        ok, theta, u, v, j00, j01, j02, j10, j11, j12 = _kb_project_jacobian(
            px, py, pz, fx, fy, cx, cy, k1, k2, k3, k4
        )
        if not ok or not (theta <= theta_max + THETA_MAX_SLACK):
            continue
        # rotation of the Gaussian (normalised quaternion; zero -> identity)
        qw, qx, qy, qz = (np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]),
                          np.float64(quats[i, 3]))
        qn2 = qw * qw + qx * qx + qy * qy + qz * qz
        if qn2 > 0.0 and math.isfinite(qn2):
            qn = math.sqrt(qn2)
            qw, qx, qy, qz = qw / qn, qx / qn, qy / qn, qz / qn
        else:
            qw, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
        r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
        r01 = 2.0 * (qx * qy - qw * qz)
        r02 = 2.0 * (qx * qz + qw * qy)
        r10 = 2.0 * (qx * qy + qw * qz)
        r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
        r12 = 2.0 * (qy * qz - qw * qx)
        r20 = 2.0 * (qx * qz - qw * qy)
        r21 = 2.0 * (qy * qz + qw * qx)
        r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
        s0 = math.exp(np.float64(log_scales[i, 0]))
        s1 = math.exp(np.float64(log_scales[i, 1]))
        s2 = math.exp(np.float64(log_scales[i, 2]))
        # W = J Rcw (2x3), then JM = W R diag(s)
        w00 = j00 * Rcw[0, 0] + j01 * Rcw[1, 0] + j02 * Rcw[2, 0]
        w01 = j00 * Rcw[0, 1] + j01 * Rcw[1, 1] + j02 * Rcw[2, 1]
        w02 = j00 * Rcw[0, 2] + j01 * Rcw[1, 2] + j02 * Rcw[2, 2]
        w10 = j10 * Rcw[0, 0] + j11 * Rcw[1, 0] + j12 * Rcw[2, 0]
        w11 = j10 * Rcw[0, 1] + j11 * Rcw[1, 1] + j12 * Rcw[2, 1]
        w12 = j10 * Rcw[0, 2] + j11 * Rcw[1, 2] + j12 * Rcw[2, 2]
        a0 = (w00 * r00 + w01 * r10 + w02 * r20) * s0
        a1 = (w00 * r01 + w01 * r11 + w02 * r21) * s1
        a2 = (w00 * r02 + w01 * r12 + w02 * r22) * s2
        b0 = (w10 * r00 + w11 * r10 + w12 * r20) * s0
        b1 = (w10 * r01 + w11 * r11 + w12 * r21) * s1
        b2 = (w10 * r02 + w11 * r12 + w12 * r22) * s2
        sxx0 = a0 * a0 + a1 * a1 + a2 * a2
        sxy = a0 * b0 + a1 * b1 + a2 * b2
        syy0 = b0 * b0 + b1 * b1 + b2 * b2
        m01 = a0 * b1 - a1 * b0
        m02 = a0 * b2 - a2 * b0
        m12 = a1 * b2 - a2 * b1
        det0 = m01 * m01 + m02 * m02 + m12 * m12  # Cauchy-Binet: exact sign, no cancellation
        sxx = sxx0 + dilation
        syy = syy0 + dilation
        det = det0 + dilation * (sxx0 + syy0) + dilation * dilation
        half_tr = 0.5 * (sxx + syy)
        if not (det > MIN_DET_2D_ABS and det > MIN_DET_2D_REL * half_tr * half_tr and math.isfinite(det)):
            continue
        lo = np.float64(logit_op[i])
        if lo >= 0.0:
            op = 1.0 / (1.0 + math.exp(-lo))
        else:
            el = math.exp(lo)
            op = el / (1.0 + el)
        if compensate:
            op = op * math.sqrt(det0 / det)
        if not (op >= ALPHA_THRESHOLD):
            continue
        lim = 2.0 * (math.log(op) + LOG_INV_ALPHA_THRESHOLD)
        hx = math.sqrt(lim * sxx) * (1.0 + BBOX_MARGIN_REL) + BBOX_MARGIN_PX
        hy = math.sqrt(lim * syy) * (1.0 + BBOX_MARGIN_REL) + BBOX_MARGIN_PX
        if u + hx < 0.0 or u - hx > width - 1.0 or v + hy < 0.0 or v - hy > height - 1.0:
            continue
        # SH colour, view direction from the camera centre (world frame)
        dx_, dy_, dz_ = mx - campos[0], my - campos[1], mz - campos[2]
        dn = math.sqrt(dx_ * dx_ + dy_ * dy_ + dz_ * dz_)
        if dn > 0.0:
            dx_, dy_, dz_ = dx_ / dn, dy_ / dn, dz_ / dn
        else:
            dx_, dy_, dz_ = 0.0, 0.0, 1.0
        deg = min(sh_degree, 3)
        if deg >= 3 and n_rest < 15:
            deg = 2
        if deg >= 2 and n_rest < 8:
            deg = 1
        if deg >= 1 and n_rest < 3:
            deg = 0
        xx, yy, zz = dx_ * dx_, dy_ * dy_, dz_ * dz_
        xy, yz, xz = dx_ * dy_, dy_ * dz_, dx_ * dz_
        y1_0, y1_1, y1_2 = -SH_C1 * dy_, SH_C1 * dz_, -SH_C1 * dx_
        y2_0, y2_1, y2_2, y2_3, y2_4 = (
            _C2_0 * xy, _C2_1 * yz, _C2_2 * (2.0 * zz - xx - yy), _C2_3 * xz, _C2_4 * (xx - yy)
        )
        y3_0 = _C3_0 * dy_ * (3.0 * xx - yy)
        y3_1 = _C3_1 * xy * dz_
        y3_2 = _C3_2 * dy_ * (4.0 * zz - xx - yy)
        y3_3 = _C3_3 * dz_ * (2.0 * zz - 3.0 * xx - 3.0 * yy)
        y3_4 = _C3_4 * dx_ * (4.0 * zz - xx - yy)
        y3_5 = _C3_5 * dz_ * (xx - yy)
        y3_6 = _C3_6 * dx_ * (xx - 3.0 * yy)
        for ch in range(3):
            c = SH_C0 * np.float64(sh0[i, ch])
            if deg >= 1:
                c += y1_0 * sh_rest[i, 0, ch] + y1_1 * sh_rest[i, 1, ch] + y1_2 * sh_rest[i, 2, ch]
            if deg >= 2:
                c += (
                    y2_0 * sh_rest[i, 3, ch] + y2_1 * sh_rest[i, 4, ch] + y2_2 * sh_rest[i, 5, ch]
                    + y2_3 * sh_rest[i, 6, ch] + y2_4 * sh_rest[i, 7, ch]
                )
            if deg >= 3:
                c += (
                    y3_0 * sh_rest[i, 8, ch] + y3_1 * sh_rest[i, 9, ch] + y3_2 * sh_rest[i, 10, ch]
                    + y3_3 * sh_rest[i, 11, ch] + y3_4 * sh_rest[i, 12, ch] + y3_5 * sh_rest[i, 13, ch]
                    + y3_6 * sh_rest[i, 14, ch]
                )
            c += 0.5
            packed[i, 6 + ch] = c if c > 0.0 else 0.0
        packed[i, 0] = u
        packed[i, 1] = v
        packed[i, 2] = syy / det
        packed[i, 3] = -sxy / det
        packed[i, 4] = sxx / det
        packed[i, 5] = op
        packed[i, 9] = depth
        _write_footprint(packed, i, sxx, sxy, syy, det)
        uv_out[i, 0] = u
        uv_out[i, 1] = v
        depth_out[i] = depth
        valid_out[i] = packed[i, 10] >= 0.0
        if valid_out[i]:
            counts_out[i] = _row_tiles(packed, i, width, height, 1, dummy, False)


@njit(cache=True, fastmath=False)
def _write_footprint(packed, i, sxx, sxy, syy, det):  # pragma: no cover - compiled
    """Columns 10..15 of row ``i`` from its 2D covariance ``[[sxx, sxy], [sxy, syy]]`` (float64, ``det`` its
    determinant) and the stored opacity (``lim = -1``: no footprint)."""
    op = np.float64(packed[i, 5])
    if op >= ALPHA_THRESHOLD and det > 0.0 and sxx > 0.0 and syy > 0.0:
        lim = 2.0 * (math.log(op) + LOG_INV_ALPHA_THRESHOLD)
        packed[i, 10] = lim
        packed[i, 11] = math.sqrt(lim * syy) * (1.0 + BBOX_MARGIN_REL) + BBOX_MARGIN_PX
        packed[i, 12] = 1.0 / syy
        packed[i, 13] = -sxy / syy
        packed[i, 14] = det / syy
        packed[i, 15] = math.sqrt(lim * sxx) * (1.0 + BBOX_MARGIN_REL) + BBOX_MARGIN_PX
    else:
        packed[i, 10] = -1.0
        for col in range(11, 16):
            packed[i, col] = 0.0


@njit(cache=True, inline="always")
def _footprint_from_conic(packed, i):  # pragma: no cover - compiled
    """Columns 10..15 of row ``i`` from its conic (columns 2..4) and opacity (column 5)."""
    a, b, c = np.float64(packed[i, 2]), np.float64(packed[i, 3]), np.float64(packed[i, 4])
    detc = a * c - b * b
    if detc > 0.0 and a > 0.0 and c > 0.0:
        _write_footprint(packed, i, c / detc, -b / detc, a / detc, 1.0 / detc)
    else:
        _write_footprint(packed, i, 0.0, 0.0, 0.0, 0.0)


@njit(parallel=True, cache=True, fastmath=False)
def footprint_kernel(packed):  # pragma: no cover - compiled
    """Fill columns 10..15 of every row from its conic (columns 2..4) and opacity (column 5)."""
    for i in prange(packed.shape[0]):
        _footprint_from_conic(packed, i)


@njit(parallel=True, cache=True, fastmath=False)
def pack_kernel(uv, conic, opacity, color, depth, packed):  # pragma: no cover - compiled
    """Every row of ``packed [V, PACKED_COLS]``: columns 0..9 from the projection's outputs ``uv [V, 2]``, ``conic
    [V, 3]``, ``opacity [V]``, ``color [V, 3]``, ``depth [V]`` (the dtype of ``packed``), then the footprint
    columns as :func:`footprint_kernel` (one parallel pass instead of a zero fill, five strided copies and that
    kernel)."""
    for i in prange(packed.shape[0]):
        packed[i, 0] = uv[i, 0]
        packed[i, 1] = uv[i, 1]
        for c in range(3):
            packed[i, 2 + c] = conic[i, c]
            packed[i, 6 + c] = color[i, c]
        packed[i, 5] = opacity[i]
        packed[i, 9] = depth[i]
        _footprint_from_conic(packed, i)


# ------------------------------------------------------------------------------------------------------------
# Footprints: bounding boxes, tile tests, per-row pixel spans (float64, shared by binning, forward, backward)
# ------------------------------------------------------------------------------------------------------------
@njit(cache=True, fastmath=False)
def _pixel_range(center, half, lo, hi):
    """Integer pixel span ``[ceil(center - half), floor(center + half)]`` clipped to ``[lo, hi]``."""
    a = center - half
    b = center + half
    if not (b >= lo and a <= hi):
        return 1, 0
    ia = lo if a <= lo else int(math.ceil(a))
    ib = hi if b >= hi else int(math.floor(b))
    return ia, ib


@njit(cache=True, fastmath=False)
def _quad(a, beta, gamma, dx, dy):
    """``a (dx + beta dy)^2 + gamma dy^2`` (the conic quadratic form without cancellation)."""
    e = dx + beta * dy
    return a * e * e + gamma * dy * dy


@njit(cache=True, fastmath=False)
def _ellipse_hits_rect(mx, my, a, beta, gamma, lim, x0, x1, y0, y1):
    """Whether ``min over [x0,x1]x[y0,y1]`` of the quadratic form (``d = p - mean``) is ``<= lim``."""
    if x0 <= mx <= x1 and y0 <= my <= y1:
        return True
    tol = lim * (1.0 + 1e-6) + 1e-9
    c = a * beta * beta + gamma  # conic c; the conic b is a * beta
    best = np.inf
    for k in range(2):
        dx = (x0 if k == 0 else x1) - mx  # vertical edge: minimise over dy
        dy = -a * beta * dx / c
        dy = min(max(dy, y0 - my), y1 - my)
        best = min(best, _quad(a, beta, gamma, dx, dy))
        dy = (y0 if k == 0 else y1) - my  # horizontal edge: minimise over dx
        dx = -beta * dy
        dx = min(max(dx, x0 - mx), x1 - mx)
        best = min(best, _quad(a, beta, gamma, dx, dy))
    return best <= tol


@njit(cache=True, fastmath=False)
def _tile_rect(packed, g, width, height):
    """Tile range ``tx0, tx1, ty0, ty1`` (inclusive; empty when tx0 > tx1) of the footprint of row ``g``."""
    if packed[g, 10] < 0.0:
        return 1, 0, 1, 0
    ix0, ix1 = _pixel_range(np.float64(packed[g, 0]), np.float64(packed[g, 15]), 0, width - 1)
    iy0, iy1 = _pixel_range(np.float64(packed[g, 1]), np.float64(packed[g, 11]), 0, height - 1)
    if ix0 > ix1 or iy0 > iy1:
        return 1, 0, 1, 0
    return ix0 // _TS, ix1 // _TS, iy0 // _TS, iy1 // _TS


@njit(cache=True, fastmath=False)
def _row_tiles(packed, g, width, height, tiles_x, out, fill):
    """Count (``fill=False``) or write into ``out`` the tiles reached by the footprint of row ``g``."""
    tx0, tx1, ty0, ty1 = _tile_rect(packed, g, width, height)
    mx, my = np.float64(packed[g, 0]), np.float64(packed[g, 1])
    lim = np.float64(packed[g, 10])
    gamma, beta = np.float64(packed[g, 12]), np.float64(packed[g, 13])
    inv_a = np.float64(packed[g, 14])
    a = 1.0 / inv_a if inv_a > 0.0 else 0.0
    n = 0
    for ty in range(ty0, ty1 + 1):
        y0 = ty * _TS
        y1 = min(y0 + _TS - 1, height - 1)
        for tx in range(tx0, tx1 + 1):
            x0 = tx * _TS
            x1 = min(x0 + _TS - 1, width - 1)
            if _ellipse_hits_rect(mx, my, a, beta, gamma, lim, x0, x1, y0, y1):
                if fill:
                    out[n] = ty * tiles_x + tx
                n += 1
    return n


@njit(parallel=True, cache=True, fastmath=False)
def count_tiles_kernel(packed, rows, width, height, counts):  # pragma: no cover - compiled
    """``counts[i]`` = number of tiles whose pixel rectangle the footprint of ``packed[rows[i]]`` reaches."""
    dummy = np.empty(0, dtype=np.int64)
    for i in prange(rows.shape[0]):
        counts[i] = _row_tiles(packed, rows[i], width, height, 1, dummy, False)


@njit(parallel=True, cache=True, fastmath=False)
def fill_tiles_kernel(packed, rows, start_of, counts, width, height, tiles_x, isect_tile, isect_row):  # pragma: no cover
    """Intersection records of ``rows[i]`` at ``start_of[i] .. start_of[i] + counts[i]`` (Gaussian-major, the
    Gaussians in depth order): ``isect_tile[e]``, ``isect_row[e]``; same decisions as :func:`count_tiles_kernel`."""
    for i in prange(rows.shape[0]):
        e0 = start_of[i]
        e1 = e0 + counts[i]
        if e1 > e0:
            _row_tiles(packed, rows[i], width, height, tiles_x, isect_tile[e0:e1], True)
            for e in range(e0, e1):
                isect_row[e] = rows[i]


@njit(cache=True, fastmath=False)
def sort_by_tile_kernel(isect_tile, isect_row, n_tiles, tile_start, sorted_row, pos_of_isect):  # pragma: no cover
    """Stable counting sort of the intersections by tile (keeps the depth order within each tile)."""
    m = isect_tile.shape[0]
    for t in range(n_tiles + 1):
        tile_start[t] = 0
    for e in range(m):
        tile_start[isect_tile[e] + 1] += 1
    for t in range(n_tiles):
        tile_start[t + 1] += tile_start[t]
    cursor = tile_start[:-1].copy()
    for e in range(m):
        t = isect_tile[e]
        p = cursor[t]
        cursor[t] = p + 1
        sorted_row[p] = isect_row[e]
        pos_of_isect[e] = p


@njit(cache=True, fastmath=False)
def radix_argsort_f64(keys):  # pragma: no cover - compiled
    """Stable argsort of non-negative finite float64 keys (LSD radix on the IEEE bits, 4 x 16-bit digits)."""
    n = keys.shape[0]
    bits = keys.view(np.uint64)
    idx = np.arange(n).astype(np.int64)
    tmp = np.empty(n, dtype=np.int64)
    count = np.zeros(65537, dtype=np.int64)
    for shift in range(0, 64, 16):
        count[:] = 0
        for i in range(n):
            d = np.int64((bits[idx[i]] >> np.uint64(shift)) & np.uint64(0xFFFF))
            count[d + 1] += 1
        if count[1:].max() == n:  # all keys share this digit: the pass would not move anything
            continue
        for d in range(65536):
            count[d + 1] += count[d]
        for i in range(n):
            j = idx[i]
            d = np.int64((bits[j] >> np.uint64(shift)) & np.uint64(0xFFFF))
            tmp[count[d]] = j
            count[d] += 1
        idx, tmp = tmp, idx
    return idx


# ------------------------------------------------------------------------------------------------------------
# Rasterisation
# ------------------------------------------------------------------------------------------------------------
@njit(cache=True, fastmath=False)
def _row_span(mx, my, lim, gamma, beta, inv_a, yf, x_lo, x_hi):
    """Pixels ``[xa, xb]`` of row ``yf`` (clipped to ``[x_lo, x_hi]``) that may lie inside the footprint
    ``|dx + beta dy| <= sqrt((lim - gamma dy^2) / a)`` (float64 arguments; one square root)."""
    dy = yf - my
    r = (lim - gamma * dy * dy) * inv_a
    sq = math.sqrt(r) if r > 0.0 else 0.0
    half = sq * (1.0 + BBOX_MARGIN_REL) + BBOX_MARGIN_PX
    return _pixel_range(mx - beta * dy, half, x_lo, x_hi)


@njit(cache=True, fastmath=False)
def _gather_tile(packed, uv64, sorted_row, s0, s1, x0, y0):  # pragma: no cover - compiled
    """Rows ``sorted_row[s0:s1]`` of ``packed`` as a contiguous ``[s1 - s0, 16]`` buffer with the means in
    tile-local pixels (``uv64 - (x0, y0)``: float32 then resolves them to ~1e-6 px at any image size)."""
    n = max(s1 - s0, 0)
    tp = np.empty((n, packed.shape[1]), dtype=packed.dtype)
    for j in range(n):
        g = sorted_row[s0 + j]
        for col in range(2, packed.shape[1]):
            tp[j, col] = packed[g, col]
        tp[j, 0] = uv64[g, 0] - x0
        tp[j, 1] = uv64[g, 1] - y0
    return tp


@njit(cache=True, inline="always")
def _tile_gaussian(tp, j):  # pragma: no cover - compiled
    """Row ``j`` of a tile's gathered Gaussians (:func:`_gather_tile`) as the tile loops read it: ``(mx, my, a,
    opacity, r, g, b, ray_depth, gamma, beta)`` in the working dtype, then ``(mx, my, lim, gamma, beta, 1/a)`` in
    float64 for the row spans."""
    mx, my = tp[j, 0], tp[j, 1]
    gam, bet = tp[j, 12], tp[j, 13]
    return (mx, my, tp[j, 2], tp[j, 5], tp[j, 6], tp[j, 7], tp[j, 8], tp[j, 9], gam, bet,
            np.float64(mx), np.float64(my), np.float64(tp[j, 10]), np.float64(gam), np.float64(bet),
            np.float64(tp[j, 14]))


@njit(cache=True, inline="always")
def _fwd_tile_begin(t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, cst, active):
    """Tile ``t``'s frame and start state for the forward tile loops: ``(x0, y0, tw, th, npix, T, Cr, Cg, Cb, D,
    last, done, n_done, s0, tp)`` — pixels with ``active`` False start done; a tile without an active pixel gathers
    none of its Gaussians (``tp`` empty)."""
    one = cst[3]
    npx = _TS * _TS
    ty = t // tiles_x
    tx = t - ty * tiles_x
    x0 = tx * _TS
    y0 = ty * _TS
    tw = min(x0 + _TS, width) - x0
    th = min(y0 + _TS, height) - y0
    npix = tw * th
    T = np.full(npx, one)
    Cr = np.zeros(npx, dtype=packed.dtype)
    Cg = np.zeros(npx, dtype=packed.dtype)
    Cb = np.zeros(npx, dtype=packed.dtype)
    D = np.zeros(npx, dtype=packed.dtype)
    last = np.full(npx, -1, dtype=np.int32)
    done = np.zeros(npx, dtype=np.bool_)
    n_done = 0
    for yl in range(th):
        for xl in range(tw):
            if not active[y0 + yl, x0 + xl]:
                done[yl * _TS + xl] = True
                n_done += 1
    s0 = tile_start[t]
    s1 = s0 if n_done == npix else tile_start[t + 1]
    tp = _gather_tile(packed, uv64, sorted_row, s0, s1, x0, y0)
    return x0, y0, tw, th, npix, T, Cr, Cg, Cb, D, last, done, n_done, s0, tp


@njit(cache=True, inline="always")
def _fwd_tile_end(t, x0, y0, tw, th, T, Cr, Cg, Cb, D, last, evals,
                  out_rgb, out_depth, out_T, out_last, out_evals):  # pragma: no cover - compiled
    """Tile ``t``'s pixels into the forward outputs."""
    out_evals[t] = evals
    for yl in range(th):
        for xl in range(tw):
            p = yl * _TS + xl
            out_rgb[y0 + yl, x0 + xl, 0] = Cr[p]
            out_rgb[y0 + yl, x0 + xl, 1] = Cg[p]
            out_rgb[y0 + yl, x0 + xl, 2] = Cb[p]
            out_depth[y0 + yl, x0 + xl] = D[p]
            out_T[y0 + yl, x0 + xl] = T[p]
            out_last[y0 + yl, x0 + xl] = last[p]


@njit(cache=True, inline="always")
def _composite(p, alpha, cr, cg, cb, dep, s32, t_thr, one, T, Cr, Cg, Cb, D, last, done):  # pragma: no cover
    """Pixel ``p`` of a tile takes one Gaussian of ``alpha`` (>= the threshold) front to back; returns 1 when the
    pixel's transmittance would fall below ``t_thr`` (it is then done and takes nothing), else 0."""
    Tp = T[p]
    test_T = Tp * (one - alpha)
    if test_T < t_thr:
        done[p] = True
        return 1
    w = alpha * Tp
    Cr[p] += w * cr
    Cg[p] += w * cg
    Cb[p] += w * cb
    D[p] += w * dep
    T[p] = test_T
    last[p] = s32
    return 0


@njit(cache=True, inline="always")
def _row_alphas(lx, mx, a, op, bdy, gdy, max_alpha, half, zero, G_row, alpha_row):  # pragma: no cover - compiled
    """One pixel row of a tile, all 16 lanes at once (no branch: LLVM vectorises it): ``G_row[x] = exp(power)`` and
    ``alpha_row[x] = min(max_alpha, opacity G)``, 0 where ``power > 0``, with ``power = -(a e^2 + gamma dy^2) / 2``,
    ``e = x - mx + beta dy``. The same instructions per pixel as the scalar loops, so the same bits; lanes outside
    the row's span are computed and never read."""
    for x in range(_TS):
        e = lx[x] - mx + bdy
        power = -half * (a * e * e + gdy)
        G = fexp(power)
        G_row[x] = G
        al = min(max_alpha, op * G)
        alpha_row[x] = al if power <= zero else zero


@njit(cache=True, inline="always")
def _lanes_x(xs, dtype_zero):  # pragma: no cover - compiled
    """``xs`` (tile-local pixel x, ``arange(16)`` or fewer) padded to 16 lanes."""
    lx = np.full(_TS, dtype_zero)
    for x in range(min(_TS, xs.shape[0])):
        lx[x] = xs[x]
    return lx


@njit(cache=True, inline="always")
def _raster_fwd_tile(
    t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst, active,
    out_rgb, out_depth, out_T, out_last, out_evals,
):  # pragma: no cover - compiled
    """Tile ``t`` of :func:`raster_fwd_kernel` (inlined into each forward kernel: numba compiles it with the
    caller's floating-point flags). Each row a Gaussian covers first gets its 16 lanes' alphas at once
    (:func:`_row_alphas`, vectorised), then the row's span composites them pixel by pixel; the same bits as the
    scalar loop of :func:`_raster_fwd_tile_scalar`, ~1.25x faster. Pixels with ``active`` False start (and stay)
    done; a tile without an active pixel reads none of its Gaussians."""
    max_alpha, a_thr, t_thr, one, half, zero = cst[0], cst[1], cst[2], cst[3], cst[4], cst[5]
    x0, y0, tw, th, npix, T, Cr, Cg, Cb, D, last, done, n_done, s0, tp = _fwd_tile_begin(
        t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, cst, active)
    lx = _lanes_x(xs, zero)
    G_row = np.empty(_TS, dtype=packed.dtype)
    alpha_row = np.empty(_TS, dtype=packed.dtype)
    evals = 0
    for j in range(tp.shape[0]):
        if tp[j, 10] < zero:
            continue
        mx, my, a, op, cr, cg, cb, dep, gam, bet, mx64, my64, lim64, gam64, bet64, inva64 = _tile_gaussian(tp, j)
        ya, yb = _pixel_range(my64, np.float64(tp[j, 11]), 0, th - 1)
        s32 = np.int32(s0 + j)
        for y in range(ya, yb + 1):
            xa, xb = _row_span(mx64, my64, lim64, gam64, bet64, inva64, np.float64(y), 0, tw - 1)
            if xa > xb:
                continue
            evals += xb - xa + 1
            dy = ys[y] - my
            _row_alphas(lx, mx, a, op, bet * dy, gam * dy * dy, max_alpha, half, zero, G_row, alpha_row)
            base = y * _TS
            for x in range(xa, xb + 1):
                p = base + x
                if done[p]:
                    continue
                alpha = alpha_row[x]
                if alpha < a_thr:
                    continue
                n_done += _composite(p, alpha, cr, cg, cb, dep, s32, t_thr, one, T, Cr, Cg, Cb, D, last, done)
        if n_done == npix:
            break
    _fwd_tile_end(t, x0, y0, tw, th, T, Cr, Cg, Cb, D, last, evals, out_rgb, out_depth, out_T, out_last, out_evals)


@njit(cache=True, inline="always")
def _raster_fwd_tile_scalar(
    t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst, active,
    out_rgb, out_depth, out_T, out_last, out_evals,
):  # pragma: no cover - compiled
    """:func:`_raster_fwd_tile` evaluating each (Gaussian, pixel) pair on its own, only inside the row's span (the
    loop before session 38): the reference of ``tests/splat/test_raster_workers.py``."""
    max_alpha, a_thr, t_thr, one, half, zero = cst[0], cst[1], cst[2], cst[3], cst[4], cst[5]
    x0, y0, tw, th, npix, T, Cr, Cg, Cb, D, last, done, n_done, s0, tp = _fwd_tile_begin(
        t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, cst, active)
    evals = 0
    for j in range(tp.shape[0]):
        if tp[j, 10] < zero:
            continue
        mx, my, a, op, cr, cg, cb, dep, gam, bet, mx64, my64, lim64, gam64, bet64, inva64 = _tile_gaussian(tp, j)
        ya, yb = _pixel_range(my64, np.float64(tp[j, 11]), 0, th - 1)
        s32 = np.int32(s0 + j)
        for y in range(ya, yb + 1):
            xa, xb = _row_span(mx64, my64, lim64, gam64, bet64, inva64, np.float64(y), 0, tw - 1)
            if xa > xb:
                continue
            evals += xb - xa + 1
            dy = ys[y] - my
            gdy = gam * dy * dy
            bdy = bet * dy
            base = y * _TS
            for x in range(xa, xb + 1):
                p = base + x
                if done[p]:
                    continue
                e = xs[x] - mx + bdy
                power = -half * (a * e * e + gdy)
                if power > zero:
                    continue
                alpha = min(max_alpha, op * fexp(power))
                if alpha < a_thr:
                    continue
                n_done += _composite(p, alpha, cr, cg, cb, dep, s32, t_thr, one, T, Cr, Cg, Cb, D, last, done)
        if n_done == npix:
            break
    _fwd_tile_end(t, x0, y0, tw, th, T, Cr, Cg, Cb, D, last, evals, out_rgb, out_depth, out_T, out_last, out_evals)


@njit(parallel=True, cache=True, fastmath=False)
def raster_fwd_kernel(
    packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst, active,
    out_rgb, out_depth, out_T, out_last, out_evals, n_workers,
):  # pragma: no cover - compiled
    """Front-to-back compositing per 16x16 tile, parallel over tiles: worker ``k`` of ``n_workers`` (numba's thread
    count, passed in: a cached kernel cannot ask for it) takes tiles ``k, k + n_workers, k + 2 n_workers, ...``. On 2
    idle cores this is ~1.3x faster than numba handing out one tile at a time, and each row's alphas computed in
    vector lanes (:func:`_row_alphas`) another ~1.25x: the same bytes as the reference
    :func:`_raster_fwd_kernel_per_tile` (one tile per hand-out, scalar pairs); ``benchmarks/raster_workers.py``.

    Each tile first copies its rows of ``packed`` (``sorted_row[tile_start[t]:tile_start[t+1]]``, depth order)
    into a contiguous local buffer (:func:`_gather_tile`, means from ``uv64`` in tile-local pixels) and then reads
    them sequentially; ``xs``/``ys`` = ``arange(16)``. For each Gaussian of the tile (depth order) only the rows of its
    footprint are visited, and of each row only its span's pixels composite. ``active [H, W]`` bool: pixels left
    out (False) composite nothing (the values of an empty pixel below) and cost nothing once their tile has no
    active pixel; the others are exactly what an all-active call gives. Outputs (background NOT added):
    ``out_rgb [H, W, 3] = sum_i c_i alpha_i T_i``,
    ``out_depth [H, W] = sum_i t_i alpha_i T_i``, ``out_T [H, W]`` final transmittance, ``out_last [H, W]``
    int32 position (in ``sorted_row``) of the last composited Gaussian (-1: none), ``out_evals [n_tiles]``
    (Gaussian, pixel) pairs visited.
    """
    n_tiles = tile_start.shape[0] - 1
    for k in prange(n_workers):
        for t in range(k, n_tiles, n_workers):
            _raster_fwd_tile(t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst, active,
                             out_rgb, out_depth, out_T, out_last, out_evals)


@njit(parallel=True, cache=True, fastmath=False)
def _raster_fwd_kernel_per_tile(
    packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst, active,
    out_rgb, out_depth, out_T, out_last, out_evals,
):  # pragma: no cover - compiled
    """:func:`raster_fwd_kernel` as it was before session 37: a ``prange`` over the tiles, which numba hands out one
    chunk at a time (``numba.parallel_chunksize``), and each (Gaussian, pixel) pair evaluated on its own
    (:func:`_raster_fwd_tile_scalar`). The same outputs; the reference of the tests and
    ``benchmarks/raster_workers.py``."""
    for t in prange(tile_start.shape[0] - 1):
        _raster_fwd_tile_scalar(t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst, active,
                                out_rgb, out_depth, out_T, out_last, out_evals)


@njit(parallel=True, cache=True, fastmath=False)
def _raster_fwd_kernel_scalar(
    packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst, active,
    out_rgb, out_depth, out_T, out_last, out_evals, n_workers,
):  # pragma: no cover - compiled
    """:func:`raster_fwd_kernel` with the scalar pair loop (:func:`_raster_fwd_tile_scalar`; session 37's kernel):
    ``benchmarks/raster_workers.py`` times the lanes against it. The same outputs."""
    n_tiles = tile_start.shape[0] - 1
    for k in prange(n_workers):
        for t in range(k, n_tiles, n_workers):
            _raster_fwd_tile_scalar(t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst,
                                    active, out_rgb, out_depth, out_T, out_last, out_evals)


@njit(parallel=True, cache=True, fastmath={"contract"})
def raster_fwd_fused_kernel(
    packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst, active,
    out_rgb, out_depth, out_T, out_last, out_evals, n_workers,
):  # pragma: no cover - compiled
    """:func:`raster_fwd_kernel` with fused multiply-adds (LLVM ``contract``, nothing else of fastmath): for
    inference only, where no backward re-evaluates the pairs. Outputs differ from :func:`raster_fwd_kernel`'s by
    rounding (~4e-7 in float32 colour); ~x1.17 faster on the 2-core machine (benchmarks/raster_occupancy.py)."""
    n_tiles = tile_start.shape[0] - 1
    for k in prange(n_workers):
        for t in range(k, n_tiles, n_workers):
            _raster_fwd_tile(t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst, active,
                             out_rgb, out_depth, out_T, out_last, out_evals)


@njit(cache=True, inline="always")
def _bwd_tile_begin(t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, final_T, last_idx, g_rgb,
                    g_depth, g_T, out_grad):  # pragma: no cover - compiled
    """Tile ``t``'s frame and start state for the backward tile loops (its rows of ``out_grad`` zeroed):
    ``(tw, th, state, max_last, tp)`` with ``state = (Tc, Tf, lastp, gc, gd, gT, Rc, Rd, la, lc, ld)`` per pixel
    (transmittance being recovered, final transmittance, last contributor, the three output gradients, the colour
    and depth composited behind, the last alpha / colour / depth taken) and ``tp`` the tile's Gaussians up to the
    last contributor of any pixel."""
    first = tile_start[t]
    ty = t // tiles_x
    tx = t - ty * tiles_x
    x0 = tx * _TS
    y0 = ty * _TS
    tw = min(x0 + _TS, width) - x0
    th = min(y0 + _TS, height) - y0
    n = _TS * _TS
    Tc = np.ones(n, dtype=packed.dtype)
    Tf = np.ones(n, dtype=packed.dtype)
    lastp = np.full(n, -1, dtype=np.int64)
    gc = np.zeros((n, 3), dtype=packed.dtype)
    gd = np.zeros(n, dtype=packed.dtype)
    gT = np.zeros(n, dtype=packed.dtype)
    Rc = np.zeros((n, 3), dtype=packed.dtype)
    Rd = np.zeros(n, dtype=packed.dtype)
    la = np.zeros(n, dtype=packed.dtype)
    lc = np.zeros((n, 3), dtype=packed.dtype)
    ld = np.zeros(n, dtype=packed.dtype)
    max_last = -1
    for y in range(y0, y0 + th):
        for x in range(x0, x0 + tw):
            p = (y - y0) * _TS + (x - x0)
            Tf[p] = final_T[y, x]
            Tc[p] = final_T[y, x]
            lastp[p] = last_idx[y, x]
            max_last = max(max_last, last_idx[y, x])
            gc[p, 0] = g_rgb[y, x, 0]
            gc[p, 1] = g_rgb[y, x, 1]
            gc[p, 2] = g_rgb[y, x, 2]
            gd[p] = g_depth[y, x]
            gT[p] = g_T[y, x]
    for pos in range(first, tile_start[t + 1]):
        for col in range(out_grad.shape[1]):
            out_grad[pos, col] = 0.0
    tp = _gather_tile(packed, uv64, sorted_row, first, max_last + 1, x0, y0)
    return tw, th, (Tc, Tf, lastp, gc, gd, gT, Rc, Rd, la, lc, ld), max_last, tp


@njit(cache=True, fastmath=False)
def _uncomposite(p, alpha, G, oG, dx, dy, cr, cg, cb, dep, a64, b64, c64, max_alpha, one, state,
                 acc):  # pragma: no cover - compiled
    """Pixel ``p`` gives back one Gaussian (back to front) of ``alpha = min(max_alpha, oG)``, ``oG = opacity G``, at
    ``(dx, dy)`` from its mean: its transmittance is recovered and its gradients added to ``acc`` (float64
    ``[10]``: d/d(u, v, a, b, c, opacity, r, g, b, ray_depth); the clamped alpha has none for the opacity and
    the footprint).

    Not ``inline="always"``: numba's IR inliner compiled this function (its ``state`` tuple unpacked, ``acc``
    updated in place) into wrong gradients, which ``tests/splat/test_grad.py`` caught and the byte comparison with
    the reference, which shares it, could not. Called as a function, LLVM inlines it (the same speed)."""
    Tc, Tf, lastp, gc, gd, gT, Rc, Rd, la, lc, ld = state
    Ti = Tc[p] / (one - alpha)
    w = alpha * Ti
    g0, g1, g2, gdp = gc[p, 0], gc[p, 1], gc[p, 2], gd[p]
    acc[6] += np.float64(w * g0)
    acc[7] += np.float64(w * g1)
    acc[8] += np.float64(w * g2)
    acc[9] += np.float64(w * gdp)
    lap = la[p]
    r0 = lap * lc[p, 0] + (one - lap) * Rc[p, 0]
    r1 = lap * lc[p, 1] + (one - lap) * Rc[p, 1]
    r2 = lap * lc[p, 2] + (one - lap) * Rc[p, 2]
    rd = lap * ld[p] + (one - lap) * Rd[p]
    Rc[p, 0] = r0
    Rc[p, 1] = r1
    Rc[p, 2] = r2
    Rd[p] = rd
    dL_dalpha = Ti * (g0 * (cr - r0) + g1 * (cg - r1) + g2 * (cb - r2) + gdp * (dep - rd))
    dL_dalpha -= gT[p] * Tf[p] / (one - alpha)
    la[p] = alpha
    lc[p, 0] = cr
    lc[p, 1] = cg
    lc[p, 2] = cb
    ld[p] = dep
    Tc[p] = Ti
    if oG <= max_alpha:
        acc[5] += np.float64(G * dL_dalpha)
        dLdp = np.float64(alpha * dL_dalpha)
        dx64 = np.float64(dx)
        dy64 = np.float64(dy)
        acc[2] += -0.5 * dLdp * dx64 * dx64
        acc[3] += -dLdp * dx64 * dy64
        acc[4] += -0.5 * dLdp * dy64 * dy64
        acc[0] += dLdp * (a64 * dx64 + b64 * dy64)
        acc[1] += dLdp * (b64 * dx64 + c64 * dy64)


@njit(cache=True, inline="always")
def _raster_bwd_tile(
    t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst,
    final_T, last_idx, g_rgb, g_depth, g_T, out_grad,
):  # pragma: no cover - compiled
    """Tile ``t`` of :func:`raster_bwd_kernel` (inlined into it): each row a Gaussian covers first gets its 16
    lanes' ``exp`` and alphas at once (:func:`_row_alphas`, vectorised), then the row's span gives them back
    pixel by pixel; the same bits as :func:`_raster_bwd_tile_scalar`."""
    max_alpha, a_thr, one, half, zero = cst[0], cst[1], cst[3], cst[4], cst[5]
    s_begin = tile_start[t]
    if tile_start[t + 1] == s_begin:
        return
    tw, th, state, max_last, tp = _bwd_tile_begin(t, packed, uv64, tile_start, sorted_row, width, height, tiles_x,
                                                  final_T, last_idx, g_rgb, g_depth, g_T, out_grad)
    lastp = state[2]
    lx = _lanes_x(xs, zero)
    G_row = np.empty(_TS, dtype=packed.dtype)
    alpha_row = np.empty(_TS, dtype=packed.dtype)
    acc = np.empty(GRAD_COLS, dtype=np.float64)
    for s in range(max_last, s_begin - 1, -1):
        j = s - s_begin
        if tp[j, 10] < zero:
            continue
        mx, my, a, op, cr, cg, cb, dep, gam, bet, mx64, my64, lim64, gam64, bet64, inva64 = _tile_gaussian(tp, j)
        a64, b64, c64 = np.float64(a), np.float64(tp[j, 3]), np.float64(tp[j, 4])
        ya, yb = _pixel_range(my64, np.float64(tp[j, 11]), 0, th - 1)
        acc[:] = 0.0
        for y in range(ya, yb + 1):
            xa, xb = _row_span(mx64, my64, lim64, gam64, bet64, inva64, np.float64(y), 0, tw - 1)
            if xa > xb:
                continue
            dy = ys[y] - my
            _row_alphas(lx, mx, a, op, bet * dy, gam * dy * dy, max_alpha, half, zero, G_row, alpha_row)
            base = y * _TS
            for x in range(xa, xb + 1):
                p = base + x
                if s > lastp[p]:
                    continue
                alpha = alpha_row[x]
                if not (alpha >= a_thr):
                    continue
                G = G_row[x]
                _uncomposite(p, alpha, G, op * G, xs[x] - mx, dy, cr, cg, cb, dep, a64, b64, c64, max_alpha, one,
                             state, acc)
        for col in range(GRAD_COLS):
            out_grad[s, col] = acc[col]


@njit(cache=True, inline="always")
def _raster_bwd_tile_scalar(
    t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst,
    final_T, last_idx, g_rgb, g_depth, g_T, out_grad,
):  # pragma: no cover - compiled
    """:func:`_raster_bwd_tile` evaluating each (Gaussian, pixel) pair on its own, only inside the row's span (the
    loop before session 38): the reference of ``tests/splat/test_raster_workers.py``."""
    max_alpha, a_thr, one, half, zero = cst[0], cst[1], cst[3], cst[4], cst[5]
    s_begin = tile_start[t]
    if tile_start[t + 1] == s_begin:
        return
    tw, th, state, max_last, tp = _bwd_tile_begin(t, packed, uv64, tile_start, sorted_row, width, height, tiles_x,
                                                  final_T, last_idx, g_rgb, g_depth, g_T, out_grad)
    lastp = state[2]
    acc = np.empty(GRAD_COLS, dtype=np.float64)
    for s in range(max_last, s_begin - 1, -1):
        j = s - s_begin
        if tp[j, 10] < zero:
            continue
        mx, my, a, op, cr, cg, cb, dep, gam, bet, mx64, my64, lim64, gam64, bet64, inva64 = _tile_gaussian(tp, j)
        a64, b64, c64 = np.float64(a), np.float64(tp[j, 3]), np.float64(tp[j, 4])
        ya, yb = _pixel_range(my64, np.float64(tp[j, 11]), 0, th - 1)
        acc[:] = 0.0
        for y in range(ya, yb + 1):
            xa, xb = _row_span(mx64, my64, lim64, gam64, bet64, inva64, np.float64(y), 0, tw - 1)
            if xa > xb:
                continue
            dy = ys[y] - my
            gdy = gam * dy * dy
            bdy = bet * dy
            base = y * _TS
            for x in range(xa, xb + 1):
                p = base + x
                if s > lastp[p]:
                    continue
                dx = xs[x] - mx
                e = dx + bdy
                power = -half * (a * e * e + gdy)
                G = fexp(power)
                oG = op * G
                alpha = min(max_alpha, oG)
                if not ((alpha >= a_thr) and (power <= zero)):
                    continue
                _uncomposite(p, alpha, G, oG, dx, dy, cr, cg, cb, dep, a64, b64, c64, max_alpha, one, state, acc)
        for col in range(GRAD_COLS):
            out_grad[s, col] = acc[col]


@njit(parallel=True, cache=True, fastmath=False)
def raster_bwd_kernel(
    packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst,
    final_T, last_idx, g_rgb, g_depth, g_T, out_grad, n_workers,
):  # pragma: no cover - compiled
    """Backward of :func:`raster_fwd_kernel` (INRIA style: back to front from each pixel's last contributor,
    transmittance recovered from the stored final T; the same instructions decide which pairs count), its tiles
    shared among the workers as in the forward.

    ``g_rgb [H, W, 3]``, ``g_depth [H, W]``, ``g_T [H, W]``: gradients of the loss w.r.t. the three forward
    outputs. Writes ``out_grad [M, 10]`` per intersection position ``s`` (race-free: each position belongs to
    one tile): d/d(u, v, conic a, b, c, opacity, r, g, b, ray_depth).
    """
    n_tiles = tile_start.shape[0] - 1
    for k in prange(n_workers):
        for t in range(k, n_tiles, n_workers):
            _raster_bwd_tile(t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst,
                             final_T, last_idx, g_rgb, g_depth, g_T, out_grad)


@njit(parallel=True, cache=True, fastmath=False)
def _raster_bwd_kernel_per_tile(
    packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst,
    final_T, last_idx, g_rgb, g_depth, g_T, out_grad,
):  # pragma: no cover - compiled
    """:func:`raster_bwd_kernel` as it was before session 37: one tile per ``prange`` iteration, each pair on its own
    (:func:`_raster_bwd_tile_scalar`). The same outputs; the reference of the tests and
    ``benchmarks/raster_workers.py``."""
    for t in prange(tile_start.shape[0] - 1):
        _raster_bwd_tile_scalar(t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst,
                                final_T, last_idx, g_rgb, g_depth, g_T, out_grad)


@njit(parallel=True, cache=True, fastmath=False)
def _raster_bwd_kernel_scalar(
    packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst,
    final_T, last_idx, g_rgb, g_depth, g_T, out_grad, n_workers,
):  # pragma: no cover - compiled
    """:func:`raster_bwd_kernel` with the scalar pair loop (:func:`_raster_bwd_tile_scalar`; session 37's kernel):
    ``benchmarks/raster_workers.py`` times the lanes against it. The same outputs."""
    n_tiles = tile_start.shape[0] - 1
    for k in prange(n_workers):
        for t in range(k, n_tiles, n_workers):
            _raster_bwd_tile_scalar(t, packed, uv64, tile_start, sorted_row, width, height, tiles_x, xs, ys, cst,
                                    final_T, last_idx, g_rgb, g_depth, g_T, out_grad)


@njit(parallel=True, cache=True, fastmath=False)
def reduce_grads_kernel(isect_grad, pos_of_isect, offsets, rows, out):  # pragma: no cover - compiled
    """``out[rows[i]] = sum of isect_grad[pos_of_isect[e]]`` over the intersections ``e`` of Gaussian ``i``."""
    ncol = isect_grad.shape[1]
    for i in prange(rows.shape[0]):
        g = rows[i]
        for col in range(ncol):
            acc = 0.0
            for e in range(offsets[i], offsets[i + 1]):
                acc += np.float64(isect_grad[pos_of_isect[e], col])
            out[g, col] = acc
