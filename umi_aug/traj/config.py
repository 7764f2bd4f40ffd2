"""Typed configuration of the trajectory stage (frozen dataclasses; defaults from :mod:`.constants`).

Units: metres, radians, seconds. Weights multiply cost terms that are themselves normalised to be independent
of T (see :mod:`umi_aug.traj.objective`), so a weight means the same for T = 32 or T = 128.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from umi_aug.config_check import is_positive
from umi_aug.errors import TrajError
from umi_aug.traj import constants as C

__all__ = ["ObjectiveWeights", "SolverConfig", "RRTConfig", "TimingConfig", "TrajConfig"]


def _check_nonneg(obj, names: tuple[str, ...] | None = None, positive: tuple[str, ...] = ()) -> None:
    for f in fields(obj):
        if names is not None and f.name not in names:
            continue
        v = getattr(obj, f.name)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        if not is_positive(v, allow_zero=f.name not in positive):
            raise TrajError(f"{type(obj).__name__}.{f.name} = {v!r}; expected a finite value "
                            f"{'> 0' if f.name in positive else '>= 0'}")


@dataclass(frozen=True)
class ObjectiveWeights:
    """Weights of the §3.2 objective. ``funnel_w_min/max`` shape the funnel weights (normalised to sum 1)."""

    funnel: float = C.FUNNEL_WEIGHT
    funnel_w_min: float = C.FUNNEL_W_MIN
    funnel_w_max: float = C.FUNNEL_W_MAX
    collision: float = C.COLLISION_WEIGHT
    render: float = C.RENDER_WEIGHT
    acc: float = C.ACC_WEIGHT
    jerk: float = C.JERK_WEIGHT
    rot_acc: float = C.ROT_ACC_WEIGHT
    rot_jerk: float = C.ROT_JERK_WEIGHT

    def __post_init__(self) -> None:
        _check_nonneg(self)
        if not (0.0 <= self.funnel_w_min <= 1.0 and 0.0 <= self.funnel_w_max <= 1.0):
            raise TrajError(f"ObjectiveWeights: funnel_w_min={self.funnel_w_min}, funnel_w_max={self.funnel_w_max}; "
                            f"the paper requires 0 <= w <= 1")
        if self.funnel_w_min + self.funnel_w_max <= 0:
            raise TrajError("ObjectiveWeights: funnel_w_min and funnel_w_max are both 0")


@dataclass(frozen=True)
class SolverConfig:
    """Batched Levenberg–Marquardt settings."""

    max_iterations: int = C.MAX_ITERATIONS
    ftol: float = C.FTOL
    xtol: float = C.XTOL
    gtol: float = C.GTOL
    lambda_init: float = C.LM_LAMBDA_INIT
    lambda_max: float = C.LM_LAMBDA_MAX
    batch_size: int = C.BATCH_SIZE
    #: Emit a trajectory that hit the iteration limit when it is otherwise valid (default: it is a failure).
    accept_iteration_limit: bool = False

    def __post_init__(self) -> None:
        _check_nonneg(self, positive=("max_iterations", "lambda_init", "lambda_max", "batch_size"))


@dataclass(frozen=True)
class RRTConfig:
    """RRT* initial guesses around the inflated obstacle hull (obstacle mode only)."""

    max_iterations: int = C.RRT_MAX_ITERATIONS
    extra_iterations: int = C.RRT_EXTRA_ITERATIONS
    step: float = C.RRT_STEP_M
    goal_bias: float = C.RRT_GOAL_BIAS
    rewire_radius: float = C.RRT_REWIRE_RADIUS_M
    clearance: float = C.RRT_CLEARANCE_M
    bounds_pad: float = C.RRT_BOUNDS_PAD_M
    shortcut_passes: int = C.RRT_SHORTCUT_PASSES
    segment_check_step: float = C.RRT_SEGMENT_CHECK_STEP_M

    def __post_init__(self) -> None:
        _check_nonneg(self, positive=("max_iterations", "step", "rewire_radius", "segment_check_step"))
        if not 0.0 <= self.goal_bias <= 1.0:
            raise TrajError(f"RRTConfig.goal_bias = {self.goal_bias}; expected [0, 1]")


@dataclass(frozen=True)
class TimingConfig:
    """Time parameterisation of the augmented segment and the splice."""

    max_speed: float = C.MAX_SPEED_MPS
    max_accel: float = C.MAX_ACCEL_MPS2
    max_ang_speed: float = C.MAX_ANG_SPEED_RADPS
    max_ang_accel: float = C.MAX_ANG_ACCEL_RADPS2
    speed_smoothing: float = C.SPEED_SMOOTHING_S
    rot_scale: float = C.TIMING_ROT_SCALE_M
    blend_duration: float = C.BLEND_DURATION_S
    max_stretch_steps: int = C.MAX_TIMING_STRETCH_STEPS
    stretch_factor: float = C.TIMING_STRETCH_FACTOR

    def __post_init__(self) -> None:
        _check_nonneg(self, positive=("max_speed", "max_accel", "max_ang_speed", "max_ang_accel", "rot_scale"))
        if self.stretch_factor <= 1.0:
            raise TrajError(f"TimingConfig.stretch_factor = {self.stretch_factor}; expected > 1")


@dataclass(frozen=True)
class TrajConfig:
    """Everything the trajectory stage needs besides the demo and the scene."""

    n_waypoints: int = C.N_WAYPOINTS
    margin: float = C.MARGIN_M
    collision_buffer: float = C.COLLISION_BUFFER_M
    hinge_eta: float = C.HINGE_ETA_M
    contact_tail_fraction: float = C.CONTACT_TAIL_FRACTION
    render_radius: float = C.RENDER_RADIUS_M
    render_rot_scale: float = C.RENDER_ROT_SCALE_M
    render_k: int = C.RENDER_K
    render_candidates: int = C.RENDER_CANDIDATES
    render_max_views: int = C.RENDER_MAX_VIEWS
    render_min_separation: float = C.RENDER_MIN_SEPARATION_M
    weights: ObjectiveWeights = field(default_factory=ObjectiveWeights)
    solver: SolverConfig = field(default_factory=SolverConfig)
    rrt: RRTConfig = field(default_factory=RRTConfig)
    timing: TimingConfig = field(default_factory=TimingConfig)

    def __post_init__(self) -> None:
        _check_nonneg(self, positive=("render_radius", "render_rot_scale", "render_k", "render_candidates",
                                      "render_max_views"))
        if isinstance(self.n_waypoints, bool) or not isinstance(self.n_waypoints, int) or self.n_waypoints < 4:
            raise TrajError(f"TrajConfig.n_waypoints = {self.n_waypoints!r}; expected an int >= 4")
        if not 0.0 <= self.contact_tail_fraction < 1.0:
            raise TrajError(f"TrajConfig.contact_tail_fraction = {self.contact_tail_fraction}; expected [0, 1)")
        if self.render_candidates < self.render_k:
            raise TrajError(f"TrajConfig.render_candidates ({self.render_candidates}) < render_k ({self.render_k})")
