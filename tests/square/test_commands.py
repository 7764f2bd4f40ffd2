"""The square env's commanded targets (issue #29 B2): what the OSC was told, and the exact way back to its deltas."""

from __future__ import annotations

import numpy as np
import pytest

from umi_aug.errors import SimError
from umi_aug.geometry import pos_rotvec_to_pose, pose_to_pos_rotvec, so3_exp, so3_log
from umi_aug.square.commands import (GRIPPER_OPEN_M, commanded_targets, gripper_command, gripper_width_target,
                                         osc_delta_from_target, path_command_targets)


def _random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0.0, np.pi, n)
    angle[: n // 4] = np.pi - rng.uniform(0.0, 1e-6, n // 4)  # rotations near π
    T[:, :3, :3] = so3_exp(axis * angle[:, None])
    T[:, :3, 3] = rng.uniform(-1.0, 1.0, (n, 3))
    return T


def _reference_targets(T: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Row by row, as robosuite's OSC set_goal does it (obviously correct, slow)."""
    out = [np.concatenate([pose_to_pos_rotvec(T[0]), [0.0 if a[0, 6] > 0 else GRIPPER_OPEN_M]])]
    goal_R = T[0, :3, :3]
    for t in range(len(T) - 1):
        u = np.clip(a[t], -1.0, 1.0)
        p = T[t, :3, 3] + 0.05 * u[:3]
        if any(x != 0.0 for x in u[3:6]):  # robosuite: math.isclose(elem, 0.0) for each component
            goal_R = so3_exp(0.5 * u[3:6]) @ T[t, :3, :3]
        G = np.eye(4)
        G[:3, :3], G[:3, 3] = goal_R, p
        out.append(np.concatenate([pose_to_pos_rotvec(G), [0.0 if u[6] > 0 else GRIPPER_OPEN_M]]))
    return np.array(out)


def test_commanded_targets_match_the_reference_and_invert_exactly(rng):
    n = 64
    T = _random_poses(rng, n)
    a = rng.uniform(-1.3, 1.3, (n, 7))  # some beyond the controller's clip
    a[rng.choice(n, 16, replace=False), 3:6] = 0.0  # exactly-zero rotation: the OSC keeps its previous goal
    a[:, 6] = rng.choice([-1.0, 1.0], n)
    c = commanded_targets(T, a)
    assert c.shape == (n, 7) and np.isfinite(c).all()
    ref = _reference_targets(T, a)
    np.testing.assert_allclose(c[:, :3], ref[:, :3], atol=1e-12)
    for t in range(n):  # rotation vectors near π may flip sign: compare the rotations
        R, Rr = pos_rotvec_to_pose(c[t, :6])[:3, :3], pos_rotvec_to_pose(ref[t, :6])[:3, :3]
        assert np.linalg.norm(so3_log(R @ Rr.T)) < 1e-9
    np.testing.assert_array_equal(c[:, 6], ref[:, 6])
    # executing target t+1 from pose t gives back the clipped action (nonzero rotation rows)
    for t in range(n - 1):
        back = osc_delta_from_target(T[t], c[t + 1])
        u = np.clip(a[t], -1.0, 1.0)
        np.testing.assert_allclose(back[:3], u[:3], atol=1e-9)
        if np.any(u[3:6] != 0.0):
            np.testing.assert_allclose(back[3:6], u[3:6], atol=1e-8)
        assert back[6] == u[6]


def test_targets_and_deltas_reject_bad_input():
    T = np.tile(np.eye(4), (3, 1, 1))
    with pytest.raises(SimError, match="NaN"):
        commanded_targets(T, np.full((3, 7), np.nan))
    with pytest.raises(SimError, match=r"\[T, 7\]"):
        commanded_targets(T, np.zeros((2, 7)))
    with pytest.raises(SimError, match="finite"):
        osc_delta_from_target(np.eye(4), np.array([0, 0, 0, 0, 0, 0, np.inf]))
    with pytest.raises(SimError, match="lead_steps"):
        path_command_targets(T, np.zeros(3), lead_steps=-1.0)


def test_gripper_targets_round_trip():
    cmd = np.array([-1.0, 1.0, 0.3, -0.2])
    w = gripper_width_target(cmd)
    np.testing.assert_array_equal(w, [GRIPPER_OPEN_M, 0.0, 0.0, GRIPPER_OPEN_M])
    assert [gripper_command(x) for x in w] == [-1.0, 1.0, 1.0, -1.0]


def test_path_targets_lead_along_the_path_and_rest_at_its_end(rng):
    n, lead = 20, 3.0
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = np.linspace(0.0, 0.19, n)[:, None] * np.array([1.0, 0.5, 0.0])  # 1 cm per step along x
    T[:, :3, :3] = so3_exp(np.linspace(0.0, 0.6, n)[:, None] * np.array([0.0, 0.0, 1.0]))
    w = np.full(n, 0.08)
    w[-2:] = 0.01
    c = path_command_targets(T, w, lead)
    np.testing.assert_allclose(c[0, :6], pose_to_pos_rotvec(T[0]), atol=1e-12)
    for t in range(1, n - 4):  # row t = the pose `lead` steps after t − 1
        np.testing.assert_allclose(c[t, :6], pose_to_pos_rotvec(T[t - 1 + 3]), atol=1e-9)
    np.testing.assert_allclose(c[-3:, :6], np.tile(pose_to_pos_rotvec(T[-1]), (3, 1)), atol=1e-12)
    half = path_command_targets(T, w, 2.5)[5, :3]  # fractional lead: between two path poses
    np.testing.assert_allclose(half, 0.5 * (T[6, :3, 3] + T[7, :3, 3]), atol=1e-12)
    assert list(c[:, 6]) == [GRIPPER_OPEN_M] * (n - 2) + [0.0, 0.0]


@pytest.fixture(scope="module")
def env():
    pytest.importorskip("robosuite")
    from umi_aug.square.env import SquareEnv

    e = SquareEnv(image_size=None)
    yield e
    e.close()


@pytest.fixture(scope="module")
def expert_episode(env):
    from umi_aug.square.episode import rollout_expert

    ep = rollout_expert(env, seed=2, render=False)
    assert ep.success
    return ep


def test_a_restored_start_state_behaves_like_a_reset(env, expert_episode):
    """reset_to(initial=True) puts the controller where robosuite's reset leaves it (posture reference, goal): the
    demo's own actions replayed from its first state after a reset with ANOTHER seed reproduce its states (without
    it they diverged at step 1 by 0.3)."""
    ep = expert_episode
    env.reset(seed=0)
    env.reset_to(ep.states[0], initial=True)
    for t in range(60):
        np.testing.assert_allclose(env.get_state()[1:], ep.states[t][1:], atol=1e-5, err_msg=f"step {t}")
        env.step(ep.actions[t])


def test_commanded_targets_executed_from_the_current_pose_reproduce_the_demo(env, expert_episode):
    """The label/controller contract: target t+1 turned into a delta from the CURRENT pose is the demo's action, so
    the arm retraces the demo through grasp and insertion and the task succeeds."""
    ep = expert_episode
    c = commanded_targets(ep.T_world_tcp, ep.actions)
    env.reset(seed=0)
    env.reset_to(ep.states[0], initial=True)
    success = False
    for t in range(len(ep) - 1):
        env.step(osc_delta_from_target(env.tcp_pose(), c[t + 1]))
        success = success or env.is_success()
    np.testing.assert_allclose(env.tcp_pose()[:3, 3], ep.T_world_tcp[-1, :3, 3], atol=1e-4)
    assert success


def test_path_targets_drive_the_arm_along_a_demo_approach(env, expert_episode):
    """A kinematic path's lead targets (what augmented frames are labelled with) bring the simulated arm along the
    path to its end: the expert's own approach (up to its pre-grasp hover pose, where augmented episodes splice) as
    the path. An approximation (module docstring): it lags while the expert accelerates at its clip and overshoots
    a little after the end, so it is measured, not exact."""
    from umi_aug.square.env import NUT_BODY
    from umi_aug.square.source import splice_index

    ep = expert_episode
    nut = []
    for t in range(len(ep)):
        env.reset_to(ep.states[t])
        nut.append(env.body_pose(NUT_BODY))
    K = splice_index(ep.T_world_tcp, np.array(nut), float(env.rs.table_offset[2]))
    c = path_command_targets(ep.T_world_tcp[: K + 1], ep.gripper_width[: K + 1])
    env.reset(seed=0)
    env.reset_to(ep.states[0], initial=True)
    dev = []
    for t in range(K + 30):
        env.step(osc_delta_from_target(env.tcp_pose(), c[min(t + 1, K)]))
        dev.append(np.linalg.norm(env.tcp_pose()[:3, 3] - ep.T_world_tcp[min(t + 1, K), :3, 3]))
    assert dev[-1] < 4e-3, f"ends {dev[-1] * 1e3:.2f} mm from the path's end"
    assert max(dev) < 0.08  # the lag while the expert accelerates at its clip (measured 15-60 mm over 14 demos)
