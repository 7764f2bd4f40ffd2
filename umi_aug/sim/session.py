"""A synthetic UMI session: mapping scan + mug→plate demos rendered through the GoPro fisheye, with ground truth.

``make_session(out_dir, seed)`` writes a folder laid out like a real UMI session after UMI's SLAM pipeline
(umi_stack.md §1), plus the ground truth a real session never has::

    <out>/
      demos/mapping/            raw_video.mp4, mapping_camera_trajectory.csv, tx_slam_tag.json
      demos/demo_sim<seed>_<k>/ raw_video.mp4, camera_trajectory.csv
      calibration/              gopro_intrinsics_2_7k.json (UMI's), gopro_intrinsics_<W>x<H>.json (render size),
                                policy_intrinsics_<S>x<S>.json (the zarr images)
      dataset.zarr.zip          UMI replay buffer of the demos (TCP via UMI's camera→TCP offset, 224² images
                                made like UMI's 07 script: gripper mask, full-height centre crop, INTER_AREA)
      ground_truth/             scene/ (MJCF + textures, layout.json, scene_points.ply/.npz),
                                <sequence>/trajectory.npz, frames.zarr.zip (ray depth, gripper mask),
                                events.json (demos),
                                valid_mask.png
      contact_sheet.png, session.json

As in a real session the frames exist only as ``raw_video.mp4`` (H.264 yuv420p, like the GoPro's files; no
extracted ``images/``), read back by :mod:`umi_aug.recon.session_io`. World frame = SLAM map = table-tag frame (tag
id 13 at the origin, ``tx_slam_tag`` = identity); camera poses are exact (``state`` 2 = OK, never lost). The mapping
video runs at ``scan_fps`` (default 59.94/4); demos at UMI's 59.94 fps; every CSV row is one video frame with
``timestamp = frame_idx / fps``. Same seed → same bytes for the CSVs, videos and the zarr arrays (the zip container
holds timestamps).
"""

from __future__ import annotations

import json
import logging
import os
import platform
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numcodecs
import numpy as np
import zarr
from tqdm import tqdm

from umi_aug.camera.calib_io import gopro_intrinsics_2_7k, save_umi_intrinsics_json
from umi_aug.camera.umi_image import umi_policy_image
from umi_aug.data import CameraTrajectory, ReplayBuffer, make_umi_episode, validate_replay_buffer, \
    write_camera_trajectory_csv
from umi_aug.data.video import DEFAULT_CRF, VideoWriter
from umi_aug.errors import SimError, UmiAugError
from umi_aug.geometry.umi import umi_T_cam_tcp
from umi_aug.io_utils import atomic_path
from umi_aug.sim.bench import benchmark_fisheye_render
from umi_aug.sim.fisheye_renderer import FisheyeRenderer
from umi_aug.sim.gl import import_mujoco
from umi_aug.sim.pointcloud import sample_geom_points, write_ply
from umi_aug.sim.raster import RasterOptions
from umi_aug.sim.scene import SCENE_FAR, SCENE_NEAR, build_tabletop_scene
from umi_aug.sim.tabletop_state import TabletopState
from umi_aug.sim.trajectories import UMI_FPS, DemoPlan, plan_demo, scan_trajectory

__all__ = ["SessionConfig", "make_session", "load_ray_depth", "load_gripper_mask", "DEPTH_SCALE_M", "SESSION_LAYOUT"]

log = logging.getLogger(__name__)

#: Version of the folder layout :func:`make_session` writes (2: UMI's real layout, videos only, no images/).
SESSION_LAYOUT: int = 2
#: Ground-truth ray depth is stored as uint16 in units of this many metres (0.1 mm; max 6.55 m).
DEPTH_SCALE_M: float = 1e-4
#: File name of the per-frame ground truth (ray depth, gripper mask) in ``ground_truth/<sequence>/``.
FRAMES_GT_NAME: str = "frames.zarr.zip"
#: Frames per chunk of the per-frame ground truth arrays.
GT_CHUNK_FRAMES: int = 16
#: ORB-SLAM3 tracking state "OK".
SLAM_STATE_OK: int = 2
#: Every this many frames is flagged as a keyframe in the trajectory CSVs.
KEYFRAME_EVERY: int = 10
#: Room surfaces get a sparser ground-truth point cloud than the table and objects (points per m²).
ROOM_POINT_DENSITY: float = 1500.0
OBJECT_POINT_DENSITY: float = 20000.0


