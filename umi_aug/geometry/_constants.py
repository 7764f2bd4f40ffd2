"""Numerical thresholds of the geometry stage, all in one place (radians unless stated).

Why each value (float64 unless stated; eps = 2.2e-16):

* ``EXP_TAYLOR_ANGLE``: ``sin θ/θ`` and ``(1−cos θ)/θ² = ½·sinc²(θ/2)`` are evaluated without cancellation for any
  θ > 0, so the Taylor branch only exists to avoid 0/0 (and to keep autograd finite at θ = 0). Below 1e-4 the
  truncated series (error ≈ θ⁶/5040 < 1e-27) is exact to machine precision.
* ``LOG_TAYLOR_SIN``: same role for ``θ/sin θ`` in the logarithm (series in s = sin θ, error ≈ 5s⁶/112).
* ``LOG_PI_BRANCH_COS``: the generic log ``θ·w/sin θ`` (w = vee(R−Rᵀ)/2) has axis error ≈ eps/sin θ; the
  symmetric-part log (axis from ``(R+Rᵀ)/2 − cos θ·I``) has error ≈ eps/(1−cos θ). They cross at θ = π/2, so
  the symmetric branch is used when cos θ < 0. It never divides by sin θ.
* ``JAC_SERIES_ANGLE``: ``(θ−sin θ)/θ³`` and ``1/θ² − cot(θ/2)/(2θ)`` (left Jacobian and its inverse) lose
  ≈ eps/θ² absolutely; their 5-term series lose ≈ θ¹⁰/6e9. The two errors meet near θ ≈ 0.3 (float64) and
  θ ≈ 1.0 (float32, eps = 1.2e-7), where both are ≈ 2e-15 resp. 1e-7.
* ``NORM_EPS``: a vector shorter than this is treated as zero (degenerate direction/axis fallbacks).
* ``PARALLEL_EPS``: |a×b| below this (unit vectors) is treated as parallel/antiparallel; the result is then
  within ≈ 2·PARALLEL_EPS of exact, whichever perpendicular axis is picked.
"""

from __future__ import annotations

import math

EXP_TAYLOR_ANGLE: float = 1e-4
LOG_TAYLOR_SIN: float = 1e-4
LOG_PI_BRANCH_COS: float = 0.0
JAC_SERIES_ANGLE: float = 0.3
JAC_SERIES_ANGLE_F32: float = 1.0
NORM_EPS: float = 1e-12
PARALLEL_EPS: float = 1e-15
TWO_PI: float = 2.0 * math.pi
LOOK_AT_PARALLEL_EPS: float = 1e-6  # |forward × up| (unit vectors) below this → use a fallback up hint
BALL_BISECTION_ITERS: int = 64  # inverse-CDF bisection steps for the SO(3) ball angle (interval / 2**64)
