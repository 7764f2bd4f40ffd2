"""Analytic SDFs: distance vs brute force (dense surface samples), sign vs an inside test, gradient vs finite
differences, and the Protocol."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from umi_aug.errors import GeometryError
from umi_aug.geometry.sdf import (
    CapsuleSDF,
    BoxSDF,
    ConvexPolytopeSDF,
    CylinderSDF,
    HalfSpaceSDF,
    InflatedSDF,
    SignedDistanceField,
    SphereSDF,
    UnionSDF,
)
from tests.geometry._helpers import random_rotations

SPACING = 2e-3  # surface sample spacing, m (brute-force distance error <= SPACING)


def _grid(n_u: int, n_v: int) -> tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.linspace(-1, 1, n_u), np.linspace(-1, 1, n_v), indexing="ij")
    return u.ravel(), v.ravel()


def _box_surface(h: np.ndarray) -> np.ndarray:
    pts = []
    for ax in range(3):
        o = [a for a in range(3) if a != ax]
        u, v = _grid(int(2 * h[o[0]] / SPACING) + 2, int(2 * h[o[1]] / SPACING) + 2)
        for sgn in (-1.0, 1.0):
            p = np.zeros((u.size, 3))
            p[:, ax] = sgn * h[ax]
            p[:, o[0]] = u * h[o[0]]
            p[:, o[1]] = v * h[o[1]]
            pts.append(p)
    return np.concatenate(pts)


def _cylinder_surface(r: float, hh: float) -> np.ndarray:
    n_phi = int(2 * np.pi * r / SPACING) + 2
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    z = np.linspace(-hh, hh, int(2 * hh / SPACING) + 2)
    P, Z = np.meshgrid(phi, z, indexing="ij")
    side = np.stack([r * np.cos(P).ravel(), r * np.sin(P).ravel(), Z.ravel()], -1)
    rho = np.linspace(0, r, int(r / SPACING) + 2)
    Rr, Pp = np.meshgrid(rho, phi, indexing="ij")
    disk = np.stack([(Rr * np.cos(Pp)).ravel(), (Rr * np.sin(Pp)).ravel()], -1)
    caps = [np.concatenate([disk, np.full((len(disk), 1), s * hh)], -1) for s in (-1, 1)]
    return np.concatenate([side] + caps)


def _check_brute(sdf: SignedDistanceField, surface_world: np.ndarray, inside, q: np.ndarray) -> None:
    d, _ = sdf.distance_and_gradient(q)
    brute, _ = cKDTree(surface_world).query(q)
    sign = np.where(inside(q), -1.0, 1.0)
    np.testing.assert_array_less(np.abs(d - sign * brute), SPACING)
    assert np.all(np.sign(d[np.abs(d) > SPACING]) == sign[np.abs(d) > SPACING])


def _check_fd(sdf: SignedDistanceField, q: np.ndarray, h: float = 1e-6, tol: float = 1e-5) -> None:
    d, g = sdf.distance_and_gradient(q)
    fd = np.empty_like(q)
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        fd[:, i] = (sdf.distance_and_gradient(q + e)[0] - sdf.distance_and_gradient(q - e)[0]) / (2 * h)
    np.testing.assert_allclose(g, fd, atol=tol)
    np.testing.assert_allclose(np.linalg.norm(g, axis=-1), 1.0, atol=1e-12)


def _away_from_kinks(q: np.ndarray, kink_dist, min_dist: float = 1e-3) -> np.ndarray:
    return q[kink_dist(q) > min_dist]


def test_sphere_brute_force_and_gradient(rng):
    c, r = rng.normal(0, 0.3, 3), rng.uniform(0.05, 0.2)
    s = SphereSDF(c, r)
    n = int(4 * np.pi * r * r / SPACING**2 * 2)
    dirs = rng.standard_normal((n, 3))
    surf = c + r * dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    q = c + rng.uniform(-2 * r, 2 * r, (300, 3))
    _check_brute(s, surf, lambda p: np.linalg.norm(p - c, axis=-1) < r, q)
    _check_fd(s, _away_from_kinks(q, lambda p: np.linalg.norm(p - c, axis=-1)))
    d, g = s.distance_and_gradient(c)  # the centre: finite, unit gradient
    assert d == pytest.approx(-r) and np.linalg.norm(g) == pytest.approx(1.0)


@pytest.mark.parametrize("oriented", [False, True])
def test_box_brute_force_and_gradient(rng, oriented):
    c, h = rng.normal(0, 0.3, 3), rng.uniform(0.03, 0.12, 3)
    R = random_rotations(rng, 1)[0] if oriented else np.eye(3)
    box = BoxSDF(c, h, R if oriented else None)
    surf = _box_surface(h) @ R.T + c
    q = c + rng.uniform(-2.2, 2.2, (400, 3)) * h.max()
    local = lambda p: (p - c) @ R  # noqa: E731
    _check_brute(box, surf, lambda p: np.all(np.abs(local(p)) < h, axis=-1), q)

    def kink(p):  # distance to the non-smooth set: inner medial planes |q_i|-h_i == |q_j|-h_j, edges of outside
        e = np.abs(local(p)) - h
        srt = np.sort(e, axis=-1)
        inside = srt[:, -1] < 0
        return np.where(inside, srt[:, -1] - srt[:, -2], np.min(np.abs(e), axis=-1) + 0.0 * srt[:, -1])

    _check_fd(box, _away_from_kinks(q, kink))


def test_box_from_bounds():
    box = BoxSDF.from_bounds([0, 0, 0], [1, 2, 3])
    d, g = box.distance_and_gradient(np.array([[0.5, 1.0, 4.0], [0.5, 0.1, 1.5]]))
    np.testing.assert_allclose(d, [1.0, -0.1])
    np.testing.assert_allclose(g, [[0, 0, 1], [0, -1, 0]])


def test_cylinder_brute_force_and_gradient(rng):
    c, r, hh = rng.normal(0, 0.3, 3), rng.uniform(0.03, 0.1), rng.uniform(0.03, 0.1)
    R = random_rotations(rng, 1)[0]
    cyl = CylinderSDF(c, r, hh, R)
    surf = _cylinder_surface(r, hh) @ R.T + c
    q = c + rng.uniform(-2.5, 2.5, (400, 3)) * max(r, hh)
    local = lambda p: (p - c) @ R  # noqa: E731

    def inside(p):
        lq = local(p)
        return (np.hypot(lq[:, 0], lq[:, 1]) < r) & (np.abs(lq[:, 2]) < hh)

    _check_brute(cyl, surf, inside, q)

    def kink(p):
        lq = local(p)
        e = np.stack([np.hypot(lq[:, 0], lq[:, 1]) - r, np.abs(lq[:, 2]) - hh], -1)
        ins = np.all(e < 0, -1)
        return np.where(ins, np.abs(e[:, 0] - e[:, 1]), np.min(np.abs(e), -1))

    _check_fd(cyl, _away_from_kinks(q, kink))


def test_capsule_brute_force_and_gradient(rng):
    c, r, hl = rng.normal(0, 0.3, 3), rng.uniform(0.01, 0.05), rng.uniform(0.0, 0.08)
    R = random_rotations(rng, 1)[0]
    cap = CapsuleSDF(c, r, hl, R)
    # surface: cylinder side (grid) + two hemispherical caps (Fibonacci points), spacing <= SPACING / 2
    h = SPACING / 2
    phi = np.linspace(0, 2 * np.pi, int(2 * np.pi * r / h) + 2, endpoint=False)
    zz = np.linspace(-hl, hl, int(2 * hl / h) + 2)
    P, Z = np.meshgrid(phi, zz, indexing="ij")
    side = np.stack([r * np.cos(P).ravel(), r * np.sin(P).ravel(), Z.ravel()], -1)
    m = int(2 * np.pi * r * r / h**2) + 10
    i = np.arange(m) + 0.5
    cz = i / m  # uniform in z on the unit hemisphere = uniform by area
    ang = np.pi * (1 + 5**0.5) * i
    hemi = np.stack([np.sqrt(1 - cz**2) * np.cos(ang), np.sqrt(1 - cz**2) * np.sin(ang), cz], -1) * r
    caps = [hemi + np.array([0, 0, hl]), hemi * np.array([1, 1, -1]) - np.array([0, 0, hl])]
    ring = np.concatenate([side] + caps)
    surf = ring @ R.T + c
    q = c + rng.uniform(-3, 3, (400, 3)) * max(r, hl + r)

    def seg_dist(p):
        lq = (p - c) @ R
        z = np.clip(lq[:, 2], -hl, hl)
        return np.linalg.norm(lq - np.stack([0 * z, 0 * z, z], -1), axis=1)

    _check_brute(cap, surf, lambda p: seg_dist(p) < r, q)
    _check_fd(cap, q[seg_dist(q) > 1e-3])
    d, g = cap.distance_and_gradient(c)  # on the segment: finite, unit gradient, depth = radius
    assert np.isclose(d, -r) and np.isclose(np.linalg.norm(g), 1.0)


def test_half_space(rng):
    p0, n = rng.normal(0, 1, 3), rng.normal(0, 1, 3)
    hs = HalfSpaceSDF(p0, n)
    q = rng.normal(0, 1, (100, 3))
    d, g = hs.distance_and_gradient(q)
    nu = n / np.linalg.norm(n)
    np.testing.assert_allclose(d, (q - p0) @ nu, atol=1e-14)
    proj = q - d[:, None] * nu  # brute force: the foot point is on the plane and the nearest
    np.testing.assert_allclose((proj - p0) @ nu, 0.0, atol=1e-12)
    _check_fd(hs, q)


def test_convex_polytope_matches_box_inside_and_lower_bound_outside(rng):
    c, h = rng.normal(0, 0.3, 3), rng.uniform(0.03, 0.12, 3)
    R = random_rotations(rng, 1)[0]
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h @ R.T + c
    poly = ConvexPolytopeSDF.from_points(np.concatenate([corners, c + rng.uniform(-0.5, 0.5, (20, 3)) * h @ R.T]))
    box = BoxSDF(c, h, R)
    q = c + rng.uniform(-2.5, 2.5, (500, 3)) * h.max()
    dp, gp = poly.distance_and_gradient(q)
    db, _ = box.distance_and_gradient(q)
    inside = db < 0
    np.testing.assert_allclose(dp[inside], db[inside], atol=1e-12)  # exact inside
    assert np.all(dp[~inside] <= db[~inside] + 1e-12)  # lower bound outside
    e = np.abs((q - c) @ R) - h  # face regions outside: exactly one positive excess
    face = (~inside) & (np.sum(e > 0, axis=-1) == 1)
    np.testing.assert_allclose(dp[face], db[face], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(gp, axis=-1), 1.0)
    srt = np.sort(q @ poly.normals.T + poly.offsets, axis=-1)
    _check_fd(poly, q[srt[:, -1] - srt[:, -2] > 1e-3])


def test_polytope_from_degenerate_points_raises():
    with pytest.raises(GeometryError, match="convex hull"):
        ConvexPolytopeSDF.from_points(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]))


def test_union_and_inflation(rng):
    parts = [SphereSDF(rng.normal(0, 0.2, 3), 0.1), BoxSDF(rng.normal(0, 0.2, 3), [0.05, 0.08, 0.1]),
             HalfSpaceSDF([0, 0, -0.3], [0, 0, 1])]
    margin = 0.02
    u = UnionSDF(parts, inflation=margin)
    q = rng.normal(0, 0.3, (400, 3))
    d, g = u.distance_and_gradient(q)
    each = np.stack([p.distance_and_gradient(q)[0] for p in parts])
    np.testing.assert_allclose(d, each.min(0) - margin, atol=1e-14)
    srt = np.sort(each, axis=0)
    _check_fd(u, q[srt[1] - srt[0] > 1e-3][:100], tol=1e-4)
    inf = InflatedSDF(parts[0], margin)
    np.testing.assert_allclose(inf.distance_and_gradient(q)[0], each[0] - margin)
    assert isinstance(u, SignedDistanceField) and isinstance(inf, SignedDistanceField)


def test_batch_shapes_and_no_nan():
    s = UnionSDF([SphereSDF([0, 0, 0], 0.1), CylinderSDF([0, 0, 0], 0.1, 0.1)])
    q = np.zeros((2, 5, 3))  # exactly at centres / on the axis
    d, g = s.distance_and_gradient(q)
    assert d.shape == (2, 5) and g.shape == (2, 5, 3)
    assert np.isfinite(d).all() and np.isfinite(g).all()


@pytest.mark.parametrize("bad", [
    lambda: SphereSDF([0, 0, 0], -1.0),
    lambda: BoxSDF([0, 0, 0], [0.1, 0.0, 0.1]),
    lambda: BoxSDF([0, 0, 0], [0.1, 0.1, 0.1], np.diag([1.0, 1.0, -1.0])),
    lambda: HalfSpaceSDF([0, 0, 0], [0, 0, 0]),
    lambda: UnionSDF([]),
    lambda: SphereSDF([0, np.nan, 0], 0.1),
])
def test_bad_input_raises(bad):
    with pytest.raises(GeometryError):
        bad()


def test_bad_points_raise():
    with pytest.raises(GeometryError):
        SphereSDF([0, 0, 0], 0.1).distance_and_gradient(np.array([[0.0, np.nan, 0.0]]))
