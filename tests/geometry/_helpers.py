"""Shared generators for the geometry tests (inputs are drawn from the per-test ``rng`` fixture)."""

from __future__ import annotations

import math

import numpy as np

EXTREME_ANGLES = [
    0.0, 1e-12, 1e-8, 1e-6, 1e-3, 1.0, math.pi / 2, math.pi - 1e-3, math.pi - 1e-6, math.pi - 1e-9, math.pi,
]


def random_axes(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.standard_normal((n, 3))
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def rotvecs_with_angle(rng: np.random.Generator, n: int, angle: float) -> np.ndarray:
    return random_axes(rng, n) * angle


def random_rotvecs(rng: np.random.Generator, n: int, max_angle: float = math.pi) -> np.ndarray:
    return random_axes(rng, n) * rng.uniform(0.0, max_angle, (n, 1))


def random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.random(n, random_state=rng).as_matrix()


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = random_rotations(rng, n)
    T[:, :3, 3] = rng.normal(0.0, 0.5, (n, 3))
    T[:, 3, 3] = 1.0
    return T


def rotvec_close_mod_pi(a: np.ndarray, b: np.ndarray, angle: float, atol: float) -> bool:
    """Equality of rotation vectors, allowing ±axis when the angle is within ``atol`` of π (θn and −θn are then
    the same rotation up to 2·(π − θ) ≤ 2·atol; exactly at π they are identical)."""
    err = np.abs(a - b).max(-1)
    if angle >= math.pi - atol:
        err = np.minimum(err, np.abs(a + b).max(-1))
    return bool((err <= atol).all())
