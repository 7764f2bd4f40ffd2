"""The stage end to end on a synthetic session, measured against its ground truth."""

import json
import math

import numpy as np
import pytest

from umi_aug.errors import ReconError

pytest.importorskip("pycolmap")
pytest.importorskip("open3d")


def _gt(session):
    from umi_aug.recon.cloud import SceneCloud

    z = np.load(session / "ground_truth" / "scene" / "scene_points.npz")
    return SceneCloud(z["points"].astype(float), z["colors"], z["normals"].astype(float))


ROI = (np.array([-0.6, -0.2, -0.01]), np.array([0.6, 0.6, 0.3]))  # the table top and what stands on it


def test_known_poses_pipeline_against_ground_truth(sim_session, recon_known):
    from umi_aug.recon import read_ply, VoxelSDF
    from umi_aug.recon.evaluate import cloud_metrics, sdf_metrics

    o = recon_known
    assert o.sfm.registered_fraction >= 0.9 and o.sfm.mean_reproj_error_px < 1.0
    assert o.sim3.s == 1.0
    cm = cloud_metrics(o.cloud.points, _gt(sim_session).points, _gt(sim_session).normals, ROI)
    print("\ncloud vs GT:", {k: round(v, 2) for k, v in cm.items()})
    assert cm["accuracy_median_mm"] < 5.0 and cm["within_2cm_pct"] > 20.0
    # files
    back = read_ply(o.paths["cloud"])
    assert len(back) == len(o.cloud)
    sdf = VoxelSDF.load(o.paths["sdf"])
    rep = json.loads(open(o.paths["report"]).read())
    assert rep["sfm"]["registered"] == int(o.sfm.registered.sum())
    # SDF vs the ground-truth cloud's SDF above the table
    rng = np.random.default_rng(0)
    lo, hi = sdf.bounds
    q = rng.uniform(np.maximum(lo, ROI[0]), np.minimum(hi, ROI[1]), (3000, 3))
    sm = sdf_metrics(sdf, _gt(sim_session), q, sdf.voxel)
    print("SDF vs GT:", {k: round(v, 2) for k, v in sm.items()})
    assert sm["false_free_pct"] < 2.0


def test_contact_within_two_frames_of_ground_truth(sim_session, recon_known):
    for c in recon_known.contacts:
        gt = json.loads((sim_session / "ground_truth" / c.name / "events.json").read_text())["contact_frame"]
        print(f"\n{c.name}: detected {c.contact_index} (proximity {c.proximity_index}), ground truth {gt}")
        assert c.contact_index is not None and abs(c.contact_index - gt) <= 2
    assert recon_known.contacts


def test_session_with_wrong_intrinsics_raises(sim_session):
    from umi_aug.camera import gopro_intrinsics_2_7k
    from umi_aug.recon import load_session

    with pytest.raises(ReconError, match="2704x2028"):
        load_session(sim_session, intrinsics=gopro_intrinsics_2_7k())


@pytest.mark.slow
def test_full_sfm_and_sim3_alignment(sim_session, tmp_path):
    from umi_aug.recon import SfmConfig, align_sfm_to_poses, load_session, run_sfm
    from umi_aug.recon.evaluate import pose_metrics

    from umi_aug.recon.session_io import write_frames

    s = load_session(sim_session)
    m = s.mapping
    paths = write_frames(m, range(len(m)), tmp_path / "frames")  # decoded from raw_video.mp4
    names = [f"mapping/{p.name}" for p in paths]
    r = run_sfm(paths, names, s.intrinsics, tmp_path / "w", SfmConfig(mode="full"))
    aligned, sim = align_sfm_to_poses(r, m.T_world_cam, m.valid)
    gt = np.load(sim_session / "ground_truth" / "mapping" / "trajectory.npz")["T_world_cam"]
    pm = pose_metrics(aligned.T_world_cam, gt, aligned.registered)
    print(f"\nfull SfM: {r.registered.sum()}/{len(names)} registered, {len(r.points)} points, "
          f"{r.mean_reproj_error_px:.2f} px, Sim3 residual {sim.residual_rms_m * 1000:.2f} mm, {pm}")
    assert r.registered_fraction >= 0.9
    assert sim.residual_rms_m < 0.01 and pm["rot_mean_deg"] < 1.0 and math.isfinite(sim.s)
