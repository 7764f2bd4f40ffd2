"""`umi-aug demo`: run every stage that exists today end to end on the built-in default scene.

Today:

1. **sim** — a synthetic UMI session of the built-in MuJoCo tabletop (mapping scan + one mug→plate demo,
   rendered through the true GoPro fisheye, with ground truth): :func:`umi_aug.sim.session.make_session`.
2. **geometry** — new start poses sampled in the paper's quaternion cone around the demo's first view
   (θ = 50° by default), and straight-line (slerp + lerp, eased) camera paths from each start to the demo's
   pre-grasp pose. These are the *initial guess* of the trajectory optimiser, which is not built yet: no
   collision check beyond keeping the camera above the table.
3. **camera** — the pre-contact frames of each new episode rendered through the Kannala–Brandt fisheye (cube faces
   + remap) and turned into UMI policy images (gripper mask, crop, INTER_AREA); the post-contact part is the
   original motion, so its frames are the original frames (nothing re-rendered). The renderer is the
   simulator's ground-truth scene, standing in for the 3DGS renderer that is not built yet.
4. **data** — one UMI ``dataset.zarr.zip`` with the original and the new episodes, validated and read back.
5. Pictures: the sampled cone, a contact sheet original vs. new episodes, the lens geometry.

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

log = logging.getLogger(__name__)

#: The method's stages, their package and the issue that delivers each (for the status table).
STAGES: tuple[tuple[str, str, str], ...] = (
    ("geometry", "umi_aug.geometry", "SE(3), so(3), 6-D rotations, cone sampling (#2)"),
    ("camera", "umi_aug.camera", "Kannala–Brandt fisheye, cubemap remap, UMI masks (#2)"),
    ("data", "umi_aug.data", "UMI zarr replay buffer, camera_trajectory.csv (#2)"),
    ("sim", "umi_aug.sim", "MuJoCo fisheye scene, synthetic UMI session (#3)"),
    ("recon", "umi_aug.recon", "SfM, SDF, contact detection, obstacles (#5)"),
    ("splat", "umi_aug.splat", "fisheye 3D Gaussian Splatting on CPU (#4)"),
    ("traj", "umi_aug.traj", "SE(3) trajectory optimisation, RRT* (#6)"),
    ("augment", "umi_aug.augment", "augmentation pipeline and Dataset (#9)"),
    ("policy", "umi_aug.policy", "Diffusion Policy with CLIP ViT-B/16 (#8)"),
    ("eval", "umi_aug.eval", "RoboMimic square evaluation, UR deployment (#7)"),
)

#: Stages this demo actually runs today.
STAGES_RUN_BY_DEMO = frozenset({"geometry", "camera", "data", "sim"})

#: Lowest camera height above the table top (world z, metres) accepted for a sampled start pose.
MIN_START_HEIGHT_M = 0.10


@dataclass(frozen=True)
class DemoConfig:
    """Settings of the demo. Angles in radians unless named ``*_deg``; lengths in metres."""

    out_dir: Path = Path("umi_aug_demo")
    seed: int = 0
    n_episodes: int = 4
    scan_frames: int = 120
    cone_half_angle_deg: float = 50.0
    max_extra_rotation_deg: float = 10.0
    policy_size: int = 224


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


def _ease(n: int) -> np.ndarray:
    """``n`` path parameters in [0, 1] with zero velocity at both ends (smoothstep)."""
    t = np.linspace(0.0, 1.0, n)
    return t * t * (3.0 - 2.0 * t)


def run_demo(cfg: DemoConfig) -> dict:
    """Run the demo; returns a summary dict (also written to ``out_dir/summary.json``)."""
    from tqdm import tqdm

    from umi_aug.camera import load_umi_intrinsics_json
    from umi_aug.camera.umi_image import umi_policy_image
    from umi_aug.data import ReplayBuffer, make_umi_episode, validate_replay_buffer
    from umi_aug.demo import pictures
    from umi_aug.geometry import (
        interpolate_pose,
        rotation_geodesic_distance,
        sample_cone_start_poses,
        tcp_poses_from_camera_poses,
    )
    from umi_aug.sim.fisheye_renderer import FisheyeRenderer
    from umi_aug.sim.gl import import_mujoco
    from umi_aug.sim.raster import RasterOptions
    from umi_aug.sim.scene import SCENE_FAR, SCENE_NEAR
    from umi_aug.sim.session import make_session
    from umi_aug.sim.tabletop_state import TabletopState

    timings: dict[str, float] = {}
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(cfg.seed)

    # 1. sim: the synthetic session (scan + one demo) --------------------------------------------------------
    t0 = time.perf_counter()
    session_dir = out / "session"
    session = make_session(session_dir, seed=cfg.seed, n_demos=1, scan_frames=cfg.scan_frames,
                           policy_size=cfg.policy_size, benchmark_frames=0, overwrite=True)
    timings["make_session_s"] = time.perf_counter() - t0

    demo_name = sorted(p.name for p in (session_dir / "demos").iterdir() if p.name.startswith("demo_"))[0]
    gt = np.load(session_dir / "ground_truth" / demo_name / "trajectory.npz")
    events = json.loads((session_dir / "ground_truth" / demo_name / "events.json").read_text())["events"]
    T_demo = gt["T_world_cam"]
    widths = gt["gripper_width"]
    T_mug = gt["T_world_mug"]
    goal = int(events["pregrasp"])  # splice index: new approach up to here, original motion after it
    contact = int(events["contact"])
    original = ReplayBuffer.open(session_dir / "dataset.zarr.zip").get_episode(0)

    # 2. geometry: cone-sampled starts and straight-line paths to the pre-grasp pose --------------------------
    t0 = time.perf_counter()
    T_start, T_goal = T_demo[0], T_demo[goal]
    pivot = tcp_poses_from_camera_poses(T_demo[contact])[:3, 3]  # the grasp point on the handle
    starts: list[np.ndarray] = []
    for _ in range(100):
        cand = sample_cone_start_poses(T_start, pivot, np.deg2rad(cfg.cone_half_angle_deg), cfg.n_episodes, rng,
                                       max_extra_rotation=np.deg2rad(cfg.max_extra_rotation_deg))
        starts += [T for T in cand if T[2, 3] >= MIN_START_HEIGHT_M]
        if len(starts) >= cfg.n_episodes:
            break
    starts_arr = np.stack(starts[: cfg.n_episodes])
    s = _ease(goal + 1)
    paths = np.stack([interpolate_pose(T0[None], T_goal[None], s) for T0 in starts_arr])  # [E, goal+1, 4, 4]
    timings["sample_and_interpolate_s"] = time.perf_counter() - t0

    # 3. camera: render only the new pre-contact frames ------------------------------------------------------
    t0 = time.perf_counter()
    mujoco = import_mujoco()
    model = mujoco.MjModel.from_xml_path(str(session_dir / "ground_truth" / "scene" / "scene.xml"))
    intr = load_umi_intrinsics_json(next((session_dir / "calibration").glob("gopro_intrinsics_*x*.json")))
    state = TabletopState(model)
    new_frames = np.zeros((cfg.n_episodes, goal + 1, cfg.policy_size, cfg.policy_size, 3), np.uint8)
    with FisheyeRenderer(model, intr, options=RasterOptions(near=SCENE_NEAR, far=SCENE_FAR)) as renderer:
        remapper = renderer.cubemap
        with tqdm(total=new_frames.shape[0] * new_frames.shape[1], desc="render new pre-contact frames",
                  unit="frame") as bar:
            for e in range(cfg.n_episodes):
                for k in range(goal + 1):
                    state.set(paths[e, k], float(widths[k]), T_mug[k])
                    frame = renderer.render(paths[e, k], state.data, rgb=True, depth=False)
                    new_frames[e, k] = umi_policy_image(frame.rgb, intr, cfg.policy_size)
                    bar.update(1)
    timings["render_s"] = time.perf_counter() - t0
    timings["render_ms_per_frame"] = 1e3 * timings["render_s"] / new_frames[:, :, 0, 0, 0].size

    # 4. data: original + new episodes in one UMI replay buffer ---------------------------------------------
    t0 = time.perf_counter()
    buf = ReplayBuffer.create()
    buf.add_episode(original)
    episodes_cam = []
    for e in range(cfg.n_episodes):
        T_world_cam = np.concatenate([paths[e], T_demo[goal + 1 :]])
        episodes_cam.append(T_world_cam)
        images = np.concatenate([new_frames[e], original["camera0_rgb"][goal + 1 :]])
        buf.add_episode(make_umi_episode(tcp_poses_from_camera_poses(T_world_cam), widths, images={0: images}))
    zarr_path = out / "dataset.zarr.zip"
    buf.save(zarr_path)
    report = validate_replay_buffer(zarr_path)
    timings["dataset_write_validate_s"] = time.perf_counter() - t0

    # 5. pictures --------------------------------------------------------------------------------------------
    t0 = time.perf_counter()
    reread = ReplayBuffer.open(zarr_path)
    sheet_eps = [reread.get_episode(i, keys=["camera0_rgb"])["camera0_rgb"] for i in range(reread.n_episodes)]
    pictures.contact_sheet(np.stack(sheet_eps), out / "contact_sheet.png", splice_index=goal,
                           row_names=["original"] + [f"new {e}" for e in range(cfg.n_episodes)])
    pictures.cone_figure(T_start, pivot, T_goal, starts_arr, np.stack(episodes_cam), out / "cone.png",
                         demo_path=T_demo)
    pictures.lens_figure(intr.umi_policy(cfg.policy_size), out / "lens.png")
    timings["pictures_s"] = time.perf_counter() - t0

    start_angles = np.degrees(rotation_geodesic_distance(starts_arr[:, :3, :3], T_start[:3, :3]))
    start_dist = np.linalg.norm(starts_arr[:, :3, 3] - T_start[:3, 3], axis=-1)
    policy_intr = intr.umi_policy(cfg.policy_size)
    coverage = remapper.coverage_report()
    summary = {
        "out_dir": str(out),
        "session": str(session_dir),
        "session_frames": int(session["timings"]["frames_total"]),
        "render_intrinsics": intr.to_dict(),
        "policy_intrinsics": policy_intr.to_dict(),
        "fold_over_deg": float(np.degrees(intr.theta_fold)),
        "max_theta_seen_deg": float(coverage["max_theta_deg"]),
        "cube_faces_rendered": list(coverage["faces_needed"]),
        "cube_face_size": int(coverage["face_size"]),
        "demo": demo_name,
        "splice_index": goal,
        "contact_index": contact,
        "new_episodes": cfg.n_episodes,
        "start_rotation_from_demo_start_deg": [round(float(a), 1) for a in start_angles],
        "start_distance_from_demo_start_m": [round(float(d), 3) for d in start_dist],
        "dataset": str(zarr_path),
        "dataset_episodes": int(report.n_episodes),
        "dataset_steps": int(report.n_steps),
        "timings": {k: round(v, 4) for k, v in {**timings, **{
            "session_render_ms_per_frame": session["timings"]["ms_per_frame_including_writes"]}}.items()},
        "stages": [{"stage": n, "status": st, "what": d} for n, st, d in stage_status()],
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary
