"""Dataset episodes that are UMI's tracked segments of the demo videos (06_generate_dataset_plan): lost CSV rows
dropped, several episodes per video, videos without one. The session reader crops each demo to its episode, from
``dataset_plan.pkl`` or by matching ``robot0_eef_pos`` with the CSV's TCP poses. Tiny hand-built session (no
MuJoCo, under a second per test)."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

W, H, FPS, S = 64, 48, 30.0, 32
#: demo name → (video frames, lost frames)
DEMOS = {"demo_a": (40, [0, 1, 2, 18, 19, 20, 37, 38, 39]), "demo_b": (30, [0, 1]), "demo_c": (12, [])}
#: episodes (demo, first frame, end frame): two tracked segments of demo_a, a cut segment of demo_b; demo_c has none
EPISODES = [("demo_a", 3, 18), ("demo_a", 21, 37), ("demo_b", 2, 28)]


def _poses(n: int, seed: int) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    t = np.arange(n) / n
    T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    rv = np.stack([0.3 * t, 0.2 * np.sin(3 * t + seed), 0.1 * t + seed], 1)
    T[:, :3, :3] = Rotation.from_rotvec(rv).as_matrix()
    T[:, :3, 3] = np.stack([0.2 * t + 0.1 * seed, 0.05 * np.cos(4 * t), 0.3 + 0.1 * t], 1)
    return T


def _video(path, n: int, base: int) -> None:
    from umi_aug.data.video import VideoWriter

    path.parent.mkdir(parents=True, exist_ok=True)
    with VideoWriter(path, W, H, FPS) as vw:
        for i in range(n):
            vw.write(np.full((H, W, 3), base + 4 * i, np.uint8))  # frame i is flat grey base + 4 i


def _csv(path, T: np.ndarray, lost) -> None:
    from umi_aug.data.trajectory_csv import CameraTrajectory, write_camera_trajectory_csv

    n = len(T)
    is_lost = np.zeros(n, bool)
    is_lost[list(lost)] = True
    T = T.copy()
    T[is_lost] = 0.0
    write_camera_trajectory_csv(path, CameraTrajectory(
        frame_idx=np.arange(n), timestamp=np.arange(n) / FPS, state=np.where(is_lost, 3, 2), is_lost=is_lost,
        is_keyframe=np.zeros(n, bool), T_world_cam=T))


def _build(root, plan: bool | list = False, pos_shift: dict[int, float] | None = None):
    """The session: tag frame ≠ SLAM frame (tx_slam_tag), dataset episodes = EPISODES with UMI's TCP poses."""
    from umi_aug.camera.calib_io import gopro_intrinsics_2_7k, save_umi_intrinsics_json
    from umi_aug.data import ReplayBuffer, make_umi_episode
    from umi_aug.geometry.umi import umi_T_cam_tcp

    tx_slam_tag = np.eye(4)
    tx_slam_tag[:3, 3] = [0.1, -0.2, 0.05]
    _video(root / "demos" / "mapping" / "raw_video.mp4", 6, 0)
    _csv(root / "demos" / "mapping" / "mapping_camera_trajectory.csv", _poses(6, 9), [])
    (root / "demos" / "mapping" / "tx_slam_tag.json").write_text(json.dumps({"tx_slam_tag": tx_slam_tag.tolist()}))
    slam = {}
    for k, (name, (n, lost)) in enumerate(DEMOS.items()):
        slam[name] = _poses(n, k)
        _video(root / "demos" / name / "raw_video.mp4", n, 40 * k)
        _csv(root / "demos" / name / "camera_trajectory.csv", slam[name], lost)
    (root / "calibration").mkdir(parents=True, exist_ok=True)
    save_umi_intrinsics_json(gopro_intrinsics_2_7k().scaled(W, H),
                             root / "calibration" / f"gopro_intrinsics_{W}x{H}.json")
    buf = ReplayBuffer.create()
    rng = np.random.default_rng(0)
    widths = []
    for e, (name, s, t) in enumerate(EPISODES):
        T_tag_tcp = np.linalg.inv(tx_slam_tag) @ slam[name][s:t] @ umi_T_cam_tcp()
        T_tag_tcp[:, 0, 3] += (pos_shift or {}).get(e, 0.0)
        widths.append(rng.uniform(0.0, 0.08, t - s))
        buf.add_episode(make_umi_episode(T_tag_tcp, widths[-1], {0: np.zeros((t - s, S, S, 3), np.uint8)}))
    buf.save(root / "dataset.zarr.zip")
    if plan:
        segs = EPISODES if plan is True else plan
        items = [{"episode_timestamps": np.arange(s, t) / FPS, "grippers": [],
                  "cameras": [{"video_path": f"{name}/raw_video.mp4", "video_start_end": (s, t)}]}
                 for name, s, t in segs]
        (root / "dataset_plan.pkl").write_bytes(pickle.dumps(items))
    return root, slam, tx_slam_tag, widths


def _check_cropped(sess, slam, tx_slam_tag, widths) -> None:
    assert [d.name for d in sess.demos] == ["demo_a_000003", "demo_a_000021", "demo_b"]
    for d, (name, s, t), w in zip(sess.demos, EPISODES, widths):
        assert (d.n_frames, d.frame_offset) == (t - s, s) and d.valid.all()
        assert np.allclose(d.T_world_cam, np.linalg.inv(tx_slam_tag) @ slam[name][s:t], atol=1e-9)
        assert np.allclose(d.timestamp, np.arange(s, t) / FPS)
        assert np.array_equal(d.gripper_width, w.astype(np.float32))  # stored float32
        # frame k of the cropped demo is video frame s + k
        base = 40 * list(DEMOS).index(name)
        frames = d.read_frames([0, t - s - 1])
        assert abs(float(frames[0].mean()) - (base + 4 * s)) < 3
        assert abs(float(frames[1].mean()) - (base + 4 * (t - 1))) < 3


