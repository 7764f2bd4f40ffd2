"""UVC capture card (GoPro HDMI out) through OpenCV, with receive timestamps and UMI's policy-image transform.

A background thread reads frames (``cv2.VideoCapture``: a V4L2 device index/path, or a video file for tests),
stamps each with ``time.monotonic() − latency`` (UMI: ``camera_obs_latency`` 0.17 s subtracted from the receive
time) and keeps the last ``buffer`` transformed images. The transform is UMI's eval-time one (``umi_env``):
full-height centre crop to a square, ``cv2.resize`` INTER_AREA to ``size``², then the predefined polygons drawn
black with anti-aliasing on the small image — the mirrors when ``mask_mirror`` (UMI ``--no_mirror``) and, added
here, the gripper when ``mask_gripper`` (training images have it black: ``umi_policy_image``).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass

import cv2
import numpy as np

from umi_aug.camera.masks import draw_predefined_mask
from umi_aug.data.video import centre_crop
from umi_aug.deploy.safety import SafetyStop
from umi_aug.errors import DeployError

__all__ = ["CameraConfig", "policy_image", "UVCCamera"]

log = logging.getLogger(__name__)


@dataclass
class CameraConfig:
    """The ``camera:`` block of a robot config."""

    device: str = "/dev/video0"  # V4L2 path, device index ("0") or a video file
    width: int = 1920
    height: int = 1080
    fps: float = 60.0
    latency: float = 0.17  # s, subtracted from receive times (UMI's camera_obs_latency)
    size: int = 224
    mask_gripper: bool = True
    mask_mirror: bool = False  # True for policies trained with mirrors masked (UMI's --no_mirror)
    buffer: int = 64
    realtime: bool = True  # for a file source: pace reading at fps (False: as fast as possible)


def policy_image(frame_rgb: np.ndarray, size: int = 224, mask_gripper: bool = True, mask_mirror: bool = False
                 ) -> np.ndarray:
    """[H, W, 3] uint8 RGB camera frame → [size, size, 3] uint8 policy image (centre square, INTER_AREA, masks)."""
    if frame_rgb.ndim != 3 or frame_rgb.shape[2] != 3 or frame_rgb.shape[1] < frame_rgb.shape[0]:
        raise DeployError(f"camera frame must be [H, W, 3] with W >= H, got {frame_rgb.shape}")
    x0, y0, cw, ch = centre_crop(frame_rgb.shape[1], frame_rgb.shape[0], size, size)
    img = cv2.resize(frame_rgb[y0:y0 + ch, x0:x0 + cw], (size, size), interpolation=cv2.INTER_AREA)
    if mask_gripper or mask_mirror:
        img = draw_predefined_mask(img, color=(0, 0, 0), mirror=mask_mirror, gripper=mask_gripper, finger=False,
                                   use_aa=True)
    return img


class UVCCamera:
    """:class:`~umi_aug.deploy.interfaces.CameraInterface` over OpenCV; ``start()`` opens it and starts reading."""

    def __init__(self, cfg: CameraConfig) -> None:
        self.cfg = cfg
        self.fps = float(cfg.fps)
        self._frames: collections.deque = collections.deque(maxlen=int(cfg.buffer))
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cap = None
        self._error: str | None = None
        self.n_read = 0
        self.eof = False

    def start(self, timeout_s: float = 10.0) -> None:
        c = self.cfg
        src: int | str = int(c.device) if str(c.device).isdigit() else str(c.device)
        cap = cv2.VideoCapture(src)
        if not cap.isOpened():
            raise DeployError(f"camera.device={c.device!r}: OpenCV cannot open it")
        if isinstance(src, int) or str(src).startswith("/dev/"):
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*"MJPG"))
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, c.width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, c.height)
            cap.set(cv2.CAP_PROP_FPS, c.fps)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        self._cap = cap
        self._thread = threading.Thread(target=self._loop, name="uvc_camera", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self._frames:
            if self._error or time.monotonic() > deadline:
                self.stop()
                raise DeployError(f"camera.device={c.device!r}: no frame within {timeout_s} s "
                                  f"({self._error or 'timeout'})")
            time.sleep(0.005)

    def _loop(self) -> None:
        c, t0 = self.cfg, time.monotonic()
        while not self._stop.is_set():
            ok, bgr = self._cap.read()
            t_recv = time.monotonic()
            if not ok:
                self.eof = True
                self._error = "capture returned no frame (unplugged or end of file)"
                return
            if bgr.shape[0] != c.height or bgr.shape[1] != c.width:
                self._error = f"frame is {bgr.shape[1]}x{bgr.shape[0]}, camera.width/height say {c.width}x{c.height}"
                return
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            img = policy_image(rgb, c.size, c.mask_gripper, c.mask_mirror)
            with self._lock:
                self._frames.append((t_recv - c.latency, img))
                self.n_read += 1
            if not c.realtime:
                continue
            if isinstance(self.cfg.device, str) and not self.cfg.device.startswith("/dev/") \
                    and not self.cfg.device.isdigit():
                time.sleep(max(0.0, t0 + self.n_read / self.fps - time.monotonic()))

    def get_frames(self, n: int) -> dict[str, np.ndarray]:
        with self._lock:
            items = list(self._frames)[-int(n):]
        if not items:
            raise SafetyStop(f"camera: no frame ({self._error or 'not started'})")
        return {"timestamp": np.array([t for t, _ in items]), "rgb": np.stack([im for _, im in items])}

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._cap is not None:
            self._cap.release()
            self._cap = None
