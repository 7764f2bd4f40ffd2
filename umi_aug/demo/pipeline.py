"""`umi-aug demo`: the whole method end to end on the built-in default scene (paper §3, Fig. 2).

1. **sim** — a synthetic UMI session of the built-in MuJoCo tabletop (mapping scan + one mug→plate demo through
   the true GoPro fisheye, written like a real UMI session, ground truth beside it):
   :func:`umi_aug.sim.session.make_session`. Reused when it already exists for the same settings.
2. **augment** — :func:`umi_aug.augment.exporter` on that session, exactly what ``umi-aug augment`` runs:
   reconstruction (SfM with the session's poses → cloud → distance field of the reachable region, contact
   split) → fisheye 3DGS trained on the scan → per episode: cone start (θ = 50°, r = 0.15 m) (+ an obstacle
   placed on the approach) → optimised trajectory → 3DGS frames with the real gripper overlaid → one UMI
   ``dataset.zarr.zip`` (original + augmented episodes, per-episode records). Stages are cached in ``work/``.
3. **check** — the simulator renders the ground truth at the augmented free-space poses; PSNR of the augmented
   frames against it (pixels inside the lens circle, gripper overlay excluded), a comparison picture, and a
   timing + error table (``summary.json``).
"""

from __future__ import annotations

import importlib.util
import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from umi_aug.demo import pictures
from umi_aug.errors import AugmentError
from umi_aug.io_utils import atomic_write_text
from umi_aug.sim.gl import import_mujoco
from umi_aug.sim.raster import RasterOptions
from umi_aug.splat.warmup import start_background_compile

log = logging.getLogger(__name__)

#: The method's stages, their package and the issue that delivers each (for the status table).
STAGES: tuple[tuple[str, str, str], ...] = (
    ("geometry", "umi_aug.geometry", "SE(3), so(3), 6-D rotations, cone sampling (#2)"),
    ("camera", "umi_aug.camera", "Kannala–Brandt fisheye, cubemap remap, UMI masks (#2)"),
    ("data", "umi_aug.data", "UMI zarr replay buffer, camera_trajectory.csv (#2)"),
    ("sim", "umi_aug.sim", "MuJoCo fisheye scene, synthetic UMI session (#3)"),
    ("recon", "umi_aug.recon", "SfM, SDF, contact detection, obstacles (#5)"),
    ("splat", "umi_aug.splat", "fisheye 3D Gaussian Splatting on CPU: trainer, renderer, composition (#4)"),
    ("traj", "umi_aug.traj", "SE(3) trajectory optimisation, RRT* (#6)"),
    ("augment", "umi_aug.augment", "augmentation pipeline, offline export (#9)"),
    ("policy", "umi_aug.policy", "Diffusion Policy + CLIP ViT-B/16, AugmentedUmiDataset (#8, #9)"),
    ("square", "umi_aug.square", "RoboMimic square, fisheye wrist camera, expert, IK start configs (#7)"),
    ("eval", "umi_aug.eval", "policy evaluation over the 1000 start configs, UR deployment"),
)

#: Stages this demo runs.
STAGES_RUN_BY_DEMO = frozenset({"geometry", "camera", "data", "sim", "recon", "splat", "traj", "augment"})
#: How to run the stages the demo does not.
NOT_RUN_HINT = {
    "policy": "not run by the demo: python train/train.py task=demo (or aug=freespace task=session)",
    "square": "not run by the demo: umi-aug square-demos / square-init-configs",
}


@dataclass(frozen=True)
class DemoConfig:
    """Settings of the demo (small defaults: ~4.5–5 minutes on 2 free CPU cores, cold numba cache). Lengths in
    metres."""

    out_dir: Path = Path("umi_aug_demo")
    seed: int = 0
    #: augmented episodes per mode
    n_episodes: int = 4
    #: "freespace", "obstacle" or "both"
    mode: str = "both"
    scan_frames: int = 120
    policy_size: int = 224
    cone_half_angle_deg: float = 50.0
    cone_radius_m: float = 0.15
    splat_iterations: int = 1500
    splat_max_gaussians: int = 25_000
    #: augmented (pre-splice) frames compared with ground-truth renders
    gt_frames: int = 32


def stage_status() -> list[tuple[str, str, str]]:
    """(stage, status, description) for every stage: ``"ran"``, a hint for stages the demo leaves to their own
    command, or ``"not yet available"`` (package looked up without importing it)."""
    rows = []
    for name, mod, desc in STAGES:
        if name in STAGES_RUN_BY_DEMO:
            status = "ran"
        elif importlib.util.find_spec(mod.rsplit(".", 1)[0]) is not None and _has_module(mod):
            status = NOT_RUN_HINT.get(name, "present, not run by the demo")
        else:
            status = "not yet available"
        rows.append((name, status, desc))
    return rows


