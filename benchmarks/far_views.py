"""Far views: how the 3DGS scene renders at cone starts θ away from the demo's first viewpoint, against the
simulator's ground truth (issue #34 item 5).

Run: ``python benchmarks/far_views.py [--session DIR] [--work DIR] [--thetas 0 10 20 30 40 50] [--azimuths 8]``

A synthetic UMI session (``umi-aug make-session``; made in ``<work>/session`` when ``--session`` is not given) has
ground truth for any camera pose. Its ``dataset.zarr.zip`` goes in as a plain UMI dataset, one episode, exactly as a
real dataset's episode does (``umi-aug augment <dataset>``: the scene is triangulated and trained from that demo's
own frames only). For each θ the camera is placed on the paper's cone (radius ``cone_radius_m`` around the pivot
``cone_radius_m`` in front of the demo's first camera, re-aimed at the pivot, as the planner's starts) at
``--azimuths`` evenly spaced azimuths, and both the 3DGS scene (no gripper overlay) and the simulator render it.
Reported per setting and θ: PSNR over the lens circle minus the gripper mask (the pixels the overlay does not
cover), and the fraction of those pixels the 3DGS leaves uncovered (accumulated opacity < 0.5 without counting the
background shell's Gaussians, i.e. what the demo never saw from anywhere near that direction).

Settings (``--settings``):
* ``one demo, no shell``: the demo's frames only, no background Gaussians.
* ``one demo (default)``: the default: plus the far-background shell (``DatasetInput.background_points``), the
  measure aimed at unseen regions (what is behind the seen scene renders as a plausible far background instead of
  black).
* ``one demo, before (every 2nd frame, 600 full-size steps)``: the dataset defaults before 2026-11-27: every
  2nd pre-grasp frame triangulated (``DatasetInput.sfm_stride``) and 600 3DGS steps at full size
  (``SplatStageConfig.coarse_downscale`` 1); the default since is every 4th frame and 1,200 steps with the first
  half at half size (27.3 dB held-out on the real episode in less time; ``benchmarks/real_scene_cost.py``).
  ``--iterations`` does not change it.
* ``one demo, SfM every 2nd frame``: the default with every 2nd frame triangulated.
* ``two demos pooled``: both demos' frames build one scene (``--scene-group 2``; the session's demos share the
  tag frame and the table), with the shell: what pooling the episodes of one place does (issue #34 item 2).
* ``one demo, 3DGS schedule before (...)``: the default's scene trained as a dataset's scenes were before
  2026-11-29: 1,200 steps (first half at half size) at the trainer's learning rates and growth, where the default is
  550 steps (600 before session 42) with ``DATASET_SPLAT_SCHEDULE`` (``umi_aug/augment/splat_defaults.py``;
  ``docs/real_scale.md`` 1f).
* ``one demo, pose pairs (...)``: the default before session 38: the known-pose triangulation also matches every
  two frames within 0.25 m and 45° (``DatasetInput.sfm_pose_pairs``; the default matches only each frame's
  sequential neighbours and the loop grid, a third less triangulation time on the real episode,
  ``docs/real_scale.md`` 1i).
* ``two demos pooled, pose pairs (...)``: the pooled scene as before session 38, its triangulation also matching
  every two frames within 0.25 m and 45° (the loop grid alone also spans both demos).
* ``one demo, 500 3DGS steps, growth from step 50 (600, 100)``: a shorter 3DGS run (``docs/real_scale.md`` 1j;
  the parentheses name the defaults of its time).
* ``one demo, 500 3DGS steps (600)``: the same with the default's growth (``umi-aug augment --splat-iterations 500``).
* ``one demo, 600 3DGS steps (550; the default before session 42)``: ``umi-aug augment --splat-iterations 600``
  (``docs/real_scale.md`` 1m).
* ``one demo, matches verified by the known poses (...)``: the known-pose triangulation keeps the matches that
  agree with the known poses instead of COLMAP's two-view RANSAC (``DatasetInput.sfm_known_pose_verification``;
  ``docs/real_scale.md`` 1j).
* ``scan + demos``: the session path (``umi-aug augment <session>``): the mapping scan's frames and both demos
  (the upper bound a short scan gives).

Writes ``<work>/far_views.json`` and a contact sheet ``<work>/far_views.png`` (rows θ, one azimuth; columns ground
truth and each setting). Quality only: no timing is compared (the scene builds' seconds are printed for context).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

#: the dataset's 3DGS before 2026-11-29: 1,200 steps (coarse-to-fine) at the trainer's learning rates and growth
SCHEDULE_BEFORE = "one demo, 3DGS schedule before (1,200 steps, the trainer's rates and growth)"
#: the dataset defaults before 2026-11-27: every 2nd frame triangulated, 600 full-size steps, the trainer's schedule
DEFAULTS_BEFORE = "one demo, before (every 2nd frame, 600 full-size steps)"
#: the known-pose triangulation also matching every two frames within 0.25 m and 45 deg (the default before session 38)
POSE_PAIRS = "one demo, pose pairs (the default before session 38)"
#: both demos pooled with the triangulation also matching pose pairs (the default before session 38)
POOLED_POSE_PAIRS = "two demos pooled, pose pairs (the default before session 38)"
#: a shorter 3DGS run: 500 steps, the MCMC growth from step 50 (the default: 600 steps, growth from step 100)
SHORT_500 = "one demo, 500 3DGS steps, growth from step 50 (600, 100)"
#: a shorter 3DGS run with the default's growth: ``umi-aug augment --splat-iterations 500``
SHORT_500_PLAIN = "one demo, 500 3DGS steps (600)"
#: the 3DGS steps of a dataset's scene before session 42 (now 550)
SPLAT_600 = "one demo, 600 3DGS steps (550; the default before session 42)"
#: the triangulation's matches verified by the known poses instead of COLMAP's two-view RANSAC
KNOWN_POSE_VERIFICATION = "one demo, matches verified by the known poses (COLMAP's RANSAC)"
SETTINGS = ("one demo, no shell", "one demo (default)", DEFAULTS_BEFORE,
            "one demo, SfM every 2nd frame", "two demos pooled", "scan + demos", SCHEDULE_BEFORE, POSE_PAIRS,
            POOLED_POSE_PAIRS, SHORT_500, SHORT_500_PLAIN, SPLAT_600, KNOWN_POSE_VERIFICATION)


def cone_ring_poses(T_ref: np.ndarray, radius: float, theta: float, n: int) -> np.ndarray:
    """``[n, 4, 4]`` camera poses exactly ``theta`` (radians) off the cone axis at ``n`` evenly spaced azimuths:
    the construction of :func:`umi_aug.geometry.sample_cone_start_poses` (pivot ``radius`` in front of ``T_ref``,
    positions on the sphere of that radius, the reference re-aimed and carried along by the minimal rotation)
    with the direction fixed instead of drawn."""
    from umi_aug.geometry.cone import rotation_between_vectors

    pivot = T_ref[:3, 3] + radius * T_ref[:3, 2]
    axis = (T_ref[:3, 3] - pivot) / radius
    R_aim = rotation_between_vectors(T_ref[:3, 2], -axis) @ T_ref[:3, :3]
    u = np.cross(axis, T_ref[:3, 0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    out = np.tile(np.eye(4), (n, 1, 1))
    for k, phi in enumerate(np.arange(n) * 2 * math.pi / n):
        d = math.cos(theta) * axis + math.sin(theta) * (math.cos(phi) * u + math.sin(phi) * v)
        out[k, :3, :3] = rotation_between_vectors(axis, d) @ R_aim
        out[k, :3, 3] = pivot + radius * d
    return out


def masked_psnr(a: np.ndarray, b: np.ndarray, valid: np.ndarray) -> float:
    """PSNR (dB, 8-bit) of ``a`` against ``b`` over the ``valid`` [S, S] pixels."""
    d = a[valid].astype(np.float64) - b[valid].astype(np.float64)
    mse = float(np.mean(d * d))
    return float("inf") if mse == 0 else 10.0 * math.log10(255.0 ** 2 / mse)


def jittered_dataset(session: Path, out: Path, episodes: tuple[int, ...] = (0, 1), sigma_m: float = 2e-5) -> Path:
    """The session's first episodes with ``sigma_m`` of noise on the TCP positions: the synthetic demos hold the
    camera exactly still for their first frames, which the dataset check rejects as lost tracking (a hand-held
    camera never holds still to the micrometre)."""
    from umi_aug.data import ReplayBuffer

    if out.exists():
        return out
    rng = np.random.default_rng(0)
    dst = ReplayBuffer.create()
    with ReplayBuffer.open(session / "dataset.zarr.zip") as src:
        for e in episodes:
            ep = src.get_episode(e)
            ep["robot0_eef_pos"] = ep["robot0_eef_pos"] + rng.normal(0.0, sigma_m, ep["robot0_eef_pos"].shape)
            dst.add_episode(ep)
    return dst.save(out)


def build(setting: str, session: Path, work: Path, iterations: int | None, seed: int = 0):
    """Demo 0's assets of the setting with root seed ``seed`` (``AugmentConfig.seed``: the 3DGS's view order,
    relocation and noise, the background shell's points; scene built or loaded from ``work``) and the seconds it
    took."""
    from umi_aug.augment.config import AugmentConfig, dataset_splat_stage
    from umi_aug.augment.dataset_source import DatasetInput, prepare_dataset
    from umi_aug.augment.sources.session import prepare_session

    base = AugmentConfig(seed=seed)
    t0 = time.perf_counter()
    if setting == "scan + demos":
        cfg = base if iterations is None else dataclasses.replace(
            base, splat=dataclasses.replace(base.splat, iterations=iterations))
        assets = prepare_session(session, work, dataclasses.replace(cfg, mode="freespace"), progress=False)
        return assets, time.perf_counter() - t0
    splat = dataset_splat_stage(iterations=iterations)
    before = setting == DEFAULTS_BEFORE
    if before:
        splat = dataclasses.replace(splat, iterations=600, coarse_downscale=1, extra={})
    if setting == SCHEDULE_BEFORE:
        splat = dataclasses.replace(splat, iterations=iterations or 1200, extra={})
    if setting == SHORT_500:
        splat = dataclasses.replace(splat, iterations=500, extra={**splat.extra, "refine_start": 50})
    if setting in (SHORT_500_PLAIN, SPLAT_600):
        splat = dataclasses.replace(splat, iterations=500 if setting == SHORT_500_PLAIN else 600)
    cfg = dataclasses.replace(base, mode="freespace", splat=splat)
    pooled = setting in ("two demos pooled", POOLED_POSE_PAIRS)
    inp = DatasetInput(episodes=(0, 1) if pooled else (0,), scene_group=2 if pooled else 1,
                       background_points=0 if "no shell" in setting else DatasetInput.background_points,
                       sfm_stride=2 if (before or "2nd" in setting) else DatasetInput.sfm_stride,
                       sfm_pose_pairs=before or setting in (POSE_PAIRS, POOLED_POSE_PAIRS),
                       sfm_known_pose_verification=setting == KNOWN_POSE_VERIFICATION)
    dataset = jittered_dataset(session, work.parent / "dataset_jittered.zarr.zip")
    assets = prepare_dataset(dataset, work, cfg, inp, progress=False)
    return assets.for_demo(0), time.perf_counter() - t0


def render_3dgs(assets, T_world_cam: np.ndarray, shell_from_m: float | None) -> tuple[np.ndarray, np.ndarray]:
    """``(rgb [S, S, 3] uint8, alpha [S, S] of the scene without the background shell)`` at the policy view; the
    shell is every Gaussian further than ``shell_from_m`` from the demo's first camera (None: no shell)."""
    import torch

    from umi_aug.splat.compose import render_composed, rgb_to_uint8

    cfg, g = assets.cfg, assets.gaussians
    kw = dict(background=(0.0, 0.0, 0.0), near=cfg.render_near_m, far=cfg.render_far_m)
    out = render_composed(g, [], T_world_cam, assets.policy_intrinsics, **kw)
    alpha = out.alpha
    if shell_from_m is not None:
        c0 = torch.as_tensor(assets.demos[0].T_world_cam[0][:3, 3], dtype=g.means.dtype)
        near = torch.linalg.norm(g.means.detach() - c0, dim=1) < shell_from_m
        alpha = render_composed(g.select(near), [], T_world_cam, assets.policy_intrinsics, **kw).alpha
    return rgb_to_uint8(out.rgb), np.asarray(alpha, np.float64).reshape(out.rgb.shape[:2])


