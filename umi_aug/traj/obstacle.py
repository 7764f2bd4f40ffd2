"""An added obstacle as the inflated convex hull of its point cloud (paper §3.2, obstacle augmentation).

The inflated hull is ``{p : max_i(n_i·p + b_i) ≤ inflation}`` (every facet plane pushed out by ``inflation``):
a polytope containing the Minkowski sum hull ⊕ ball(inflation), so tests against it are conservative. Membership
and segment tests are EXACT (half-space arithmetic, no sampling); the distance used as an SDF is exact inside
and in facet regions and a lower bound near edges/vertices (:class:`umi_aug.geometry.sdf.ConvexPolytopeSDF`).
World frame, metres.
"""

from __future__ import annotations

import numpy as np

from umi_aug.errors import TrajError
from umi_aug.geometry.sdf import ConvexPolytopeSDF

__all__ = ["ConvexObstacle"]


class ConvexObstacle:
    """Convex hull of an obstacle point cloud, inflated.

    Args:
        points_world: np.ndarray,  # [N, 3] obstacle points (N >= 4, not coplanar), world, metres
        inflation: float,  # metres >= 0

    Attributes:
        normals: np.ndarray,  # [F, 3] unit outward facet normals
        offsets: np.ndarray,  # [F] plane offsets (n·p + b = signed distance to the un-inflated facet plane)
        vertices: np.ndarray,  # [V, 3] hull vertices
        simplices: np.ndarray,  # [F, 3] vertex indices (into ``points_world``) of the hull triangles
    """

    def __init__(self, points_world: np.ndarray, inflation: float) -> None:
        from scipy.spatial import ConvexHull, QhullError  # lazy, start-up: scipy

        pts = np.asarray(points_world, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 4 or not np.isfinite(pts).all():
            raise TrajError(f"ConvexObstacle: `points_world` must be finite [N >= 4, 3], got {pts.shape}")
        try:
            inflation = float(inflation)
        except (TypeError, ValueError) as exc:
            raise TrajError(f"ConvexObstacle: `inflation` must be a float, got {inflation!r}") from exc
        if not np.isfinite(inflation) or inflation < 0:
            raise TrajError(f"ConvexObstacle: `inflation` = {inflation!r}; expected a finite value >= 0 (metres)")
        try:
            hull = ConvexHull(pts)
        except (QhullError, ValueError) as exc:
            raise TrajError(f"ConvexObstacle: convex hull of {len(pts)} points failed (coplanar or degenerate "
                            f"obstacle point cloud): {exc}") from exc
        eq = hull.equations
        n = np.linalg.norm(eq[:, :3], axis=1)
        self.normals = eq[:, :3] / n[:, None]
        self.offsets = eq[:, 3] / n
        self.inflation = inflation
        self.points = pts
        self.vertices = pts[hull.vertices]
        self.simplices = hull.simplices
        self.sdf = ConvexPolytopeSDF(self.normals, self.offsets - inflation)  # inflated: plane offsets shifted

    def plane_values(self, p: np.ndarray) -> np.ndarray:
        """``max_i(n_i·p + b_i) − inflation`` for points ``[..., 3]`` → ``[...]`` (≤ 0 ⇔ inside the inflated hull)."""
        return np.max(p @ self.normals.T + self.offsets, axis=-1) - self.inflation

    def contains(self, p: np.ndarray, extra: np.ndarray | float = 0.0) -> np.ndarray:
        """Whether points ``[..., 3]`` lie inside the hull inflated by ``inflation + extra`` (closed set)."""
        return self.plane_values(np.asarray(p, dtype=np.float64)) <= extra

    def segments_intersect(self, a: np.ndarray, b: np.ndarray, extra: np.ndarray | float = 0.0) -> np.ndarray:
        """Exact test: does the segment ``a→b`` touch the hull inflated by ``inflation + extra``? (Cyrus–Beck
        clipping of the segment against every facet half-space.)

        Args:
            a: np.ndarray,  # [..., 3] world, metres
            b: np.ndarray,  # [..., 3]
            extra: float or np.ndarray,  # broadcast to [...], metres (e.g. a sphere radius)
        Returns:
            np.ndarray,  # [...] bool
        """
        a = np.asarray(a, dtype=np.float64)
        b = np.asarray(b, dtype=np.float64)
        off = self.offsets - self.inflation - np.asarray(extra, dtype=np.float64)[..., None]
        fa = a @ self.normals.T + off  # [..., F]  f(u) = fa + u (fb − fa) ≤ 0 inside facet i's half-space
        fb = b @ self.normals.T + off
        df = fb - fa
        lo = np.zeros(fa.shape[:-1])
        hi = np.ones(fa.shape[:-1])
        entering = df < 0  # crosses into the half-space at u = −fa/df
        leaving = df > 0
        parallel_out = (df == 0) & (fa > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(df != 0, -fa / np.where(df != 0, df, 1.0), 0.0)
        lo = np.maximum(lo, np.max(np.where(entering, u, -np.inf), axis=-1))
        hi = np.minimum(hi, np.min(np.where(leaving, u, np.inf), axis=-1))
        return (lo <= hi) & ~np.any(parallel_out, axis=-1)

    def bounds(self, extra: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Approximate axis-aligned bounds of the inflated hull: vertices ± (3·inflation + extra) (plane offsets
        move sharp corners further than ``inflation``; used only to size sampling boxes)."""
        pad = 3.0 * self.inflation + extra
        return self.vertices.min(0) - pad, self.vertices.max(0) + pad
