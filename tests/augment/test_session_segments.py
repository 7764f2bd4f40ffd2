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
