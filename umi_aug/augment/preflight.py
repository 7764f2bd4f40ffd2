"""Checks of every input of an ``augment`` run, in one pass, before any stage computes (issue #18).

:func:`check_session_inputs` reads a UMI session's ``dataset.zarr.zip`` (readable zip, layout, NaN/Inf, complete
image-chunk listing) and loads the session through the session reader, which maps every episode onto its demo video
(a whole video, or UMI's tracked segment of one: :func:`umi_aug.recon.session_io.load_session`) and checks the CSVs
(columns, monotonic timestamps, rows per video frame; the mapping CSV) and the intrinsics at the frames' size, then
the camera poses of every episode's frames (no lost row, no jump: :func:`check_demo_trajectories`). Each
problem raises one :class:`~umi_aug.errors.AugmentError` naming the file, key, row and value; suspicious-but-legal
intrinsics (principal point outside the image, large ``|k1|``, focal lengths far from a fisheye's) become warnings.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from umi_aug.errors import AugmentError, UmiAugError

__all__ = ["InputCheck", "check_session_inputs", "intrinsics_warnings", "check_demo_trajectories",
           "demo_trajectory_problem"]

log = logging.getLogger(__name__)

#: Consecutive TCP poses further apart than this (metres per frame) mean a lost-tracking gap (UMI drops the
#: untracked frames, so a gap shows as a jump). 0.05 m/frame = 3 m/s at 60 fps. Shared by the session demos' check
#: here and the plain-dataset check (:mod:`umi_aug.augment.dataset_source`).
MAX_STEP_M: float = 0.05
#: Same, rotation (degrees per frame).
MAX_STEP_DEG: float = 20.0

#: |k1| above this is unusual for a GoPro-like fisheye (UMI's 2.7k calibration: k1 ≈ 0.02).
K1_WARN = 0.5


@dataclass
class InputCheck:
    """What the checks found: episodes in the input dataset, its size (bytes), warnings (also logged)."""

    n_episodes: int
    dataset_bytes: int
    warnings: list[str] = field(default_factory=list)


def intrinsics_warnings(intr, source: str, frame_size: tuple[int, int] | None = None) -> list[str]:
    """Warnings for suspicious-but-legal fisheye intrinsics (``intr``: :class:`FisheyeIntrinsics`, pixels)."""
    out = []
    if not (0 <= intr.cx < intr.width and 0 <= intr.cy < intr.height):
        out.append(f"{source}: principal point (cx, cy) = ({intr.cx:.1f}, {intr.cy:.1f}) px lies outside the "
                   f"{intr.width}x{intr.height} image")
    if abs(intr.k[0]) > K1_WARN:
        out.append(f"{source}: |k1| = {abs(intr.k[0]):.3g} > {K1_WARN} is unusual for a fisheye calibration")
    if not 0.5 < intr.fx / intr.fy < 2.0:
        out.append(f"{source}: fx / fy = {intr.fx / intr.fy:.3g} (fx {intr.fx:.1f}, fy {intr.fy:.1f} px): a wrong "
                   f"focal length?")
    # an equidistant fisheye of 120..220 degrees maps half the width to ~1 rad: fx ~ width / 2 .. width / 4
    if not intr.width / 8 < intr.fx < intr.width:
        out.append(f"{source}: fx = {intr.fx:.1f} px for a {intr.width} px wide fisheye image (expected about "
                   f"{intr.width / 4:.0f}..{intr.width / 2:.0f} px): a wrong focal length or a calibration of "
                   f"another resolution?")
    if frame_size is not None and tuple(frame_size) != (intr.width, intr.height):
        out.append(f"{source}: intrinsics are {intr.width}x{intr.height} but the frames are "
                   f"{frame_size[0]}x{frame_size[1]}")
    return out


def _frame_ranges(frames: np.ndarray, limit: int = 4) -> str:
    """``[3, 4, 5, 9]`` → ``"3..5, 9"`` (the first ``limit`` runs, then "…")."""
    runs, start = [], int(frames[0])
    for a, b in zip(frames[:-1], frames[1:]):
        if int(b) != int(a) + 1:
            runs.append((start, int(a)))
            start = int(b)
    runs.append((start, int(frames[-1])))
    text = ", ".join(f"{a}..{b}" if b > a else f"{a}" for a, b in runs[:limit])
    return text + (f", … ({len(runs)} runs)" if len(runs) > limit else "")


def demo_trajectory_problem(seq, csv: Path) -> str | None:
    """Why the camera poses of an episode's frames cannot be augmented, or None.

    ``seq``: a demo of :func:`umi_aug.recon.session_io.load_session`, already mapped onto its dataset episode (its
    frames are the episode's). UMI's episodes are tracked segments (06_generate_dataset_plan drops lost frames), so
    a lost row inside one — its placeholder pose is the origin — or a jump of the camera between two frames further
    than a hand moves it (:data:`MAX_STEP_M` /
    :data:`MAX_STEP_DEG` per frame, the plain-dataset check's limits) is a SLAM
    fault; planned through, either failed minutes later as a "collision". The message names the CSV, its lines
    and the frames."""

    off = int(seq.frame_offset)
    fix = (f"re-create dataset.zarr.zip with UMI's pipeline (its episodes are the tracked segments: "
           f"06_generate_dataset_plan), or remove demos/{csv.parent.name} and its episode")
    lost = np.flatnonzero(~np.asarray(seq.valid, bool))
    if len(lost):
        return (f"{csv}: {len(lost)} of the {seq.n_frames} rows of the dataset episode's frames are lost by SLAM "
                f"(is_lost=true): frames {_frame_ranges(lost + off)} (CSV lines {int(lost[0]) + off + 2}.."
                f"{int(lost[-1]) + off + 2}); a lost row has no pose (augmenting would plan through the placeholder "
                f"at the origin): {fix}")
    T = np.asarray(seq.T_world_cam, np.float64)
    if len(T) < 2:
        return None
    step = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    R_rel = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])
    ang = np.degrees(np.arccos(np.clip((np.trace(R_rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    jump = np.flatnonzero((step > MAX_STEP_M) | (ang > MAX_STEP_DEG))
    if not len(jump):
        return None
    i = int(jump[0])
    f = off + i + 1
    return (f"{csv}: line {f + 2} (frame {f}): the camera pose jumps {step[i]:.3f} m / {ang[i]:.1f} deg from frame "
            f"{f - 1} (limits {MAX_STEP_M} m, {MAX_STEP_DEG} deg per frame: faster than a hand moves the gripper — "
            f"a SLAM relocalisation error){f' ({len(jump)} such steps)' if len(jump) > 1 else ''}: re-run UMI's "
            f"SLAM for demos/{csv.parent.name}, or remove it and its episode")


def check_demo_trajectories(sess) -> None:
    """Raise :class:`AugmentError` for the first demo of ``sess`` (a loaded session) whose episode frames hold a
    lost row or a pose jump (:func:`demo_trajectory_problem`), and for a mapping CSV without one tracked row."""
    root = Path(sess.root)
    m = sess.mapping
    if m.T_world_cam is not None and not np.asarray(m.valid, bool).any():
        raise AugmentError(f"{root / 'demos' / 'mapping' / 'mapping_camera_trajectory.csv'}: all {m.n_frames} rows "
                           f"are lost by SLAM (is_lost=true): the scan has no camera pose to reconstruct from; re-run "
                           f"UMI's SLAM mapping")
    for d in sess.demos:
        csv = Path(d.source).parent / "camera_trajectory.csv"
        problem = demo_trajectory_problem(d, csv) if d.T_world_cam is not None else None
        if problem:
            raise AugmentError(problem)


def _dataset_check(ds: Path, image_size: int | None) -> tuple[int, int]:
    """Validate the session's dataset: (episodes, bytes)."""
    # lazy, start-up: zarr
    from umi_aug.data import ReplayBuffer
    from umi_aug.data.validate import gripper_width_problem

    try:
        with ReplayBuffer.open(ds) as buf:  # layout, NaN/Inf, complete chunk listing (umi_aug.data.validate)
            if "robot0_gripper_width" not in buf:
                raise AugmentError(f"{ds}: no key 'data/robot0_gripper_width' (the demos' gripper widths); "
                                   f"keys: {buf.keys()}")
            problem = gripper_width_problem(buf["robot0_gripper_width"][:], buf.episode_ends)
            if problem:  # before: 16x "TrajError: gripper_width must be finite, >= 0" minutes later
                raise AugmentError(f"{ds}: key 'data/robot0_gripper_width' {problem}")
            n = buf.n_episodes
            if image_size is not None and "camera0_rgb" in buf:
                shape = tuple(buf["camera0_rgb"].shape[1:3])
                if shape != (image_size, image_size):
                    raise AugmentError(f"{ds}: key 'data/camera0_rgb' has {shape[1]}x{shape[0]} frames but "
                                       f"image_size = {image_size}; export at the dataset's resolution "
                                       f"(--image-size {shape[0]})")
    except AugmentError:
        raise
    except UmiAugError as exc:
        raise AugmentError(str(exc)) from exc
    return n, ds.stat().st_size


def _once(msg: str) -> str:
    """``"a.csv: a.csv: line 5 ..."`` (a reader's message wrapped with its path again) → ``"a.csv: line 5 ..."``."""
    head, sep, rest = msg.partition(": ")
    return rest if sep and rest.startswith(head + ": ") else msg


def check_session_inputs(session_dir: str | os.PathLike, image_size: int | None = None) -> InputCheck:
    """Check a UMI session folder before any stage runs (see the module doc). Returns an :class:`InputCheck`.

    ``image_size``: the run's policy image side (pixels): the dataset's frames must have it (None: not checked).

    Raises:
        AugmentError: the first problem, naming the file/key/row/value.
    """
    from umi_aug.recon.session_io import load_session  # lazy, start-up: cv2

    root = Path(session_dir)
    ds = root / "dataset.zarr.zip"
    if not ds.exists():
        raise AugmentError(f"{root}: no dataset.zarr.zip (the original episodes); run UMI's "
                           "07_generate_replay_buffer first")
    n_eps, nbytes = _dataset_check(ds, image_size)
    try:
        sess = load_session(root)  # CSVs (columns, monotonic timestamps, one row per frame), mapping, intrinsics
    except UmiAugError as exc:
        raise AugmentError(_once(str(exc))) from exc
    csvs = {"mapping": root / "demos" / "mapping" / "mapping_camera_trajectory.csv"}
    csvs.update({d.name: root / "demos" / d.name / "camera_trajectory.csv" for d in sess.demos})
    for seq in [sess.mapping, *sess.demos]:
        if seq.T_world_cam is None:
            raise AugmentError(f"{csvs[seq.name]}: missing (the camera trajectory of {seq.source}, from UMI's SLAM "
                               f"step); every sequence needs its CSV")
    # load_session mapped every episode onto its demo video (whole video, or UMI's tracked segment of it)
    if len(sess.demos) != n_eps or any(d.gripper_width is None for d in sess.demos):
        raise AugmentError(f"{ds}: {n_eps} episodes but the session's demo videos give {len(sess.demos)} "
                           f"({', '.join(d.name for d in sess.demos) or 'none'}); the dataset belongs to another "
                           f"session")
    check_demo_trajectories(sess)
    warnings = intrinsics_warnings(sess.intrinsics, f"{root}: intrinsics", None)
    for w in warnings:
        log.warning("%s", w)
    return InputCheck(n_episodes=n_eps, dataset_bytes=nbytes, warnings=warnings)
