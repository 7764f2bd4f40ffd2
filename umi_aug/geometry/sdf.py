"""Signed distance fields (numpy float64): the interface every stage shares, and analytic implementations.

Convention: ``sdf(p) > 0`` in free space, ``< 0`` inside matter, ``|sdf|`` in metres; the gradient is the unit
outward direction (``‖∇sdf‖ = 1`` wherever it is defined). Points are in the world frame (the UMI table-tag
frame, z up). This module sits in the lowest shared stage so that scene reconstruction (issue #5) can implement
:class:`SignedDistanceField` from a TSDF/ESDF and the trajectory stage can consume it without back-references.

At the non-smooth points of an analytic field (a sphere's centre, a box's medial planes, the seam of a union)
the gradient is one valid one-sided gradient (documented per class); it is always finite and never NaN.
"""

from __future__ import annotations

from typing import Protocol, Sequence, runtime_checkable

import numpy as np

from umi_aug.config_check import is_positive
from umi_aug.errors import GeometryError
from umi_aug.geometry._checks import as_float

__all__ = [
    "SignedDistanceField",
    "SphereSDF",
    "BoxSDF",
    "CylinderSDF",
    "CapsuleSDF",
    "HalfSpaceSDF",
    "ConvexPolytopeSDF",
    "UnionSDF",
    "InflatedSDF",
    "check_sdf_output",
]

#: Below this norm a direction is treated as zero (sphere centre, cylinder axis); the fallback gradient is used.
_SDF_NORM_EPS: float = 1e-12


