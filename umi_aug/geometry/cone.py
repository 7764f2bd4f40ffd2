"""Start-pose sampling in the paper's "quaternion cone" (§3.2) and look-at helpers (numpy float64).

Positions: uniform by AREA on a spherical cap of half-angle θ around the reference viewpoint direction
(``cos α ~ U[cos θ, 1]``, ``φ ~ U[0, 2π)``; sampling ``α ~ U[0, θ]`` would pile samples up at the pole), at a
fixed radius or uniform in a shell volume. Orientations: the reference camera re-aimed at the pivot, carried
along the cap by the minimal rotation, then optionally perturbed by a Haar-uniform rotation inside a geodesic
ball (angle density ∝ sin²(α/2)). Cameras are OpenCV (x right, y down, z forward); poses are ``T_world_cam``;
metres and radians. Randomness comes only from the ``rng`` argument (Generator or int seed).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from umi_aug.errors import GeometryError
from umi_aug.geometry._checks import as_float, as_generator
from umi_aug.geometry._constants import BALL_BISECTION_ITERS, LOOK_AT_PARALLEL_EPS, PARALLEL_EPS
from umi_aug.geometry.se3 import _make_pose
from umi_aug.geometry.so3 import _jac_series_c, _so3_exp

__all__ = [
    "rotation_between_vectors",
    "look_at_rotation",
    "sample_directions_in_cap",
    "sample_rotations_in_ball",
    "sample_cone_start_poses",
]


def _unit(v: np.ndarray, name: str, func: str) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    if np.any(n <= 1e-300):
        raise GeometryError(f"{func}: `{name}` (shape {v.shape}) contains a zero-length vector")
    return v / n


def _least_aligned_axis(v: np.ndarray) -> np.ndarray:
    return np.eye(3)[np.argmin(np.abs(v), axis=-1)]


def _rotation_between_units(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cr = np.cross(a, b)
    s = np.linalg.norm(cr, axis=-1, keepdims=True)
    c = np.sum(a * b, axis=-1, keepdims=True)
    par = s <= PARALLEL_EPS
    fallback = np.cross(a, _least_aligned_axis(a))  # any axis ⊥ a (b ≈ ±a)
    n = np.where(par, fallback, cr)
    n = n - np.sum(n * a, axis=-1, keepdims=True) * a
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return _so3_exp(n * np.arctan2(s, c))


def rotation_between_vectors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimal rotation ``R`` with ``R @ unit(a) == unit(b)`` (about ``a × b``); for ``b ≈ −a`` a rotation by π
    about a fixed perpendicular axis (the one from the basis axis least aligned with ``a``).

    Args:
        a: np.ndarray,  # [..., 3] non-zero
        b: np.ndarray,  # [..., 3] non-zero, batch broadcasts with a
    Returns:
        R: np.ndarray,  # [..., 3, 3]
    """
    a = _unit(as_float(a, "a", "rotation_between_vectors", (3,)), "a", "rotation_between_vectors")
    b = _unit(as_float(b, "b", "rotation_between_vectors", (3,)), "b", "rotation_between_vectors")
    try:
        a, b = np.broadcast_arrays(a, b)
    except ValueError as exc:
        raise GeometryError(
            f"rotation_between_vectors: shapes of `a` {a.shape} and `b` {b.shape} do not broadcast"
        ) from exc
    return _rotation_between_units(a, b)


def look_at_rotation(cam_pos: np.ndarray, target: np.ndarray, up_hint: np.ndarray) -> np.ndarray:
    """OpenCV camera orientation ``R_world_cam`` looking from ``cam_pos`` at ``target``.

    Columns: z = unit(target − cam_pos) (forward), x = unit(z × up_hint) (right), y = z × x (down), so
    ``up_hint`` appears along −y. When forward ∥ up_hint (|z × û| < LOOK_AT_PARALLEL_EPS) the world basis axis
    least aligned with z is used as the hint instead.

    Args:
        cam_pos: np.ndarray,  # [..., 3] world, metres
        target: np.ndarray,  # [..., 3] world, metres (≠ cam_pos)
        up_hint: np.ndarray,  # [..., 3] world direction (non-zero)
    Returns:
        R_world_cam: np.ndarray,  # [..., 3, 3]
    """
    f = "look_at_rotation"
    cam_pos = as_float(cam_pos, "cam_pos", f, (3,))
    target = as_float(target, "target", f, (3,))
    up = _unit(as_float(up_hint, "up_hint", f, (3,)), "up_hint", f)
    try:
        cam_pos, target, up = np.broadcast_arrays(cam_pos, target, up)
    except ValueError as exc:
        raise GeometryError(f"{f}: shapes of `cam_pos`, `target`, `up_hint` do not broadcast") from exc
    d = target - cam_pos
    if np.any(np.linalg.norm(d, axis=-1) <= 1e-12):
        raise GeometryError(f"{f}: `target` coincides with `cam_pos` (distance <= 1e-12 m); no view direction")
    z = d / np.linalg.norm(d, axis=-1, keepdims=True)
    x = np.cross(z, up)
    nx = np.linalg.norm(x, axis=-1, keepdims=True)
    par = nx < LOOK_AT_PARALLEL_EPS
    if np.any(par):
        x = np.where(par, np.cross(z, _least_aligned_axis(z)), x)
        nx = np.linalg.norm(x, axis=-1, keepdims=True)
    x = x / nx
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def _check_angle(value, name: str, func: str, hi: float = math.pi) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{func}: `{name}` must be a float in radians, got {value!r}") from exc
    if not (0.0 <= v <= hi):
        raise GeometryError(f"{func}: `{name}` is {value!r}; expected radians in [0, {hi:.6g}]")
    return v


