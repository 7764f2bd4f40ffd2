from __future__ import annotations

import json

import numpy as np
import pytest
import zarr

from tests.data.helpers import lowdim_data, smooth_images, write_raw_buffer
from umi_aug.data import ReplayBuffer, validate_replay_buffer
from umi_aug.errors import DatasetError


def _raises(path, *fragments: str) -> str:
    """Assert that both the validator and ReplayBuffer.open reject ``path`` naming it and ``fragments``."""
    for fn in (validate_replay_buffer, ReplayBuffer.open):
        with pytest.raises(DatasetError) as info:
            fn(path)
        msg = str(info.value)
        assert str(path) in msg, msg
        for f in fragments:
            assert f in msg, (f, msg)
    return msg


def test_valid_buffer_report(tmp_path, rng):
    data = dict(lowdim_data(rng, 5), camera0_rgb=smooth_images(rng, 5, 8, 8))
    path = write_raw_buffer(tmp_path / "ok.zarr", data, np.array([2, 5], np.int64))
    rep = validate_replay_buffer(path)
    assert (rep.n_episodes, rep.n_steps, rep.warnings) == (2, 5, [])
    assert rep.keys["camera0_rgb"].shape == (5, 8, 8, 3) and rep.keys["robot0_demo_end_pose"].dtype == "float64"
    rep = validate_replay_buffer(write_raw_buffer(tmp_path / "i32.zarr", lowdim_data(rng, 5), np.array([5], np.int32)))
    assert any("int64" in w for w in rep.warnings)


@pytest.mark.parametrize("group", ["data", "meta"])
def test_missing_group(tmp_path, rng, group):
    path = write_raw_buffer(tmp_path / "b.zarr", lowdim_data(rng, 3), np.array([3]))
    zarr.open_group(str(path), mode="a").__delitem__(group)
    _raises(path, f"missing group '{group}/'")


def test_missing_episode_ends(tmp_path, rng):
    path = write_raw_buffer(tmp_path / "b.zarr", lowdim_data(rng, 3), None)
    _raises(path, "meta/episode_ends")


@pytest.mark.parametrize("ends", [np.array([[3]]), np.array([3.0])], ids=["2d", "float"])
def test_episode_ends_not_1d_integer(tmp_path, rng, ends):
    path = write_raw_buffer(tmp_path / "b.zarr", lowdim_data(rng, 3), ends)
    _raises(path, "meta/episode_ends", "1-D integer")


@pytest.mark.parametrize("ends,frag", [([2, 2, 3], "strictly increasing"), ([0, 3], "> 0"),
                                       ([2, 1, 3], "episode_ends[1] = 1")])
def test_episode_ends_not_increasing(tmp_path, rng, ends, frag):
    path = write_raw_buffer(tmp_path / "b.zarr", lowdim_data(rng, 3), np.array(ends, np.int64))
    _raises(path, "meta/episode_ends", frag)


@pytest.mark.parametrize("n,frag", [(4, "extra trailing data"), (2, "missing rows")])
def test_length_mismatch(tmp_path, rng, n, frag):
    data = lowdim_data(rng, 3)
    data["robot0_gripper_width"] = rng.uniform(size=(n, 1)).astype(np.float32)
    path = write_raw_buffer(tmp_path / "b.zarr", data, np.array([3], np.int64))
    _raises(path, "data/robot0_gripper_width", f"length {n}", frag)


@pytest.mark.parametrize("key", ["robot0_eef_pos", "robot0_eef_rot_axis_angle", "robot0_gripper_width",
                                 "robot0_demo_start_pose", "robot0_demo_end_pose"])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nonfinite_pose_values(tmp_path, rng, key, bad):
    data = lowdim_data(rng, 6)
    data[key][4, 0] = bad
    data[key][5, 0] = bad
    path = write_raw_buffer(tmp_path / "b.zarr", data, np.array([3, 6], np.int64))
    _raises(path, f"data/{key}", "row 4")
    assert validate_replay_buffer(path, check_values=False).n_steps == 6


@pytest.mark.parametrize("img", [np.zeros((3, 8, 8), np.uint8), np.zeros((3, 8, 8, 4), np.uint8),
                                 np.zeros((3, 8, 8, 3), np.float32), np.zeros((3, 8, 8, 3), np.uint16)],
                         ids=["no-channels", "rgba", "float32", "uint16"])
def test_bad_image_shape_or_dtype(tmp_path, rng, img):
    path = write_raw_buffer(tmp_path / "b.zarr", dict(lowdim_data(rng, 3), camera1_rgb=img), np.array([3]))
    _raises(path, "data/camera1_rgb", "uint8" if img.ndim == 4 and img.shape[-1] == 3 else "(N, H, W, 3)")


@pytest.mark.parametrize("key,shape", [("robot0_eef_pos", (3, 4)), ("robot0_eef_rot_axis_angle", (3, 2)),
                                       ("robot0_gripper_width", (3,)), ("robot0_gripper_width", (3, 2)),
                                       ("robot0_demo_start_pose", (3, 7)), ("robot1_demo_end_pose", (3, 3))])
def test_wrong_pose_trailing_shape(tmp_path, rng, key, shape):
    data = dict(lowdim_data(rng, 3), **{key: np.zeros(shape, np.float32)})
    path = write_raw_buffer(tmp_path / "b.zarr", data, np.array([3]))
    _raises(path, f"data/{key}", "must have shape")


@pytest.mark.parametrize("where", ["data/robot0_eef_pos", "meta/episode_ends"])
def test_unknown_codec(tmp_path, rng, where):
    path = write_raw_buffer(tmp_path / "b.zarr", lowdim_data(rng, 3), np.array([3]))
    zpath = path / where / ".zarray"
    meta = json.loads(zpath.read_text())
    meta["compressor"] = {"id": "imagecodecs_made_up_codec", "level": 3}
    zpath.write_text(json.dumps(meta))
    _raises(path, f"'{where}'", "imagecodecs_made_up_codec", "register")


def test_unreadable_paths(tmp_path):
    bad_zip = tmp_path / "bad.zarr.zip"
    bad_zip.write_bytes(b"this is not a zip file")
    _raises(bad_zip, "not a readable zip")
    empty_dir = tmp_path / "empty.zarr"
    empty_dir.mkdir()
    _raises(empty_dir, "not a zarr group")
    with pytest.raises(DatasetError, match="not a zarr group"):
        ReplayBuffer.open(empty_dir, mode="a")
    assert list(empty_dir.iterdir()) == []  # append mode never creates a group
    _raises(tmp_path / "missing.zarr.zip", "no such file")


def test_validator_accepts_group_and_buffer(rng):
    rb = ReplayBuffer.create()
    rb.add_episode(lowdim_data(rng, 3))
    assert validate_replay_buffer(rb).n_steps == 3
    assert validate_replay_buffer(rb.root, name_for_messages="X").n_episodes == 1
    rb.data["robot0_eef_pos"][1] = np.nan
    with pytest.raises(DatasetError, match=r"X: key 'data/robot0_eef_pos' holds NaN/Inf, first at row 1"):
        validate_replay_buffer(rb.root, name_for_messages="X")
