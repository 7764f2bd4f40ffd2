from __future__ import annotations

import numpy as np
import pytest
import zarr

from tests.data.helpers import JXL_MAE_BOUND, JXL_MAX_BOUND, random_episode, random_tcp_poses
from umi_aug.data import ReplayBuffer, UmiJpegXl, episode_tcp_poses, make_umi_episode
from umi_aug.errors import DatasetError


def _assert_episode_equal(got: dict, want: dict) -> None:
    assert sorted(got) == sorted(want)
    for k, v in want.items():
        assert got[k].dtype == v.dtype and got[k].shape == v.shape, k
        if k.endswith("_rgb"):
            err = np.abs(got[k].astype(int) - v)
            assert err.mean() < JXL_MAE_BOUND and err.max() <= JXL_MAX_BOUND, (k, err.mean(), err.max())
        else:
            np.testing.assert_array_equal(got[k], v, err_msg=k)


@pytest.mark.parametrize("suffix", [".zarr", ".zarr.zip"])
def test_round_trip(tmp_path, rng, suffix):
    episodes = [random_episode(rng, n) for n in (4, 6, 3)]
    rb = ReplayBuffer.create()
    for ep in episodes:
        rb.add_episode(ep)
    assert rb.n_episodes == 3 and rb.n_steps == 13
    np.testing.assert_array_equal(rb.episode_lengths, [4, 6, 3])
    path = rb.save(tmp_path / f"ds{suffix}")
    assert [p.name for p in tmp_path.iterdir()] == [path.name]
    with ReplayBuffer.open(path) as rb2:
        assert rb2.episode_ends.dtype == np.int64
        np.testing.assert_array_equal(rb2.episode_ends, [4, 10, 13])
        assert rb2.keys() == sorted(episodes[0])
        for i, ep in enumerate(episodes):
            _assert_episode_equal(rb2.get_episode(i), ep)
        _assert_episode_equal(rb2.get_episode(-1), episodes[-1])
        assert rb2.get_episode_slice(1) == slice(4, 10)
        pos = [ep["robot0_eef_pos"] for ep in episodes]
        np.testing.assert_array_equal(rb2.get_steps("robot0_eef_pos", 2, 7), np.concatenate([pos[0][2:], pos[1][:3]]))
        info = rb2.report.keys["camera0_rgb"]
        assert info.chunks == (1, 64, 64, 3) and info.compressor == "imagecodecs_jpegxl"
        assert rb2.report.keys["robot0_eef_pos"].compressor is None
        with pytest.raises(DatasetError, match="read-only"):
            rb2.add_episode(episodes[0])
        copy = rb2.save(tmp_path / "copy.zarr")  # raw chunk copy from an opened (read-only) store
    with ReplayBuffer.open(copy) as rb3:
        _assert_episode_equal(rb3.get_episode(2), episodes[2])
    mem = ReplayBuffer.open(path, load_to_memory=True)
    assert isinstance(mem.root.store, zarr.MemoryStore)
    _assert_episode_equal(mem.get_episode(1), episodes[1])


def test_read_is_lazy(tmp_path, rng, monkeypatch):
    rb = ReplayBuffer.create()
    for n in (5, 4):
        rb.add_episode(random_episode(rng, n))
    path = rb.save(tmp_path / "ds.zarr.zip")
    calls = []
    orig = UmiJpegXl.decode
    monkeypatch.setattr(UmiJpegXl, "decode", lambda self, buf, out=None: calls.append(1) or orig(self, buf, out))
    with ReplayBuffer.open(path) as rb2:
        assert calls == []
        rb2.get_episode(1, keys=["camera0_rgb"])
        assert len(calls) == 4
        rb2["camera0_rgb"][7]
        assert len(calls) == 5


def test_episode_index_and_step_range_errors(rng):
    rb = ReplayBuffer.create()
    rb.add_episode(random_episode(rng, 3, images=False))
    rb.add_episode(random_episode(rng, 2, images=False))
    with pytest.raises(DatasetError, match=r"episode index 2 .*n_episodes=2"):
        rb.get_episode(2)
    with pytest.raises(DatasetError, match=r"-3 .*n_episodes=2"):
        rb.get_episode(-3)
    with pytest.raises(DatasetError, match="robot0_eef_pos"):
        rb.get_steps("robot0_eef_pos", 3, 6)
    with pytest.raises(DatasetError, match="nope"):
        rb["nope"]


