"""A UMI session folder (``demos/``, ``calibration/``, ``dataset.zarr.zip``) as export input: the default kind.

:func:`prepare_session` runs, in order, only the stages the mode needs (each skipped when up to date, see
:mod:`umi_aug.augment.cache`):

1. ``reconstruct`` — SfM cloud + scene SDF over the reachable region + contact frames
   (:func:`umi_aug.recon.reconstruct_session`);
2. ``contact`` — the pre-/post-contact split per demo (:func:`umi_aug.augment.stages.contact_stage`; demos without
   a splice frame are skipped, with a warning);
3. ``splat`` — the scene's fisheye 3DGS (:func:`umi_aug.splat.train_session.train_splat_from_session`, initialised
   from the SfM cloud; ``iterations = 0`` → the initial Gaussians only, no optimisation — for smoke runs);
4. ``gripper_mask`` — the overlay mask at policy resolution (:func:`umi_aug.augment.stages.gripper_mask_stage`);
5. ``obstacles/<asset>`` (obstacle modes only) — one Gaussian model per obstacle asset, object frame
   (:func:`umi_aug.splat.obstacle_gaussians.obstacle_gaussians`), fitted when an episode first renders that asset
   (:meth:`SessionAssets.obstacle_gaussians`; a blocking lock makes executor workers wait for one fit), so a run
   whose episodes use two of three assets fits two; ``prefit_obstacles`` fits the first attempts' assets beside
   the 3DGS training instead.

:class:`SessionSource` is the session's :class:`~umi_aug.augment.sources.base.InputSource`: its check is
:func:`umi_aug.augment.preflight.check_session_inputs`, its fingerprint :func:`session_fingerprint`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from umi_aug.augment.cache import StageResult, run_stage
from umi_aug.augment.config import AugmentConfig, splat_key
from umi_aug.augment.obstacle_stage import check_obstacle_assets, start_obstacle_prefit
from umi_aug.augment.preflight import InputCheck, check_demo_trajectories, check_session_inputs
from umi_aug.augment.session_assets import OBSTACLE_WORK_KEY, DemoInfo, SessionAssets
from umi_aug.augment.stages import contact_stage, gripper_mask_stage, init_only_gaussians
from umi_aug.data.fingerprint import content_fingerprint, file_fingerprint
from umi_aug.errors import AugmentError, UmiAugError
from umi_aug.recon.pipeline import reconstruct_session
from umi_aug.recon.session_io import load_session
from umi_aug.splat.warmup import start_background_compile

__all__ = ["SessionSource", "open_session", "prepare_session", "session_fingerprint", "SESSION_INPUTS"]

log = logging.getLogger(__name__)

#: What a session's stages read, relative to its folder: the export never writes inside them.
SESSION_INPUTS: tuple[str, ...] = ("demos", "calibration", "dataset.zarr.zip")


@dataclass(frozen=True)
class SessionSource:
    """A UMI session folder as :class:`~umi_aug.augment.sources.base.InputSource` (no settings of its own).

    Attributes:
        path: the folder, as the caller gave it (messages name it so).
    """

    path: str | os.PathLike

    @property
    def root(self) -> Path:
        return Path(self.path)

    @property
    def dataset(self) -> Path:
        return self.root / "dataset.zarr.zip"

    def reads(self) -> tuple[Path, ...]:
        """The session's inputs (:data:`SESSION_INPUTS`); a folder without ``demos/`` is no session: all of it."""
        if not (self.root / "demos").is_dir():
            return (self.root,)
        return tuple(self.root / sub for sub in SESSION_INPUTS)

    def check(self, image_size: int) -> InputCheck:
        if not (self.root / "demos").is_dir():
            raise AugmentError(f"{self.path}: neither a UMI session folder (no demos/) nor a UMI dataset "
                               f"(*.zarr.zip or a zarr directory with data/ and meta/)")
        return check_session_inputs(self.path, image_size)  # all inputs, before compute

    def fingerprint(self) -> str:
        return session_fingerprint(self.root)

    def n_augment(self, n_episodes: int) -> int:
        return n_episodes  # every demo with a contact frame

    def prepare(self, work: Path, cfg: AugmentConfig, *, progress: bool = True,
                prefit_obstacles: Sequence[str] = ()) -> SessionAssets:
        # the obstacle assets the jobs' first attempts draw are fitted beside the 3DGS training
        return prepare_session(self.path, work, cfg, progress=progress, prefit_obstacles=prefit_obstacles)


def open_session(path: str | os.PathLike, settings: Any = None) -> SessionSource:
    """The :class:`SessionSource` of ``path`` (a session takes no input settings: ``settings`` is ignored, as the
    export's ``dataset_input`` always was for a session)."""
    return SessionSource(path)


