"""UMI / ORB-SLAM3 ``camera_trajectory.csv`` (``System::SaveTrajectoryCSV`` of cheng-chi/ORB_SLAM3).

Header ``frame_idx,timestamp,state,is_lost,is_keyframe,x,y,z,q_x,q_y,q_z,q_w``; one row per video frame;
the pose is ``T_world_cam`` (camera → SLAM map, metres) with the quaternion in **xyzw** order;
``is_lost`` / ``is_keyframe`` are ``true`` / ``false``; lost rows hold ``0,0,0,0,0,0,0``. Lost frames are
flagged (``is_lost``), never dropped.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from umi_aug.errors import DatasetError
from umi_aug.geometry import matrix_to_quat_xyzw, pos_quat_xyzw_to_pose, quat_xyzw_to_matrix
from umi_aug.io_utils import atomic_write_text

COLUMNS: tuple[str, ...] = ("frame_idx", "timestamp", "state", "is_lost", "is_keyframe",
                            "x", "y", "z", "q_x", "q_y", "q_z", "q_w")
POSE_COLUMNS: tuple[str, ...] = COLUMNS[5:]
#: Accepted quaternion norm on tracked rows; outside → error, inside → renormalised.
QUAT_NORM_RANGE = (0.9, 1.1)
#: Norm deviations below this are kept as written (so read∘write∘read is bit-exact).
QUAT_RENORM_TOL = 1e-12


@dataclass
class CameraTrajectory:
    """One SLAM trajectory, one row per video frame.

    Attributes:
        frame_idx: int64 [N] strictly increasing video frame indices.
        timestamp: float64 [N] seconds from the video start (frame_idx / fps).
        state: int64 [N] ORB-SLAM tracking state.
        is_lost: bool [N] True where tracking was lost (pose is a placeholder).
        is_keyframe: bool [N].
        T_world_cam: float64 [N, 4, 4] camera pose in the SLAM map frame (metres); identity on lost rows.
        quat_xyzw: float64 [N, 4] or None: the rotation as read from the file (xyzw; zeros on lost rows).
            The writer uses it where it still matches ``T_world_cam`` exactly, so read∘write is exact;
            otherwise (or when None) the quaternion is derived from ``T_world_cam``.
    """

    frame_idx: np.ndarray
    timestamp: np.ndarray
    state: np.ndarray
    is_lost: np.ndarray
    is_keyframe: np.ndarray
    T_world_cam: np.ndarray
    quat_xyzw: np.ndarray | None = None

    @property
    def valid(self) -> np.ndarray:
        """bool [N]: rows with a tracked pose (``~is_lost``)."""
        return ~np.asarray(self.is_lost, dtype=bool)

    def __len__(self) -> int:
        return int(np.shape(self.frame_idx)[0])


def _fail(path: Path, line: int, column: str, msg: str) -> DatasetError:
    col = f"column '{column}' (#{COLUMNS.index(column) + 1})" if column in COLUMNS else f"column '{column}'"
    return DatasetError(f"{path}: line {line}, {col}: {msg}")


def _parse_bool(text: str, path: Path, line: int, column: str) -> bool:
    low = text.lower()
    if low not in ("true", "false"):
        raise _fail(path, line, column, f"expected 'true' or 'false', got {text!r}")
    return low == "true"


def _parse_num(text: str, kind: type, path: Path, line: int, column: str) -> float | int:
    try:
        return kind(text)
    except ValueError:
        raise _fail(path, line, column, f"cannot parse {text!r} as {kind.__name__}") from None


def read_camera_trajectory_csv(path: str | os.PathLike) -> CameraTrajectory:
    """Read a ``camera_trajectory.csv``; see :class:`CameraTrajectory` for the fields.

    Raises:
        DatasetError (naming file, line and column): missing/renamed header columns, wrong field count,
        unparsable numbers, booleans other than true/false, non-increasing frame_idx or timestamp, non-finite
        timestamp, non-finite pose or quaternion norm outside [0.9, 1.1] on a tracked row.
    """
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read camera trajectory CSV ({exc})") from exc
    if not lines or not lines[0].strip():
        raise DatasetError(f"{path}: line 1: empty file; expected header {','.join(COLUMNS)}")
    header = [h.strip() for h in lines[0].split(",")]
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise DatasetError(f"{path}: line 1: header lacks column(s) {missing}; got {','.join(header)}; "
                           f"expected {','.join(COLUMNS)}")
    col = {c: header.index(c) for c in COLUMNS}
    rows: list[tuple] = []
    for line_no, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        f = [s.strip() for s in line.split(",")]
        if len(f) != len(header):
            raise DatasetError(f"{path}: line {line_no}: expected {len(header)} fields, got {len(f)}")
        fi = _parse_num(f[col["frame_idx"]], int, path, line_no, "frame_idx")
        ts = _parse_num(f[col["timestamp"]], float, path, line_no, "timestamp")
        st = _parse_num(f[col["state"]], int, path, line_no, "state")
        lost = _parse_bool(f[col["is_lost"]], path, line_no, "is_lost")
        kf = _parse_bool(f[col["is_keyframe"]], path, line_no, "is_keyframe")
        pose = [_parse_num(f[col[c]], float, path, line_no, c) for c in POSE_COLUMNS]
        if rows and fi <= rows[-1][0]:
            raise _fail(path, line_no, "frame_idx", f"frame_idx must increase: {fi} after {rows[-1][0]}")
        if not math.isfinite(ts):
            raise _fail(path, line_no, "timestamp", f"non-finite timestamp {ts}")
        if rows and ts <= rows[-1][1]:
            raise _fail(path, line_no, "timestamp", f"timestamps must increase: {ts!r} s after {rows[-1][1]!r} s "
                        f"(frame_idx {fi} after {rows[-1][0]})")
        if not lost:
            for c, v in zip(POSE_COLUMNS, pose):
                if not math.isfinite(v):
                    raise _fail(path, line_no, c, f"non-finite pose value {v} on a tracked (is_lost=false) row")
            norm = math.sqrt(sum(v * v for v in pose[3:]))
            if not QUAT_NORM_RANGE[0] <= norm <= QUAT_NORM_RANGE[1]:
                raise _fail(path, line_no, "q_w", f"quaternion (x,y,z,w)={pose[3:]} has norm {norm:.6g}, "
                            f"outside {list(QUAT_NORM_RANGE)} on a tracked row")
            if abs(norm - 1.0) > QUAT_RENORM_TOL:
                pose[3:] = [v / norm for v in pose[3:]]
        rows.append((fi, ts, st, lost, kf, pose))
    n = len(rows)
    is_lost = np.array([r[3] for r in rows], dtype=bool)
    pose_arr = np.array([r[5] for r in rows], dtype=np.float64).reshape(n, 7)
    T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    if (~is_lost).any():
        T[~is_lost] = pos_quat_xyzw_to_pose(pose_arr[~is_lost, :3], pose_arr[~is_lost, 3:])
    return CameraTrajectory(
        frame_idx=np.array([r[0] for r in rows], dtype=np.int64),
        timestamp=np.array([r[1] for r in rows], dtype=np.float64),
        state=np.array([r[2] for r in rows], dtype=np.int64),
        is_lost=is_lost,
        is_keyframe=np.array([r[4] for r in rows], dtype=bool),
        T_world_cam=T,
        quat_xyzw=np.where(is_lost[:, None], 0.0, pose_arr[:, 3:]),
    )


def _quats_for_writing(traj: CameraTrajectory, T: np.ndarray) -> np.ndarray:
    """xyzw quaternions of ``T``: the stored ones where they reproduce ``T``'s rotation bit-exactly."""
    n = T.shape[0]
    q = np.zeros((n, 4))
    valid = traj.valid
    if not valid.any():
        return q
    q[valid] = matrix_to_quat_xyzw(T[valid, :3, :3])
    stored = None if traj.quat_xyzw is None else np.asarray(traj.quat_xyzw, dtype=np.float64)
    if stored is not None and stored.shape == (n, 4):
        cand = stored[valid]
        ok = (np.linalg.norm(cand, axis=1) > 0.5) & np.isfinite(cand).all(axis=1)
        same = np.zeros(ok.shape, dtype=bool)
        if ok.any():
            same[ok] = (quat_xyzw_to_matrix(cand[ok]) == T[valid][ok, :3, :3]).all(axis=(1, 2))
        q[np.flatnonzero(valid)[same]] = cand[same]
    return q


