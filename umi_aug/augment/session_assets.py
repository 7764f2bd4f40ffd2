"""Session-level stages (cached on disk) and the light, picklable handle the per-episode functions use.

:func:`prepare_session` runs, in order, only the stages the mode needs (each skipped when up to date, see
:mod:`umi_aug.augment.cache`):

1. ``reconstruct`` — SfM cloud + scene SDF over the reachable region + contact frames
   (:func:`umi_aug.recon.reconstruct_session`);
2. ``contact`` — the pre-/post-contact split per demo: the detected contact frame (reconstruction report) and
   the splice frame, the last frame before it with ``pregrasp_clearance_m`` gripper clearance (demos without one
   are skipped, with a warning);
3. ``splat`` — the scene's fisheye 3DGS (:func:`umi_aug.splat.train_session.train_splat_from_session`, initialised from
   the SfM cloud; ``iterations = 0`` → the initial Gaussians only, no optimisation — for smoke runs);
4. ``gripper_mask`` — the overlay mask at policy resolution (:mod:`umi_aug.augment.overlay`);
5. ``obstacles/<asset>`` (obstacle modes only) — one Gaussian model per obstacle asset, object frame
   (:func:`umi_aug.splat.obstacle_gaussians.obstacle_gaussians`), fitted when an episode first renders that asset
   (:meth:`SessionAssets.obstacle_gaussians`; a blocking lock makes executor workers wait for one fit), so a run
   whose episodes use two of three assets fits two.

:class:`SessionAssets` keeps paths and small arrays; the heavy things (scene Gaussians, SDF, original dataset,
obstacle models, trajectory problems) load lazily, once per process, and are dropped when pickled.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from umi_aug.augment.cache import StageResult, run_stage
from umi_aug.augment.config import AugmentConfig
from umi_aug.augment.obstacle_stage import (check_obstacle_assets, load_obstacle_asset, obstacle_lock,
                                            obstacle_stage, start_obstacle_prefit)
from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import AugmentError, UmiAugError

__all__ = ["DemoInfo", "SessionAssets", "prepare_session", "session_fingerprint", "OBSTACLE_WORK_KEY"]

#: ``SessionAssets.paths`` key of the folder whose ``obstacles/`` holds the per-asset obstacle stages.
OBSTACLE_WORK_KEY = "obstacle_work"

log = logging.getLogger(__name__)

#: Version of the overlay-mask rule (3: "auto" = UMI's jaw polygons + the static finger pixels of the trapezoid).
OVERLAY_MASK_RULE = 3

#: Heavy members of unpickled :class:`SessionAssets`, per process, keyed by :attr:`SessionAssets.cache_id`.
_PROCESS_CACHE: dict[str, dict[str, Any]] = {}


@dataclass
class DemoInfo:
    """One original demonstration (index = its episode in the session's ``dataset.zarr.zip``).

    Attributes:
        index, name: episode index and demo folder name.
        T_world_cam: np.ndarray,  # [H, 4, 4] camera poses (table-tag world, OpenCV camera), metres
        timestamps: np.ndarray,  # [H] seconds
        gripper_width: np.ndarray,  # [H] metres
        contact_index: int | None,  # splice frame: the pre-contact pose the augmentation funnels into and
            the first replayed frame (``contact`` stage; None: no contact/pre-grasp frame, not augmented)
    """

    index: int
    name: str
    T_world_cam: np.ndarray
    timestamps: np.ndarray
    gripper_width: np.ndarray
    contact_index: int | None


@dataclass
class SessionAssets:
    """What the per-episode functions need; cheap to pickle (heavy members load lazily per process).

    Attributes:
        session_dir, work_dir: folders; cfg: the :class:`AugmentConfig`.
        intrinsics: raw frame intrinsics; demos: list[DemoInfo];
        render_views: np.ndarray,  # [V, 4, 4] the poses the 3DGS was trained on (scan + demos' pre-contact)
        gripper_mask: np.ndarray,  # [S, S] bool overlay mask; mask_info: how it was chosen
        paths: {"sdf", "cloud", "splat", "dataset"}: files, and in obstacle modes ``"obstacle_work"``: the folder of
            the per-asset obstacle stages; stages: StageResult per stage run by :func:`prepare_session`.
    """

    session_dir: Path
    work_dir: Path
    cfg: AugmentConfig
    intrinsics: FisheyeIntrinsics
    demos: list[DemoInfo]
    render_views: np.ndarray
    gripper_mask: np.ndarray
    mask_info: dict
    paths: dict[str, str]
    stages: dict[str, StageResult] = field(default_factory=dict)
    _lazy: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_lazy"] = {}
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        # copies unpickled in one process (one per task of an executor) share the heavy members
        self._lazy = _PROCESS_CACHE.setdefault(self.cache_id, {})

    @property
    def cache_id(self) -> str:
        """Identity of the lazily loaded members (their files and the config)."""
        from umi_aug.augment.config import config_hash

        return config_hash(sorted(self.paths.items()), self.cfg)

    @property
    def policy_intrinsics(self) -> FisheyeIntrinsics:
        """Intrinsics of the ``S x S`` policy images (UMI full-height centre crop, resized)."""
        return self.intrinsics.umi_policy(self.cfg.image_size)

    # -------------------------------------------------------------------------------------- lazy members
    def _get(self, key: str, make):
        if key not in self._lazy:
            self._lazy[key] = make()
        return self._lazy[key]

    @property
    def sdf(self):
        """The reconstructed scene SDF (:class:`umi_aug.recon.VoxelSDF`)."""
        from umi_aug.recon.sdf_grid import VoxelSDF

        return self._get("sdf", lambda: VoxelSDF.load(self.paths["sdf"]))

    @property
    def gaussians(self):
        """The scene's 3DGS (:class:`umi_aug.splat.Gaussians`, float32)."""
        from umi_aug.splat import read_ply

        return self._get("gaussians", lambda: read_ply(self.paths["splat"]))

    @property
    def original(self):
        """The session's original replay buffer (read-only, lazy chunk access). Opened once per process: a
        forked child re-opens it, as a zip file handle shared across a fork shares its read offset (concurrent reads
        then fail with ``BadZipFile``)."""
        from umi_aug.data import ReplayBuffer

        if self._lazy.get("original_pid") != os.getpid():
            self._lazy["original"] = ReplayBuffer.open(self.paths["dataset"])
            self._lazy["original_pid"] = os.getpid()
        return self._lazy["original"]

    def original_frames(self, demo_index: int, frames: np.ndarray | slice) -> np.ndarray:
        """Original policy frames ``[K, S, S, 3]`` uint8 of demo ``demo_index``."""
        sl = self.original.get_episode_slice(int(demo_index))
        arr = self.original["camera0_rgb"]
        if isinstance(frames, slice):
            return arr[sl][frames]
        idx = np.asarray(frames, dtype=np.int64) + sl.start
        if len(idx) == 0:
            return np.zeros((0,) + arr.shape[1:], np.uint8)
        lo, hi = int(idx.min()), int(idx.max()) + 1
        return arr[lo:hi][idx - lo]

    def obstacle_gaussians(self, asset: str):
        """Gaussians of obstacle ``asset`` in its object frame: its ``obstacles/<asset>`` stage, fitted on first
        use (in any process) and read from the cache after."""
        from umi_aug.splat import read_ply

        if OBSTACLE_WORK_KEY not in self.paths or asset not in self.cfg.obstacle.assets:
            raise AugmentError(f"{self.work_dir}: no obstacle Gaussians for asset {asset!r} (obstacle assets of "
                               f"this run: {list(self.cfg.obstacle.assets) if OBSTACLE_WORK_KEY in self.paths else []})")
        work = Path(self.paths[OBSTACLE_WORK_KEY])

        def load():
            try:  # one lock per asset: two workers fit two different assets at once
                with obstacle_lock(work, asset):
                    st = obstacle_stage(work, self.cfg, asset)
            except UmiAugError as exc:
                raise AugmentError(f"stage obstacles/{asset} failed: {exc}") from exc
            return read_ply(st.path("ply"))

        return self._get(f"obstacle/{asset}", load)

    def obstacle_asset(self, asset: str):
        """The :class:`umi_aug.recon.ObstacleAsset` named ``asset`` (procedural name or mesh path)."""
        return self._get(f"asset/{asset}", lambda: load_obstacle_asset(asset))

    def traj_problem(self, demo_index: int):
        """The free-space :class:`umi_aug.traj.TrajProblem` of a demo (built once per process)."""
        return self._get(f"problem/{demo_index}", lambda: self.make_problem(demo_index, None))

    def make_problem(self, demo_index: int, obstacle):
        """A :class:`TrajProblem` of demo ``demo_index`` with an optional :class:`umi_aug.traj.ConvexObstacle`."""
        from umi_aug.traj import Demonstration, TrajProblem, TrajScene

        d = self.demo(demo_index)
        demo = Demonstration(T_world_cam=d.T_world_cam, timestamps=d.timestamps, gripper_width=d.gripper_width,
                             contact_index=int(d.contact_index))
        return TrajProblem(demo, TrajScene(sdf=self.sdf, render_views=self.render_views, obstacle=obstacle),
                           self.cfg.traj)

    def demo(self, demo_index: int) -> DemoInfo:
        """The demo with index ``demo_index``; raises when it has no contact (cannot be augmented)."""
        if not 0 <= int(demo_index) < len(self.demos):
            raise AugmentError(f"{self.session_dir}: demo index {demo_index} out of range (0..{len(self.demos) - 1})")
        d = self.demos[int(demo_index)]
        if d.contact_index is None:
            raise AugmentError(f"{self.session_dir}: demo {d.name} has no contact frame (see "
                               f"{self.work_dir}/reconstruct/recon_report.json); set recon.contact_overrides")
        return d

    def for_demo(self, demo_index: int) -> "SessionAssets":
        """The handle whose scene (SDF, Gaussians, render views, overlay mask) serves demo ``demo_index``: a
        session has one scene, so itself (a plain dataset's :class:`~umi_aug.augment.dataset_source.DatasetAssets`
        returns the demo's scene group)."""
        return self

    def embodiment_failure(self, demo_index: int, episode) -> str | None:
        """Why the robot cannot execute a planned :class:`umi_aug.traj.AugmentedEpisode` (None: it can, or the
        input knows no robot — a UMI session's hand-held gripper; a simulated robot's input overrides this)."""
        return None

    def umi_episode(self, episode, demo_index: int | None = None) -> dict[str, np.ndarray]:
        """UMI replay-buffer keys of an :class:`umi_aug.traj.AugmentedEpisode` of demo ``demo_index`` (no
        images; sources whose originals carry more keys than UMI's use the demo index to fill them)."""
        return episode.umi_episode()

    @property
    def augmentable(self) -> list[int]:
        """Indices of the demos that have a contact frame."""
        return [d.index for d in self.demos if d.contact_index is not None]


def session_fingerprint(session_dir: Path) -> str:
    """Content hash of what the stages read from a session: every file under ``demos/`` and ``calibration/``
    (CSV/JSON/intrinsics whole, videos by size + first/last MiB), ``dataset_plan.pkl`` and ``dataset.zarr.zip``'s
    entries with their CRCs (:func:`umi_aug.data.fingerprint.content_fingerprint`): an in-place edit of the same
    size changes it."""
    from umi_aug.data.fingerprint import content_fingerprint, file_fingerprint

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
    from umi_aug.recon.pipeline import reconstruct_session

    rcfg = dataclasses.replace(cfg.recon, cone_half_angle_deg=cfg.cone_half_angle_deg)

    def fn(out: Path):
        o = reconstruct_session(session_dir, out, rcfg)
        info = {k: o.report[k] for k in ("sfm", "cloud", "sdf", "timings_s")}
        info["sfm"] = {k: v for k, v in info["sfm"].items() if k != "config"}
        return ({"cloud": "scene_cloud.ply", "sdf": "scene_sdf.npz", "report": "recon_report.json"},
                ["scene_cloud.ply", "scene_sdf.npz", "recon_report.json"], info)

    return run_stage("reconstruct", work, rcfg, {"session": fp}, fn)


def _stage_contact(work: Path, recon: StageResult, sess, overrides: dict[str, int], pregrasp_m: float
                   ) -> StageResult:
    """Per demo: the detected contact frame (reconstruction report, or an override) and the splice frame — the
    last frame at or before it whose gripper clearance to the reconstructed SDF is at least ``pregrasp_m`` (the
    pre-contact pose the new trajectories funnel into; frames from it on are replayed)."""
    from umi_aug.io_utils import atomic_write_text
    from umi_aug.recon.contact import gripper_clearance
    from umi_aug.recon.sdf_grid import VoxelSDF

    def fn(out: Path):
        report = json.loads(recon.path("report").read_text())
        found = {c["episode"]: c for c in report.get("contacts", [])}
        sdf = VoxelSDF.load(recon.path("sdf"))
        rows = []
        for i, d in enumerate(sess.demos):
            c = found.get(d.name, {})
            idx = overrides.get(d.name, c.get("contact_index"))
            splice = None
            if idx is None:
                log.warning("contact: demo %s has no contact frame (%s); it is not augmented", d.name,
                            c.get("message", "not in the reconstruction report"))
            else:
                clr, _ = gripper_clearance(sdf, d.T_world_cam[: int(idx) + 1], d.gripper_width[: int(idx) + 1])
                ok = np.flatnonzero(clr[1:] >= pregrasp_m) + 1
                splice = int(ok[-1]) if len(ok) else None
                if splice is None:
                    log.warning("contact: demo %s: no frame before contact %d keeps %.3f m clearance; not augmented",
                                d.name, idx, pregrasp_m)
            rows.append({"index": i, "name": d.name, "contact_index": None if idx is None else int(idx),
                         "splice_index": splice, "overridden": d.name in overrides})
        atomic_write_text(out / "contacts.json", json.dumps(rows, indent=2) + "\n")
        return {"contacts": "contacts.json"}, ["contacts.json"], {"demos": rows}

    return run_stage("contact", work, {"overrides": dict(sorted(overrides.items())), "pregrasp_m": pregrasp_m},
                     {"reconstruct": recon.key}, fn)


def _init_only_gaussians(cloud_path: Path, sh_degree: int):
    """Isotropic Gaussians at the SfM points (σ = mean distance to the 3 nearest neighbours), no optimisation."""
    from scipy.spatial import cKDTree

    from umi_aug.recon.cloud import read_ply as read_cloud
    from umi_aug.splat import Gaussians

    cloud = read_cloud(cloud_path)
    if len(cloud) < 4:
        raise AugmentError(f"{cloud_path}: {len(cloud)} points; too few to initialise Gaussians")
    d, _ = cKDTree(cloud.points).query(cloud.points, k=4)
    sigma = np.clip(d[:, 1:].mean(axis=1), 1e-3, 0.05)
    return Gaussians.from_points(cloud.points, cloud.colors / 255.0, sigma, opacity=0.8, sh_degree=sh_degree)


def _stage_splat(session_dir: Path, work: Path, cfg: AugmentConfig, fp: str, recon: StageResult,
                 contact: StageResult, progress: bool, beside_training: Callable[[], object] | None = None
                 ) -> StageResult:
    """The scene's 3DGS stage; ``beside_training`` is called right before the training starts (not when the stage
    is cached or untrained): work that should use the core the training leaves idle."""
    sc = cfg.splat

    def fn(out: Path):
        if sc.iterations == 0:
            from umi_aug.splat import write_ply

            log.warning("splat: iterations = 0 → the SfM-initialised Gaussians are used without optimisation")
            write_ply(out / "scene.ply", _init_only_gaussians(recon.path("cloud"), sc.sh_degree))
            return {"ply": "scene.ply"}, ["scene.ply"], {"trained": False}
        try:
            from umi_aug.splat.train import SplatTrainConfig
            from umi_aug.splat.train_session import train_splat_from_session
        except ImportError as exc:
            raise AugmentError("the splat stage needs umi_aug.splat.train (fisheye 3DGS training); it is not "
                               f"importable here ({exc}); set splat.iterations = 0 for an untrained scene") from exc
        tcfg = SplatTrainConfig(iterations=sc.iterations, max_gaussians=sc.max_gaussians, sh_degree=sc.sh_degree,
                                holdout_every=sc.holdout_every, seed=cfg.seed, **dict(sc.extra))
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

    return run_stage("splat", work, {"splat": sc, "seed": cfg.seed},
                     {"session": fp, "reconstruct": recon.key, "contact": contact.key}, fn)


def _f(v) -> float | None:
    try:
        return None if v is None else float(v)
    except (TypeError, ValueError):
        return None


def _stage_gripper_mask(work: Path, cfg: AugmentConfig, fp: str, dataset: Path, demos: list[DemoInfo],
                        contact: StageResult) -> StageResult:
    import cv2

    from umi_aug.augment.overlay import choose_overlay_mask
    from umi_aug.data import ReplayBuffer
    from umi_aug.recon.pipeline import first_close_index

    S = cfg.image_size

    def fn(out: Path):
        frames = []
        with ReplayBuffer.open(dataset) as buf:
            if "camera0_rgb" not in buf:
                raise AugmentError(f"{dataset}: no key 'data/camera0_rgb'; the gripper overlay needs the originals")
            shape = tuple(buf["camera0_rgb"].shape[1:])
            if shape != (S, S, 3):
                raise AugmentError(f"{dataset}: key 'data/camera0_rgb' has frames {shape}, but image_size = {S}; "
                                   f"export at the dataset's resolution (--image-size {shape[0]})")
            for d in demos:
                end = d.contact_index if d.contact_index is not None else first_close_index(d.gripper_width)
                end = len(d.gripper_width) if end is None else int(end)
                sl = buf.get_episode_slice(d.index)
                idx = np.linspace(0, max(0, end - 1), min(end, 48)).round().astype(int)
                # only these frames are decoded (one chunk per frame), not the whole episode
                uniq, inv = np.unique(idx, return_inverse=True)
                frames.append(buf["camera0_rgb"].get_orthogonal_selection((uniq + sl.start,))[inv])
        mask, info = choose_overlay_mask(np.concatenate(frames), S, cfg.overlay.mask, cfg.overlay.std_threshold,
                                         cfg.overlay.min_coverage)
        np.save(out / "mask.npy", mask)
        cv2.imwrite(str(out / "mask.png"), mask.astype(np.uint8) * 255)
        return {"mask": "mask.npy", "png": "mask.png"}, ["mask.npy", "mask.png"], info

    # "rule": bump when choose_overlay_mask's rule changes, so cached masks of the old rule are rebuilt
    return run_stage("gripper_mask", work, {"overlay": cfg.overlay, "image_size": S, "rule": OVERLAY_MASK_RULE},
                     {"session": fp, "contact": contact.key}, fn)


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
    from umi_aug.recon.session_io import load_session

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
    from umi_aug.augment.preflight import check_demo_trajectories

    check_demo_trajectories(sess)  # a lost row or a pose jump in an episode's frames: named, not a "collision"
    fp = session_fingerprint(session_dir)
    if renders:  # a bad asset name or mesh fails here, before any stage runs (their Gaussians are fitted later)
        check_obstacle_assets(cfg)
    if renders:  # a cold numba cache compiles the 3DGS kernels in a child process while SfM runs
        from umi_aug.splat.warmup import start_background_compile

        start_background_compile()
    stages: dict[str, StageResult] = {}
    try:
        stages["reconstruct"] = recon = _stage_reconstruct(session_dir, work, cfg, fp)
        stages["contact"] = contact = _stage_contact(work, recon, sess, dict(cfg.recon.contact_overrides),
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
            stages["gripper_mask"] = gm = _stage_gripper_mask(work, cfg, fp, dataset, demos, contact)
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
