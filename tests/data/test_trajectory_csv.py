from __future__ import annotations

import numpy as np
import pytest

from tests.data.helpers import random_tcp_poses
from umi_aug.data import CameraTrajectory, read_camera_trajectory_csv, write_camera_trajectory_csv
from umi_aug.errors import DatasetError

HEADER = "frame_idx,timestamp,state,is_lost,is_keyframe,x,y,z,q_x,q_y,q_z,q_w"
# ORB-SLAM3-style rows: quaternion xyzw; row 2 lost. q = rotation of 90 deg about z -> (0,0,sin45,cos45).
SLAM_TEXT = (HEADER + "\n"
             "0,0,2,false,true,0.1,0.2,0.3,0,0,0.70710678,0.70710678\n"
             "1,0.0166833,2,false,false,0.11,0.2,0.3,0,0,0,1\n"
             "2,0.0333667,3,true,false,0,0,0,0,0,0,0\n"
             "3,0.05005,2,false,false,0.12,0.2,0.3,0,0,0,1\n")


def _write(tmp_path, text: str, name: str = "camera_trajectory.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


def _random_traj(rng, n: int) -> CameraTrajectory:
    lost = rng.uniform(size=n) < 0.3
    T = random_tcp_poses(rng, n)
    T[lost] = np.eye(4)
    fi = np.cumsum(rng.integers(1, 3, n)) - 1
    return CameraTrajectory(frame_idx=fi.astype(np.int64), timestamp=fi / 59.94, state=np.where(lost, 3, 2),
                            is_lost=lost, is_keyframe=~lost & (rng.uniform(size=n) < 0.2), T_world_cam=T)


def test_parse_slam_rows_lost_flagged_not_dropped(tmp_path):
    tr = read_camera_trajectory_csv(_write(tmp_path, SLAM_TEXT))
    assert len(tr) == 4 and tr.frame_idx.dtype == np.int64 and tr.state.dtype == np.int64
    np.testing.assert_array_equal(tr.is_lost, [False, False, True, False])
    np.testing.assert_array_equal(tr.valid, [True, True, False, True])
    np.testing.assert_array_equal(tr.is_keyframe, [True, False, False, False])
    np.testing.assert_array_equal(tr.T_world_cam[2], np.eye(4))
    np.testing.assert_allclose(tr.T_world_cam[0, :3, 3], [0.1, 0.2, 0.3])
    np.testing.assert_allclose(tr.T_world_cam[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-8)
    assert tr.timestamp[1] == 0.0166833


def test_write_read_round_trip_exact(tmp_path, rng):
    traj = _random_traj(rng, 40)
    traj.is_lost[3], traj.is_keyframe[3], traj.T_world_cam[3] = True, False, np.eye(4)
    p1 = write_camera_trajectory_csv(tmp_path / "a.csv", traj)
    lines = p1.read_text().splitlines()
    assert lines[0] == HEADER and len(lines) == 41
    assert lines[4].split(",", 3)[3] == "true,false,0,0,0,0,0,0,0"
    r1 = read_camera_trajectory_csv(p1)
    for f in ("frame_idx", "timestamp", "state", "is_lost", "is_keyframe"):
        np.testing.assert_array_equal(getattr(r1, f), getattr(traj, f), err_msg=f)
    np.testing.assert_allclose(r1.T_world_cam[r1.valid], traj.T_world_cam[traj.valid], atol=1e-14)
    np.testing.assert_array_equal(r1.T_world_cam[r1.is_lost], np.broadcast_to(np.eye(4), (r1.is_lost.sum(), 4, 4)))
    r2 = read_camera_trajectory_csv(write_camera_trajectory_csv(tmp_path / "b.csv", r1))
    for f in ("frame_idx", "timestamp", "state", "is_lost", "is_keyframe", "T_world_cam", "quat_xyzw"):
        np.testing.assert_array_equal(getattr(r2, f), getattr(r1, f), err_msg=f)
    assert (tmp_path / "b.csv").read_text() == p1.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "b.csv"]


def test_edited_pose_is_written_not_stale_quaternion(tmp_path):
    tr = read_camera_trajectory_csv(_write(tmp_path, SLAM_TEXT))
    tr.T_world_cam[0, :3, :3] = np.eye(3)
    back = read_camera_trajectory_csv(write_camera_trajectory_csv(tmp_path / "o.csv", tr))
    np.testing.assert_allclose(back.T_world_cam[0], tr.T_world_cam[0], atol=1e-15)


def test_small_quaternion_deviation_is_renormalised(tmp_path):
    text = SLAM_TEXT.replace("0.11,0.2,0.3,0,0,0,1", "0.11,0.2,0.3,0,0,0,1.05")
    tr = read_camera_trajectory_csv(_write(tmp_path, text))
    np.testing.assert_allclose(tr.quat_xyzw[1], [0, 0, 0, 1])
    np.testing.assert_allclose(tr.T_world_cam[1, :3, :3], np.eye(3))


def test_nan_on_lost_row_is_fine(tmp_path):
    text = SLAM_TEXT.replace("3,true,false,0,0,0,0,0,0,0", "3,true,false,nan,nan,nan,0,0,0,0")
    assert read_camera_trajectory_csv(_write(tmp_path, text)).is_lost[2]


@pytest.mark.parametrize("old,new,line,column", [
    ("q_w", "qw", 1, "q_w"),
    ("is_keyframe,", "", 1, "is_keyframe"),
    ("1,0.0166833,2", "1,0.01x6833,2", 3, "timestamp"),
    ("1,0.0166833,2", "1.5,0.0166833,2", 3, "frame_idx"),
    ("1,0.0166833,2", "1,0.0166833,two", 3, "state"),
    ("3,true,false", "3,yes,false", 4, "is_lost"),
    ("2,false,false,0.11", "2,false,False_,0.11", 3, "is_keyframe"),
    ("3,0.05005", "1,0.05005", 5, "frame_idx"),
    ("0.11,0.2,0.3", "0.11,nan,0.3", 3, "y"),
    ("0.12,0.2,0.3,0,0,0,1", "0.12,0.2,0.3,0,0,0,inf", 5, "q_w"),
    ("0.12,0.2,0.3,0,0,0,1", "0.12,0.2,0.3,0,0,0,0", 5, "q_w"),
    ("0.12,0.2,0.3,0,0,0,1", "0.12,0.2,0.3,0,0,0,1.5", 5, "q_w"),
    ("1,0.0166833,2", "1,nan,2", 3, "timestamp"),
])
def test_malformed_csv(tmp_path, old, new, line, column):
    assert old in SLAM_TEXT
    path = _write(tmp_path, SLAM_TEXT.replace(old, new, 1))
    with pytest.raises(DatasetError) as info:
        read_camera_trajectory_csv(path)
    msg = str(info.value)
    assert str(path) in msg and f"line {line}" in msg and column in msg, msg


def test_wrong_field_count_and_empty(tmp_path):
    with pytest.raises(DatasetError, match=r"line 3: expected 12 fields, got 11"):
        read_camera_trajectory_csv(_write(tmp_path, SLAM_TEXT.replace("0.11,0.2,", "0.11,")))
    with pytest.raises(DatasetError, match="line 1: empty file"):
        read_camera_trajectory_csv(_write(tmp_path, ""))
    with pytest.raises(DatasetError, match="cannot read"):
        read_camera_trajectory_csv(tmp_path / "missing.csv")


def test_writer_rejects_bad_trajectories(tmp_path, rng):
    traj = _random_traj(rng, 5)
    traj.is_lost[:] = False
    traj.T_world_cam[2, 0, 3] = np.nan
    with pytest.raises(DatasetError, match="row 2"):
        write_camera_trajectory_csv(tmp_path / "x.csv", traj)
    traj.timestamp = traj.timestamp[:4]
    with pytest.raises(DatasetError, match="timestamp"):
        write_camera_trajectory_csv(tmp_path / "x.csv", traj)
    assert list(tmp_path.iterdir()) == []
