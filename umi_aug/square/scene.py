"""Scene model of the square demos: ONE static-scene fisheye 3DGS + ONE nut asset, composed per demo.

The simulator's analogue of UMI's mapping scan (issue #15 item 1). Square scenes differ only in the nut's pose
(table, pegs and room never move; the robot is pasted in later by the gripper overlay and is never in the scene
model), so instead of a 3DGS per demo the scene is

- ``static``: a fisheye 3DGS trained on a short simulated wrist-camera scan of the workspace with the robot and
  the nut hidden (:func:`umi_aug.square.scan.scan_poses`, rendered through the true GoPro fisheye at the
  policy intrinsics), initialised from the scan's ray depth;
- ``nut``: a 3DGS of the nut alone in its body frame, trained on close orbit views (equidistant fisheye, nut on a
  white background) of the nut at the reference state's pose;

and a demo's scene is ``static + nut moved to the demo's nut pose`` (:func:`demo_gaussians`, the project's scene
+ obstacle composition: :func:`umi_aug.splat.compose.transform_gaussians` + concatenation; :func:`scene_parts`
gives the pieces for the faster :func:`umi_aug.splat.compose.render_composed`). :func:`train_demo_scene` is the
per-demo alternative (a scan of that demo's full initial scene, trained alone) that ``benchmarks/square_scene.py``
measures the composition against.

Measured (``benchmarks/square_scene.py``, 84², 3 demos other than the reference x 12 augmented poses, PSNR inside
the image circle vs the simulator with the robot hidden, median / 5th percentile; 2 shared cores at load 6-9):
defaults (static 1500 steps, 40 views, 12k Gaussians; nut 800 steps at 30²): composed 24.5 / 23.4 dB, SSIM 0.925
/ 0.901; per-demo 3DGS (same recipe, 15k Gaussians) 24.8 / 23.9 dB, 0.931 / 0.911; static alone (no nut) 19.2 /
18.4 dB. With the once-trained static scene given 3000 steps and 64 views: composed 25.0 / 24.0 dB, 0.937 / 0.918.
Training: static ~200 s (3000 steps: ~400 s) + nut ~50 s once for ALL demos, vs ~80-350 s per demo (load).

Stages (:func:`umi_aug.augment.cache.run_stage`, under ``work_dir``; each keyed by its config subset, the env
meta / model and the reference state): ``model`` (state layout of the model: nq, nv), ``static``, ``nut``,
``demo_<state hash>``. A second build with the same inputs retrains nothing. Every training folder holds
``scene.ply``, ``metrics.json``, ``contact_sheet.png`` (held-out GT | render | error) and ``curve.png``.
"""

from __future__ import annotations

import copy
import hashlib
import logging
import math
import os
import threading
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from umi_aug.augment.cache import StageResult, run_stage
from umi_aug.augment.config import config_hash
from umi_aug.errors import AugmentError
from umi_aug.geometry import pose_inverse
from umi_aug.sim.gl import import_mujoco
from umi_aug.square.camera import camera_pose_cv, wrist_intrinsics
from umi_aug.square.env import SquareEnv
from umi_aug.square.scan import (ScanRenderer, body_pose, data_at_state, nut_orbit_intrinsics, nut_orbit_poses,
                                 scan_points, scan_poses)

__all__ = ["SquareSceneConfig", "SquareScene", "DemoScene", "build_square_scene", "train_demo_scene",
           "demo_gaussians", "scene_parts", "load_scene_gaussians", "scan_center", "SCENE_VERSION"]

log = logging.getLogger(__name__)

#: Bumped when the stages' outputs change for the same config.
SCENE_VERSION: int = 1
#: Distance (metres) of the augmentation cone's pivot ahead of the initial wrist camera (``init_configs``' radius).
CONE_PIVOT_M: float = 0.15


