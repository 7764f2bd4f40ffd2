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


def _sampson_sq_loop(x1, x2, E):
    """Squared Sampson distance, one correspondence at a time (the obviously correct reference)."""
    out = []
    for a, b in zip(x1, x2):
        p, q = np.array([a[0], a[1], 1.0]), np.array([b[0], b[1], 1.0])
        Ep, Etq = E @ p, E.T @ q
        out.append((q @ E @ p) ** 2 / (Ep[0] ** 2 + Ep[1] ** 2 + Etq[0] ** 2 + Etq[1] ** 2))
    return np.array(out)


def _two_views(rng, angle):
    """Points in front of camera 1, camera 2 = ``(R about a random axis by angle, t)`` from camera 1."""
    from umi_aug.geometry import hat, so3_exp

    X = rng.uniform([-1, -1, 1.0], [1, 1, 4.0], (200, 3))
    axis = rng.normal(size=3) * (0.05 if angle > 3.0 else 1.0) + np.array([0.0, 0.0, 1.0])  # near pi: about z
    R = so3_exp(axis / np.linalg.norm(axis) * angle)
    t = rng.normal(size=3) * 0.2
    X2 = X @ R.T + t
    keep = X2[:, 2] > 0.2
    X, X2 = X[keep], X2[keep]
    E = hat(t / np.linalg.norm(t)) @ R
    return X[:, :2] / X[:, 2:], X2[:, :2] / X2[:, 2:], E, R, t


@pytest.mark.parametrize("angle", [0.0, 0.3, np.pi - 1e-6])
def test_epipolar_sampson_equals_the_per_point_reference(rng, angle):
    from umi_aug.recon.sfm import epipolar_sampson_sq

    x1, x2, E, _, _ = _two_views(rng, angle)
    exact = epipolar_sampson_sq(x1, x2, E)
    assert np.all(np.isfinite(exact)) and exact.max() < 1e-20  # the true correspondences lie on their lines
    noisy = x2 + rng.normal(size=x2.shape) * 0.01
    got, want = epipolar_sampson_sq(x1, noisy, E), _sampson_sq_loop(x1, noisy, E)
    # q E p is a sum of O(1) terms: each way of summing it is within ~1e-16 of the other, so its square may
    # differ by ~2e-16 |q E p| (relative error up to 4e-10 at a residual of 7e-7, seen once); a wrong formula
    # is off by the order of the values themselves (median > 1e-7)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-15 * np.sqrt(np.maximum(want, 0.0)).max())
    assert np.median(got) > 1e-7  # 0.01 of noise is seen


def test_known_pose_verification_keeps_the_matches_the_poses_explain(tmp_path, rng):
    """Raw matches in a COLMAP database (true ones and shuffled ones) between three frames of known poses: the
    verification keeps every true match and drops nearly every shuffled one, writes CALIBRATED geometries with the
    poses' relative pose, and leaves a pair without baseline unverified. (A shuffled match survives where it
    happens to fall within 4 px of its epipolar line, as it would in COLMAP's RANSAC: ~1 in 6 at 320x240.)"""
    pc = pytest.importorskip("pycolmap")
    from umi_aug.geometry import so3_exp
    from umi_aug.recon.sfm import verify_with_known_poses

    cam = pc.Camera(model="OPENCV_FISHEYE", width=INTR.width, height=INTR.height, params=colmap_camera_params(INTR))
    T = np.tile(np.eye(4), (3, 1, 1))
    T[1, :3, :3], T[1, :3, 3] = so3_exp(np.array([0.0, 0.2, 0.05])), [0.15, 0.02, 0.01]
    T[2, :3, :3], T[2, :3, 3] = so3_exp(np.array([0.01, 0.0, 0.0])), [0.0, 0.0, 0.0005]  # < 1 mm from frame 0
    X = rng.uniform([-1, -1, 1.5], [1, 1, 3.0], (300, 3))  # world = camera 0's frame
    names = ["s/0.png", "s/1.png", "s/2.png"]
    db = pc.Database.open(str(tmp_path / "db.db"))
    cid = db.write_camera(cam)
    ids = [db.write_image(pc.Image(name=n, camera_id=cid)) for n in names]
    for iid, Tk in zip(ids, T):
        Xc = (X - Tk[:3, 3]) @ Tk[:3, :3]  # camera frame
        db.write_keypoints(iid, np.asarray(cam.img_from_cam(Xc), np.float32))
    n_true = len(X)
    true = np.stack([np.arange(n_true), np.arange(n_true)], 1).astype(np.uint32)
    wrong = np.stack([np.arange(0, n_true, 3), rng.permutation(n_true)[: len(range(0, n_true, 3))]], 1)
    wrong = wrong[wrong[:, 0] != wrong[:, 1]].astype(np.uint32)
    for a, b in ((0, 1), (0, 2)):
        db.write_matches(ids[a], ids[b], np.concatenate([true, wrong]))
    db.close()
    written = verify_with_known_poses(pc, tmp_path / "db.db", names, T, max_error_px=4.0, min_inliers=15)
    assert written == 1
    db = pc.Database.open(str(tmp_path / "db.db"))
    g = db.read_two_view_geometry(ids[0], ids[1])
    assert g.config == pc.TwoViewGeometryConfiguration.CALIBRATED
    inl = {tuple(m) for m in np.asarray(g.inlier_matches).tolist()}
    assert all((i, i) in inl for i in range(n_true))
    assert sum(tuple(m) in inl for m in wrong.tolist()) < 0.3 * len(wrong)
    np.testing.assert_allclose(g.cam2_from_cam1.matrix(), (np.linalg.inv(T[1]) @ T[0])[:3, :4], atol=1e-12)
    assert not db.exists_two_view_geometry(ids[0], ids[2])
    db.close()
    db = pc.Database.open(str(tmp_path / "db.db"))
    db.clear_two_view_geometries()
    db.close()
    untrusted = np.array([True, False, True])  # frame 1's pose not trusted: its pair keeps no geometry
    assert verify_with_known_poses(pc, tmp_path / "db.db", names, T, 4.0, 15, pose_valid=untrusted) == 0