def write_camera_trajectory_csv(path: str | os.PathLike, traj: CameraTrajectory) -> Path:
    """Write ``traj`` as a UMI ``camera_trajectory.csv`` (atomic; floats as Python ``repr``, so reading
    the file back gives the same values). Lost rows are written ``...,true,<kf>,0,0,0,0,0,0,0``.

    Raises:
        DatasetError: inconsistent field lengths/shapes, or non-finite pose on a tracked row.
    """
    path = Path(path)
    fi = np.asarray(traj.frame_idx)
    n = fi.shape[0] if fi.ndim == 1 else -1
    T = np.asarray(traj.T_world_cam, dtype=np.float64)
    shapes = {"frame_idx": fi.shape, "timestamp": np.shape(traj.timestamp), "state": np.shape(traj.state),
              "is_lost": np.shape(traj.is_lost), "is_keyframe": np.shape(traj.is_keyframe)}
    bad = {k: s for k, s in shapes.items() if s != (n,)}
    if n < 0 or bad or T.shape != (n, 4, 4):
        raise DatasetError(f"{path}: CameraTrajectory fields must be [N] and T_world_cam [N,4,4]; got "
                           f"{shapes}, T_world_cam {T.shape}")
    valid = traj.valid
    finite = np.isfinite(T.reshape(n, 16)).all(axis=1) | ~valid
    if not finite.all():
        raise DatasetError(f"{path}: T_world_cam row {int(np.argmin(finite))} is non-finite on a tracked row")
    q = _quats_for_writing(traj, T)
    lines = [",".join(COLUMNS)]
    for i in range(n):
        head = (f"{int(fi[i])},{float(traj.timestamp[i])!r},{int(traj.state[i])},"
                f"{'true' if traj.is_lost[i] else 'false'},{'true' if traj.is_keyframe[i] else 'false'}")
        if not valid[i]:
            lines.append(head + ",0,0,0,0,0,0,0")
        else:
            vals = list(T[i, :3, 3]) + list(q[i])
            lines.append(head + "," + ",".join(repr(float(v)) for v in vals))
    return atomic_write_text(path, "\n".join(lines) + "\n")
