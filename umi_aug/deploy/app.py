"""Assemble and run one deployment episode from a config mapping (what ``eval/deploy_ur.py`` calls).

Config keys (``configs/deploy_ur.yaml`` + ``configs/robot/*.yaml`` + ``configs/deploy_policy/*.yaml``):
``robot.{backend,robot,gripper,camera,safety}``, ``policy.{kind,...}``, ``checkpoint``, ``out_dir``, ``dry_run``,
``confirm``, ``dt``, ``steps_per_inference``, ``max_duration``, ``start_delay``, ``n_cycles``, ``device``,
``reach_tolerance_m``.

Order of one episode: every config value is checked (bounds included) → the devices start **observe-only**
(nothing sent to arm or gripper) → pre-flight: one observation and one policy call (current TCP, first chunk) →
on a real arm (``robot.backend=rtde``) the operator confirms what will move (or ``confirm=true``) → unless
``dry_run``, the devices are enabled → the policy loop → halt → recording.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from umi_aug.config_check import reject_unknown_keys
from umi_aug.deploy.camera import CameraConfig, UVCCamera
from umi_aug.deploy.clock import MonotonicClock
from umi_aug.deploy.interpolator import pose_distance
from umi_aug.deploy.policies import ReachPolicy
from umi_aug.deploy.recorder import EpisodeRecorder
from umi_aug.deploy.runner import ObsSpec, PolicyRunner, Preflight, RunnerConfig
from umi_aug.deploy.safety import SafetyLimits
from umi_aug.deploy.sim_ur5e import (SimCameraConfig, SimFisheyeCamera, SimGripper, SimGripperConfig, SimUR5eRobot,
                                     SimURConfig, base_pose_matrix)
from umi_aug.deploy.ur_rtde import URConfig, URRTDERobot
from umi_aug.deploy.wsg50 import WSG50Gripper, WSGConfig
from umi_aug.errors import DeployError

__all__ = ["run_deploy"]

log = logging.getLogger(__name__)

RUN_KEYS = {"robot", "policy", "checkpoint", "out_dir", "dry_run", "confirm", "dt", "steps_per_inference",
            "max_duration", "start_delay", "n_cycles", "device", "reach_tolerance_m", "action_exec_latency",
            "late_actions"}


def _camera_cfg(m: Mapping[str, Any]) -> CameraConfig:
    reject_unknown_keys(m, CameraConfig.__dataclass_fields__, "robot.camera", DeployError)
    return CameraConfig(**{k: (str(v) if k == "device" else v) for k, v in m.items()})


def _build_policy(cfg: Mapping[str, Any], fps: float) -> tuple[Any, ObsSpec, float]:
    p = dict(cfg.get("policy") or {})
    kind = p.pop("kind", "checkpoint")
    if kind == "reach":
        pol = ReachPolicy(**p)
        return pol, ObsSpec(1, 2, 3), float(cfg.get("dt") or pol.dt)
    if kind == "checkpoint":
        ckpt = cfg.get("checkpoint")
        # lazy, start-up: torch
        from umi_aug.policy.checkpoint import checkpoint_file_problem
        from umi_aug.policy.inference import Policy

        problem = checkpoint_file_problem(ckpt) if ckpt else "no such file"
        if problem == "no such file":
            raise DeployError(f"checkpoint={ckpt!r}: not a file; pass checkpoint=PATH (or policy=reach)")
        if problem:  # a folder: the run folder instead of its checkpoints/latest.ckpt?
            raise DeployError(f"checkpoint={ckpt}: {problem}")

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
        ur = SimURConfig.from_mapping(rc.get("robot") or {}, "robot.robot")
        grip_cfg = SimGripperConfig.from_mapping(rc.get("gripper") or {}, "robot.gripper")
        cam_cfg = SimCameraConfig.from_mapping(rc.get("camera") or {}, "robot.camera")
        robot, gripper = SimUR5eRobot(ur), SimGripper(grip_cfg)
        camera = SimFisheyeCamera(cam_cfg, robot, gripper, base_pose_matrix(ur.base_pose))
        return camera, gripper, robot, [gripper, robot, camera], (ur, grip_cfg, cam_cfg)
    raise DeployError(f"robot.backend={backend!r}; expected 'rtde' (a real arm) or 'sim' (simulated UR5e)")


def late_action_counts(cycles: list[Any], rule: str) -> dict[str, Any]:
    """How the late-action rule acted over an episode: actions dropped, cycles in which the arm held (nothing
    sent), chunks dropped whole because their observation was too old after inference."""
    return {"rule": rule, "n_dropped": int(sum(c.n_dropped for c in cycles)),
            "n_hold_cycles": int(sum(c.held for c in cycles)), "n_stale_chunks": int(sum(c.stale for c in cycles))}


def _would_stop_summary(cycles: list[Any], keep: int = 20) -> dict[str, Any]:
    """Dry run: how many would-be commands would have stopped the run, in which cycle first, and the first
    ``keep`` distinct reasons."""
    reasons = [(i, r) for i, c in enumerate(cycles) for r in c.would_stop]
    distinct = list(dict.fromkeys(r for _, r in reasons))
    return {"n_commands": len(reasons), "first_cycle": reasons[0][0] if reasons else None,
            "reasons": distinct[:keep]}


def _fmt(v: Any, nd: int = 3) -> str:
    return str(np.round(np.asarray(v, float), nd).tolist())


def confirmation_text(ur: Any, limits: SafetyLimits, pre: Preflight, policy: Any) -> str:
    """What the operator of a real arm sees before it moves: robot IP, TCP, workspace box, speed limits, the
    current TCP and the first commanded target with its distance (positions in m, base frame; rotations rad)."""
    first, last = pre.actions[0], pre.actions[-1]
    d_first, d_last = pose_distance(pre.tcp_pose, first[:6]), pose_distance(pre.tcp_pose, last[:6])
    lines = [
        f"About to move a REAL arm: {ur.robot_type} at robot_ip={ur.robot_ip}",
        f"  TCP: setTcp([0, 0, {ur.tcp_offset}, 0, 0, 0]) (robot.robot.tcp_offset, m along the flange z axis)",
        f"  workspace box (safety.workspace_min/max, m): {_fmt(limits.workspace_min)} .. {_fmt(limits.workspace_max)};"
        f" table height_threshold {limits.height_threshold} m",
        f"  speed limits: max_pos_speed {ur.max_pos_speed} m/s, max_rot_speed {ur.max_rot_speed} rad/s; max step "
        f"from the current TCP {limits.max_step_m} m / {limits.max_step_rad} rad",
        f"  current TCP: {_fmt(pre.tcp_pose)}; gripper {pre.gripper_width:.3f} m",
        f"  first target: {_fmt(first[:6])}, {d_first[0]:.3f} m / {d_first[1]:.3f} rad from the current TCP",
        f"  end of the first chunk ({len(pre.actions)} actions, {len(pre.actions) * pre.dt:.1f} s): {_fmt(last[:6])}, "
        f"{d_last[0]:.3f} m / {d_last[1]:.3f} rad away",
    ]
    if ur.joints_init is not None:
        lines.append(f"  FIRST a moveJ to joints_init={_fmt(ur.joints_init, 1)} deg (the poses above are before it)")
    if isinstance(policy, ReachPolicy):
        d = pose_distance(pre.tcp_pose, policy.target)
        lines.append(f"  reach target: {_fmt(policy.target)}, {d[0]:.3f} m / {d[1]:.3f} rad from the current TCP")
    return "\n".join(lines)


def confirm_real_arm(text: str, confirm: bool, ask: Callable[[str], str | None] | None) -> None:
    """Require an explicit yes before a real arm moves: ``confirm`` (``confirm=true`` on the command line), or
    ``ask(text)`` answering ``yes`` (an interactive prompt; ``ask`` is None or returns None when there is no
    terminal).

    Raises:
        DeployError: not confirmed (nothing was sent to the arm).
    """
    if confirm:
        log.warning("confirm=true: moving the real arm without a prompt\n%s", text)
        return
    answer = ask(text) if ask is not None else None
    if answer is None:
        raise DeployError("robot.backend=rtde moves a real arm: confirm at the interactive prompt, or pass "
                          "confirm=true for scripted use; nothing was sent to the arm")
    if answer.strip().lower() != "yes":
        raise DeployError(f"not confirmed (answer {answer.strip()!r}, expected 'yes'); nothing was sent to the arm")
    log.info("confirmed by the operator\n%s", text)


def run_deploy(cfg: Mapping[str, Any], ask: Callable[[str], str | None] | None = None) -> dict[str, Any]:
    """Check the config, connect observe-only, pre-flight, confirm (real arm), enable, run one episode, halt,
    record. Returns the summary (also ``out_dir/timing.json``).

    Args:
        cfg: the composed config mapping.
        ask: shows the confirmation text and returns the operator's answer (None: no terminal); used only for
            ``robot.backend=rtde`` without ``dry_run`` or ``confirm``.

    Raises:
        DeployError: bad config, not confirmed, or a safety stop (after the robot was halted and the episode
            recorded).
    """
    reject_unknown_keys(cfg, RUN_KEYS, "deploy config", DeployError)
    rc = cfg.get("robot") or {}
    unknown = sorted(set(rc) - {"backend", "robot", "gripper", "camera", "safety"})
    if unknown:
        raise DeployError(f"robot config: unknown block(s) {unknown}; expected backend, robot, gripper, camera, "
                          f"safety")
    camera, gripper, robot, start_order, (ur, wsg, cam_cfg) = _build_backends(rc)
    limits = SafetyLimits.from_mapping(rc.get("safety") or {}, "robot.safety", tcp_offset=ur.tcp_offset)
    policy, spec, dt = _build_policy(cfg, cam_cfg.fps)
    task = getattr(policy, "task", None)  # a checkpoint: the whole predicted horizon, as UMI's action_pred
    run_cfg = RunnerConfig(dt=dt, steps_per_inference=int(cfg.get("steps_per_inference", 6)),
                           robot_action_latency=ur.action_latency, gripper_action_latency=wsg.action_latency,
                           action_exec_latency=float(cfg.get("action_exec_latency", 0.01)),
                           frame_latency=1.0 / cam_cfg.fps, start_delay=float(cfg.get("start_delay", 1.0)),
                           max_duration=float(cfg.get("max_duration", 60.0)), dry_run=bool(cfg.get("dry_run")),
                           n_action_steps=int(task.action_horizon) if task is not None else None,
                           late_actions=str(cfg.get("late_actions", "drop")))
    out_dir = Path(cfg.get("out_dir") or "deploy_runs/latest")
    started: list[Any] = []
    summary: dict[str, Any] = {"dry_run": run_cfg.dry_run, "dt": dt, "policy": type(policy).__name__,
                               "backend": rc.get("backend", "rtde")}
    try:
        for dev in start_order:  # observe-only: nothing is sent to arm or gripper yet
            dev.start()
            started.append(dev)
        rec = EpisodeRecorder(robot, gripper, camera)
        done = None
        if isinstance(policy, ReachPolicy):
            tol = float(cfg.get("reach_tolerance_m", 0.005))

            def done(c):  # noqa: ANN001 - CycleLog
                return pose_distance(c.tcp_pose, policy.target)[0] < tol

        runner = PolicyRunner(policy, robot, gripper, camera, MonotonicClock(), run_cfg, limits, spec, rec.on_cycle)
        pre = runner.preflight()
        summary["start_tcp_pose"] = pre.tcp_pose.tolist()
        if summary["backend"] == "rtde" and not run_cfg.dry_run:
            confirm_real_arm(confirmation_text(ur, limits, pre, policy), bool(cfg.get("confirm")), ask)
        if not run_cfg.dry_run:
            gripper.enable()
            robot.enable()
        try:
            runner.run(n_cycles=cfg.get("n_cycles"), done=done)
        finally:
            summary["stop_reason"] = runner.stop_reason
            summary["cycles"] = len(runner.cycles)
            if run_cfg.dry_run:
                summary["dry_run_would_stop"] = _would_stop_summary(runner.cycles)
            summary["late_actions"] = late_action_counts(runner.cycles, run_cfg.late_actions)
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
