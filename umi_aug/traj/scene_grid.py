"""A conservative, precomputed lower bound of the scene SDF on a regular grid.

Used to skip exact SDF queries that cannot matter: RRT* edge checks, and the collision term for gripper spheres
that are provably far from every surface (a sphere whose lower bound already clears the hinge contributes
exactly zero cost and gradient, so skipping it changes nothing). For a 1-Lipschitz distance field, the value at
the nearest grid node minus half the cell diagonal is a lower bound anywhere in that node's cell.
"""

from __future__ import annotations

import numpy as np

from umi_aug.errors import TrajError
from umi_aug.geometry.sdf import SignedDistanceField

__all__ = ["SceneGrid"]


class SceneGrid:
    """The scene SDF sampled once on a regular grid; nearest-node value minus half the cell diagonal is a LOWER
    bound of the distance (the SDF is 1-Lipschitz); points outside the grid fall back to the exact SDF.

    Args:
        sdf: the scene SDF.
        lo, hi: np.ndarray,  # [3] grid box, world, metres
        step: cell size, metres
    """

    def __init__(self, sdf: SignedDistanceField, lo: np.ndarray, hi: np.ndarray, step: float) -> None:
        self.sdf = sdf
        self.step = float(step)
        self.lo = np.asarray(lo, dtype=np.float64)
        self.shape = np.maximum(np.ceil((np.asarray(hi) - self.lo) / self.step).astype(int) + 1, 2)
        axes = [self.lo[i] + self.step * np.arange(self.shape[i]) for i in range(3)]
        G = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
        self.values = np.asarray(sdf.distance_and_gradient(G)[0], dtype=np.float64) - 0.5 * np.sqrt(3.0) * self.step
        if not np.isfinite(self.values).all():
            raise TrajError("SceneGrid: the scene SDF returned non-finite distances on the grid")

    def lower_bound(self, p: np.ndarray) -> np.ndarray:
        """Lower bound of the scene SDF at points ``[..., 3]`` → ``[...]``."""
        f = (p - self.lo) / self.step
        i = np.rint(f).astype(np.int64)
        inside = np.all((i >= 0) & (i < self.shape), axis=-1)
        ic = np.clip(i, 0, self.shape - 1)
        out = self.values[ic[..., 0], ic[..., 1], ic[..., 2]]
        if not inside.all():
            out = np.where(inside, out, 0.0)
            out[~inside] = self.sdf.distance_and_gradient(p[~inside])[0]
        return out
