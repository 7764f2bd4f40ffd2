"""Sim(3) alignment (Umeyama 1991) of an SfM reconstruction into the metric demo pose frame.

Full SfM returns cameras in an arbitrary similarity frame; the session's SLAM poses (UMI table-tag frame, metres)
of the same frames fix it: find ``s, R, t`` minimising ``Σ ‖s R c_i + t − c'_i‖²`` over camera centres ``c_i``
(SfM) and ``c'_i`` (SLAM). The residual reported is the RMS centre distance after alignment (metres) and the
mean rotation disagreement (radians) between the aligned SfM orientations and the SLAM ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from umi_aug.errors import ReconError
from umi_aug.recon import constants as C
from umi_aug.recon.sfm import SfmResult

__all__ = ["Sim3", "umeyama", "align_sfm_to_poses"]


@dataclass(frozen=True)
class Sim3:
    """Similarity ``x ↦ s R x + t`` with its fit quality.

    Attributes:
        s: float scale (> 0); R: np.ndarray [3, 3] rotation; t: np.ndarray [3] metres.
        residual_rms_m: RMS distance of the aligned source points to the targets, metres.
        rotation_residual_rad: mean geodesic angle between aligned and target camera orientations (NaN-free;
            0 when not computed).
        n: number of correspondences used.
    """

    s: float
    R: np.ndarray
    t: np.ndarray
    residual_rms_m: float
    rotation_residual_rad: float = 0.0
    n: int = 0

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Map points ``[..., 3]``."""
        return self.s * np.asarray(x) @ self.R.T + self.t

    @property
    def matrix(self) -> np.ndarray:
        """``[4, 4]`` homogeneous matrix ``[[sR, t], [0, 1]]``."""
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ≈ s R src + t`` (Umeyama 1991, reflection-safe).

    Args:
        src: np.ndarray,  # [N, 3], N >= 3 not collinear
        dst: np.ndarray,  # [N, 3]
        with_scale: fit the scale (else s = 1).
    Returns:
        (s, R [3, 3], t [3])
    Raises:
        ReconError: fewer than 3 points, non-finite input, or a degenerate (collinear / zero-spread) source.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 3:
        raise ReconError(f"umeyama: need matching [N >= 3, 3] point sets, got {src.shape} and {dst.shape}")
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise ReconError("umeyama: non-finite correspondences")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = float(np.mean(np.sum(xs * xs, axis=1)))
    if var_s <= 1e-18:
        raise ReconError("umeyama: the source points coincide (zero spread): the scale is undefined")
    cov = xd.T @ xs / src.shape[0]
    U, D, Vt = np.linalg.svd(cov)
    if D[1] <= 1e-12 * max(D[0], 1e-300):
        raise ReconError("umeyama: the correspondences are collinear; rotation about their line is undefined")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def align_sfm_to_poses(sfm: SfmResult, T_world_cam: np.ndarray, valid: np.ndarray | None = None,
                       max_residual_m: float = C.MAX_ALIGN_RESIDUAL_M) -> tuple[SfmResult, Sim3]:
    """Align a full-SfM result to metric camera poses of the same frames.

    Args:
        sfm: result of :func:`umi_aug.recon.sfm.run_sfm` (``names`` in the order of ``T_world_cam``).
        T_world_cam: np.ndarray,  # [N, 4, 4] metric poses (world = table-tag frame) of the same N frames
        valid: np.ndarray | None,  # [N] bool, usable metric poses (default all)
        max_residual_m: refuse alignments whose RMS centre residual exceeds this.
    Returns:
        (the result in the world frame, :class:`Sim3` with residuals). A ``known_poses`` result is returned
        unchanged with the identity (its frame is already metric).
    Raises:
        ReconError: fewer than 3 usable correspondences, degenerate scale (metric cameras spread less than
            ``MIN_ALIGN_SPREAD_M`` or collinear), residual above ``max_residual_m``.
    """
    T = np.asarray(T_world_cam, dtype=np.float64)
    if T.shape != (len(sfm.names), 4, 4):
        raise ReconError(f"align_sfm_to_poses: T_world_cam {T.shape} for {len(sfm.names)} SfM frames")
    ok = sfm.registered & (np.ones(len(T), bool) if valid is None else np.asarray(valid, bool))
    if sfm.mode == "known_poses":
        return sfm, Sim3(1.0, np.eye(3), np.zeros(3), 0.0, 0.0, int(ok.sum()))
    if ok.sum() < 3:
        raise ReconError(f"Sim(3) alignment: only {int(ok.sum())} frames are both registered by SfM and tracked "
                         f"by SLAM (need >= 3); re-run SLAM on the scan or use more frames")
    dst = T[ok, :3, 3]
    spread = float(np.sqrt(np.mean(np.sum((dst - dst.mean(0)) ** 2, axis=1))))
    if spread < C.MIN_ALIGN_SPREAD_M:
        raise ReconError(f"Sim(3) alignment: the metric camera centres spread only {spread * 1000:.1f} mm "
                         f"(< {C.MIN_ALIGN_SPREAD_M * 1000:.0f} mm): scale is degenerate; scan while moving the "
                         f"camera over a wider path")
    s, R, t = umeyama(sfm.T_world_cam[ok, :3, 3], dst)
    if not (np.isfinite(s) and s > 1e-9):
        raise ReconError(f"Sim(3) alignment: degenerate scale {s!r}; the SfM cameras do not follow the SLAM path")
    aligned = sfm.transformed(s, R, t)
    res = np.linalg.norm(aligned.T_world_cam[ok, :3, 3] - dst, axis=1)
    rms = float(np.sqrt(np.mean(res ** 2)))
    Rrel = np.einsum("nji,njk->nik", aligned.T_world_cam[ok, :3, :3], T[ok, :3, :3])
    ang = np.arccos(np.clip((np.trace(Rrel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
    sim = Sim3(s, R, t, rms, float(ang.mean()), int(ok.sum()))
    if rms > max_residual_m:
        raise ReconError(f"Sim(3) alignment residual {rms * 1000:.1f} mm > {max_residual_m * 1000:.0f} mm over "
                         f"{int(ok.sum())} frames: SfM and SLAM disagree (wrong intrinsics, a mis-registered "
                         f"frame, or poses of another session); check the scan or use mode 'known_poses'")
    return aligned, sim