def _check_n(n, func: str) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or int(n) < 1:
        raise GeometryError(f"{func}: `n` must be an int >= 1, got {n!r}")
    return int(n)


def sample_directions_in_cap(
    axis: np.ndarray, half_angle: float, n: int, rng: np.random.Generator | int
) -> np.ndarray:
    """Unit directions uniform by area on the cap {d : angle(d, axis) ≤ half_angle}.

    ``1 − cos α = u · (1 − cos θ)`` with u ~ U[0, 1), ``φ ~ U[0, 2π)`` (pbrt UniformSampleCone); draws
    ``u`` (n values) then ``φ`` (n values) from ``rng``.

    Args:
        axis: np.ndarray,  # [3] cap centre direction (non-zero, normalised here)
        half_angle: float,  # radians in [0, π]
        n: int,  # number of samples >= 1
        rng: np.random.Generator | int,
    Returns:
        d: np.ndarray,  # [n, 3] unit vectors
    """
    f = "sample_directions_in_cap"
    axis = _unit(as_float(axis, "axis", f, (3,)), "axis", f)
    if axis.shape != (3,):
        raise GeometryError(f"{f}: `axis` has shape {axis.shape}; expected [3]")
    theta = _check_angle(half_angle, "half_angle", f)
    n = _check_n(n, f)
    gen = as_generator(rng, f)
    w = gen.random(n) * (2.0 * math.sin(0.5 * theta) ** 2)  # 1 − cos α, cancellation-free
    phi = gen.random(n) * (2.0 * math.pi)
    sin_a = np.sqrt(np.clip(w * (2.0 - w), 0.0, None))
    local = np.stack([sin_a * np.cos(phi), sin_a * np.sin(phi), 1.0 - w], axis=-1)
    R = _rotation_between_units(np.array([0.0, 0.0, 1.0]), axis)
    return local @ R.T


def _ball_cdf_num(alpha: np.ndarray) -> np.ndarray:
    """α − sin α (∝ CDF of the Haar angle), computed as α³·(α − sin α)/α³ without cancellation."""
    return alpha**3 * _jac_series_c(alpha)


def sample_rotations_in_ball(max_angle: float, n: int, rng: np.random.Generator | int) -> np.ndarray:
    """Rotations uniform (Haar) inside the geodesic ball of radius ``max_angle`` around the identity.

    Axis uniform on S² (normalised Gaussian, drawn first: n×3 normals), angle by inverse CDF
    ``F(α) = (α − sin α)/(β − sin β)`` (density ∝ sin²(α/2)) of n uniforms, solved by bisection.

    Args:
        max_angle: float,  # β, radians in [0, π]
        n: int,  # >= 1
        rng: np.random.Generator | int,
    Returns:
        R: np.ndarray,  # [n, 3, 3]
    """
    f = "sample_rotations_in_ball"
    beta = _check_angle(max_angle, "max_angle", f)
    n = _check_n(n, f)
    gen = as_generator(rng, f)
    axis = gen.standard_normal((n, 3))
    nrm = np.linalg.norm(axis, axis=-1, keepdims=True)
    axis = np.where(nrm > 1e-12, axis / np.where(nrm > 1e-12, nrm, 1.0), np.array([0.0, 0.0, 1.0]))
    u = gen.random(n)
    if beta == 0.0:
        return np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    goal = u * _ball_cdf_num(np.array(beta))
    lo, hi = np.zeros(n), np.full(n, beta)
    for _ in range(BALL_BISECTION_ITERS):
        mid = 0.5 * (lo + hi)
        below = _ball_cdf_num(mid) < goal
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return _so3_exp(axis * (0.5 * (lo + hi))[:, None])