def test_add_episode_rejects_mismatches(rng):
    rb = ReplayBuffer.create()
    first = random_episode(rng, 3)
    rb.add_episode(first)
    ep = random_episode(rng, 2)
    with pytest.raises(DatasetError, match="missing.*robot0_gripper_width"):
        rb.add_episode({k: v for k, v in ep.items() if k != "robot0_gripper_width"})
    with pytest.raises(DatasetError, match="unexpected.*extra"):
        rb.add_episode(dict(ep, extra=np.zeros((2, 1), np.float32)))
    with pytest.raises(DatasetError, match=r"camera0_rgb.*\(64, 64, 3\).*\(32, 32, 3\)"):
        rb.add_episode(dict(ep, camera0_rgb=np.zeros((2, 32, 32, 3), np.uint8)))
    with pytest.raises(DatasetError, match=r"robot0_eef_pos.*float32.*float64"):
        rb.add_episode(dict(ep, robot0_eef_pos=ep["robot0_eef_pos"].astype(np.float64)))
    with pytest.raises(DatasetError, match="same length|one length"):
        rb.add_episode(dict(ep, robot0_gripper_width=np.zeros((3, 1), np.float32)))
    bad = ep["robot0_eef_rot_axis_angle"].copy()
    bad[1, 2] = np.nan
    with pytest.raises(DatasetError, match=r"robot0_eef_rot_axis_angle.*index 1"):
        rb.add_episode(dict(ep, robot0_eef_rot_axis_angle=bad))
    with pytest.raises(DatasetError, match="camera0_rgb.*uint8"):
        rb.add_episode(dict(ep, camera0_rgb=ep["camera0_rgb"].astype(np.float32)))
    assert rb.n_episodes == 1 and rb.n_steps == 3 and rb["camera0_rgb"].shape[0] == 3  # nothing written


def test_chunk_and_compressor_overrides(tmp_path, rng):
    rb = ReplayBuffer.create()
    ep = random_episode(rng, 5, images=False)
    rb.add_episode(ep, chunks={"robot0_eef_pos": (2, 3)}, compressors={"robot0_eef_pos": "default"})
    rb.add_episode(random_episode(rng, 3, images=False))
    assert rb["robot0_eef_pos"].chunks == (2, 3)
    assert rb["robot0_eef_pos"].compressor.get_config()["cname"] == "lz4"
    assert rb["robot0_gripper_width"].chunks == (5, 1)  # from the first episode's length, like UMI
    assert rb["robot0_gripper_width"].compressor is None
    with ReplayBuffer.open(rb.save(tmp_path / "x.zarr.zip")) as rb2:
        np.testing.assert_array_equal(rb2.get_episode(0)["robot0_eef_pos"], ep["robot0_eef_pos"])


def test_append_in_place_directory(tmp_path, rng):
    rb = ReplayBuffer.create()
    eps = [random_episode(rng, 3), random_episode(rng, 4)]
    rb.add_episode(eps[0])
    path = rb.save(tmp_path / "ds.zarr")
    with ReplayBuffer.open(path, mode="a") as rb2:
        rb2.add_episode(eps[1])
    with ReplayBuffer.open(path) as rb3:
        np.testing.assert_array_equal(rb3.episode_ends, [3, 7])
        _assert_episode_equal(rb3.get_episode(1), eps[1])
    with pytest.raises(DatasetError, match="cannot be appended"):
        ReplayBuffer.open(rb.save(tmp_path / "ds.zarr.zip"), mode="a")


def _crash_append(path, rng, monkeypatch, half_written: bool) -> None:
    def boom(self, new_end):
        if half_written:
            self.meta["episode_ends"].resize(self.n_episodes + 1)  # grown but value not yet written
        raise RuntimeError("simulated crash")

    with ReplayBuffer.open(path, mode="a") as rb:
        with monkeypatch.context() as m:
            m.setattr(ReplayBuffer, "_commit_episode_end", boom)
            with pytest.raises(RuntimeError, match="simulated crash"):
                rb.add_episode(random_episode(rng, 2))


