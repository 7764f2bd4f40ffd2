"""Typed settings of the augmentation pipeline (frozen dataclasses; Hydra/OmegaConf structured-config friendly).

Units: metres, seconds; angles in degrees only where the name says ``*_deg``. Every random choice derives from
``AugmentConfig.seed`` (see :func:`umi_aug.augment.plan.episode_seed`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from typing import Any

from umi_aug.augment.mirrors import MIRROR_MODES
from umi_aug.augment.splat_defaults import (DATASET_SPLAT_EVALUATION, DATASET_SPLAT_ITERATIONS,
                                            DATASET_SPLAT_MAX_GAUSSIANS, DATASET_SPLAT_SCHEDULE)
from umi_aug.errors import AugmentError
from umi_aug.recon.pipeline import ReconConfig
from umi_aug.recon.sfm import SfmConfig
from umi_aug.traj.config import TrajConfig

__all__ = ["MODES", "SESSION_SPLAT_ITERATIONS", "SESSION_SPLAT_MAX_GAUSSIANS", "SESSION_SPLAT_SCALE_REG",
           "DATASET_SPLAT_SCALE_REG", "DATASET_SPLAT_COARSE_DOWNSCALE", "DATASET_SPLAT_ITERATIONS",
           "DATASET_SPLAT_MAX_GAUSSIANS", "DATASET_SPLAT_SCHEDULE", "DATASET_SPLAT_EVALUATION", "dataset_splat_stage",
           "TRAINER_SCALE_REG",
           "DEFAULT_RENDER_MIN_TRANSMITTANCE", "splat_key",
           "SplatStageConfig", "ObstacleConfig", "OverlayConfig", "AugmentConfig", "config_hash", "jsonable",
           "modes_of"]

#: Augmentation modes of one episode (``both`` in :class:`AugmentConfig` runs each of them).
MODES: tuple[str, ...] = ("freespace", "obstacle")
#: 3DGS of a session's scene (scan + demos): the knee of the render quality/speed trade-off on the synthetic session
#: (``benchmarks/render_tradeoff.py``, ``docs/real_scale.md`` section 4): 1,500 steps, 25k Gaussians, scale
#: regulariser 1.0 — 982 episodes/h at 26.8 dB against the ground truth, where the earlier 4,000 steps / 60k /
#: 0.01 gave 400/h at 28.4 dB (4,000 / 60k / 1.0: 695/h at 28.1 dB).
SESSION_SPLAT_ITERATIONS: int = 1500
SESSION_SPLAT_MAX_GAUSSIANS: int = 25_000
SESSION_SPLAT_SCALE_REG: float = 1.0
#: :attr:`SplatStageConfig.scale_reg` of a plain dataset's scenes (a demo's own frames): the trainer's default, as
#: before — 1.0 was chosen on the synthetic session; on the real episode see ``docs/real_scale.md`` section 4.
DATASET_SPLAT_SCALE_REG: float = 0.01
#: :attr:`SplatStageConfig.coarse_downscale` of a plain dataset's scenes: the first half of the steps at half size.
#: On the real episode 1,200 such steps reach 27.0 dB held-out in 12 % less time than 1,200 full-size ones (26.97 dB)
#: (``docs/real_scale.md`` section 1b); a session's scenes keep full size (not measured there).
DATASET_SPLAT_COARSE_DOWNSCALE: int = 2
#: :attr:`AugmentConfig.render_min_transmittance`'s default: the renderer's early termination
#: (``umi_aug.splat._constants.TRANSMITTANCE_THRESHOLD``, INRIA 3DGS / gsplat), not imported here (no splat at import)
DEFAULT_RENDER_MIN_TRANSMITTANCE: float = 1e-4
#: ``SplatTrainConfig.scale_reg``'s default: what every scene was trained with before the setting existed.
TRAINER_SCALE_REG: float = 0.01


@dataclass(frozen=True)
class SplatStageConfig:
    """Fisheye 3DGS training of the scene (passed to ``umi_aug.splat.train.SplatTrainConfig``).

    Attributes:
        iterations: optimisation steps; max_gaussians: densification budget; sh_degree: 0..3;
        holdout_every: every n-th frame held out for PSNR/SSIM; image_size: training width (height keeps the
        aspect ratio) or None (the frames' size);
        scale_reg: weight of ``mean(scale / scene_scale)`` in the loss (``SplatTrainConfig.scale_reg``; the
            trainer's own default, 3DGS-MCMC's, is 0.01). Smaller Gaussians cover fewer pixels each, so every new
            frame composites fewer of them: on the synthetic session 1.0 composites 1.9-2.6x fewer per pixel than
            0.01 (export 1.3-1.7x faster) for 0.6-0.7 dB held-out; on the real episode's 600 steps it cost 1.7 dB
            (``docs/real_scale.md`` section 4, issue #34 item 4);
        coarse_downscale: coarse-to-fine training (``SplatTrainConfig.coarse_downscale``): the first half of the
            steps on the frames downscaled by this integer factor; 1 = full size throughout;
        extra: further ``SplatTrainConfig`` fields by name (e.g. learning rates; a ``scale_reg`` here wins).
        ``iterations = 0``: no training, the SfM-initialised Gaussians (smoke runs only).
    """

    iterations: int = SESSION_SPLAT_ITERATIONS
    max_gaussians: int = SESSION_SPLAT_MAX_GAUSSIANS
    sh_degree: int = 3
    holdout_every: int = 8
    image_size: int | None = None
    scale_reg: float = SESSION_SPLAT_SCALE_REG
    coarse_downscale: int = 1
    extra: dict[str, Any] = field(default_factory=dict)

    def train_kwargs(self) -> dict[str, Any]:
        """The ``SplatTrainConfig`` fields this stage sets (``extra`` last: it overrides)."""
        return {"iterations": self.iterations, "max_gaussians": self.max_gaussians, "sh_degree": self.sh_degree,
                "holdout_every": self.holdout_every, "scale_reg": self.scale_reg,
                "coarse_downscale": int(self.coarse_downscale), **dict(self.extra)}


def dataset_splat_stage(**fields: Any) -> SplatStageConfig:
    """The 3DGS stage of a plain dataset's scenes: :data:`DATASET_SPLAT_ITERATIONS` steps (the first half at
    1/:data:`DATASET_SPLAT_COARSE_DOWNSCALE` size), :data:`DATASET_SPLAT_MAX_GAUSSIANS` Gaussians,
    :data:`DATASET_SPLAT_SCALE_REG`, :data:`DATASET_SPLAT_SCHEDULE`, evaluated once at the end
    (:data:`DATASET_SPLAT_EVALUATION`). ``fields``: any ``SplatStageConfig`` field to set instead (``None`` = the
    default; an ``extra`` dict is laid over the schedule and the evaluation settings)."""
    given = {k: v for k, v in fields.items() if v is not None}
    extra = {**dict(DATASET_SPLAT_SCHEDULE), **dict(DATASET_SPLAT_EVALUATION), **dict(given.pop("extra", {}))}
    kw = {"iterations": DATASET_SPLAT_ITERATIONS, "max_gaussians": DATASET_SPLAT_MAX_GAUSSIANS,
          "scale_reg": DATASET_SPLAT_SCALE_REG, "coarse_downscale": DATASET_SPLAT_COARSE_DOWNSCALE, **given}
    kw["coarse_downscale"] = int(kw["coarse_downscale"])
    return SplatStageConfig(**kw, extra=extra)


#: :attr:`ObstacleConfig.fit_iterations`' default (= ``umi_aug.splat.obstacle_gaussians.ObstacleGaussianConfig``'s)
OBSTACLE_FIT_ITERATIONS = 1000


@dataclass(frozen=True)
class ObstacleConfig:
    """Obstacle augmentation (paper §3.2/§3.3): an asset placed where it blocks the demo's straight approach.

    Attributes:
        assets: procedural asset names (:data:`umi_aug.recon.obstacles.PROCEDURAL_ASSETS`) or mesh file paths;
            each episode draws one (seeded).
        scale_range: uniform scale factor drawn per episode.
        inflation_m: convex-hull inflation used by the trajectory constraint and the final frame check.
        clearance_m: clearance of the demo's pre-contact tail and post-contact motion from the inflated hull.
        fit_gaussians: fit the obstacle Gaussians to renders of the mesh (else: surface-sampled init only).
        n_gaussians: Gaussians per obstacle asset.
        fit_iterations: 3DGS steps of each asset's fit (``fit_gaussians``); fewer fit faster and look coarser.
        placement_tries: candidate placements per attempt (:func:`umi_aug.recon.sample_obstacle_placement`).
    """

    assets: tuple[str, ...] = ("box", "bottle", "cylinder")
    scale_range: tuple[float, float] = (1.0, 1.3)
    inflation_m: float = 0.01
    clearance_m: float = 0.015
    fit_gaussians: bool = True
    n_gaussians: int = 6000
    fit_iterations: int = OBSTACLE_FIT_ITERATIONS
    placement_tries: int = 2000


@dataclass(frozen=True)
class OverlayConfig:
    """Gripper overlay (paper §3.4): real gripper pixels composited onto every rendered frame.

    Attributes:
        mask: ``"predefined"`` (UMI's gripper polygons + finger trapezoid at policy resolution), ``"estimated"``
            (low temporal variance over the demos' pre-contact frames), or ``"auto"`` (predefined when it covers
            the estimate, else the estimate).
        feather_px: width of the outward alpha ramp at the mask edge (pixels; 0 = hard edge). Pixels inside the
            mask are always exactly the original's.
        std_threshold: grey-level temporal std (0..255) below which a pixel counts as static (estimate).
        min_coverage: ``"auto"``: minimal fraction of the estimated static region inside the predefined mask.
        mirrors: UMI's side mirrors (:mod:`umi_aug.augment.mirrors`): ``"source"`` (their pixels come from the
            overlay's original frame, as the gripper's: black, swapped or a real reflection, as the dataset has
            them), ``"scene"`` (the 3DGS render; a rig without mirrors), or ``"auto"`` (``"source"`` unless the
            frames show no mirror there). A source without UMI's rig (the square benchmark) ignores it.
    """

    mask: str = "auto"
    feather_px: float = 2.0
    std_threshold: float = 6.0
    min_coverage: float = 0.9
    mirrors: str = "auto"


@dataclass(frozen=True)
class AugmentConfig:
    """Everything :func:`umi_aug.augment.prepare_session`, :func:`plan_episode` and :func:`export` need.

    Attributes:
        mode: ``"freespace"``, ``"obstacle"`` or ``"both"`` (each demo gets ``n_per_demo`` episodes per mode).
        n_per_demo: augmented episodes per demo and mode.
        seed: root seed of every random choice.
        cone_half_angle_deg / cone_radius_m / max_extra_rotation_deg: the start-pose cone (paper θ, r).
        image_size: policy image side S (UMI: 224); frames are rendered directly at ``intr.umi_policy(S)``.
        max_attempts: start poses (and obstacle placements) tried per episode before it is reported failed.
        pregrasp_clearance_m: the splice (pre-contact) frame is the last frame before the detected contact whose
            gripper keeps this clearance from the reconstructed scene (the contact frame itself touches it, and
            the trajectory validation needs free space around its goal).
        splat / recon / obstacle / overlay / traj: stage settings.
        render_near_m / render_far_m: 3DGS culling distances.
        render_min_transmittance: early termination of the new frames' 3DGS render: a pixel stops compositing
            when its transmittance would fall below this (:func:`umi_aug.splat.render`'s ``min_transmittance``;
            1e-4 = INRIA 3DGS / gsplat). Larger is faster and drops the faint tail of each pixel.
        executor / workers: how the export's episodes are planned and rendered
            (:func:`umi_aug.augment.executor.map_ordered`: ``"local"`` with 1 worker = this process, more =
            spawned processes; ``"ray"``); results are written in job order either way (same dataset).
        ray_address: an existing Ray cluster (``"auto"``, ``"ray://host:10001"``); None = a local cluster with
            ``workers`` CPUs.
        include_original: copy the original episodes first in the exported dataset.
        rerender_originals: also write each augmentable demo once more (``meta/aug_mode`` 3, ``aug_id`` 0, ahead
            of its augmented episodes) with its approach (frames before the splice) rendered by the scene model at
            the demo's own poses, its labels and the rest of its frames as recorded: a policy then sees the same
            approach in both looks, the camera's and the renders' (the square study's ``ours_rerender``,
            ``docs/square_learning.md`` §2e). Off by default.
        jpegxl_effort: libjxl encoder effort (1 fastest .. 9 slowest; None: the library's default, 7) for the
            new frames of a JPEG-XL image array; the exported array's codec config is the source dataset's with
            this ``effort`` (one of UMI's eleven JpegXl keys, read by UMI's codec; decoding does not depend on it,
            so the replayed original chunks are still copied as stored). 4 (default) encodes ~3x faster than 7 at
            UMI's level 99 with the same PSNR against the render and the ground truth (``umi_aug/augment/README.md``).
    """

    mode: str = "freespace"
    n_per_demo: int = 4
    seed: int = 0
    cone_half_angle_deg: float = 50.0
    cone_radius_m: float = 0.15
    max_extra_rotation_deg: float = 10.0
    image_size: int = 224
    max_attempts: int = 8
    pregrasp_clearance_m: float = 0.02
    splat: SplatStageConfig = field(default_factory=SplatStageConfig)
    recon: ReconConfig = field(default_factory=lambda: ReconConfig(sfm=SfmConfig(mode="known_poses")))
    obstacle: ObstacleConfig = field(default_factory=ObstacleConfig)
    overlay: OverlayConfig = field(default_factory=OverlayConfig)
    traj: TrajConfig = field(default_factory=TrajConfig)
    render_near_m: float = 0.01
    render_far_m: float = 20.0
    render_min_transmittance: float = DEFAULT_RENDER_MIN_TRANSMITTANCE
    executor: str = "local"
    workers: int = 1
    ray_address: str | None = None
    include_original: bool = True
    jpegxl_effort: int | None = 4
    rerender_originals: bool = False

    def __post_init__(self) -> None:
        if self.mode not in (*MODES, "both"):
            raise AugmentError(f"AugmentConfig.mode = {self.mode!r}; expected one of {(*MODES, 'both')}")
        for name in ("n_per_demo", "max_attempts", "image_size", "workers"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < (0 if name == "n_per_demo" else 1):
                raise AugmentError(f"AugmentConfig.{name} = {v!r}; expected a positive int")
        if not 0.0 <= self.cone_half_angle_deg <= 180.0:
            raise AugmentError(f"AugmentConfig.cone_half_angle_deg = {self.cone_half_angle_deg}; expected [0, 180]")
        if not (self.cone_radius_m > 0 and math.isfinite(self.cone_radius_m)):
            raise AugmentError(f"AugmentConfig.cone_radius_m = {self.cone_radius_m}; expected metres > 0")
        sr = self.splat.scale_reg
        if isinstance(sr, bool) or not isinstance(sr, (int, float)) or not (sr >= 0.0 and math.isfinite(sr)):
            raise AugmentError(f"SplatStageConfig.scale_reg = {sr!r}; expected a finite number >= 0")
        cd = self.splat.coarse_downscale
        if isinstance(cd, bool) or not isinstance(cd, int) or cd < 1 or self.image_size % cd:
            raise AugmentError(f"SplatStageConfig.coarse_downscale = {cd!r}; expected an int >= 1 that divides the "
                               f"image size {self.image_size}")
        t = self.render_min_transmittance
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0.0 < t < 1.0:
            raise AugmentError(f"AugmentConfig.render_min_transmittance = {t!r}; expected a number in (0, 1) "
                               f"(1e-4: INRIA 3DGS / gsplat)")
        e = self.jpegxl_effort
        if e is not None and (isinstance(e, bool) or not isinstance(e, int) or not 1 <= e <= 9):
            raise AugmentError(f"AugmentConfig.jpegxl_effort = {e!r}; expected an int in 1..9 or None")
        for name in ("include_original", "rerender_originals"):
            if not isinstance(getattr(self, name), bool):
                raise AugmentError(f"AugmentConfig.{name} = {getattr(self, name)!r}; expected True or False")
        if self.executor not in ("local", "ray"):
            raise AugmentError(f"AugmentConfig.executor = {self.executor!r}; expected 'local' or 'ray'")
        if self.overlay.mask not in ("predefined", "estimated", "auto"):
            raise AugmentError(f"OverlayConfig.mask = {self.overlay.mask!r}; expected predefined/estimated/auto")
        if self.overlay.mirrors not in MIRROR_MODES:
            raise AugmentError(f"OverlayConfig.mirrors = {self.overlay.mirrors!r}; expected one of "
                               f"{list(MIRROR_MODES)}")
        fi = self.obstacle.fit_iterations
        if isinstance(fi, bool) or not isinstance(fi, int) or fi < 1:
            raise AugmentError(f"ObstacleConfig.fit_iterations = {fi!r}; expected a positive int")
        if not self.obstacle.assets and self.mode != "freespace":
            raise AugmentError("ObstacleConfig.assets is empty but the mode needs obstacles")

    @property
    def modes(self) -> tuple[str, ...]:
        """The per-episode modes this config runs, in export order."""
        return modes_of(self.mode)


def obstacle_key(obstacle: ObstacleConfig) -> dict[str, Any]:
    """The obstacle settings as cache keys hash them: every field, except ``fit_iterations`` at its default (so the
    keys of work folders and exports made before that setting existed stay the same)."""
    return {f.name: getattr(obstacle, f.name) for f in dataclasses.fields(obstacle)
            if not (f.name == "fit_iterations" and obstacle.fit_iterations == OBSTACLE_FIT_ITERATIONS)}


def splat_key(splat: SplatStageConfig) -> dict[str, Any]:
    """The 3DGS settings as cache keys hash them: every field, except ``scale_reg`` at the trainer's default 0.01
    and ``coarse_downscale`` at 1 (what scenes were trained with before the settings existed, so their stage caches
    and exports keep their keys)."""
    return {f.name: getattr(splat, f.name) for f in dataclasses.fields(splat)
            if not (f.name == "scale_reg" and splat.scale_reg == TRAINER_SCALE_REG)
            and not (f.name == "coarse_downscale" and splat.coarse_downscale == 1)}


def modes_of(mode: str) -> tuple[str, ...]:
    """``"both"`` → ``("freespace", "obstacle")``; a single mode → ``(mode,)``."""
    return MODES if mode == "both" else (mode,)


def jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON values (what :func:`config_hash` hashes): a dataclass → a dict of its fields, a dict →
    sorted by key, a tuple → a list, a non-finite float → its repr, anything else unknown → its repr."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return repr(obj)
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    return repr(obj)


def config_hash(*parts: Any) -> str:
    """sha256 (hex, 16 chars) of the canonical JSON of ``parts`` (dataclasses, dicts, lists, scalars)."""
    text = json.dumps(jsonable(list(parts)), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]