@dataclass(frozen=True)
class SessionConfig:
    """Settings of :func:`make_session` (defaults: a few minutes on 2 CPU cores).

    Attributes:
        seed: scene layout, trajectories and textures (same seed → same session).
        width, height: rendered frame size (the GoPro 2.7K calibration scaled to it; 4:3 like the GoPro).
        n_demos: number of demonstrations.
        scan_frames: frames of the mapping sweep.
        scan_fps: frame rate of the mapping video (its timestamps are ``frame_idx / scan_fps``).
        fps: demo frame rate (UMI: 59.94).
        policy_size: side of the square zarr images (UMI: 224).
        face_size: cube-face size for rendering (default: matched to the lens at ``width × height``).
        video_crf: libx264 constant rate factor of the ``raw_video.mp4`` files (the frames' only copy; lower =
            better; default :data:`umi_aug.data.video.DEFAULT_CRF`, as close to the renders as JPEG quality 95).
        n_distractors: static distractor objects on the table.
        shadows: shadow mapping (much slower on CPU).
        benchmark_frames: frames of the 224² timing run reported in ``session.json`` (0: skip).
        progress: tqdm progress bar.
        overwrite: replace an existing non-empty ``out_dir``.
    """

    seed: int = 0
    width: int = 320
    height: int = 240
    n_demos: int = 2
    scan_frames: int = 240
    scan_fps: float = UMI_FPS / 4.0
    fps: float = UMI_FPS
    policy_size: int = 224
    face_size: int | None = None
    video_crf: int = DEFAULT_CRF
    n_distractors: int = 4
    shadows: bool = False
    benchmark_frames: int = 30
    progress: bool = True
    overwrite: bool = False

    def check(self) -> None:
        """Raise :class:`SimError` for invalid settings."""
        if self.width < 32 or self.height < 32 or self.width < self.height:
            raise SimError(f"SessionConfig: need width >= height >= 32 (landscape like the GoPro), got "
                           f"{self.width}x{self.height}")
        if self.n_demos < 1 or self.scan_frames < 2:
            raise SimError(f"SessionConfig: need n_demos >= 1 and scan_frames >= 2, got {self.n_demos}, "
                           f"{self.scan_frames}")
        if not 0 <= int(self.video_crf) <= 51:
            raise SimError(f"SessionConfig.video_crf must be in [0, 51] (libx264), got {self.video_crf}")
        if not (self.fps > 0 and self.scan_fps > 0):
            raise SimError(f"SessionConfig: frame rates must be > 0, got fps={self.fps}, scan_fps={self.scan_fps}")


# ------------------------------------------------------------------------------------------ small writers
def _write_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2, sort_keys=True) + "\n", encoding="utf-8")


def _trajectory_csv(path: Path, T_world_cam: np.ndarray, fps: float) -> None:
    n = len(T_world_cam)
    idx = np.arange(n, dtype=np.int64)
    traj = CameraTrajectory(
        frame_idx=idx, timestamp=idx / float(fps), state=np.full(n, SLAM_STATE_OK, dtype=np.int64),
        is_lost=np.zeros(n, dtype=bool), is_keyframe=(idx % KEYFRAME_EVERY == 0), T_world_cam=T_world_cam,
    )
    write_camera_trajectory_csv(path, traj)


# -------------------------------------------------------------------------------------- sequence render
@dataclass
class _Rendered:
    policy_images: np.ndarray | None
    thumbs: list[np.ndarray]
    depth_thumb: np.ndarray | None
    mask_thumb: np.ndarray | None
    mask_fraction: float
    seconds: float


