"""(e) latency compensation / action scheduling / observation alignment against a fake clock;
(f) out-of-workspace command, stale frame, NaN action, lost connection → safe stop with one clear message."""

from __future__ import annotations

import numpy as np
import pytest

from umi_aug.deploy.clock import FakeClock
from umi_aug.deploy.runner import ObsSpec, PolicyRunner, RunnerConfig, select_actions
from umi_aug.deploy.safety import SafetyLimits, SafetyStop, check_command, clamp_to_table
from umi_aug.errors import DeployError

from tests.deploy.fakes import FakeCamera, KinematicGripper, KinematicRobot, ScriptedPolicy

POSE0 = np.array([0.4, 0.0, 0.3, np.pi, 0.0, 0.0])  # TCP pointing down


def make(offsets=None, *, dry_run=False, infer_s=0.05, cam_latency=0.1, limits=None, spi=6, **cfg_kw):
    clock = FakeClock(100.0)
    robot, grip = KinematicRobot(clock, POSE0), KinematicGripper(clock)
    cam = FakeCamera(clock, fps=60.0, latency=cam_latency)
    if offsets is None:
        offsets = np.zeros((16, 6))
        offsets[:, 0] = 0.002 * np.arange(16)
    pol = ScriptedPolicy(clock, offsets, infer_s=infer_s)
    cfg = RunnerConfig(dt=0.1, steps_per_inference=spi, dry_run=dry_run, start_delay=1.0, **cfg_kw)
    r = PolicyRunner(pol, robot, grip, cam, clock, cfg, limits or SafetyLimits(),
                     obs_spec=ObsSpec(img_horizon=2, low_dim_horizon=2, down_sample_steps=3))
    return r, clock, robot, grip, cam, pol


# ---------------------------------------------------------------------------------------------- (e)
def test_select_actions_drops_past_and_falls_back_to_next_slot():
    a = np.arange(8 * 7, dtype=float).reshape(8, 7)
    kept, due, n = select_actions(a, t_obs_last=10.0, now=10.25, dt=0.1, exec_latency=0.01, t_start=9.0)
    assert n == 3 and np.allclose(due, 10.0 + 0.1 * np.arange(3, 8)) and np.array_equal(kept, a[3:])
    # exactly on the boundary (now + latency) is dropped too: strictly later only
    kept, due, n = select_actions(a, 0.0, 0.25, 0.25, 0.25, -1.0)  # exact binary fractions: due 0.5 == 0.5
    assert n == 3 and np.isclose(due[0], 0.75)
    # everything in the past, UMI's rule (the default): nothing kept, all counted — the arm holds
    kept, due, n = select_actions(a, 10.0, 11.234, 0.1, 0.01, 9.0)
    assert n == 8 and kept.shape == (0, 7) and due.shape == (0,)
    # the earlier rule, opt-in: only the last action, at the next dt slot after now (from t_start)
    kept, due, n = select_actions(a, 10.0, 11.234, 0.1, 0.01, 9.0, late="next_slot")
    assert n == 7 and np.array_equal(kept, a[-1:]) and np.allclose(due, [11.3])
    kept, due, n = select_actions(a, 10.0, 11.295, 0.1, 0.01, 9.0, late="next_slot")  # slot too close → one more
    assert np.allclose(due, [11.4])
    # a lead of several dt (exec + action latency, slow CPU policy): still the first slot after now + lead,
    # so the latency-compensated time (due − action latency) is not in the past
    kept, due, n = select_actions(a, 10.0, 11.234, 0.1, 0.4, 9.0, late="next_slot")
    assert np.allclose(due, [11.7])