def test_episodes_matched_by_tcp_poses(tmp_path):
    from umi_aug.recon.session_io import load_session

    root, slam, tag, widths = _build(tmp_path / "s")
    _check_cropped(load_session(root), slam, tag, widths)


def test_episodes_from_dataset_plan(tmp_path):
    from umi_aug.recon.session_io import load_session

    root, slam, tag, widths = _build(tmp_path / "s", plan=True)
    _check_cropped(load_session(root), slam, tag, widths)


def test_plan_disagreeing_with_the_session_names_the_episode(tmp_path):
    from umi_aug.errors import ReconError
    from umi_aug.recon.session_io import load_session

    root, *_ = _build(tmp_path / "s", plan=[("demo_a", 3, 18), ("demo_a", 21, 37), ("demo_b", 3, 29)])
    with pytest.raises(ReconError, match=r"dataset_plan.pkl: episode 2 \(cameras\[0\] = demo_b/raw_video.mp4, "
                                         r"video_start_end = \(3, 29\)\): the dataset's robot0_eef_pos/rot differ "
                                         r"from the TCP of camera_trajectory.csv by up to 0.0\d+ m"):
        load_session(root)
    root, *_ = _build(tmp_path / "t", plan=[("demo_a", 3, 18), ("demo_a", 20, 36), ("demo_b", 2, 28)])
    with pytest.raises(ReconError, match=r"episode 1 .*: frame 20 is lost in .*demo_a/camera_trajectory.csv"):
        load_session(root)


def test_unmatched_episode_is_named_with_the_tolerance(tmp_path):
    from umi_aug.errors import ReconError
    from umi_aug.recon.session_io import SEGMENT_POS_TOL_M, load_session

    root, *_ = _build(tmp_path / "s", pos_shift={1: 0.005})  # episode 1's TCP 5 mm off
    with pytest.raises(ReconError) as e:
        load_session(root)
    msg = str(e.value)
    assert "dataset.zarr.zip: episode 1 (16 steps) matches no tracked segment of the demo videos (demo_a, demo_b, " \
           "demo_c)" in msg
    assert f"within {SEGMENT_POS_TOL_M} m on every frame; nearest tracked start: demo_a frame 21 at 0.0050 m" in msg
    # a shift below the tolerance still matches
    root, slam, tag, widths = _build(tmp_path / "t", pos_shift={1: 0.5 * SEGMENT_POS_TOL_M})
    _check_cropped(load_session(root), slam, tag, widths)


def test_augment_preflight_accepts_segments_and_reports_mismatch(tmp_path):
    from umi_aug.augment.preflight import check_session_inputs
    from umi_aug.errors import AugmentError

    root, *_ = _build(tmp_path / "s")
    assert check_session_inputs(root).n_episodes == 3
    root, *_ = _build(tmp_path / "t", pos_shift={0: 0.01})
    with pytest.raises(AugmentError, match=r"episode 0 \(15 steps\) matches no tracked segment"):
        check_session_inputs(root)


def test_tags_inpainted_as_umi_does(tmp_path):
    """UMI's tag_detection.pkl next to a video: decoded frames (any size, cropped demos included) get the detected
    tags covered with the median border colour of the 1.4x grown quad; frames without a detection are as stored."""
    from umi_aug.data.video import VideoWriter, inpaint_tag
    from umi_aug.recon.session_io import load_session

    root, *_ = _build(tmp_path / "s")
    n = DEMOS["demo_b"][0]
    quad = np.array([[26, 18], [38, 18], [38, 30], [26, 30]], np.float64)  # a 12 px dark "tag" at the centre
    with VideoWriter(root / "demos" / "demo_b" / "raw_video.mp4", W, H, FPS) as vw:
        for _ in range(n):
            img = np.full((H, W, 3), 150, np.uint8)
            img[18:30, 26:38] = 10
            vw.write(img)
    detections = [{"frame_idx": i, "time": i / FPS, "tag_dict": {} if i == 3 else {13: {"corners": quad[None]}}}
                  for i in range(n)]
    (root / "demos" / "demo_b" / "tag_detection.pkl").write_bytes(pickle.dumps(detections))
    d = load_session(root).demos[2]  # demo_b from video frame 2
    assert d.frame_offset == 2 and d.tag_corners is not None
    full = d.read_frames([0, 1])  # video frames 2 (tag detected) and 3 (none)
    assert abs(float(full[0, 18:30, 26:38].mean()) - 150) < 4  # covered with the surrounding grey
    assert float(full[1, 20:28, 28:36].mean()) < 40  # no detection: as stored
    small = d.read_frames([0, 1], size=(32, 24))  # centre crop 64 → 64x48 ... scaled: the tag moves with it
    assert abs(float(small[0, 9:15, 13:19].mean()) - 150) < 6 and float(small[1, 10:14, 14:18].mean()) < 50
    # the fill rule: median of the grown quad's border samples, quad grown 1.4x about its centre
    img = np.full((40, 40, 3), 200, np.uint8)
    img[15:26, 15:26] = 0  # the tag
    img[13, 13:19] = 90  # a few of the border's 16 samples darker: the median ignores them
    out = inpaint_tag(img.copy(), np.array([[15, 15], [25, 15], [25, 25], [15, 25]]))
    assert (out[13:28, 13:28] == 200).all()  # the 1.4x grown quad (side 14 px about the centre) filled
    keep = np.ones((40, 40), bool)
    keep[12:29, 12:29] = False
    assert (out[keep] == img[keep]).all()  # nothing outside it changed
