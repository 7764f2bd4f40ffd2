import numpy as np
import pytest

pytest.importorskip("open3d")

from umi_aug.errors import ReconError
from umi_aug.recon.cloud import clean_cloud, read_ply, write_ply


def test_clean_removes_outliers_orients_normals_and_roundtrips(tmp_path):
    rng = np.random.default_rng(0)
    P = np.column_stack([rng.uniform(-0.2, 0.2, (4000, 2)), rng.normal(scale=0.0005, size=4000)])
    out = rng.uniform(-0.5, 0.5, (10, 3)) + np.array([0, 0, 0.8])  # floating outliers
    pts = np.concatenate([P, out])
    view = np.tile([0.1, 0.0, 1.0], (len(pts), 1))
    c = clean_cloud(pts, None, view / np.linalg.norm(view, axis=1, keepdims=True), voxel_m=0.005)
    assert np.all(c.points[:, 2] < 0.01)  # outliers gone
    assert np.mean(c.normals[:, 2] > 0.9) > 0.98  # oriented towards the cameras
    p = write_ply(tmp_path / "c.ply", c)
    back = read_ply(p)
    np.testing.assert_allclose(back.points, c.points, atol=1e-6)
    np.testing.assert_array_equal(back.colors, c.colors)
    assert not list(tmp_path.glob("*.tmp-*"))


def test_empty_or_tiny_cloud_raises(tmp_path):
    with pytest.raises(ReconError, match="points"):
        clean_cloud(np.zeros((0, 3)))
    with pytest.raises(ReconError, match="points"):
        clean_cloud(np.random.default_rng(0).normal(size=(20, 3)))
    (tmp_path / "x.ply").write_bytes(b"not a ply")
    with pytest.raises(ReconError):
        read_ply(tmp_path / "x.ply")
