"""Slow references of the recon stage (gsplat ``_torch_impl`` style: private, for tests only).

* :func:`_reference_sdf` mirrors :func:`umi_aug.recon.sdf_grid.build_scene_sdf` (the scene SDF as a
  :class:`~umi_aug.recon.sdf_grid.VoxelSDF`): brute-force nearest points, same sign rule, evaluated exactly at each
  query (no grid, no offset).
* :func:`_reference_unsigned_sdf`: the unsigned field as the signed one folded to its magnitude.
"""

from __future__ import annotations

import numpy as np

from umi_aug.recon.cloud import SceneCloud
from umi_aug.recon.constants import SDF_SIGN_NEIGHBOURS
from umi_aug.recon.sdf_grid import VoxelSDF, build_scene_sdf, sign_vote


def _reference_sdf(points_world: np.ndarray, cloud: SceneCloud, h: float, sign_neighbours: int = SDF_SIGN_NEIGHBOURS,
                   chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Reference of :func:`umi_aug.recon.sdf_grid.build_scene_sdf`'s field: signed distance to the nearest cloud
    point and its gradient ``s·(q − p*)/‖q − p*‖``.

    Args:
        points_world: np.ndarray,  # [M, 3]
        cloud: points + oriented normals.
        h: softening length of the sign vote (the grid's voxel size, so the rule is identical).
    Returns:
        (sdf [M], grad [M, 3])
    """
    q = np.asarray(points_world, np.float64).reshape(-1, 3)
    P = cloud.points
    k = int(min(sign_neighbours, len(P)))
    d_out = np.empty(len(q))
    g_out = np.empty((len(q), 3))
    for a in range(0, len(q), chunk):
        qq = q[a:a + chunk]
        # [m, N] brute force, one coordinate at a time (the same sums as over a [m, N, 3] difference, ~10x faster)
        D = np.sqrt((qq[:, 0, None] - P[None, :, 0]) ** 2 + (qq[:, 1, None] - P[None, :, 1]) ** 2
                    + (qq[:, 2, None] - P[None, :, 2]) ** 2)
        # the k nearest, closest first (ties by point index; a tie at the k-th distance keeps either point)
        idx = np.argpartition(D, k - 1, axis=1)[:, :k] if k < D.shape[1] else np.tile(np.arange(k), (len(qq), 1))
        dk = np.take_along_axis(D, idx, axis=1)
        order = np.lexsort((idx, dk), axis=1)
        idx, dk = np.take_along_axis(idx, order, axis=1), np.take_along_axis(dk, order, axis=1)
        s = sign_vote(qq, P[idx], cloud.normals[idx], dk, h)
        near = P[idx[:, 0]]
        v = qq - near
        nv = np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        d_out[a:a + chunk] = s * dk[:, 0]
        g_out[a:a + chunk] = s[:, None] * v / nv
    return d_out, g_out


def _reference_unsigned_sdf(cloud: SceneCloud, lo: np.ndarray, hi: np.ndarray, voxel: float,
                            inflation: float = 0.0) -> VoxelSDF:
    """Reference of ``build_scene_sdf(..., signed=False)``: the signed field (every sign vote taken) folded to its
    magnitude, ``|v + √3/2·h| − √3/2·h`` per node (how a dataset scene's unsigned field was made before session 40).
    Returns a :class:`~umi_aug.recon.sdf_grid.VoxelSDF`."""
    sdf = build_scene_sdf(cloud, lo, hi, voxel, inflation)
    half = np.sqrt(3.0) / 2.0 * sdf.voxel
    return VoxelSDF(np.abs(sdf.values + half) - half, sdf.origin, sdf.voxel, sdf.inflation)
