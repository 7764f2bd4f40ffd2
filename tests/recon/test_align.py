import numpy as np
import pytest

from umi_aug.errors import ReconError
from umi_aug.geometry import so3_exp
from umi_aug.recon.align import align_sfm_to_poses, umeyama
from umi_aug.recon.sfm import SfmResult


def _sfm(T, mode="full"):
    n = len(T)
    return SfmResult([f"m/{i}" for i in range(n)], np.ones(n, bool), T, np.zeros((5, 3)), np.zeros((5, 3), np.uint8),
                     np.zeros(5), np.full(5, 3), np.tile([0, 0, 1.0], (5, 1)), 0.1, np.zeros(0, int), np.zeros(0, int),
                     mode)


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R = so3_exp(np.array([0.3, -0.5, 1.1]))
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 0.5])
    s, R2, t = umeyama(src, dst)
    assert s == pytest.approx(2.5, rel=1e-10)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(t, [1.0, -2.0, 0.5], atol=1e-10)


def test_umeyama_degenerate_inputs_raise():
    with pytest.raises(ReconError, match="N >= 3"):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ReconError, match="zero spread"):
        umeyama(np.ones((5, 3)), np.random.default_rng(0).normal(size=(5, 3)))
    line = np.outer(np.arange(5.0), [1.0, 0.0, 0.0])
    with pytest.raises(ReconError, match="collinear"):
        umeyama(line, line * 2)


def test_align_sfm_to_poses_residual_and_errors():
    rng = np.random.default_rng(1)
    n = 20
    T_gt = np.tile(np.eye(4), (n, 1, 1))
    T_gt[:, :3, 3] = rng.uniform(-0.3, 0.3, (n, 3))
    for i in range(n):
        T_gt[i, :3, :3] = so3_exp(rng.normal(scale=0.3, size=3))
    # SfM frame: x_sfm = (R^T (x - t)) / s
    s, R, t = 0.2, so3_exp(np.array([0.1, 0.2, -0.3])), np.array([0.5, 0.1, 0.0])
    T_sfm = T_gt.copy()
    T_sfm[:, :3, 3] = (T_gt[:, :3, 3] - t) @ R / s
    T_sfm[:, :3, :3] = np.einsum("ji,njk->nik", R, T_gt[:, :3, :3])
    aligned, sim = align_sfm_to_poses(_sfm(T_sfm), T_gt)
    assert sim.s == pytest.approx(s, rel=1e-9)
    assert sim.residual_rms_m < 1e-9 and sim.rotation_residual_rad < 1e-6
    np.testing.assert_allclose(aligned.T_world_cam, T_gt, atol=1e-9)
    # degenerate scale: all metric cameras at (almost) one place
    T_bad = T_gt.copy()
    T_bad[:, :3, 3] = 0.001 * rng.normal(size=(n, 3))
    with pytest.raises(ReconError, match="scale is degenerate"):
        align_sfm_to_poses(_sfm(T_sfm), T_bad)
    # large residual: poses of another trajectory
    T_other = T_gt.copy()
    T_other[:, :3, 3] = rng.uniform(-0.3, 0.3, (n, 3))
    with pytest.raises(ReconError, match="residual"):
        align_sfm_to_poses(_sfm(T_sfm), T_other)