def _has_module(mod: str) -> bool:
    try:
        return importlib.util.find_spec(mod) is not None
    except ModuleNotFoundError:
        return False


def _session(cfg: DemoConfig, say: Callable[[str], None]) -> tuple[Path, dict]:
    """The synthetic session (made, or reused when it exists for the same settings)."""
    from umi_aug.sim.session import SESSION_LAYOUT, make_session  # lazy, start-up: cv2, zarr

    session_dir = Path(cfg.out_dir) / "session"
    marker = Path(cfg.out_dir) / "session.settings.json"
    settings = {"seed": cfg.seed, "scan_frames": cfg.scan_frames, "policy_size": cfg.policy_size, "n_demos": 1,
                "layout": SESSION_LAYOUT}  # a session of an older layout (images/ folders) is rendered again
    if (session_dir / "dataset.zarr.zip").is_file() and marker.is_file() \
            and json.loads(marker.read_text()) == settings:
        say(f"sim: reusing the synthetic session {session_dir}")
        return session_dir, {"reused": True}
    say(f"sim: rendering a synthetic UMI session (scan {cfg.scan_frames} frames + 1 demo) → {session_dir}")
    info = make_session(session_dir, seed=cfg.seed, n_demos=1, scan_frames=cfg.scan_frames,
                        policy_size=cfg.policy_size, benchmark_frames=0, overwrite=True)
    marker.write_text(json.dumps(settings))
    return session_dir, {"reused": False, "frames": int(info["timings"]["frames_total"])}


def _masked_psnr(a: np.ndarray, b: np.ndarray, valid: np.ndarray) -> float:
    """PSNR (dB, 8-bit peak) of ``a`` vs ``b`` ``[..., H, W, 3]`` uint8 over ``valid`` ``[H, W]`` pixels."""
    d = (a.astype(np.float64) - b.astype(np.float64))[..., valid, :]
    mse = float(np.mean(d * d))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0 ** 2 / mse)


