"""The simulated camera (:class:`SimFisheyeCamera`): the built-in tabletop scene (:func:`umi_aug.sim.scene.
build_tabletop_scene`) with its UMI gripper placed at ``T_world_base · T_base_tcp · T_cam_tcp⁻¹`` (UMI's
camera→TCP offset) and the fingers at the simulated width, rendered through the GoPro fisheye
(:class:`~umi_aug.sim.fisheye_renderer.FisheyeRenderer`, the 2.7K calibration scaled to ``width×height``) and
turned into the policy image exactly as the demo session's zarr images (:func:`umi_aug.camera.umi_image.
umi_policy_image`: gripper mask, centre crop, INTER_AREA). Frames are delivered ``latency`` seconds after the
state they show and stamped ``receive time − latency`` like the UVC camera. The arm itself is not drawn (it is
behind the wrist camera; the demo sessions have no arm either).

One of the three roles of the simulated UR5e (:mod:`umi_aug.deploy.sim_ur5e`); :class:`SimFisheyeCamera`
implements :class:`~umi_aug.deploy.interfaces.CameraInterface`. Its render process dies with the runner
(:func:`~umi_aug.deploy.device_process.child_setup`, plus a parent-alive check every loop).
"""

from __future__ import annotations

import collections
import logging
import multiprocessing as mp
import os
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from umi_aug.config_check import reject_unknown_keys, require_positive
from umi_aug.deploy.device_process import child_setup, parent_alive
from umi_aug.deploy.safety import SafetyStop
from umi_aug.deploy.shared_state import SharedStateBuffer
from umi_aug.errors import DeployError
from umi_aug.geometry.se3 import pos_rotvec_to_pose
from umi_aug.sim.gl import import_mujoco

__all__ = ["SimCameraConfig", "SimFisheyeCamera"]

log = logging.getLogger(__name__)


@dataclass
class SimCameraConfig:
    """The ``camera:`` block of ``configs/robot/sim_ur5e.yaml``.

    Attributes:
        fps: nominal frame rate the observation timing uses (UMI's GoPro, 60).
        render_fps: frames actually rendered per second (CPU rendering; the runner picks the newest frame at or
            before each observation time, as with a real camera).
        latency: seconds between the state a frame shows and its delivery (subtracted again on receipt).
        width, height: rendered fisheye frame (the GoPro 2.7K calibration scaled; the demo session's 320×240).
        size: policy image side. mask_gripper: paint UMI's gripper mask black (as the training images).
        scene_seed, n_distractors: the built-in tabletop scene. start_timeout_s: first frame within this.
    """

    fps: float = 60.0
    render_fps: float = 20.0
    latency: float = 0.1
    width: int = 320
    height: int = 240
    size: int = 224
    mask_gripper: bool = True
    scene_seed: int = 0
    n_distractors: int = 4
    buffer: int = 64
    start_timeout_s: float = 120.0

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any], where: str = "camera") -> "SimCameraConfig":
        reject_unknown_keys(m, cls.__dataclass_fields__, where, DeployError)
        c = cls(**dict(m))
        require_positive(where, c, ("fps", "render_fps", "latency", "width", "height", "size", "buffer",
                                    "start_timeout_s"), DeployError)
        if c.width < c.height:
            raise DeployError(f"{where}: need width >= height (landscape GoPro frame), got {c.width}x{c.height}")
        return c


def _camera_main(cfg: SimCameraConfig, T_world_base: np.ndarray, robot_state: SharedStateBuffer,
                 gripper_state: SharedStateBuffer, frames: Any, stop_event: Any, errors: Any,
                 parent_pid: int) -> None:
    child_setup(parent_pid)
    try:
        # lazy: the render stack (MuJoCo, the ``sim`` extra) loads in the render process only
        from umi_aug.camera.calib_io import gopro_intrinsics_2_7k
        from umi_aug.camera.umi_image import umi_policy_image
        from umi_aug.geometry.umi import umi_T_cam_tcp
        from umi_aug.sim.fisheye_renderer import FisheyeRenderer
        from umi_aug.sim.raster import RasterOptions
        from umi_aug.sim.scene import SCENE_FAR, SCENE_NEAR, build_tabletop_scene
        from umi_aug.sim.tabletop_state import TabletopState

        model = build_tabletop_scene(int(cfg.scene_seed), n_distractors=int(cfg.n_distractors)).compile()
        scene = TabletopState(model)
        intr = gopro_intrinsics_2_7k().scaled(int(cfg.width), int(cfg.height))
        T_tcp_cam = np.linalg.inv(umi_T_cam_tcp())
        period = 1.0 / cfg.render_fps
        pending: collections.deque = collections.deque()
        with FisheyeRenderer(model, intr, options=RasterOptions(near=SCENE_NEAR, far=SCENE_FAR)) as renderer:
            t_next = time.monotonic()
            while not stop_event.is_set():
                if not parent_alive(parent_pid):
                    raise SafetyStop(f"the runner process {parent_pid} died")
                now = time.monotonic()
                if now >= t_next:
                    tcp = robot_state.latest(1)["tcp_pose"][-1]
                    width = float(gripper_state.latest(1)["width"][-1])
                    T_world_cam = T_world_base @ pos_rotvec_to_pose(tcp) @ T_tcp_cam
                    scene.set(T_world_cam, max(width, 0.0))
                    rgb = renderer.render(T_world_cam, scene.data, depth=False).rgb
                    pending.append((now, umi_policy_image(rgb, intr, int(cfg.size), bool(cfg.mask_gripper))))
                    t_next += period
                    if t_next < time.monotonic():  # rendering is slower than render_fps: no burst afterwards
                        t_next = time.monotonic() + period
                while pending and pending[0][0] + cfg.latency <= time.monotonic():
                    frames.put(pending.popleft())
                wake = min([t_next] + ([pending[0][0] + cfg.latency] if pending else []))
                time.sleep(min(max(0.0, wake - time.monotonic()), 0.05))
    except BaseException as exc:  # noqa: BLE001 - reported to the runner
        errors.put(f"{type(exc).__name__}: {exc}")


