"""Panda feasibility of wrist-camera paths (IK along the path, limits, speeds, contacts) and the GT wrist render.

Everything is generated here (a seeded reset + a short expert rollout): no demo files are needed.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("robosuite")

from umi_aug.errors import SimError  # noqa: E402
from umi_aug.geometry import interpolate_pose, pose_inverse, rotation_geodesic_distance  # noqa: E402
from umi_aug.square.camera import T_CAM_TCP, camera_pose_cv  # noqa: E402
from umi_aug.square.env import FISHEYE_KEY, GRIP_SITE, NUT_BODY, SquareEnv  # noqa: E402
from umi_aug.square.episode import rollout_expert  # noqa: E402
from umi_aug.square.expert import ExpertConfig, expert_pregrasp_pose, pregrasp_error  # noqa: E402
from umi_aug.square.feasibility import (  # noqa: E402
    PANDA_VEL_LIMITS_RAD_S, FeasibilityConfig, check_panda_path, render_gt_frames, state_qpos)
from umi_aug.square.ik import PandaIK  # noqa: E402

SEED = 3  # reset seed of the generated demo


@pytest.fixture(scope="module")
def env():
    e = SquareEnv(image_size=84)
    yield e
    e.close()


@pytest.fixture(scope="module")
def demo(env):
    """A short expert demo up to (a few frames past) its pre-grasp splice frame: states, camera poses, widths."""
    ep = rollout_expert(env, SEED, horizon=45, render=False)
    T_cam = ep.T_world_tcp @ pose_inverse(np.asarray(T_CAM_TCP))
    table_z = float(env.rs.table_offset[2])
    splice = None
    for t, s in enumerate(ep.states):
        env.rs.sim.set_state_from_flattened(s)
        env.rs.sim.forward()
        dp, dr = pregrasp_error(env.site_pose(GRIP_SITE), expert_pregrasp_pose(env.body_pose(NUT_BODY), table_z))
        if dp <= ExpertConfig().pos_tol and dr <= ExpertConfig().rot_tol:
            splice = t
            break
    assert splice is not None and splice > 5, "the expert did not reach its pre-grasp pose in 45 steps"
    return {"states": ep.states, "T_cam": T_cam, "width": ep.gripper_width, "splice": splice,
            "joints": ep.obs["robot0_joint_pos"]}


def _fk_camera(env, state, q_rows):
    """Reference: camera poses of arm joints ``q_rows`` [K, 7] via a plain MjData + mj_forward."""
    import mujoco

    ik = PandaIK(env.model)
    d = mujoco.MjData(env.model)
    out = []
    for q in q_rows:
        d.qpos[:] = state_qpos(env, state)
        d.qpos[ik.qadr] = q
        mujoco.mj_forward(env.model, d)
        out.append(camera_pose_cv(env.model, d))
    return np.asarray(out)


def _reset_pose(env, seed=SEED):
    env.reset(seed=seed)
    return env.get_state(), env.wrist_pose()


def test_demo_pregrasp_path_passes(env, demo):
    s = demo["splice"]
    T, w = demo["T_cam"][: s + 1], demo["width"][: s + 1]
    res = check_panda_path(env, demo["states"][0], T, w, scene_state=demo["states"][s])
    assert res.ok, res.reason
    assert res.reason is None and res.upto == s + 1 and res.collision_frames == []
    assert np.all(np.isfinite(res.q)) and res.q.shape == (s + 1, 7)
    cfg = FeasibilityConfig()
    assert np.all(res.pos_err_m <= cfg.pos_tol_m) and np.all(res.rot_err_rad <= cfg.rot_tol_rad)
    # frame 0 is the state's own pose: the warm start is already the solution
    np.testing.assert_allclose(res.q[0], demo["joints"][0], atol=1e-6)
    # the reported statistics against a recomputation from q
    steps = np.abs(np.diff(res.q, axis=0))
    assert res.max_joint_speed_rad_s == pytest.approx(steps.max() * 20.0, rel=1e-12)
    assert res.max_speed_ratio == pytest.approx((steps * 20.0 / PANDA_VEL_LIMITS_RAD_S).max(), rel=1e-12)
    assert res.max_speed_ratio <= 1.0
    ik = PandaIK(env.model)
    assert res.min_limit_margin_rad == pytest.approx(np.minimum(res.q - ik.lo, ik.hi - res.q).min(), abs=1e-12)
    assert res.min_limit_margin_rad >= cfg.limit_margin_rad - 1e-9
    # forward kinematics of the solution puts the camera on the requested poses
    T_fk = _fk_camera(env, demo["states"][0], res.q)
    assert np.abs(T_fk[:, :3, 3] - T[:, :3, 3]).max() < 1.5e-3
    assert max(rotation_geodesic_distance(a[:3, :3], b[:3, :3]) for a, b in zip(T_fk, T)) < np.radians(0.6)
    # the caller's env state is unchanged
    before = env.get_state()
    check_panda_path(env, demo["states"][0], T[:3], w[:3])
    np.testing.assert_array_equal(env.get_state(), before)


def test_straight_line_to_pregrasp_passes_and_is_deterministic(env):
    state, T0 = _reset_pose(env)
    T_cam_site = pose_inverse(T0) @ env.site_pose(GRIP_SITE)
    goal = expert_pregrasp_pose(env.body_pose(NUT_BODY), float(env.rs.table_offset[2]))
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])  # the gripper is symmetric under a half turn about its axis
    R_now = env.site_pose(GRIP_SITE)[:3, :3]
    goal = min((goal, goal @ flip), key=lambda G: rotation_geodesic_distance(G[:3, :3], R_now))
    T1 = goal @ pose_inverse(T_cam_site)
    T = interpolate_pose(T0, T1, np.linspace(0.0, 1.0, 60))
    w = np.full(60, 0.08)
    a = check_panda_path(env, state, T, w)
    b = check_panda_path(env, state, T, w)
    assert a.ok, a.reason
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.pos_err_m, b.pos_err_m)
    assert (a.reason, a.max_joint_speed_rad_s, a.repaired_frames) == (b.reason, b.max_joint_speed_rad_s,
                                                                       b.repaired_frames)


def test_path_through_table_fails_naming_the_frame(env):
    state, T0 = _reset_pose(env)
    table_z = float(env.rs.table_offset[2])
    drop = env.site_pose(GRIP_SITE)[2, 3] - (table_z - 0.05)  # grip site ends 5 cm below the table top
    n = 40
    T = np.repeat(T0[None], n, axis=0)
    T[:, 2, 3] -= np.linspace(0.0, drop, n)
    w = np.full(n, 0.08)
    res = check_panda_path(env, state, T, w)
    assert not res.ok and res.collision_frames
    k = res.collision_frames[0]
    assert res.reason.startswith(f"frame {k}: collision"), res.reason
    assert "table" in res.reason or "Nut" in res.reason or "peg" in res.reason, res.reason
    assert 0 < k < n and np.all(np.isfinite(res.q[:k + 1])) and np.all(np.isnan(res.q[k + 1:]))
    site_z = (T[k] @ pose_inverse(T0) @ env.site_pose(GRIP_SITE))[2, 3]
    assert site_z < table_z + 0.06  # the fingers reach down to the table there
    # the same path with the splice at that frame: contacts after it are not checked
    ok = check_panda_path(env, state, T, w, upto=k)
    assert ok.ok, ok.reason


def test_out_of_reach_fails_with_an_ik_reason(env):
    state, T0 = _reset_pose(env)
    far = T0.copy()
    far[0, 3] += 1.5
    res = check_panda_path(env, state, np.stack([T0, far, far]), np.full(3, 0.05))
    assert not res.ok and res.reason.startswith("frame 1: no IK solution"), res.reason
    assert np.all(np.isfinite(res.q[0])) and np.all(np.isnan(res.q[1:]))
    res0 = check_panda_path(env, state, far[None], np.full(1, 0.05), cfg=FeasibilityConfig(first_restarts=2))
    assert not res0.ok and res0.reason.startswith("frame 0: no IK solution"), res0.reason


def test_half_radian_joint_jump_fails_the_speed_check(env):
    state, _ = _reset_pose(env)
    q0 = state_qpos(env, state)[PandaIK(env.model).qadr]
    qs = np.repeat(q0[None], 10, axis=0)
    qs[5:, 0] += 0.5  # joint 1 jumps by 0.5 rad between frames 4 and 5
    T = _fk_camera(env, state, qs)
    res = check_panda_path(env, state, T, np.full(10, 0.04))
    assert not res.ok and res.reason.startswith("frame 5: joint"), res.reason
    assert "rad/s > limit" in res.reason
    assert 5 in res.repaired_frames  # the repair was tried before giving up
    # smooth: the same displacement over 10 frames (0.05 rad per frame < 2.175 rad/s × 0.05 s) passes
    qs[:, 0] = q0[0] + np.linspace(0.0, 0.5, 10)
    ok = check_panda_path(env, state, _fk_camera(env, state, qs), np.full(10, 0.04))
    assert ok.ok, ok.reason


def test_refine_respects_bounds_and_reaches(env, rng):
    from umi_aug.geometry import so3_exp

    state, _ = _reset_pose(env, int(rng.integers(1 << 20)))
    ik = PandaIK(env.model)
    T0 = env.site_pose(GRIP_SITE)
    q0 = env.data.qpos[ik.qadr].copy()
    lo, hi = ik.lo + 0.02, ik.hi - 0.02
    for _ in range(3):
        T = T0.copy()
        T[:3, 3] += rng.uniform(-0.05, 0.05, 3)
        T[:3, :3] = so3_exp(rng.uniform(-0.3, 0.3, 3)) @ T0[:3, :3]
        q, pe, re, _ = ik.refine(env.data, T, q0, lo=lo, hi=hi)
        assert pe < 1e-4 and re < np.radians(0.05)
        assert np.all(q >= lo) and np.all(q <= hi)
        Tq = ik.site_pose(q, env.data)  # reference: the residual recomputed from forward kinematics
        assert np.linalg.norm(Tq[:3, 3] - T[:3, 3]) == pytest.approx(pe, abs=1e-12)


def test_bad_inputs_raise(env):
    state, T0 = _reset_pose(env)
    with pytest.raises(SimError, match="T_world_cam"):
        check_panda_path(env, state, T0, np.zeros(1))
    with pytest.raises(SimError, match="gripper_width"):
        check_panda_path(env, state, T0[None], np.zeros(2))
    with pytest.raises(SimError, match="upto"):
        check_panda_path(env, state, T0[None], np.zeros(1), upto=2)
    with pytest.raises(SimError, match="state0"):
        check_panda_path(env, state[:-1], T0[None], np.zeros(1))
    bad = T0[None].copy()
    bad[0, 0, 3] = np.nan
    with pytest.raises(SimError, match="finite"):
        check_panda_path(env, state, bad, np.zeros(1))


def test_gt_render_equals_the_env_render(env, demo, gl):
    s = demo["splice"]
    T, w = demo["T_cam"][: s + 1], demo["width"][: s + 1]
    res = check_panda_path(env, demo["states"][0], T, w, scene_state=demo["states"][s])
    assert res.ok, res.reason
    frames = [0, s]
    gt = render_gt_frames(env, [demo["states"][t] for t in frames], res.q, w, T, frames)
    assert gt.shape == (2, 84, 84, 3) and gt.dtype == np.uint8
    for k, t in enumerate(frames):
        own = env.reset_to(demo["states"][t])[FISHEYE_KEY]  # the env's own observation at that state
        mse = np.mean((gt[k].astype(float) - own) ** 2)
        psnr = 10 * np.log10(255.0**2 / max(mse, 1e-12))
        assert psnr > 35.0, (t, psnr)
    # a camera pose the arm does not reach is refused, naming the frame
    T_off = T.copy()
    T_off[s, 2, 3] += 0.005
    with pytest.raises(SimError, match=f"frame {s}"):
        render_gt_frames(env, demo["states"][s], res.q, w, T_off, [s])
    q_nan = res.q.copy()
    q_nan[1] = np.nan
    with pytest.raises(SimError, match="frame 1"):
        render_gt_frames(env, demo["states"][0], q_nan, w, None, [1])


def test_contacts_find_self_collision(env):
    env.reset(seed=0)
    ik = PandaIK(env.model)
    q = env.data.qpos[ik.qadr].copy()
    assert ik.contacts(env.data, q) == []  # the reset pose is free
    q[3], q[5] = -3.0, 0.3  # elbow folded, wrist bent back: link 7 / hand into links 1–2
    own = ik.contacts(env.data, q, 1e-3, self_collision=True)
    assert own and all(a.startswith(("robot0_", "gripper0_")) and b.startswith(("robot0_", "gripper0_"))
                       for a, b, _ in own)
    assert all(d < -1e-3 for _, _, d in own)
    assert ik.contacts(env.data, q, 1e-3, self_collision=False) == []


def test_posture_step_keeps_the_site(env, rng):
    env.reset(seed=int(rng.integers(1 << 20)))
    ik = PandaIK(env.model)
    q = env.data.qpos[ik.qadr].copy()
    T0 = ik.site_pose(q, env.data)
    import mujoco

    jacp, jacr = np.zeros((3, env.model.nv)), np.zeros((3, env.model.nv))
    mujoco.mj_jacSite(env.model, env.data, jacp, jacr, ik.site)
    null = np.linalg.svd(np.vstack([jacp[:, ik.dadr], jacr[:, ik.dadr]]))[2][-1]  # reference null direction
    q_rest = q + 0.5 * null + 0.1 * rng.normal(0.0, 1.0, 7)
    cap = np.full(7, 0.02)
    q1 = ik.posture_step(env.data, q, q_rest, 0.5, cap)
    dq = q1 - q
    assert np.all(np.abs(dq) <= cap + 1e-12) and np.linalg.norm(dq) > 1e-3
    assert abs(dq @ null) / np.linalg.norm(dq) > 0.999  # the step lies in the null space
    moved = np.linalg.norm(ik.site_pose(q1, env.data)[:3, 3] - T0[:3, 3])
    # reference: an unprojected step of the same size moves the site by first order
    plain = q + (q_rest - q) * np.linalg.norm(dq) / np.linalg.norm(q_rest - q)
    moved_plain = np.linalg.norm(ik.site_pose(plain, env.data)[:3, 3] - T0[:3, 3])
    assert moved < 0.1 * moved_plain and moved < 2e-4