def shell_distance_m(assets, inp_radius: float) -> float:
    """Half the background shell's radius (``background_shell_points``: radius x the cameras' spread, >= 0.5 m)
    for the demo's pre-closing cameras: Gaussians beyond it are the shell's."""
    from umi_aug.recon.pipeline import first_close_index

    d = assets.demos[0]
    end = first_close_index(d.gripper_width) or len(d.gripper_width)
    c = d.T_world_cam[:end, :3, 3]
    return 0.5 * inp_radius * max(0.5, float(np.linalg.norm(c - c.mean(0), axis=1).max()))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--session", default=None, help="synthetic session folder (default: made in <work>/session)")
    ap.add_argument("--work", default="/tmp/umi_aug_far_views", help="stage caches and outputs")
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--thetas", nargs="+", type=float, default=[0, 10, 20, 30, 40, 50], help="degrees")
    ap.add_argument("--azimuths", type=int, default=8)
    ap.add_argument("--iterations", type=int, default=None, help="3DGS steps (default: each input kind's)")
    ap.add_argument("--seed", type=int, default=0,
                    help="root seed of the scenes (AugmentConfig.seed); one 3DGS seed moves a θ's PSNR by tenths")
    args = ap.parse_args()

    from umi_aug.augment.dataset_source import DatasetInput
    from umi_aug.camera.kb import unproject
    from umi_aug.io_utils import atomic_write_text
    from umi_aug.camera.umi_image import umi_policy_image
    from umi_aug.recon.session_io import load_session
    from umi_aug.sim.fisheye_renderer import FisheyeRenderer
    from umi_aug.sim.gl import import_mujoco
    from umi_aug.sim.raster import RasterOptions
    from umi_aug.sim.scene import SCENE_FAR, SCENE_NEAR
    from umi_aug.sim.session import make_session
    from umi_aug.sim.tabletop_state import TabletopState

    work = Path(args.work)
    session = Path(args.session) if args.session else work / "session"
    if not (session / "dataset.zarr.zip").exists():
        print(f"# making the synthetic session {session}")
        make_session(session)
    gt_dir = session / "ground_truth"
    demo0 = sorted(p.name for p in gt_dir.iterdir() if (p / "trajectory.npz").is_file() and p.name != "mapping")[0]
    gt_traj = np.load(gt_dir / demo0 / "trajectory.npz")
    T_ref, T_mug0, w0 = gt_traj["T_world_cam"][0], gt_traj["T_world_mug"][0], float(gt_traj["gripper_width"][0])

    session_intrinsics = load_session(session).intrinsics
    mujoco = import_mujoco()
    model = mujoco.MjModel.from_xml_path(str(gt_dir / "scene" / "scene.xml"))
    state = TabletopState(model)
    rows, sheet = [], {}
    for setting in args.settings:
        name = setting.split(" (")[0].replace(" ", "_").replace(",", "").replace("+", "and")
        assets, secs = build(setting, session, work / name, args.iterations, args.seed)
        S = assets.cfg.image_size
        # the dataset path's camera poses are the zarr's TCP poses through T_cam_tcp: they must be the simulator's
        err = float(np.abs(assets.demos[0].T_world_cam[0] - T_ref).max())
        if err > 1e-4:
            raise SystemExit(f"error: {setting}: the input's first camera pose differs from the ground truth by {err}")
        uu, vv = np.meshgrid(np.arange(S), np.arange(S))
        _, in_lens = unproject(np.stack([uu.ravel(), vv.ravel()], -1).astype(np.float64), assets.policy_intrinsics)
        valid = in_lens.reshape(S, S) & ~assets.gripper_mask
        shell = None if setting in ("one demo, no shell", "scan + demos") else \
            shell_distance_m(assets, DatasetInput.background_radius)
        intr = session_intrinsics  # the ground truth is rendered as the session's frames were (its raw camera)
        with FisheyeRenderer(model, intr, options=RasterOptions(near=SCENE_NEAR, far=SCENE_FAR)) as renderer:
            for theta in args.thetas:
                poses = cone_ring_poses(T_ref, assets.cfg.cone_radius_m, math.radians(theta), args.azimuths)
                ps, holes = [], []
                for k, T in enumerate(poses):
                    state.set(T, w0, T_mug0)
                    gt = umi_policy_image(renderer.render(T, state.data, rgb=True, depth=False).rgb, intr, S)
                    img, seen = render_3dgs(assets, T, shell)
                    ps.append(masked_psnr(img, gt, valid))
                    holes.append(float(np.mean(seen[valid] < 0.5)))
                    if k == 0:
                        sheet.setdefault(theta, {"ground truth": gt})[setting] = img
                rows.append({"setting": setting, "theta_deg": theta, "n": len(ps),
                             "psnr_db_median": float(np.median(ps)),
                             "psnr_db_min": float(np.min(ps)), "psnr_db_max": float(np.max(ps)),
                             "uncovered_median": float(np.median(holes)), "build_s": round(secs, 1)})
                r = rows[-1]
                print(f"{setting:22s} θ={theta:4.0f}°  PSNR median {r['psnr_db_median']:6.2f} dB "
                      f"[{r['psnr_db_min']:.2f}, {r['psnr_db_max']:.2f}]  "
                      f"uncovered {100 * r['uncovered_median']:5.1f} %",
                      flush=True)
    print("\n| setting | " + " | ".join(f"θ = {t:.0f}°" for t in args.thetas) + " |")
    print("|---|" + "---|" * len(args.thetas))
    for setting in args.settings:
        cells = [r for r in rows if r["setting"] == setting]
        print(f"| {setting} | " + " | ".join(f"{r['psnr_db_median']:.2f} dB ({100 * r['uncovered_median']:.0f} %)"
                                             for r in cells) + " |")
    out = work / "far_views.json"
    atomic_write_text(out, json.dumps({"session": str(session), "seed": args.seed, "rows": rows}, indent=2) + "\n")
    write_sheet(sheet, ["ground truth", *args.settings], work / "far_views.png")
    print(f"\n{out}\n{work / 'far_views.png'}")
    return 0


def write_sheet(sheet: dict, columns: list[str], path: Path) -> None:
    """Rows θ, columns ground truth and each setting (the first azimuth), labelled."""
    import cv2

    from umi_aug.io_utils import atomic_write_bytes

    rows = []
    for theta, imgs in sheet.items():
        tiles = []
        for c in columns:
            im = imgs[c].copy()
            cv2.putText(im, f"{c}  {theta:.0f} deg", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 0), 1,
                        cv2.LINE_AA)
            tiles.append(im)
        rows.append(np.concatenate(tiles, axis=1))
    ok, png = cv2.imencode(".png", cv2.cvtColor(np.concatenate(rows, axis=0), cv2.COLOR_RGB2BGR))
    if not ok:
        raise SystemExit(f"error: {path}: PNG encoding failed")
    atomic_write_bytes(path, png.tobytes())


if __name__ == "__main__":
    raise SystemExit(main())