@dataclass(frozen=True)
class SquareSceneConfig:
    """Settings of the square scene model (every field is part of the cache keys of the stages that use it).

    Attributes:
        image_size: policy image size (renders use :func:`umi_aug.square.camera.wrist_intrinsics`).
        n_scan_views: views of the static (and per-demo) scan; every ``holdout_every``-th is held out.
        scan_image_size: scan / training image size (None: ``image_size``).
        scan_radius: camera distance range from the scan centre, metres.
        scan_max_polar_deg: scan cap half-angle around the vertical, degrees.
        scan_target_radius: look-at points lie within this distance of the scan centre (metres).
        static_iterations, static_max_gaussians: trainer steps and Gaussian budget of the static scene (the
            per-demo scene uses the same steps and ``static_max_gaussians + nut_max_gaussians``).
        n_nut_views, nut_fov_deg, nut_radius: the nut's orbit views (equidistant lens, ``nut_fov_deg`` across).
        nut_image_size: orbit image size; None: the policy lens's pixel density at its centre (``fx`` of
            :func:`wrist_intrinsics` (``image_size``) per radian) x ``nut_oversample`` (60 px at 84²). The
            density decides the look: a nut trained on coarser views than it is rendered at comes out thin and
            see-through (its Gaussians sized for the coarse pixels; the table shows through), one trained much
            denser a pixel too wide. At 84², 24 views at 0.75 (the default until 2026-11-29) render the nut at
            15.5 dB / saturation 112 against the simulator's 152 at the demos' own poses and 15.6 dB at augmented
            poses; 48 views at 1.5: 18.5 / 142 and 18.8 dB, the image circle as good or better; 2.0: 19.2 dB on the
            nut, the circle 1 dB worse (``benchmarks/square_demo_rerender.py``; ``docs/square_learning.md`` §2f).
        nut_iterations, nut_max_gaussians: trainer steps and budget of the nut asset.
        init_fraction: initial Gaussians from the scan's depth, as a fraction of the budget.
        sh_degree: SH degree of every model.
        holdout_every: trainer hold-out period (views 0, n, 2n, ...).
        seed: scan poses, point sampling, training.
    """

    image_size: int = 84
    n_scan_views: int = 40
    scan_image_size: int | None = None
    scan_radius: tuple[float, float] = (0.18, 0.40)
    scan_max_polar_deg: float = 60.0
    scan_target_radius: float = 0.12
    static_iterations: int = 1500
    static_max_gaussians: int = 12000
    n_nut_views: int = 48
    nut_image_size: int | None = None
    nut_oversample: float = 1.5
    nut_fov_deg: float = 70.0
    nut_radius: tuple[float, float] = (0.16, 0.26)
    nut_iterations: int = 800
    nut_max_gaussians: int = 3000
    init_fraction: float = 0.7
    sh_degree: int = 1
    holdout_every: int = 8
    seed: int = 0

    def check(self) -> None:
        """Raise :class:`AugmentError` naming the first invalid field."""
        def bad(name: str, why: str) -> AugmentError:
            return AugmentError(f"SquareSceneConfig.{name} = {getattr(self, name)!r}: {why}")

        if int(self.image_size) < 16:
            raise bad("image_size", "must be >= 16 pixels")
        for name in ("scan_image_size", "nut_image_size"):
            if getattr(self, name) is not None and int(getattr(self, name)) < 16:
                raise bad(name, "must be None or >= 16 pixels")
        if not 0.25 <= float(self.nut_oversample) <= 8.0:
            raise bad("nut_oversample", "must be in [0.25, 8]")
        for name in ("n_scan_views", "n_nut_views"):
            if int(getattr(self, name)) < 2:
                raise bad(name, "must be >= 2")
        for name in ("static_iterations", "static_max_gaussians", "nut_iterations", "nut_max_gaussians"):
            if int(getattr(self, name)) < 1:
                raise bad(name, "must be >= 1")
        if not 0.0 < self.init_fraction <= 1.0:
            raise bad("init_fraction", "must be in (0, 1]")
        if not 0 <= self.sh_degree <= 3:
            raise bad("sh_degree", "must be in 0..3")
        for name in ("scan_radius", "nut_radius"):
            r = tuple(getattr(self, name))
            if len(r) != 2 or not 0.0 < float(r[0]) <= float(r[1]):
                raise bad(name, "must be (min, max) metres with 0 < min <= max")

    @property
    def scan_size(self) -> int:
        return int(self.scan_image_size or self.image_size)

    @property
    def nut_size(self) -> int:
        """Orbit image size (see ``nut_image_size``), at least 16."""
        if self.nut_image_size is not None:
            return int(self.nut_image_size)

        fx = wrist_intrinsics(self.image_size).fx
        return max(16, int(round(fx * math.radians(self.nut_fov_deg) * float(self.nut_oversample))))


