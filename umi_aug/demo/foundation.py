"""`umi-aug demo`: run every stage that exists today end to end on the built-in default scene.

Today that is the foundation (geometry, fisheye camera, UMI dataset I/O) on the analytic room
(:mod:`umi_aug.demo.room`):

1. the built-in UMI GoPro calibration, converted to the 224² policy image the way UMI does;
2. start poses sampled in the paper's quaternion cone around an overhead reference view;
3. straight-line (slerp + lerp) camera paths from each start to a pre-contact pose — the *initial guess*
   of the trajectory optimiser, not an optimised trajectory;
4. true fisheye frames rendered through pinhole cube faces remapped by the Kannala–Brandt model, with UMI's
   gripper mask painted in;
5. a UMI ``dataset.zarr.zip`` (TCP poses via UMI's camera→TCP offset), validated and read back, plus a
   ``camera_trajectory.csv``;
6. pictures: lens geometry, sampled cone, contact sheet.

Stages that are not built yet are listed as such; nothing is faked.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from umi_aug.demo.room import AnalyticRoom

log = logging.getLogger(__name__)

#: The method's stages, their package and the issue that delivers each (for the status table).
STAGES: tuple[tuple[str, str, str], ...] = (
    ("geometry", "umi_aug.geometry", "SE(3), so(3), 6-D rotations, cone sampling (#2)"),
    ("camera", "umi_aug.camera", "Kannala–Brandt fisheye, cubemap remap, UMI masks (#2)"),
    ("data", "umi_aug.data", "UMI zarr replay buffer, camera_trajectory.csv (#2)"),
    ("sim", "umi_aug.sim", "MuJoCo fisheye scenes, synthetic UMI sessions (#3, #7)"),
    ("recon", "umi_aug.recon", "SfM, SDF, contact detection, obstacles (#5)"),
    ("splat", "umi_aug.splat", "fisheye 3D Gaussian Splatting on CPU (#4)"),
    ("traj", "umi_aug.traj", "SE(3) trajectory optimisation, RRT* (#6)"),
    ("augment", "umi_aug.augment", "augmentation pipeline and Dataset (#9)"),
    ("policy", "umi_aug.policy", "Diffusion Policy with CLIP ViT-B/16 (#8)"),
    ("eval", "umi_aug.eval", "RoboMimic square evaluation, UR deployment (#7)"),
)


@dataclass(frozen=True)
class DemoConfig:
    """Settings of the foundation demo. Angles in radians unless named ``*_deg``; lengths in metres."""

    out_dir: Path = Path("umi_aug_demo")
    seed: int = 0
    n_episodes: int = 6
    n_frames: int = 30
    image_size: int = 224
    cone_half_angle_deg: float = 50.0
    max_extra_rotation_deg: float = 10.0
    gripper_width_m: float = 0.08
    fps: float = 59.94005994005994


#: Stages this demo actually runs today.
STAGES_RUN_BY_DEMO = frozenset({"geometry", "camera", "data"})


def stage_status() -> list[tuple[str, str, str]]:
    """(stage, status, description) for every stage of the method. Status is ``"ran"`` for stages the demo
    runs, ``"present, not used by the demo yet"`` for a package that exists but is not wired in, and
    ``"not yet available"`` otherwise (package looked up without importing it)."""
    rows = []
    for name, mod, desc in STAGES:
        if name in STAGES_RUN_BY_DEMO:
            status = "ran"
        elif importlib.util.find_spec(mod) is not None:
            status = "present, not used by the demo yet"
        else:
            status = "not yet available"
        rows.append((name, status, desc))
    return rows


def _reference_poses(room: AnalyticRoom) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overhead reference start view, cone pivot and pre-contact camera pose (world, metres)."""
    from umi_aug.geometry import look_at_rotation, make_pose

    pivot = np.array([0.0, 0.0, 0.0])  # plate centre on the table
    up = np.array([0.0, 1.0, 0.0])  # world +y appears "up" in the image (camera −y)
    start_pos = np.array([0.0, -0.18, 0.42])
    T_world_start = make_pose(look_at_rotation(start_pos, pivot, up), start_pos)
    mug = np.array([0.18, -0.12, 0.03])
    goal_pos = np.array([0.16, -0.33, 0.13])
    T_world_goal = make_pose(look_at_rotation(goal_pos, mug, up), goal_pos)
    return T_world_start, pivot, T_world_goal


