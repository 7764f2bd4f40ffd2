"""make-session: UMI layout, valid zarr, CSVs consistent with ground truth, same seed → same bytes."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

SMALL = dict(width=160, height=120, n_demos=1, scan_frames=10, fps=15.0, scan_fps=5.0, policy_size=64,
             benchmark_frames=2, progress=False)


def _digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def two_sessions(tmp_path_factory):
    from umi_aug.sim.gl import select_gl_backend
    from umi_aug.sim.session import make_session

    select_gl_backend()
    root = tmp_path_factory.mktemp("sessions")
    a = make_session(root / "a", seed=5, **SMALL)
    b = make_session(root / "b", seed=5, **SMALL)
    return root / "a", root / "b", a


@pytest.mark.slow
def test_session_layout_and_validator(two_sessions, gl):
    from umi_aug.camera.calib_io import load_umi_intrinsics_json
    from umi_aug.data import validate_replay_buffer

    a, _, summary = two_sessions
    demo = a / "demos" / "demo_sim5_00"
    for rel in ("demos/mapping/mapping_camera_trajectory.csv", "demos/mapping/tx_slam_tag.json",
                "demos/mapping/raw_video.mp4",
                "demos/demo_sim5_00/camera_trajectory.csv", "demos/demo_sim5_00/raw_video.mp4",
                "calibration/gopro_intrinsics_2_7k.json", "calibration/gopro_intrinsics_160x120.json",
                "dataset.zarr.zip", "contact_sheet.png", "session.json",
                "ground_truth/scene/scene.xml", "ground_truth/scene/layout.json",
                "ground_truth/scene/scene_points.ply", "ground_truth/demo_sim5_00/frames.zarr.zip",
                "ground_truth/demo_sim5_00/events.json",
                "ground_truth/demo_sim5_00/trajectory.npz"):
        assert (a / rel).is_file(), rel
    n = summary["sequences"]["demo_sim5_00"]["frames"]
    assert not list(a.glob("demos/*/images"))  # UMI's real layout: the videos are the only frames
    from umi_aug.data.video import probe_video

    info = probe_video(demo / "raw_video.mp4")
    assert (info.width, info.height, info.n_frames) == (160, 120, n) and abs(info.fps - 15.0) < 0.01
    assert probe_video(a / "demos" / "mapping" / "raw_video.mp4").n_frames == 10
    rep = validate_replay_buffer(a / "dataset.zarr.zip")
    assert rep.n_episodes == 1 and rep.n_steps == n
    assert rep.keys["camera0_rgb"].shape == (n, 64, 64, 3)
    intr = load_umi_intrinsics_json(a / "calibration" / "gopro_intrinsics_160x120.json")
    assert (intr.width, intr.height) == (160, 120)
    info = json.loads((a / "session.json").read_text())
    bench = info["timings"]["benchmark_224"]
    assert bench["resolution"] == "224x224" and "render/front" in bench["breakdown_ms"]
    assert not list(a.parent.glob("a.tmp-*"))  # atomic: no temporaries left


@pytest.mark.slow
def test_session_poses_consistent(two_sessions, gl):
    from umi_aug.data import ReplayBuffer, read_camera_trajectory_csv
    from umi_aug.geometry.umi import umi_T_cam_tcp

    a, _, summary = two_sessions
    demo = a / "demos" / "demo_sim5_00"
    gt = np.load(a / "ground_truth" / "demo_sim5_00" / "trajectory.npz")
    traj = read_camera_trajectory_csv(demo / "camera_trajectory.csv")
    np.testing.assert_allclose(traj.T_world_cam, gt["T_world_cam"], atol=1e-9)
    np.testing.assert_allclose(traj.timestamp, np.arange(len(traj)) / 15.0)
    assert not traj.is_lost.any()
    with ReplayBuffer.open(a / "dataset.zarr.zip") as buf:
        pos = buf["robot0_eef_pos"][:]
        width = buf["robot0_gripper_width"][:, 0]
        img = buf["camera0_rgb"][0]
    T_tcp = gt["T_world_cam"] @ umi_T_cam_tcp()
    np.testing.assert_allclose(pos, T_tcp[:, :3, 3], atol=1e-6)
    np.testing.assert_allclose(width, gt["gripper_width"], atol=1e-6)
    assert img[-1, :8].max() < 30  # UMI's gripper mask is painted black into the policy images
    ev = json.loads((a / "ground_truth" / "demo_sim5_00" / "events.json").read_text())
    assert ev["contact_frame"] == summary["demo_events"]["demo_sim5_00"]["contact"]
    layout = json.loads((a / "ground_truth" / "scene" / "layout.json").read_text())
    np.testing.assert_allclose(T_tcp[ev["contact_frame"] - 1], np.array(layout["T_world_grasp"]), atol=1e-9)


@pytest.mark.slow
def test_session_ground_truth_depth_and_mask(two_sessions, gl):
    from umi_aug.camera import kb
    from umi_aug.camera.calib_io import load_umi_intrinsics_json
    from umi_aug.sim.session import load_gripper_mask, load_ray_depth

    a, _, _ = two_sessions
    intr = load_umi_intrinsics_json(a / "calibration" / "gopro_intrinsics_160x120.json")
    depth = load_ray_depth(a / "ground_truth" / "mapping")
    mask = load_gripper_mask(a / "ground_truth" / "mapping" / "frames.zarr.zip")
    gt = np.load(a / "ground_truth" / "mapping" / "trajectory.npz")
    assert depth.shape == mask.shape == (10, 120, 160)
    vv, uu = np.mgrid[0:120, 0:160]
    rays, valid = kb.unproject(np.stack([uu, vv], -1).astype(float), intr)
    assert 0.03 < mask.mean() < 0.4 and (depth[:, valid] > 0).mean() > 0.99 and (depth[:, ~valid] == 0).all()
    # table pixels (rays hitting z = 0 inside the table top, away from objects) back-project onto z = 0
    T = gt["T_world_cam"][0]
    pts = T[:3, 3] + (rays * depth[0][..., None]) @ T[:3, :3].T
    sel = valid & (depth[0] > 0) & ~mask[0] & (np.abs(pts[..., 0]) < 0.55) & (pts[..., 1] > -0.15) \
        & (pts[..., 1] < 0.55) & (np.abs(pts[..., 2]) < 0.01)
    assert sel.sum() > 500
    assert np.median(np.abs(pts[..., 2][sel])) < 1e-3


@pytest.mark.slow
def test_same_seed_same_bytes(two_sessions, gl):
    import zarr

    from umi_aug.data import register_codecs

    a, b, _ = two_sessions
    for rel in ("demos/mapping/mapping_camera_trajectory.csv", "demos/demo_sim5_00/camera_trajectory.csv",
                "calibration/gopro_intrinsics_160x120.json", "ground_truth/scene/scene.xml",
                "ground_truth/scene/layout.json", "ground_truth/scene/scene_points.ply",
                "demos/demo_sim5_00/raw_video.mp4", "demos/mapping/raw_video.mp4",
                "ground_truth/demo_sim5_00/trajectory.npz", "contact_sheet.png"):
        assert _digest(a / rel) == _digest(b / rel), rel
    register_codecs()
    za = zarr.open_group(zarr.ZipStore(str(a / "dataset.zarr.zip"), mode="r"), mode="r")
    zb = zarr.open_group(zarr.ZipStore(str(b / "dataset.zarr.zip"), mode="r"), mode="r")
    keys = sorted(za["data"].array_keys())
    assert keys == sorted(zb["data"].array_keys())
    for k in keys:
        ca = [za["data"][k].store[p] for p in sorted(za["data"][k].store) if p.startswith(f"data/{k}/")]
        cb = [zb["data"][k].store[p] for p in sorted(zb["data"][k].store) if p.startswith(f"data/{k}/")]
        assert ca == cb, k  # identical encoded chunks (JPEG XL bytes included)
    np.testing.assert_array_equal(za["meta"]["episode_ends"][:], zb["meta"]["episode_ends"][:])
    from umi_aug.sim.session import load_gripper_mask, load_ray_depth

    for seq in ("mapping", "demo_sim5_00"):
        np.testing.assert_array_equal(load_ray_depth(a / "ground_truth" / seq), load_ray_depth(b / "ground_truth" / seq))
        np.testing.assert_array_equal(load_gripper_mask(a / "ground_truth" / seq),
                                      load_gripper_mask(b / "ground_truth" / seq))


def test_refuses_to_overwrite(tmp_path, gl):
    from umi_aug.errors import SimError
    from umi_aug.sim.session import make_session

    (tmp_path / "x.txt").write_text("keep")
    with pytest.raises(SimError, match="not empty"):
        make_session(tmp_path, seed=0, **SMALL)
    assert (tmp_path / "x.txt").read_text() == "keep"


@pytest.mark.slow
def test_session_video_read_back(two_sessions, gl):
    """The session reader decodes the videos; the frames match the zarr's policy images (made from the renders)."""
    from umi_aug.camera.umi_image import umi_policy_image
    from umi_aug.data import ReplayBuffer
    from umi_aug.recon.session_io import load_session

    a, _, summary = two_sessions
    s = load_session(a)
    d = s.demos[0]
    n = summary["sequences"]["demo_sim5_00"]["frames"]
    assert (len(s.mapping), len(d), d.frame_size) == (10, n, (160, 120)) and d.valid.all()
    assert d.gripper_width is not None and len(d.gripper_width) == n
    idx = np.arange(0, n, 7)
    frames = d.read_frames(idx)
    with ReplayBuffer.open(a / "dataset.zarr.zip") as buf:
        ref = buf["camera0_rgb"][idx]
    ours = np.stack([umi_policy_image(f, s.intrinsics, 64) for f in frames])
    mse = np.mean((ours.astype(float) - ref.astype(float)) ** 2)
    psnr = 10 * np.log10(255.0 ** 2 / mse)
    assert psnr > 33.0, psnr  # H.264 at crf 8 loses little (the JPEG-95 frames it replaced: ~36 dB at full size)