@pytest.mark.parametrize("half_written", [False, True])
def test_interrupted_append_is_detected_and_repaired(tmp_path, rng, monkeypatch, half_written):
    rb = ReplayBuffer.create()
    eps = [random_episode(rng, 3), random_episode(rng, 4)]
    for ep in eps:
        rb.add_episode(ep)
    path = rb.save(tmp_path / "ds.zarr")
    _crash_append(path, rng, monkeypatch, half_written)
    expect = "strictly increasing" if half_written else r"length 9 but episode_ends\[-1\] = 7.*`umi-aug repair "
    with pytest.raises(DatasetError, match=expect) as info:
        ReplayBuffer.open(path)
    assert str(path) in str(info.value)
    with ReplayBuffer.open(path, mode="a", repair=True) as rb2:
        assert rb2.n_episodes == 2 and rb2.n_steps == 7
        assert any("truncated key 'data/camera0_rgb'" in w for w in rb2.report.warnings)
        new = random_episode(rng, 5)
        rb2.add_episode(new)
    with ReplayBuffer.open(path) as rb3:
        np.testing.assert_array_equal(rb3.episode_ends, [3, 7, 12])
        _assert_episode_equal(rb3.get_episode(1), eps[1])
        _assert_episode_equal(rb3.get_episode(2), new)


@pytest.mark.parametrize("suffix", [".zarr", ".zarr.zip"])
def test_failed_save_leaves_nothing(tmp_path, rng, monkeypatch, suffix):
    rb = ReplayBuffer.create()
    rb.add_episode(random_episode(rng, 3))
    real_copy = zarr.copy_store

    def failing_copy(source, dest, **kw):
        real_copy(source, dest, includes=["meta/.*"], **kw)  # write part of the store, then fail
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(zarr, "copy_store", failing_copy)
    with pytest.raises(OSError, match="simulated"):
        rb.save(tmp_path / f"out{suffix}")
    assert list(tmp_path.iterdir()) == []


def test_failed_overwrite_keeps_old_file(tmp_path, rng, monkeypatch):
    rb = ReplayBuffer.create()
    rb.add_episode(random_episode(rng, 3, images=False))
    path = rb.save(tmp_path / "out.zarr.zip")
    before = path.read_bytes()
    rb.add_episode(random_episode(rng, 2, images=False))
    monkeypatch.setattr(zarr, "copy_store", lambda *a, **k: (_ for _ in ()).throw(OSError("boom")))
    with pytest.raises(OSError):
        rb.save(path)
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["out.zarr.zip"]


def test_make_umi_episode_keys_and_inverse(rng):
    T = random_tcp_poses(rng, 6)
    width = rng.uniform(0, 0.08, 6)
    ep = make_umi_episode(T, width, robot=1)
    assert {k: (v.shape, v.dtype) for k, v in ep.items()} == {
        "robot1_eef_pos": ((6, 3), np.float32), "robot1_eef_rot_axis_angle": ((6, 3), np.float32),
        "robot1_gripper_width": ((6, 1), np.float32), "robot1_demo_start_pose": ((6, 6), np.float64),
        "robot1_demo_end_pose": ((6, 6), np.float64)}
    np.testing.assert_allclose(ep["robot1_demo_start_pose"][3, :3], T[0, :3, 3])
    np.testing.assert_allclose(ep["robot1_demo_end_pose"][0, :3], T[-1, :3, 3])
    T_back = episode_tcp_poses(ep, robot=1)
    assert T_back.dtype == np.float64 and T_back.shape == (6, 4, 4)
    np.testing.assert_allclose(T_back, T, atol=2e-6)  # float32 storage
    ep2 = make_umi_episode(T, width[:, None], demo_start_pose=T[2], demo_end_pose=np.arange(6.0))
    np.testing.assert_array_equal(ep2["robot0_demo_start_pose"], np.tile(_p6(T[2]), (6, 1)))
    np.testing.assert_array_equal(ep2["robot0_demo_end_pose"], np.tile(np.arange(6.0), (6, 1)))
    with pytest.raises(DatasetError, match="gripper_width"):
        make_umi_episode(T, width[:5])
    with pytest.raises(DatasetError, match=r"images\[0\]"):
        make_umi_episode(T, width, {0: np.zeros((6, 8, 8, 3), np.float32)})
    with pytest.raises(DatasetError, match="robot0_eef_pos"):
        episode_tcp_poses(ep)


def _p6(T):
    from umi_aug.geometry import pose_to_pos_rotvec

    return pose_to_pos_rotvec(T)
