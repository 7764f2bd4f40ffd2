"""The Kannala–Brandt radial polynomial and the camera stage's named constants (numpy float64, no torch).

``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``, its derivative and its fold-over
angle. Split from :mod:`umi_aug.camera.kb` so that :mod:`umi_aug.camera.intrinsics` (which needs the fold-over)
and :mod:`umi_aug.camera.kb` (which needs :class:`~umi_aug.camera.intrinsics.FisheyeIntrinsics`) do not import
each other; :mod:`umi_aug.camera.kb` re-exports every name here.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np


__all__ = [
    "NEWTON_TOL",
    "NEWTON_MAX_ITER",
    "NEWTON_MIN_DERIVATIVE",
    "NEWTON_RESIDUAL_ULPS",
    "SMALL_T",
    "SMALL_THETA",
    "MIN_POINT_NORM",
    "THETA_PI_MARGIN",
    "THETA_MAX_SLACK",
    "THETA_D_MAX_REL_SLACK",
    "FOLD_GRID_SIZE",
    "kb_theta_d",
    "kb_dtheta_d",
    "theta_fold",
]

# --------------------------------------------------------------------------------------------------------------
# Named constants of the camera stage (used by kb.py, kb_torch.py and intrinsics.py).
# --------------------------------------------------------------------------------------------------------------
#: Newton convergence tolerance on the update of theta (radians) in float64.
NEWTON_TOL: float = 1e-15
#: Iteration cap of the guarded Newton inverse (quadratic convergence needs ~3-5; the flat region next to the
#: fold-over converges linearly, <= ~55 halvings).
NEWTON_MAX_ITER: int = 100
#: Below this |d theta_d / d theta| a Newton step is not attempted; the guarded solver bisects instead.
NEWTON_MIN_DERIVATIVE: float = 1e-14
#: Newton also stops once |theta_d(theta) - theta_d| <= NEWTON_RESIDUAL_ULPS * eps * theta_d (rounding level).
NEWTON_RESIDUAL_ULPS: float = 4.0
#: Series branch for t = r / z <= SMALL_T (z > 0): atan(t)/t is evaluated by its Taylor series (error ~ t^10/11),
#: which gives the exact r -> 0 limit and smooth derivatives on the optical axis.
SMALL_T: float = 1e-2
#: Series branch for sin(theta)/theta when theta <= SMALL_THETA (error ~ theta^8 / 9!).
SMALL_THETA: float = 1e-2
#: A 3-D point whose largest |coordinate| is <= this is "at the camera centre" and has no direction.
MIN_POINT_NORM: float = 1e-150
#: Without fold-over or lens limit, theta_max = pi * (1 - THETA_PI_MARGIN) (theta = pi has no azimuth).
THETA_PI_MARGIN: float = 1e-9
#: Rounding slack of the ray-angle validity test: a direction is valid iff theta <= theta_max + THETA_MAX_SLACK,
#: so that rays returned by ``unproject`` for pixels on the image circle always project back as valid.
THETA_MAX_SLACK: float = 1e-13
#: Same for pixels: ``unproject`` accepts theta_d <= theta_d_max * (1 + THETA_D_MAX_REL_SLACK) (clamped to the
#: circle), so that ``project`` of a ray at exactly theta_max unprojects as valid despite rounding.
THETA_D_MAX_REL_SLACK: float = 1e-12
#: Grid size of the sign-change scan that backs up the polynomial root solve for the fold-over angle.
FOLD_GRID_SIZE: int = 4097

_EPS = float(np.finfo(np.float64).eps)


# --------------------------------------------------------------------------------------------------------------
# Radial polynomial
# --------------------------------------------------------------------------------------------------------------
def _k4(k: Sequence[float] | np.ndarray) -> tuple[float, float, float, float]:
    k1, k2, k3, k4 = (float(c) for c in k)
    return k1, k2, k3, k4


def kb_theta_d(theta: np.ndarray | float, k: Sequence[float]) -> np.ndarray:
    """Distorted angle ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``.

    Args:
        theta: angle from the optical axis, radians, any shape ``[...]``.
        k: the four KB coefficients ``(k1, k2, k3, k4)``.

    Returns:
        ``theta_d``, float64 ``[...]`` (dimensionless; pixels are ``f * theta_d`` from the principal point).
    """
    k1, k2, k3, k4 = _k4(k)
    t = np.asarray(theta, dtype=np.float64)
    t2 = t * t
    return t * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))


def kb_dtheta_d(theta: np.ndarray | float, k: Sequence[float]) -> np.ndarray:
    """Derivative ``d theta_d / d theta = 1 + 3 k1 theta^2 + 5 k2 theta^4 + 7 k3 theta^6 + 9 k4 theta^8``.

    Args:
        theta: radians ``[...]``.
        k: ``(k1, k2, k3, k4)``.

    Returns:
        float64 ``[...]``.
    """
    k1, k2, k3, k4 = _k4(k)
    t = np.asarray(theta, dtype=np.float64)
    t2 = t * t
    return 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))


def _poly(t2: np.ndarray, k: tuple[float, float, float, float]) -> np.ndarray:
    """``P(t2) = 1 + k1 t2 + k2 t2^2 + k3 t2^3 + k4 t2^4`` so that ``theta_d = theta * P(theta^2)``."""
    k1, k2, k3, k4 = k
    return 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))


def _dpoly(t2: np.ndarray, k: tuple[float, float, float, float]) -> np.ndarray:
    """``P'(t2) = k1 + 2 k2 t2 + 3 k3 t2^2 + 4 k4 t2^3``."""
    k1, k2, k3, k4 = k
    return k1 + t2 * (2.0 * k2 + t2 * (3.0 * k3 + t2 * 4.0 * k4))


