"""numba kernels of the 3DGS trainer's per-step parameter update: Adam (:meth:`umi_aug.splat.optim.GaussianAdam.step`)
and the MCMC position noise (:func:`umi_aug.splat.densify.inject_noise`), one pass over the Gaussians each.

The torch versions they replace (``GaussianAdam._step_torch``, ``densify._inject_noise_torch``, the references of
``tests/splat/test_optim_kernels.py``) run a dozen element-wise torch operations per parameter, each waking torch's
thread pool for a few microseconds of work; on the real episode's 29k Gaussians they took ~11 ms per training step
on 2 cores, as much as the rasteriser's forward (``benchmarks/splat_optimiser.py``).

Arithmetic: every element is computed in float64 from the stored values and rounded once to the parameter's dtype
when stored; the moments are read back as stored before the parameter update uses them (as torch does, which
computes in float32 throughout). No fastmath.
"""

from __future__ import annotations

import math

from numba import njit, prange

from umi_aug.runtime import quiet_numba_threading_warning
from umi_aug.splat._numba_cache import install as install_kernel_cache

quiet_numba_threading_warning()
install_kernel_cache()  # before the first @njit(cache=True): stamped with every kernel source


@njit(parallel=True, cache=True, fastmath=False)
def adam_rows_kernel(p, g, m, v, n_cols, step_size, b1, b2, bias_correction2, eps):  # pragma: no cover - compiled
    """Adam on the first ``n_cols`` columns of ``[N, C]`` arrays ``p`` (parameters), ``g`` (gradient), ``m``, ``v``
    (first and second moments), in place: ``m = b1 m + (1 - b1) g``, ``v = b2 v + (1 - b2) g^2``,
    ``p -= step_size m / (sqrt(v / bias_correction2) + eps)`` with ``step_size = lr / bias_correction1``."""
    for i in prange(p.shape[0]):
        for j in range(n_cols):
            gij = float(g[i, j])
            m[i, j] = b1 * float(m[i, j]) + (1.0 - b1) * gij
            v[i, j] = b2 * float(v[i, j]) + (1.0 - b2) * (gij * gij)
            denom = math.sqrt(float(v[i, j]) / bias_correction2) + eps
            p[i, j] = float(p[i, j]) - step_size * (float(m[i, j]) / denom)


@njit(cache=True, fastmath=False)
def _sigmoid(x):  # pragma: no cover - compiled
    return 1.0 / (1.0 + math.exp(-x)) if x >= 0.0 else math.exp(x) / (1.0 + math.exp(x))


@njit(parallel=True, cache=True, fastmath=False)
def position_noise_kernel(means, logit_opacities, quats_wxyz, log_scales, eps, scale, gate_k,
                          gate_x0):  # pragma: no cover - compiled
    """``means[i] += R_i diag(s_i^2) R_i^T eps[i] * scale * gate(o_i)`` in place, ``R_i`` the rotation of the
    normalised quaternion ``[w, x, y, z]`` (a norm <= 1e-30 is used as it is, as
    :func:`umi_aug.geometry.se3_torch.quat_wxyz_to_matrix` does), ``s_i = exp(log_scales[i])``,
    ``o_i = sigmoid(logit_opacities[i])``, ``gate(o) = sigmoid(gate_k ((1 - o) - gate_x0))``."""
    for i in prange(means.shape[0]):
        op = _sigmoid(float(logit_opacities[i]))
        gate = _sigmoid(gate_k * ((1.0 - op) - gate_x0))
        w, x, y, z = float(quats_wxyz[i, 0]), float(quats_wxyz[i, 1]), float(quats_wxyz[i, 2]), float(quats_wxyz[i, 3])
        n = math.sqrt(w * w + x * x + y * y + z * z)
        if n > 1e-30:
            w, x, y, z = w / n, x / n, y / n, z / n
        r00, r01, r02 = 1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)
        r10, r11, r12 = 2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)
        r20, r21, r22 = 2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)
        e0, e1, e2 = float(eps[i, 0]), float(eps[i, 1]), float(eps[i, 2])
        # R^T eps, scaled by s^2 per axis
        l0 = (r00 * e0 + r10 * e1 + r20 * e2) * math.exp(2.0 * float(log_scales[i, 0]))
        l1 = (r01 * e0 + r11 * e1 + r21 * e2) * math.exp(2.0 * float(log_scales[i, 1]))
        l2 = (r02 * e0 + r12 * e1 + r22 * e2) * math.exp(2.0 * float(log_scales[i, 2]))
        k = gate * scale
        means[i, 0] = float(means[i, 0]) + (r00 * l0 + r01 * l1 + r02 * l2) * k
        means[i, 1] = float(means[i, 1]) + (r10 * l0 + r11 * l1 + r12 * l2) * k
        means[i, 2] = float(means[i, 2]) + (r20 * l0 + r21 * l1 + r22 * l2) * k