def session_fingerprint(session_dir: Path) -> str:
    """Content hash of what the stages read from a session: every file under ``demos/`` and ``calibration/``
    (CSV/JSON/intrinsics whole, videos by size + first/last MiB), ``dataset_plan.pkl`` and ``dataset.zarr.zip``'s
    entries with their CRCs (:func:`umi_aug.data.fingerprint.content_fingerprint`): an in-place edit of the same
    size changes it."""
    root = Path(session_dir)
    h = hashlib.sha256()
    for sub in ("demos", "calibration"):
        for dirpath, dirnames, filenames in sorted(os.walk(root / sub)):
            dirnames.sort()
            for fn in sorted(filenames):
                p = Path(dirpath) / fn
                rel = p.relative_to(root).as_posix()
                h.update(f"{rel}:{file_fingerprint(p)};".encode())
    ds = root / "dataset.zarr.zip"
    h.update(f"dataset:{content_fingerprint(ds) if ds.exists() else -1}".encode())
    plan = root / "dataset_plan.pkl"  # which video segment each episode is (umi_aug.recon.session_io)
    if plan.is_file():
        h.update(f"plan:{file_fingerprint(plan)}".encode())
    return h.hexdigest()[:16]


# ------------------------------------------------------------------------------------------------ stages
def _stage_reconstruct(session_dir: Path, work: Path, cfg: AugmentConfig, fp: str) -> StageResult:
    rcfg = dataclasses.replace(cfg.recon, cone_half_angle_deg=cfg.cone_half_angle_deg)

    def fn(out: Path):
        o = reconstruct_session(session_dir, out, rcfg)
        info = {k: o.report[k] for k in ("sfm", "cloud", "sdf", "timings_s")}
        info["sfm"] = {k: v for k, v in info["sfm"].items() if k != "config"}
        return ({"cloud": "scene_cloud.ply", "sdf": "scene_sdf.npz", "report": "recon_report.json"},
                ["scene_cloud.ply", "scene_sdf.npz", "recon_report.json"], info)

    # version 2: no cloud points inside the camera's own path; later approaches gate the grasp search too
    return run_stage("reconstruct", work, rcfg, {"session": fp}, fn, version=2)


def _stage_splat(session_dir: Path, work: Path, cfg: AugmentConfig, fp: str, recon: StageResult,
                 contact: StageResult, progress: bool, beside_training: Callable[[], object] | None = None
                 ) -> StageResult:
    """The scene's 3DGS stage; ``beside_training`` is called right before the training starts (not when the stage
    is cached or untrained): work that should use the core the training leaves idle."""
    sc = cfg.splat

    def fn(out: Path):
        if sc.iterations == 0:
            from umi_aug.splat import write_ply  # lazy: torch

            log.warning("splat: iterations = 0 → the SfM-initialised Gaussians are used without optimisation")
            write_ply(out / "scene.ply", init_only_gaussians(recon.path("cloud"), sc.sh_degree))
            return {"ply": "scene.ply"}, ["scene.ply"], {"trained": False}
        try:  # lazy and optional: the fisheye 3DGS trainer (torch)
            from umi_aug.splat.train import SplatTrainConfig
            from umi_aug.splat.train_session import train_splat_from_session
        except ImportError as exc:
            raise AugmentError("the splat stage needs umi_aug.splat.train (fisheye 3DGS training); it is not "
                               f"importable here ({exc}); set splat.iterations = 0 for an untrained scene") from exc
        tcfg = SplatTrainConfig(seed=cfg.seed, **sc.train_kwargs())
        rows = json.loads((contact.dir / "contacts.json").read_text())
        contacts = {r["name"]: int(r["splice_index"]) for r in rows if r["splice_index"] is not None}
        if beside_training is not None:
            beside_training()
        res = train_splat_from_session(session_dir, out, cfg=tcfg, init_cloud=recon.path("cloud"),
                                       image_size=sc.image_size, contact=contacts, progress=progress)
        ply = Path(res.ply_path).resolve()
        try:
            rel = ply.relative_to(out.resolve()).as_posix()
        except ValueError as exc:
            raise AugmentError(f"splat: trained PLY {ply} is outside the stage folder {out}") from exc
        info = {"trained": True, "heldout_psnr": _f(res.heldout_psnr), "heldout_ssim": _f(res.heldout_ssim),
                "gaussians": int(res.gaussians.n)}
        return {"ply": rel}, [rel], info

    return run_stage("splat", work, {"splat": splat_key(sc), "seed": cfg.seed},
                     {"session": fp, "reconstruct": recon.key, "contact": contact.key}, fn)


