"""Named constants of the scene-reconstruction stage (metres, radians, pixels unless stated), in one place.

Why each value:

* SfM: small video frames (UMI SLAM runs at 960x720, tests at 320x240) carry a few hundred to a few thousand SIFT
  features; sequential matching against ``SEQUENTIAL_OVERLAP`` neighbours plus a sparse all-pairs "loop" grid every
  ``LOOP_STRIDE`` frames stands in for COLMAP's vocabulary-tree loop detection (its vocabulary file would have to be
  downloaded). A reconstruction that registers fewer than ``MIN_REGISTERED_FRACTION`` of the frames is refused.
* Alignment: the Sim(3) residual is the RMS camera-centre distance after alignment; above
  ``MAX_ALIGN_RESIDUAL_M`` the scan and the demo poses disagree and the reconstruction is refused.
* Clean-up: open3d statistical outlier removal with ``SOR_NEIGHBOURS`` / ``SOR_STD_RATIO``; voxel down-sampling.
* SDF: the grid holds at most ``SDF_MAX_VOXELS`` nodes; the voxel size is the cube root of region volume / that
  count, clamped to [``SDF_MIN_VOXEL_M``, ``SDF_MAX_VOXEL_M``]. The sign of a node is the weighted vote of the
  oriented normals of its ``SDF_SIGN_NEIGHBOURS`` nearest cloud points.
* Contact: a gripper sphere "touches" the scene when its clearance is below ``CONTACT_THRESHOLD_M``; a grasp
  onset is a width drop of more than ``GRASP_CLOSE_DROP_M`` within ``GRASP_WINDOW_S`` after proximity.
"""

from __future__ import annotations

# ----------------------------------------------------------------------------------------------------- SfM
SEQUENTIAL_OVERLAP: int = 6  #: each frame is matched with this many following frames of its sequence
LOOP_STRIDE: int = 6  #: every LOOP_STRIDE-th frame of all sequences is matched with every other such frame
SIFT_MAX_FEATURES: int = 2048
SIFT_PEAK_THRESHOLD: float = 0.004  #: lower than COLMAP's 0.0067: small, slightly blurred fisheye frames
MIN_REGISTERED_FRACTION: float = 0.5
MIN_REGISTERED_IMAGES: int = 5
MIN_POINTS3D: int = 100
MASK_DILATE_PX: int = 3  #: grow the gripper mask by this much (feature support regions straddle its edge)
IMAGE_CIRCLE_MARGIN: float = 0.97  #: keep pixels inside this fraction of the valid fisheye image circle
#: COLMAP's pixel convention puts the top-left pixel's CENTRE at (0.5, 0.5); OpenCV (ours) at (0, 0).
COLMAP_PIXEL_OFFSET: float = 0.5

# ------------------------------------------------------------------------------------------------ alignment
MAX_ALIGN_RESIDUAL_M: float = 0.05
MIN_ALIGN_SPREAD_M: float = 0.02  #: RMS spread of the camera centres below this: scale is unobservable

# ------------------------------------------------------------------------------------------------- clean-up
SOR_NEIGHBOURS: int = 16
SOR_STD_RATIO: float = 2.0
ROR_RADIUS_M: float = 0.05  #: radius outlier removal: isolated points (gripper leaks, bad tracks) float in free space
ROR_MIN_POINTS: int = 3
MIN_TRACK_LENGTH: int = 3  #: SfM points seen by fewer images are dropped before clean-up
MAX_POINT_ERROR_PX: float = 2.0  #: SfM points with a larger mean reprojection error are dropped
CLOUD_VOXEL_M: float = 0.003
MIN_CLOUD_POINTS: int = 50
NORMAL_NEIGHBOURS: int = 16

# ------------------------------------------------------------------------------------------------------ SDF
SDF_MAX_VOXELS: int = 2_000_000
SDF_MIN_VOXEL_M: float = 0.004
SDF_MAX_VOXEL_M: float = 0.03
SDF_SIGN_NEIGHBOURS: int = 8
SDF_QUERY_CHUNK: int = 1 << 18  #: nodes/queries per KD-tree batch (bounds memory)
#: Reach of the gripper spheres beyond the camera centre (fingertips at z ≈ 0.226 m + radius) plus slack.
GRIPPER_REACH_M: float = 0.30
REGION_PAD_M: float = 0.05

# -------------------------------------------------------------------------------------------------- contact
CONTACT_THRESHOLD_M: float = 0.03
GRASP_CLOSE_DROP_M: float = 0.002
GRASP_WINDOW_S: float = 1.5
GRASP_ONSET_TOL_M: float = 1e-6  #: width changes smaller than this count as "not closing" when walking back

# ------------------------------------------------------------------------------------------------ obstacles
OBSTACLE_SURFACE_POINTS: int = 2000
OBSTACLE_INFLATION_M: float = 0.01
OBSTACLE_CLEARANCE_M: float = 0.015  #: gripper spheres at the pre-contact pose keep this from the inflated hull
OBSTACLE_MAX_TRIES: int = 400