@dataclass
class SquareScene:
    """The cached scene model (paths + small arrays; cheap to pickle into workers).

    Attributes:
        work_dir: the folder of the stages.
        static_ply, nut_ply: the two Gaussian sets (INRIA PLY; static in the world frame, nut in its body frame).
        scan_T_world_cam: np.ndarray,  # [V, 4, 4] the static scan's camera poses (OpenCV, world)
        T_world_nut_ref: np.ndarray,  # [4, 4] the nut pose its asset was scanned at (reference state)
        image_size: policy image size.
        key: cache identity of the pair (static key + nut key).
        report: ``{"static": {...}, "nut": {...}}``: held-out PSNR / SSIM, Gaussians, views, training seconds.
    """

    work_dir: Path
    static_ply: Path
    nut_ply: Path
    scan_T_world_cam: np.ndarray
    T_world_nut_ref: np.ndarray
    image_size: int
    key: str
    report: dict[str, Any] = field(default_factory=dict)

    @property
    def intrinsics(self):
        """Policy-image fisheye intrinsics (:func:`umi_aug.square.camera.wrist_intrinsics`)."""
        return wrist_intrinsics(self.image_size)


@dataclass
class DemoScene:
    """A per-demo 3DGS (:func:`train_demo_scene`): ``ply`` (world frame), ``scan_T_world_cam`` [V, 4, 4],
    ``report`` (held-out PSNR / SSIM, seconds, Gaussians), ``key``."""

    ply: Path
    scan_T_world_cam: np.ndarray
    report: dict[str, Any]
    key: str


# ------------------------------------------------------------------------------------------------- inputs
def _env_meta_of(source: Any) -> Any:
    """A :class:`SquareEnv` stands for its env_meta (its model is used as is, no second environment)."""
    return getattr(source, "env_meta", source) if type(source).__name__ == "SquareEnv" else source


def _source_key(source: Any) -> str:
    source = _env_meta_of(source)
    if isinstance(source, dict):
        return "env_meta:" + config_hash(source)
    if isinstance(source, str):
        return "xml:" + hashlib.sha256(source.encode()).hexdigest()[:16]
    raise AugmentError(f"square scene: the model source must be a robomimic env_meta dict or an MJCF string, got "
                       f"{type(source).__name__}")


def _load_model(source: Any):
    """A raw ``mujoco.MjModel`` of the square task from an env_meta dict (via SquareEnv), a SquareEnv or an MJCF
    string (a copy: the scan never changes the caller's model)."""
    _source_key(source)
    if type(source).__name__ == "SquareEnv":
        return copy.deepcopy(source.model)
    if isinstance(source, str):
        try:
            return import_mujoco().MjModel.from_xml_string(source)
        except ValueError as exc:
            raise AugmentError(f"square scene: the MJCF does not compile ({exc})") from exc

    env = SquareEnv(env_meta=source, image_size=None)
    try:
        return copy.deepcopy(env.model)
    finally:
        env.close()


class _Model:
    """The model, loaded on first use (a stage that is up to date needs none)."""

    def __init__(self, source: Any) -> None:
        self.source = source
        self._m = None

    def get(self):
        if self._m is None:
            self._m = _load_model(self.source)
        return self._m


def _state_key(state0: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(state0, dtype=np.float64).tobytes()).hexdigest()[:16]


