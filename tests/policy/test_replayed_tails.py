"""``task.sample_replayed_tails=false``: an augmented episode's samples that only read its replayed tail are left
out, and each of them is exactly a sample its source episode still gives (issue #29)."""

import numpy as np
import pytest
import torch

from tests.policy.helpers import images, smooth_trajectory, tiny_config
from umi_aug.data import ReplayBuffer
from umi_aug.data.umi_episode import make_umi_episode
from umi_aug.errors import PolicyError
from umi_aug.policy.dataset import UmiPolicyDataset, replayed_tail_first_sample

# (aug_id, source demo, splice) per episode: two originals (demos 0 and 1), their augmented episodes, one whose
# source (demo 7) is not in the buffer, and a SPARTN short episode of demo 0 (aug_id -2: not an original)
_EPISODES = [(-1, 0, 10), (-1, 1, 6), (0, 0, 12), (1, 0, 5), (0, 1, 9), (0, 7, 8), (-2, 0, -1)]
_LENGTHS = {0: 100, 1: 90}


def _augmented_buffer(path, rng, records=True, bad_key=None, episodes=_EPISODES):
    """Originals of random smooth motion; each augmented episode = a new head (its own frames) + its source's frames
    from the source's splice on, as the export writes them (the start pose is the episode's own first pose)."""
    originals = {}
    buf = ReplayBuffer.create()
    for aug_id, src, k in episodes:
        if aug_id == -2:
            T, g = smooth_trajectory(rng, 50)
            ep = make_umi_episode(T, g, {0: images(rng, 50)})
        elif aug_id < 0:
            n = _LENGTHS[src]
            T, g = smooth_trajectory(rng, n)
            originals[src] = (T, g, images(rng, n), k)
            ep = make_umi_episode(T, g, {0: originals[src][2]})
        else:
            To, go, io, ko = originals[min(src, 1)]
            Th, gh = smooth_trajectory(rng, k)
            T = np.concatenate([Th, To[ko:]])
            g = np.concatenate([gh.reshape(-1), go.reshape(-1)[ko:]])
            ep = make_umi_episode(T, g, {0: np.concatenate([images(rng, k), io[ko:]])})
        buf.add_episode(ep)
    if records:
        for j, key in enumerate(("aug_id", "aug_source_episode", "aug_splice_index")):
            vals = np.array([e[j] for e in episodes], np.int64)
            buf.meta.array(key, vals[:-1] if key == bad_key else vals)
    buf.save(path)
    return path


def _task(path, tmp_path, **kw):
    return tiny_config(path, tmp_path, val_ratio=0.0, start_pose_noise=0.0, **kw).task


def _same(a, b, skip=("robot0_eef_rot_axis_angle_wrt_start",)):
    return torch.equal(a["action"], b["action"]) and all(torch.equal(a["obs"][k], b["obs"][k])
                                                         for k in a["obs"] if k not in skip)


@pytest.mark.parametrize("obs_down_sample_steps,img_obs_horizon", [(2, 2), (1, 1), (3, 2)])
def test_left_out_samples_are_the_sources_own(tmp_path, obs_down_sample_steps, img_obs_horizon):
    path = _augmented_buffer(tmp_path / "aug.zarr.zip", np.random.default_rng(5))
    kw = dict(obs_down_sample_steps=obs_down_sample_steps, img_obs_horizon=img_obs_horizon)
    every = UmiPolicyDataset(path, _task(path, tmp_path, **kw), "all")
    fewer = UmiPolicyDataset(path, _task(path, tmp_path, sample_replayed_tails=False, **kw), "all")
    kept = {tuple(r) for r in fewer.indices.tolist()}
    left_out = [i for i, r in enumerate(every.indices.tolist()) if tuple(r) not in kept]
    assert kept <= {tuple(r) for r in every.indices.tolist()} and left_out
    ends = every.episode_ends
    starts = np.concatenate([[0], ends[:-1]])
    sources = [every[i] for i, r in enumerate(every.indices.tolist()) if r[1] in (starts[0], starts[1])]
    for i in left_out:
        ep = int(np.searchsorted(ends, every.indices[i, 0], side="right"))
        assert _EPISODES[ep][0] >= 0 and _EPISODES[ep][1] in (0, 1)  # only augmented episodes with a source here
        sample = every[i]
        assert any(_same(sample, o) for o in sources), f"left-out sample {every.indices[i]} is no copy"
    # every augmented sample that is kept reads something new: it is no copy of a source sample
    for i, r in enumerate(every.indices.tolist()):
        ep = int(np.searchsorted(ends, r[0], side="right"))
        if tuple(r) in kept and _EPISODES[ep][0] >= 0 and _EPISODES[ep][1] in (0, 1):
            sample = every[i]
            assert not any(_same(sample, o) for o in sources), f"kept sample {r} is a copy"
    # originals and the episode without its source in the buffer keep every sample
    for ep in (0, 1, 5, 6):
        mine = lambda ds: [tuple(r) for r in ds.indices.tolist() if r[1] == starts[ep]]  # noqa: E731
        assert mine(every) == mine(fewer) and mine(every)


