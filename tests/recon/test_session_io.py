"""The session reader on hand-made sessions in UMI's real layout (raw_video.mp4 + camera_trajectory.csv, lost
rows, tx_slam_tag, UMI's 2.7K calibration only), the old images/ layout, and one clear ReconError per bad input."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from umi_aug.errors import ReconError

pytest.importorskip("imageio_ffmpeg")

W, H = 96, 72  # 4:3 like the GoPro's 2704x2028
FPS = 59.94
N_MAP, N_DEMO = 12, 9
LOST = [3, 4]  # tracking lost in the demo


def _frame(i: int) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    img = np.stack([128 + 90 * np.sin(xx / 6.0 + i), 128 + 90 * np.cos(yy / 4.0), 128 + 0 * xx], -1)
    img[H // 3 : 2 * H // 3, W // 3 : 2 * W // 3] = 12 * i + 6  # grey level encodes the frame index
    return np.clip(img, 0, 255).astype(np.uint8)


def _index_of(img: np.ndarray) -> int:
    h, w = img.shape[:2]
    return int(round((float(img[h // 2 - 1 : h // 2 + 1, w // 2 - 1 : w // 2 + 1].mean()) - 6) / 12))


def _poses(n: int, x0: float) -> np.ndarray:
    T = np.repeat(np.eye(4)[None], n, 0)
    T[:, 0, 3] = x0 + 0.01 * np.arange(n)
    T[:, 2, 3] = 0.5
    return T


def _csv(path, n, lost=(), fps=FPS, T=None):
    from umi_aug.data import CameraTrajectory, write_camera_trajectory_csv

    is_lost = np.zeros(n, bool)
    is_lost[list(lost)] = True
    fi = np.arange(n)
    write_camera_trajectory_csv(path, CameraTrajectory(fi, fi / fps, np.where(is_lost, 3, 2), is_lost,
                                                       fi % 5 == 0, _poses(n, 0.0) if T is None else T))


TX_SLAM_TAG = np.array([[0.0, -1, 0, 0.1], [1, 0, 0, 0.2], [0, 0, 1, -0.05], [0, 0, 0, 1]])


@pytest.fixture()
def session(tmp_path):
    """UMI's real layout: videos only, UMI's 2.7K calibration JSON, a demo with two SLAM-lost frames."""
    from umi_aug.camera.calib_io import gopro_intrinsics_2_7k, save_umi_intrinsics_json
    from umi_aug.data.video import VideoWriter

    root = tmp_path / "session"
    (root / "calibration").mkdir(parents=True)
    save_umi_intrinsics_json(gopro_intrinsics_2_7k(), root / "calibration" / "gopro_intrinsics_2_7k.json")
    for name, n, csv, lost in (("mapping", N_MAP, "mapping_camera_trajectory.csv", ()),
                               ("demo_C3441328164125_2024.01.10_10.57.34.882633", N_DEMO, "camera_trajectory.csv",
                                LOST)):
        d = root / "demos" / name
        d.mkdir(parents=True)
        with VideoWriter(d / "raw_video.mp4", W, H, FPS) as wr:
            for i in range(n):
                wr.write(_frame(i))
        _csv(d / csv, n, lost)
    (root / "demos" / "mapping" / "tx_slam_tag.json").write_text(json.dumps({"tx_slam_tag": TX_SLAM_TAG.tolist()}))
    return root


def test_real_layout(session, tmp_path):
    from umi_aug.camera.calib_io import gopro_intrinsics_2_7k
    from umi_aug.recon.session_io import load_session, write_frames

    s = load_session(session)
    assert (s.intrinsics.width, s.intrinsics.height) == (W, H)
    assert s.intrinsics == gopro_intrinsics_2_7k().scaled(W, H)  # the 2.7K JSON, scaled UMI's way
    m, d = s.mapping, s.demos[0]
    assert (len(m), len(d), m.frame_size, m.image_paths) == (N_MAP, N_DEMO, (W, H), None)
    assert abs(m.fps - FPS) < 0.01
    # lost rows: invalid, identity pose; tracked rows: inv(tx_slam_tag) @ T_slam_cam
    assert d.valid.tolist() == [i not in LOST for i in range(N_DEMO)]
    np.testing.assert_allclose(d.T_world_cam[0], np.linalg.inv(TX_SLAM_TAG) @ _poses(1, 0.0)[0], atol=1e-12)
    np.testing.assert_allclose(d.timestamp, np.arange(N_DEMO) / FPS)
    # frames by index, at the stored size and reduced (intrinsics_at ↔ read_frames size)
    idx = [0, 2, 5, 8]
    f = d.read_frames(idx)
    assert f.shape == (4, H, W, 3) and [_index_of(x) for x in f] == idx
    intr, size = s.intrinsics_at(48)
    assert size == (48, 36) and intr == s.intrinsics.scaled(48, 36)
    assert [_index_of(x) for x in d.read_frames(idx, size)] == idx
    assert s.intrinsics_at(None) == (s.intrinsics, None) and s.intrinsics_at(4000)[1] is None
    paths = write_frames(m, [1, 7], tmp_path / "frames", size)
    assert [p.name for p in paths] == ["000001.png", "000007.png"]
    assert [_index_of(cv2.imread(str(p))[..., ::-1]) for p in paths] == [1, 7]
    with pytest.raises(ReconError, match="increasing within"):
        d.read_frames([N_DEMO])


def test_old_images_layout_still_read(session):
    from umi_aug.recon.session_io import load_session

    for seq in ("mapping", "demo_C3441328164125_2024.01.10_10.57.34.882633"):
        d = session / "demos" / seq
        n = N_MAP if seq == "mapping" else N_DEMO
        (d / "images").mkdir()
        for i in range(n):
            cv2.imwrite(str(d / "images" / f"{i:06d}.png"), _frame(i)[..., ::-1])
        (d / "raw_video.mp4").unlink()
    s = load_session(session)
    assert s.mapping.image_paths is not None and len(s.mapping) == N_MAP
    np.testing.assert_array_equal(s.mapping.read_frames([3])[0], _frame(3))
    assert s.demos[0].valid.tolist() == [i not in LOST for i in range(N_DEMO)]


def _demo(root):
    return next(p for p in (root / "demos").iterdir() if p.name.startswith("demo"))


def test_bad_inputs_name_the_file(session):
    from umi_aug.recon.session_io import load_session

    demo = _demo(session)
    csv = demo / "camera_trajectory.csv"
    good = csv.read_text()
    # CSV of another length than the video
    lines = good.splitlines()
    csv.write_text("\n".join(lines[:-2]) + "\n")
    with pytest.raises(ReconError, match=r"camera_trajectory.csv: 7 rows but .*raw_video.mp4 has 9 frames"):
        load_session(session)
    # non-monotonic timestamps
    f = lines[4].split(",")
    f[1] = "0.001"
    csv.write_text("\n".join(lines[:4] + [",".join(f)] + lines[5:]) + "\n")
    with pytest.raises(ReconError, match=r"camera_trajectory.csv.*line 5.*timestamps must increase"):
        load_session(session)
    # timestamps of another frame rate (a CSV of another video)
    _csv(csv, N_DEMO, fps=30.0)
    with pytest.raises(ReconError, match=r"camera_trajectory.csv: line \d+: timestamp .* does not match frame"):
        load_session(session)
    # frame_idx not 0..n-1
    _csv(csv, N_DEMO + 1)
    text = csv.read_text().splitlines()
    csv.write_text("\n".join(text[:1] + text[2:]) + "\n")  # rows for frames 1..9
    with pytest.raises(ReconError, match=r"row 1 \(line 2\) has frame_idx 1, expected 0"):
        load_session(session)
    csv.write_text(good)
    load_session(session)
    # corrupt video
    video = demo / "raw_video.mp4"
    data = video.read_bytes()
    video.write_bytes(data[: len(data) // 3])
    with pytest.raises(ReconError, match=r"raw_video.mp4"):
        s = load_session(session)
        s.demos[0].read_frames(range(N_DEMO))
    video.write_bytes(b"\x00" * 100)
    with pytest.raises(ReconError, match=r"raw_video.mp4: not a readable video"):
        load_session(session)
    # missing mapping video
    video.write_bytes(data)
    (session / "demos" / "mapping" / "raw_video.mp4").unlink()
    with pytest.raises(ReconError, match=r"demos/mapping: no raw_video.mp4.*make-session"):
        load_session(session)


def test_intrinsics_lookup_errors(session):
    from umi_aug.camera.calib_io import gopro_intrinsics_2_7k
    from umi_aug.recon.session_io import load_session

    shutil.rmtree(session / "calibration")
    with pytest.raises(ReconError, match=rf"no fisheye calibration for the {W}x{H} frames"):
        load_session(session)
    with pytest.raises(ReconError, match=f"frames are {W}x{H} but the intrinsics are 2704x2028"):
        load_session(session, intrinsics=gopro_intrinsics_2_7k())
    assert load_session(session, intrinsics=gopro_intrinsics_2_7k().scaled(W, H)).intrinsics.width == W
