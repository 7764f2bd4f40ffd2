"""Render prior: keep waypoints near the views the fisheye 3DGS was trained on (paper §3.2, L_render).

For a waypoint ``x = (R, t)`` and a training view ``j`` the SE(3) distance is
``d_j² = ‖t − t_j‖² + ℓ²·‖log(Rᵀ R_j)‖²`` (ℓ = ``rot_scale``, metres per radian). The per-waypoint cost is the mean
over the K nearest views (in this metric) of ``min(d_j², ρ²)``: views inside the ball of radius ρ pull the
waypoint with the paper's quadratic, views outside contribute the constant ρ² (no force). Unlike a hard ball
membership this is continuous in ``x``. Views with ``‖t − t_j‖ ≥ ρ`` cannot lie in the ball, so candidates come
from a KD-tree on positions (``k_candidates`` nearest within ρ); the result is exact whenever no waypoint has more
than ``k_candidates`` views within ρ in position (and a close approximation otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from umi_aug.errors import TrajError
from umi_aug.geometry.so3 import so3_log_unchecked as _so3_log

__all__ = ["RenderPrior", "RenderNeighbours"]


@dataclass(frozen=True)
class RenderNeighbours:
    """Selected (waypoint, view) pairs inside the ball, flattened.

    Attributes:
        point: np.ndarray,  # [P] int, index of the query waypoint
        view: np.ndarray,  # [P] int, index of the view
        dt: np.ndarray,  # [P, 3] t − t_j, metres
        e: np.ndarray,  # [P, 3] log(Rᵀ R_j), radians
        n_truncated: np.ndarray,  # [N] number of the K slots contributing the constant ρ²
    """

    point: np.ndarray
    view: np.ndarray
    dt: np.ndarray
    e: np.ndarray
    n_truncated: np.ndarray


def _thin_views(V: np.ndarray, min_sep: float, rot_scale: float) -> np.ndarray:
    """Indices of a greedy subset of views ``[V, 4, 4]`` (in order) in which no two are closer than ``min_sep``
    in the combined metric ``sqrt(‖Δt‖² + ℓ²θ²)``."""
    n = V.shape[0]
    if min_sep <= 0 or n <= 1:
        return np.arange(n)
    tree = cKDTree(V[:, :3, 3])
    keep = np.zeros(n, dtype=bool)
    dropped = np.zeros(n, dtype=bool)
    for i in range(n):
        if dropped[i]:
            continue
        keep[i] = True
        near = np.array(tree.query_ball_point(V[i, :3, 3], min_sep), dtype=np.int64)
        near = near[(near > i) & ~dropped[near]]
        if near.size:
            Q = V[i, :3, :3].T @ V[near, :3, :3]
            w = 0.5 * np.stack([Q[:, 2, 1] - Q[:, 1, 2], Q[:, 0, 2] - Q[:, 2, 0], Q[:, 1, 0] - Q[:, 0, 1]], -1)
            ang = np.arctan2(np.linalg.norm(w, axis=-1), 0.5 * (np.trace(Q, axis1=-2, axis2=-1) - 1.0))
            dt2 = np.sum((V[near, :3, 3] - V[i, :3, 3]) ** 2, axis=-1)
            dropped[near[dt2 + (rot_scale * ang) ** 2 < min_sep**2]] = True
    return np.flatnonzero(keep)


class RenderPrior:
    """Training views (demo + scan camera poses) and the K-nearest truncated-quadratic prior.

    Args:
        views_T_world_cam: np.ndarray,  # [V, 4, 4] camera poses the 3DGS was trained on (OpenCV cameras)
        radius: float,  # ρ, metres
        rot_scale: float,  # ℓ, metres per radian
        k: int,  # K nearest views
        k_candidates: int,  # position-nearest candidates searched (>= k)
        max_views: int,  # evenly strided subsample when V is larger (after thinning)
        min_separation: float,  # metres (combined metric): a view closer than this to an earlier kept view is
            dropped (video frames are ~5 mm apart; near-duplicates would crowd out the K nearest)
    """

    def __init__(self, views_T_world_cam: np.ndarray, radius: float, rot_scale: float, k: int,
                 k_candidates: int, max_views: int, min_separation: float = 0.0) -> None:
        V = np.asarray(views_T_world_cam, dtype=np.float64)
        if V.ndim != 3 or V.shape[1:] != (4, 4) or V.shape[0] < 1 or not np.isfinite(V).all():
            raise TrajError(f"RenderPrior: views must be finite [V >= 1, 4, 4], got {V.shape}")
        V = V[_thin_views(V, min_separation, rot_scale)]
        if V.shape[0] > max_views:
            V = V[np.unique(np.round(np.linspace(0, V.shape[0] - 1, max_views)).astype(int))]
        self.positions = np.ascontiguousarray(V[:, :3, 3])
        self.rotations = np.ascontiguousarray(V[:, :3, :3])
        self._rot_flat = self.rotations.reshape(-1, 9)
        self.radius = float(radius)
        self.rot_scale = float(rot_scale)
        self.k = int(k)
        self.k_candidates = int(min(k_candidates, self.positions.shape[0]))
        self._tree = cKDTree(self.positions)

    @property
    def n_views(self) -> int:
        return self.positions.shape[0]

    def query(self, t: np.ndarray, R: np.ndarray) -> RenderNeighbours:
        """K nearest views within the ball for each query pose.

        Args:
            t: np.ndarray,  # [N, 3] camera positions, world, metres
            R: np.ndarray,  # [N, 3, 3] R_world_cam
        """
        N = t.shape[0]
        kc = self.k_candidates
        rho2 = self.radius * self.radius
        _, idx = self._tree.query(t, k=kc, distance_upper_bound=self.radius)
        idx = idx.reshape(N, kc)
        valid = idx < self.n_views
        safe = np.where(valid, idx, 0)
        # candidate distances for selection only (the residuals below use the exact log): the geodesic angle from
        # the trace, tr(R_kᵀ R_j) = Σ R_k ⊙ R_j, which is accurate where the ρ cut-off and the ordering matter
        dt = t[:, None, :] - self.positions[safe]  # [N, kc, 3]
        tr = np.sum(R.reshape(N, 1, 9) * self._rot_flat[safe], axis=-1)
        ang = np.arccos(np.clip(0.5 * (tr - 1.0), -1.0, 1.0))
        dd = np.sum(dt * dt, axis=-1) + (self.rot_scale * ang) ** 2
        d2 = np.where(valid & (dd < rho2), dd, np.inf)
        k = min(self.k, kc)
        order = np.argsort(d2, axis=1, kind="stable")[:, :k]
        sel_d2 = np.take_along_axis(d2, order, axis=1)
        inside = np.isfinite(sel_d2)
        n_trunc = self.k - inside.sum(axis=1)
        p, c = np.nonzero(inside)
        views = idx[p, order[p, c]]
        dt = t[p] - self.positions[views]
        e = _so3_log(np.swapaxes(R[p], -1, -2) @ self.rotations[views]) if p.size else np.zeros((0, 3))
        return RenderNeighbours(point=p, view=views, dt=dt, e=e, n_truncated=n_trunc)
