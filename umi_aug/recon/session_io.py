"""Reading what reconstruction needs from a UMI session folder (umi_stack.md §1 layout).

``<session>/demos/mapping/images/*.jpg`` + ``mapping_camera_trajectory.csv`` (the scan), ``demos/<demo>/images`` +
``camera_trajectory.csv`` (demonstrations), ``demos/mapping/tx_slam_tag.json`` (SLAM map → table tag),
``calibration/gopro_intrinsics_<W>x<H>.json`` and ``dataset.zarr.zip`` (gripper widths). Poses are returned in the
world = table-tag frame: ``T_world_cam = inv(tx_slam_tag) @ T_slam_cam`` (UMI's 06 script), OpenCV camera axes,
metres. Every problem raises :class:`umi_aug.errors.ReconError` naming the file and what to do.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from umi_aug.camera.calib_io import load_umi_intrinsics_json
from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import ReconError, UmiAugError

__all__ = ["ImageSequence", "SessionData", "load_session", "check_image_sizes", "IMAGE_EXTENSIONS"]

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png")


@dataclass
class ImageSequence:
    """One video as frames on disk with its (SLAM) camera poses.

    Attributes:
        name: sequence name (``mapping`` or the demo folder name).
        image_paths: list of N paths, frame order.
        T_world_cam: np.ndarray | None,  # [N, 4, 4] table-tag frame, metres (None: no poses)
        valid: np.ndarray,  # [N] bool, pose tracked (not lost)
        timestamp: np.ndarray,  # [N] seconds
        gripper_width: np.ndarray | None,  # [N] metres (demos, from the replay buffer), None if unknown
    """

    name: str
    image_paths: list[Path]
    T_world_cam: np.ndarray | None
    valid: np.ndarray
    timestamp: np.ndarray
    gripper_width: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.image_paths)


@dataclass
class SessionData:
    """A session's scan, demos and intrinsics.

    Attributes:
        root: session folder.
        intrinsics: fisheye intrinsics at the frames' size.
        mapping: the scan sequence.
        demos: demo sequences, sorted by name (same order as the replay buffer's episodes).
    """

    root: Path
    intrinsics: FisheyeIntrinsics
    mapping: ImageSequence
    demos: list[ImageSequence]


def _images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise ReconError(f"{folder}: no image folder; extract the video's frames to {folder}/NNNNNN.jpg first")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise ReconError(f"{folder}: contains no {'/'.join(IMAGE_EXTENSIONS)} frames")
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


def _trajectory(csv: Path, n_images: int, T_tag_slam: np.ndarray, name: str) -> tuple[np.ndarray | None,
                                                                                     np.ndarray, np.ndarray]:
    from umi_aug.data import read_camera_trajectory_csv

    if not csv.is_file():
        return None, np.zeros(n_images, dtype=bool), np.arange(n_images, dtype=np.float64)
    try:
        traj = read_camera_trajectory_csv(csv)
    except UmiAugError as exc:
        raise ReconError(f"{csv}: {exc}") from exc
    if len(traj) != n_images:
        raise ReconError(f"{csv}: {len(traj)} rows but {n_images} frames in {name}/images; one row per frame "
                         f"is required (re-extract the frames or re-run SLAM)")
    T = np.einsum("ij,njk->nik", T_tag_slam, traj.T_world_cam)
    return T, traj.valid.copy(), np.asarray(traj.timestamp, dtype=np.float64)


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
    """Raise :class:`ReconError` if any (every ``every``-th) frame's size differs from the intrinsics' size."""
    for p in paths[::max(1, every)]:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ReconError(f"{p}: unreadable image")
        if img.shape[:2] != (intr.height, intr.width):
            raise ReconError(f"{p}: frame is {img.shape[1]}x{img.shape[0]} but the intrinsics are "
                             f"{intr.width}x{intr.height}; pass intrinsics for the frames' size "
                             f"(e.g. FisheyeIntrinsics.scaled({img.shape[1]}, {img.shape[0]})), never resize frames")


def load_session(root: str | os.PathLike, intrinsics: FisheyeIntrinsics | str | os.PathLike | None = None,
                 check_every: int = 10) -> SessionData:
    """Load a session folder.

    Args:
        root: the session folder.
        intrinsics: intrinsics object or calibration JSON; default ``calibration/gopro_intrinsics_<W>x<H>.json``
            for the frames' size ``W x H``.
        check_every: check the size of every this-many-th frame against the intrinsics (1 = all).
    Raises:
        ReconError: missing folders/files, CSV/frames mismatch, intrinsics of another size than the frames.
    """
    root = Path(root)
    if not (root / "demos").is_dir():
        raise ReconError(f"{root}: not a UMI session folder (no demos/); expected demos/mapping and demos/<demo>")
    T_tag_slam = np.linalg.inv(_tx_slam_tag(root))
    mdir = root / "demos" / "mapping"
    m_imgs = _images(mdir / "images")
    T, valid, ts = _trajectory(mdir / "mapping_camera_trajectory.csv", len(m_imgs), T_tag_slam, "mapping")
    mapping = ImageSequence("mapping", m_imgs, T, valid, ts)
    demos = []
    for d in sorted(p for p in (root / "demos").iterdir() if p.is_dir() and p.name.startswith("demo")):
        if not (d / "images").is_dir():
            continue
        imgs = _images(d / "images")
        T, valid, ts = _trajectory(d / "camera_trajectory.csv", len(imgs), T_tag_slam, d.name)
        demos.append(ImageSequence(d.name, imgs, T, valid, ts))
    _widths(root, demos)

    first = cv2.imread(str(m_imgs[0]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise ReconError(f"{m_imgs[0]}: unreadable image")
    h, w = first.shape[:2]
    if intrinsics is None:
        p = root / "calibration" / f"gopro_intrinsics_{w}x{h}.json"
        if not p.is_file():
            raise ReconError(f"{root}/calibration: no gopro_intrinsics_{w}x{h}.json for the {w}x{h} frames; pass "
                             f"`intrinsics` (e.g. load_umi_intrinsics_json(<2.7k json>).scaled({w}, {h}))")
        intrinsics = p
    if not isinstance(intrinsics, FisheyeIntrinsics):
        try:
            intrinsics = load_umi_intrinsics_json(intrinsics)
        except UmiAugError as exc:
            raise ReconError(f"{intrinsics}: {exc}") from exc
    for seq in [mapping, *demos]:
        check_image_sizes(seq.image_paths, intrinsics, check_every)
    return SessionData(root, intrinsics, mapping, demos)
