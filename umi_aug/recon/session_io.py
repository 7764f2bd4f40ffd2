"""Reading what reconstruction needs from a UMI session folder, in UMI's real layout (umi_stack.md §1).

``<session>/demos/mapping/raw_video.mp4`` + ``mapping_camera_trajectory.csv`` (the scan),
``demos/<demo>/raw_video.mp4`` + ``camera_trajectory.csv`` (demonstrations), ``demos/mapping/tx_slam_tag.json``
(SLAM map → table tag), the GoPro intrinsics JSON and ``dataset.zarr.zip`` (gripper widths; optional
``dataset_plan.pkl``). No frames are extracted:
:meth:`ImageSequence.read_frames` decodes only the requested frame indices, at the size a stage asks for, in one
sequential pass (:mod:`umi_aug.data.video`). Old sessions with ``images/NNNNNN.jpg`` folders and no video are still
read (frames from the files).

CSV rows are aligned with the video by ``frame_idx`` (one row per frame, as ORB-SLAM3 writes them); tracking-lost
rows (``is_lost=true``) are kept as ``valid = False`` (pose = identity) and every stage skips them. ArUco tags: where
a sequence folder holds UMI's ``tag_detection.pkl`` (04_detect_aruco), every decoded frame gets its detected tags
inpainted the way UMI's 07_generate_replay_buffer does for the dataset images (quad grown 1.4x, filled with the
median colour of its border), so the scene the 3DGS learns looks like the dataset frames it is spliced into;
without it, frames are used as stored.

Demos are returned in the order of the dataset's episodes, one per episode. UMI's episodes are the tracked
segments of each demo video (lost frames dropped; a video may hold several, or none): each demo is cropped to its
episode's segment, found from ``dataset_plan.pkl`` (``cameras[0].video_start_end``) or, without it, by matching
the episode's ``robot0_eef_pos`` with the CSV's TCP poses (:func:`_assign_episodes`).

Poses are returned in the world = table-tag frame: ``T_world_cam = inv(tx_slam_tag) @ T_slam_cam`` (UMI's 06
script), OpenCV camera axes, metres. Every problem raises :class:`umi_aug.errors.ReconError` naming the file and what
to do.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import pickle
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np
from tqdm import tqdm

from umi_aug.camera.calib_io import load_umi_intrinsics_json
from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import ReconError, UmiAugError
from umi_aug.geometry.umi import UMI_TCP_OFFSET, umi_T_cam_tcp

__all__ = ["ImageSequence", "SessionData", "load_session", "check_image_sizes", "write_frames", "IMAGE_EXTENSIONS",
           "VIDEO_NAME"]

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png")
#: UMI's per-sequence video file (00_process_videos).
VIDEO_NAME = "raw_video.mp4"
#: UMI's per-video ArUco detections (04_detect_aruco); when present, the tags are inpainted in decoded frames.
TAG_DETECTIONS_NAME = "tag_detection.pkl"
#: Relative tolerance of ``timestamp`` against ``frame_idx / fps`` (a CSV of another video fails it).
TIMESTAMP_RTOL = 0.02


@dataclass
class ImageSequence:
    """One video with its (SLAM) camera poses, one row per video frame.

    Attributes:
        name: sequence name (``mapping`` or the demo folder name).
        source: the ``raw_video.mp4`` (or, old layout, the ``images/`` folder).
        n_frames: frames in the video (= CSV rows).
        frame_size: ``(width, height)`` of the stored frames, pixels.
        T_world_cam: np.ndarray | None,  # [N, 4, 4] table-tag frame, metres (None: no poses); identity on lost rows
        valid: np.ndarray,  # [N] bool, pose tracked (not lost)
        timestamp: np.ndarray,  # [N] seconds from the video start
        gripper_width: np.ndarray | None,  # [N] metres (demos, from the replay buffer), None if unknown
        image_paths: old layout only: the N frame files; None for videos.
        fps: the video's frame rate (NaN for image folders).
        frame_offset: video frame of this sequence's frame 0 (a demo cropped to its dataset episode, a valid SLAM
            segment of the video: :meth:`cropped`); frame indices of every method are relative to it.
        tag_corners: ArUco tags per video frame (``{video frame: [[4, 2] corners, pixels of the stored frames]}``,
            from UMI's ``tag_detection.pkl``), inpainted in every decoded frame as UMI's dataset images are
            (:func:`umi_aug.data.video.inpaint_tag`); None: frames as stored.
    """

    name: str
    source: Path
    n_frames: int
    frame_size: tuple[int, int]
    T_world_cam: np.ndarray | None
    valid: np.ndarray
    timestamp: np.ndarray
    gripper_width: np.ndarray | None = None
    image_paths: list[Path] | None = None
    fps: float = float("nan")
    frame_offset: int = 0
    tag_corners: dict[int, list[np.ndarray]] | None = field(default=None, repr=False)
    _info: object | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        at = f" from video frame {self.frame_offset}" if self.frame_offset else ""
        return (f"ImageSequence({self.name!r}, {self.source}, {self.n_frames} frames{at} "
                f"{self.frame_size[0]}x{self.frame_size[1]}, {int(np.sum(self.valid))} tracked, "
                f"poses={'yes' if self.T_world_cam is not None else 'no'}, "
                f"widths={'yes' if self.gripper_width is not None else 'no'})")

    @staticmethod
    def frame_name(k: int) -> str:
        """File-style name of frame ``k`` (``000123``), used for SfM image names and 3DGS view names."""
        return f"{int(k):06d}"

    def _indices(self, indices: Sequence[int] | np.ndarray) -> np.ndarray:
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        if len(idx) and (idx.min() < 0 or idx.max() >= self.n_frames or np.any(np.diff(idx) <= 0)):
            raise ReconError(f"{self.source}: frame indices must be increasing within [0, {self.n_frames}); got "
                             f"{idx[:6].tolist()}{'...' if len(idx) > 6 else ''}")
        return idx

    def iter_frames(self, indices: Sequence[int] | np.ndarray, size: tuple[int, int] | None = None
                    ) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(k, rgb [h, w, 3] uint8)`` for the increasing frame indices ``indices``; ``size = (w, h)``: full-
        height centre crop + area resize (intrinsics ``FisheyeIntrinsics.scaled(w, h)``), None = stored size.
        Videos are decoded once, sequentially, keeping only these frames."""
        from umi_aug.data.video import centre_crop, iter_video_frames  # lazy, start-up: zarr

        idx = self._indices(indices)
        if self.image_paths is None:
            try:
                for k, img in iter_video_frames(self.source, idx + self.frame_offset, size, info=self._info):
                    yield k - self.frame_offset, self._inpaint_tags(img, k)
            except UmiAugError as exc:
                raise ReconError(f"{exc}; re-copy the video or re-create the session") from exc
            return
        for k in idx.tolist():
            p = self.image_paths[k]
            bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if bgr is None:
                raise ReconError(f"{p}: unreadable image")
            img = np.ascontiguousarray(bgr[..., ::-1])
            if img.shape[:2] != self.frame_size[::-1]:
                raise ReconError(f"{p}: frame is {img.shape[1]}x{img.shape[0]}, the sequence's first frame "
                                 f"{self.frame_size[0]}x{self.frame_size[1]}")
            if size is not None and tuple(size) != self.frame_size:
                x0, y0, cw, ch = centre_crop(*self.frame_size, *size)
                img = cv2.resize(img[y0:y0 + ch, x0:x0 + cw], tuple(int(s) for s in size),
                                 interpolation=cv2.INTER_AREA)
            yield k, self._inpaint_tags(img, k + self.frame_offset)

    def _inpaint_tags(self, img: np.ndarray, video_frame: int) -> np.ndarray:
        """``img`` (a decoded frame, possibly centre-cropped and resized) with the tags of ``video_frame`` covered
        (UMI's ``inpaint_tag``, corners mapped from the stored frame's pixels)."""
        tags = None if self.tag_corners is None else self.tag_corners.get(int(video_frame))
        if not tags:
            return img
        from umi_aug.data.video import centre_crop, inpaint_tag  # lazy, start-up: zarr

        h, w = img.shape[:2]
        W, H = self.frame_size
        x0, y0, cw, ch = (0, 0, W, H) if (w, h) == (W, H) else centre_crop(W, H, w, h)
        img = np.array(img, copy=not img.flags.writeable, order="C")
        for c in tags:
            inpaint_tag(img, (np.asarray(c, np.float64) - (x0, y0)) * (w / cw, h / ch))
        return img

    def cropped(self, start: int, stop: int, name: str | None = None) -> "ImageSequence":
        """Frames ``[start, stop)`` of this sequence as a sequence of their own (poses, validity, timestamps
        cropped; no gripper widths), reading the same video from frame ``frame_offset + start``."""
        start, stop = int(start), int(stop)
        if not 0 <= start < stop <= self.n_frames:
            raise ReconError(f"{self.source}: crop [{start}, {stop}) outside the {self.n_frames} frames")
        # image folders: the crop's image_paths start at frame ``start``; frame_offset still names the original
        # frame (tag detections are keyed by it)
        return dataclasses.replace(
            self, name=self.name if name is None else name, n_frames=stop - start,
            T_world_cam=None if self.T_world_cam is None else self.T_world_cam[start:stop].copy(),
            valid=self.valid[start:stop].copy(), timestamp=self.timestamp[start:stop].copy(), gripper_width=None,
            image_paths=None if self.image_paths is None else self.image_paths[start:stop],
            frame_offset=self.frame_offset + start)

    def read_frames(self, indices: Sequence[int] | np.ndarray, size: tuple[int, int] | None = None,
                    progress: bool = False) -> np.ndarray:
        """:meth:`iter_frames` stacked: ``[K, h, w, 3]`` uint8 RGB."""
        idx = self._indices(indices)
        w, h = self.frame_size if size is None else (int(size[0]), int(size[1]))
        out = np.empty((len(idx), h, w, 3), dtype=np.uint8)
        it = self.iter_frames(idx, size)
        if progress:
            it = tqdm(it, total=len(idx), desc=f"decode {self.name}", unit="frame")
        for j, (_, img) in enumerate(it):
            out[j] = img
        return out


@dataclass
class SessionData:
    """A session's scan, demos and intrinsics.

    Attributes:
        root: session folder.
        intrinsics: fisheye intrinsics at the stored frames' size (``frame_size`` of every sequence).
        mapping: the scan sequence.
        demos: demo sequences, sorted by name (same order as the replay buffer's episodes).
    """

    root: Path
    intrinsics: FisheyeIntrinsics
    mapping: ImageSequence
    demos: list[ImageSequence]

    def intrinsics_at(self, width: int | None) -> tuple[FisheyeIntrinsics, tuple[int, int] | None]:
        """Intrinsics for frames decoded at most ``width`` pixels wide (height keeps the aspect ratio) and the
        ``size`` argument of :meth:`ImageSequence.read_frames` (None = stored size)."""
        intr = self.intrinsics
        if width is None or int(width) >= intr.width:
            return intr, None
        w = int(width)
        h = int(round(w * intr.height / intr.width))
        return intr.scaled(w, h), (w, h)


def _image_files(folder: Path) -> list[Path]:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise ReconError(f"{folder}: contains no {'/'.join(IMAGE_EXTENSIONS)} frames and there is no "
                         f"{folder.parent / VIDEO_NAME}")
    return files


def _tx_slam_tag(root: Path) -> np.ndarray:
    p = root / "demos" / "mapping" / "tx_slam_tag.json"
    if not p.is_file():
        return np.eye(4)
    try:
        T = np.asarray(json.loads(p.read_text())["tx_slam_tag"], dtype=np.float64)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ReconError(f"{p}: unreadable key `tx_slam_tag` ({exc}); re-run UMI's calibrate_slam_tag") from exc
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ReconError(f"{p}: `tx_slam_tag` must be a finite 4x4 matrix, got shape {T.shape}")
    return T


def _sequence(folder: Path, name: str, csv: Path, T_tag_slam: np.ndarray) -> ImageSequence:
    """The frames (video, else old-layout images/) and the trajectory of one sequence folder."""
    from umi_aug.data.video import probe_video  # lazy, start-up: zarr

    video = folder / VIDEO_NAME
    if video.exists():
        try:
            info = probe_video(video)
        except UmiAugError as exc:
            raise ReconError(str(exc)) from exc
        seq = ImageSequence(name, video, info.n_frames, (info.width, info.height), None,
                            np.zeros(info.n_frames, bool), np.arange(info.n_frames) / info.fps, fps=info.fps,
                            _info=info)
    elif (folder / "images").is_dir():
        files = _image_files(folder / "images")
        first = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise ReconError(f"{files[0]}: unreadable image")
        seq = ImageSequence(name, folder / "images", len(files), (first.shape[1], first.shape[0]), None,
                            np.zeros(len(files), bool), np.arange(len(files), dtype=np.float64), image_paths=files)
    else:
        raise ReconError(f"{folder}: no {VIDEO_NAME} (UMI session layout: demos/<demo>/{VIDEO_NAME} + "
                         f"camera_trajectory.csv); re-create a synthetic session with `umi-aug make-session`")
    _trajectory(seq, csv, T_tag_slam)
    tags = folder / TAG_DETECTIONS_NAME
    if tags.is_file():
        from umi_aug.data.video import read_tag_detections  # lazy, start-up: zarr

        try:
            seq.tag_corners = read_tag_detections(tags)
        except UmiAugError as exc:
            raise ReconError(str(exc)) from exc
        log.info("%s: ArUco tags of %d frames are inpainted when decoded", tags, len(seq.tag_corners))
    return seq


def _trajectory(seq: ImageSequence, csv: Path, T_tag_slam: np.ndarray) -> None:
    """Fill ``seq``'s poses from ``csv`` (rows aligned to video frames by ``frame_idx``; lost rows invalid)."""
    from umi_aug.data import read_camera_trajectory_csv  # lazy, start-up: zarr

    if not csv.is_file():
        return
    try:
        traj = read_camera_trajectory_csv(csv)
    except UmiAugError as exc:
        raise ReconError(f"{csv}: {exc}") from exc
    n = seq.n_frames
    what = f"{seq.source}" if seq.image_paths is None else f"{seq.source} ({n} images)"
    if len(traj) != n:
        raise ReconError(f"{csv}: {len(traj)} rows but {what} has {n} frames; one row per video frame is required "
                         f"(this CSV belongs to another video, or the video was cut: re-run UMI's SLAM)")
    bad = np.flatnonzero(traj.frame_idx != np.arange(n))
    if len(bad):
        r = int(bad[0])
        raise ReconError(f"{csv}: row {r + 1} (line {r + 2}) has frame_idx {int(traj.frame_idx[r])}, expected {r}: "
                         f"rows must be the video's frames 0..{n - 1} in order")
    if np.isfinite(seq.fps) and n > 1:
        expect = traj.frame_idx / seq.fps
        off = np.abs(traj.timestamp - traj.timestamp[0] - (expect - expect[0]))
        tol = TIMESTAMP_RTOL * max(float(expect[-1] - expect[0]), 1.0 / seq.fps) + 0.5 / seq.fps
        if off.max() > tol:
            r = int(np.argmax(off))
            raise ReconError(f"{csv}: line {r + 2}: timestamp {traj.timestamp[r]!r} s does not match frame "
                             f"{int(traj.frame_idx[r])} of {seq.source} at {seq.fps:.3f} fps ({expect[r]:.4f} s)")
    seq.T_world_cam = np.einsum("ij,njk->nik", T_tag_slam, traj.T_world_cam)
    seq.valid = traj.valid.copy()
    seq.timestamp = np.asarray(traj.timestamp, dtype=np.float64)
    if (~seq.valid).any():
        log.info("%s: %d of %d frames lost by SLAM (skipped)", csv, int((~seq.valid).sum()), n)


#: Largest ``|robot0_eef_pos − TCP position|`` (metres) on any frame of a matched episode ↔ video segment; the TCP
#: comes from ``camera_trajectory.csv`` (pose in the tag frame via ``tx_slam_tag.json``, UMI's camera→TCP offset).
SEGMENT_POS_TOL_M = 2e-3
#: Largest rotation angle (radians) between ``robot0_eef_rot_axis_angle`` and the CSV pose's rotation of a match.
SEGMENT_ROT_TOL_RAD = 0.01
#: UMI's plan of the dataset episodes (06_generate_dataset_plan.py), read for ``cameras[0].video_start_end``.
PLAN_NAME = "dataset_plan.pkl"


@dataclass
class _Episodes:
    """What the segment matching reads from ``dataset.zarr.zip`` (all steps concatenated)."""

    path: Path
    lengths: np.ndarray  # [E] steps
    width: np.ndarray  # [N] metres
    pos: np.ndarray | None  # [N, 3] TCP positions, metres (None: key absent)
    rotvec: np.ndarray | None  # [N, 3]

    def starts(self) -> np.ndarray:
        return np.concatenate([[0], np.cumsum(self.lengths)[:-1]]).astype(np.int64)


def _read_episodes(zp: Path) -> _Episodes | None:
    """The dataset's episode lengths, widths and TCP poses; None when it cannot be read (the augment preflight
    reports the dataset's own problems)."""
    from umi_aug.data import ReplayBuffer  # lazy, start-up: zarr

    try:
        with ReplayBuffer.open(zp) as buf:
            if "robot0_gripper_width" not in buf:
                return None
            lengths = np.asarray(buf.episode_lengths, dtype=np.int64)
            w = np.asarray(buf["robot0_gripper_width"][:], dtype=np.float64)
            width = w.reshape(len(w), -1)[:, 0]
            pos = np.asarray(buf["robot0_eef_pos"][:], np.float64) if "robot0_eef_pos" in buf else None
            rot = (np.asarray(buf["robot0_eef_rot_axis_angle"][:], np.float64)
                   if "robot0_eef_rot_axis_angle" in buf else None)
    except UmiAugError:
        return None
    return _Episodes(zp, lengths, width, pos, rot)


def _segment_error(ep: _Episodes, e: int, T_world_tcp: np.ndarray) -> tuple[float, float]:
    """(max position error m, max rotation error rad) of episode ``e`` against TCP poses ``[L, 4, 4]``."""
    from scipy.spatial.transform import Rotation  # lazy, start-up: scipy

    a = int(ep.starts()[e])
    sl = slice(a, a + int(ep.lengths[e]))
    dp = float(np.linalg.norm(ep.pos[sl] - T_world_tcp[:, :3, 3], axis=1).max()) if ep.pos is not None else 0.0
    dr = 0.0
    if ep.rotvec is not None:
        rel = Rotation.from_rotvec(ep.rotvec[sl]).inv() * Rotation.from_matrix(T_world_tcp[:, :3, :3])
        dr = float(np.max(rel.magnitude()))
    return dp, dr


def _tcp_poses(demos: list[ImageSequence]) -> dict[int, np.ndarray]:
    T_cam_tcp = umi_T_cam_tcp()
    return {i: d.T_world_cam @ T_cam_tcp for i, d in enumerate(demos) if d.T_world_cam is not None}


def _segments_from_plan(root: Path, ep: _Episodes, demos: list[ImageSequence]) -> list[tuple[int, int]]:
    """``(demo, start frame)`` per episode from UMI's ``dataset_plan.pkl`` (``cameras[0].video_start_end``),
    checked against the videos, the tracking and (when the dataset has them) the TCP poses."""
    p = root / PLAN_NAME
    try:
        with open(p, "rb") as f:
            plan = pickle.load(f)  # the user's own pipeline output (UMI writes it with pickle)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is the same bad-input error
        raise ReconError(f"{p}: unreadable ({type(exc).__name__}: {exc}); re-run UMI's 06_generate_dataset_plan "
                         f"or remove it (episodes are then matched by their TCP poses)") from exc
    if not isinstance(plan, list) or len(plan) != len(ep.lengths):
        n = len(plan) if isinstance(plan, list) else type(plan).__name__
        raise ReconError(f"{p}: {n} planned episodes but {ep.path} has {len(ep.lengths)}; the plan belongs to "
                         f"another dataset (07_generate_replay_buffer writes one episode per plan entry)")
    by_name = {d.name: i for i, d in enumerate(demos)}
    tcp = _tcp_poses(demos)
    out = []
    for e, item in enumerate(plan):
        try:
            cam = item["cameras"][0]
            video = Path(str(cam["video_path"]))
            s, t = (int(v) for v in cam["video_start_end"])
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            raise ReconError(f"{p}: episode {e}: no readable cameras[0].video_path / video_start_end "
                             f"({exc!r})") from exc
        di = by_name.get(video.parent.name)
        where = f"{p}: episode {e} (cameras[0] = {video}, video_start_end = ({s}, {t}))"
        if di is None:
            raise ReconError(f"{where}: no demo folder {video.parent.name} with {VIDEO_NAME} and "
                             f"camera_trajectory.csv under {root / 'demos'}")
        d = demos[di]
        if t - s != int(ep.lengths[e]) or not 0 <= s < t <= d.n_frames:
            raise ReconError(f"{where}: {t - s} frames, but the dataset's episode {e} has {int(ep.lengths[e])} steps "
                             f"and {d.source} {d.n_frames} frames")
        if not d.valid[s:t].all():
            k = s + int(np.flatnonzero(~d.valid[s:t])[0])
            raise ReconError(f"{where}: frame {k} is lost in {root / 'demos' / d.name / 'camera_trajectory.csv'}; "
                             f"UMI's episodes are tracked segments: the plan belongs to another SLAM run")
        dp, dr = _segment_error(ep, e, tcp[di][s:t])
        if dp > SEGMENT_POS_TOL_M or dr > SEGMENT_ROT_TOL_RAD:
            raise ReconError(f"{where}: the dataset's robot0_eef_pos/rot differ from the TCP of "
                             f"camera_trajectory.csv by up to {dp:.4f} m / {dr:.4f} rad (tolerance "
                             f"{SEGMENT_POS_TOL_M} m / {SEGMENT_ROT_TOL_RAD} rad); plan, dataset and session disagree")
        out.append((di, s))
    return out


def _segments_by_tcp(ep: _Episodes, demos: list[ImageSequence]) -> list[tuple[int, int]]:
    """``(demo, start frame)`` per episode: the tracked segment of a demo video whose TCP positions (camera pose
    ∘ UMI's camera→TCP offset, tag frame) match the episode's ``robot0_eef_pos`` on every frame within
    :data:`SEGMENT_POS_TOL_M` (and its rotations within :data:`SEGMENT_ROT_TOL_RAD`). Episodes are searched in the
    demo of the previous episode first (UMI writes them in demo order), then in the other demos."""
    if ep.pos is None:
        raise ReconError(f"{ep.path}: {len(ep.lengths)} episodes of {ep.lengths.tolist()[:8]} steps do not map "
                         f"one-to-one onto the {len(demos)} demo videos ({[d.n_frames for d in demos][:8]} frames) and "
                         f"there is no key 'data/robot0_eef_pos' to match them by; add UMI's {PLAN_NAME}")
    tcp = _tcp_poses(demos)
    starts = ep.starts()
    out: list[tuple[int, int]] = []
    prev = 0
    for e, L in enumerate(ep.lengths.tolist()):
        P = ep.pos[starts[e]: starts[e] + L]
        order = [prev] + [i for i in range(len(demos)) if i != prev]
        found, nearest = None, (np.inf, "", -1)
        for di in order:
            if di not in tcp or demos[di].n_frames < L:
                continue
            d, Q = demos[di], tcp[di][:, :3, 3]
            dist0 = np.linalg.norm(Q[: d.n_frames - L + 1] - P[0], axis=1)
            dist0[~d.valid[: d.n_frames - L + 1]] = np.inf
            if dist0.min() < nearest[0]:
                nearest = (float(dist0.min()), d.name, int(np.argmin(dist0)))
            best = None
            for s in np.flatnonzero(dist0 <= SEGMENT_POS_TOL_M).tolist():
                if not d.valid[s:s + L].all():
                    continue
                dp, dr = _segment_error(ep, e, tcp[di][s:s + L])
                if dp <= SEGMENT_POS_TOL_M and dr <= SEGMENT_ROT_TOL_RAD and (best is None or dp < best[0]):
                    best = (dp, s)
            if best is not None:
                found = (di, best[1])
                break
        if found is None:
            near = (f"; nearest tracked start: {nearest[1]} frame {nearest[2]} at {nearest[0]:.4f} m"
                    if np.isfinite(nearest[0]) else "")
            raise ReconError(f"{ep.path}: episode {e} ({L} steps) matches no tracked segment of the demo videos "
                             f"({', '.join(d.name for d in demos) or 'none'}): robot0_eef_pos must equal the TCP of "
                             f"camera_trajectory.csv (tag frame via tx_slam_tag.json, UMI's camera→TCP offset, "
                             f"tcp_offset {_tcp_offset():.3f} m) within {SEGMENT_POS_TOL_M} m on every frame{near}; "
                             f"add UMI's {PLAN_NAME} to the session, or use the dataset made from this session")
        out.append(found)
        prev = found[0]
    return out


def _tcp_offset() -> float:
    return float(UMI_TCP_OFFSET)


def _assign_episodes(root: Path, demos: list[ImageSequence]) -> list[ImageSequence]:
    """The demo sequences in the order of ``dataset.zarr.zip``'s episodes, each with its gripper widths.

    One episode per whole video (episode lengths = video frames) and no ``dataset_plan.pkl``: the demos as they are
    (a plan, when present, is always read and checked: a garbage one is refused, never ignored). Otherwise the episodes
    are UMI's valid SLAM segments (06_generate_dataset_plan: tracked runs of a video, lost frames dropped): each
    episode's segment comes from ``dataset_plan.pkl`` when present, else from its TCP poses
    (:func:`_segments_by_tcp`), and the demo is cropped to it (:meth:`ImageSequence.cropped`; named
    ``<demo>_<first frame>`` when a video holds several episodes). No dataset (or one without widths): unchanged.
    """
    zp = root / "dataset.zarr.zip"
    ep = _read_episodes(zp) if zp.exists() else None
    if ep is None:
        return demos
    starts = ep.starts()
    has_plan = (root / PLAN_NAME).is_file()  # read (and checked) whenever present: a garbage plan is refused
    if not has_plan and len(ep.lengths) == len(demos) and all(int(L) == d.n_frames
                                                              for L, d in zip(ep.lengths, demos)):
        for e, d in enumerate(demos):
            d.gripper_width = ep.width[starts[e]: starts[e] + d.n_frames].copy()
        return demos
    segs = _segments_from_plan(root, ep, demos) if has_plan else _segments_by_tcp(ep, demos)
    per_demo = np.bincount([di for di, _ in segs], minlength=len(demos))
    out = []
    for e, (di, s) in enumerate(segs):
        d, L = demos[di], int(ep.lengths[e])
        seq = d.cropped(s, s + L, d.name if per_demo[di] == 1 else f"{d.name}_{s:06d}")
        seq.gripper_width = ep.width[starts[e]: starts[e] + L].copy()
        out.append(seq)
    used = [d.name for i, d in enumerate(demos) if per_demo[i] == 0]
    log.info("%s: %d episodes matched to segments of %d demo videos%s", zp, len(out), len(demos) - len(used),
             f" ({len(used)} videos without an episode: {', '.join(used[:5])})" if used else "")
    return out


def check_image_sizes(paths: list[Path], intr: FisheyeIntrinsics, every: int = 1) -> None:
    """Raise :class:`ReconError` if any (every ``every``-th) image file's size differs from the intrinsics' size."""
    for p in paths[::max(1, every)]:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ReconError(f"{p}: unreadable image")
        if img.shape[:2] != (intr.height, intr.width):
            raise ReconError(f"{p}: frame is {img.shape[1]}x{img.shape[0]} but the intrinsics are "
                             f"{intr.width}x{intr.height}; pass intrinsics for the frames' size "
                             f"(e.g. FisheyeIntrinsics.scaled({img.shape[1]}, {img.shape[0]})), never resize frames")


def write_frames(seq: ImageSequence, indices: Sequence[int] | np.ndarray, folder: str | os.PathLike,
                 size: tuple[int, int] | None = None) -> list[Path]:
    """Decode frames ``indices`` of ``seq`` (at ``size``, see :meth:`ImageSequence.iter_frames`) into
    ``folder/<seq.name>/NNNNNN.png`` (lossless, for COLMAP) and return the paths in order."""
    out = Path(folder) / seq.name
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, img in seq.iter_frames(indices, size):
        p = out / f"{seq.frame_name(k)}.png"
        if not cv2.imwrite(str(p), img[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise ReconError(f"could not write {p}")
        paths.append(p)
    return paths


def _find_intrinsics(root: Path, w: int, h: int) -> FisheyeIntrinsics:
    """``calibration/gopro_intrinsics_<w>x<h>.json``, else the first calibration JSON (``calibration/*.json``,
    ``*intrinsics*.json`` at the root; e.g. UMI's ``gopro_intrinsics_2_7k.json``) of the frames' size or of their
    aspect ratio (scaled UMI's way, :meth:`FisheyeIntrinsics.scaled`)."""
    exact = root / "calibration" / f"gopro_intrinsics_{w}x{h}.json"
    cands = [exact] if exact.is_file() else []
    cands += sorted((root / "calibration").glob("*.json")) if (root / "calibration").is_dir() else []
    cands += sorted(root.glob("*intrinsics*.json"))
    tried = []
    for p in cands:
        try:
            intr = load_umi_intrinsics_json(p)
        except UmiAugError as exc:
            if p == exact:
                raise ReconError(f"{p}: {exc}") from exc
            continue
        tried.append(f"{p.name} ({intr.width}x{intr.height})")
        if (intr.width, intr.height) == (w, h):
            return intr
        if abs(intr.width * h - intr.height * w) <= max(intr.width, w) // 200:
            log.info("%s: %dx%d calibration scaled to the %dx%d frames", p, intr.width, intr.height, w, h)
            return intr.scaled(w, h)
    raise ReconError(f"{root}: no fisheye calibration for the {w}x{h} frames (looked for calibration/"
                     f"gopro_intrinsics_{w}x{h}.json, calibration/*.json, *intrinsics*.json; found "
                     f"{', '.join(tried) or 'none'}); pass `intrinsics` (e.g. load_umi_intrinsics_json(<2.7k "
                     f"json>).scaled({w}, {h}))")


def load_session(root: str | os.PathLike, intrinsics: FisheyeIntrinsics | str | os.PathLike | None = None,
                 check_every: int = 10) -> SessionData:
    """Load a session folder (nothing is decoded; frames come from :meth:`ImageSequence.read_frames`).

    Args:
        root: the session folder.
        intrinsics: intrinsics object or calibration JSON at the frames' size; default: found in the session
            (:func:`_find_intrinsics`).
        check_every: old ``images/`` layout only: check the size of every this-many-th frame (1 = all).
    Raises:
        ReconError: missing folders/files, an unreadable video, a CSV whose rows / frame indices / timestamps
            disagree with its video, sequences of different frame sizes, intrinsics of another size than the frames,
            dataset episodes that match no tracked video segment (naming the episode and the tolerance).
    """
    root = Path(root)
    if not (root / "demos").is_dir():
        raise ReconError(f"{root}: not a UMI session folder (no demos/); expected demos/mapping and demos/<demo>")
    T_tag_slam = np.linalg.inv(_tx_slam_tag(root))
    mdir = root / "demos" / "mapping"
    if not mdir.is_dir():
        raise ReconError(f"{root}/demos: no mapping/ folder (the scan: {VIDEO_NAME} + mapping_camera_trajectory.csv)")
    mapping = _sequence(mdir, "mapping", mdir / "mapping_camera_trajectory.csv", T_tag_slam)
    demos, missing = [], []
    for d in sorted(p for p in (root / "demos").iterdir() if p.is_dir() and p.name.startswith("demo")):
        if not (d / VIDEO_NAME).exists() and not (d / "images").is_dir():
            log.warning("%s: no %s; demo skipped", d, VIDEO_NAME)
            missing.append(d / VIDEO_NAME)
            continue
        demos.append(_sequence(d, d.name, d / "camera_trajectory.csv", T_tag_slam))
        if demos[-1].T_world_cam is None:
            missing.append(d / "camera_trajectory.csv")
    try:
        demos = _assign_episodes(root, demos)
    except ReconError as exc:
        if not missing:
            raise
        # the matching fails because a demo's video (or CSV) is gone: that file is the cause, not the poses
        more = f" (and {len(missing) - 1} more: {', '.join(str(m) for m in missing[1:4])})" if len(missing) > 1 else ""
        raise ReconError(f"{missing[0]}: missing{more}; without it the episodes of {root / 'dataset.zarr.zip'} "
                         f"cannot all be matched to the demo videos (each episode is a segment of one demo's "
                         f"{VIDEO_NAME} with its camera_trajectory.csv): restore the missing file(s), or remove that "
                         f"demo folder and re-create dataset.zarr.zip with UMI") from exc
    w, h = mapping.frame_size
    for s in demos:
        if s.frame_size != (w, h):
            raise ReconError(f"{s.source}: frames are {s.frame_size[0]}x{s.frame_size[1]} but the mapping video's are "
                             f"{w}x{h}; one camera setting per session is required")
    if intrinsics is None:
        intrinsics = _find_intrinsics(root, w, h)
    if not isinstance(intrinsics, FisheyeIntrinsics):
        try:
            intrinsics = load_umi_intrinsics_json(intrinsics)
        except UmiAugError as exc:
            raise ReconError(f"{intrinsics}: {exc}") from exc
    if (intrinsics.width, intrinsics.height) != (w, h):
        raise ReconError(f"{mapping.source}: frames are {w}x{h} but the intrinsics are {intrinsics.width}x"
                         f"{intrinsics.height}; pass intrinsics for the frames' size (e.g. "
                         f"FisheyeIntrinsics.scaled({w}, {h})), never resize frames")
    for seq in [mapping, *demos]:
        if seq.image_paths is not None:
            check_image_sizes(seq.image_paths, intrinsics, check_every)
    return SessionData(root, intrinsics, mapping, demos)
