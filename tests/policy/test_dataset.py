import numpy as np
import pytest
import torch

from tests.policy.helpers import SIZE, make_dataset, tiny_config, with_commanded_targets
from umi_aug.data import ReplayBuffer
from umi_aug.errors import PolicyError
from umi_aug.geometry import pos_rotvec_to_pose, relative_pose
from umi_aug.policy.dataset import UmiPolicyDataset, get_val_mask, sample_frame_indices


def _umi_sampler_reference(ends, horizon_a, ds, h_obs):
    """UMI's SequenceSampler index logic written out literally (action_padding=False, latency 0)."""
    out = []
    for i in range(len(ends)):
        s, e = (0 if i == 0 else ends[i - 1]), ends[i]
        for c in range(s, e):
            if e < c + (horizon_a - 1) * ds + 1:
                continue
            n_valid = min(h_obs, (c - s) // ds + 1)
            rgb = list(range(c - (n_valid - 1) * ds, c + 1, ds))
            rgb = [rgb[0]] * (h_obs - len(rgb)) + rgb
            low = [min(max(c - k * ds, s), e - 1) for k in range(h_obs)][::-1]
            act = list(range(c, min(e, c + (horizon_a - 1) * ds + 1), ds))
            out.append((c, s, e, rgb, low, act))
    return out


def test_sample_layout_matches_umi(dataset_path, tmp_path):
    cfg = tiny_config(dataset_path, tmp_path)
    ds = UmiPolicyDataset(dataset_path, cfg.task, "train")
    s = ds[0]
    assert set(s) == {"obs", "action"}
    want = {"camera0_rgb": (2, 3, SIZE, SIZE), "robot0_eef_pos": (2, 3), "robot0_eef_rot_axis_angle": (2, 6),
            "robot0_gripper_width": (2, 1), "robot0_eef_rot_axis_angle_wrt_start": (2, 6)}
    assert {k: tuple(v.shape) for k, v in s["obs"].items()} == want
    assert all(v.dtype == torch.float32 for v in s["obs"].values())
    assert s["action"].shape == (16, 10) and s["action"].dtype == torch.float32
    img = s["obs"]["camera0_rgb"]
    assert 0.0 <= float(img.min()) and float(img.max()) <= 1.0
    # shape_meta is UMI's task/umi.yaml layout
    assert ds.shape_meta["action"] == {"shape": [10], "horizon": 16, "down_sample_steps": 2}
    assert ds.shape_meta["obs"]["robot0_eef_rot_axis_angle"]["shape"] == [6]


def test_indices_and_values_match_umi_sampler(dataset_path, tmp_path):
    cfg = tiny_config(dataset_path, tmp_path, val_ratio=0.0, start_pose_noise=0.0)
    ds = UmiPolicyDataset(dataset_path, cfg.task, "all")
    with ReplayBuffer.open(dataset_path) as buf:
        ends = buf.episode_ends
        pos = buf["robot0_eef_pos"][:].astype(np.float64)
        rot = buf["robot0_eef_rot_axis_angle"][:].astype(np.float64)
        grip = buf["robot0_gripper_width"][:].astype(np.float64)
        rgb_all = buf["camera0_rgb"][:]
        start6 = buf["robot0_demo_start_pose"][:]
    ref = _umi_sampler_reference(list(ends), 16, 2, 2)
    assert len(ds) == len(ref) == 4 * (40 - 30)
    for k in (0, 3, len(ref) - 1):
        c, s, e, rgb, low, act = ref[k]
        assert tuple(ds.indices[k]) == (c, s, e)
        r, lo = sample_frame_indices(c, s, e, 2, 2)
        assert r.tolist() == rgb and lo.tolist() == low
        sample = ds[k]
        np.testing.assert_allclose(sample["obs"]["camera0_rgb"].numpy(),
                                   rgb_all[rgb].transpose(0, 3, 1, 2).astype(np.float32) / 255.0)
        T = pos_rotvec_to_pose(np.concatenate([pos, rot], 1))
        rel_obs = relative_pose(T[low[-1]], T[low])
        np.testing.assert_allclose(sample["obs"]["robot0_eef_pos"].numpy(), rel_obs[:, :3, 3], atol=1e-6)
        rel_act = relative_pose(T[low[-1]], T[act])
        np.testing.assert_allclose(sample["action"][:, :3].numpy(), rel_act[:, :3, 3], atol=1e-6)
        np.testing.assert_allclose(sample["action"][:, 3:9].numpy(), rel_act[:, :2, :3].reshape(16, 6), atol=1e-6)
        np.testing.assert_allclose(sample["action"][:, 9].numpy(), grip[act, 0], atol=1e-7)
        np.testing.assert_allclose(sample["obs"]["robot0_gripper_width"].numpy(), grip[low], atol=1e-7)
        S = pos_rotvec_to_pose(start6[c])
        np.testing.assert_allclose(sample["obs"]["robot0_eef_rot_axis_angle_wrt_start"].numpy(),
                                   relative_pose(S, T[low])[:, :2, :3].reshape(2, 6), atol=1e-6)


def test_action_key_labels_with_the_stored_commanded_targets(dataset_path, tmp_path, rng):
    """issue #29 B2: with task.action_key the action window holds the stored commanded targets, relative to the
    same observed current pose (not the future poses)."""
    path, act, _ = with_commanded_targets(dataset_path, tmp_path / "act.zarr.zip", rng)
    with ReplayBuffer.open(path) as buf:
        T = pos_rotvec_to_pose(np.concatenate([buf["robot0_eef_pos"][:], buf["robot0_eef_rot_axis_angle"][:]], 1)
                               .astype(np.float64))
    cfg = tiny_config(path, tmp_path, val_ratio=0.0, start_pose_noise=0.0, action_key="action")
    ds = UmiPolicyDataset(path, cfg.task, "all")
    plain = UmiPolicyDataset(path, tiny_config(path, tmp_path, val_ratio=0.0, start_pose_noise=0.0).task, "all")
    for k in (0, 7, len(ds) - 1):
        c, s, e = (int(v) for v in ds.indices[k])
        rows = c + 2 * np.arange(16)
        sample, base = ds[k], plain[k]
        rel = relative_pose(T[c], pos_rotvec_to_pose(act[rows, :6]))
        np.testing.assert_allclose(sample["action"][:, :3].numpy(), rel[:, :3, 3], atol=1e-6)
        np.testing.assert_allclose(sample["action"][:, 3:9].numpy(), rel[:, :2, :3].reshape(16, 6), atol=1e-6)
        np.testing.assert_allclose(sample["action"][:, 9].numpy(), act[rows, 6], atol=1e-7)
        for key in sample["obs"]:  # observations are the same as without the key
            torch.testing.assert_close(sample["obs"][key], base["obs"][key])
    norm = ds.fit_normalizer()  # fitted on the commanded targets
    assert norm is not None


def test_action_key_errors_name_the_key(dataset_path, tmp_path, rng):
    cfg = tiny_config(dataset_path, tmp_path, action_key="action")
    with pytest.raises(PolicyError, match=r"\['action'\].*missing"):
        UmiPolicyDataset(dataset_path, cfg.task)
    with ReplayBuffer.open(dataset_path) as buf:
        n = buf.n_steps
    bad, _, _ = with_commanded_targets(dataset_path, tmp_path / "bad.zarr.zip", rng, shape=(n, 6))
    with pytest.raises(PolicyError, match=r"'data/action'.* shape"):
        UmiPolicyDataset(bad, cfg.task)
    nan, _, _ = with_commanded_targets(dataset_path, tmp_path / "nan.zarr.zip", rng, nan_row=5)
    with pytest.raises(PolicyError, match=r"'data/action'.*NaN/Inf.* row 5"):
        UmiPolicyDataset(nan, cfg.task)
    cfg.task.n_robots = 2  # 7 columns where two arms need 14
    with pytest.raises(PolicyError, match=r"robot1_eef_pos"):
        UmiPolicyDataset(with_commanded_targets(dataset_path, tmp_path / "one.zarr.zip", rng)[0], cfg.task)
    from umi_aug.policy.config import check_config

    cfg.task.n_robots = 1
    cfg.task.action_key = "robot0_eef_pos"
    with pytest.raises(PolicyError, match="task.action_key"):
        check_config(cfg)


def test_batches_from_memory_equal_the_dataloader_path(dataset_path, tmp_path):
    """issue #29: frames decoded once + batches built at once give exactly the DataLoader's batches (same order,
    images, low-dim values and start-pose noise), for every epoch and a mid-epoch start."""
    from umi_aug.policy.workspace import MemoryBatches, make_loader

    cfg = tiny_config(dataset_path, tmp_path, val_ratio=0.25, start_pose_noise=0.05)
    ref = UmiPolicyDataset(dataset_path, cfg.task, "train")
    fast = UmiPolicyDataset(dataset_path, cfg.task, "train")
    assert not fast.frames_in_memory(fast.frames_nbytes() / 2e9)  # over the budget: stays per-sample
    assert fast.frames_in_memory(1.0) and fast.has_frames_in_memory
    assert fast.get_validation_dataset().has_frames_in_memory
    for epoch, start in ((0, 0), (1, 2)):
        a = list(make_loader(ref, batch_size=8, shuffle=True, seed=3, epoch=epoch, start_batch=start))
        mb = MemoryBatches(fast, 8, True, 3, epoch, start)
        b = list(mb)
        assert len(a) == len(b) == len(mb)
        for x, y in zip(a, b):
            assert torch.equal(x["obs"]["camera0_rgb"], y["obs"]["camera0_rgb"])
            for k in x["obs"]:
                torch.testing.assert_close(x["obs"][k], y["obs"][k], rtol=0, atol=1e-6)
            torch.testing.assert_close(x["action"], y["action"], rtol=0, atol=1e-6)
    with pytest.raises(PolicyError, match="in memory"):
        ref.batch(np.arange(3))
    with pytest.raises(IndexError):
        fast.batch(np.array([len(fast)]))


def test_padding_at_episode_start_repeats_like_umi():
    rgb, low = sample_frame_indices(cur=14, start=10, end=60, horizon=3, down_sample=3)
    assert rgb.tolist() == [11, 11, 14]   # earliest valid strided frame repeated
    assert low.tolist() == [10, 11, 14]   # clipped to the episode start


def test_val_split_is_umis():
    for n, r, seed in [(20, 0.05, 42), (7, 0.3, 1), (2, 0.5, 0)]:
        m = get_val_mask(n, r, seed)
        n_val = min(max(1, round(n * r)), n - 1)
        ref = np.zeros(n, bool)
        ref[np.random.default_rng(seed).choice(n, size=n_val, replace=False)] = True
        np.testing.assert_array_equal(m, ref)
    assert not get_val_mask(5, 0.0).any() and not get_val_mask(1, 0.5).any()


def test_train_val_episodes_disjoint_and_noise_only_in_train(dataset_path, tmp_path):
    cfg = tiny_config(dataset_path, tmp_path, val_ratio=0.25)
    tr = UmiPolicyDataset(dataset_path, cfg.task, "train")
    va = tr.get_validation_dataset()
    assert len(tr) == 30 and len(va) == 10
    assert not set(map(tuple, tr.indices[:, 1:])) & set(map(tuple, va.indices[:, 1:]))
    assert va.start_pose_noise == 0 and tr.start_pose_noise == cfg.task.start_pose_noise
    a, b = va[0], va[0]
    assert torch.equal(a["obs"]["robot0_eef_rot_axis_angle_wrt_start"], b["obs"]["robot0_eef_rot_axis_angle_wrt_start"])


def test_normalizer_fit_without_images(dataset_path, tmp_path, monkeypatch):
    cfg = tiny_config(dataset_path, tmp_path)
    ds = UmiPolicyDataset(dataset_path, cfg.task, "train")
    monkeypatch.setattr(ds, "read_frames", lambda *a: pytest.fail("fit_normalizer decoded an image"))
    n = ds.fit_normalizer()
    monkeypatch.undo()
    assert set(n.keys()) == {"action", "robot0_eef_pos", "robot0_eef_rot_axis_angle", "robot0_gripper_width",
                             "robot0_eef_rot_axis_angle_wrt_start"}
    sc, of = n.params("action")
    assert torch.equal(sc[3:9], torch.ones(6)) and torch.equal(of[3:9], torch.zeros(6))  # rot6d: identity
    acts = torch.stack([ds[i]["action"] for i in range(len(ds))])
    na = n.normalize(acts, "action")
    assert float(na[..., :3].min()) >= -1 - 1e-4 and float(na[..., :3].max()) <= 1 + 1e-4
    assert float(na[..., 9].min()) >= -1 - 1e-4 and float(na[..., 9].max()) <= 1 + 1e-4


def test_dataset_errors(tmp_path, rng):
    path = make_dataset(tmp_path / "short.zarr.zip", rng, n_episodes=2, length=12)
    cfg = tiny_config(path, tmp_path)
    ds = UmiPolicyDataset(path, cfg.task, "train")
    assert len(ds) == 0
    with pytest.raises(PolicyError, match="no samples"):
        ds.fit_normalizer()
    cfg.task.action_padding = True  # padding makes short episodes usable
    ds = UmiPolicyDataset(path, cfg.task, "all")
    assert len(ds) == 24 and ds[23]["action"].shape == (16, 10)
    cfg.task.image_size = 64
    with pytest.raises(PolicyError, match="image_size"):
        UmiPolicyDataset(path, cfg.task)
    cfg.task.image_size, cfg.task.n_cameras = SIZE, 2
    with pytest.raises(PolicyError, match="camera1_rgb"):
        UmiPolicyDataset(path, cfg.task)
    with pytest.raises(PolicyError, match="dataset_path"):
        UmiPolicyDataset(tmp_path / "nope.zarr.zip", cfg.task)


def test_dataloader_workers_read_the_zip(dataset_path, tmp_path):
    """Two worker processes each open their own zip handle; batches equal the in-process ones."""
    cfg = tiny_config(dataset_path, tmp_path, start_pose_noise=0.0)
    ds = UmiPolicyDataset(dataset_path, cfg.task, "train")
    ref = [ds[i]["obs"]["camera0_rgb"] for i in range(6)]
    ds[0]  # open a handle in this process first: workers must not reuse it
    dl = torch.utils.data.DataLoader(ds, batch_size=3, num_workers=2, shuffle=False,
                                     multiprocessing_context="fork")
    got = [b["obs"]["camera0_rgb"] for _, b in zip(range(2), dl)]
    assert torch.equal(torch.cat(got), torch.stack(ref))


_THREADED_PARENT = """
import pickle, sys, torch
from umi_aug.policy.dataset import UmiPolicyDataset
from umi_aug.policy.workspace import loader_context, make_loader

if __name__ == "__main__":
    torch.set_num_threads(2)
    x = torch.randn(256, 256)
    for _ in range(3):  # the parent's OpenMP pool is up, as in a training process
        (x @ x).sum(); torch.randn(64, 3, 64, 64).float().mul_(2.0)
    with open(sys.argv[2], "rb") as fh:
        task = pickle.load(fh)
    ds = UmiPolicyDataset(sys.argv[1], task, "train")
    loader = make_loader(ds, 2, True, seed=0, num_workers=2, persistent=True, context=loader_context(ds))
    n = sum(len(b["action"]) for b in loader)
    print("samples", n, "of", len(ds), flush=True)
    del loader  # workers shut down before the interpreter does
"""


def test_workers_of_a_multithreaded_parent_do_not_hang(tmp_path):
    """The training loader's workers (``loader_context``) must run when the parent has used torch's OpenMP pool:
    FORKED ones block in their first parallel kernel (reproduced: ``train/train.py device.num_workers=2`` made no
    step in 300 s). A child process with a timeout, so a hang fails the test instead of stalling the suite. 84²
    frames: a sample's uint8 → float conversion is then large enough for torch to run it in parallel."""
    import pickle
    import subprocess
    import sys

    dataset_path = make_dataset(tmp_path / "d84.zarr.zip", np.random.default_rng(5), n_episodes=3, length=40,
                                size=84)

    script, task = tmp_path / "threaded_parent.py", tmp_path / "task.pkl"
    script.write_text(_THREADED_PARENT)
    task.write_bytes(pickle.dumps(tiny_config(dataset_path, tmp_path, image_size=84).task))
    import os
    import signal

    proc = subprocess.Popen([sys.executable, str(script), str(dataset_path), str(task)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env={**os.environ, "OMP_NUM_THREADS": "2"})
    try:
        out, err = proc.communicate(timeout=180)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the blocked workers too, not only their parent
        proc.communicate()
        pytest.fail("the DataLoader workers made no batch in 180 s (forked from a multi-threaded parent?)")
    r = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    assert r.returncode == 0, r.stderr[-2000:]
    n, of = r.stdout.split()[1::2]
    assert n == of and int(n) > 0, r.stdout
