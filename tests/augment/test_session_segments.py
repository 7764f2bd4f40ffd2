"""A UMI session whose dataset episode is the tracked segment of its demo video (UMI's 06/07: lost SLAM frames at
the start and end of the video dropped, so the episode is shorter than the video) is augmented end to end, and
the augmented episodes replay the original episode's frames and poses after the splice."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from tests.augment.conftest import small_config

#: frames lost by SLAM at each end of the demo video
K = 7


@pytest.fixture(scope="module")
def segment_session(aug_session, tmp_path_factory):
    """The shared synthetic session with its demo's first/last K CSV rows lost and the dataset episode cropped to
    the tracked frames [K, N - K), as UMI's pipeline writes it."""
    from umi_aug.data import ReplayBuffer
    from umi_aug.data.trajectory_csv import read_camera_trajectory_csv, write_camera_trajectory_csv

    root = tmp_path_factory.mktemp("segment_session") / "session"
    shutil.copytree(aug_session, root)
    demo = sorted(p for p in (root / "demos").iterdir() if p.name.startswith("demo"))[0]
    csv = demo / "camera_trajectory.csv"
    traj = read_camera_trajectory_csv(csv)
    n = len(traj)
    traj.is_lost[:K] = True
    traj.is_lost[n - K:] = True
    traj.T_world_cam[traj.is_lost] = 0.0
    traj.quat_xyzw = None
    write_camera_trajectory_csv(csv, traj)
    ds = root / "dataset.zarr.zip"
    with ReplayBuffer.open(ds) as buf:
        assert buf.n_episodes == 1 and buf.n_steps == n
        ep = {k: np.asarray(v)[K:n - K] for k, v in buf.get_episode(0).items()}
    ds.unlink()
    out = ReplayBuffer.create()
    out.add_episode(ep)
    out.save(ds)
    return root, n


def test_segment_episode_is_augmented_and_replays_the_original(segment_session, aug_assets, tmp_path):
    from umi_aug.augment import export, prepare_session, read_episode_records
    from umi_aug.data import ReplayBuffer, episode_tcp_poses, validate_replay_buffer

    root, n = segment_session
    cfg = small_config(mode="freespace", n_per_demo=2)
    work = tmp_path / "work"
    out = tmp_path / "aug.zarr"
    s = export(root, out, cfg, work_dir=work, progress=False, pictures=False)
    assert (s.n_original, s.n_augmented, s.n_failed) == (1, 2, 0)
    assert validate_replay_buffer(out).n_episodes == 3

    # the demo is the video's tracked segment: the uncropped session's poses and widths [K, N - K)
    a = prepare_session(root, work, cfg, progress=False)
    assert all(r.skipped for r in a.stages.values())
    d, full = a.demos[0], aug_assets.demos[0]
    assert len(d.T_world_cam) == n - 2 * K == len(full.T_world_cam) - 2 * K
    assert np.allclose(d.T_world_cam, full.T_world_cam[K:n - K], atol=1e-9)
    assert np.array_equal(d.gripper_width, full.gripper_width[K:n - K])
    assert d.contact_index is not None and 0 < d.contact_index < n - 2 * K

    rec = read_episode_records(out)
    with ReplayBuffer.open(out) as buf, ReplayBuffer.open(root / "dataset.zarr.zip") as src:
        orig = src.get_episode(0)
        for e in (1, 2):  # after the splice: the original segment's frames, widths and TCP poses
            ep = buf.get_episode(e)
            sp = int(rec["aug_splice_index"][e])
            tail = len(ep["camera0_rgb"]) - sp
            assert 0 < sp and 0 < tail < n - 2 * K
            assert np.array_equal(ep["camera0_rgb"][sp:], orig["camera0_rgb"][-tail:])
            assert np.array_equal(ep["robot0_gripper_width"][sp:], orig["robot0_gripper_width"][-tail:])
            assert np.allclose(episode_tcp_poses(ep)[sp:], episode_tcp_poses(orig)[-tail:], atol=1e-5)
            # and they start elsewhere: the augmented part is new
            assert not np.allclose(ep["robot0_eef_pos"][0], orig["robot0_eef_pos"][0], atol=1e-3)


def test_dataset_scenes_are_built_lazily_per_group(aug_session, tmp_path):
    """A plain dataset of two episodes, one scene group each: the handle builds nothing up front, generating an
    episode builds only its group (cached on disk), and an export of group 1's episodes never builds group 0."""
    from umi_aug.augment import export, read_episode_records
    from umi_aug.augment.dataset_source import DatasetInput, prepare_dataset
    from umi_aug.data import ReplayBuffer

    ds = tmp_path / "two.zarr.zip"
    with ReplayBuffer.open(aug_session / "dataset.zarr.zip") as src:
        ep = src.get_episode(0)
    # the synthetic demo holds its pose exactly while grasping; the dataset check reads that as lost tracking
    ep["robot0_eef_pos"] = ep["robot0_eef_pos"] + 2e-6 * np.arange(len(ep["robot0_eef_pos"]), dtype=np.float32)[:, None]
    two = ReplayBuffer.create()
    two.add_episode(ep)
    two.add_episode(ep)
    two.save(ds)
    cfg = small_config(mode="freespace", n_per_demo=1)
    work = tmp_path / "work"
    scenes = work / "scenes"

    small = dict(sfm_stride=4, background_points=0)  # a cheap scene (only laziness is tested)
    a = prepare_dataset(ds, work, cfg, DatasetInput(**small), progress=False, lazy=True)
    assert sorted(a.groups) == ["ep000000", "ep000001"] and a.augmentable == [0, 1]
    assert not scenes.exists() and a.group_paths == {}
    h = a.for_demo(1)
    assert sorted(p.name for p in scenes.iterdir()) == ["ep000001"]  # group 0 untouched
    assert list(a.group_paths) == ["ep000001"] and h.paths["splat"].startswith(str(scenes / "ep000001"))
    assert a.demos[1].contact_index is not None and a.demos[0].contact_index is None

    inp = DatasetInput(episodes=(1,), **small)
    s = export(ds, tmp_path / "aug.zarr", cfg, work_dir=work, dataset_input=inp, progress=False, pictures=False)
    assert (s.n_original, s.n_augmented, s.n_failed) == (2, 1, 0)
    assert sorted(p.name for p in scenes.iterdir()) == ["ep000001"]
    rec = read_episode_records(tmp_path / "aug.zarr")
    # the original's splice record is filled in once its lazily built group knows it
    assert rec["aug_splice_index"][:2].tolist() == [-1, a.demos[1].contact_index]
    assert rec["aug_source_episode"].tolist() == [0, 1, 1]
