"""Issue #17 part 2: the on-the-fly dataset's fast paths give the reference's samples (same indices + seeds →
identical tensors), the on-disk plan cache is keyed by content, and persistent DataLoader workers (forked or
spawned) follow the epochs and give the samples of the per-epoch reference loader with any worker count.

Uses the small synthetic session of tests/augment (64², one demo; ~45 s to build and prepare once)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from tests.augment.conftest import SIZE  # fixtures aug_session/aug_assets: tests/conftest.py (shared)


def _task(**kw):
    from umi_aug.policy.config import TaskConfig

    base = dict(image_size=SIZE, obs_down_sample_steps=2, action_horizon=8, val_ratio=0.0)
    base.update(kw)
    return TaskConfig(**base)


@pytest.fixture(scope="module")
def noisy_original(aug_session):
    from umi_aug.policy.dataset import UmiPolicyDataset

    return UmiPolicyDataset(aug_session / "dataset.zarr.zip", _task(), "train")


def _dataset(original, assets, **kw):
    from umi_aug.policy.augmented_dataset import AugmentedUmiDataset

    base = dict(modes=("freespace",), ratio=0.5, n_aug_per_demo=4, seed=5)
    base.update(kw)
    return AugmentedUmiDataset(original, assets, **base)


def _same(a, b):
    assert a["obs"].keys() == b["obs"].keys()
    for k in a["obs"]:
        assert torch.equal(a["obs"][k], b["obs"][k]), k
        assert torch.isfinite(a["obs"][k]).all()
    assert torch.equal(a["action"], b["action"]) and torch.isfinite(a["action"]).all()


# ------------------------------------------------------------------------------------------- pieces vs reference
def test_read_rows_equals_original_frames(aug_assets, rng):
    from umi_aug.policy.augmented_paths import read_rows

    n = aug_assets.original.get_episode_slice(0).stop - aug_assets.original.get_episode_slice(0).start
    for rows in (rng.integers(0, n, 5), np.array([n - 1, 0, n - 1, 3]), np.array([7]), np.zeros(0, np.int64)):
        np.testing.assert_array_equal(read_rows(aug_assets, 0, rows), aug_assets.original_frames(0, rows))


def test_sample_frames_equal_render_episode_frames(aug_assets):
    from umi_aug.augment import plan_episode, render_episode_frames
    from umi_aug.errors import AugmentError
    from umi_aug.policy.augmented_paths import sample_frames

    planned = plan_episode(aug_assets, 0, 1, "freespace")
    assert planned is not None
    n, N = planned.splice_index, planned.n_frames
    timings: dict = {}
    for idx in ([0, 1], [n - 1, n], [n, N - 1], [N - 1], [n - 3, n - 3, 0], []):
        np.testing.assert_array_equal(sample_frames(aug_assets, planned, np.array(idx, np.int64), timings),
                                      render_episode_frames(aug_assets, planned, idx))
    assert timings["render"] > 0 and timings["decode"] > 0
    with pytest.raises(AugmentError, match="outside"):
        sample_frames(aug_assets, planned, np.array([N]))


# ------------------------------------------------------------------------------------------- whole samples
def test_fast_dataset_gives_the_reference_samples(noisy_original, aug_assets, tmp_path, rng):
    """Same indices and seeds → identical tensors (start-pose noise from the slot included), for the fast paths
    together and each alone; a second dataset (empty process cache) reads every plan from disk."""
    ref = _dataset(noisy_original, aug_assets, fast_paths=())
    n = len(noisy_original)
    idx = [int(i) for i in rng.choice(np.arange(n, len(ref)), size=6, replace=False)]
    want = [ref[i] for i in idx]
    for paths in (("plan_disk_cache", "frames"), ("frames",), ("plan_disk_cache",)):
        fast = _dataset(noisy_original, aug_assets, fast_paths=paths, plan_cache_dir=tmp_path / "plans")
        for i, w in zip(idx, want):
            _same(fast[i], w)
    again = _dataset(noisy_original, aug_assets, plan_cache_dir=tmp_path / "plans")
    for i, w in zip(idx, want):
        _same(again[i], w)
    assert again.stats["plans_solved"] == 0 and again.stats["plan_disk_hits"] == again.stats["plans"] > 0
    # the random samples' windows may all lie after the splice (replayed frames: nothing rendered); step 0 of a
    # planned episode is always a new, rendered frame
    demo, aug_id, mode, _ = again.slot(0)
    assert again.augmented_sample(demo, aug_id, mode, 0) is not None
    assert {"plan", "decode", "render", "lowdim", "to_tensor"} <= again.timings.keys()
    from umi_aug.errors import PolicyError

    with pytest.raises(PolicyError, match="fast_paths"):
        _dataset(noisy_original, aug_assets, fast_paths=("warp",))


def test_plan_disk_cache_is_keyed_by_content(aug_assets, tmp_path):
    import dataclasses

    from umi_aug.augment import plan_episode
    from umi_aug.policy.augmented_paths import PlanDiskCache, plan_cache_key

    cache = PlanDiskCache(tmp_path)
    assert cache.load(aug_assets, 0, 2, "freespace") == (False, None)
    planned = plan_episode(aug_assets, 0, 2, "freespace")
    cache.save(aug_assets, 0, 2, "freespace", planned)
    found, got = PlanDiskCache(tmp_path).load(aug_assets, 0, 2, "freespace")
    assert found and np.array_equal(got.episode.T_world_cam, planned.episode.T_world_cam)
    # another seed / cone / demo trajectory → another key; the same inputs → the same key
    key = plan_cache_key(aug_assets, 0)
    assert key == plan_cache_key(pickle.loads(pickle.dumps(aug_assets)), 0)
    for change in ({"seed": aug_assets.cfg.seed + 1}, {"cone_radius_m": 0.1}):
        other = dataclasses.replace(aug_assets, cfg=dataclasses.replace(aug_assets.cfg, **change))
        assert plan_cache_key(other, 0) != key
    demos = [dataclasses.replace(d) for d in aug_assets.demos]
    demos[0].gripper_width = demos[0].gripper_width + 1e-6
    assert plan_cache_key(dataclasses.replace(aug_assets, demos=demos), 0) != key
    # a file of another episode, or a broken one, is ignored (planned again)
    p = cache.path(aug_assets, 0, 3, "freespace")
    p.write_bytes(cache.path(aug_assets, 0, 2, "freespace").read_bytes())
    assert cache.load(aug_assets, 0, 3, "freespace") == (False, None)
    p.write_bytes(b"not a pickle")
    assert cache.load(aug_assets, 0, 3, "freespace") == (False, None)


# ------------------------------------------------------------------------------------------- loaders and epochs
def test_epoch_sampler_gives_the_per_epoch_loader_order():
    from umi_aug.policy.workspace import EpochSampler, epoch_seed

    ds = list(range(37))
    s = EpochSampler(len(ds), seed=42)
    for epoch in (0, 1, 5):
        g = torch.Generator()
        g.manual_seed(epoch_seed(42, epoch))
        ref = [int(i) for b in torch.utils.data.DataLoader(ds, batch_size=5, shuffle=True, generator=g) for i in b]
        s.set_epoch(epoch)
        assert list(s) == ref
    assert list(EpochSampler(5, 0, shuffle=False)) == [0, 1, 2, 3, 4]


def test_persistent_workers_follow_epochs_and_match_the_reference(noisy_original, aug_assets, tmp_path):
    """2 persistent spawned workers over 2 epochs (the epoch reaches them through shared memory) give exactly the
    batches of the reference: a new 0-worker loader per epoch with the reference paths. (Forked workers of a
    process that has rendered deadlock in numba's thread pool: the workspace spawns them, ``loader_context``.)"""
    from umi_aug.policy.workspace import loader_context, make_loader

    context = loader_context(aug_assets and _dataset(noisy_original, aug_assets))
    assert context == "spawn" and loader_context(noisy_original) == "spawn"

    n = len(noisy_original)
    ref_ds = _dataset(noisy_original, aug_assets, fast_paths=())
    ds = _dataset(noisy_original, aug_assets, plan_cache_dir=tmp_path / "plans")
    idx = list(range(0, n, max(1, n // 4)))[:4] + list(range(n, n + 8))
    orig_noise = noisy_original.start_pose_noise
    noisy_original.start_pose_noise = 0.0  # UMI's noise of ORIGINAL samples comes from each worker's RNG
    try:
        loader = make_loader(torch.utils.data.Subset(ds, idx), batch_size=4, shuffle=True, seed=3, num_workers=2,
                             persistent=True, context=context)
        for epoch in (0, 1):
            ref_ds.set_epoch(epoch)
            ds.set_epoch(epoch)
            loader.sampler.set_epoch(epoch)
            ref = make_loader(torch.utils.data.Subset(ref_ds, idx), batch_size=4, shuffle=True, seed=3,
                              epoch=epoch, num_workers=0, persistent=False)
            got = list(loader)
            want = list(ref)
            assert len(got) == len(want) == 3
            for a, b in zip(got, want):
                _same(a, b)
            if epoch == 0:
                first = got
        assert any(not torch.equal(a["action"], b["action"]) for a, b in zip(first, got))  # epochs differ
        assert loader._iterator is not None and loader._iterator._workers[0].is_alive()  # kept across epochs
    finally:
        noisy_original.start_pose_noise = orig_noise


def test_workspace_reuses_its_persistent_loader(dataset_path, tmp_path):
    from tests.policy.helpers import tiny_config
    from umi_aug.policy.dataset import UmiPolicyDataset
    from umi_aug.policy.workspace import EpochSampler, TrainWorkspace

    cfg = tiny_config(dataset_path, tmp_path)
    cfg.device.num_workers = 1
    ws = TrainWorkspace(cfg)
    ds = UmiPolicyDataset(dataset_path, cfg.task, "train")
    a, b = ws._loader(ds, True, 0), ws._loader(ds, True, 1)
    assert a is b and isinstance(a.sampler, EpochSampler) and a.sampler.epoch == 1 and a.persistent_workers
    cfg.dataloader.persistent_workers = False
    c = TrainWorkspace(cfg)._loader(ds, True, 1)
    assert not c.persistent_workers and c is not a


def test_on_the_fly_slots_skip_the_replayed_tail(aug_session, aug_assets, monkeypatch):
    """``task.sample_replayed_tails=false``: an augmented slot's current step lies before the steps that read only
    the replayed tail (those samples are the original episode's own, which the dataset already holds)."""
    from umi_aug.policy.augmented_dataset import AugmentedUmiDataset
    from umi_aug.policy.dataset import UmiPolicyDataset

    task = _task(sample_replayed_tails=False)
    original = UmiPolicyDataset(aug_session / "dataset.zarr.zip", task, "train")
    ds = _dataset(original, aug_assets)
    every = _dataset(UmiPolicyDataset(aug_session / "dataset.zarr.zip", _task(), "train"), aug_assets)
    seen: list[tuple[int, int, int, int]] = []
    real = AugmentedUmiDataset.augmented_sample

    def spy(self, demo, aug_id, mode, cur, noise_rng=None):
        p = self.planned(demo, aug_id, mode)
        seen.append((cur, p.splice_index, self.n_current_steps(p.n_frames), p.n_frames))
        return real(self, demo, aug_id, mode, cur, noise_rng)

    monkeypatch.setattr(AugmentedUmiDataset, "augmented_sample", spy)
    for i in range(len(original), len(original) + 12):
        ds[i]
    first_tail_only = [s + max(1, (task.img_obs_horizon - 1) * task.obs_down_sample_steps) for _, s, _, _ in seen]
    assert seen and all(cur < f for (cur, *_), f in zip(seen, first_tail_only))
    # the same slots with every step a sample may reach the tail: the limit is what cuts them
    _, s, n_all, n = seen[0]
    assert ds.n_current_steps(n, s) == min(n_all, first_tail_only[0]) < every.n_current_steps(n)