def compare_with_ground_truth(session_dir: Path, dataset: Path, assets, n_frames: int, out_png: Path,
                              say: Callable[[str], None]) -> dict:
    """Render the simulator's ground truth at augmented free-space poses and compare with the exported frames.

    The pre-splice frames of the free-space episodes (the mug has not moved yet) are sampled evenly; the
    simulator renders each pose at the session's raw intrinsics and UMI's policy transform makes the 224² view,
    exactly as the session's own frames were made. PSNR is over pixels inside the lens circle and outside the
    gripper overlay mask (those pixels are copied from real frames, not rendered).
    """
    # lazy, start-up: cv2, scipy, zarr
    from umi_aug.augment import plan_episode, read_episode_records
    from umi_aug.camera.umi_image import umi_policy_image
    from umi_aug.data import ReplayBuffer
    from umi_aug.sim.fisheye_renderer import FisheyeRenderer
    from umi_aug.sim.scene import SCENE_FAR, SCENE_NEAR
    from umi_aug.sim.tabletop_state import TabletopState

    rec = read_episode_records(dataset)
    free = np.flatnonzero(rec["aug_mode"] == 1)
    if len(free) == 0 or n_frames <= 0:
        return {}
    per_ep = max(1, n_frames // len(free))
    S = assets.cfg.image_size
    intr = assets.intrinsics
    policy_intr = assets.policy_intrinsics
    uu, vv = np.meshgrid(np.arange(S), np.arange(S))
    from umi_aug.camera.kb import unproject  # lazy, start-up: cv2

    _, in_lens = unproject(np.stack([uu.ravel(), vv.ravel()], -1).astype(np.float64), policy_intr)
    valid = in_lens.reshape(S, S) & ~assets.gripper_mask
    mujoco = import_mujoco()
    gt_dir = session_dir / "ground_truth"
    model = mujoco.MjModel.from_xml_path(str(gt_dir / "scene" / "scene.xml"))
    state = TabletopState(model)
    buf = ReplayBuffer.open(dataset)
    gts, augs, psnrs = [], [], []
    try:
        with FisheyeRenderer(model, intr, options=RasterOptions(near=SCENE_NEAR, far=SCENE_FAR)) as renderer:
            for e in free:
                d, a = int(rec["aug_source_episode"][e]), int(rec["aug_id"][e])
                planned = plan_episode(assets, d, a, "freespace")
                if planned is None:  # pragma: no cover - the export emitted it, so planning succeeds
                    continue
                demo_name = assets.demos[d].name
                T_mug0 = np.load(gt_dir / demo_name / "trajectory.npz")["T_world_mug"][0]
                ks = np.unique(np.linspace(0, planned.splice_index - 1, per_ep).round().astype(int))
                sl = buf.get_episode_slice(int(e))
                frames = buf["camera0_rgb"].get_orthogonal_selection((ks + sl.start,))  # only these chunks
                for k, frame in zip(ks, frames):
                    state.set(planned.episode.T_world_cam[k], float(planned.episode.gripper_width[k]), T_mug0)
                    raw = renderer.render(planned.episode.T_world_cam[k], state.data, rgb=True, depth=False).rgb
                    gt = umi_policy_image(raw, intr, S)
                    gts.append(gt)
                    augs.append(frame)
                    psnrs.append(_masked_psnr(frame, gt, valid))
    finally:
        buf.close()
    gts_a, augs_a = np.stack(gts), np.stack(augs)
    pictures.comparison_sheet(gts_a, augs_a, valid, out_png)
    say(f"check: {len(psnrs)} augmented frames vs ground-truth renders: PSNR median {np.median(psnrs):.2f} dB")
    return {"frames": len(psnrs), "psnr_db_median": float(np.median(psnrs)), "psnr_db_mean": float(np.mean(psnrs)),
            "psnr_db_min": float(np.min(psnrs)), "psnr_db_all_pixels": _masked_psnr(augs_a, gts_a, valid),
            "picture": str(out_png)}


def run_demo(cfg: DemoConfig, say: Callable[[str], None] = log.info) -> dict:
    """Run the demo; returns a summary dict (also written to ``out_dir/summary.json``)."""
    # lazy, start-up: cv2, scipy, zarr
    from umi_aug.augment import AugmentConfig, SplatStageConfig, export, prepare_session
    from umi_aug.data import validate_replay_buffer

    t_all = time.perf_counter()
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}

    t0 = time.perf_counter()

    start_background_compile()  # a cold numba cache: the 3DGS kernels compile beside the session's rendering
    session_dir, session_info = _session(cfg, say)
    timings["session_s"] = time.perf_counter() - t0

    acfg = AugmentConfig(mode=cfg.mode, n_per_demo=cfg.n_episodes, seed=cfg.seed, image_size=cfg.policy_size,
                         cone_half_angle_deg=cfg.cone_half_angle_deg, cone_radius_m=cfg.cone_radius_m,
                         splat=SplatStageConfig(iterations=cfg.splat_iterations,
                                                max_gaussians=cfg.splat_max_gaussians))
    work = out / "work"
    dataset = out / "dataset.zarr.zip"
    say(f"augment: reconstruct → 3DGS ({cfg.splat_iterations} steps, ≤{cfg.splat_max_gaussians} Gaussians) → "
        f"{cfg.n_episodes} episode(s) per mode ({cfg.mode}) → {dataset}")
    t0 = time.perf_counter()
    try:
        exp = export(session_dir, dataset, acfg, work_dir=work)
    except AugmentError as exc:
        if "another configuration" not in str(exc):
            raise
        say(f"augment: {dataset} was made with other settings or an older version: writing it anew")
        exp = export(session_dir, dataset, acfg, work_dir=work, resume=False)
    timings["augment_s"] = time.perf_counter() - t0
    report = validate_replay_buffer(dataset)

    t0 = time.perf_counter()
    assets = prepare_session(session_dir, work, acfg, progress=False)  # cached: loads, runs nothing
    check = compare_with_ground_truth(session_dir, dataset, assets, cfg.gt_frames, out / "render_vs_gt.png", say)
    timings["ground_truth_check_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    policy_intr = assets.policy_intrinsics
    pictures.lens_figure(policy_intr, out / "lens.png")
    timings["pictures_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_all

    splat_stage = assets.stages.get("splat")
    splat_metrics = dict(splat_stage.info) if splat_stage is not None else {}
    summary = {
        "out_dir": str(out),
        "session": str(session_dir),
        "session_info": session_info,
        "dataset": str(dataset),
        "dataset_episodes": int(report.n_episodes),
        "dataset_steps": int(report.n_steps),
        "export": asdict(exp),
        "splat": splat_metrics,
        "stage_seconds_this_run": exp.stages,
        "ground_truth_check": check,
        "timings": {k: round(v, 3) for k, v in timings.items()},
        "stages": [{"stage": n, "status": st, "what": d} for n, st, d in stage_status()],
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()},
    }
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2))
    return summary
