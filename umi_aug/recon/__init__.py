"""Scene reconstruction stage (paper §3.1, §3.2 obstacles): SfM on fisheye frames, metric Sim(3) alignment,
point-cloud clean-up, scene SDF over the reachable region, contact detection, obstacle assets.

World frame = UMI table-tag frame (z up), metres; camera poses ``T_world_cam`` with OpenCV axes. Errors raise
:class:`umi_aug.errors.ReconError`. Needs the ``recon`` extra (pycolmap, open3d-cpu, trimesh); importing this package
imports none of them (they load when used).
"""

from umi_aug.recon.align import Sim3, align_sfm_to_poses, umeyama
from umi_aug.recon.cloud import SceneCloud, clean_cloud, read_ply, write_ply
from umi_aug.recon.contact import ContactResult, detect_contact, detect_contacts, gripper_clearance
from umi_aug.recon.obstacles import (
    PROCEDURAL_ASSETS,
    ObstacleAsset,
    ObstaclePlacement,
    load_mesh_asset,
    obstacle_hull_sdf,
    packaged_mesh_assets,
    procedural_asset,
    sample_obstacle_placement,
)
from umi_aug.recon.pipeline import ReconConfig, ReconOutput, first_close_index, reconstruct_session
from umi_aug.recon.sdf_grid import VoxelSDF, build_scene_sdf, choose_voxel_size, reachable_region
from umi_aug.recon.session_io import ImageSequence, SessionData, load_session
from umi_aug.recon.sfm import SfmConfig, SfmResult, colmap_camera_params, feature_mask, run_sfm

__all__ = [
    "Sim3", "umeyama", "align_sfm_to_poses",
    "SceneCloud", "clean_cloud", "read_ply", "write_ply",
    "ContactResult", "detect_contact", "detect_contacts", "gripper_clearance",
    "PROCEDURAL_ASSETS", "ObstacleAsset", "ObstaclePlacement", "load_mesh_asset", "obstacle_hull_sdf",
    "packaged_mesh_assets", "procedural_asset", "sample_obstacle_placement",
    "ReconConfig", "ReconOutput", "first_close_index", "reconstruct_session",
    "VoxelSDF", "build_scene_sdf", "choose_voxel_size", "reachable_region",
    "ImageSequence", "SessionData", "load_session",
    "SfmConfig", "SfmResult", "colmap_camera_params", "feature_mask", "run_sfm",
]