def test_cycle_timing_latency_compensation_and_sleep_schedule():
    r, clock, robot, grip, cam, pol = make(infer_s=0.05, cam_latency=0.1, robot_action_latency=0.1,
                                           gripper_action_latency=0.07)
    logs = r.run(n_cycles=3)
    assert len(logs) == 3 and robot.stopped == 1 and grip.stopped == 1 and cam.stopped == 1
    t_start = 100.0 + 1.0
    # sleeps: first to t_start - frame_latency, then t_start + (it + spi)·dt - frame_latency
    fl = 1 / 60
    assert np.allclose(clock.sleeps[:3], [t_start - fl, t_start + 0.6 - fl, t_start + 1.2 - fl])
    for c in logs:
        # newest frame captured ≤ now - camera latency; obs → action latency = capture delay + inference
        assert 0.1 <= c.obs_to_action_latency <= 0.1 + 1 / 60 + 0.05 + 1e-9
        # due times continue the 0.1 s grid from the obs timestamp; none is in the past when sent
        k0 = np.round((c.action_timestamps - c.obs_timestamps[-1]) / 0.1)
        assert np.allclose(c.action_timestamps, c.obs_timestamps[-1] + 0.1 * k0)
        # none is due before now + exec latency + the largest action latency (its scheduled time would be past)
        assert (c.action_timestamps > c.t_action_sent + 0.01 + 0.1 - 1e-12).all()
        assert c.n_dropped == int(k0[0]) and c.n_dropped >= 3  # 0.1 s camera + 0.05 s inference + 0.11 s lead
        assert len(c.commands) + c.n_dropped == 16
    # robot waypoints scheduled at due − robot_action_latency, gripper at due − gripper_action_latency
    due = np.concatenate([c.action_timestamps for c in logs])
    assert np.allclose([t for _, t, _ in robot.scheduled], due - 0.1)
    assert np.allclose([t for _, t in grip.scheduled], due - 0.07)
    cmds = np.concatenate([c.commands for c in logs])
    assert np.allclose([p for p, _, _ in robot.scheduled], cmds[:, :6])


def test_observation_alignment_interpolates_robot_to_camera_timestamps():
    r, clock, robot, grip, cam, pol = make()
    # robot moving at constant speed along y from t=100 to 103 (0.1 m/s), observed with 2 ms latency
    target = POSE0.copy()
    target[1] += 0.3
    robot.interp = robot.interp.schedule_waypoint(target, 103.0, 1.0, 1.0, 100.0)
    robot.obs_latency = 0.002
    clock.t = 101.237
    obs, ts = r.get_obs()
    # camera: newest frame is floor((now - 0.1)·60)/60; low-dim timestamps step 3 frames back
    t_last = np.floor((101.237 - 0.1) * 60) / 60
    assert np.allclose(ts, [t_last - 3 / 60, t_last])
    assert np.allclose(obs["robot0_eef_pos"][:, 1], 0.1 * (ts - 100.0), atol=1e-9)
    assert np.allclose(obs["robot0_eef_rot_axis_angle"], POSE0[3:])
    # image frames are the ones captured at those timestamps (pixel value = frame index mod 256)
    assert np.array_equal(obs["camera0_rgb"][:, 0, 0, 0], (np.round(ts * 60) % 256).astype(np.uint8))
    assert obs["robot0_gripper_width"].shape == (2, 1)


def test_n_action_steps_is_passed_to_the_policy():
    r, clock, robot, grip, cam, pol = make(n_action_steps=12)
    asked = []
    orig = pol.predict_action

    def predict(obs, n_steps=None):
        asked.append(n_steps)
        return {"action": orig(obs)["action"][:n_steps]}

    pol.predict_action = predict
    logs = r.run(n_cycles=2)
    assert asked == [12, 12] and all(len(c.commands) + c.n_dropped == 12 for c in logs)


def test_dry_run_sends_nothing_but_logs_commands():
    r, clock, robot, grip, cam, pol = make(dry_run=True)
    logs = r.run(n_cycles=2)
    assert robot.scheduled == [] and grip.scheduled == [] and robot.stopped == 1
    assert len(logs) == 2 and all(len(c.commands) > 0 and c.would_stop == [] for c in logs)


def test_dry_run_records_would_be_stops_and_goes_on():
    off = np.zeros((16, 6))
    off[:, 0] = 0.05  # x 0.45 m > workspace_max 0.42 m: a real run stops in cycle 1
    lim = SafetyLimits(workspace_min=[0.0, -0.5, 0.0], workspace_max=[0.42, 0.5, 0.6])
    r, clock, robot, grip, cam, pol = make(off, limits=lim, dry_run=True)
    logs = r.run(n_cycles=3)
    assert len(logs) == 3 and robot.scheduled == [] and grip.scheduled == []
    assert all(len(c.would_stop) == len(c.commands) > 0 for c in logs)
    assert "outside the workspace box" in logs[0].would_stop[0]
    assert np.allclose(logs[0].commands[:, 0], 0.45)  # the raw would-be command is what was recorded