def _f(v) -> float | None:
    try:
        return None if v is None else float(v)
    except (TypeError, ValueError):
        return None


def prepare_session(session_dir: str | os.PathLike, work_dir: str | os.PathLike, cfg: AugmentConfig,
                    *, renders: bool = True, progress: bool = True,
                    prefit_obstacles: Sequence[str] = ()) -> SessionAssets:
    """Run (or skip, when cached) the session stages the mode needs and return the light handle.

    Args:
        session_dir: UMI session folder (``demos/``, ``calibration/``, ``dataset.zarr.zip``).
        work_dir: cache folder of the stages (one sub-folder per stage).
        cfg: :class:`AugmentConfig`.
        renders: False → plan-only (skip the 3DGS, mask and obstacle-Gaussian stages).
        progress: progress bars of the long stages (3DGS training).
        prefit_obstacles: obstacle assets the caller will need (obstacle mode, rendering): fitted by a background
            process (:func:`~umi_aug.augment.obstacle_stage.start_obstacle_prefit`) while the 3DGS trains, instead
            of on first use (not when the 3DGS stage is cached). Empty: every asset is fitted when an episode
            first uses it.
    Raises:
        AugmentError: missing session parts, a stage's failure (wrapped with the stage's name).
    """
    session_dir, work = Path(session_dir), Path(work_dir)
    dataset = session_dir / "dataset.zarr.zip"
    if not dataset.exists():
        raise AugmentError(f"{session_dir}: no dataset.zarr.zip (the original episodes); run UMI's "
                           "07_generate_replay_buffer first")
    work.mkdir(parents=True, exist_ok=True)
    try:
        sess = load_session(session_dir)
    except UmiAugError as exc:
        raise AugmentError(f"{session_dir}: {exc}") from exc
    if any(d.T_world_cam is None or d.gripper_width is None for d in sess.demos):
        raise AugmentError(f"{session_dir}: every demo needs camera_trajectory.csv and widths in dataset.zarr.zip")
    check_demo_trajectories(sess)  # a lost row or a pose jump in an episode's frames: named, not a "collision"
    fp = session_fingerprint(session_dir)
    if renders:  # a bad asset name or mesh fails here, before any stage runs (their Gaussians are fitted later)
        check_obstacle_assets(cfg)
    if renders:  # a cold numba cache compiles the 3DGS kernels in a child process while SfM runs
        start_background_compile()
    stages: dict[str, StageResult] = {}
    try:
        stages["reconstruct"] = recon = _stage_reconstruct(session_dir, work, cfg, fp)
        stages["contact"] = contact = contact_stage(work, recon, sess.demos, dict(cfg.recon.contact_overrides),
                                                    cfg.pregrasp_clearance_m)
    except UmiAugError as exc:
        raise AugmentError(f"stage failed: {exc}") from exc
    rows = json.loads((contact.dir / "contacts.json").read_text())
    demos = [DemoInfo(i, d.name, d.T_world_cam, d.timestamp, d.gripper_width, rows[i]["splice_index"])
             for i, d in enumerate(sess.demos)]
    paths = {"sdf": str(recon.path("sdf")), "cloud": str(recon.path("cloud")), "dataset": str(dataset)}
    mask = np.zeros((cfg.image_size, cfg.image_size), bool)
    mask_info: dict = {}
    if renders:
        prefit = None
        if "obstacle" in cfg.modes and prefit_obstacles:  # beside the 3DGS training (it leaves part of a core idle)
            names = [n for n in prefit_obstacles if n in cfg.obstacle.assets]
            prefit = lambda: start_obstacle_prefit(work, cfg, names)  # noqa: E731
        try:
            stages["splat"] = splat = _stage_splat(session_dir, work, cfg, fp, recon, contact, progress, prefit)
            stages["gripper_mask"] = gm = gripper_mask_stage(work, cfg, fp, dataset, demos, contact)
            if "obstacle" in cfg.modes:  # each asset's Gaussians are fitted when an episode first uses it
                paths[OBSTACLE_WORK_KEY] = str(work)
        except UmiAugError as exc:
            raise AugmentError(f"stage failed: {exc}") from exc
        paths["splat"] = str(splat.path("ply"))
        mask, mask_info = np.load(gm.path("mask")), gm.info
    views = [sess.mapping.T_world_cam[sess.mapping.valid]] if sess.mapping.T_world_cam is not None else []
    for d in demos:
        if d.contact_index is not None:
            views.append(d.T_world_cam[: d.contact_index + 1])
    render_views = np.concatenate(views) if views else np.zeros((0, 4, 4))
    return SessionAssets(session_dir, work, cfg, sess.intrinsics, demos, render_views, mask, mask_info, paths, stages)
