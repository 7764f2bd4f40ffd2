"""Session → scene cloud, scene SDF and per-demo contact frames (the reconstruction stage end to end).

``reconstruct_session(session, out_dir)``:
1. frames: the scan (every ``scan_stride``-th) and each demo's frames before the gripper first closes (every
   ``demo_stride``-th; the objects have not moved yet), decoded from the session's videos at most ``frame_width``
   wide (UMI's SLAM runs at 960x720) into ``frames/`` (removed after SfM, with ``colmap/images``);
2. SfM (:mod:`umi_aug.recon.sfm`, ``full`` or ``known_poses`` with the session's SLAM poses), then the Sim(3)
   alignment into the table-tag frame (:mod:`umi_aug.recon.align`);
3. point filtering (track length, reprojection error) and clean-up (:mod:`umi_aug.recon.cloud`) →
   ``scene_cloud.ply``;
4. the SDF over the region the demos' augmented trajectories can reach (:mod:`umi_aug.recon.sdf_grid`) →
   ``scene_sdf.npz``;
5. contact detection per demo (:mod:`umi_aug.recon.contact`) → ``recon_report.json`` (all numbers).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from umi_aug.errors import ReconError
from umi_aug.io_utils import atomic_write_text
from umi_aug.recon import constants as C
from umi_aug.recon.align import Sim3, align_sfm_to_poses
from umi_aug.recon.cloud import SceneCloud, clean_cloud, inside_camera_body, write_ply
from umi_aug.recon.contact import ContactResult, detect_contact
from umi_aug.recon.session_io import SessionData, load_session, write_frames
from umi_aug.recon.sdf_grid import VoxelSDF, build_scene_sdf, reachable_region
from umi_aug.recon.sfm import SfmConfig, SfmResult, feature_mask, run_sfm

__all__ = ["ReconConfig", "ReconOutput", "reconstruct_session", "first_close_index"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReconConfig:
    """Settings of :func:`reconstruct_session`.

    Attributes:
        sfm: SfM settings (mode ``full`` or ``known_poses``).
        scan_stride / demo_stride: use every n-th scan / pre-contact demo frame.
        frame_width: decode frames at most this wide for SfM (None = the videos' size; intrinsics scaled to match).
        include_demo_frames: add the demos' pre-closing frames to SfM.
        cone_half_angle_deg / cone_radius_m: the trajectory stage's start-pose cone (θ, r; None = the demo's
            start-to-contact distance) bounding the SDF region.
        voxel_m: SDF voxel (None = chosen from the region and ``max_voxels``); inflation_m: SDF margin.
        contact_threshold_m / contact_rule / contact_overrides: contact detection (overrides: demo name → frame).
        carve: visibility carving in the SDF sign rule.
    """

    sfm: SfmConfig = field(default_factory=SfmConfig)
    scan_stride: int = 2
    demo_stride: int = 4
    frame_width: int | None = 960
    include_demo_frames: bool = True
    cone_half_angle_deg: float = 45.0
    cone_radius_m: float | None = None
    voxel_m: float | None = None
    max_voxels: int = C.SDF_MAX_VOXELS
    inflation_m: float = 0.0
    carve: bool = True
    contact_threshold_m: float = C.CONTACT_THRESHOLD_M
    contact_rule: str = "proximity+grasp"
    contact_overrides: dict[str, int] = field(default_factory=dict)


@dataclass
class ReconOutput:
    """Everything :func:`reconstruct_session` produced (arrays in the world = table-tag frame, metres)."""

    session: SessionData
    sfm: SfmResult
    sim3: Sim3
    cloud: SceneCloud
    sdf: VoxelSDF
    contacts: list[ContactResult]
    frame_seq: list[tuple[str, int]]  #: (sequence name, frame index) of every SfM image
    timings_s: dict[str, float]
    report: dict
    paths: dict[str, str]


def first_close_index(width: np.ndarray | None, drop: float = C.GRASP_CLOSE_DROP_M) -> int | None:
    """First frame where the gripper width falls more than ``drop`` below its running maximum (None: never)."""
    if width is None:
        return None
    w = np.asarray(width, np.float64)
    hit = np.flatnonzero(w < np.maximum.accumulate(w) - drop)
    return int(hit[0]) if len(hit) else None


def _free_space_poses(sess: SessionData, T_frames: np.ndarray) -> np.ndarray:
    """Camera poses ``[K, 4, 4]`` where the camera moved through free space: the tracked frames given to SfM and
    every demo's frames before its gripper first closes (:func:`umi_aug.recon.cloud.inside_camera_body`)."""
    poses = [np.asarray(T_frames, np.float64).reshape(-1, 4, 4)]
    for d in sess.demos:
        if d.T_world_cam is not None:
            c = first_close_index(d.gripper_width)
            poses.append(d.T_world_cam[: len(d.T_world_cam) if c is None else c])
    return np.concatenate(poses)


