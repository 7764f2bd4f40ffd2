"""The light, picklable handle the episode loop, the planner and the renderer use: :class:`SessionAssets`.

Every input source's ``prepare`` returns one (:mod:`umi_aug.augment.sources`): a UMI session's
(:func:`umi_aug.augment.sources.session.prepare_session`), a plain dataset's
(:class:`~umi_aug.augment.dataset_source.DatasetAssets`: one scene per group) or a registered kind's (square
demos' ``SquareAssets`` in ``umi_aug.square.source``: one scene per demo); :meth:`SessionAssets.for_demo` gives
the handle of a demo's scene. It keeps paths and small arrays; the heavy things (scene Gaussians, SDF, original
dataset, obstacle models, trajectory problems) load lazily, once per process (shared by the handles of one scene:
:meth:`SessionAssets.use_process_cache`), and are dropped when pickled.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from umi_aug.augment.cache import StageResult
from umi_aug.augment.config import AugmentConfig, config_hash
from umi_aug.augment.obstacle_stage import load_obstacle_asset, obstacle_lock, obstacle_stage
from umi_aug.augment.overlay import overlay_alpha
from umi_aug.camera.intrinsics import FisheyeIntrinsics
from umi_aug.errors import AugmentError, UmiAugError
from umi_aug.recon.sdf_grid import VoxelSDF
from umi_aug.traj import Demonstration, TrajProblem, TrajScene

__all__ = ["DemoInfo", "SessionAssets", "OBSTACLE_WORK_KEY", "drop_process_cache"]

#: ``SessionAssets.paths`` key of the folder whose ``obstacles/`` holds the per-asset obstacle stages.
OBSTACLE_WORK_KEY = "obstacle_work"

log = logging.getLogger(__name__)

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
            the per-asset obstacle stages; stages: StageResult per stage its source's ``prepare`` ran.
        memo: this process's lazily made members, key → value (not pickled; :meth:`use_process_cache` shares it
            between handles of one scene). :meth:`memoized` fills it; a module may keep a value it derives from
            the assets here under a key of its own.
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
    memo: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["memo"] = {}
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.use_process_cache()  # copies unpickled in one process (one per task of an executor) share them

    @property
    def cache_id(self) -> str:
        """Identity of the lazily loaded members (their files and the config)."""
        return config_hash(sorted(self.paths.items()), self.cfg)

    def use_process_cache(self, key: str | None = None) -> None:
        """Load the heavy members into (and read them from) this process's cache under ``key`` (default
        :attr:`cache_id`), shared with every other handle of that key — a handle made per demo of one scene
        (:meth:`for_demo`) loads the scene once. :func:`drop_process_cache` frees a key."""
        self.memo = _PROCESS_CACHE.setdefault(self.cache_id if key is None else key, {})

    @property
    def policy_intrinsics(self) -> FisheyeIntrinsics:
        """Intrinsics of the ``S x S`` policy images (UMI full-height centre crop, resized)."""
        return self.intrinsics.umi_policy(self.cfg.image_size)

    # -------------------------------------------------------------------------------------- lazy members
    def memoized(self, key: str, make: Callable[[], Any]) -> Any:
        """``memo[key]``, made by ``make()`` on first use in this process."""
        if key not in self.memo:
            self.memo[key] = make()
        return self.memo[key]

    @property
    def overlay_alpha(self) -> np.ndarray:
        """[S, S] float32 gripper-overlay alpha (the mask feathered by ``cfg.overlay.feather_px``)."""
        return self.memoized("overlay_alpha", lambda: overlay_alpha(self.gripper_mask, self.cfg.overlay.feather_px))

    @property
    def rendered_pixels(self) -> np.ndarray:
        """[S, S] bool: the pixels of a new frame that show the render (overlay alpha < 1); the others are the
        original frame's after :func:`~umi_aug.augment.overlay.composite_overlay`, so they need no render."""
        return self.memoized("rendered_pixels", lambda: np.ascontiguousarray(self.overlay_alpha < 1.0))

    @property
    def sdf(self):
        """The reconstructed scene SDF (:class:`umi_aug.recon.VoxelSDF`)."""
        return self.memoized("sdf", lambda: VoxelSDF.load(self.paths["sdf"]))

    @property
    def gaussians(self):
        """The scene's 3DGS (:class:`umi_aug.splat.Gaussians`, float32)."""
        from umi_aug.splat import read_ply  # lazy, start-up: torch

        return self.memoized("gaussians", lambda: read_ply(self.paths["splat"]))

    @property
    def original(self):
        """The session's original replay buffer (read-only, lazy chunk access). Opened once per process: a
        forked child re-opens it, as a zip file handle shared across a fork shares its read offset (concurrent reads
        then fail with ``BadZipFile``)."""
        from umi_aug.data import ReplayBuffer  # lazy, start-up: zarr

        if self.memo.get("original_pid") != os.getpid():
            self.memo["original"] = ReplayBuffer.open(self.paths["dataset"])
            self.memo["original_pid"] = os.getpid()
        return self.memo["original"]

    def original_frames(self, demo_index: int, frames: np.ndarray | slice, shared: bool = False) -> np.ndarray:
        """Original policy frames ``[K, S, S, 3]`` uint8 of demo ``demo_index``. ``shared``: through this process's
        :func:`umi_aug.data.rows.shared_decoded_chunks` (frames the scene's stages decoded are not decoded again)."""
        from umi_aug.data.rows import read_rows, shared_decoded_chunks  # lazy, start-up: zarr

        sl = self.original.get_episode_slice(int(demo_index))
        rows = np.arange(sl.start, sl.stop)[frames] if isinstance(frames, slice) else (
            np.asarray(frames, dtype=np.int64) + sl.start)
        # only these frames, decoded on the cores
        return read_rows(self.original["camera0_rgb"], rows, cache=shared_decoded_chunks() if shared else None)

    def original_lowdim(self, demo_index: int) -> dict[str, np.ndarray]:
        """Every non-image key of demo ``demo_index``'s original episode, as stored (key → ``[H, ...]`` rows)."""
        from umi_aug.data import schema  # lazy, start-up: zarr

        buf = self.original
        sl = buf.get_episode_slice(int(demo_index))
        return {k: np.asarray(buf[k][sl]) for k in buf.keys() if not schema.is_image_key(k)}

    def obstacle_gaussians(self, asset: str):
        """Gaussians of obstacle ``asset`` in its object frame: its ``obstacles/<asset>`` stage, fitted on first
        use (in any process) and read from the cache after."""
        from umi_aug.splat import read_ply  # lazy, start-up: torch

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

        return self.memoized(f"obstacle/{asset}", load)

    def obstacle_asset(self, asset: str):
        """The :class:`umi_aug.recon.ObstacleAsset` named ``asset`` (procedural name or mesh path)."""
        return self.memoized(f"asset/{asset}", lambda: load_obstacle_asset(asset))

    def traj_problem(self, demo_index: int):
        """The free-space :class:`umi_aug.traj.TrajProblem` of a demo (built once per process)."""
        return self.memoized(f"problem/{demo_index}", lambda: self.make_problem(demo_index, None))

    def make_problem(self, demo_index: int, obstacle):
        """A :class:`TrajProblem` of demo ``demo_index`` with an optional :class:`umi_aug.traj.ConvexObstacle`."""
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

    def scene_to_build(self, demo_index: int) -> str | None:
        """The scene that demo ``demo_index``'s episodes need built first, as a key for :meth:`build_scene` (a
        plain dataset's scene group), or None: nothing left to build (a session's one scene is built by
        ``prepare``). The export runs each key's build as a task of its own, ahead of its episodes."""
        return None

    def build_scene(self, key: str) -> Path:
        """Build (or load from the stage cache) the scene ``key`` of :meth:`scene_to_build`; returns the folder
        its stages are written to (under :attr:`work_dir`)."""
        raise AugmentError(f"{self.session_dir}: this input has no scenes built per key (asked for {key!r})")


def drop_process_cache(key: str) -> None:
    """Free the heavy members this process loaded under ``key`` (:meth:`SessionAssets.use_process_cache`); a handle
    still using them keeps them until it is dropped, a new one loads them again."""
    _PROCESS_CACHE.pop(key, None)
