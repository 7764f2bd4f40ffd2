"""Named constants of the trajectory stage, all in one place (metres, radians, seconds unless stated).

Defaults of the config dataclasses (:mod:`umi_aug.traj.config`) are taken from here, so a value is changed in one
place. Why each value:

* Collision: ``MARGIN_M`` is the clearance every emitted gripper sphere keeps from the scene and the inflated
  obstacle; the optimiser aims at ``MARGIN_M + COLLISION_BUFFER_M`` so that the hinge penalty's small residual
  penetration (≈ force balance / weight) never eats into the validated margin. ``HINGE_ETA_M`` smooths the hinge
  onset (spheres start to feel the penalty up to η before the required clearance): with a plain hinge the
  obstacle problems needed ~25 (p90 ~55) LM iterations instead of ~9 (p90 ~25).
* Weights: every term is a mean square in m² (or m²-equivalent), so W_c = 1e4 makes 1 cm of penetration of one
  sphere at one waypoint cost as much as 1e4/T·1e-4 ≈ 0.016 m², ~10× a typical converged total; W_c = 1e6 is
  stable too (tested) but converges more slowly.
* Solver: Levenberg–Marquardt with Nielsen's damping update and the smoothness metric as damping matrix;
  ``FTOL`` is the relative cost decrease and ``XTOL`` the largest waypoint step (m or rad) below which a trajectory
  counts as converged (only for nearly undamped steps), plus a stagnation window over accepted steps.
* Timing: bounds on the augmented (pre-contact) segment; UMI's own teleop interpolator allows far more
  (2·√3 m/s), these keep the motion human-like. The demo's speed profile is smoothed with a Gaussian of
  ``SPEED_SMOOTHING_S`` before it is reused (hand tremor would otherwise dominate the acceleration bound).
"""

from __future__ import annotations

import math

# ---------------------------------------------------------------------------------------------------- problem
N_WAYPOINTS: int = 64  #: T, waypoints per optimised trajectory (both endpoints included)
MARGIN_M: float = 0.015  #: required clearance of every gripper sphere (scene SDF and inflated obstacle)
COLLISION_BUFFER_M: float = 0.003  #: extra clearance the optimiser aims at beyond MARGIN_M
HINGE_ETA_M: float = 0.01  #: half-width of the smoothed collision-hinge onset (0 = plain squared hinge)
CONTACT_TAIL_FRACTION: float = 0.15  #: last fraction of the path where the demo's own clearance may relax the margin
OBSTACLE_INFLATION_M: float = 0.01  #: default inflation of an added obstacle's convex hull (plane offset)
DEGENERATE_TOL: float = 1e-9  #: start ≈ goal below this combined distance (m + rad) → constant trajectory

# ------------------------------------------------------------------------------------------------- objective
FUNNEL_WEIGHT: float = 1.0  #: L_funnel (weighted mean squared distance to the demo, m²)
FUNNEL_W_MIN: float = 0.02  #: w_min of w_k = w_min + (w_max − w_min)(k/T)³ (before normalising to sum 1)
FUNNEL_W_MAX: float = 1.0
COLLISION_WEIGHT: float = 1e4  #: L_collision (mean over waypoints of Σ_spheres hinge², m²)
RENDER_WEIGHT: float = 0.05  #: L_render (mean truncated squared SE(3) distance to the K nearest views, m²)
RENDER_RADIUS_M: float = 0.15  #: ρ: neighbourhood radius of the render prior in the combined metric
RENDER_ROT_SCALE_M: float = 0.1  #: ℓ: metres per radian in the render prior's SE(3) distance
RENDER_K: int = 4  #: K nearest training views per waypoint
RENDER_CANDIDATES: int = 16  #: position-nearest candidates searched for the K nearest in the combined metric
RENDER_MAX_VIEWS: int = 2048  #: training views kept (evenly strided subsample beyond this)
RENDER_MIN_SEPARATION_M: float = 0.01  #: views closer than this (combined metric) to a kept view are dropped
ACC_WEIGHT: float = 2e-3  #: ∫‖d²t/ds²‖² ds over s ∈ [0, 1] (m²)
JERK_WEIGHT: float = 2e-5  #: ∫‖d³t/ds³‖² ds
ROT_ACC_WEIGHT: float = 2e-4  #: same in the rotation tangent space (rad²)
ROT_JERK_WEIGHT: float = 2e-6

