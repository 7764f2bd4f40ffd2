"""(d) the camera path fed from a video file made of real UMI frames, through the same OpenCV code."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from umi_aug.camera.masks import predefined_mask
from umi_aug.deploy.camera import CameraConfig, UVCCamera, policy_image

REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "realdata" / "umi_cup_in_the_wild_ep0" / "dataset.zarr.zip"


@pytest.fixture(scope="module")
def real_video(tmp_path_factory):
    if not REAL.exists():
        pytest.skip(f"real UMI data not found at {REAL} (../shared/realdata is outside the repository)")
    from umi_aug.data import ReplayBuffer
    from umi_aug.data.video import VideoWriter

    with ReplayBuffer.open(REAL) as rb:
        frames = np.asarray(rb["camera0_rgb"][:40:2])  # 20 real 224² policy frames
    # a 16:9 capture frame: the real square frame in the middle (upscaled 2x), textured side bands that the
    # centre crop must remove
    n, s = len(frames), 448
    W, H = 800, s
    rng = np.random.default_rng(0)
    out = np.zeros((n, H, W, 3), np.uint8)
    out[:] = rng.integers(0, 255, (1, H, W, 3), dtype=np.uint8)
    x0 = (W - s) // 2
    out[:, :, x0:x0 + s] = np.repeat(np.repeat(frames, 2, axis=1), 2, axis=2)
    path = tmp_path_factory.mktemp("cam") / "capture.mp4"
    with VideoWriter(path, W, H, fps=60.0, crf=12) as vw:
        for f in out:
            vw.write(f)
    return path, frames, out


def _psnr(a, b):
    return 10 * np.log10(255.0 ** 2 / np.mean((a.astype(float) - b.astype(float)) ** 2))


def test_camera_from_real_video(real_video):
    path, frames, raw = real_video
    cam = UVCCamera(CameraConfig(device=str(path), width=800, height=448, fps=60.0, latency=0.17, buffer=64,
                                 realtime=False))
    t_before = time.monotonic()
    cam.start()
    deadline = time.monotonic() + 30
    while not cam.eof and time.monotonic() < deadline:
        time.sleep(0.01)
    got = cam.get_frames(100)
    cam.stop()
    assert len(got["timestamp"]) == len(frames) == cam.n_read
    ts = got["timestamp"]
    assert np.all(np.diff(ts) >= 0) and ts[0] >= t_before - 0.17 and ts[-1] <= time.monotonic() - 0.17
    mask = predefined_mask(224, 224, mirror=False, gripper=True)
    inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)  # AA edge excluded
    assert got["rgb"].shape == (len(frames), 224, 224, 3)
    assert got["rgb"][:, inner].max() == 0  # gripper painted black
    # the same transform applied to the uncompressed capture frames: the decode path loses little
    ref = np.stack([policy_image(f) for f in raw])
    assert _psnr(got["rgb"], ref) > 30
    # and the crop is the real frame (side bands removed): compare outside the mask with the original
    assert _psnr(got["rgb"][:, ~mask], frames[:, ~mask]) > 25
    # a wrong configured size is one clear error
    bad = UVCCamera(CameraConfig(device=str(path), width=1920, height=1080, realtime=False))
    with pytest.raises(Exception, match="frame is 800x448, camera.width/height say 1920x1080"):
        bad.start()


def test_policy_image_geometry():
    img = np.zeros((100, 300, 3), np.uint8)
    img[:, 100:200] = 200  # the centre square
    out = policy_image(img, size=50, mask_gripper=False)
    assert out.shape == (50, 50, 3) and out.min() == 200
    with pytest.raises(Exception, match="W >= H"):
        policy_image(np.zeros((300, 100, 3), np.uint8))
