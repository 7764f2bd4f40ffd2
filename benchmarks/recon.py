"""Reconstruction stage benchmark on a synthetic session: error against run time.

    python benchmarks/recon.py [--session DIR] [--scan-frames 120] [--out /tmp/recon_bench]

Builds a synthetic session (unless --session is given), then for several SfM settings runs the whole stage
(:func:`umi_aug.recon.reconstruct_session`) and prints, against the session's ground truth: registered frames,
reprojection error, Sim(3) residual, camera pose error, point-cloud accuracy / completeness / Chamfer (mm, inside the
table-top ROI), contact-frame error and SfM time; then SDF voxel size vs error vs build time vs queries/s.
Results are also written to ``<out>/recon_bench.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "2")


def _gt_cloud(session: Path):
    from umi_aug.recon.cloud import SceneCloud

    z = np.load(session / "ground_truth" / "scene" / "scene_points.npz")
    return SceneCloud(z["points"].astype(float), z["colors"], z["normals"].astype(float))


ROI = (np.array([-0.6, -0.2, -0.01]), np.array([0.6, 0.6, 0.3]))  # the table top and the objects on it


def run_setting(session: Path, out: Path, name: str, sfm_kwargs: dict, gt) -> dict:
    from umi_aug.recon import ReconConfig, SfmConfig, reconstruct_session
    from umi_aug.recon.evaluate import cloud_metrics, pose_metrics

    t = time.perf_counter()
    o = reconstruct_session(session, out / name, ReconConfig(sfm=SfmConfig(**sfm_kwargs)))
    total = time.perf_counter() - t
    # pose error of the registered frames against the ground-truth trajectories
    cache = {}
    T_gt = []
    for seq, i in o.frame_seq:
        if seq not in cache:
            cache[seq] = np.load(session / "ground_truth" / seq / "trajectory.npz")["T_world_cam"]
        T_gt.append(cache[seq][i])
    pm = pose_metrics(o.sfm.T_world_cam, np.array(T_gt), o.sfm.registered)
    cm = cloud_metrics(o.cloud.points, gt.points, gt.normals, ROI)
    cerr = []
    for c in o.contacts:
        g = json.loads((session / "ground_truth" / c.name / "events.json").read_text())["contact_frame"]
        cerr.append(math.inf if c.contact_index is None else c.contact_index - g)
    return {"setting": name, **sfm_kwargs, "frames": len(o.sfm.names), "registered": int(o.sfm.registered.sum()),
            "reproj_px": o.sfm.mean_reproj_error_px, "sim3_residual_mm": 1000 * o.sim3.residual_rms_m,
            **pm, **cm, "contact_err_frames": cerr, "sfm_s": o.timings_s["sfm"], "total_s": total,
            "cloud_points": len(o.cloud), "_out": o}


def sdf_sweep(o, gt, voxels) -> list[dict]:
    from umi_aug.recon.evaluate import sdf_metrics
    from umi_aug.recon.sdf_grid import build_scene_sdf

    lo, hi = o.sdf.bounds
    rng = np.random.default_rng(0)
    q = rng.uniform(np.maximum(lo, ROI[0]), np.minimum(hi, ROI[1]), (5000, 3))
    keep = (o.sfm.track_length >= 3) & (o.sfm.errors_px <= 2.0)
    ok = o.sfm.registered[o.sfm.obs_image] & keep[o.sfm.obs_point]
    rays = (o.sfm.T_world_cam[o.sfm.obs_image[ok], :3, 3], o.sfm.points[o.sfm.obs_point[ok]])
    rows = []
    for v in voxels:
        t = time.perf_counter()
        sdf = build_scene_sdf(o.cloud, lo, hi, voxel=v, max_voxels=10_000_000, rays=rays)
        build = time.perf_counter() - t
        big = rng.uniform(lo, hi, (500_000, 3))
        t = time.perf_counter()
        sdf.distance_and_gradient(big)
        qps = len(big) / (time.perf_counter() - t)
        rows.append({"voxel_mm": 1000 * v, "nodes": int(np.prod(sdf.shape)), "build_s": build,
                     "Mqueries_per_s": qps / 1e6, **sdf_metrics(sdf, gt, q, sdf.voxel)})
    return rows


def _table(rows: list[dict], cols: list[tuple[str, str]]) -> str:
    head = " | ".join(h for h, _ in cols)
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(" | ".join(f.format(r[k]) if not isinstance(r[k], list) else str(r[k])
                                for (k, f) in ((c[0], c[1]) for c in cols)))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", type=Path, default=None)
    ap.add_argument("--scan-frames", type=int, default=120)
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "recon_bench")
    ap.add_argument("--quick", action="store_true", help="two SfM settings, two voxel sizes")
    a = ap.parse_args(argv)
    from umi_aug.runtime import configure_threads

    configure_threads()
    a.out.mkdir(parents=True, exist_ok=True)
    session = a.session
    if session is None:
        from umi_aug.sim.session import make_session

        session = a.out / f"session_{a.scan_frames}"
        if not (session / "session.json").exists():
            t = time.perf_counter()
            make_session(session, 0, n_demos=1, scan_frames=a.scan_frames, benchmark_frames=0, progress=False,
                         overwrite=True)
            print(f"session rendered in {time.perf_counter() - t:.0f} s: {session}")
    gt = _gt_cloud(session)
    settings = [
        ("known_poses/2048", {"mode": "known_poses", "max_num_features": 2048}),
        ("full/2048", {"mode": "full", "max_num_features": 2048}),
        ("full/512", {"mode": "full", "max_num_features": 512}),
        ("full/2048/half-res", {"mode": "full", "max_num_features": 2048, "max_image_size": 160}),
    ]
    if a.quick:
        settings = settings[:2]
    rows = []
    for name, kw in settings:
        try:
            rows.append(run_setting(session, a.out, name.replace("/", "_"), kw, gt) | {"setting": name})
        except Exception as exc:  # a failed setting is a result too
            print(f"{name}: FAILED: {exc}", file=sys.stderr)
    cols = [("setting", "{}"), ("frames", "{}"), ("registered", "{}"), ("reproj_px", "{:.2f}"),
            ("sim3_residual_mm", "{:.2f}"), ("trans_mean_cm", "{:.2f}"), ("rot_mean_deg", "{:.2f}"),
            ("accuracy_median_mm", "{:.1f}"), ("chamfer_mm", "{:.1f}"), ("within_1cm_pct", "{:.0f}"),
            ("within_2cm_pct", "{:.0f}"), ("contact_err_frames", "{}"), ("sfm_s", "{:.1f}"), ("total_s", "{:.1f}")]
    print("\nSfM settings vs ground truth (cloud metrics inside the table-top ROI; accuracy point-to-plane):")
    print(_table(rows, cols))
    sweep = []
    if rows:
        voxels = [0.01, 0.02] if a.quick else [0.0075, 0.01, 0.015, 0.02]
        sweep = sdf_sweep(rows[0]["_out"], gt, voxels)
        print(f"\nSDF voxel size vs error vs time (cloud of '{rows[0]['setting']}', queries in the ROI; GT = SDF of "
              f"the ground-truth cloud):")
        print(_table(sweep, [("voxel_mm", "{:.1f}"), ("nodes", "{}"), ("build_s", "{:.2f}"),
                             ("Mqueries_per_s", "{:.1f}"), ("median_abs_err_mm", "{:.1f}"),
                             ("free_median_err_mm", "{:.1f}"), ("false_free_pct", "{:.2f}"),
                             ("false_occupied_pct", "{:.2f}"), ("lower_bound_pct", "{:.1f}")]))
    res = {"session": str(session), "sfm": [{k: v for k, v in r.items() if k != "_out"} for r in rows], "sdf": sweep}
    (a.out / "recon_bench.json").write_text(json.dumps(res, indent=2, default=float) + "\n")
    return 0 if rows else 1


if __name__ == "__main__":
    sys.exit(main())
