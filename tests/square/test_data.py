"""Square demo datasets: generated hdf5 loads with robomimic, UMI zarr, resume, converter round trip."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

pytest.importorskip("robosuite")
# one full rendered expert demo (~15 s on 2 idle cores, shared with test_source.py) plus its conversion
pytestmark = pytest.mark.slow

from umi_aug.square.env import FISHEYE_KEY, LOW_DIM_KEYS  # noqa: E402
from umi_aug.square.generate import DemoConfig, generate_demos  # noqa: E402

SIZE = 84


@pytest.fixture(scope="module")
def demos(square_demo):
    """The session's shared demo (tests/conftest.py: seed 7, 84²)."""
    return square_demo


def test_generate_writes_both_formats(demos):
    out, rep = demos
    assert rep["successes"] == 1 and rep["seeds"] == [7]
    with h5py.File(rep["paths"]["hdf5"], "r") as f:
        meta = json.loads(f["data"].attrs["env_args"])
        assert meta["env_name"] == "NutAssemblySquare"
        g = f["data/demo_0"]
        T = g.attrs["num_samples"]
        assert f["data"].attrs["total"] == T
        assert g["actions"].shape == (T, 7) and g["states"].shape[0] == T
        assert g["rewards"].shape == (T,) and g["dones"][-1] == 1
        assert g["obs"][FISHEYE_KEY].shape == (T, SIZE, SIZE, 3) and g["obs"][FISHEYE_KEY].dtype == np.uint8
        for k in LOW_DIM_KEYS:
            assert g["obs"][k].shape[0] == T
        assert "<mujoco" in g.attrs["model_file"]
    from umi_aug.data import ReplayBuffer, episode_tcp_poses

    with ReplayBuffer.open(rep["paths"]["zarr"]) as rb:
        assert rb.n_episodes == 1 and rb.n_steps == T
        ep = rb.get_episode(0)
        assert ep["camera0_rgb"].shape == (T, SIZE, SIZE, 3)
        assert np.asarray(rb.root.attrs["T_cam_tcp"]).shape == (4, 4)
        Tt = episode_tcp_poses(ep)
        with h5py.File(rep["paths"]["hdf5"], "r") as f:
            np.testing.assert_allclose(Tt[:, :3, 3], f["data/demo_0/obs/robot0_eef_pos"][()], atol=1e-6)


def test_hdf5_loads_with_robomimic_dataset(demos):
    from umi_aug.square.env import init_robomimic_obs_utils

    init_robomimic_obs_utils()
    from robomimic.utils.dataset import SequenceDataset

    _, rep = demos
    ds = SequenceDataset(
        hdf5_path=rep["paths"]["hdf5"], obs_keys=("robot0_eef_pos", "robot0_eef_quat", "object", FISHEYE_KEY),
        dataset_keys=("actions", "rewards", "dones"), load_next_obs=False, frame_stack=1, seq_length=10,
        pad_frame_stack=True, pad_seq_length=True, get_pad_mask=False, goal_mode=None,
        hdf5_cache_mode=None, hdf5_use_swmr=True, hdf5_normalize_obs=False, filter_by_attribute=None)
    assert len(ds) > 0
    item = ds[0]
    assert item["actions"].shape == (10, 7)
    assert item["obs"][FISHEYE_KEY].shape[-3:] in ((3, SIZE, SIZE), (SIZE, SIZE, 3))


def test_generate_resumes_without_rerunning(demos):
    out, rep = demos
    again = generate_demos(out, DemoConfig(n=1, image_size=SIZE, workers=1, start_seed=7))
    assert again["seeds"] == rep["seeds"] and again["seconds_per_demo"] is None  # nothing rolled out again


