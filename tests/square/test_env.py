"""Square env: creation through robomimic's env_meta, fisheye observations, poses, the expert."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("robosuite")  # the robomimic extra; CI installs it (README)

from umi_aug.square.camera import T_CAM_TCP, wrist_intrinsics  # noqa: E402
from umi_aug.square.env import FISHEYE_KEY, UMI_IMAGE_KEY, SquareEnv, square_env_meta  # noqa: E402
from umi_aug.square.episode import rollout_expert  # noqa: E402
from umi_aug.square.expert import nut_yaw_error  # noqa: E402


@pytest.fixture(scope="module")
def env():
    e = SquareEnv(env_meta=json.loads(json.dumps(square_env_meta())), image_size=84)
    yield e
    e.close()


def test_env_meta_is_robomimic_square():
    meta = square_env_meta()
    assert meta["env_name"] == "NutAssemblySquare" and meta["type"] == 1
    cc = meta["env_kwargs"]["controller_configs"]
    assert cc["type"] == "OSC_POSE" and cc["output_max"] == [0.05, 0.05, 0.05, 0.5, 0.5, 0.5]
    assert meta["env_kwargs"]["control_freq"] == 20 and meta["env_kwargs"]["robots"] == ["Panda"]


def test_env_created_through_robomimic(env):
    from robomimic.envs.env_robosuite import EnvRobosuite

    assert isinstance(env.env, EnvRobosuite)
    assert type(env.rs).__name__ == "NutAssemblySquare"


def test_observation_keys_and_fisheye_image(env, rng):
    obs = env.reset(seed=int(rng.integers(1 << 30)))
    for k in ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos", "robot0_joint_pos",
              "robot0_eef_rot_axis_angle", "robot0_gripper_width", FISHEYE_KEY, UMI_IMAGE_KEY):
        assert k in obs, k
        assert np.all(np.isfinite(obs[k]))
    img = obs[FISHEYE_KEY]
    assert img.shape == (84, 84, 3) and img.dtype == np.uint8
    wrist_intrinsics(84).check_image_shape(img.shape)  # raises on a size mismatch
    assert img[42 - 10: 42 + 10, 42 - 10: 42 + 10].mean() > 20  # the centre sees the lit scene
    assert img[0, 0].max() == 0  # the corner lies outside the GoPro image circle
    np.testing.assert_array_equal(obs[UMI_IMAGE_KEY], img)
    # UMI TCP position = robomimic eef position (grip site); TCP rotation = camera axes
    np.testing.assert_allclose(env.tcp_pose()[:3, 3], obs["robot0_eef_pos"], atol=1e-12)
    np.testing.assert_allclose(env.tcp_pose()[:3, :3], env.wrist_pose()[:3, :3], atol=1e-12)
    np.testing.assert_allclose(env.T_cam_tcp(), T_CAM_TCP, atol=1e-6)
    assert 0.0 <= obs["robot0_gripper_width"][0] <= 0.081


def test_wrist_camera_looks_down_the_gripper(env):
    env.reset(seed=0)
    T = env.wrist_pose()
    assert T[2, 2] < -0.95  # optical axis (OpenCV z) points down at the table
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) > 0


def test_reset_seed_is_deterministic(env, rng):
    s = int(rng.integers(1 << 30))
    a = env.reset(seed=s)
    sa = env.get_state()
    env.reset(seed=s + 1)
    b = env.reset(seed=s)
    np.testing.assert_array_equal(sa, env.get_state())
    np.testing.assert_array_equal(a[FISHEYE_KEY], b[FISHEYE_KEY])


def test_gt_render_hook_any_pose(env):
    env.reset(seed=3)
    T = env.wrist_pose()
    img0 = env.render_wrist()
    np.testing.assert_array_equal(img0, env.render_wrist(T))
    T2 = T.copy()
    T2[:3, 3] += np.array([0.0, 0.0, 0.1])
    img1 = env.render_wrist(T2)
    assert np.abs(img1.astype(int) - img0.astype(int)).mean() > 2.0
    np.testing.assert_array_equal(img0, env.render_wrist())  # the state was not changed


def test_nut_yaw_error_symmetry():
    def rz(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])

    for a in (0.1, 0.1 + np.pi / 2, 0.1 - np.pi, 0.1 + 3 * np.pi / 2):
        assert nut_yaw_error(rz(a)) == pytest.approx(0.1, abs=1e-9)
    assert -np.pi / 4 <= nut_yaw_error(rz(np.pi / 4 + 1e-3)) < np.pi / 4


def test_expert_solves_a_few_seeds(env, rng):
    seeds = [int(s) for s in rng.integers(0, 1 << 30, size=3)]
    results = [rollout_expert(env, s, render=False) for s in seeds]
    assert sum(r.success for r in results) >= 2, [(s, r.info) for s, r in zip(seeds, results)]
    ok = next(r for r in results if r.success)
    assert ok.dones[-1] == 1 and ok.dones[:-1].sum() == 0 and ok.rewards[-1] > 0
    assert ok.states.shape[0] == ok.actions.shape[0] == len(ok)
    assert np.all(np.abs(ok.actions) <= 1.0)


def test_model_xml_survives_other_model_loads(env):
    """robomimic's ``model_file`` must be this env's MJCF even after another model was loaded in the process
    (MuJoCo's ``mj_saveLastXML`` is process-wide: a tabletop scene loaded later used to leak into the demos)."""
    import mujoco

    xml = env.model_xml()
    assert "square" in xml.lower() and "nut" in xml.lower()
    mujoco.MjModel.from_xml_string("<mujoco model='unrelated'><worldbody/></mujoco>")
    assert env.model_xml() == xml
    state = env.get_state()
    env.reset_to(state, model_xml=xml)  # reloading from the stored XML gives the same model
    assert env.model_xml() == xml and env.model.nbody > 2
    np.testing.assert_allclose(env.get_state(), state, atol=1e-9)