# ---------------------------------------------------------------------------------------------- (f)
def _run_expect_stop(r, robot, grip, match):
    with pytest.raises(SafetyStop, match=match) as ei:
        r.run(n_cycles=5)
    assert robot.stopped == 1 and grip.stopped == 1  # halted on the way out
    assert r.stop_reason == str(ei.value) and "\n" not in r.stop_reason
    return ei.value


def test_command_outside_workspace_stops_before_sending():
    off = np.zeros((16, 6))
    off[:, 0] = 0.05  # x 0.45 m > workspace_max 0.42 m
    lim = SafetyLimits(workspace_min=[0.0, -0.5, 0.0], workspace_max=[0.42, 0.5, 0.6])
    r, clock, robot, grip, cam, pol = make(off, limits=lim)
    _run_expect_stop(r, robot, grip, r"outside the workspace box")
    assert robot.scheduled == [] and grip.scheduled == []


def test_stale_frame_stops():
    r, clock, robot, grip, cam, pol = make()
    cam.frozen_at = 101.0  # camera stream stalls; the loop keeps going
    _run_expect_stop(r, robot, grip, r"stale camera observation")
    assert len(r.cycles) >= 1  # it ran normally while the frames were fresh


def test_nan_action_stops():
    off = np.zeros((16, 6))
    off[5:, 2] = np.nan
    r, clock, robot, grip, cam, pol = make(off)
    _run_expect_stop(r, robot, grip, r"non-finite command")
    assert robot.scheduled == []


def test_lost_connection_stops():
    r, clock, robot, grip, cam, pol = make()
    orig = pol.predict_action

    def predict(obs):
        if len(pol.seen) == 2:
            robot.disconnect()
        return orig(obs)

    pol.predict_action = predict
    _run_expect_stop(r, robot, grip, r"stale robot observation")
    assert len(r.cycles) == 3  # the cycle during which it dropped completes; the next one refuses


def _raise_in_cycle(pol, n: int, exc: BaseException) -> None:
    """Make ``pol.predict_action`` raise ``exc`` in inference cycle ``n`` (0-based)."""
    orig = pol.predict_action

    def predict(obs):
        if len(pol.seen) == n:
            pol.seen.append(obs)
            raise exc
        return orig(obs)

    pol.predict_action = predict


def test_policy_exception_halts_robot_and_gripper():
    """Already safe before #31 (docs/deploy_safety.md): an exception inside the policy propagates after robot,
    gripper and camera are stopped; nothing is scheduled in the failing cycle."""
    r, clock, robot, grip, cam, pol = make()
    _raise_in_cycle(pol, 2, RuntimeError("CUDA error: device-side assert triggered"))
    with pytest.raises(RuntimeError, match="CUDA error"):
        r.run(n_cycles=5)
    assert robot.stopped == 1 and grip.stopped == 1 and cam.stopped == 1
    assert len(r.cycles) == 2 and len(robot.scheduled) == sum(len(c.commands) for c in r.cycles) > 0  # good ones
    assert r.stop_reason == "CUDA error: device-side assert triggered"


def test_ctrl_c_halts_robot_and_gripper():
    """Already safe before #31: Ctrl-C (KeyboardInterrupt in the runner) ends the run normally after the halt, with
    its reason recorded (the device children ignore SIGINT and run their own stop sequence when stopped)."""
    r, clock, robot, grip, cam, pol = make()
    _raise_in_cycle(pol, 1, KeyboardInterrupt())
    logs = r.run(n_cycles=5)
    assert len(logs) == 1 and robot.stopped == 1 and grip.stopped == 1 and cam.stopped == 1
    assert r.stop_reason == "stopped by the user (Ctrl-C)"


def test_max_step_and_table_clamp():
    lim = SafetyLimits(max_step_m=0.05, height_threshold=0.0)
    cur = POSE0.copy()
    far = cur.copy()
    far[0] += 0.06
    with pytest.raises(SafetyStop, match="max_step_m=0.05"):
        check_command(far, 0.05, cur, lim)
    low = cur.copy()
    low[2] = -0.01
    pose, w = check_command(low, 0.2, np.r_[cur[:2], 0.0, cur[3:]], lim)
    assert pose[2] == pytest.approx(0.0) and w == pytest.approx(0.09)  # raised to the table, width clipped
    # tilted 90° about y: finger corners at ±width/2 along base z → TCP raised by width/2
    tilted = np.array([0.4, 0.0, 0.0, 0.0, np.pi / 2, 0.0])
    assert clamp_to_table(tilted, 0.08, 0.0)[2] == pytest.approx(0.04)
    with pytest.raises(DeployError, match="workspace_min/max"):
        SafetyLimits.from_mapping({"workspace_min": [0, 0, 1], "workspace_max": [1, 1, 0]})
    with pytest.raises(DeployError, match="unknown key"):
        SafetyLimits.from_mapping({"max_stepp": 1})


