"""The on-the-fly AugmentedUmiDataset: equals the offline export, deterministic, worker-safe, bounded caches."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from tests.augment.conftest import SIZE, small_config


def _task(**kw):
    from umi_aug.policy.config import TaskConfig

    base = dict(image_size=SIZE, obs_down_sample_steps=1, action_horizon=8, val_ratio=0.0)
    base.update(kw)
    return TaskConfig(**base)


@pytest.fixture(scope="module")
def original(aug_session):
    from umi_aug.policy.dataset import UmiPolicyDataset

    return UmiPolicyDataset(aug_session / "dataset.zarr.zip", _task(), "train", start_pose_noise=0.0)


@pytest.fixture(scope="module")
def noisy_original(aug_session):
    """UMI's training-split start-pose noise on (``task.start_pose_noise``)."""
    from umi_aug.policy.dataset import UmiPolicyDataset

    return UmiPolicyDataset(aug_session / "dataset.zarr.zip", _task(), "train")


def _dataset(original, assets, **kw):
    from umi_aug.policy.augmented_dataset import AugmentedUmiDataset

    base = dict(modes=("freespace",), ratio=0.5, n_aug_per_demo=3, seed=11)
    base.update(kw)
    return AugmentedUmiDataset(original, assets, **base)


def _same(a, b, atol=0.0):
    assert a.keys() == b.keys()
    for k in a["obs"]:
        torch.testing.assert_close(a["obs"][k], b["obs"][k], atol=atol, rtol=0)
    torch.testing.assert_close(a["action"], b["action"], atol=atol, rtol=0)


def test_layout_ratio_and_original_samples(original, aug_assets):
    ds = _dataset(original, aug_assets, ratio=0.25)
    n = len(original)
    assert len(ds) == n + round(n * 0.25 / 0.75)
    _same(ds[3], original[3])
    with pytest.raises(IndexError):
        ds[len(ds)]


def test_augmented_samples_are_deterministic_and_render_only_the_window(noisy_original, aug_assets, rng):
    """Same seed → same augmented samples, start-pose noise included (it comes from the slot's generator)."""
    original = noisy_original
    a, b = _dataset(original, aug_assets), _dataset(original, aug_assets)
    n = len(original)
    idx = [int(i) for i in rng.choice(np.arange(n, len(a)), size=3, replace=False)]
    for i in idx:
        _same(a[i], b[i])
    s = a[idx[0]]
    assert s["obs"]["camera0_rgb"].shape == (2, 3, SIZE, SIZE)
    assert torch.isfinite(s["action"]).all() and s["action"].shape == (8, 10)
    # only the observation window's frames were made: at most img_obs_horizon (2) distinct frames per sample
    assert 0 < a.stats["frames_rendered"] <= 2 * (len(idx) + 1)
    # a new epoch draws other slots; the same epoch again gives the same samples
    a.set_epoch(1)
    moved = [a.slot(j)[:3] for j in range(20)]
    a.set_epoch(0)
    assert [a.slot(j)[:3] for j in range(20)] != moved
    _same(a[idx[1]], b[idx[1]])


def test_plan_cache_is_bounded(original, aug_assets):
    ds = _dataset(original, aug_assets, plan_cache_size=2, n_aug_per_demo=5)
    for aug_id in range(4):
        ds.planned(0, aug_id, "freespace")
    assert len(ds._plans) == 2 and ds.stats["plans"] == 4
    ds.planned(0, 3, "freespace")
    assert ds.stats["plan_hits"] == 1


