"""A plain UMI replay buffer (``*.zarr.zip`` / zarr directory, no session folder) as augmentation input.

UMI's published datasets hold only the policy frames (``camera0_rgb``, ``S x S``, gripper polygon blacked out),
TCP poses in the table-tag frame, gripper widths and ``meta/episode_ends``: no scan, no raw video. Per scene group
(one episode by default; ``scene_group = N`` consecutive episodes, or an explicit map) this module builds what
:class:`~umi_aug.augment.session_assets.SessionAssets` needs, each step a cached stage under
``<work>/scenes/<group>/`` (:mod:`umi_aug.augment.cache`), one group at a time (never all scenes in memory;
``prepare_dataset(lazy=True)``, as the export runs it: a group is built when its first episode is generated):

1. ``scene`` — camera poses ``T_world_cam = T_world_tcp @ inv(T_cam_tcp)`` (UMI's fixed offset, ``tcp_offset``
   configurable, :func:`umi_aug.geometry.umi_T_cam_tcp`); the episodes' frames before the gripper first closes
   (the scene is static there) → known-pose triangulation at the policy intrinsics
   (:func:`umi_aug.recon.sfm.run_sfm`, gripper/mirror pixels masked) → cleaned cloud → SDF over the reachable
   region → contact per episode (proximity + grasp onset, :func:`umi_aug.recon.contact.detect_contact`; an
   episode whose sparse cloud never comes within the threshold falls back to the grasp onset from the widths);
2. ``contact`` — the splice frame (:func:`umi_aug.augment.stages.contact_stage`, as every source);
3. ``splat`` — fisheye 3DGS on the group's own pre-splice frames (every ``view_stride``-th; every
   ``holdout_every``-th view held out), loss masked by UMI's gripper/mirror/finger polygons, initialised from
   the triangulated cloud, topped up with random points, plus an optional far-background shell
   (:func:`background_shell_points`);
4. ``gripper_mask`` — the overlay mask (:func:`umi_aug.augment.stages.gripper_mask_stage`, as every source).

:class:`umi_aug.augment.sources.dataset.DatasetSource` is this input's
:class:`~umi_aug.augment.sources.base.InputSource` (what ``umi-aug augment DATASET`` runs).

:func:`check_dataset` rejects a bad dataset (missing keys, wrong image size, NaN poses, lost-tracking jumps)
with ONE error naming the key and episode before anything is computed.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import cv2
import numpy as np
from tqdm import tqdm

from umi_aug.augment.cache import StageResult, build_lock, run_stage
from umi_aug.augment.config import AugmentConfig, splat_key
from umi_aug.augment.obstacle_stage import check_obstacle_assets
from umi_aug.augment.prefetch import import_in_background
from umi_aug.augment.preflight import MAX_STEP_DEG, MAX_STEP_M
from umi_aug.augment.scene_grouping import group_by_place
from umi_aug.augment.session_assets import OBSTACLE_WORK_KEY, DemoInfo, SessionAssets, drop_process_cache
from umi_aug.augment.stages import contact_stage, gripper_mask_stage, init_only_gaussians
from umi_aug.camera.calib_io import gopro_intrinsics_2_7k
from umi_aug.data import ReplayBuffer, make_umi_episode
from umi_aug.data.fingerprint import content_fingerprint
from umi_aug.data.rows import read_rows, shared_decoded_chunks
from umi_aug.data.validate import (FROZEN_ANGLE_RAD, FROZEN_MIN_STEPS, FROZEN_STEP_M, first_frozen_step,
                                   gripper_width_problem)
from umi_aug.errors import AugmentError, UmiAugError
from umi_aug.geometry import pos_rotvec_to_pose
from umi_aug.geometry.umi import camera_poses_from_tcp_poses, umi_T_cam_tcp
from umi_aug.io_utils import atomic_write_text
from umi_aug.recon import constants as RC
from umi_aug.recon.cloud import SceneCloud, clean_cloud, inside_camera_body, read_ply, write_ply
from umi_aug.recon.contact import detect_contact
from umi_aug.recon.pipeline import first_close_index
from umi_aug.recon.sdf_grid import build_scene_sdf, reachable_region
from umi_aug.recon.sfm import feature_mask, run_sfm

__all__ = ["DatasetInput", "DatasetAssets", "DatasetCheck", "is_dataset_path", "check_dataset",
           "parse_episodes", "parse_scene_group", "scene_groups", "dataset_fingerprint", "prepare_dataset", "background_shell_points",
           "REQUIRED_KEYS"]

log = logging.getLogger(__name__)

#: Keys a plain UMI dataset must hold (robot 0, camera 0).
REQUIRED_KEYS: tuple[str, ...] = ("camera0_rgb", "robot0_eef_pos", "robot0_eef_rot_axis_angle",
                                  "robot0_gripper_width")
#: Shortest episode that can be augmented (frames).
MIN_EPISODE_FRAMES: int = 16
#: Cloud points further than this outside the reachable region are left out of the SDF (metres).
SDF_CROP_M: float = 0.15
#: What a dataset scene's stages after the triangulation import (on a thread while it runs: _stage_scene):
#: the cloud clean-up's open3d, the distance field's KD-tree and the pictures' matplotlib (not pyplot, which picks a
#: backend on import: augment.pictures sets Agg first); with renders, torch and the 3DGS trainer.
_LATER_MODULES: tuple[str, ...] = ("open3d", "scipy.spatial", "matplotlib.figure", "matplotlib.backends.backend_agg")
_SPLAT_MODULES: tuple[str, ...] = ("torch", "umi_aug.splat.train", "umi_aug.splat.train_session",
                                   "umi_aug.splat.renderer", "umi_aug.splat.compose")
#: Groups whose heavy members (SDF, Gaussians, problems) stay loaded per process.
_MAX_LOADED_GROUPS = 2
_LOADED: list[str] = []


@dataclass(frozen=True)
class DatasetInput:
    """How a plain replay buffer becomes scenes.

    Attributes:
        tcp_offset_m: UMI's ``tcp_offset`` (gripper tip to mounting screw, metres) of ``T_cam_tcp``.
        episodes: the episodes to augment (None: all); the others are copied unchanged.
        scene_group: N > 1 → N consecutive episodes (``index // N``) share one scene; ``"auto"`` → episodes
            recorded in one place share a scene, found from the data (:mod:`umi_aug.augment.scene_grouping`: SIFT
            matches of frames at nearby poses that agree with those poses' epipolar geometry), at most
            ``max_scene_episodes`` per scene.
        scene_map: explicit groups ``{group name: [episode, ...]}`` (overrides ``scene_group``); episodes not
            named get a scene of their own.
        sfm_stride: every n-th pre-closing frame enters the triangulation (4: on the real cup episode a quarter
            of every 2nd frame's time at the same 3DGS quality; on the synthetic session -0.3 dB held-out and up to
            -0.6 dB at far cone starts: docs/real_scale.md sections 1, 1b and 5).
        sfm_upscale: frames are enlarged this many times (bicubic) for SIFT: 224² policy frames give few
            features (563 points on the real cup episode at x1).
        sfm_pose_pairs: besides each frame's sequential neighbours and the loop grid (which spans every episode of a
            pooled scene), the triangulation also matches every two frames whose known poses are close
            (``SfmConfig.pose_pair_max_dist_m`` / ``_deg``). Off by default: on the real cup episode that is 194 of
            416 pairs and a third of the triangulation time, at the same held-out PSNR without them (+0.03 dB over 3
            seeds); on the synthetic session they cost 0.4-0.75 dB at every cone start for one demo's scene and
            0.03-0.31 dB for two demos pooled (-0.11 dB held-out there; docs/real_scale.md 1i).
        sfm_known_pose_verification: the triangulation keeps the matches that agree with the two frames' known poses
            (``SfmConfig.known_pose_verification``) instead of COLMAP's two-view RANSAC. Off by default: on the real
            cup episode it gives the same held-out PSNR over 3 seeds (+0.04 dB; 1380 points instead of 1444) with
            the matching and triangulation in ~0.6-0.8x the time, but on the synthetic session (one seed) its scene
            renders the cone starts 0.4-0.9 dB worse (docs/real_scale.md 1j).
        view_stride: every n-th pre-splice frame is a 3DGS view.
        background_points: Gaussians on the far-background shell (0 = none).
        background_radius: shell radius in multiples of the cameras' spread (≥ 3).
        max_step_m / max_step_deg: lost-tracking jump thresholds per frame.
    """

    tcp_offset_m: float = 0.205
    episodes: tuple[int, ...] | None = None
    scene_group: int | str = 1
    max_scene_episodes: int = 4
    scene_map: Mapping[str, Sequence[int]] | None = None
    sfm_stride: int = 4
    sfm_upscale: int = 2
    sfm_pose_pairs: bool = False
    sfm_known_pose_verification: bool = False
    view_stride: int = 1
    background_points: int = 4000
    background_radius: float = 8.0
    max_step_m: float = MAX_STEP_M
    max_step_deg: float = MAX_STEP_DEG

    @property
    def T_cam_tcp(self) -> np.ndarray:
        return umi_T_cam_tcp(tcp_offset=self.tcp_offset_m)


def is_dataset_path(path: str | os.PathLike) -> bool:
    """True for a ``*.zarr.zip`` / ``*.zip`` file or a zarr directory with ``data/`` and ``meta/`` groups (and no
    ``demos/``, i.e. not a session folder)."""
    p = Path(path)
    if p.is_file():
        return p.name.endswith(".zip")
    return p.is_dir() and not (p / "demos").is_dir() and (p / "data").is_dir() and (p / "meta").is_dir()


def parse_episodes(spec: str | None) -> tuple[int, ...] | None:
    """``"0:50"`` / ``"3"`` / ``"0,2,5:8"`` → sorted episode indices (None for None/"" = all)."""
    if spec is None or str(spec).strip() == "":
        return None
    out: set[int] = set()
    for part in str(spec).split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?::\s*(\d+)\s*)?", part)
        if not m:
            raise AugmentError(f"--episodes {spec!r}: expected 'A:B' (B exclusive), 'A' or a comma list of them")
        a = int(m.group(1))
        b = int(m.group(2)) if m.group(2) is not None else a + 1
        if b <= a:
            raise AugmentError(f"--episodes {spec!r}: empty range {a}:{b}")
        out.update(range(a, b))
    return tuple(sorted(out))


def load_scene_map(path: str | os.PathLike) -> dict[str, list[int]]:
    """A JSON scene map: ``{"kitchen": [0, 1, 2], "desk": [3]}`` or ``[[0, 1, 2], [3]]``."""
    try:
        raw = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise AugmentError(f"{path}: cannot read the scene map JSON ({exc})") from exc
    if isinstance(raw, list):
        raw = {f"group_{i:04d}": v for i, v in enumerate(raw)}
    if not isinstance(raw, dict) or not all(isinstance(v, list) and all(isinstance(e, int) for e in v)
                                            for v in raw.values()):
        raise AugmentError(f"{path}: scene map must be {{name: [episode, ...]}} or [[episode, ...], ...]")
    return {str(k): list(v) for k, v in raw.items()}


def parse_scene_group(value: Any) -> int | str | None:
    """A scene-group setting as typed (``--scene-group``, ``aug.scene_group``): ``"auto"`` (any case: group by
    place) or an int >= 1 (episodes per scene); None when it is neither."""
    if str(value).strip().lower() == "auto":
        return "auto"
    if isinstance(value, bool):
        return None
    try:
        n = int(value)
    except (TypeError, ValueError):
        return None
    return n if n >= 1 and float(value) == n else None


def scene_groups(n_episodes: int, selected: Sequence[int], inp: DatasetInput,
                 by_place: Callable[[list[int]], dict[str, list[int]]] | None = None) -> dict[str, list[int]]:
    """``{group name: [episode, ...]}`` covering the ``selected`` episodes (ordered by first episode).
    ``by_place``: the grouping of ``scene_group = "auto"`` (episodes → groups), for the episodes the scene map
    leaves."""
    groups: dict[str, list[int]] = {}
    owner: dict[int, str] = {}
    if inp.scene_map:
        for name, eps in inp.scene_map.items():
            for e in eps:
                if not 0 <= int(e) < n_episodes:
                    raise AugmentError(f"scene map group {name!r}: episode {e} outside 0..{n_episodes - 1}")
                if int(e) in owner:
                    raise AugmentError(f"scene map: episode {e} is in groups {owner[int(e)]!r} and {name!r}")
                owner[int(e)] = str(name)
    if inp.scene_group == "auto":
        if by_place is None:
            raise AugmentError("scene_groups: scene_group 'auto' needs the place grouping (by_place)")
        owner.update({e: g for g, eps in by_place([int(e) for e in selected if int(e) not in owner]).items()
                      for e in eps})
        n = 1
    elif isinstance(inp.scene_group, str) or int(inp.scene_group) < 1:
        raise AugmentError(f"scene_group {inp.scene_group!r}: expected an int >= 1 or 'auto'")
    else:
        n = int(inp.scene_group)
    for e in selected:
        g = owner.get(e, f"ep{e:06d}" if n == 1 else f"eps{(e // n) * n:06d}-{(e // n) * n + n - 1:06d}")
        groups.setdefault(g, []).append(int(e))
    return dict(sorted(groups.items(), key=lambda kv: min(kv[1])))


@dataclass
class DatasetCheck:
    """What :func:`check_dataset` read (small arrays only).

    Attributes:
        n_episodes, episode_ends, image_size: the dataset's layout.
        T_world_tcp / gripper_width / fps: per selected episode ([T, 4, 4] metres, [T] metres, frames/s).
    """

    n_episodes: int
    episode_ends: np.ndarray
    image_size: int
    T_world_tcp: dict[int, np.ndarray] = field(default_factory=dict)
    gripper_width: dict[int, np.ndarray] = field(default_factory=dict)


def check_dataset(path: str | os.PathLike, image_size: int, inp: DatasetInput) -> DatasetCheck:
    """Read and check a plain UMI dataset before any compute; ONE :class:`AugmentError` naming the key/episode.

    Checks: readable; keys :data:`REQUIRED_KEYS` present; ``camera0_rgb`` uint8 ``[N, S, S, 3]`` with
    ``S = image_size``; lowdim lengths = ``episode_ends[-1]``; per selected episode: at least
    :data:`MIN_EPISODE_FRAMES` frames, finite poses and widths, no lost-tracking jump (consecutive TCP poses more
    than ``max_step_m`` / ``max_step_deg`` apart) and no frozen-pose run (identical poses = SLAM holding the last
    pose).
    """
    p = Path(path)
    if not p.exists():
        raise AugmentError(f"{p}: no such dataset")
    try:
        buf = ReplayBuffer.open(p, check_values=False)  # NaN checked below, per episode (named)
    except UmiAugError as exc:
        raise AugmentError(f"{p}: not a readable UMI replay buffer ({exc})") from exc
    with buf:
        missing = [k for k in REQUIRED_KEYS if k not in buf]
        if missing:
            raise AugmentError(f"{p}: missing key(s) {['data/' + k for k in missing]} (have {buf.keys()}); a UMI "
                               f"dataset from 07_generate_replay_buffer holds {list(REQUIRED_KEYS)}")
        img = buf["camera0_rgb"]
        if img.dtype != np.uint8 or img.ndim != 4 or tuple(img.shape[1:]) != (image_size, image_size, 3):
            raise AugmentError(f"{p}: key 'data/camera0_rgb' is {img.dtype} {tuple(img.shape)}; expected uint8 "
                               f"(N, {image_size}, {image_size}, 3) (--image-size {image_size}; pass the "
                               f"dataset's own size)")
        ends = np.asarray(buf.episode_ends, np.int64)
        E = len(ends)
        if E == 0:
            raise AugmentError(f"{p}: 'meta/episode_ends' is empty (no episodes)")
        for k in REQUIRED_KEYS:
            if buf[k].shape[0] != ends[-1]:
                raise AugmentError(f"{p}: key 'data/{k}' has {buf[k].shape[0]} rows, 'meta/episode_ends' ends at "
                                   f"{ends[-1]}")
        sel = range(E) if inp.episodes is None else inp.episodes
        bad = [e for e in sel if not 0 <= e < E]
        if bad:
            raise AugmentError(f"{p}: --episodes {bad[:5]} outside the dataset's 0..{E - 1}")
        pos_all = np.asarray(buf["robot0_eef_pos"][:], np.float64)
        rot_all = np.asarray(buf["robot0_eef_rot_axis_angle"][:], np.float64)
        w_all = np.asarray(buf["robot0_gripper_width"][:], np.float64).reshape(len(pos_all), -1)[:, 0]
    out = DatasetCheck(E, ends, image_size)
    starts = np.concatenate([[0], ends[:-1]])
    for e in range(E):  # every episode is copied into the output: none may hold NaN
        a, b = int(starts[e]), int(ends[e])
        for k, v in (("robot0_eef_pos", pos_all[a:b]), ("robot0_eef_rot_axis_angle", rot_all[a:b]),
                     ("robot0_gripper_width", w_all[a:b])):
            fin = np.isfinite(v.reshape(b - a, -1)).all(axis=1)
            if not fin.all():
                raise AugmentError(f"{p}: episode {e}: key 'data/{k}' holds NaN/Inf at step {int(np.argmin(fin))} "
                                   f"(row {a + int(np.argmin(fin))}); repair the dataset or drop the episode")
    problem = gripper_width_problem(w_all, ends)  # copied episodes included: the output trains on them
    if problem:
        raise AugmentError(f"{p}: key 'data/robot0_gripper_width' {problem}")
    for e in sel:
        a, b = int(starts[e]), int(ends[e])
        where = f"{p}: episode {e} (rows {a}..{b - 1})"
        if b - a < MIN_EPISODE_FRAMES:
            raise AugmentError(f"{where}: {b - a} frames; an augmentable episode needs >= {MIN_EPISODE_FRAMES} "
                               f"(leave it out with --episodes)")
        pos, rot = pos_all[a:b], rot_all[a:b]
        step = np.linalg.norm(np.diff(pos, axis=0), axis=1)
        T = pos_rotvec_to_pose(np.concatenate([pos, rot], axis=1))
        R_rel = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])
        ang = np.degrees(np.arccos(np.clip((np.trace(R_rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
        jump = np.flatnonzero((step > inp.max_step_m) | (ang > inp.max_step_deg))
        if len(jump):
            i = int(jump[0])
            raise AugmentError(f"{where}: key 'data/robot0_eef_pos'/'robot0_eef_rot_axis_angle' jumps "
                               f"{step[i]:.3f} m / {ang[i]:.1f} deg between steps {i} and {i + 1} (a lost-tracking "
                               f"gap; limits {inp.max_step_m} m, {inp.max_step_deg} deg per frame); split or drop "
                               f"the episode (--episodes)")
        i = first_frozen_step(pos, rot)  # within a tolerance: round-off turns identical poses by ~1e-8 rad
        if i is not None:
            raise AugmentError(f"{where}: key 'data/robot0_eef_pos' is frozen (identical poses within "
                               f"{FROZEN_STEP_M} m / {FROZEN_ANGLE_RAD} rad) from step {i} for >= "
                               f"{FROZEN_MIN_STEPS} frames: tracking was lost and the last pose held; drop the "
                               f"episode (--episodes)")
        out.T_world_tcp[e] = T
        out.gripper_width[e] = w_all[a:b].copy()
    return out


def dataset_fingerprint(path: str | os.PathLike) -> str:
    """Content hash of the dataset (:func:`umi_aug.data.fingerprint.content_fingerprint`: zip entries with their
    CRC-32s, or a directory's files): an in-place edit of the same size changes it."""
    return content_fingerprint(path)


def background_shell_points(T_world_cam: np.ndarray, n: int, radius: float, rng: np.random.Generator,
                            forward_only: bool = True) -> np.ndarray:
    """``n`` points on a sphere of radius ``radius x`` (camera spread, ≥ 0.5 m) around the mean camera centre,
    in the directions the cameras look (half-space of the mean optical axis when ``forward_only``): Gaussians for
    the far background (sky, trees) that SfM cannot triangulate and that otherwise end up as floaters near the
    cameras. World frame, metres."""
    T = np.asarray(T_world_cam, np.float64).reshape(-1, 4, 4)
    c = T[:, :3, 3]
    spread = max(0.5, float(np.linalg.norm(c - c.mean(0), axis=1).max()))
    d = rng.normal(size=(int(n) * 3, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if forward_only:
        fwd = T[:, :3, 2].mean(0)
        fwd /= max(np.linalg.norm(fwd), 1e-9)
        d = d[d @ fwd > -0.2]
    return c.mean(0) + radius * spread * d[: int(n)]


# ---------------------------------------------------------------------------------------------------- handle
@dataclass
class DatasetAssets(SessionAssets):
    """:class:`SessionAssets` of a plain dataset: one scene per group; :meth:`for_demo` gives the handle of the
    demo's group (its SDF, Gaussians, render views, overlay mask) that the per-episode functions use, building the
    group's stages first if this handle has not (:meth:`build_group`: cached on disk, so another process or a
    later run only reads them).

    Attributes (besides the base ones): group_of: {episode: group name}; groups: {group: [episode, ...]};
    group_paths: {group: paths}; group_views: {group: [V, 4, 4] render views}; group_masks: {group: [S, S]
    bool} (the groups built so far); T_cam_tcp: [4, 4]; build: what :meth:`build_group` needs.
    """

    group_of: dict[int, str] = field(default_factory=dict)
    group_paths: dict[str, dict[str, str]] = field(default_factory=dict)
    group_views: dict[str, np.ndarray] = field(default_factory=dict)
    group_masks: dict[str, np.ndarray] = field(default_factory=dict)
    T_cam_tcp: np.ndarray = field(default_factory=lambda: np.eye(4))
    groups: dict[str, list[int]] = field(default_factory=dict)
    build: dict[str, Any] = field(default_factory=dict)

    def build_group(self, g: str) -> None:
        """Build (or load from the stage cache) group ``g``'s scene and record its paths, views, mask and the
        splice frames of its episodes."""
        if g in self.group_paths:
            return
        if g not in self.groups:
            raise AugmentError(f"{self.session_dir}: no scene group {g!r} (groups: {sorted(self.groups)[:8]})")
        b = self.build
        gd = {e: EpisodePoses(self.demos[e].name, self.demos[e].T_world_cam, self.demos[e].gripper_width)
              for e in self.groups[g]}
        fps = {e: 1.0 / float(np.median(np.diff(self.demos[e].timestamps))) if len(gd[e].gripper_width) > 1
               else 59.94 for e in gd}
        res = _build_group(self.session_dir, self.work_dir, b["fp"], g, gd, fps, self.cfg, b["inp"], b["renders"],
                           b["progress"], b["extra"])
        for e, c in res["contact"].items():
            self.demos[e].contact_index = None if c is None else int(c)
        self.group_views[g], self.group_masks[g] = res["views"], res["mask"]
        self.stages.update(res["stages"])
        if not self.mask_info:
            self.mask_info = res["mask_info"]
        self.group_paths[g] = res["paths"]

    def scene_to_build(self, demo_index: int) -> str | None:
        """The demo's scene group, unless this handle has built it already."""
        g = self.group_of.get(int(demo_index))
        return None if g is None or g in self.group_paths else g

    def build_scene(self, key: str) -> Path:
        self.build_group(key)
        return self.work_dir / "scenes" / key

    @property
    def augmentable(self) -> list[int]:
        """Selected episodes with a splice frame, and those of groups not built yet (not known)."""
        return [e for e in sorted(self.group_of)
                if self.group_of[e] not in self.group_paths or self.demos[e].contact_index is not None]

    def for_demo(self, demo_index: int) -> SessionAssets:
        g = self.group_of.get(int(demo_index))
        if g is None:
            raise AugmentError(f"{self.session_dir}: episode {demo_index} was not selected for augmentation")
        self.build_group(g)
        sa = SessionAssets(self.session_dir, self.work_dir, self.cfg, self.intrinsics, self.demos,
                           self.group_views[g], self.group_masks[g], self.mask_info, dict(self.group_paths[g]),
                           self.stages)
        cid = sa.cache_id
        if cid in _LOADED:
            _LOADED.remove(cid)
        _LOADED.append(cid)
        while len(_LOADED) > _MAX_LOADED_GROUPS:  # never all scenes in memory
            drop_process_cache(_LOADED.pop(0))
        sa.use_process_cache(cid)
        return sa

    def umi_episode(self, episode, demo_index: int | None = None) -> dict[str, np.ndarray]:
        """UMI keys of an augmented episode with THIS dataset's camera→TCP offset."""
        return make_umi_episode(np.asarray(episode.T_world_cam) @ self.T_cam_tcp, episode.gripper_width)


# ------------------------------------------------------------------------------------------------------ stages
def _policy_intrinsics(image_size: int):
    return gopro_intrinsics_2_7k().umi_policy(image_size)


def _read_frames(dataset: Path, episode: int, idx: np.ndarray) -> np.ndarray:
    with ReplayBuffer.open(dataset) as buf:
        sl = buf.get_episode_slice(int(episode))
        arr = buf["camera0_rgb"]
        # their chunks decoded on the cores, once per process: the triangulation, the 3DGS views, the gripper mask
        # and the overlay originals read many of the same frames
        return read_rows(arr, np.asarray(idx, np.int64) + sl.start, cache=shared_decoded_chunks())


@dataclass
class EpisodePoses:
    """What a scene group's stages read of one episode (``stages.contact_stage`` among them): its name, camera
    poses ``T_world_cam`` [N, 4, 4] (m, the group's frame) and gripper widths [N] (m)."""

    name: str
    T_world_cam: np.ndarray
    gripper_width: np.ndarray


def _stage_scene(work: Path, dataset: Path, fp: str, eps: list[int], demos: dict[int, EpisodePoses],
                 fps: dict[int, float], cfg: AugmentConfig, inp: DatasetInput,
                 prefetch: Sequence[str] = ()) -> tuple[StageResult, threading.Thread | None]:
    """Known-pose triangulation + cloud of one group (outputs as the session reconstruction's). ``prefetch``:
    modules the later stages import, imported on a thread while the triangulation runs on one core
    (:mod:`umi_aug.augment.prefetch`). Returns the stage and that thread (None: the stage was cached)."""
    started: list[threading.Thread] = []
    # known poses always (the TCP poses are the SLAM's); the same key whatever sfm.mode the caller left
    sfm_fields: dict = {} if inp.sfm_pose_pairs else {"pose_pair_max_dist_m": 0.0}
    if inp.sfm_known_pose_verification:
        sfm_fields["known_pose_verification"] = True
    rc = dataclasses.replace(cfg.recon, cone_half_angle_deg=cfg.cone_half_angle_deg,
                             sfm=dataclasses.replace(cfg.recon.sfm, mode="known_poses", **sfm_fields))
    up = max(1, int(inp.sfm_upscale))
    intr = _policy_intrinsics(cfg.image_size * up)

    def fn(out: Path):
        frames_dir = out / "frames"
        frames_dir.mkdir(parents=True, exist_ok=True)
        paths, names, T, lengths, free = [], [], [], [], []
        for e in eps:
            d = demos[e]
            end = first_close_index(d.gripper_width)
            end = len(d.gripper_width) if end is None else max(int(end), 2)
            free.append(d.T_world_cam[:end])
            idx = np.arange(0, end, max(1, inp.sfm_stride))
            imgs = _read_frames(dataset, e, idx)
            for i, im in zip(idx, imgs):
                fpth = frames_dir / f"{d.name}_{int(i):05d}.png"
                if up > 1:
                    im = cv2.resize(im, (intr.width, intr.height), interpolation=cv2.INTER_CUBIC)
                cv2.imwrite(str(fpth), cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
                paths.append(fpth)
                names.append(f"{d.name}/{int(i):05d}.png")
                T.append(d.T_world_cam[int(i)])
            lengths.append(len(idx))
        try:
            sfm = run_sfm(paths, names, intr, out / "colmap", rc.sfm, sequence_lengths=lengths,
                          T_world_cam=np.stack(T), masks=feature_mask(intr),
                          before_mapping=(lambda: started.append(import_in_background(prefetch))) if prefetch
                          else None)
        finally:
            import shutil

            shutil.rmtree(frames_dir, ignore_errors=True)
            shutil.rmtree(out / "colmap", ignore_errors=True)
        keep = (sfm.track_length >= RC.MIN_TRACK_LENGTH) & (sfm.errors_px <= RC.MAX_POINT_ERROR_PX)
        # where the camera went before the grasp no scene point can be (artefacts; they faked contacts)
        body = inside_camera_body(sfm.points, np.concatenate(free))
        keep &= ~body
        # no radius-outlier removal: a single demo's cloud is sparse, isolated points are still real surface
        cloud = clean_cloud(sfm.points[keep], sfm.colors[keep], sfm.view_dirs[keep], radius_m=0.0)
        write_ply(out / "scene_cloud.ply", cloud)
        info = {"sfm": {"mode": sfm.mode, "frames": len(names), "registered": int(sfm.registered.sum()),
                        "points3D": int(len(sfm.points)), "mean_reproj_error_px": sfm.mean_reproj_error_px,
                        "timings_s": sfm.timings_s},
                "cloud": {"points": len(cloud), "inside_camera_body": int(body.sum())}}
        atomic_write_text(out / "sfm_report.json", json.dumps(info, indent=2, default=float) + "\n")
        return {"cloud": "scene_cloud.ply", "sfm_report": "sfm_report.json"}, ["scene_cloud.ply"], info

    conf = {"recon": rc, "image_size": cfg.image_size, "sfm_stride": inp.sfm_stride, "up": up,
            "tcp": inp.tcp_offset_m}
    # version 2: no cloud points inside the camera's own path (recon.cloud.inside_camera_body)
    st = run_stage("scene", work, conf, {"dataset": fp, "episodes": ",".join(map(str, eps))}, fn, version=2)
    return st, (started[0] if started else None)


def _stage_sdf(work: Path, dataset: Path, scene: StageResult, eps: list[int], demos: dict[int, EpisodePoses],
               fps: dict[int, float], cfg: AugmentConfig) -> StageResult:
    """SDF of one group over the reachable region + contact per episode (``recon_report.json`` as the session
    reconstruction writes it).

    The field is UNSIGNED (distance to the nearest cloud point minus half a voxel diagonal): a single demo's sparse
    cloud (mostly far background, few table points) has normals too poor for the inside/outside vote, which put
    the demo's own camera path 17 cm "inside" on the real cup episode. Points further than ``SDF_CROP_M`` outside
    the region are left out. A trajectory cannot tunnel through a surface without coming within the clearance.
    """
    rc = dataclasses.replace(cfg.recon, cone_half_angle_deg=cfg.cone_half_angle_deg)

    def fn(out: Path):
        theta = np.radians(rc.cone_half_angle_deg)
        boxes = []
        for e in eps:
            d = demos[e]
            c = first_close_index(d.gripper_width)
            boxes.append(reachable_region(d.T_world_cam, len(d.gripper_width) - 1 if c is None else c, theta,
                                          rc.cone_radius_m))
        lo, hi = np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)
        cloud = read_ply(scene.path("cloud"))
        inside = ((cloud.points >= lo - SDF_CROP_M) & (cloud.points <= hi + SDF_CROP_M)).all(axis=1)
        if inside.sum() < 50:
            raise AugmentError(f"{dataset}: episodes {eps}: {int(inside.sum())} of {len(cloud)} triangulated points "
                               f"lie near the reachable region; too little of the scene around the gripper to "
                               f"check collisions")
        near = SceneCloud(cloud.points[inside], cloud.colors[inside], cloud.normals[inside])
        sdf = build_scene_sdf(near, lo, hi, rc.voxel_m, rc.inflation_m, max_voxels=rc.max_voxels, signed=False)
        sdf.save(out / "scene_sdf.npz")
        contacts = []
        for e in eps:
            d = demos[e]
            c = detect_contact(sdf, d.T_world_cam, d.gripper_width, fps[e], rc.contact_threshold_m, rc.contact_rule,
                               rc.contact_overrides.get(d.name), d.name)
            row = {"episode": d.name, "contact_index": c.contact_index, "proximity_index": c.proximity_index,
                   "grasp_onset_index": c.grasp_onset_index, "rule": c.rule, "overridden": c.overridden,
                   "min_clearance_m": float(c.clearance.min()), "message": c.message}
            if c.contact_index is None:  # a sparse cloud of a single demo: fall back to the grasp onset
                onset = first_close_index(d.gripper_width)
                if onset is not None:
                    row.update(contact_index=int(onset), rule="grasp (no proximity in the sparse cloud)")
                    log.warning("contact: %s: %s; using the grasp onset %d", d.name, c.message, onset)
            contacts.append(row)
        report = {"dataset": str(dataset), "episodes": eps, "frame": "world = UMI table-tag frame, z up, metres",
                  "sdf": {"lo": sdf.bounds[0].tolist(), "hi": sdf.bounds[1].tolist(), "voxel_m": sdf.voxel,
                          "shape": list(sdf.shape), "points": int(inside.sum()), "signed": False},
                  "contacts": contacts}
        atomic_write_text(out / "recon_report.json", json.dumps(report, indent=2, default=float) + "\n")
        return ({"sdf": "scene_sdf.npz", "report": "recon_report.json"}, ["scene_sdf.npz", "recon_report.json"],
                {"sdf": report["sdf"], "contacts": contacts})

    # version 2: later approaches gate the grasp search too (recon.contact.detect_contact)
    return run_stage("sdf", work, {"recon": rc, "crop": SDF_CROP_M}, {"scene": scene.key}, fn, version=2)


def dataset_views(dataset: Path, demos: dict[int, EpisodePoses], splice: dict[int, int], image_size: int,
                  stride: int = 1, mask_finger: bool = True):
    """3DGS views of a group: each episode's frames ``0..splice`` (every ``stride``-th) at the policy intrinsics,
    loss mask = valid image circle minus UMI's gripper/mirror(/finger) polygons, and not the black pixels UMI's
    pipeline painted. Returns ``(views, intrinsics)``."""
    # lazy, start-up: torch
    from umi_aug.splat.train import TrainView
    from umi_aug.splat.train_session import loss_mask

    intr = _policy_intrinsics(image_size)
    base = loss_mask(intr, finger=mask_finger)
    views = []
    for e, d in demos.items():
        if e not in splice:
            continue
        idx = np.arange(0, int(splice[e]) + 1, max(1, int(stride)))
        for i, im in zip(idx, _read_frames(dataset, e, idx)):
            views.append(TrainView(f"{d.name}/{int(i):05d}", im, d.T_world_cam[int(i)], base.copy()))
    return views, intr


def _stage_splat(work: Path, dataset: Path, fp: str, demos: dict[int, EpisodePoses], scene: StageResult,
                 contact: StageResult, cfg: AugmentConfig, inp: DatasetInput, progress: bool) -> StageResult:
    # lazy, start-up: torch
    from umi_aug.splat import write_ply
    from umi_aug.splat.train import SplatTrainConfig, train_splat
    from umi_aug.splat.train_session import read_point_cloud, top_up_init_points

    sc = cfg.splat

    def fn(out: Path):
        rows = json.loads(contact.path("contacts").read_text())
        by_name = {r["name"]: r for r in rows}
        splice = {e: int(by_name[d.name]["splice_index"]) for e, d in demos.items()
                  if by_name.get(d.name, {}).get("splice_index") is not None}
        if not splice:
            raise AugmentError(f"{dataset}: episodes {sorted(demos)}: no splice frame (see {contact.dir}); nothing "
                               f"to train the scene on")
        if sc.iterations == 0:
            write_ply(out / "scene.ply", init_only_gaussians(scene.path("cloud"), sc.sh_degree))
            return {"ply": "scene.ply"}, ["scene.ply"], {"trained": False}
        views, intr = dataset_views(dataset, demos, splice, cfg.image_size, inp.view_stride)
        tcfg = SplatTrainConfig(seed=cfg.seed, **sc.train_kwargs())
        rng = np.random.default_rng([cfg.seed, 0x1A17])
        Tv = np.stack([v.T_world_cam for v in views])
        xyz, rgb = read_point_cloud(scene.path("cloud"))
        if len(xyz) > sc.max_gaussians // 2:
            keep = np.sort(rng.choice(len(xyz), sc.max_gaussians // 2, replace=False))
            xyz, rgb = xyz[keep], (None if rgb is None else rgb[keep])
        n_bg = min(int(inp.background_points), sc.max_gaussians // 4)
        if n_bg > 0:
            bg = background_shell_points(Tv, n_bg, inp.background_radius, rng)
            bg_rgb = np.full((len(bg), 3), float(np.median(np.stack([v.image for v in views[::8]]))) / 255.0)
            rgb = rng.uniform(0, 1, (len(xyz), 3)) if rgb is None else rgb
            xyz, rgb = np.concatenate([xyz, bg]), np.concatenate([rgb, bg_rgb])
        floor = int(0.5 * sc.max_gaussians)
        if len(xyz) < floor:
            xyz, rgb = top_up_init_points(xyz, rgb, floor, Tv, rng)
        res = train_splat(views, intr, xyz, rgb, tcfg, out, progress=progress)
        rel = Path(res.ply_path).resolve().relative_to(out.resolve()).as_posix()
        info = {"trained": True, "views": len(views), "heldout_psnr": float(res.heldout_psnr),
                "heldout_ssim": float(res.heldout_ssim), "gaussians": int(res.gaussians.n),
                "train_seconds": float(res.history[-1]["seconds"]) if res.history else None}
        return {"ply": rel}, [rel], info

    conf = {"splat": splat_key(sc), "seed": cfg.seed, "view_stride": inp.view_stride, "bg": (inp.background_points,
                                                                                  inp.background_radius)}
    return run_stage("splat", work, conf, {"dataset": fp, "scene": scene.key, "contact": contact.key}, fn)


def _build_group(dataset: Path, work: Path, fp: str, g: str, gd: dict[int, EpisodePoses], fps: dict[int, float],
                 cfg: AugmentConfig, inp: DatasetInput, renders: bool, progress: bool, extra_paths: dict[str, str]
                 ) -> dict[str, Any]:
    """Build (or find cached under ``<work>/scenes/<g>/``) one group's stages: ``{paths, views, mask, mask_info,
    contact: {episode: splice frame or None}, stages}``."""
    gw = work / "scenes" / g
    eps = sorted(gd)
    with build_lock(gw):
        try:
            scene, importing = _stage_scene(gw, dataset, fp, eps, gd, fps, cfg, inp,
                                            _LATER_MODULES + (_SPLAT_MODULES if renders else ()))
            sdf_st = _stage_sdf(gw, dataset, scene, eps, gd, fps, cfg)
            contact = contact_stage(gw, sdf_st, [gd[e] for e in eps], dict(cfg.recon.contact_overrides),
                                    cfg.pregrasp_clearance_m)
            if importing is not None:
                importing.join()  # before any worker is forked (umi_aug.augment.prefetch)
            rows = json.loads(contact.path("contacts").read_text())
            contact_idx = {e: r["splice_index"] for e, r in zip(eps, rows)}
            paths = {"sdf": str(sdf_st.path("sdf")), "cloud": str(scene.path("cloud")), "dataset": str(dataset)}
            stages = {f"{g}/scene": scene, f"{g}/sdf": sdf_st, f"{g}/contact": contact}
            mask, mask_info = np.zeros((cfg.image_size, cfg.image_size), bool), {}
            if renders:
                splat = _stage_splat(gw, dataset, fp, gd, scene, contact, cfg, inp, progress)
                infos = [DemoInfo(e, gd[e].name, gd[e].T_world_cam, np.zeros(0), gd[e].gripper_width,
                                  contact_idx[e]) for e in eps]
                gm = gripper_mask_stage(gw, cfg, fp, dataset, infos, contact)
                paths["splat"] = str(splat.path("ply"))
                mask, mask_info = np.load(gm.path("mask")), gm.info
                stages[f"{g}/splat"], stages[f"{g}/gripper_mask"] = splat, gm
        except UmiAugError as exc:
            raise AugmentError(f"scene group {g} (episodes {eps}): stage failed: {exc}") from exc
    paths.update(extra_paths)
    views = [gd[e].T_world_cam[: contact_idx[e] + 1] for e in eps if contact_idx[e] is not None]
    return {"paths": paths, "views": np.concatenate(views) if views else np.zeros((0, 4, 4)), "mask": mask,
            "mask_info": mask_info, "contact": contact_idx, "stages": stages}


def _groups_by_place(dataset: Path, work: Path, chk: DatasetCheck, episodes: list[int], image_size: int,
                     inp: DatasetInput, progress: bool) -> dict[str, list[int]]:
    """``scene_group = "auto"``: :func:`umi_aug.augment.scene_grouping.group_by_place` over the episodes' frames
    before the gripper first closes; the groups and every comparison's evidence go to
    ``<work>/scene_groups.json`` (to read, or to edit into a ``--scene-map``)."""
    T = {}
    for e in episodes:
        Tc = camera_poses_from_tcp_poses(chk.T_world_tcp[e], inp.T_cam_tcp)
        c = first_close_index(chk.gripper_width[e])
        T[e] = Tc[: len(Tc) if c is None else max(int(c), 2)]
    intr = _policy_intrinsics(image_size)
    with ReplayBuffer.open(dataset) as buf:
        start = {e: buf.get_episode_slice(e).start for e in episodes}
        frames = buf["camera0_rgb"]
        groups, evidence = group_by_place(episodes, T, lambda e, f: np.asarray(frames[start[e] + int(f)]), intr,
                                          feature_mask(intr), max_group=inp.max_scene_episodes, progress=progress)
    work.mkdir(parents=True, exist_ok=True)
    rows = [{"a": ev.episode_a, "b": ev.episode_b, "same_place": ev.same_place, "frame_pairs": ev.frame_pairs,
             "matches": ev.matches, "epipolar_inliers": ev.inliers} for ev in evidence]
    atomic_write_text(work / "scene_groups.json", json.dumps({"groups": groups, "evidence": rows}, indent=1) + "\n")
    log.info("scene groups by place: %d episodes in %d scenes (%s)", len(episodes), len(groups),
             work / "scene_groups.json")
    return groups


def prepare_dataset(dataset: str | os.PathLike, work_dir: str | os.PathLike, cfg: AugmentConfig,
                    inp: DatasetInput = DatasetInput(), *, renders: bool = True, progress: bool = True,
                    lazy: bool = False) -> DatasetAssets:
    """Check the dataset, then build (or reuse from ``work_dir``) each selected group's scene, one at a time.

    Args:
        dataset: plain UMI replay buffer (``*.zarr.zip`` or zarr directory).
        work_dir: stage cache (``scenes/<group>/<stage>/``).
        cfg: :class:`AugmentConfig` (``image_size`` must be the dataset's).
        inp: :class:`DatasetInput`.
        renders: False → plan only (no 3DGS / mask / obstacle Gaussians).
        lazy: build nothing here: a group's scene is built (or loaded from its cache) the first time one of its
            episodes is generated (:meth:`DatasetAssets.for_demo`, in whichever process runs the episode), so
            a run over ~1400 episodes starts at once and never holds more than a couple of scenes. Until then
            the group's episodes count as augmentable (their contact frames are not known yet).
    Raises:
        AugmentError: a bad dataset (before any compute) or a failed stage (named with its group).
    """
    dataset, work = Path(dataset), Path(work_dir)
    chk = check_dataset(dataset, cfg.image_size, inp)
    fp = dataset_fingerprint(dataset)
    selected = sorted(chk.T_world_tcp)
    T_cam_tcp = inp.T_cam_tcp
    groups = scene_groups(chk.n_episodes, selected, inp,
                          lambda eps: _groups_by_place(dataset, work, chk, eps, cfg.image_size, inp, progress))
    fps = 59.94  # UMI keeps every frame of the GoPro's 59.94 fps video
    work.mkdir(parents=True, exist_ok=True)
    stages: dict[str, StageResult] = {}
    extra: dict[str, str] = {}
    if renders and "obstacle" in cfg.modes:  # each asset's Gaussians are fitted when an episode first uses it
        check_obstacle_assets(cfg)
        extra = {OBSTACLE_WORK_KEY: str(work)}
    demos = []
    ends = chk.episode_ends
    for e in range(chk.n_episodes):
        if e in chk.T_world_tcp:
            Tc, w = camera_poses_from_tcp_poses(chk.T_world_tcp[e], T_cam_tcp), chk.gripper_width[e]
        else:  # not selected: copied as is, never augmented (poses not needed)
            n = int(ends[e] - (ends[e - 1] if e else 0))
            Tc, w = np.tile(np.eye(4), (n, 1, 1)), np.zeros(n)
        demos.append(DemoInfo(e, f"episode_{e:06d}", Tc, np.arange(len(w)) / fps, w, None))
    group_of = {e: g for g, eps in groups.items() for e in eps}
    assets = DatasetAssets(dataset, work, cfg, gopro_intrinsics_2_7k(), demos, np.zeros((0, 4, 4)),
                           np.zeros((cfg.image_size, cfg.image_size), bool), {}, {"dataset": str(dataset), **extra},
                           stages, group_of=group_of, T_cam_tcp=T_cam_tcp, groups=groups,
                           build={"fp": fp, "inp": inp, "renders": renders, "progress": progress, "extra": extra})
    if not lazy:
        for g in tqdm(list(groups), desc="scenes", unit="group", disable=not progress or len(groups) < 2):
            assets.build_group(g)
        first = group_of[selected[0]] if selected else None
        if first is not None:  # the base handle shows the first group's scene (as a session's handle its one)
            assets.render_views, assets.gripper_mask = assets.group_views[first], assets.group_masks[first]
            assets.paths = {"dataset": str(dataset), **assets.group_paths[first]}
    return assets


def describe(assets: DatasetAssets) -> dict[str, Any]:
    """Per group: episodes, cloud points, contact/splice frames and the 3DGS held-out metrics (JSON)."""
    out = {}
    for g in assets.group_paths:
        eps = sorted(e for e, gg in assets.group_of.items() if gg == g)
        row: dict[str, Any] = {"episodes": eps}
        for k in ("scene", "sdf", "contact", "splat"):
            st = assets.stages.get(f"{g}/{k}")
            if st is not None:
                row[k] = st.info
        out[g] = row
    return out