@runtime_checkable
class SignedDistanceField(Protocol):
    """A scene's signed distance, queried in batches.

    ``distance_and_gradient(points_world)`` takes ``[..., 3]`` float64 world points (metres) and returns
    ``(sdf [...], grad [..., 3])``: signed distance (free space positive) and its spatial gradient (unit length
    where defined). Implementations must be pure (same input → same output), thread-compatible and must never
    return NaN for finite input. Fields that are only an approximation of the true distance (a truncated TSDF,
    a conservative polytope distance) must be a LOWER bound of the true distance in free space, so that
    "clearance ≥ margin" checks stay conservative.
    """

    def distance_and_gradient(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ...


def check_sdf_output(sdf: np.ndarray, grad: np.ndarray, points_shape: tuple[int, ...], who: str) -> None:
    """Validate an SDF's output (shapes and finiteness); raise :class:`GeometryError` naming ``who``."""
    if sdf.shape != points_shape[:-1] or grad.shape != points_shape:
        raise GeometryError(f"{who}: SDF returned shapes {sdf.shape}/{grad.shape} for points {points_shape}; "
                            f"expected {points_shape[:-1]}/{points_shape}")
    if not (np.isfinite(sdf).all() and np.isfinite(grad).all()):
        raise GeometryError(f"{who}: SDF returned non-finite distance or gradient")


def _points(p: np.ndarray, who: str) -> np.ndarray:
    return as_float(p, "points_world", who, (3,))


def _vec3(v, name: str, who: str) -> np.ndarray:
    a = as_float(v, name, who, (3,))
    if a.shape != (3,):
        raise GeometryError(f"{who}: `{name}` has shape {a.shape}; expected [3]")
    return a


def _positive(v, name: str, who: str, allow_zero: bool = False) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{who}: `{name}` must be a float (metres), got {v!r}") from exc
    if not is_positive(f, allow_zero=allow_zero):
        raise GeometryError(f"{who}: `{name}` is {v!r}; expected a finite value {'>=' if allow_zero else '>'} 0")
    return f


def _rotation(R, who: str) -> np.ndarray:
    if R is None:
        return np.eye(3)
    R = as_float(R, "R_world_obj", who, (3, 3))
    if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
        raise GeometryError(f"{who}: `R_world_obj` must be a 3x3 rotation matrix")
    return R


class SphereSDF:
    """Solid ball: ``‖p − c‖ − r``. At the centre the gradient is +z (any unit vector is valid).

    Args:
        center: np.ndarray,  # [3] world, metres
        radius: float,  # metres > 0
    """

    def __init__(self, center: np.ndarray, radius: float) -> None:
        self.center = _vec3(center, "center", "SphereSDF")
        self.radius = _positive(radius, "radius", "SphereSDF")

    def distance_and_gradient(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = _points(points_world, "SphereSDF")
        d = p - self.center
        n = np.sqrt(np.sum(d * d, axis=-1))
        ok = n > _SDF_NORM_EPS
        g = np.where(ok[..., None], d / np.where(ok, n, 1.0)[..., None], np.array([0.0, 0.0, 1.0]))
        return n - self.radius, g


def _box_local(q: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact SDF of the axis-aligned box ``|q_i| ≤ h_i`` (local frame) and its gradient.

    Outside: ``‖max(|q| − h, 0)‖`` with gradient ``sign(q)·max(|q|−h,0)/‖·‖``; inside: ``max_i(|q_i| − h_i)``
    (distance to the nearest face, negative) with gradient ``sign(q_i) e_i`` of that face (ties: lowest axis;
    ``sign(0) = +1``)."""
    s = np.where(q < 0.0, -1.0, 1.0)
    e = np.abs(q) - h
    pos = np.maximum(e, 0.0)
    out_n = np.sqrt(np.sum(pos * pos, axis=-1))
    inner = np.max(e, axis=-1)
    outside = inner > 0.0
    d = np.where(outside, out_n, inner)
    axis = np.argmax(e, axis=-1)
    g_in = np.eye(3)[axis] * s
    g_out = s * pos / np.where(outside, out_n, 1.0)[..., None]
    return d, np.where(outside[..., None], g_out, g_in)


class BoxSDF:
    """Solid box, axis-aligned or oriented (exact distance inside and outside).

    Args:
        center: np.ndarray,  # [3] world, metres
        half_extents: np.ndarray,  # [3] metres > 0, along the box's own axes
        R_world_obj: np.ndarray | None,  # [3, 3] box axes in the world (None = axis-aligned)
    """

    def __init__(self, center: np.ndarray, half_extents: np.ndarray, R_world_obj: np.ndarray | None = None) -> None:
        who = "BoxSDF"
        self.center = _vec3(center, "center", who)
        self.half_extents = _vec3(half_extents, "half_extents", who)
        if np.any(self.half_extents <= 0):
            raise GeometryError(f"{who}: `half_extents` {self.half_extents.tolist()} must all be > 0")
        self.R_world_obj = _rotation(R_world_obj, who)

    @classmethod
    def from_bounds(cls, lo: np.ndarray, hi: np.ndarray) -> "BoxSDF":
        """Axis-aligned box from its corners ``lo < hi`` (world, metres)."""
        lo, hi = _vec3(lo, "lo", "BoxSDF.from_bounds"), _vec3(hi, "hi", "BoxSDF.from_bounds")
        return cls(0.5 * (lo + hi), 0.5 * (hi - lo))

    def distance_and_gradient(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = _points(points_world, "BoxSDF")
        q = (p - self.center) @ self.R_world_obj  # local coordinates: R^T (p - c)
        d, g = _box_local(q, self.half_extents)
        return d, g @ self.R_world_obj.T


class CylinderSDF:
    """Solid capped cylinder (exact distance): axis = the object's z axis through ``center``.

    Args:
        center: np.ndarray,  # [3] world, metres (middle of the axis)
        radius: float,  # metres > 0
        half_height: float,  # metres > 0
        R_world_obj: np.ndarray | None,  # [3, 3] (None: axis = world z)
    """

    def __init__(self, center: np.ndarray, radius: float, half_height: float,
                 R_world_obj: np.ndarray | None = None) -> None:
        who = "CylinderSDF"
        self.center = _vec3(center, "center", who)
        self.radius = _positive(radius, "radius", who)
        self.half_height = _positive(half_height, "half_height", who)
        self.R_world_obj = _rotation(R_world_obj, who)

    def distance_and_gradient(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = _points(points_world, "CylinderSDF")
        q = (p - self.center) @ self.R_world_obj
        rho = np.sqrt(q[..., 0] ** 2 + q[..., 1] ** 2)
        ok = rho > _SDF_NORM_EPS
        radial = np.where(ok[..., None], q[..., :2] / np.where(ok, rho, 1.0)[..., None], np.array([1.0, 0.0]))
        # 2-D box in (rho, z) with half extents (radius, half_height)
        q2 = np.stack([rho, q[..., 2]], axis=-1)
        d, g2 = _box_local_2d(q2, np.array([self.radius, self.half_height]))
        g_local = np.concatenate([g2[..., :1] * radial, g2[..., 1:]], axis=-1)
        return d, g_local @ self.R_world_obj.T


def _box_local_2d(q: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    s = np.where(q < 0.0, -1.0, 1.0)
    e = np.abs(q) - h
    pos = np.maximum(e, 0.0)
    out_n = np.sqrt(np.sum(pos * pos, axis=-1))
    inner = np.max(e, axis=-1)
    outside = inner > 0.0
    d = np.where(outside, out_n, inner)
    first = e[..., 0] >= e[..., 1]
    g_in = np.where(first[..., None], np.array([1.0, 0.0]), np.array([0.0, 1.0])) * s
    g_out = s * pos / np.where(outside, out_n, 1.0)[..., None]
    return d, np.where(outside[..., None], g_out, g_in)


class CapsuleSDF:
    """Solid capsule (exact distance): points within ``radius`` of the segment ``center ± half_length · axis``,
    axis = the object's z axis (MuJoCo's capsule convention). On the segment itself the gradient is the object's
    x axis (any direction normal to the segment is valid).

    Args:
        center: np.ndarray,  # [3] world, metres (middle of the segment)
        radius: float,  # metres > 0
        half_length: float,  # metres >= 0 (0: a sphere)
        R_world_obj: np.ndarray | None,  # [3, 3] (None: axis = world z)
    """

    def __init__(self, center: np.ndarray, radius: float, half_length: float,
                 R_world_obj: np.ndarray | None = None) -> None:
        who = "CapsuleSDF"
        self.center = _vec3(center, "center", who)
        self.radius = _positive(radius, "radius", who)
        self.half_length = _positive(half_length, "half_length", who, allow_zero=True)
        self.R_world_obj = _rotation(R_world_obj, who)

    def distance_and_gradient(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = _points(points_world, "CapsuleSDF")
        q = (p - self.center) @ self.R_world_obj
        closest_z = np.clip(q[..., 2], -self.half_length, self.half_length)
        d = q - np.stack([np.zeros_like(closest_z), np.zeros_like(closest_z), closest_z], axis=-1)
        n = np.sqrt(np.sum(d * d, axis=-1))
        ok = n > _SDF_NORM_EPS
        g_local = np.where(ok[..., None], d / np.where(ok, n, 1.0)[..., None], np.array([1.0, 0.0, 0.0]))
        return n - self.radius, g_local @ self.R_world_obj.T


class HalfSpaceSDF:
    """Solid half-space below a plane (e.g. a table top): ``n · (p − p0)``, free space where the normal points.

    Args:
        point: np.ndarray,  # [3] a point on the plane, world, metres
        normal: np.ndarray,  # [3] towards free space (normalised here)
    """

    def __init__(self, point: np.ndarray, normal: np.ndarray) -> None:
        who = "HalfSpaceSDF"
        self.point = _vec3(point, "point", who)
        n = _vec3(normal, "normal", who)
        nn = float(np.linalg.norm(n))
        if nn <= _SDF_NORM_EPS:
            raise GeometryError(f"{who}: `normal` must be non-zero")
        self.normal = n / nn

    def distance_and_gradient(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = _points(points_world, "HalfSpaceSDF")
        d = (p - self.point) @ self.normal
        return d, np.broadcast_to(self.normal, p.shape).copy()


class ConvexPolytopeSDF:
    """Solid convex polytope ``{p : A p + b ≤ 0}`` (rows of ``A`` unit outward normals), e.g. a convex hull.

    Distance = ``max_i(A_i p + b_i)``: EXACT inside (distance to the nearest facet) and wherever the nearest
    boundary point lies inside a facet; near edges/vertices outside it is a LOWER bound of the true distance
    (conservative for clearance checks). Gradient: the normal of the maximising facet (ties: lowest index).
    Build from points with :meth:`from_points` (scipy ``ConvexHull.equations``).

    Args:
        normals: np.ndarray,  # [F, 3] outward, normalised here
        offsets: np.ndarray,  # [F] so that n·p + offset = signed plane distance
    """

    def __init__(self, normals: np.ndarray, offsets: np.ndarray) -> None:
        who = "ConvexPolytopeSDF"
        A = as_float(normals, "normals", who, (3,))
        b = as_float(offsets, "offsets", who)
        if A.ndim != 2 or b.shape != (A.shape[0],) or A.shape[0] < 4:
            raise GeometryError(f"{who}: need normals [F, 3] and offsets [F] with F >= 4, got {A.shape}, {b.shape}")
        n = np.linalg.norm(A, axis=-1)
        if np.any(n <= _SDF_NORM_EPS):
            raise GeometryError(f"{who}: a facet normal has zero length")
        self.normals = A / n[:, None]
        self.offsets = b / n

    @classmethod
    def from_points(cls, points: np.ndarray) -> "ConvexPolytopeSDF":
        """Convex hull of a point cloud (``scipy.spatial.ConvexHull``; needs ≥ 4 non-coplanar points)."""
        from scipy.spatial import ConvexHull, QhullError  # lazy, start-up: scipy

        pts = as_float(points, "points", "ConvexPolytopeSDF.from_points", (3,)).reshape(-1, 3)
        try:
            hull = ConvexHull(pts)
        except (QhullError, ValueError) as exc:
            raise GeometryError(f"ConvexPolytopeSDF.from_points: convex hull of {len(pts)} points failed "
                                f"(need >= 4 non-coplanar points): {exc}") from exc
        return cls(hull.equations[:, :3], hull.equations[:, 3])

    def distance_and_gradient(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = _points(points_world, "ConvexPolytopeSDF")
        s = p @ self.normals.T + self.offsets
        i = np.argmax(s, axis=-1)
        return np.take_along_axis(s, i[..., None], axis=-1)[..., 0], self.normals[i]


class UnionSDF:
    """Union of solids: ``min_i sdf_i(p) − inflation``; gradient of the minimising part (ties: first part).

    Exact for the union's exterior distance; inside overlapping parts it is the usual min (an upper bound of the
    true interior depth), which is what collision penalties need.

    Args:
        parts: sequence of :class:`SignedDistanceField`
        inflation: float,  # metres >= 0, subtracted from the distance (grows every solid by this much)
    """

    def __init__(self, parts: Sequence[SignedDistanceField], inflation: float = 0.0) -> None:
        parts = list(parts)
        if not parts:
            raise GeometryError("UnionSDF: `parts` is empty")
        for i, part in enumerate(parts):
            if not hasattr(part, "distance_and_gradient"):
                raise GeometryError(f"UnionSDF: part {i} ({type(part).__name__}) has no distance_and_gradient")
        self.parts = parts
        self.inflation = _positive(inflation, "inflation", "UnionSDF", allow_zero=True)

    def distance_and_gradient(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = _points(points_world, "UnionSDF")
        best_d, best_g = self.parts[0].distance_and_gradient(p)
        best_d, best_g = np.array(best_d, dtype=np.float64), np.array(best_g, dtype=np.float64)
        for part in self.parts[1:]:
            d, g = part.distance_and_gradient(p)
            closer = d < best_d
            best_d = np.where(closer, d, best_d)
            best_g = np.where(closer[..., None], g, best_g)
        return best_d - self.inflation, best_g


class InflatedSDF:
    """Any field grown by a margin: ``sdf(p) − inflation`` (same gradient).

    Args:
        base: :class:`SignedDistanceField`
        inflation: float,  # metres >= 0
    """

    def __init__(self, base: SignedDistanceField, inflation: float) -> None:
        if not hasattr(base, "distance_and_gradient"):
            raise GeometryError(f"InflatedSDF: `base` ({type(base).__name__}) has no distance_and_gradient")
        self.base = base
        self.inflation = _positive(inflation, "inflation", "InflatedSDF", allow_zero=True)

    def distance_and_gradient(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d, g = self.base.distance_and_gradient(points_world)
        return d - self.inflation, g