def test_matches_the_offline_export(original, aug_session, aug_assets, tmp_path):
    """The same (demo, aug_id, mode, step) gives the same sample on the fly and from ``umi-aug augment``'s zarr
    (low-dim to float32 storage precision; images up to the export's JPEG-XL compression)."""
    from umi_aug.augment import export, read_episode_records
    from umi_aug.policy.dataset import UmiPolicyDataset

    out = tmp_path / "export.zarr.zip"
    export(aug_session, out, small_config(mode="freespace", n_per_demo=2), work_dir=aug_assets.work_dir,
           progress=False, pictures=False)
    rec = read_episode_records(out)
    exported = UmiPolicyDataset(out, _task(), "all", start_pose_noise=0.0)
    ds = _dataset(original, aug_assets)
    checked = 0
    for e in np.flatnonzero(rec["aug_mode"] == 1):
        demo, aug_id = int(rec["aug_source_episode"][e]), int(rec["aug_id"][e])
        start = 0 if e == 0 else int(exported.episode_ends[e - 1])
        rows = np.flatnonzero(exported.indices[:, 1] == start)
        for r in rows[[0, len(rows) // 2, -1]]:
            cur = int(exported.indices[r, 0]) - start
            on_the_fly = ds.augmented_sample(demo, aug_id, "freespace", cur)
            offline = exported[int(r)]
            torch.testing.assert_close(on_the_fly["action"], offline["action"], atol=2e-5, rtol=0)
            for k in offline["obs"]:
                if k != "camera0_rgb":
                    torch.testing.assert_close(on_the_fly["obs"][k], offline["obs"][k], atol=2e-5, rtol=0)
            diff = (on_the_fly["obs"]["camera0_rgb"] - offline["obs"]["camera0_rgb"]).abs()
            psnr = 10 * np.log10(1.0 / max(float((diff ** 2).mean()), 1e-12))
            assert psnr > 35.0, (e, cur, psnr)
            checked += 1
    assert checked >= 3


def test_rerendered_demo_samples_match_the_export_and_keep_the_demos_labels(original, aug_session, aug_assets,
                                                                          tmp_path):
    """``rerender_fraction``: a slot drawn as a re-rendered demo gives the sample of the export's
    ``--rerender-originals`` episode at the same step (images up to JPEG-XL), whose labels are the demo's own
    sample's; the approach frames are renders, not the recorded ones; 0 draws nothing more (the slots of a
    dataset without it); about that fraction of the slots is drawn."""
    from umi_aug.augment import RERENDER_MODE, export, read_episode_records
    from umi_aug.policy.dataset import UmiPolicyDataset

    out = tmp_path / "rr.zarr.zip"
    export(aug_session, out, small_config(mode="freespace", n_per_demo=1, rerender_originals=True),
           work_dir=aug_assets.work_dir, progress=False, pictures=False)
    rec = read_episode_records(out)
    e = int(np.flatnonzero(rec["aug_mode"] == 3)[0])
    c = int(rec["aug_splice_index"][e])
    exported = UmiPolicyDataset(out, _task(), "all", start_pose_noise=0.0)
    ds = _dataset(original, aug_assets, rerender_fraction=0.5)
    start = int(exported.episode_ends[e - 1])
    rows = np.flatnonzero(exported.indices[:, 1] == start)
    checked = 0
    for r in rows[[0, min(c // 2, len(rows) - 1), -1]]:
        cur = int(exported.indices[r, 0]) - start
        on_the_fly, offline, demo = ds.augmented_sample(0, 0, RERENDER_MODE, cur), exported[int(r)], original[cur]
        _same({"obs": {k: v for k, v in on_the_fly["obs"].items() if k != "camera0_rgb"},
               "action": on_the_fly["action"]},
              {"obs": {k: v for k, v in demo["obs"].items() if k != "camera0_rgb"}, "action": demo["action"]})
        torch.testing.assert_close(on_the_fly["action"], offline["action"], atol=0, rtol=0)
        diff = (on_the_fly["obs"]["camera0_rgb"] - offline["obs"]["camera0_rgb"]).abs()
        psnr = 10 * np.log10(1.0 / max(float((diff ** 2).mean()), 1e-12))
        assert psnr > 35.0, (cur, psnr)
        if cur < c - 1:  # every observed frame before the splice: rendered, not recorded
            to_recorded = (on_the_fly["obs"]["camera0_rgb"] - demo["obs"]["camera0_rgb"]).abs().mean()
            assert float(to_recorded) > 4 * float(diff.mean()), (cur, float(to_recorded), float(diff.mean()))
        checked += 1
    assert checked == 3
    plain = _dataset(original, aug_assets)
    assert [plain.slot(j)[:3] for j in range(30)] == [_dataset(original, aug_assets, rerender_fraction=0.0).slot(j)[:3]
                                                     for j in range(30)]
    modes = [ds.slot(j)[2] for j in range(400)]
    assert 150 <= modes.count(RERENDER_MODE) <= 250 and set(modes) == {"freespace", RERENDER_MODE}


def test_dataloader_workers_give_the_same_samples(original, aug_assets):
    ds = _dataset(original, aug_assets, ratio=0.2)
    n = len(original)
    idx = list(range(n, min(len(ds), n + 4)))
    sub = torch.utils.data.Subset(ds, idx)
    serial = list(torch.utils.data.DataLoader(sub, batch_size=2, num_workers=0))
    parallel = list(torch.utils.data.DataLoader(sub, batch_size=2, num_workers=2,
                                                multiprocessing_context="spawn"))
    for a, b in zip(serial, parallel):
        _same(a, b)


def test_normalizer_covers_augmented_episodes(original, aug_assets):
    """The ranges are fitted over the original AND planned augmented episodes, so the relative actions of the
    episodes it planned map into [-1, 1] (the original-only normaliser need not cover them)."""
    ds = _dataset(original, aug_assets)
    plain, wide = original.fit_normalizer(), ds.fit_normalizer(n_episodes=3)
    assert plain.keys() == wide.keys()
    s_plain, _ = plain.params("action")
    s_wide, _ = wide.params("action")
    assert (s_wide[:3] <= s_plain[:3] * (1 + 1e-5)).all()  # range scale = 2 / (max - min): never narrower
    planned = [ds.planned(*ds.slot(k, 1_000_000)[:3]) for k in range(3)]
    assert any(p is not None for p in planned)
    pose6, grip, start, _ = ds._episode_arrays(next(p for p in planned if p is not None))
    from umi_aug.policy.dataset import lowdim_from_rows, window_rows

    n = len(pose6[0])
    cur = np.arange(ds.n_current_steps(n), dtype=np.int64)
    low, a_rows = window_rows(original.task, cur, np.zeros_like(cur), np.full_like(cur, n))
    act = torch.from_numpy(lowdim_from_rows(original.task, pose6, grip, start, low, a_rows, cur)["action"])
    y = wide.normalize(act.float(), "action")
    assert torch.isfinite(y).all() and y[..., :3].abs().max() <= 1.0 + 1e-4


def test_bad_settings_are_named(original, aug_assets):
    from umi_aug.errors import PolicyError

    with pytest.raises(PolicyError, match="ratio"):
        _dataset(original, aug_assets, ratio=1.0)
    with pytest.raises(PolicyError, match="modes"):
        _dataset(original, aug_assets, modes=("sideways",))
    for bad in (1.0, -0.1, float("nan")):
        with pytest.raises(PolicyError, match="rerender_fraction"):
            _dataset(original, aug_assets, rerender_fraction=bad)
    from umi_aug.policy.dataset import UmiPolicyDataset

    other = UmiPolicyDataset(original.path, _task(image_size=SIZE), "train")
    other.task = _task(image_size=2 * SIZE)
    with pytest.raises(PolicyError, match="task.image_size"):
        _dataset(other, aug_assets)


@pytest.mark.slow  # the first user of the session fixture demo_run pays for the demo run (shared with tests/cli)
def test_train_workspace_with_aug_freespace(demo_run, tmp_path):
    """``aug=freespace`` end to end through the training workspace: the session holding task.dataset_path is
    prepared, augmented samples are drawn, a few optimisation steps run and a checkpoint is written.

    The session is a copy of the one ``umi-aug demo`` made (session fixture ``demo_run``) with a copy of its work
    folder: the trainer's settings give the same stage keys as the demo's, so every stage is a cache hit (asserted)
    instead of a second reconstruction."""
    import shutil

    from tests.conftest import DEMO_SPLAT_ITERATIONS, DEMO_SPLAT_MAX_GAUSSIANS
    from tests.policy.helpers import tiny_config
    from umi_aug.policy.augmented_dataset import AugmentedUmiDataset
    from umi_aug.policy.workspace import TrainWorkspace

    assert demo_run.rc == 0
    session = Path(shutil.copytree(demo_run.out / "session", tmp_path / "session"))
    work = Path(shutil.copytree(demo_run.out / "work", tmp_path / "aug_work"))
    cfg = tiny_config(session / "dataset.zarr.zip", tmp_path, image_size=224, obs_down_sample_steps=1,
                      action_horizon=8, val_ratio=0.0)
    cfg.aug.name = "freespace"
    cfg.aug.splat_iterations = DEMO_SPLAT_ITERATIONS
    cfg.aug.splat_max_gaussians = DEMO_SPLAT_MAX_GAUSSIANS
    cfg.aug.work_dir = str(work)
    cfg.aug.ratio = 0.5
    cfg.training.max_steps = 3
    ws = TrainWorkspace(cfg)
    train, _ = ws.build_datasets()
    assert isinstance(train, AugmentedUmiDataset) and train.n_augmented == len(train.original)
    stages = train.assets.stages
    assert {"reconstruct", "splat"} <= stages.keys() and all(st.skipped for st in stages.values()), \
        {k: st.skipped for k, st in stages.items()}
    summary = ws.run()
    assert (tmp_path / "run" / "checkpoints" / "latest.ckpt").is_file()
    assert summary["train_samples"] == len(train)