#: Conservative scene-SDF grid (``umi_aug.traj.scene_grid``) used to skip SDF queries that cannot matter (RRT*
#: edges, far-away gripper spheres): cell size, padding around the demo / views / obstacle, node budget (the cell
#: grows when the box would need more nodes). Metres.
SCENE_GRID_STEP_M: float = 0.02
SCENE_GRID_PAD_M: float = 0.35
SCENE_GRID_MAX_POINTS: int = 300_000

# ---------------------------------------------------------------------------------------------------- solver
MAX_ITERATIONS: int = 60
FTOL: float = 1e-5
XTOL: float = 1e-5
GTOL: float = 1e-10
LM_LAMBDA_INIT: float = 1e-6  #: Levenberg damping λ·I (variables in m and rad)
LM_LAMBDA_MAX: float = 1e8
LM_CONVERGED_LAMBDA: float = 1e-2  #: FTOL/XTOL only count for steps damped by less than λ = this (× smoothness metric)
LM_STAGNATION_WINDOW: int = 5  #: converged when the cost fell by < FTOL (relative) over this many iterations
LM_MIN_GAIN: float = 1e-4  #: accept a step when actual/predicted decrease exceeds this
BATCH_SIZE: int = 64

# ------------------------------------------------------------------------------------------------------- RRT*
RRT_MAX_ITERATIONS: int = 400
RRT_EXTRA_ITERATIONS: int = 30  #: iterations after the first solution (RRT* improvement)
RRT_STEP_M: float = 0.1
RRT_GOAL_BIAS: float = 0.2
RRT_REWIRE_RADIUS_M: float = 0.2
RRT_CLEARANCE_M: float = 0.02  #: extra clearance of the planned gripper spheres beyond the margin
RRT_BOUNDS_PAD_M: float = 0.2  #: sampling box = bounding box of start, goal and hull, padded by this
RRT_SHORTCUT_PASSES: int = 25
RRT_SEGMENT_CHECK_STEP_M: float = 0.02  #: sampling step of the gripper pose along RRT edges
#: Neighbours considered for choose-parent / rewiring (the nearest ones within the rewire radius).
RRT_MAX_NEIGHBOURS: int = 12
#: Paths up to this many nodes are shortcut by checking all node pairs at once.
SHORTCUT_ALL_PAIRS_MAX: int = 24
#: Spacing of the densified RRT* path before the final arc-length resampling (metres).
RRT_DENSIFY_M: float = 0.005
#: Near an endpoint the required hull clearance is relaxed to the endpoint's own: flat within this radius of it
#: (metres of camera motion), then growing by RRT_RELAX_SLOPE per metre up to margin + rrt.clearance.
RRT_RELAX_RADIUS_M: float = 0.05
RRT_RELAX_SLOPE: float = 0.5

# ------------------------------------------------------------------------------------------------------ timing
MAX_SPEED_MPS: float = 0.6
MAX_ACCEL_MPS2: float = 3.0
MAX_ANG_SPEED_RADPS: float = 3.0
MAX_ANG_ACCEL_RADPS2: float = 20.0
SPEED_SMOOTHING_S: float = 0.1
MIN_MEAN_PROGRESS_SPEED: float = 0.05  #: m/s (progress metric); floor of the demo-derived mean speed
TIMING_ROT_SCALE_M: float = 0.1  #: metres per radian in the progress (arc-length) metric used for timing
BLEND_DURATION_S: float = 0.4  #: window before the splice over which the velocity mismatch is blended out
MAX_TIMING_STRETCH_STEPS: int = 12
TIMING_STRETCH_FACTOR: float = 1.15
UMI_FPS: float = 60000.0 / 1001.0  #: GoPro frame rate when a demo gives no usable timestamps

# ------------------------------------------------------------------------------------------------------ driver
OVERSAMPLE: float = 1.25  #: problems sampled per missing trajectory in each generate() round
MAX_ROUNDS: int = 8

DEG: float = math.pi / 180.0