# ---------------------------------------------------------------------------------------------- #31 item 5
@pytest.mark.parametrize("key, value, match", [
    ("max_step_m", 50.0, r"safety.max_step_m=50.0 is outside \(0, 0.5\] \(m; a UMI chunk"),
    ("max_step_rad", 3.2, r"safety.max_step_rad=3.2 is outside \(0, 3.14159"),
    ("max_obs_age_s", 1e9, r"safety.max_obs_age_s=1000000000.0 is outside \(0, 1\]"),
    ("max_obs_age_s", 0.0, r"safety.max_obs_age_s=0.0 is outside \(0, 1\]"),
    ("height_threshold", -1e9, r"safety.height_threshold=-1000000000.0 is outside \[-0.1, 1\] \(m; UMI's is"),
    ("gripper_max_m", 0.2, r"safety.gripper_max_m=0.2 is outside \(0, 0.11\] \(m; the WSG-50"),
    ("workspace_max", [100.0, 100.0, 100.0], r"safety.workspace_min/max: corner \[100.0, 100.0, 100.0\] m is "
                                            r"173.\d+ m from the shoulder > the reach 1.085 m"),
])
def test_safety_limits_are_bounded(key, value, match):
    with pytest.raises(DeployError, match=match):
        SafetyLimits.from_mapping({key: value}, "safety", tcp_offset=0.235)


@pytest.mark.parametrize("key, value, match", [
    ("max_pos_speed", 100.0, r"robot.max_pos_speed=100.0 is outside \(0, 1\] \(m/s; UR's default TCP speed"),
    ("max_pos_speed", 1.5, r"robot.max_pos_speed=1.5 is outside \(0, 1\]"),
    ("max_rot_speed", 4.0, r"robot.max_rot_speed=4.0 is outside \(0, 3.14159"),
    ("watchdog_s", 1e6, r"robot.watchdog_s=1000000.0 is outside \[0.2, 1\]"),
    ("watchdog_s", 0.05, r"robot.watchdog_s=0.05 is outside \[0.2, 1\]"),
])
def test_robot_limits_are_bounded_for_the_arm_and_the_simulation(key, value, match):
    from umi_aug.deploy.sim_ur5e import SimURConfig
    from umi_aug.deploy.ur_rtde import URConfig

    for cls in (URConfig, SimURConfig):
        with pytest.raises(DeployError, match=match):
            cls.from_mapping({key: value}, "robot")
    # UMI's own eval speeds only with the explicit flag, and never above them
    URConfig.from_mapping({"max_pos_speed": 3.0, "max_rot_speed": 10.0, "allow_fast_speeds": True})
    with pytest.raises(DeployError, match=r"robot.max_pos_speed=5.0 is outside \(0, 3.4641"):
        URConfig.from_mapping({"max_pos_speed": 5.0, "allow_fast_speeds": True}, "robot")


def test_shipped_robot_configs_are_within_the_bounds():
    import yaml
    from pathlib import Path

    from umi_aug.deploy.sim_ur5e import SimURConfig
    from umi_aug.deploy.ur_rtde import URConfig

    root = Path(__file__).resolve().parents[2] / "configs" / "robot"
    for name, cls in (("ur5e.yaml", URConfig), ("sim_ur5e.yaml", SimURConfig)):
        rc = yaml.safe_load((root / name).read_text())
        r = cls.from_mapping(rc["robot"], "robot.robot")
        SafetyLimits.from_mapping(rc["safety"], "robot.safety", tcp_offset=r.tcp_offset)