def _frames(sess: SessionData, cfg: ReconConfig, frames_dir: Path, size: tuple[int, int] | None):
    paths, names, T, valid, lengths, seq = [], [], [], [], [], []
    shutil.rmtree(frames_dir, ignore_errors=True)
    jobs = [(sess.mapping, np.arange(0, len(sess.mapping), max(1, cfg.scan_stride)))]
    if cfg.include_demo_frames:
        for d in sess.demos:
            end = first_close_index(d.gripper_width)
            end = len(d) if end is None else end
            jobs.append((d, np.arange(0, end, max(1, cfg.demo_stride))))
    for s, idx in jobs:
        if len(idx) == 0:
            continue
        lengths.append(len(idx))
        paths.extend(write_frames(s, idx, frames_dir, size))
        for i in idx:
            names.append(f"{s.name}/{s.frame_name(i)}.png")
            seq.append((s.name, int(i)))
            T.append(s.T_world_cam[i] if s.T_world_cam is not None else np.eye(4))
            valid.append(bool(s.valid[i]) if s.T_world_cam is not None else False)
    return paths, names, np.array(T), np.array(valid), lengths, seq


def reconstruct_session(session: str | os.PathLike | SessionData, out_dir: str | os.PathLike,
                        config: ReconConfig | None = None, gripper_mask: np.ndarray | None = None) -> ReconOutput:
    """Run the whole stage on a session folder; write ``scene_cloud.ply``, ``scene_sdf.npz``,
    ``recon_report.json`` (and COLMAP's scratch under ``colmap/``) into ``out_dir``.

    Args:
        session: session folder or loaded :class:`SessionData`.
        out_dir: output folder.
        config: :class:`ReconConfig`.
        gripper_mask: ``[H, W]`` bool gripper mask for feature extraction at the videos' size (default UMI's
            predefined mask).
    Raises:
        ReconError: with the failing step and what to do.
    """
    cfg = config or ReconConfig()
    t0 = time.perf_counter()
    sess = session if isinstance(session, SessionData) else load_session(session)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    intr, size = sess.intrinsics_at(cfg.frame_width)
    if gripper_mask is not None and size is not None:
        x0, y0, cw, ch = sess.intrinsics.crop_geometry(*size)
        gm = np.asarray(gripper_mask, dtype=np.uint8)[y0:y0 + ch, x0:x0 + cw]
        gripper_mask = cv2.resize(gm, size, interpolation=cv2.INTER_NEAREST) > 0
    paths, names, T, valid, lengths, seq = _frames(sess, cfg, out / "frames", size)
    if cfg.sfm.mode == "known_poses" and valid.sum() < 2:
        raise ReconError(f"{sess.root}: mode 'known_poses' but the session's trajectory CSVs give "
                         f"{int(valid.sum())} tracked poses; run UMI's SLAM first or use mode 'full'")
    tm: dict[str, float] = {}
    t = time.perf_counter()
    mask = feature_mask(intr, gripper_mask)
    sfm = run_sfm(paths, names, intr, out / "colmap", cfg.sfm, sequence_lengths=lengths,
                  T_world_cam=T if valid.any() else None, pose_valid=valid, masks=mask)
    for scratch in (out / "frames", out / "colmap" / "images"):  # decoded frames + COLMAP's links to them
        shutil.rmtree(scratch, ignore_errors=True)
    tm["sfm"] = time.perf_counter() - t
    if cfg.sfm.mode == "full" and valid.sum() < 3:
        raise ReconError(f"{sess.root}: full SfM needs metric poses of >= 3 frames to fix scale "
                         f"(mapping_camera_trajectory.csv); got {int(valid.sum())}")
    sfm, sim = align_sfm_to_poses(sfm, T, valid)  # known_poses: identity
    t = time.perf_counter()
    keep = (sfm.track_length >= C.MIN_TRACK_LENGTH) & (sfm.errors_px <= C.MAX_POINT_ERROR_PX)
    body = inside_camera_body(sfm.points, _free_space_poses(sess, T[valid]))
    keep &= ~body
    cloud = clean_cloud(sfm.points[keep], sfm.colors[keep], sfm.view_dirs[keep])
    paths_out = {"cloud": str(write_ply(out / "scene_cloud.ply", cloud))}
    tm["cloud"] = time.perf_counter() - t

    t = time.perf_counter()
    theta = math.radians(cfg.cone_half_angle_deg)
    boxes = []
    pre_idx = {}
    for d in sess.demos:
        if d.T_world_cam is None:
            continue
        c = first_close_index(d.gripper_width)
        c = cfg.contact_overrides.get(d.name, len(d) - 1 if c is None else c)
        pre_idx[d.name] = c
        boxes.append(reachable_region(d.T_world_cam, c, theta, cfg.cone_radius_m))
    if boxes:
        lo = np.min([b[0] for b in boxes], axis=0)
        hi = np.max([b[1] for b in boxes], axis=0)
    else:  # no demos: the scanned cameras' region
        cams = sfm.T_world_cam[sfm.registered, :3, 3]
        lo, hi = cams.min(0) - C.GRIPPER_REACH_M, cams.max(0) + C.GRIPPER_REACH_M
    rays = None
    if cfg.carve:
        ok = sfm.registered[sfm.obs_image] & keep[sfm.obs_point]
        rays = (sfm.T_world_cam[sfm.obs_image[ok], :3, 3], sfm.points[sfm.obs_point[ok]])
    sdf = build_scene_sdf(cloud, lo, hi, cfg.voxel_m, cfg.inflation_m, max_voxels=cfg.max_voxels, rays=rays)
    paths_out["sdf"] = str(sdf.save(out / "scene_sdf.npz"))
    tm["sdf"] = time.perf_counter() - t

    t = time.perf_counter()
    contacts = []
    for d in sess.demos:
        if d.T_world_cam is None or d.gripper_width is None:
            log.warning("%s: no poses or gripper widths; contact not detected", d.name)
            continue
        fps = 1.0 / float(np.median(np.diff(d.timestamp))) if len(d) > 1 else 60.0
        contacts.append(detect_contact(sdf, d.T_world_cam, d.gripper_width, fps, cfg.contact_threshold_m,
                                       cfg.contact_rule, cfg.contact_overrides.get(d.name), d.name))
    tm["contact"] = time.perf_counter() - t
    tm["total"] = time.perf_counter() - t0
    report = {
        "session": str(sess.root),
        "frame": "world = UMI table-tag frame, z up, metres",
        "sfm": {"mode": sfm.mode, "frames": len(names), "registered": int(sfm.registered.sum()),
                "registered_fraction": sfm.registered_fraction, "points3D": int(len(sfm.points)),
                "mean_reproj_error_px": sfm.mean_reproj_error_px, "models": sfm.n_models,
                "timings_s": sfm.timings_s, "config": asdict(cfg.sfm)},
        "sim3": {"scale": sim.s, "residual_rms_m": sim.residual_rms_m,
                 "rotation_residual_deg": math.degrees(sim.rotation_residual_rad), "n": sim.n},
        "cloud": {"points": len(cloud), "inside_camera_body": int(body.sum())},
        "sdf": {"lo": sdf.bounds[0].tolist(), "hi": sdf.bounds[1].tolist(), "voxel_m": sdf.voxel,
                "shape": list(sdf.shape), "inflation_m": sdf.inflation},
        "contacts": [{"episode": c.name, "contact_index": c.contact_index, "proximity_index": c.proximity_index,
                      "grasp_onset_index": c.grasp_onset_index, "overridden": c.overridden, "rule": c.rule,
                      "min_clearance_m": float(c.clearance.min()), "message": c.message} for c in contacts],
        "timings_s": tm,
    }
    paths_out["report"] = str(atomic_write_text(out / "recon_report.json", json.dumps(report, indent=2) + "\n"))
    return ReconOutput(sess, sfm, sim, cloud, sdf, contacts, seq, tm, report, paths_out)
