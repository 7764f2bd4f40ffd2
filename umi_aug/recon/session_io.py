"""Reading what reconstruction needs from a UMI session folder, in UMI's real layout (umi_stack.md §1).

``<session>/demos/mapping/raw_video.mp4`` + ``mapping_camera_trajectory.csv`` (the scan),
``demos/<demo>/raw_video.mp4`` + ``camera_trajectory.csv`` (demonstrations), ``demos/mapping/tx_slam_tag.json``
(SLAM map → table tag), the GoPro intrinsics JSON and ``dataset.zarr.zip`` (gripper widths). No frames are extracted:
:meth:`ImageSequence.read_frames` decodes only the requested frame indices, at the size a stage asks for, in one
sequential pass (:mod:`umi_aug.data.video`). Old sessions with ``images/NNNNNN.jpg`` folders and no video are still
read (frames from the files).

CSV rows are aligned with the video by ``frame_idx`` (one row per frame, as ORB-SLAM3 writes them); tracking-lost
rows (``is_lost=true``) are kept as ``valid = False`` (pose = identity) and every stage skips them. ArUco tags are
left in the frames, as UMI's SLAM sees them (its mask covers only the mirrors and fingers); UMI removes tags only
when it makes the 224² dataset images (``inpaint_tag`` in 07_generate_replay_buffer).

Poses are returned in the world = table-tag frame: ``T_world_cam = inv(tx_slam_tag) @ T_slam_cam`` (UMI's 06
script), OpenCV camera axes, metres. Every problem raises :class:`umi_aug.errors.ReconError` naming the file and what
to do.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np

from umi_aug.camera.calib_io import load_umi_intrinsics_json
from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import ReconError, UmiAugError

__all__ = ["ImageSequence", "SessionData", "load_session", "check_image_sizes", "write_frames", "IMAGE_EXTENSIONS",
           "VIDEO_NAME"]

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png")
#: UMI's per-sequence video file (00_process_videos).
VIDEO_NAME = "raw_video.mp4"
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
    _info: object | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        return (f"ImageSequence({self.name!r}, {self.source}, {self.n_frames} frames "
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
        from umi_aug.data.video import centre_crop, iter_video_frames

        idx = self._indices(indices)
        if self.image_paths is None:
            try:
                yield from iter_video_frames(self.source, idx, size, info=self._info)
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
            yield k, img

    def read_frames(self, indices: Sequence[int] | np.ndarray, size: tuple[int, int] | None = None,
                    progress: bool = False) -> np.ndarray:
        """:meth:`iter_frames` stacked: ``[K, h, w, 3]`` uint8 RGB."""
        idx = self._indices(indices)
        w, h = self.frame_size if size is None else (int(size[0]), int(size[1]))
        out = np.empty((len(idx), h, w, 3), dtype=np.uint8)
        it = self.iter_frames(idx, size)
        if progress:
            from tqdm import tqdm

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
    from umi_aug.data.video import probe_video

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
    return seq


def _trajectory(seq: ImageSequence, csv: Path, T_tag_slam: np.ndarray) -> None:
    """Fill ``seq``'s poses from ``csv`` (rows aligned to video frames by ``frame_idx``; lost rows invalid)."""
    from umi_aug.data import read_camera_trajectory_csv

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


def _widths(root: Path, demos: list[ImageSequence]) -> None:
    zp = root / "dataset.zarr.zip"
    if not zp.exists():
        return
    from umi_aug.data import ReplayBuffer

    try:
        with ReplayBuffer.open(zp) as buf:
            if buf.n_episodes != len(demos) or "robot0_gripper_width" not in buf:
                return
            for i, d in enumerate(demos):
                w = np.asarray(buf.get_episode(i, ["robot0_gripper_width"])["robot0_gripper_width"],
                               dtype=np.float64).reshape(-1)
                if len(w) == len(d):
                    d.gripper_width = w
    except UmiAugError:
        return


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
            disagree with its video, sequences of different frame sizes, intrinsics of another size than the frames.
    """
    root = Path(root)
    if not (root / "demos").is_dir():
        raise ReconError(f"{root}: not a UMI session folder (no demos/); expected demos/mapping and demos/<demo>")
    T_tag_slam = np.linalg.inv(_tx_slam_tag(root))
    mdir = root / "demos" / "mapping"
    if not mdir.is_dir():
        raise ReconError(f"{root}/demos: no mapping/ folder (the scan: {VIDEO_NAME} + mapping_camera_trajectory.csv)")
    mapping = _sequence(mdir, "mapping", mdir / "mapping_camera_trajectory.csv", T_tag_slam)
    demos = []
    for d in sorted(p for p in (root / "demos").iterdir() if p.is_dir() and p.name.startswith("demo")):
        if not (d / VIDEO_NAME).exists() and not (d / "images").is_dir():
            log.warning("%s: no %s; demo skipped", d, VIDEO_NAME)
            continue
        demos.append(_sequence(d, d.name, d / "camera_trajectory.csv", T_tag_slam))
    _widths(root, demos)
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
