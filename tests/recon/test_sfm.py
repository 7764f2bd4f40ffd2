"""SfM helpers (pixel convention, pairs, masks) and failure cases; the session-based runs are in test_pipeline.py."""

import cv2
import numpy as np
import pytest

from umi_aug.camera import gopro_intrinsics_2_7k, project
from umi_aug.errors import ReconError
from umi_aug.recon.sfm import SfmConfig, colmap_camera_params, feature_mask, pose_pairs, run_sfm, video_pairs

INTR = gopro_intrinsics_2_7k().scaled(320, 240)


def test_colmap_pixel_convention_matches_kb_project():
    pycolmap = pytest.importorskip("pycolmap")
    cam = pycolmap.Camera(model="OPENCV_FISHEYE", width=INTR.width, height=INTR.height,
                          params=colmap_camera_params(INTR))
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(200, 3)) + np.array([0, 0, 2.0])
    pts = pts[np.arctan2(np.linalg.norm(pts[:, :2], axis=1), pts[:, 2]) < np.radians(80)]
    uv, ok = project(pts, INTR)
    uv_c = np.asarray(cam.img_from_cam(pts))
    np.testing.assert_allclose(uv_c[ok] - 0.5, uv[ok], atol=1e-6)


def test_video_and_pose_pairs():
    p = video_pairs([10, 5], overlap=2, loop_stride=5)
    s = {tuple(x) for x in p.tolist()}
    assert (0, 1) in s and (0, 2) in s and (0, 3) not in s
    assert (9, 10) not in s  # no sequential pair across videos
    assert (0, 10) in s and (5, 10) in s  # loop grid spans videos
    assert np.all(p[:, 0] < p[:, 1]) and len(s) == len(p)
    T = np.tile(np.eye(4), (4, 1, 1))
    T[:, 0, 3] = [0.0, 0.1, 0.2, 1.0]
    pp = pose_pairs(T, np.array([True, True, True, True]), 0.15, 30)
    assert {tuple(x) for x in pp.tolist()} == {(0, 1), (1, 2)}


def test_feature_mask():
    m = feature_mask(INTR)
    assert m.shape == (240, 320) and m.dtype == np.uint8
    assert m[0, 0] == 0 and m[239, 160] == 0 and m[100, 160] == 255  # outside circle / gripper / scene
    with pytest.raises(ReconError, match="does not match"):
        feature_mask(INTR, np.zeros((10, 10), bool))


def test_frames_of_another_size_than_the_intrinsics(tmp_path):
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"{i:06d}.png"), np.zeros((80, 100, 3), np.uint8))
    paths = sorted(tmp_path.glob("*.png"))
    with pytest.raises(ReconError, match="100x80 but the intrinsics are 320x240"):
        run_sfm(paths, [f"s/{p.name}" for p in paths], INTR, tmp_path / "w")


def test_sfm_registering_too_few_frames_raises(tmp_path):
    pytest.importorskip("pycolmap")
    rng = np.random.default_rng(0)
    d = tmp_path / "img"
    d.mkdir()
    for i in range(6):  # unrelated noise frames: nothing to match
        img = cv2.GaussianBlur(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8), (3, 3), 0)
        cv2.imwrite(str(d / f"{i:06d}.png"), img)
    paths = sorted(d.glob("*.png"))
    with pytest.raises(ReconError, match="(no model|registered)"):
        run_sfm(paths, [f"s/{p.name}" for p in paths], INTR, tmp_path / "w", SfmConfig(max_num_features=500))
    with pytest.raises(ReconError, match="known_poses' needs T_world_cam"):
        run_sfm(paths, [f"s/{p.name}" for p in paths], INTR, tmp_path / "w2", SfmConfig(mode="known_poses"))
