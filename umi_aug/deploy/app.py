"""Assemble and run one deployment episode from a config mapping (what ``eval/deploy_ur.py`` calls).

Config keys (``configs/deploy_ur.yaml`` + ``configs/robot/*.yaml`` + ``configs/deploy_policy/*.yaml``):
``robot.{backend,robot,gripper,camera,safety}``, ``policy.{kind,...}``, ``checkpoint``, ``out_dir``, ``dry_run``, ``dt``,
``steps_per_inference``, ``max_duration``, ``start_delay``, ``n_cycles``, ``device``, ``reach_tolerance_m``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping

from umi_aug.deploy.camera import CameraConfig, UVCCamera
from umi_aug.deploy.clock import MonotonicClock
from umi_aug.deploy.interpolator import pose_distance
from umi_aug.deploy.policies import ReachPolicy
from umi_aug.deploy.recorder import EpisodeRecorder
from umi_aug.deploy.runner import ObsSpec, PolicyRunner, RunnerConfig
from umi_aug.deploy.safety import SafetyLimits
from umi_aug.deploy.ur_rtde import URConfig, URRTDERobot
from umi_aug.deploy.wsg50 import WSG50Gripper, WSGConfig
from umi_aug.deploy.config_check import reject_unknown_keys
from umi_aug.errors import DeployError

__all__ = ["run_deploy"]

log = logging.getLogger(__name__)

RUN_KEYS = {"robot", "policy", "checkpoint", "out_dir", "dry_run", "dt", "steps_per_inference", "max_duration",
            "start_delay", "n_cycles", "device", "reach_tolerance_m", "action_exec_latency"}


def _camera_cfg(m: Mapping[str, Any]) -> CameraConfig:
    reject_unknown_keys(m, CameraConfig.__dataclass_fields__, "robot.camera")
    return CameraConfig(**{k: (str(v) if k == "device" else v) for k, v in m.items()})


def _build_policy(cfg: Mapping[str, Any], fps: float) -> tuple[Any, ObsSpec, float]:
    p = dict(cfg.get("policy") or {})
    kind = p.pop("kind", "checkpoint")
    if kind == "reach":
        pol = ReachPolicy(**p)
        return pol, ObsSpec(1, 2, 3), float(cfg.get("dt") or pol.dt)
    if kind == "checkpoint":
        ckpt = cfg.get("checkpoint")
        if not ckpt or not Path(ckpt).is_file():
            raise DeployError(f"checkpoint={ckpt!r}: not a file; pass checkpoint=PATH (or policy=reach)")
        from umi_aug.policy.inference import Policy

        pol = Policy.from_checkpoint(ckpt, device=cfg.get("device") or "cpu")
        spec = ObsSpec.from_policy(pol)
        return pol, spec, float(cfg.get("dt") or spec.down_sample_steps / fps)
    raise DeployError(f"policy.kind={kind!r}; expected 'checkpoint' or 'reach'")


def _build_backends(rc: Mapping[str, Any]) -> tuple[Any, Any, Any, list[Any], tuple[Any, Any, Any]]:
    """Robot, gripper and camera backends from ``robot.backend``: ``rtde`` (ur-rtde arm, WSG-50, UVC camera) or
    ``sim`` (the simulated UR5e of :mod:`umi_aug.deploy.sim_ur5e`). Returns ``(camera, gripper, robot, start
    order, (robot cfg, gripper cfg, camera cfg))``; nothing is started."""
    backend = rc.get("backend", "rtde")
    if backend == "rtde":
        ur = URConfig.from_mapping(rc.get("robot") or {}, "robot.robot")
        wsg = WSGConfig.from_mapping(rc.get("gripper") or {}, "robot.gripper")
        cam_cfg = _camera_cfg(rc.get("camera") or {})
        camera, gripper, robot = UVCCamera(cam_cfg), WSG50Gripper(wsg), URRTDERobot(ur)
        return camera, gripper, robot, [camera, gripper, robot], (ur, wsg, cam_cfg)
    if backend == "sim":
        from umi_aug.deploy.sim_ur5e import (SimCameraConfig, SimFisheyeCamera, SimGripper, SimGripperConfig,
                                             SimUR5eRobot, SimURConfig, base_pose_matrix)

        ur = SimURConfig.from_mapping(rc.get("robot") or {}, "robot.robot")
        grip_cfg = SimGripperConfig.from_mapping(rc.get("gripper") or {}, "robot.gripper")
        cam_cfg = SimCameraConfig.from_mapping(rc.get("camera") or {}, "robot.camera")
        robot, gripper = SimUR5eRobot(ur), SimGripper(grip_cfg)
        camera = SimFisheyeCamera(cam_cfg, robot, gripper, base_pose_matrix(ur.base_pose))
        return camera, gripper, robot, [gripper, robot, camera], (ur, grip_cfg, cam_cfg)
    raise DeployError(f"robot.backend={backend!r}; expected 'rtde' (a real arm) or 'sim' (simulated UR5e)")


def run_deploy(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Connect, run one episode, halt, record. Returns the summary (also ``out_dir/timing.json``).

    Raises:
        DeployError: bad config or a safety stop (after the robot was halted and the episode recorded).
    """
    extra = sorted(set(cfg) - RUN_KEYS)
    if extra:
        raise DeployError(f"deploy config: unknown key(s) {extra}; known: {sorted(RUN_KEYS)}")
    rc = cfg.get("robot") or {}
    unknown = sorted(set(rc) - {"backend", "robot", "gripper", "camera", "safety"})
    if unknown:
        raise DeployError(f"robot config: unknown block(s) {unknown}; expected backend, robot, gripper, camera, "
                          f"safety")
    camera, gripper, robot, start_order, (ur, wsg, cam_cfg) = _build_backends(rc)
    limits = SafetyLimits.from_mapping(rc.get("safety") or {}, "robot.safety")
    policy, spec, dt = _build_policy(cfg, cam_cfg.fps)
    task = getattr(policy, "task", None)  # a checkpoint: the whole predicted horizon, as UMI's action_pred
    run_cfg = RunnerConfig(dt=dt, steps_per_inference=int(cfg.get("steps_per_inference", 6)),
                           robot_action_latency=ur.action_latency, gripper_action_latency=wsg.action_latency,
                           action_exec_latency=float(cfg.get("action_exec_latency", 0.01)),
                           frame_latency=1.0 / cam_cfg.fps, start_delay=float(cfg.get("start_delay", 1.0)),
                           max_duration=float(cfg.get("max_duration", 60.0)), dry_run=bool(cfg.get("dry_run")),
                           n_action_steps=int(task.action_horizon) if task is not None else None)
    out_dir = Path(cfg.get("out_dir") or "deploy_runs/latest")
    started: list[Any] = []
    summary: dict[str, Any] = {"dry_run": run_cfg.dry_run, "dt": dt, "policy": type(policy).__name__,
                               "backend": rc.get("backend", "rtde")}
    try:
        for dev in start_order:
            dev.start()
            started.append(dev)
        rec = EpisodeRecorder(robot, gripper, camera)
        done = None
        if isinstance(policy, ReachPolicy):
            tol = float(cfg.get("reach_tolerance_m", 0.005))

            def done(c):  # noqa: ANN001 - CycleLog
                return pose_distance(c.tcp_pose, policy.target)[0] < tol

        runner = PolicyRunner(policy, robot, gripper, camera, MonotonicClock(), run_cfg, limits, spec, rec.on_cycle)
        try:
            runner.run(n_cycles=cfg.get("n_cycles"), done=done)
        finally:
            summary["stop_reason"] = runner.stop_reason
            summary["cycles"] = len(runner.cycles)
            if isinstance(policy, ReachPolicy) and runner.cycles:
                final = robot.get_states(1)["tcp_pose"][-1] if robot in started else runner.cycles[-1].tcp_pose
                dpos, drot = pose_distance(final, policy.target)
                summary["final_error_m"], summary["final_error_rad"] = dpos, drot
            for dev in started:  # the simulation's own counters (real-time keeping, rendered frames)
                if hasattr(dev, "sim_stats"):
                    summary.setdefault("sim", {}).update(dev.sim_stats())
            summary.update(rec.save(out_dir, fps=1.0 / (dt * run_cfg.steps_per_inference), extra=summary))
    finally:
        for dev in reversed(started):
            try:
                dev.stop()
            except Exception as exc:  # noqa: BLE001
                log.error("stopping %s failed: %s", type(dev).__name__, exc)
    summary["out_dir"] = str(out_dir)
    return summary
