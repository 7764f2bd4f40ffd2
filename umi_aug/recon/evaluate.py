"""Accuracy of a reconstruction against ground truth (synthetic sessions): point cloud, poses, SDF, contact.

Distances in metres in, reported in millimetres / centimetres / degrees (keys say which). World frame.
"""

from __future__ import annotations

import math

import numpy as np

from umi_aug.geometry.sdf import SignedDistanceField
from umi_aug.recon.cloud import SceneCloud
from umi_aug.recon.constants import SDF_SIGN_NEIGHBOURS
from umi_aug.recon.sdf_grid import sign_vote

__all__ = ["cloud_metrics", "pose_metrics", "sdf_metrics", "in_box"]


def in_box(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``[N]`` bool: points ``[N, 3]`` inside the box."""
    return np.all((p >= lo) & (p <= hi), axis=1)


def cloud_metrics(recon: np.ndarray, gt_points: np.ndarray, gt_normals: np.ndarray | None = None,
                  roi: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, float]:
    """Accuracy (reconstruction → GT) and completeness (GT → reconstruction) inside ``roi``.

    Returns (mm / %): ``accuracy_mean_mm`` / ``accuracy_median_mm`` (point-to-plane with GT normals when given —
    the GT cloud is a sampling, so point-to-point would measure its spacing), ``completeness_mean_mm``,
    ``within_1cm_pct`` / ``within_2cm_pct`` (% of GT points with a reconstructed point that close), ``chamfer_mm``
    (mean of the two point-to-point means), ``n_recon``, ``n_gt``.
    """
    from scipy.spatial import cKDTree  # lazy, start-up: scipy

    R = np.asarray(recon, np.float64).reshape(-1, 3)
    G = np.asarray(gt_points, np.float64).reshape(-1, 3)
    N = None if gt_normals is None else np.asarray(gt_normals, np.float64).reshape(-1, 3)
    if roi is not None:
        kr, kg = in_box(R, *roi), in_box(G, *roi)
        R, G = R[kr], G[kg]
        N = None if N is None else N[kg]
    out = {"n_recon": float(len(R)), "n_gt": float(len(G))}
    if len(R) == 0 or len(G) == 0:
        return out | {"accuracy_mean_mm": math.inf, "accuracy_median_mm": math.inf, "completeness_mean_mm": math.inf,
                      "within_1cm_pct": 0.0, "within_2cm_pct": 0.0, "chamfer_mm": math.inf}
    d_rg, i_rg = cKDTree(G).query(R)
    acc = np.abs(np.sum((R - G[i_rg]) * N[i_rg], axis=1)) if N is not None else d_rg
    d_gr, _ = cKDTree(R).query(G)
    return out | {
        "accuracy_mean_mm": 1000 * float(acc.mean()), "accuracy_median_mm": 1000 * float(np.median(acc)),
        "completeness_mean_mm": 1000 * float(d_gr.mean()),
        "within_1cm_pct": 100 * float(np.mean(d_gr <= 0.01)), "within_2cm_pct": 100 * float(np.mean(d_gr <= 0.02)),
        "chamfer_mm": 1000 * 0.5 * float(d_rg.mean() + d_gr.mean()),
    }


def pose_metrics(T_est: np.ndarray, T_gt: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """Camera pose error: ``trans_mean_cm``, ``trans_max_cm``, ``rot_mean_deg``, ``rot_max_deg`` over ``mask``."""
    A = np.asarray(T_est, np.float64)
    B = np.asarray(T_gt, np.float64)
    m = np.ones(len(A), bool) if mask is None else np.asarray(mask, bool)
    if not m.any():
        return {"trans_mean_cm": math.inf, "trans_max_cm": math.inf, "rot_mean_deg": math.inf, "rot_max_deg": math.inf}
    dt = np.linalg.norm(A[m, :3, 3] - B[m, :3, 3], axis=1)
    Rr = np.einsum("nji,njk->nik", A[m, :3, :3], B[m, :3, :3])
    ang = np.degrees(np.arccos(np.clip((np.trace(Rr, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return {"trans_mean_cm": 100 * float(dt.mean()), "trans_max_cm": 100 * float(dt.max()),
            "rot_mean_deg": float(ang.mean()), "rot_max_deg": float(ang.max())}


def sdf_metrics(sdf: SignedDistanceField, gt_cloud: SceneCloud, queries: np.ndarray, h: float) -> dict[str, float]:
    """SDF vs the ground-truth cloud's SDF (nearest GT point, sign from the GT normals, same vote) at ``queries``.

    Returns: ``median_abs_err_mm``, ``free_median_err_mm`` (signed, grid − GT, in GT free space; < 0 =
    conservative), ``false_free_pct`` (grid > 0 where GT < 0: dangerous), ``false_occupied_pct`` (grid < 0 where
    GT > 0: conservative), ``lower_bound_pct`` (% of GT-free queries where grid ≤ GT).
    """
    from scipy.spatial import cKDTree  # lazy, start-up: scipy

    q = np.asarray(queries, np.float64).reshape(-1, 3)
    d, idx = cKDTree(gt_cloud.points).query(q, k=SDF_SIGN_NEIGHBOURS)
    s = sign_vote(q, gt_cloud.points[idx], gt_cloud.normals[idx], d, h)
    gt = s * d[:, 0]
    v = np.asarray(sdf.distance_and_gradient(q)[0])
    free = gt > 0
    return {
        "median_abs_err_mm": 1000 * float(np.median(np.abs(v - gt))),
        "free_median_err_mm": 1000 * float(np.median(v[free] - gt[free])) if free.any() else 0.0,
        "false_free_pct": 100 * float(np.mean((v > 0) & (gt < 0))),
        "false_occupied_pct": 100 * float(np.mean((v < 0) & (gt > 0))),
        "lower_bound_pct": 100 * float(np.mean(v[free] <= gt[free])) if free.any() else 100.0,
    }