class FisheyeRoomRenderer:
    """Renders the analytic room through the true fisheye: pinhole cube faces → Kannala–Brandt remap."""

    def __init__(self, room: AnalyticRoom, intr) -> None:
        from umi_aug.camera.cubemap import CubemapFisheyeRemap, face_rotation

        self.room = room
        self.intr = intr
        self.remapper = CubemapFisheyeRemap(intr)
        s = self.remapper.face_size
        K = self.remapper.face_intrinsics_matrix()
        u, v = np.meshgrid(np.arange(s, dtype=np.float64), np.arange(s, dtype=np.float64))
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
        self._face_z = 1.0 / np.linalg.norm(rays, axis=-1)  # cos(angle to the face normal)
        rays_face = rays * self._face_z[..., None]
        self._rays_cam = {f: rays_face @ face_rotation(f).T for f in self.remapper.faces_needed}

    def render(self, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """RGB uint8 ``[H, W, 3]`` and ray depth float32 ``[H, W]`` [m] at camera pose ``T_world_cam``."""
        R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
        faces_rgb, faces_z = {}, {}
        for name, rays_cam in self._rays_cam.items():
            rgb, depth = self.room.render_rays(np.broadcast_to(t, rays_cam.shape), rays_cam @ R.T)
            faces_rgb[name] = (rgb * 255.0 + 0.5).astype(np.uint8)
            faces_z[name] = (depth * self._face_z).astype(np.float32)
        return self.remapper.remap(faces_rgb), self.remapper.remap_depth(faces_z)


def run_demo(cfg: DemoConfig) -> dict:
    """Run the foundation demo; returns a summary dict (also written to ``out_dir/summary.json``)."""
    from tqdm import tqdm

    from umi_aug.camera.calib_io import gopro_intrinsics_2_7k, save_umi_intrinsics_json
    from umi_aug.camera.masks import draw_predefined_mask
    from umi_aug.data import (
        CameraTrajectory,
        ReplayBuffer,
        make_umi_episode,
        validate_replay_buffer,
        write_camera_trajectory_csv,
    )
    from umi_aug.geometry import (
        interpolate_pose,
        rotation_geodesic_distance,
        sample_cone_start_poses,
        tcp_poses_from_camera_poses,
    )
    from umi_aug.demo import pictures

    timings: dict[str, float] = {}
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(cfg.seed)
    room = AnalyticRoom()

    t0 = time.perf_counter()
    intr_full = gopro_intrinsics_2_7k()
    intr = intr_full.umi_policy(cfg.image_size)
    save_umi_intrinsics_json(intr, out / "intrinsics_224.json")
    renderer = FisheyeRoomRenderer(room, intr)
    timings["camera_setup_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    T_world_start, pivot, T_world_goal = _reference_poses(room)
    starts = []
    while len(starts) < cfg.n_episodes:  # keep samples inside the room and above the table
        cand = sample_cone_start_poses(
            T_world_start,
            pivot,
            np.deg2rad(cfg.cone_half_angle_deg),
            cfg.n_episodes,
            rng,
            max_extra_rotation=np.deg2rad(cfg.max_extra_rotation_deg),
        )
        starts += [T for T in cand if room.contains(T[:3, 3], margin=0.05)]
    starts = np.stack(starts[: cfg.n_episodes])
    s = np.linspace(0.0, 1.0, cfg.n_frames)
    episodes_cam = np.stack([interpolate_pose(T0[None], T_world_goal[None], s) for T0 in starts])
    timings["sample_and_interpolate_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    frames = np.zeros((cfg.n_episodes, cfg.n_frames, intr.height, intr.width, 3), np.uint8)
    depth0 = None
    with tqdm(total=cfg.n_episodes * cfg.n_frames, desc="render fisheye frames", unit="frame") as bar:
        for e in range(cfg.n_episodes):
            for k in range(cfg.n_frames):
                rgb, depth = renderer.render(episodes_cam[e, k])
                frames[e, k] = draw_predefined_mask(rgb, color=(0, 0, 0), mirror=False, gripper=True)
                if e == 0 and k == 0:
                    depth0 = depth
                bar.update(1)
    timings["render_s"] = time.perf_counter() - t0
    timings["render_ms_per_frame"] = 1e3 * timings["render_s"] / (cfg.n_episodes * cfg.n_frames)

    t0 = time.perf_counter()
    buf = ReplayBuffer.create()
    for e in range(cfg.n_episodes):
        T_world_tcp = tcp_poses_from_camera_poses(episodes_cam[e])
        width = np.full(cfg.n_frames, cfg.gripper_width_m)
        buf.add_episode(make_umi_episode(T_world_tcp, width, images={0: frames[e]}))
    zarr_path = out / "dataset.zarr.zip"
    buf.save(zarr_path)
    report = validate_replay_buffer(zarr_path)
    reread = ReplayBuffer.open(zarr_path)
    ep0 = reread.get_episode(0)
    image_err = float(np.abs(ep0["camera0_rgb"].astype(np.int16) - frames[0].astype(np.int16)).mean())
    times = np.arange(cfg.n_frames) / cfg.fps
    traj = CameraTrajectory(
        frame_idx=np.arange(cfg.n_frames, dtype=np.int64),
        timestamp=times,
        state=np.full(cfg.n_frames, 2, dtype=np.int64),  # ORB-SLAM3 "OK" tracking state
        is_lost=np.zeros(cfg.n_frames, dtype=bool),
        is_keyframe=np.zeros(cfg.n_frames, dtype=bool),
        T_world_cam=episodes_cam[0],
    )
    write_camera_trajectory_csv(out / "camera_trajectory.csv", traj)
    timings["dataset_write_read_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    pictures.lens_figure(intr, renderer.remapper, out / "lens.png")
    pictures.cone_figure(T_world_start, pivot, T_world_goal, starts, episodes_cam, out / "cone.png")
    pictures.contact_sheet(frames, out / "contact_sheet.png", depth0=depth0)
    timings["pictures_s"] = time.perf_counter() - t0

    coverage = renderer.remapper.coverage_report()
    start_angles = np.degrees(rotation_geodesic_distance(starts[:, :3, :3], T_world_start[:3, :3]))
    summary = {
        "out_dir": str(out),
        "intrinsics_224": intr.to_dict(),
        "fold_over_deg": float(np.degrees(intr.theta_fold)),
        "fov_deg": float(intr.fov_deg),
        "max_theta_seen_deg": float(coverage["max_theta_deg"]),
        "fraction_pixels_in_image_circle": float(coverage["fraction_valid"]),
        "cube_faces_rendered": list(renderer.remapper.faces_needed),
        "cube_face_size": int(renderer.remapper.face_size),
        "episodes": cfg.n_episodes,
        "frames_per_episode": cfg.n_frames,
        "start_rotation_from_reference_deg": [round(float(a), 2) for a in start_angles],
        "dataset": str(zarr_path),
        "dataset_steps": int(report.n_steps),
        "jpegxl_mean_abs_error": image_err,
        "timings": {k: round(v, 4) for k, v in timings.items()},
        "stages": [{"stage": n, "status": st, "what": d} for n, st, d in stage_status()],
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary
