"""UMI's latency-compensated policy loop (``eval_real.py``), hardware-independent.

Per inference cycle:

1. observations: the latest camera frames at ``t_last − arange(H)[::-1]·down_sample/fps`` and robot TCP pose and
   gripper width interpolated to the same timestamps (UMI ``get_obs``); each stream's age is checked;
2. ``policy.predict_action(obs)`` → absolute ``[n, 7]`` (pos, rotvec, gripper width);
3. action ``k`` is due at ``t_obs_last + k·dt``; actions due before ``now + action_exec_latency +
   max(action latencies)`` are dropped (UMI drops at ``now + action_exec_latency`` and the controller then ignores
   the ones whose compensated time is past); if none is left, the last action goes to the next ``dt`` slot after
   that lead;
4. every kept command passes :func:`~umi_aug.deploy.safety.check_command`, then is scheduled at
   ``t − robot_action_latency`` / ``t − gripper_action_latency`` (latency compensation) — or only logged in
   dry-run mode;
5. sleep until ``t_start + (iter + steps_per_inference)·dt − frame_latency``.

Any exception (a :class:`SafetyStop`, Ctrl-C, a backend error) halts robot and gripper before it propagates.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Callable, Protocol

import numpy as np

from umi_aug.deploy.clock import Clock
from umi_aug.deploy.interfaces import CameraInterface, GripperInterface, RobotInterface
from umi_aug.deploy.interpolator import PoseTrajectoryInterpolator, ScalarTrajectoryInterpolator
from umi_aug.deploy.safety import SafetyLimits, SafetyStop, check_command, check_obs_age
from umi_aug.errors import DeployError

__all__ = ["RunnerConfig", "ObsSpec", "PolicyRunner", "CycleLog", "select_actions"]

log = logging.getLogger(__name__)


class PolicyLike(Protocol):
    def predict_action(self, obs_dict: dict[str, np.ndarray]) -> np.ndarray: ...

    def reset(self) -> None: ...


@dataclass
class ObsSpec:
    """Observation window the policy was trained with (``policy.task``)."""

    img_horizon: int = 1
    low_dim_horizon: int = 2
    down_sample_steps: int = 3

    @classmethod
    def from_policy(cls, policy: Any) -> "ObsSpec":
        t = getattr(policy, "task", None)
        if t is None:
            return cls()
        return cls(int(t.img_obs_horizon), int(t.low_dim_obs_horizon), int(t.obs_down_sample_steps))


@dataclass
class RunnerConfig:
    """Loop timing (seconds). ``dt`` = policy step; UMI's defaults except ``dt`` (see ``configs/deploy_ur.yaml``)."""

    dt: float = 0.1
    steps_per_inference: int = 6
    robot_action_latency: float = 0.1
    gripper_action_latency: float = 0.1
    action_exec_latency: float = 0.01
    frame_latency: float = 1.0 / 60.0
    start_delay: float = 1.0
    max_duration: float = 60.0
    dry_run: bool = False
    n_action_steps: int | None = None  # passed as predict_action(n_steps=...); UMI's eval uses the whole horizon

    def __post_init__(self) -> None:
        if not (self.dt > 0 and self.steps_per_inference >= 1 and self.max_duration > 0):
            raise DeployError(f"runner: need dt > 0, steps_per_inference >= 1, max_duration > 0; got dt={self.dt}, "
                              f"steps_per_inference={self.steps_per_inference}, max_duration={self.max_duration}")


@dataclass
class CycleLog:
    """What one inference cycle saw and did (times in seconds on the runner clock)."""

    t_cycle_start: float
    obs_timestamps: np.ndarray
    t_action_sent: float
    action_timestamps: np.ndarray  # when each kept action is due (before latency compensation)
    commands: np.ndarray  # [k, 7] safe commands (pose + width)
    n_dropped: int
    tcp_pose: np.ndarray  # [6] current TCP pose at obs time

    @property
    def obs_to_action_latency(self) -> float:
        """Capture time of the newest frame → commands handed to the backends."""
        return self.t_action_sent - float(self.obs_timestamps[-1])


