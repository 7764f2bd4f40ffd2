"""UMI's latency-compensated policy loop (``eval_real.py``), hardware-independent.

Before the first cycle :meth:`PolicyRunner.check_start` checks that the current TCP is inside the box and above
the table (:meth:`PolicyRunner.preflight` did the same before the devices were enabled). Per inference cycle:

1. observations: the latest camera frames at ``t_last − arange(H)[::-1]·down_sample/fps`` and robot TCP pose and
   gripper width interpolated to the same timestamps (UMI ``get_obs``); each stream's age is checked;
2. ``policy.predict_action(obs)["action"]`` → absolute ``[n, 7]`` (pos, rotvec, gripper width); the policy is
   anything with the contract of :mod:`umi_aug.policy.contract` (``reset()``, ``predict_action(obs_dict)``);
3. late actions (``late_actions``): action ``k`` is due at ``t_obs_last + k·dt``; actions due before
   ``now + action_exec_latency + max(action latencies)`` — their latency-compensated time has passed — are
   dropped and counted (UMI drops at ``now + action_exec_latency`` and its controller then ignores the ones whose
   compensated time is past). ``"drop"`` (default, UMI's rule): if none is left, nothing is sent and the arm holds
   (it ends the trajectory already scheduled); the observation's age is checked again after inference, and a chunk
   computed from an observation older than ``safety.max_obs_age_s`` is dropped whole (the arm holds; counted as
   stale). ``"next_slot"`` (this project's earlier rule, explicit opt-in): if none is left, the last action goes
   to the first ``dt`` slot after that lead, and there is no re-check;
4. every kept command passes :func:`~umi_aug.deploy.safety.check_command`, then is scheduled at
   ``t − robot_action_latency`` / ``t − gripper_action_latency`` (latency compensation) — or, in a dry run, only
   logged, with the reason any of them would have stopped the run (:attr:`CycleLog.would_stop`; the run goes on);
5. sleep until ``t_start + (iter + steps_per_inference)·dt − frame_latency``.

Any exception (a :class:`SafetyStop`, Ctrl-C, a backend error) halts robot and gripper before it propagates.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from umi_aug.deploy.clock import Clock
from umi_aug.deploy.interfaces import CameraInterface, GripperInterface, RobotInterface
from umi_aug.deploy.interpolator import PoseTrajectoryInterpolator, ScalarTrajectoryInterpolator
from umi_aug.deploy.safety import SafetyLimits, SafetyStop, check_command, check_obs_age, check_start_pose
from umi_aug.errors import DeployError
from umi_aug.policy.contract import PolicyLike, action_chunk

__all__ = ["RunnerConfig", "ObsSpec", "PolicyRunner", "CycleLog", "Preflight", "select_actions", "LATE_ACTIONS"]

log = logging.getLogger(__name__)

#: ``late_actions`` rules: "drop" = UMI's (past actions dropped, the arm holds when none is left, the observation
#: age re-checked after inference); "next_slot" = the earlier rule (the last action moved to the next free slot).
LATE_ACTIONS = ("drop", "next_slot")


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
    n_action_steps: int | None = None  # passed as predict_action(n_steps=...), a keyword beyond the contract that
    # umi_aug.policy.Policy takes (app.py sets it for a checkpoint: UMI's eval uses the whole horizon)
    late_actions: str = "drop"  # "drop" (UMI: drop the past, hold, count) | "next_slot" (earlier rule, opt-in)

    def __post_init__(self) -> None:
        if not (self.dt > 0 and self.steps_per_inference >= 1 and self.max_duration > 0):
            raise DeployError(f"runner: need dt > 0, steps_per_inference >= 1, max_duration > 0; got dt={self.dt}, "
                              f"steps_per_inference={self.steps_per_inference}, max_duration={self.max_duration}")
        if self.late_actions not in LATE_ACTIONS:
            raise DeployError(f"late_actions={self.late_actions!r}; expected one of {list(LATE_ACTIONS)}")


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
    would_stop: list[str] = field(default_factory=list)  # dry run: why commands would have stopped the run
    stale: bool = False  # the whole chunk was dropped: its observation was older than max_obs_age_s after inference
    gripper_width: float = float("nan")  # m, at obs time

    @property
    def held(self) -> bool:
        """Nothing was sent this cycle (every action late, or a stale chunk): the arm holds."""
        return len(self.commands) == 0

    @property
    def obs_to_action_latency(self) -> float:
        """Capture time of the newest frame → commands handed to the backends."""
        return self.t_action_sent - float(self.obs_timestamps[-1])


@dataclass
class Preflight:
    """What the runner saw before anything moved (:meth:`PolicyRunner.preflight`): the current TCP pose [6]
    (base frame, m / rotvec), the gripper width (m) and the policy's first chunk ``actions`` [n, 7] (absolute
    TCP poses + widths, spaced ``dt`` s from the observation)."""

    tcp_pose: np.ndarray
    gripper_width: float
    actions: np.ndarray
    dt: float


def select_actions(actions: np.ndarray, t_obs_last: float, now: float, dt: float, exec_latency: float,
                   t_start: float, late: str = "drop") -> tuple[np.ndarray, np.ndarray, int]:
    """UMI's action scheduling: ``(kept actions [k, D], their due times [k] in s, number dropped)``.

    Action ``k`` is due at ``t_obs_last + k·dt``; those not later than ``now + exec_latency`` are dropped. If all
    are: ``late="drop"`` keeps none (the arm holds); ``late="next_slot"`` keeps the last action, due at the first
    slot ``t_start + k·dt`` after ``now + exec_latency``.
    """
    ts = t_obs_last + np.arange(len(actions)) * dt
    keep = ts > now + exec_latency
    if keep.any() or late == "drop":
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

    def _predict(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """``policy.predict_action(obs)["action"]`` → [n, >=7] float64 actions (checked shape)."""
        kw = {} if self.cfg.n_action_steps is None else {"n_steps": int(self.cfg.n_action_steps)}
        action = np.asarray(action_chunk(self.policy.predict_action(obs, **kw)), np.float64)
        if action.ndim != 2 or action.shape[1] < 7 or len(action) < 1:
            raise DeployError(f"policy returned actions of shape {action.shape}; expected [n, 7]")
        return action

    def check_start(self) -> None:
        """Start-up check on the newest robot and gripper states: TCP inside the box and above the table
        (:func:`~umi_aug.deploy.safety.check_start_pose`); :class:`SafetyStop` otherwise."""
        pose = np.asarray(self.robot.get_states(1)["tcp_pose"][-1], np.float64)
        check_start_pose(pose, float(self.gripper.get_states(1)["width"][-1]), self.limits)

    def preflight(self) -> Preflight:
        """Observe once, run the start-up check and the policy once, sending nothing (the devices may still be
        observe-only): what the operator confirms before a real arm moves. The policy is reset again by
        :meth:`run`.

        Raises:
            SafetyStop: the current TCP is outside the box or below the table, or a stale/bad observation.
        """
        self.robot.check_ok()
        self.gripper.check_ok()
        obs, _ = self.get_obs()
        cur = np.concatenate([obs["robot0_eef_pos"][-1], obs["robot0_eef_rot_axis_angle"][-1]])
        width = float(obs["robot0_gripper_width"][-1, 0])
        check_start_pose(cur, width, self.limits)
        self.policy.reset()
        return Preflight(cur, width, self._predict(obs)[:, :7], self.cfg.dt)

    # ------------------------------------------------------------------ one cycle
    def step(self, it: int, t_start: float) -> CycleLog:
        """One inference cycle (steps 1–4 of the module docstring); returns its log."""
        cfg = self.cfg
        t0 = self.clock.now()
        self.robot.check_ok()
        self.gripper.check_ok()
        obs, obs_ts = self.get_obs()
        action = self._predict(obs)
        now = self.clock.now()
        # an action whose latency-compensated time is already past would be ignored by the controller's
        # interpolator (silently, in UMI): drop it here, where it is counted
        lead = cfg.action_exec_latency + max(cfg.robot_action_latency, cfg.gripper_action_latency)
        age = now - float(obs_ts[-1])
        stale = cfg.late_actions == "drop" and age > self.limits.max_obs_age_s
        if stale:  # computed from an observation that is too old by now: drop the whole chunk, hold
            log.warning("observation %.3f s old after inference > safety.max_obs_age_s=%s: chunk dropped, arm holds",
                        age, self.limits.max_obs_age_s)
            kept, due, n_drop = action[:0, :7], np.zeros(0), len(action)
        else:
            kept, due, n_drop = select_actions(action[:, :7], float(obs_ts[-1]), now, cfg.dt, lead, t_start,
                                               cfg.late_actions)
        cur = np.concatenate([obs["robot0_eef_pos"][-1], obs["robot0_eef_rot_axis_angle"][-1]])
        safe, would_stop = self._check_commands(kept, cur)
        if not cfg.dry_run:
            self.robot.check_ok()
            for a, t in zip(safe, due):
                self.robot.schedule_waypoint(a[:6], float(t) - cfg.robot_action_latency)
                self.gripper.schedule_waypoint(float(a[6]), float(t) - cfg.gripper_action_latency)
        c = CycleLog(t0, obs_ts, self.clock.now(), due, safe, n_drop, cur, would_stop, stale,
                     float(obs["robot0_gripper_width"][-1, 0]))
        self.cycles.append(c)
        if self.on_cycle is not None:
            self.on_cycle(c)
        return c

    def _check_commands(self, kept: np.ndarray, cur: np.ndarray) -> tuple[np.ndarray, list[str]]:
        """Every kept action [k, 7] through :func:`check_command` against the current TCP ``cur`` [6]. Returns the
        (clamped) commands and, in a dry run, the reasons any of them would have stopped the run (the raw action
        is kept in its row); outside a dry run the first violation raises :class:`SafetyStop`."""
        safe = np.empty_like(kept)
        would_stop: list[str] = []
        for k, a in enumerate(kept):
            try:
                pose, width = check_command(a[:6], float(a[6]), cur, self.limits)
            except SafetyStop as exc:
                if not self.cfg.dry_run:
                    raise
                would_stop.append(str(exc))
                pose, width = a[:6], float(a[6])
            safe[k, :6], safe[k, 6] = pose, width
        return safe, would_stop

    # ------------------------------------------------------------------ episode
    def run(self, n_cycles: int | None = None,
            done: Callable[[CycleLog], bool] | None = None) -> list[CycleLog]:
        """Run until ``n_cycles`` cycles, ``cfg.max_duration`` or ``done(cycle_log)``; robot and gripper are
        halted on every exit path. Exceptions propagate after the halt (``self.stop_reason`` holds the message)."""
        cfg = self.cfg
        self.policy.reset()
        t_start = self.clock.now() + cfg.start_delay
        try:
            self.check_start()  # again after enabling (a moveJ to joints_init may have moved the arm)
            self.clock.sleep_until(t_start - cfg.frame_latency)
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