def _check_radius(radius, default: float, func: str) -> tuple[float, float]:
    if radius is None:
        return default, default
    if isinstance(radius, (tuple, list, np.ndarray)) and np.ndim(radius) == 1:
        if len(radius) != 2:
            raise GeometryError(f"{func}: `radius` tuple must be (r_min, r_max), got {radius!r}")
        r_min, r_max = (float(r) for r in radius)
        if not (np.isfinite(r_min) and np.isfinite(r_max) and 0.0 < r_min <= r_max):
            raise GeometryError(f"{func}: `radius` is {radius!r}; expected 0 < r_min <= r_max (metres)")
        return r_min, r_max
    try:
        r = float(radius)
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{func}: `radius` must be a float or (r_min, r_max), got {radius!r}") from exc
    if not (np.isfinite(r) and r > 0.0):
        raise GeometryError(f"{func}: `radius` is {radius!r}; expected a finite value > 0 (metres)")
    return r, r


def sample_cone_start_poses(
    T_world_cam_ref: np.ndarray,
    pivot_world: np.ndarray,
    half_angle: float,
    n: int,
    rng: np.random.Generator | int,
    radius: float | Sequence[float] | None = None,
    max_extra_rotation: float = 0.0,
) -> np.ndarray:
    """Camera start poses in a cone of half-angle θ around the reference viewpoint, looking at a pivot.

    Cap axis ``a = unit(p_ref − pivot)``; positions ``pivot + r·d`` with d uniform by area on the cap (θ) and
    r = ``|p_ref − pivot|`` (default), a fixed radius, or uniform in the shell volume for ``(r_min, r_max)``
    (``r = (U (r_max³ − r_min³) + r_min³)^{1/3}``). Orientation: ``Q_d @ A @ R_ref @ E`` where ``A`` is the minimal
    rotation of the reference optical axis onto ``−a`` (re-aim at the pivot), ``Q_d`` the minimal rotation
    taking ``a`` to ``d`` (roll about the view direction inherited continuously) and ``E`` (camera frame) a
    Haar-uniform rotation of angle ≤ ``max_extra_rotation``. Draw order from ``rng``: directions, radii (only
    for a shell), extra rotations (only when max_extra_rotation > 0).

    Args:
        T_world_cam_ref: np.ndarray,  # [4, 4] reference camera pose (OpenCV camera)
        pivot_world: np.ndarray,  # [3] point looked at, world, metres (≠ reference position)
        half_angle: float,  # θ, radians in [0, π]
        n: int,  # >= 1
        rng: np.random.Generator | int,
        radius: float | tuple[float, float] | None,  # metres
        max_extra_rotation: float,  # radians in [0, π]
    Returns:
        T_world_cam: np.ndarray,  # [n, 4, 4]
    """
    f = "sample_cone_start_poses"
    T_ref = as_float(T_world_cam_ref, "T_world_cam_ref", f, (4, 4))
    if T_ref.shape != (4, 4):
        raise GeometryError(f"{f}: `T_world_cam_ref` has shape {T_ref.shape}; expected [4, 4]")
    pivot = as_float(pivot_world, "pivot_world", f, (3,))
    if pivot.shape != (3,):
        raise GeometryError(f"{f}: `pivot_world` has shape {pivot.shape}; expected [3]")
    theta = _check_angle(half_angle, "half_angle", f)
    n = _check_n(n, f)
    extra = _check_angle(max_extra_rotation, "max_extra_rotation", f)
    gen = as_generator(rng, f)
    p_ref, R_ref = T_ref[:3, 3], T_ref[:3, :3]
    v = p_ref - pivot
    dist = float(np.linalg.norm(v))
    if dist <= 1e-9:
        raise GeometryError(f"{f}: `pivot_world` {pivot.tolist()} coincides with the reference camera position")
    r_min, r_max = _check_radius(radius, dist, f)
    axis = v / dist
    R_aim = _rotation_between_units(R_ref[:, 2], -axis) @ R_ref
    d = sample_directions_in_cap(axis, theta, n, gen)
    if r_min == r_max:
        r = np.full(n, r_min)
    else:
        lo3, hi3 = r_min**3, r_max**3
        r = np.cbrt(gen.random(n) * (hi3 - lo3) + lo3)
    Q = _rotation_between_units(np.broadcast_to(axis, d.shape), d)
    R = Q @ R_aim
    if extra > 0.0:
        R = R @ sample_rotations_in_ball(extra, n, gen)
    return _make_pose(R, pivot + r[:, None] * d)