def test_convert_round_trip(demos, tmp_path):
    from umi_aug.square.convert import convert_robomimic_hdf5

    _, rep = demos
    src = rep["paths"]["hdf5"]
    # a short copy (first 25 steps) keeps the test fast
    small = tmp_path / "small.hdf5"
    with h5py.File(src, "r") as f, h5py.File(small, "w") as g:
        g.create_group("data").attrs["env_args"] = f["data"].attrs["env_args"]
        d = g.create_group("data/demo_0")
        for k in ("states", "actions", "rewards", "dones"):
            d.create_dataset(k, data=f[f"data/demo_0/{k}"][:25])
        d.attrs["model_file"] = f["data/demo_0"].attrs["model_file"]
        g["data"].attrs["total"] = 25
        ref_obs = {k: f[f"data/demo_0/obs/{k}"][:25] for k in (*LOW_DIM_KEYS, FISHEYE_KEY)}
    paths = convert_robomimic_hdf5(small, tmp_path / "conv", image_size=SIZE, progress=False)
    with h5py.File(paths["hdf5"], "r") as f:
        g = f["data/demo_0"]
        with h5py.File(small, "r") as s:
            np.testing.assert_array_equal(g["states"][()], s["data/demo_0/states"][()])
            np.testing.assert_array_equal(g["actions"][()], s["data/demo_0/actions"][()])
        for k in LOW_DIM_KEYS:
            np.testing.assert_allclose(g["obs"][k][()], ref_obs[k], atol=1e-6, err_msg=k)
        img = g["obs"][FISHEYE_KEY][()].astype(int)
        assert np.abs(img - ref_obs[FISHEYE_KEY].astype(int)).mean() < 1.0
    from umi_aug.data import ReplayBuffer

    with ReplayBuffer.open(paths["zarr"]) as rb:
        assert rb.n_steps == 25


def test_convert_rejects_non_robomimic(tmp_path):
    from umi_aug.errors import SimError
    from umi_aug.square.convert import convert_robomimic_hdf5

    bad = tmp_path / "bad.hdf5"
    with h5py.File(bad, "w") as f:
        f.create_group("other")
    with pytest.raises(SimError, match="env_args"):
        convert_robomimic_hdf5(bad, tmp_path / "o", image_size=SIZE, progress=False)


def test_eval_harness_observes_what_training_saw(demos):
    """Train/eval consistency: restoring demo states in the evaluation harness's env and rendering its wrist camera
    (eval's observation path) gives the training dataset's rows — the same pose, rotation vector and gripper width
    and the same image up to the JPEG-XL compression of the dataset."""
    from umi_aug.data import ReplayBuffer
    from umi_aug.square.camera import WristFisheyeCamera
    from umi_aug.square.env import SquareEnv

    _, rep = demos
    with h5py.File(rep["paths"]["hdf5"], "r") as f:
        states = f["data/demo_0/states"][()]
        env_meta = json.loads(f["data"].attrs["env_args"])
    env = SquareEnv(env_meta=env_meta, image_size=None)  # as umi_aug.eval.runner makes it
    cam = WristFisheyeCamera(env.model, SIZE)
    try:
        with ReplayBuffer.open(rep["paths"]["zarr"]) as rb:
            ep = rb.get_episode(0)
            for t in (0, len(states) // 2, len(states) - 1):
                obs = env.reset_to(states[t])
                img = cam.render(env.data, env.wrist_pose())
                np.testing.assert_allclose(obs["robot0_eef_pos"], ep["robot0_eef_pos"][t], atol=1e-6)
                np.testing.assert_allclose(obs["robot0_eef_rot_axis_angle"], ep["robot0_eef_rot_axis_angle"][t],
                                           atol=1e-5)
                np.testing.assert_allclose(np.ravel(obs["robot0_gripper_width"]), ep["robot0_gripper_width"][t],
                                           atol=1e-6)
                diff = np.abs(img.astype(np.int16) - ep["camera0_rgb"][t].astype(np.int16))
                assert diff.mean() < 1.5 and np.percentile(diff, 99) < 16, (t, diff.mean())
    finally:
        cam.close()
        env.close()
