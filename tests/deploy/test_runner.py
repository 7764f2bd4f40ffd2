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
    # everything in the past: only the last action, at the next dt slot after now (from t_start)
    kept, due, n = select_actions(a, 10.0, 11.234, 0.1, 0.01, 9.0)
    assert n == 7 and np.array_equal(kept, a[-1:]) and np.allclose(due, [11.3])
    kept, due, n = select_actions(a, 10.0, 11.295, 0.1, 0.01, 9.0)  # next slot too close → one more dt
    assert np.allclose(due, [11.4])
    # a lead of several dt (exec + action latency, slow CPU policy): still the first slot after now + lead,
    # so the latency-compensated time (due − action latency) is not in the past
    kept, due, n = select_actions(a, 10.0, 11.234, 0.1, 0.4, 9.0)
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
        return orig(obs)[:n_steps]

    pol.predict_action = predict
    logs = r.run(n_cycles=2)
    assert asked == [12, 12] and all(len(c.commands) + c.n_dropped == 12 for c in logs)


def test_dry_run_sends_nothing_but_logs_commands():
    r, clock, robot, grip, cam, pol = make(dry_run=True)
    logs = r.run(n_cycles=2)
    assert robot.scheduled == [] and grip.scheduled == [] and robot.stopped == 1
    assert len(logs) == 2 and all(len(c.commands) > 0 for c in logs)


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
