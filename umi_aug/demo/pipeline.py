"""`umi-aug demo`: run every stage that exists today end to end on the built-in default scene.

Today:

1. **sim** — a synthetic UMI session of the built-in MuJoCo tabletop (mapping scan + one mug→plate demo,
   rendered through the true GoPro fisheye, with ground truth): :func:`umi_aug.sim.session.make_session`.
2. **traj** (+ geometry) — new start poses sampled in the paper's quaternion cone (θ = 50°, r = 0.15 m) around the
   demo's first view; batched SE(3) trajectory optimisation (funnel, gripper-sphere collision, render prior,
   smoothness; fixed ends) into the demo's pre-grasp pose, validated, retimed and spliced onto the original
   post-grasp motion. The scene's distance field is the simulator's exact one (:mod:`umi_aug.sim.scene_sdf`),
   standing in for the reconstructed one that is not wired in yet.
3. **camera** — the new pre-grasp frames of each episode rendered through the Kannala–Brandt fisheye (cube faces
   + remap) and turned into UMI policy images (gripper mask, crop, INTER_AREA); the rest is the original motion,
   so its frames are the original frames (nothing re-rendered). The renderer is the simulator's ground-truth
   scene, standing in for the 3DGS renderer that is not wired in yet.
4. **data** — one UMI ``dataset.zarr.zip`` with the original and the new episodes, validated and read back.
5. Pictures: the trajectories, a contact sheet original vs. new episodes, the lens geometry.

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
STAGES_RUN_BY_DEMO = frozenset({"geometry", "camera", "data", "sim", "traj"})


@dataclass(frozen=True)
class DemoConfig:
    """Settings of the demo. Angles in radians unless named ``*_deg``; lengths in metres."""

    out_dir: Path = Path("umi_aug_demo")
    seed: int = 0
    n_episodes: int = 4
    scan_frames: int = 120
    cone_half_angle_deg: float = 50.0
    cone_radius_m: float = 0.15
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


def run_demo(cfg: DemoConfig) -> dict:
    """Run the demo; returns a summary dict (also written to ``out_dir/summary.json``)."""
    from tqdm import tqdm

    from umi_aug.camera import load_umi_intrinsics_json
    from umi_aug.camera.umi_image import umi_policy_image
    from umi_aug.data import ReplayBuffer, make_umi_episode, validate_replay_buffer
    from umi_aug.demo import pictures
    from umi_aug.geometry import rotation_geodesic_distance
    from umi_aug.sim.fisheye_renderer import FisheyeRenderer
    from umi_aug.sim.gl import import_mujoco
    from umi_aug.sim.raster import RasterOptions
    from umi_aug.sim.scene import SCENE_FAR, SCENE_NEAR
    from umi_aug.sim.scene_sdf import scene_sdf
    from umi_aug.sim.session import make_session
    from umi_aug.sim.tabletop_state import TabletopState
    from umi_aug.traj import Demonstration, TrajProblem, TrajScene, generate, plot_trajectories

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

    mujoco = import_mujoco()
    model = mujoco.MjModel.from_xml_path(str(session_dir / "ground_truth" / "scene" / "scene.xml"))
    intr = load_umi_intrinsics_json(next((session_dir / "calibration").glob("gopro_intrinsics_*x*.json")))
    state = TabletopState(model)

    # 2. traj: cone-sampled starts, optimised trajectories into the pre-grasp pose, spliced -------------------
    t0 = time.perf_counter()
    state.set(T_demo[0], float(widths[0]), T_mug[0])  # the scene before contact: mug at its start pose
    scan_poses = np.load(session_dir / "ground_truth" / "mapping" / "trajectory.npz")["T_world_cam"]
    problem = TrajProblem(
        Demonstration(T_world_cam=T_demo, timestamps=gt["timestamp"], gripper_width=widths, contact_index=goal),
        TrajScene(sdf=scene_sdf(model, state.data), render_views=np.concatenate([scan_poses, T_demo[: goal + 1]])),
    )
    result = generate(problem, cfg.n_episodes, seed=cfg.seed, half_angle=np.deg2rad(cfg.cone_half_angle_deg),
                      radius=cfg.cone_radius_m, max_extra_rotation=np.deg2rad(cfg.max_extra_rotation_deg))
    episodes = result.episodes
    timings["trajectory_generation_s"] = time.perf_counter() - t0

    # 3. camera: render only the new pre-grasp frames --------------------------------------------------------
    t0 = time.perf_counter()
    new_frames: list[np.ndarray] = []
    with FisheyeRenderer(model, intr, options=RasterOptions(near=SCENE_NEAR, far=SCENE_FAR)) as renderer:
        remapper = renderer.cubemap
        with tqdm(total=sum(ep.splice_index for ep in episodes), desc="render new pre-grasp frames",
                  unit="frame") as bar:
            for ep in episodes:
                if not np.array_equal(ep.T_world_cam[ep.splice_index:], T_demo[ep.source_contact_index:]):
                    raise RuntimeError("spliced episode does not replay the original motion after the splice")
                frames = np.zeros((ep.splice_index, cfg.policy_size, cfg.policy_size, 3), np.uint8)
                for k in range(ep.splice_index):
                    state.set(ep.T_world_cam[k], float(ep.gripper_width[k]), T_mug[0])
                    frame = renderer.render(ep.T_world_cam[k], state.data, rgb=True, depth=False)
                    frames[k] = umi_policy_image(frame.rgb, intr, cfg.policy_size)
                    bar.update(1)
                new_frames.append(frames)
    n_rendered = sum(len(f) for f in new_frames)
    timings["render_s"] = time.perf_counter() - t0
    timings["render_ms_per_frame"] = 1e3 * timings["render_s"] / max(1, n_rendered)

    # 4. data: original + new episodes in one UMI replay buffer ---------------------------------------------
    t0 = time.perf_counter()
    buf = ReplayBuffer.create()
    buf.add_episode(original)
    for ep, frames in zip(episodes, new_frames):
        images = np.concatenate([frames, original["camera0_rgb"][ep.source_contact_index :]])
        buf.add_episode({**ep.umi_episode(), "camera0_rgb": images})
    zarr_path = out / "dataset.zarr.zip"
    buf.save(zarr_path)
    report = validate_replay_buffer(zarr_path)
    timings["dataset_write_validate_s"] = time.perf_counter() - t0

    # 5. pictures --------------------------------------------------------------------------------------------
    t0 = time.perf_counter()
    reread = ReplayBuffer.open(zarr_path)
    sheet_eps = [reread.get_episode(i, keys=["camera0_rgb"])["camera0_rgb"] for i in range(reread.n_episodes)]
    pictures.contact_sheet(sheet_eps, out / "contact_sheet.png",
                           splice_indices=[goal] + [ep.splice_index for ep in episodes],
                           row_names=["original"] + [f"new {e}" for e in range(len(episodes))])
    plot_trajectories(out / "trajectories.png", problem, episodes,
                      title=f"{len(episodes)} optimised trajectories from a {cfg.cone_half_angle_deg:.0f}° cone "
                            f"(r = {cfg.cone_radius_m} m) into the demo's pre-grasp pose")
    pictures.lens_figure(intr.umi_policy(cfg.policy_size), out / "lens.png")
    timings["pictures_s"] = time.perf_counter() - t0

    T_start = T_demo[0]
    starts = np.stack([ep.T_world_cam[0] for ep in episodes])
    start_angles = np.degrees(rotation_geodesic_distance(starts[:, :3, :3], T_start[:3, :3]))
    start_dist = np.linalg.norm(starts[:, :3, 3] - T_start[:3, 3], axis=-1)
    reports = result.reports
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
        "new_episodes": len(episodes),
        "new_frames_rendered": n_rendered,
        "trajectory_status_counts": dict(result.status_counts),
        "min_clearance_mm": [round(1e3 * r.min_clearance, 1) for r in reports],
        "required_clearance_mm": [round(1e3 * r.required_clearance, 1) for r in reports],
        "solver_iterations": [int(r.iterations) for r in reports],
        "solve_ms": [round(1e3 * r.solve_time_s, 1) for r in reports],
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
