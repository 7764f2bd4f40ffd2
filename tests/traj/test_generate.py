"""The driver end to end: exactly n valid episodes, endpoint exactness, splice continuity, determinism,
independent collision checks of everything emitted, reports and the plot."""

from __future__ import annotations

import os

import numpy as np
import pytest

from umi_aug.data import episode_tcp_poses
from umi_aug.errors import TrajError
from umi_aug.geometry import pose_to_pos_rotvec, rotation_geodesic_distance, tcp_poses_from_camera_poses
from umi_aug.traj import TimingConfig, TrajConfig, generate, plot_trajectories, solve, time_and_splice
from umi_aug.traj.splice import frame_kinematics
from tests.traj._helpers import RADIUS, THETA_50, assert_episode_collision_free, free_problem, obstacle_problem

_CACHE: dict = {}


def _run(mode: str):
    if mode not in _CACHE:
        pb = free_problem() if mode == "free" else obstacle_problem()
        _CACHE[mode] = (pb, generate(pb, 6, seed=123, half_angle=THETA_50, radius=RADIUS))
    return _CACHE[mode]


@pytest.mark.parametrize("mode", ["free", "obstacle"])
def test_exactly_n_valid_episodes_and_none_in_collision(mode):
    pb, res = _run(mode)
    assert len(res.episodes) == 6 and len(res.reports) == 6
    assert sum(res.status_counts.values()) == len(res.attempts) >= 6
    for ep, rep in zip(res.episodes, res.reports):
        assert rep.status == "converged"
        assert_episode_collision_free(pb, ep)
        assert rep.min_clearance >= pb.config.margin
        for a in (ep.T_world_cam, ep.T_world_tcp, ep.actions, ep.timestamps, ep.gripper_width):
            assert np.isfinite(a).all()
    if mode == "obstacle":
        assert any(r.used_rrt for r in res.reports)


@pytest.mark.parametrize("mode", ["free", "obstacle"])
def test_endpoints_are_exact_and_post_contact_is_the_original(mode):
    pb, res = _run(mode)
    demo = pb.demo
    c = demo.contact_index
    for ep, rep in zip(res.episodes, res.reports):
        n = ep.splice_index
        assert rep.start_error == 0.0 and rep.goal_error == 0.0
        np.testing.assert_array_equal(ep.T_world_cam[n:], demo.T_world_cam[c:])  # bit-exact replay
        np.testing.assert_array_equal(ep.gripper_width[n:], demo.gripper_width[c:])
        dt = demo.frame_dt
        np.testing.assert_allclose(np.diff(ep.timestamps[: n + 1]), dt, rtol=1e-12)
        np.testing.assert_allclose(ep.timestamps[n:] - ep.timestamps[n], demo.timestamps[c:] - demo.timestamps[c],
                                   atol=1e-12)
        assert ep.timestamps[0] == 0.0
        # UMI actions = TCP pose (camera pose @ T_cam_tcp) + gripper width
        np.testing.assert_allclose(ep.T_world_tcp, tcp_poses_from_camera_poses(ep.T_world_cam), atol=1e-15)
        np.testing.assert_allclose(ep.actions[:, :6], pose_to_pos_rotvec(ep.T_world_tcp), atol=1e-15)
        np.testing.assert_array_equal(ep.actions[:, 6], ep.gripper_width)
        umi = ep.umi_episode()
        np.testing.assert_allclose(episode_tcp_poses(umi), ep.T_world_tcp, atol=1e-5)  # float32 storage