def _render_sequence(
    name: str,
    seq_dir: Path,
    gt_dir: Path,
    renderer: FisheyeRenderer,
    state: TabletopState,
    T_world_cam: np.ndarray,
    widths: np.ndarray,
    T_world_mug: np.ndarray | None,
    fps: float,
    cfg: SessionConfig,
    pbar,
    want_policy: bool,
    thumb_idx: list[int],
) -> _Rendered:
    intr = renderer.intr
    n = len(T_world_cam)
    seq_dir.mkdir(parents=True, exist_ok=True)
    gt_dir.mkdir(parents=True, exist_ok=True)
    depth_q = np.zeros((n, intr.height, intr.width), dtype=np.uint16)
    grip = np.zeros((n, intr.height, intr.width), dtype=bool)
    policy = np.zeros((n, cfg.policy_size, cfg.policy_size, 3), dtype=np.uint8) if want_policy else None
    try:
        video = VideoWriter(seq_dir / "raw_video.mp4", intr.width, intr.height, fps, crf=cfg.video_crf)
    except UmiAugError as exc:
        raise SimError(f"{seq_dir / 'raw_video.mp4'}: {exc}") from exc
    thumbs: list[np.ndarray] = []
    depth_thumb = mask_thumb = None
    t0 = time.perf_counter()
    try:
        for i in range(n):
            state.set(T_world_cam[i], float(widths[i]), None if T_world_mug is None else T_world_mug[i])
            fr = renderer.render(T_world_cam[i], state.data, rgb=True, depth=True, segmentation=True)
            rgb = fr.rgb
            video.write(rgb)
            q = np.rint(fr.ray_depth / DEPTH_SCALE_M)
            depth_q[i] = np.where(fr.depth_valid, np.clip(q, 1, 65535), 0).astype(np.uint16)
            grip[i] = state.gripper_mask(fr.geom_id)
            if policy is not None:
                policy[i] = umi_policy_image(rgb, intr, cfg.policy_size)
            if i in thumb_idx:
                thumbs.append(rgb)
                if depth_thumb is None and i == thumb_idx[len(thumb_idx) // 2]:
                    depth_thumb = fr.ray_depth
                    mask_thumb = rgb.copy()
                    mask_thumb[grip[i]] = (0.5 * mask_thumb[grip[i]] + (0, 127, 0)).astype(np.uint8)
            if pbar is not None:
                pbar.update(1)
    finally:
        video.close()
    seconds = time.perf_counter() - t0
    _write_frames_gt(gt_dir / FRAMES_GT_NAME, depth_q, grip)
    log.debug("%s: %d frames in %.1f s", name, n, seconds)
    return _Rendered(policy, thumbs, depth_thumb, mask_thumb, float(grip.mean()), seconds)


def _write_frames_gt(path: Path, depth_q: np.ndarray, grip: np.ndarray) -> None:
    """Per-frame ground truth as a zarr ZipStore: ``ray_depth_q`` uint16 (T, H, W) in units of
    :data:`DEPTH_SCALE_M` (0 = no valid hit) and ``gripper_mask`` bool (T, H, W); Blosc zstd + bit-shuffle."""
    cpr = numcodecs.Blosc(cname="zstd", clevel=5, shuffle=numcodecs.Blosc.BITSHUFFLE)
    store = zarr.ZipStore(str(path), mode="w")
    try:
        root = zarr.group(store=store)
        n, h, w = depth_q.shape
        chunk = (min(n, GT_CHUNK_FRAMES), h, w)
        root.array("ray_depth_q", depth_q, chunks=chunk, compressor=cpr)
        root.array("gripper_mask", grip, chunks=chunk, compressor=cpr)
        root.attrs.update({"ray_depth_scale_m": DEPTH_SCALE_M, "ray_depth": "distance along each pixel's ray; "
                           "ray_depth_q * ray_depth_scale_m metres, 0 = no valid hit / outside the image circle",
                           "gripper_mask": "True where a gripper geom is the first surface seen"})
    finally:
        store.close()


def _open_frames_gt(path: str | os.PathLike):
    path = Path(path)
    if path.is_dir():
        path = path / FRAMES_GT_NAME
    if not path.is_file():
        raise SimError(f"{path}: no per-frame ground truth (expected ground_truth/<sequence>/{FRAMES_GT_NAME})")
    store = zarr.ZipStore(str(path), mode="r")
    return store, zarr.open_group(store, mode="r")


def load_ray_depth(path: str | os.PathLike, frames: slice | None = None) -> np.ndarray:
    """Read ground-truth ray depth of a sequence (``ground_truth/<sequence>`` folder or its
    ``frames.zarr.zip``): ``[T, H, W]`` float32 metres along each pixel's ray, 0 where nothing valid was hit
    (outside the image circle / beyond the far plane). ``frames`` selects a range of frames."""
    store, root = _open_frames_gt(path)
    try:
        q = root["ray_depth_q"][frames if frames is not None else slice(None)]
        return q.astype(np.float32) * np.float32(root.attrs["ray_depth_scale_m"])
    finally:
        store.close()


def load_gripper_mask(path: str | os.PathLike, frames: slice | None = None) -> np.ndarray:
    """Read the ground-truth gripper mask of a sequence: ``[T, H, W]`` bool, True where the gripper is seen."""
    store, root = _open_frames_gt(path)
    try:
        return np.asarray(root["gripper_mask"][frames if frames is not None else slice(None)], dtype=bool)
    finally:
        store.close()


# -------------------------------------------------------------------------------------------- contact sheet
def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def _depth_vis(depth: np.ndarray, max_m: float = 2.0) -> np.ndarray:
    import matplotlib  # lazy, start-up: matplotlib

    cmap = matplotlib.colormaps["turbo"]
    d = np.clip(depth / max_m, 0.0, 1.0)
    rgb = (cmap(d)[..., :3] * 255).astype(np.uint8)
    rgb[depth <= 0] = 0
    return rgb


def _fit(img: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Centre ``img`` on a black canvas of ``shape`` (scaled down if larger)."""
    h, w = shape[:2]
    s = min(1.0, h / img.shape[0], w / img.shape[1])
    if s < 1.0:
        img = cv2.resize(img, (int(img.shape[1] * s), int(img.shape[0] * s)), interpolation=cv2.INTER_AREA)
    out = np.zeros((h, w, 3), dtype=np.uint8)
    y0, x0 = (h - img.shape[0]) // 2, (w - img.shape[1]) // 2
    out[y0:y0 + img.shape[0], x0:x0 + img.shape[1]] = img
    return out


def _contact_sheet(rows: list[tuple[str, list[np.ndarray]]], path: Path) -> None:
    w = max(len(r[1]) for r in rows)
    h0, w0 = rows[0][1][0].shape[:2]
    blank = np.zeros((h0, w0, 3), dtype=np.uint8)
    lines = []
    for title, imgs in rows:
        cells = [_label(im, f"{title} {k}") if k == 0 else im for k, im in enumerate(imgs)]
        cells += [blank] * (w - len(cells))
        lines.append(np.concatenate(cells, axis=1))
    sheet = np.concatenate(lines, axis=0)
    ok = cv2.imwrite(str(path), sheet[..., ::-1])
    if not ok:
        raise SimError(f"could not write {path}")


# ----------------------------------------------------------------------------------------------- main
def make_session(out_dir: str | os.PathLike, seed: int = 0, config: SessionConfig | None = None,
                 **overrides: Any) -> dict[str, Any]:
    """Generate a synthetic UMI session folder (see the module docstring for the layout).

    Args:
        out_dir: output folder (created atomically: written to ``<out_dir>.tmp-<random>`` and renamed).
        seed: session seed (overrides ``config.seed``).
        config: :class:`SessionConfig`; keyword ``overrides`` replace its fields.

    Returns:
        The summary also written to ``session.json``: paths, frame counts, demo events (contact frames),
        timings (``render_ms_per_frame`` at the session resolution and ``benchmark_224`` with the per-face
        breakdown).

    Raises:
        SimError: bad settings, ``out_dir`` exists and is not empty (without ``overwrite``), rendering failure.
    """
    cfg = replace(config or SessionConfig(), seed=int(seed), **overrides)
    cfg.check()
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not cfg.overwrite:
        raise SimError(f"{out} exists and is not empty; choose another --out, or rerun with --overwrite to replace "
                       f"it (its contents are deleted)")
    t_start = time.perf_counter()
    ss = np.random.SeedSequence([cfg.seed, 0x5E55])
    rng_scan, rng_points, *rng_demos = (np.random.default_rng(s) for s in ss.spawn(2 + cfg.n_demos))

    scene = build_tabletop_scene(cfg.seed, n_distractors=cfg.n_distractors)
    model = scene.compile()
    state = TabletopState(model)
    gopro = gopro_intrinsics_2_7k()
    intr = gopro.scaled(cfg.width, cfg.height)
    intr_policy = intr.umi_policy(cfg.policy_size)
    opts = RasterOptions(shadows=cfg.shadows, near=SCENE_NEAR, far=SCENE_FAR)
    T_cam_tcp = umi_T_cam_tcp()

    scan_poses = scan_trajectory(scene.layout, cfg.scan_frames, rng_scan)
    plans: list[DemoPlan] = [plan_demo(scene.layout, r, fps=cfg.fps, T_cam_tcp=T_cam_tcp) for r in rng_demos]
    demo_names = [f"demo_sim{cfg.seed}_{k:02d}" for k in range(cfg.n_demos)]
    n_total = cfg.scan_frames + sum(len(p) for p in plans)

    pbar = None
    if cfg.progress:
        pbar = tqdm(total=n_total, desc=f"make-session seed {cfg.seed}", unit="frame")
    summary: dict[str, Any] = {}
    try:
        with atomic_path(out, overwrite=True) as tmp:
            tmp.mkdir(parents=True)
            demos_dir, gt_root = tmp / "demos", tmp / "ground_truth"
            # --- calibration, scene ground truth
            calib = tmp / "calibration"
            calib.mkdir()
            save_umi_intrinsics_json(gopro, calib / "gopro_intrinsics_2_7k.json", fps=UMI_FPS)
            save_umi_intrinsics_json(intr, calib / f"gopro_intrinsics_{intr.width}x{intr.height}.json", fps=UMI_FPS)
            save_umi_intrinsics_json(intr_policy, calib / f"policy_intrinsics_{cfg.policy_size}x{cfg.policy_size}.json",
                                     fps=UMI_FPS)
            scene.write(gt_root / "scene")
            _write_json(gt_root / "scene" / "layout.json", scene.layout.to_dict())
            state.set(scan_poses[0], 0.08, scene.layout.T_world_mug)
            pts = _scene_points(model, state, rng_points)
            write_ply(gt_root / "scene" / "scene_points.ply", pts["points"], pts["colors"], pts["normals"],
                      pts["geom_id"])
            np.savez_compressed(gt_root / "scene" / "scene_points.npz", **pts)

            with FisheyeRenderer(model, intr, face_size=cfg.face_size, options=opts) as renderer:
                cv2.imwrite(str(gt_root / "valid_mask.png"), renderer.valid_mask.astype(np.uint8) * 255)
                # --- mapping scan
                seq = demos_dir / "mapping"
                scan_thumbs = list(np.linspace(0, cfg.scan_frames - 1, 8).round().astype(int))
                scan_widths = np.full(cfg.scan_frames, 0.08)
                rs = _render_sequence("mapping", seq, gt_root / "mapping", renderer, state, scan_poses,
                                      scan_widths, np.repeat(scene.layout.T_world_mug[None], cfg.scan_frames, 0),
                                      cfg.scan_fps, cfg, pbar, want_policy=False, thumb_idx=scan_thumbs)
                _trajectory_csv(seq / "mapping_camera_trajectory.csv", scan_poses, cfg.scan_fps)
                _write_json(seq / "tx_slam_tag.json", {"tx_slam_tag": np.eye(4).tolist()})
                _save_gt_trajectory(gt_root / "mapping", scan_poses, scan_widths, cfg.scan_fps, T_cam_tcp,
                                    np.repeat(scene.layout.T_world_mug[None], cfg.scan_frames, 0), None)
                rows = [("scan", rs.thumbs)]
                seconds = {"mapping": rs.seconds}
                frames = {"mapping": cfg.scan_frames}
                # --- demos
                buf = ReplayBuffer.create()
                events = {}
                for name, plan in zip(demo_names, plans):
                    seq = demos_dir / name
                    thumbs = sorted({0, plan.events["pregrasp"], plan.events["contact"], plan.events["grasped"],
                                     plan.events["lifted"], plan.events["above_plate"], plan.events["release"],
                                     plan.events["end"]})
                    rd = _render_sequence(name, seq, gt_root / name, renderer, state, plan.T_world_cam,
                                          plan.gripper_width, plan.T_world_mug, plan.fps, cfg, pbar,
                                          want_policy=True, thumb_idx=thumbs)
                    _trajectory_csv(seq / "camera_trajectory.csv", plan.T_world_cam, plan.fps)
                    _save_gt_trajectory(gt_root / name, plan.T_world_cam, plan.gripper_width, plan.fps, T_cam_tcp,
                                        plan.T_world_mug, plan)
                    ev = dict(plan.events)
                    _write_json(gt_root / name / "events.json", {
                        "events": ev, "contact_frame": ev["contact"], "fps": plan.fps,
                        "description": "frame indices: contact = first frame with the TCP at the handle "
                                       "(fingers start closing); grasped = fingers closed, mug attached; "
                                       "release = fingers open, mug on the plate",
                    })
                    buf.add_episode(make_umi_episode(plan.T_world_tcp, plan.gripper_width, {0: rd.policy_images}))
                    rows.append((name, rd.thumbs))
                    if rd.depth_thumb is not None:
                        rows.append((f"{name} GT ray depth | gripper mask | policy {cfg.policy_size}",
                                     [_depth_vis(rd.depth_thumb), rd.mask_thumb,
                                      _fit(rd.policy_images[thumbs[len(thumbs) // 2]], rd.mask_thumb.shape)]))
                    seconds[name] = rd.seconds
                    frames[name] = len(plan)
                    events[name] = ev
                render_timing = renderer.timing_report()
            buf.save(tmp / "dataset.zarr.zip")
            report = validate_replay_buffer(tmp / "dataset.zarr.zip")
            _contact_sheet(rows, tmp / "contact_sheet.png")

            bench = None
            if cfg.benchmark_frames > 0:
                state.set(scan_poses[0], 0.08, scene.layout.T_world_mug)
                idx = np.linspace(0, cfg.scan_frames - 1, cfg.benchmark_frames).round().astype(int)
                bench = benchmark_fisheye_render(model, state.data, gopro.umi_policy(224), scan_poses[idx],
                                                 options=opts)
            total_frames = sum(frames.values())
            render_s = sum(seconds.values())
            summary = {
                "seed": cfg.seed,
                "layout": SESSION_LAYOUT,
                "config": {k: (v if not isinstance(v, float) else float(v)) for k, v in asdict(cfg).items()},
                "frame": "world = SLAM map = table-tag frame (tag 13 at origin), z up, metres",
                "intrinsics": {"render": intr.to_dict(), "policy": intr_policy.to_dict()},
                "face_size": renderer.face_size,
                "faces_rendered": list(renderer.faces_needed),
                "sequences": {k: {"frames": v, "fps": cfg.scan_fps if k == "mapping" else cfg.fps}
                              for k, v in frames.items()},
                "demo_events": events,
                "dataset": {"path": "dataset.zarr.zip", "episodes": report.n_episodes, "steps": report.n_steps},
                "timings": {
                    "render_seconds": seconds,
                    "frames_total": total_frames,
                    "ms_per_frame_including_writes": 1000.0 * render_s / max(total_frames, 1),
                    "render_breakdown_ms": render_timing,
                    "benchmark_224": bench,
                    "total_seconds": time.perf_counter() - t_start,
                },
                "environment": {"python": platform.python_version(), "mujoco_gl": os.environ.get("MUJOCO_GL", "")},
            }
            _write_json(tmp / "session.json", summary)
    finally:
        if pbar is not None:
            pbar.close()
    summary["out_dir"] = str(out)
    return summary


def _scene_points(model, state: TabletopState, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Ground-truth point cloud of the static scene (everything but the gripper) at the initial state."""
    mujoco = import_mujoco()
    grip = set(state.gripper_geom_ids.tolist())
    ids = [g for g in range(model.ngeom) if g not in grip]
    room = {"floor", "ceiling", "wall_far", "wall_near", "wall_left", "wall_right"}
    dens = {}
    for g in ids:
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or ""
        dens[g] = ROOM_POINT_DENSITY if name in room or name.startswith("table_leg") else OBJECT_POINT_DENSITY
    pts = sample_geom_points(model, state.data, ids, rng, density_per_m2=dens)
    return dict(pts)


def _save_gt_trajectory(gt_dir: Path, T_world_cam: np.ndarray, widths: np.ndarray, fps: float,
                        T_cam_tcp: np.ndarray, T_world_mug: np.ndarray, plan: DemoPlan | None) -> None:
    gt_dir.mkdir(parents=True, exist_ok=True)
    n = len(T_world_cam)
    arrays = {
        "frame_idx": np.arange(n, dtype=np.int64),
        "timestamp": np.arange(n, dtype=np.float64) / float(fps),
        "T_world_cam": np.asarray(T_world_cam, dtype=np.float64),
        "T_world_tcp": np.asarray(T_world_cam, dtype=np.float64) @ T_cam_tcp,
        "T_cam_tcp": T_cam_tcp,
        "gripper_width": np.asarray(widths, dtype=np.float64),
        "T_world_mug": np.asarray(T_world_mug, dtype=np.float64),
    }
    if plan is not None:
        arrays["attached"] = plan.attached.astype(bool)
        arrays["phase"] = np.array(plan.phases)
    np.savez(gt_dir / "trajectory.npz", **arrays)