def theta_fold(k: Sequence[float]) -> float:
    """Smallest ``theta`` in ``(0, pi]`` where ``d theta_d / d theta = 0`` (the fold-over), or ``inf``.

    The derivative is a quartic in ``s = theta^2``; its real roots in ``(0, pi^2]`` come from ``np.roots`` and are
    polished by Newton, and a sign-change scan on a dense grid (refined by bisection) backs them up. Tangential
    roots (no sign change) count as fold-over too.

    Args:
        k: ``(k1, k2, k3, k4)``.

    Returns:
        the fold-over angle in radians, or ``math.inf`` if ``theta_d`` is strictly increasing on ``(0, pi]``.
    """
    kk = _k4(k)
    k1, k2, k3, k4 = kk
    # d theta_d / d theta as a polynomial in s = theta^2 (highest power first for np.roots)
    coeffs = np.array([9.0 * k4, 7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0])
    s_max = math.pi**2
    candidates: list[float] = []

    def dfun(s: float) -> float:
        return float(np.polyval(coeffs, s))

    def ddfun(s: float) -> float:
        return float(np.polyval(np.polyder(coeffs), s))

    nz = np.flatnonzero(coeffs != 0.0)
    trimmed = coeffs[nz[0]:]
    if trimmed.size > 1:
        for root in np.roots(trimmed):
            if abs(root.imag) > 1e-7 * max(1.0, abs(root.real)):
                continue
            s = float(root.real)
            for _ in range(8):  # Newton polish in s
                d2 = ddfun(s)
                if d2 == 0.0:
                    break
                s_new = s - dfun(s) / d2
                if not math.isfinite(s_new):
                    break
                s = s_new
            if 0.0 < s <= s_max and abs(dfun(s)) <= 1e-9:
                candidates.append(math.sqrt(s))
    # sign-change scan (robust against a root-finder miss)
    grid = np.linspace(0.0, math.pi, FOLD_GRID_SIZE)
    dv = kb_dtheta_d(grid, kk)
    bad = np.flatnonzero(dv <= 0.0)
    if bad.size:
        i = int(bad[0])
        lo, hi = float(grid[i - 1]), float(grid[i])  # dv[i-1] > 0 >= dv[i]
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            if mid <= lo or mid >= hi:
                break
            if float(kb_dtheta_d(mid, kk)) > 0.0:
                lo = mid
            else:
                hi = mid
        candidates.append(lo if float(kb_dtheta_d(hi, kk)) < 0.0 and lo > 0 else hi)
    if not candidates:
        return math.inf
    return float(min(candidates))