class SimFisheyeCamera:
    """:class:`~umi_aug.deploy.interfaces.CameraInterface` of the simulated wrist camera (render process +
    receiving thread, like :class:`~umi_aug.deploy.camera.UVCCamera`'s capture thread).

    Args:
        cfg: :class:`SimCameraConfig`. robot, gripper: the simulated backends (their state buffers drive the
            rendered gripper pose and finger opening). T_world_base: [4, 4] robot base in the scene frame.
    """

    def __init__(self, cfg: SimCameraConfig, robot: Any, gripper: Any, T_world_base: np.ndarray,
                 ctx: Any = None) -> None:
        self.cfg = cfg
        self.fps = float(cfg.fps)
        self._robot_state, self._gripper_state = robot.state, gripper.state
        self.T_world_base = np.asarray(T_world_base, float)
        self._ctx = ctx or mp.get_context("spawn")
        self._frames: collections.deque = collections.deque(maxlen=int(cfg.buffer))
        self._lock = threading.Lock()
        self._stop_thread = threading.Event()
        self._proc: Any = None
        self._thread: threading.Thread | None = None
        self._error: str | None = None
        self.delivery_delay: list[float] = []  # receive time − (capture time + latency), s
        self.n_read = 0

    def start(self) -> None:
        import_mujoco()  # chooses MUJOCO_GL here, the render process inherits it
        self._q, self._errors, self._stop = self._ctx.Queue(), self._ctx.Queue(), self._ctx.Event()
        self._proc = self._ctx.Process(target=_camera_main, name="sim_camera", daemon=True,
                                       args=(self.cfg, self.T_world_base, self._robot_state, self._gripper_state,
                                             self._q, self._stop, self._errors, os.getpid()))
        self._proc.start()
        self._thread = threading.Thread(target=self._receive, name="sim_camera_rx", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + self.cfg.start_timeout_s
        while not self._frames:
            err = self._poll_error()
            if err or time.monotonic() > deadline:
                self.stop()
                raise DeployError(f"simulated camera: no frame within {self.cfg.start_timeout_s} s ({err or 'timeout'})")
            time.sleep(0.01)

    def _receive(self) -> None:
        while not self._stop_thread.is_set():
            try:
                t_cap, img = self._q.get(timeout=0.1)
            except queue.Empty:
                continue
            except (EOFError, OSError):
                return
            t_recv = time.monotonic()
            with self._lock:
                self._frames.append((t_recv - self.cfg.latency, img))
                self.delivery_delay.append(t_recv - self.cfg.latency - t_cap)
                self.n_read += 1

    def _poll_error(self) -> str | None:
        if self._error is None and self._proc is not None:
            try:
                self._error = self._errors.get_nowait()
            except queue.Empty:
                if not self._proc.is_alive():
                    self._error = f"render process exited (code {self._proc.exitcode})"
        return self._error

    def get_frames(self, n: int) -> dict[str, np.ndarray]:
        err = self._poll_error()
        if err:
            raise SafetyStop(f"simulated camera stopped: {err}")
        with self._lock:
            items = list(self._frames)[-int(n):]
        if not items:
            raise SafetyStop("simulated camera: no frame (not started)")
        return {"timestamp": np.array([t for t, _ in items]), "rgb": np.stack([im for _, im in items])}

    def sim_stats(self) -> dict[str, float]:
        """Frames received, their mean rate, and the delivery delay beyond the configured latency (ms)."""
        with self._lock:
            d = np.asarray(self.delivery_delay, float)
            ts = [t for t, _ in self._frames]
        out: dict[str, float] = {"camera_frames": self.n_read}
        if len(ts) > 1:
            out["camera_fps_recent"] = (len(ts) - 1) / (ts[-1] - ts[0])
        if len(d):
            out["camera_extra_delay_p50_ms"] = float(np.percentile(d, 50) * 1000)
            out["camera_extra_delay_p99_ms"] = float(np.percentile(d, 99) * 1000)
        return out

    def stop(self) -> None:
        """Stop the render process and the receiving thread (idempotent)."""
        if self._proc is not None:
            self._stop.set()
            self._proc.join(timeout=5.0)
            if self._proc.is_alive():
                log.error("simulated camera process did not stop in 5 s; terminating it")
                self._proc.terminate()
                self._proc.join(timeout=2.0)
            self._proc = None
        self._stop_thread.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
