"""Test doubles behind the deploy interfaces, driven by a FakeClock (no real time passes)."""

from __future__ import annotations

import numpy as np

from umi_aug.deploy.clock import FakeClock
from umi_aug.deploy.interpolator import PoseTrajectoryInterpolator


class KinematicRobot:
    """Follows scheduled waypoints exactly (UMI's interpolator, no dynamics); states sampled at ``rate`` Hz."""

    def __init__(self, clock: FakeClock, pose0, rate: float = 500.0, obs_latency: float = 0.0) -> None:
        self.clock, self.rate, self.obs_latency = clock, rate, obs_latency
        self.interp = PoseTrajectoryInterpolator([clock.now()], [pose0])
        self.last_wp: float | None = None
        self.scheduled: list[tuple[np.ndarray, float, float]] = []  # (pose, target time, time of the call)
        self.stopped = 0
        self.connected = True

    def get_states(self, n: int) -> dict[str, np.ndarray]:
        if not self.connected:  # no new state arrives: the last one ages
            now = self.disconnect_time
        else:
            now = self.clock.now()
        t = now - np.arange(min(n, 600))[::-1] / self.rate
        return {"timestamp": t - self.obs_latency, "tcp_pose": self.interp(t - self.obs_latency)}

    def schedule_waypoint(self, pose, t: float) -> None:
        self.scheduled.append((np.asarray(pose, float), float(t), self.clock.now()))
        self.interp = self.interp.schedule_waypoint(pose, t, 0.5, 2.0, self.clock.now(), self.last_wp)
        self.last_wp = t

    def check_ok(self) -> None:
        pass

    def stop(self) -> None:
        self.stopped += 1

    def disconnect(self) -> None:
        self.connected, self.disconnect_time = False, self.clock.now()


class KinematicGripper:
    def __init__(self, clock: FakeClock, width: float = 0.08) -> None:
        self.clock, self.width = clock, width
        self.scheduled: list[tuple[float, float]] = []
        self.stopped = 0

    def get_states(self, n: int) -> dict[str, np.ndarray]:
        t = self.clock.now() - np.arange(3)[::-1] / 30.0
        return {"timestamp": t, "width": np.full(3, self.width)}

    def schedule_waypoint(self, width: float, t: float) -> None:
        self.scheduled.append((width, t))
        self.width = width

    def check_ok(self) -> None:
        pass

    def stop(self) -> None:
        self.stopped += 1


class FakeCamera:
    """Frames at ``fps`` whose pixel value encodes the frame index; timestamps = capture time (latency removed)."""

    def __init__(self, clock: FakeClock, fps: float = 60.0, latency: float = 0.1, frozen_at: float | None = None):
        self.clock, self.fps, self.latency, self.frozen_at = clock, fps, latency, frozen_at
        self.stopped = 0

    def get_frames(self, n: int) -> dict[str, np.ndarray]:
        now = self.clock.now() if self.frozen_at is None else self.frozen_at
        last = np.floor((now - self.latency) * self.fps)
        idx = last - np.arange(n)[::-1]
        rgb = np.broadcast_to((idx % 256).astype(np.uint8)[:, None, None, None], (n, 8, 8, 3)).copy()
        return {"timestamp": idx / self.fps, "rgb": rgb}

    def stop(self) -> None:
        self.stopped += 1


class ScriptedPolicy:
    """Returns ``{"action": a fixed [n, 7] chunk}`` relative to the observed pose (``offsets`` added), taking
    ``infer_s`` of fake time; records the observations it saw."""

    def __init__(self, clock: FakeClock, offsets: np.ndarray, infer_s: float = 0.05, width: float = 0.05):
        self.clock, self.offsets, self.infer_s, self.width = clock, np.asarray(offsets, float), infer_s, width
        self.seen: list[dict] = []
        self.resets = 0

    def reset(self) -> None:
        self.resets += 1

    def predict_action(self, obs):
        self.seen.append({k: np.array(v) for k, v in obs.items()})
        self.clock.advance(self.infer_s)
        cur = np.concatenate([obs["robot0_eef_pos"][-1], obs["robot0_eef_rot_axis_angle"][-1]])
        a = np.zeros((len(self.offsets), 7))
        a[:, :6] = cur + self.offsets
        a[:, 6] = self.width
        return {"action": a}