def select_actions(actions: np.ndarray, t_obs_last: float, now: float, dt: float, exec_latency: float,
                   t_start: float) -> tuple[np.ndarray, np.ndarray, int]:
    """UMI's action scheduling: ``(kept actions, their due times, number dropped)``.

    Action ``k`` is due at ``t_obs_last + k·dt``; those not later than ``now + exec_latency`` are dropped. If all
    are, the last action is kept and due at the first slot ``t_start + k·dt`` after ``now + exec_latency``.
    """
    ts = t_obs_last + np.arange(len(actions)) * dt
    keep = ts > now + exec_latency
    if keep.any():
        return actions[keep], ts[keep], int((~keep).sum())
    # the first slot strictly after now + exec_latency (one extra dt was not enough for a lead longer than dt)
    nxt = t_start + (math.floor((now + exec_latency - t_start) / dt) + 1) * dt
    return actions[-1:], np.array([nxt]), len(actions) - 1


class PolicyRunner:
    """Runs a policy on a robot + gripper + camera with UMI's timing and this project's safety checks."""

    def __init__(self, policy: PolicyLike, robot: RobotInterface, gripper: GripperInterface,
                 camera: CameraInterface, clock: Clock, cfg: RunnerConfig, limits: SafetyLimits,
                 obs_spec: ObsSpec | None = None,
                 on_cycle: Callable[[CycleLog], None] | None = None) -> None:
        self.policy, self.robot, self.gripper, self.camera = policy, robot, gripper, camera
        self.clock, self.cfg, self.limits = clock, cfg, limits
        self.spec = obs_spec or ObsSpec.from_policy(policy)
        self.on_cycle = on_cycle
        self.cycles: list[CycleLog] = []
        self.stop_reason: str | None = None

    # ------------------------------------------------------------------ observations
    def get_obs(self) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Aligned observation dict (``camera0_rgb``, ``robot0_eef_pos``, ``robot0_eef_rot_axis_angle``,
        ``robot0_gripper_width``) and its low-dim timestamps [H]."""
        sp, now = self.spec, self.clock.now()
        step = sp.down_sample_steps / float(self.camera.fps)
        n_frames = (max(sp.img_horizon, 1) - 1) * sp.down_sample_steps + 2
        cam = self.camera.get_frames(n_frames)
        cam_t = np.asarray(cam["timestamp"], np.float64)
        if len(cam_t) == 0:
            raise SafetyStop("camera delivered no frame")
        t_last = float(cam_t[-1])
        check_obs_age("camera", t_last, now, self.limits)
        img_ts = t_last - np.arange(sp.img_horizon)[::-1] * step
        idx = np.clip(np.searchsorted(cam_t, img_ts + 1e-9, side="right") - 1, 0, len(cam_t) - 1)
        low_ts = t_last - np.arange(sp.low_dim_horizon)[::-1] * step
        n_state = 1000
        rs = self.robot.get_states(n_state)
        gs = self.gripper.get_states(n_state)
        check_obs_age("robot", float(rs["timestamp"][-1]), now, self.limits)
        check_obs_age("gripper", float(gs["timestamp"][-1]), now, self.limits)
        pose = _interp_pose(rs["timestamp"], rs["tcp_pose"], low_ts)
        width = _interp_scalar(gs["timestamp"], gs["width"], low_ts)
        obs = {"camera0_rgb": np.asarray(cam["rgb"])[idx], "robot0_eef_pos": pose[:, :3],
               "robot0_eef_rot_axis_angle": pose[:, 3:], "robot0_gripper_width": width.reshape(-1, 1)}
        for k, v in obs.items():
            if not np.isfinite(np.asarray(v, np.float64)).all():
                raise SafetyStop(f"observation {k} is not finite")
        return obs, low_ts

    # ------------------------------------------------------------------ one cycle
    def step(self, it: int, t_start: float) -> CycleLog:
        """One inference cycle (steps 1–4 of the module docstring); returns its log."""
        cfg = self.cfg
        t0 = self.clock.now()
        self.robot.check_ok()
        self.gripper.check_ok()
        obs, obs_ts = self.get_obs()
        kw = {} if cfg.n_action_steps is None else {"n_steps": int(cfg.n_action_steps)}
        action = np.asarray(self.policy.predict_action(obs, **kw), np.float64)
        if action.ndim != 2 or action.shape[1] < 7 or len(action) < 1:
            raise DeployError(f"policy returned actions of shape {action.shape}; expected [n, 7]")
        now = self.clock.now()
        # an action whose latency-compensated time is already past would be ignored by the controller's
        # interpolator (silently, in UMI): drop it here, where it is counted
        lead = cfg.action_exec_latency + max(cfg.robot_action_latency, cfg.gripper_action_latency)
        kept, due, n_drop = select_actions(action[:, :7], float(obs_ts[-1]), now, cfg.dt, lead, t_start)
        cur = np.concatenate([obs["robot0_eef_pos"][-1], obs["robot0_eef_rot_axis_angle"][-1]])
        safe = np.empty_like(kept)
        ref = cur
        for k, a in enumerate(kept):
            pose, width = check_command(a[:6], float(a[6]), ref, self.limits)
            safe[k, :6], safe[k, 6] = pose, width
        if not cfg.dry_run:
            self.robot.check_ok()
            for a, t in zip(safe, due):
                self.robot.schedule_waypoint(a[:6], float(t) - cfg.robot_action_latency)
                self.gripper.schedule_waypoint(float(a[6]), float(t) - cfg.gripper_action_latency)
        c = CycleLog(t0, obs_ts, self.clock.now(), due, safe, n_drop, cur)
        self.cycles.append(c)
        if self.on_cycle is not None:
            self.on_cycle(c)
        return c

    # ------------------------------------------------------------------ episode
    def run(self, n_cycles: int | None = None,
            done: Callable[[CycleLog], bool] | None = None) -> list[CycleLog]:
        """Run until ``n_cycles`` cycles, ``cfg.max_duration`` or ``done(cycle_log)``; robot and gripper are
        halted on every exit path. Exceptions propagate after the halt (``self.stop_reason`` holds the message)."""
        cfg = self.cfg
        if hasattr(self.policy, "reset"):
            self.policy.reset()
        t_start = self.clock.now() + cfg.start_delay
        self.clock.sleep_until(t_start - cfg.frame_latency)
        try:
            it = 0
            while n_cycles is None or it // cfg.steps_per_inference < n_cycles:
                c = self.step(it, t_start)
                if done is not None and done(c):
                    self.stop_reason = "done"
                    break
                if self.clock.now() - t_start > cfg.max_duration:
                    self.stop_reason = f"max_duration {cfg.max_duration} s reached"
                    break
                self.clock.sleep_until(t_start + (it + cfg.steps_per_inference) * cfg.dt - cfg.frame_latency)
                it += cfg.steps_per_inference
            else:
                self.stop_reason = f"{n_cycles} cycles done"
        except KeyboardInterrupt:
            self.stop_reason = "stopped by the user (Ctrl-C)"
            log.warning(self.stop_reason)
        except BaseException as exc:
            self.stop_reason = str(exc)
            raise
        finally:
            self.halt()
        return self.cycles

    def halt(self) -> None:
        """Stop robot, gripper and camera; errors while stopping are logged, never hide the first one."""
        for name, dev in (("robot", self.robot), ("gripper", self.gripper), ("camera", self.camera)):
            try:
                dev.stop()
            except Exception as exc:  # noqa: BLE001 - keep stopping the others
                log.error("stopping the %s failed: %s", name, exc)


def _dedupe(t: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t, np.float64)
    keep = np.concatenate([np.diff(t) > 0, [True]])
    return t[keep], np.asarray(v, np.float64)[keep]


def _interp_pose(t: np.ndarray, poses: np.ndarray, at: np.ndarray) -> np.ndarray:
    t, p = _dedupe(t, poses)
    return np.atleast_2d(PoseTrajectoryInterpolator(t, p)(np.asarray(at)))


def _interp_scalar(t: np.ndarray, v: np.ndarray, at: np.ndarray) -> np.ndarray:
    t, v = _dedupe(t, v)
    return ScalarTrajectoryInterpolator(t, v)(np.asarray(at))[:, 0]