def test_start_pose_check():
    from umi_aug.deploy.safety import check_start_pose

    lim = SafetyLimits(workspace_min=[0.0, -0.5, 0.0], workspace_max=[0.42, 0.5, 0.6], height_threshold=0.0)
    check_start_pose(POSE0, 0.05, lim)
    with pytest.raises(SafetyStop, match=r"current TCP \[0.5, 0.0, 0.3\] m is outside the workspace box"):
        check_start_pose(POSE0 + [0.1, 0, 0, 0, 0, 0], 0.05, lim)
    tilted = np.array([0.4, 0.0, 0.02, 0.0, np.pi / 2, 0.0])  # fingers ±4 cm along z: 20 mm below the table
    with pytest.raises(SafetyStop, match=r"are 20.0 mm below safety.height_threshold=0.0"):
        check_start_pose(tilted, 0.08, lim)


def test_runner_checks_the_start_pose_before_the_first_command():
    lim = SafetyLimits(workspace_min=[0.5, -0.5, 0.0], workspace_max=[0.8, 0.5, 0.6])  # excludes x = 0.4
    r, clock, robot, grip, cam, pol = make(limits=lim)
    with pytest.raises(SafetyStop, match="start-up check"):
        r.run(n_cycles=2)
    assert robot.scheduled == [] and pol.seen == [] and robot.stopped == 1


# ---------------------------------------------------------------------------------------------- #31 item 6
def test_two_second_inference_drops_the_stale_chunk_and_holds():
    """A 2 s inference (fake clock): by UMI's rule nothing computed from the 2-s-old observation is sent, the arm
    holds, every action is counted as dropped, and the run goes on."""
    lim = SafetyLimits(max_obs_age_s=1.0)
    r, clock, robot, grip, cam, pol = make(infer_s=2.0, limits=lim)
    logs = r.run(n_cycles=3)
    assert r.stop_reason == "3 cycles done" and len(logs) == 3
    assert robot.scheduled == [] and grip.scheduled == []  # held: nothing sent
    assert all(c.held and c.stale and c.n_dropped == 16 for c in logs)
    assert np.allclose(robot.get_states(1)["tcp_pose"][-1], POSE0)


def test_two_second_inference_next_slot_rule_is_the_explicit_old_behaviour():
    lim = SafetyLimits(max_obs_age_s=1.0)
    r, clock, robot, grip, cam, pol = make(infer_s=2.0, limits=lim, late_actions="next_slot")
    logs = r.run(n_cycles=2)
    assert [len(c.commands) for c in logs] == [1, 1] and not any(c.stale for c in logs)
    # the last action of the 2-s-old chunk, moved to the first slot after now + lead (its compensated time ahead)
    for c, (pose, t, t_call) in zip(logs, robot.scheduled):
        assert np.allclose(pose, c.tcp_pose + [0.03, 0, 0, 0, 0, 0]) and t > t_call


def test_late_actions_are_dropped_by_umis_rule_without_a_stale_observation():
    """0.5 s inference, an 8-action chunk (0.7 s): every action's compensated time has passed, the observation is
    not too old (0.6 s < 1 s): dropped, counted, held; the later actions of a 16-action chunk are kept."""
    lim = SafetyLimits(max_obs_age_s=1.0)
    off8 = np.zeros((8, 6))
    off8[:, 0] = 0.002 * np.arange(8)
    r, clock, robot, grip, cam, pol = make(off8, infer_s=0.5, limits=lim)
    logs = r.run(n_cycles=2)
    assert robot.scheduled == [] and all(c.held and not c.stale and c.n_dropped == 8 for c in logs)
    r, clock, robot, grip, cam, pol = make(infer_s=0.5, limits=lim)
    logs = r.run(n_cycles=2)
    assert all(not c.held and 0 < c.n_dropped < 16 for c in logs) and len(robot.scheduled) > 0
    for c in logs:  # kept actions' compensated times are ahead of when they were sent
        assert (c.action_timestamps - 0.1 > c.t_action_sent).all()


def test_observation_age_is_rechecked_after_inference():
    """0.5 s inference, max_obs_age_s 0.55: the observation was fresh (≈0.1 s) when read but ≈0.6 s old when the
    chunk came back: the whole chunk is dropped although its later actions are still in the future."""
    r, clock, robot, grip, cam, pol = make(infer_s=0.5, limits=SafetyLimits(max_obs_age_s=0.55))
    logs = r.run(n_cycles=2)
    assert robot.scheduled == [] and all(c.stale and c.held and c.n_dropped == 16 for c in logs)


def test_late_actions_config_is_checked():
    with pytest.raises(DeployError, match=r"late_actions='fallback'; expected one of \['drop', 'next_slot'\]"):
        RunnerConfig(late_actions="fallback")