def _check_state(state0: Any, layout: dict[str, int]) -> np.ndarray:
    s = np.asarray(state0, dtype=np.float64)
    n = 1 + int(layout["nq"]) + int(layout["nv"])
    if s.ndim != 1 or s.shape[0] != n:
        raise AugmentError(f"square scene: state0 has shape {list(s.shape)}; the square model needs a flat "
                           f"robomimic state of 1 + nq ({layout['nq']}) + nv ({layout['nv']}) = {n} values "
                           f"[time, qpos, qvel]")
    if not np.all(np.isfinite(s)):
        raise AugmentError("square scene: state0 has non-finite entries")
    return s


def _stage_model(work: Path, source: Any, model: _Model) -> StageResult:
    def fn(out: Path):
        m = model.get()
        return {"nq": int(m.nq), "nv": int(m.nv)}, [], {"nq": int(m.nq), "nv": int(m.nv)}

    return run_stage("model", work, {}, {"source": _source_key(source)}, fn, version=SCENE_VERSION)


def scan_center(model, data) -> np.ndarray:
    """Scan centre ``[3]`` (world, metres): on the table top, half-way (xy) between the augmentation cone's pivot
    (``CONE_PIVOT_M`` ahead of the initial wrist camera) and the nut."""
    mujoco = import_mujoco()
    T_cam = camera_pose_cv(model, data)
    pivot = T_cam[:3, 3] + CONE_PIVOT_M * T_cam[:3, 2]
    nut = body_pose(model, data)[:3, 3]
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "table_top")
    if sid < 0:
        raise AugmentError("square scene: the model has no 'table_top' site (not a robosuite table arena?)")
    c = 0.5 * (pivot + nut)
    c[2] = float(data.site_xpos[sid][2])
    return c