def test_buffers_without_augmented_episodes_are_unaffected(dataset_path, tmp_path):
    every = UmiPolicyDataset(dataset_path, _task(dataset_path, tmp_path), "all")
    fewer = UmiPolicyDataset(dataset_path, _task(dataset_path, tmp_path, sample_replayed_tails=False), "all")
    np.testing.assert_array_equal(every.indices, fewer.indices)
    # the records of an export, but no augmented episode (the square study's `none` and `spartn` variants)
    path = _augmented_buffer(tmp_path / "none.zarr.zip", np.random.default_rng(6),
                             episodes=[e for e in _EPISODES if e[0] < 0])
    fewer = UmiPolicyDataset(path, _task(path, tmp_path, sample_replayed_tails=False), "all")
    np.testing.assert_array_equal(UmiPolicyDataset(path, _task(path, tmp_path), "all").indices, fewer.indices)
    path = _augmented_buffer(tmp_path / "aug.zarr.zip", np.random.default_rng(6))
    assert len(UmiPolicyDataset(path, _task(path, tmp_path), "all")) > \
        len(UmiPolicyDataset(path, _task(path, tmp_path, sample_replayed_tails=False), "all"))  # the default: all


def test_a_source_in_the_other_split_keeps_the_tail(tmp_path):
    """With validation, an augmented episode whose source demo is held out keeps its tail samples."""
    path = _augmented_buffer(tmp_path / "aug.zarr.zip", np.random.default_rng(7))
    task = _task(path, tmp_path, sample_replayed_tails=False)
    ds = UmiPolicyDataset(path, task, "all")
    ds.val_mask = np.array([True, False, False, False, False, False, False])  # demo 0's original held out
    ds._build_indices()
    ends, every = ds.episode_ends, UmiPolicyDataset(path, _task(path, tmp_path), "all")
    for ep in range(len(_EPISODES)):
        s = 0 if ep == 0 else ends[ep - 1]
        n_every = int((every.indices[:, 1] == s).sum())
        n_train = int((ds.indices[:, 1] == s).sum())
        src = _EPISODES[ep][1]
        if ep >= 2 and src == 0:
            assert n_train == n_every  # its source is in the other split
        elif ep >= 2 and src == 1:
            assert n_train < n_every


def test_bad_records_name_the_key(tmp_path):
    path = _augmented_buffer(tmp_path / "bad.zarr.zip", np.random.default_rng(8), bad_key="aug_splice_index")
    with pytest.raises(PolicyError, match=r"bad.zarr.zip: 'meta/aug_splice_index' has shape \(6,\)"):
        UmiPolicyDataset(path, _task(path, tmp_path, sample_replayed_tails=False), "all")
    UmiPolicyDataset(path, _task(path, tmp_path), "all")  # not read when every step is a sample


def test_first_left_out_step_per_episode(tmp_path):
    path = _augmented_buffer(tmp_path / "aug.zarr.zip", np.random.default_rng(9))
    task = _task(path, tmp_path, obs_down_sample_steps=3, sample_replayed_tails=False)  # h = 2: k + 3
    with ReplayBuffer.open(path) as buf:
        first, source = replayed_tail_first_sample(buf, path, task)
    assert first.tolist() == [-1, -1, 12 + 3, 5 + 3, 9 + 3, -1, -1]
    assert source.tolist() == [-1, -1, 0, 0, 1, -1, -1]
    task.img_obs_horizon = task.low_dim_obs_horizon = 1  # one observation row: from k + 1 on
    with ReplayBuffer.open(path) as buf:
        assert replayed_tail_first_sample(buf, path, task)[0].tolist() == [-1, -1, 13, 6, 10, -1, -1]