@pytest.mark.parametrize("mode", ["free", "obstacle"])
def test_splice_is_continuous_in_pose_and_velocity(mode):
    pb, res = _run(mode)
    demo = pb.demo
    dt = demo.frame_dt
    kin_demo = frame_kinematics(demo.T_world_cam, dt)
    c = demo.contact_index
    demo_dv = np.linalg.norm(np.diff(kin_demo["v"], axis=0), axis=1)[c - 5:c + 5].max()
    demo_dw = np.linalg.norm(np.diff(kin_demo["w"], axis=0), axis=1)[c - 5:c + 5].max()
    tcfg = pb.config.timing
    for ep, rep in zip(res.episodes, res.reports):
        n = ep.splice_index
        kin = frame_kinematics(ep.T_world_cam, dt)
        dv = np.linalg.norm(kin["v"][n] - kin["v"][n - 1])  # velocity change across the splice frame
        dw = np.linalg.norm(kin["w"][n] - kin["w"][n - 1])
        assert dv <= max(3 * demo_dv, tcfg.max_accel * dt) + 1e-9, (dv, demo_dv)
        assert dw <= max(3 * demo_dw, tcfg.max_ang_accel * dt) + 1e-9, (dw, demo_dw)
        assert rep.splice_velocity_jump == pytest.approx(dv)
        # no teleports anywhere in the augmented segment: bounded speed and acceleration
        assert kin["speed"][:n].max() <= tcfg.max_speed and kin["accel"][: n - 1].max() <= tcfg.max_accel
        assert kin["ang_speed"][:n].max() <= tcfg.max_ang_speed
        assert kin["ang_accel"][: n - 1].max() <= tcfg.max_ang_accel
        # across the splice: as smooth as the demo itself is around its contact frame
        assert kin["accel"][n - 1] <= max(tcfg.max_accel, 1.5 * kin_demo["accel"][c - 3:c + 3].max())
        # consecutive frames never jump: bounded by max speed · dt
        step = np.linalg.norm(np.diff(ep.T_world_cam[: n + 1, :3, 3], axis=0), axis=1)
        assert step.max() <= tcfg.max_speed * dt + 1e-12


def test_gripper_width_follows_the_demo_before_contact():
    pb, res = _run("free")
    d = pb.demo
    c = d.contact_index
    for ep in res.episodes:
        n = ep.splice_index
        w = ep.gripper_width[: n + 1]
        assert w.min() >= d.gripper_width[: c + 1].min() - 1e-12 and w.max() <= d.gripper_width[: c + 1].max() + 1e-12
        assert w[0] == pytest.approx(d.gripper_width[0]) and w[-1] == d.gripper_width[c]


def test_generate_is_deterministic():
    pb = obstacle_problem()
    a = generate(pb, 3, seed=9, half_angle=THETA_50, radius=RADIUS)
    b = generate(obstacle_problem(), 3, seed=9, half_angle=THETA_50, radius=RADIUS)
    for ea, eb in zip(a.episodes, b.episodes):
        np.testing.assert_array_equal(ea.T_world_cam, eb.T_world_cam)
        np.testing.assert_array_equal(ea.actions, eb.actions)
        np.testing.assert_array_equal(ea.timestamps, eb.timestamps)
    assert [r.status for r in a.attempts] == [r.status for r in b.attempts]
    c = generate(pb, 3, seed=10, half_angle=THETA_50, radius=RADIUS)
    assert not np.array_equal(a.episodes[0].T_world_cam[0], c.episodes[0].T_world_cam[0])


def test_start_equal_goal_episode_is_the_post_contact_segment():
    pb = free_problem()
    res = solve(pb, pb.x_goal[None], 0)
    ep, timing = time_and_splice(pb.demo, res.T_world_cam[0], pb.config.timing)
    c = pb.demo.contact_index
    assert ep.splice_index == 0 and timing.duration_s == 0.0
    np.testing.assert_array_equal(ep.T_world_cam, pb.demo.T_world_cam[c:])
    assert np.isfinite(ep.actions).all()


def test_tight_speed_bounds_stretch_or_fail_cleanly():
    slow = TrajConfig(timing=TimingConfig(max_speed=0.1, max_ang_speed=0.5, max_stretch_steps=20))
    pb = free_problem(slow)
    res = generate(pb, 2, seed=4, half_angle=THETA_50, radius=RADIUS)
    for ep, rep in zip(res.episodes, res.reports):
        assert rep.max_speed <= 0.1 and rep.max_ang_speed <= 0.5
        assert rep.duration_s > 3.0  # stretched beyond the demo's ~2.2 s
    impossible = free_problem(TrajConfig(timing=TimingConfig(max_accel=1e-4, max_stretch_steps=2)))
    with pytest.raises(TrajError, match="timing_failed"):
        generate(impossible, 1, seed=4, half_angle=THETA_50, radius=RADIUS, max_rounds=1)