# ----------------------------------------------------------------------------------------------------- training
def _train(views, intr, xyz, rgb, iterations: int, max_gaussians: int, cfg: SquareSceneConfig, out: Path,
           progress: bool, *, background=(0.0, 0.0, 0.0), nut: bool = False):
    from umi_aug.splat.train import SplatTrainConfig, train_splat  # lazy, start-up: torch

    it = int(iterations)
    extra = {"init_opacity": 0.8, "opacity_reg": 0.0} if nut else {}  # an opaque solid (as obstacle Gaussians)
    tcfg = SplatTrainConfig(
        iterations=it, max_gaussians=int(max_gaussians), sh_degree=cfg.sh_degree, holdout_every=cfg.holdout_every,
        seed=cfg.seed, sh_increase_every=max(1, it // (cfg.sh_degree + 2)), refine_start=max(1, it // 10),
        eval_every=it, checkpoint_every=max(1, it // 4), background=tuple(float(b) for b in background), **extra)
    return train_splat(views, intr, xyz, rgb, tcfg, out, progress=progress)


def _scene_scan_stage(name: str, work: Path, source: Any, model: _Model, state0: np.ndarray, kind: str,
                      cfg: SquareSceneConfig, max_gaussians: int, progress: bool) -> StageResult:
    """Scan of ``kind`` ("static" or "scene") centred for ``state0``, rendered and trained; cached."""
    from umi_aug.splat.train import TrainView  # lazy, start-up: torch

    def fn(out: Path):
        m = model.get()
        intr = wrist_intrinsics(cfg.scan_size)
        poses = scan_poses(scan_center(m, data_at_state(m, state0)), cfg.n_scan_views, cfg.seed,
                           tuple(cfg.scan_radius), cfg.scan_max_polar_deg, cfg.scan_target_radius)
        with ScanRenderer(m, kind, intr) as r:
            frames = r.render(state0, poses, progress=progress)
        xyz, rgb = scan_points(frames, int(cfg.init_fraction * max_gaussians), cfg.seed)
        views = [TrainView(f"scan/{i:03d}", frames.rgb[i], poses[i], frames.valid) for i in range(len(poses))]
        res = _train(views, intr, xyz, rgb, cfg.static_iterations, max_gaussians, cfg, out / "train", progress)
        np.save(out / "scan_T_world_cam.npy", poses)
        info = _train_info(res, len(views))
        return {"ply": "train/scene.ply", "poses": "scan_T_world_cam.npy"}, ["train/scene.ply",
                                                                                "scan_T_world_cam.npy"], info

    sub = {"kind": kind, "scan": _scan_cfg(cfg), "iterations": cfg.static_iterations, "max_gaussians": max_gaussians}
    return run_stage(name, work, sub, {"source": _source_key(source), "state0": _state_key(state0)}, fn,
                     version=SCENE_VERSION)


def _scan_cfg(cfg: SquareSceneConfig) -> dict[str, Any]:
    d = asdict(cfg)
    return {k: d[k] for k in ("n_scan_views", "scan_radius", "scan_max_polar_deg", "scan_target_radius",
                              "init_fraction", "sh_degree", "holdout_every", "seed")} | {"size": cfg.scan_size}


def _train_info(res, n_views: int) -> dict[str, Any]:
    last = res.history[-1] if res.history else {}
    f = lambda v: None if v is None or not np.isfinite(v) else float(v)  # noqa: E731
    return {"heldout_psnr": f(res.heldout_psnr), "heldout_ssim": f(res.heldout_ssim), "gaussians": int(res.gaussians.n),
            "views": int(n_views), "train_seconds": float(last.get("seconds", float("nan"))),
            "wall_seconds": float(last.get("wall_seconds", float("nan")))}


def _stage_nut(work: Path, source: Any, model: _Model, state0: np.ndarray, cfg: SquareSceneConfig,
               progress: bool) -> StageResult:
    from umi_aug.splat.train import TrainView  # lazy, start-up: torch

    def fn(out: Path):
        m = model.get()
        T_nut = body_pose(m, data_at_state(m, state0))
        intr = nut_orbit_intrinsics(cfg.nut_size, cfg.nut_fov_deg)
        poses_w = nut_orbit_poses(T_nut, cfg.n_nut_views, cfg.seed, tuple(cfg.nut_radius))
        with ScanRenderer(m, "nut", intr) as r:
            frames = r.render(state0, poses_w, progress=progress)
        T_nut_world = pose_inverse(T_nut)
        poses_n = T_nut_world[None] @ poses_w
        imgs = np.where(frames.mask[..., None], frames.rgb, np.uint8(255))  # nut on white (as obstacle assets)
        xyz, rgb = scan_points(frames, int(cfg.init_fraction * cfg.nut_max_gaussians), cfg.seed, T_nut_world)
        views = [TrainView(f"nut/{i:03d}", imgs[i], poses_n[i], frames.valid) for i in range(len(poses_n))]
        res = _train(views, intr, xyz, rgb, cfg.nut_iterations, cfg.nut_max_gaussians, cfg, out / "train",
                     progress, background=(1.0, 1.0, 1.0), nut=True)
        np.save(out / "T_world_nut_ref.npy", T_nut)
        return ({"ply": "train/scene.ply", "T_world_nut_ref": "T_world_nut_ref.npy"},
                ["train/scene.ply", "T_world_nut_ref.npy"], _train_info(res, len(views)))

    sub = {k: v for k, v in asdict(cfg).items() if k.startswith("nut") or k in ("n_nut_views", "init_fraction",
                                                                                  "sh_degree", "holdout_every", "seed")}
    sub["size"] = cfg.nut_size
    return run_stage("nut", work, sub, {"source": _source_key(source), "state0": _state_key(state0)}, fn,
                     version=SCENE_VERSION)


# --------------------------------------------------------------------------------------------------- public API
def build_square_scene(work_dir: str | os.PathLike, source: dict[str, Any] | str, state0: np.ndarray,
                       cfg: SquareSceneConfig = SquareSceneConfig(), *, progress: bool = True) -> SquareScene:
    """Build (or reuse from ``work_dir``) the static scene and the nut asset of the square task.

    Args:
        work_dir: folder of the cached stages (``model/``, ``static/``, ``nut/``).
        source: robomimic ``env_meta`` dict of the demos (the hdf5's ``env_args``), a :class:`SquareEnv` built from
            it (its model is copied; no second environment), or the model's MJCF string.
        state0: np.ndarray,  # [1 + nq + nv] robomimic flat state of the reference demo's first frame (45 values
            for the square task); its wrist camera and nut centre the scan, its nut pose is the asset's.
        cfg: :class:`SquareSceneConfig`.
        progress: tqdm bars (scan rendering, training).
    Returns:
        :class:`SquareScene`.
    Raises:
        AugmentError: invalid config, model source or state (before any rendering or training).
    """
    cfg.check()
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    model = _Model(source)
    layout = _stage_model(work, source, model).outputs
    s0 = _check_state(state0, layout)
    st = _scene_scan_stage("static", work, source, model, s0, "static", cfg, cfg.static_max_gaussians, progress)
    nut = _stage_nut(work, source, model, s0, cfg, progress)
    return SquareScene(work, st.path("ply"), nut.path("ply"), np.load(st.path("poses")),
                       np.load(nut.path("T_world_nut_ref")), int(cfg.image_size), config_hash(st.key, nut.key),
                       {"static": dict(st.info), "nut": dict(nut.info)})


def train_demo_scene(work_dir: str | os.PathLike, source: dict[str, Any] | str, state0: np.ndarray,
                     cfg: SquareSceneConfig = SquareSceneConfig(), *, progress: bool = True) -> DemoScene:
    """The per-demo alternative: a scan of ``state0``'s full scene (robot hidden, nut in place), trained alone
    (same scan recipe and steps as the static scene; budget ``static_max_gaussians + nut_max_gaussians``);
    cached as stage ``demo_<state hash>`` under ``work_dir``."""
    cfg.check()
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    model = _Model(source)
    s0 = _check_state(state0, _stage_model(work, source, model).outputs)
    budget = cfg.static_max_gaussians + cfg.nut_max_gaussians
    st = _scene_scan_stage(f"demo_{_state_key(s0)[:12]}", work, source, model, s0, "scene", cfg, budget, progress)
    return DemoScene(st.path("ply"), np.load(st.path("poses")), dict(st.info), st.key)


_LOADED: dict[tuple, Any] = {}
_LOCK = threading.Lock()


def load_scene_gaussians(scene: SquareScene):
    """``(static, nut)`` Gaussians of ``scene`` (float32), read once per process and file version."""
    from umi_aug.splat.ply import read_ply  # lazy, start-up: torch

    out = []
    for p in (scene.static_ply, scene.nut_ply):
        p = Path(p)
        try:
            st = p.stat()
        except OSError as exc:
            raise AugmentError(f"square scene: {p} is missing ({exc}); rebuild with build_square_scene") from exc
        k = (str(p.resolve()), st.st_mtime_ns, st.st_size)
        with _LOCK:
            g = _LOADED.get(k)
        if g is None:
            g = read_ply(p)
            with _LOCK:
                _LOADED[k] = g
        out.append(g)
    return out[0], out[1]


def scene_parts(scene: SquareScene, T_world_nut: np.ndarray):
    """``(static Gaussians, [PlacedGaussians(nut at T_world_nut)])`` for
    :func:`umi_aug.splat.compose.render_composed` (no copy of the static set).

    Args:
        T_world_nut: np.ndarray,  # [4, 4] rigid nut body pose of the demo (world)
    """
    from umi_aug.splat.compose import PlacedGaussians  # lazy, start-up: torch

    static, nut = load_scene_gaussians(scene)
    return static, [PlacedGaussians(nut, np.asarray(T_world_nut, dtype=np.float64), f"square_nut-{scene.key}")]


def demo_gaussians(scene: SquareScene, T_world_nut: np.ndarray):
    """One demo's scene as ONE Gaussian set (world frame, float32): the static set + the nut asset moved rigidly to
    ``T_world_nut`` (means, rotations and SH rotated: :func:`umi_aug.splat.compose.transform_gaussians`).

    Args:
        T_world_nut: np.ndarray,  # [4, 4] rigid nut body pose of the demo (world)
    Raises:
        SplatError: ``T_world_nut`` is not a finite rigid pose.
    """
    # lazy, start-up: torch
    from umi_aug.splat.compose import transform_gaussians
    from umi_aug.splat.gaussians import Gaussians

    static, placed = scene_parts(scene, T_world_nut)
    return Gaussians.cat([static, transform_gaussians(placed[0].gaussians, placed[0].T_world_obj)])