def test_reports_and_plot(tmp_path):
    pb, res = _run("obstacle")
    for rep in res.reports:
        d = rep.as_dict()
        for k in ("min_clearance", "max_speed", "max_accel", "rms_jerk", "render_distance_mean", "solve_time_s",
                  "iterations", "status"):
            assert k in d
        assert np.isfinite([rep.min_clearance, rep.max_speed, rep.max_accel, rep.rms_jerk,
                            rep.render_distance_mean, rep.solve_time_s]).all()
    out = plot_trajectories(tmp_path / "traj.png", pb, res.episodes, title="test")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert os.listdir(tmp_path) == ["traj.png"]  # atomic: no temporary left behind


def test_generate_argument_checks():
    pb = free_problem()
    with pytest.raises(TrajError):
        generate(pb, 0, seed=0, half_angle=THETA_50, radius=RADIUS)
    with pytest.raises(TrajError):
        pb.sample_starts(2, 0, -0.1, RADIUS)
    with pytest.raises(TrajError):
        pb.sample_starts(2, 0, THETA_50, 0.0)
    x = pb.sample_starts(5, 0, THETA_50, RADIUS)
    ang = rotation_geodesic_distance(x[:, :3, :3], pb.demo.T_world_cam[0, :3, :3])
    assert np.all(ang <= THETA_50 + 1e-9)
    piv = pb.default_pivot(RADIUS)
    np.testing.assert_allclose(np.linalg.norm(x[:, :3, 3] - piv, axis=1), RADIUS)


def test_contact_tail_relaxes_the_margin_to_the_demos_own_clearance():
    # a margin larger than the demo's own clearance at the pre-contact pose (~6 cm): only the contact tail may
    # come as close as the demo did; everywhere else the margin holds
    pb = free_problem(TrajConfig(margin=0.08))
    assert pb.required_tail.min() < 0.08
    res = generate(pb, 3, seed=2, half_angle=THETA_50, radius=RADIUS)
    for ep, rep in zip(res.episodes, res.reports):
        n = ep.splice_index
        clr = pb.sphere_clearance(ep.T_world_cam[: n + 1])
        req = pb.required_clearance(ep.progress)
        assert np.all(clr >= req - 1e-12)
        tail = ep.progress >= 1 - pb.config.contact_tail_fraction
        assert np.all(clr[~tail] >= 0.08)
        assert rep.required_clearance == pytest.approx(pb.required_tail.min())
    strict = free_problem(TrajConfig(margin=0.08, contact_tail_fraction=0.0))
    with pytest.raises(TrajError):
        generate(strict, 1, seed=2, half_angle=THETA_50, radius=RADIUS, max_rounds=1)


@pytest.mark.parametrize("where", ["first", "last"])
def test_extreme_contact_indices(where):
    from umi_aug.traj import Demonstration, TrajProblem, TrajScene
    from tests.traj._helpers import synthetic

    st = synthetic()
    d = st.demo
    H = len(d.T_world_cam)
    if where == "first":  # contact one frame after the start: the augmented segment replaces a single step
        demo = Demonstration(d.T_world_cam[d.contact_index - 1:], d.timestamps[d.contact_index - 1:],
                             d.gripper_width[d.contact_index - 1:], 1)
    else:  # contact at the last frame: nothing is replayed after the splice
        demo = Demonstration(d.T_world_cam[: d.contact_index + 1], d.timestamps[: d.contact_index + 1],
                             d.gripper_width[: d.contact_index + 1], d.contact_index)
    pb = TrajProblem(demo, TrajScene(st.sdf, st.render_views))
    res = generate(pb, 2, seed=1, half_angle=THETA_50, radius=RADIUS)
    for ep in res.episodes:
        n = ep.splice_index
        np.testing.assert_array_equal(ep.T_world_cam[n:], demo.T_world_cam[demo.contact_index:])
        assert np.isfinite(ep.actions).all() and len(ep.timestamps) == n + len(demo.T_world_cam) - demo.contact_index
    assert H > 2
