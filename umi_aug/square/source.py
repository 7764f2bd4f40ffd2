"""Square-task demos (``umi-aug square-demos`` output) as augmentation input: the simulator's UMI session.

A square demo folder holds the same demos twice: a robomimic fisheye hdf5 (MuJoCo states, env meta) and a UMI
replay buffer (``camera0_rgb`` policy frames, TCP = grip-site poses, widths; root attribute ``T_cam_tcp``). What
the augmentation needs per demo (:class:`~umi_aug.augment.session_assets.SessionAssets`) comes from the simulator
instead of a reconstruction, each step a cached stage (:mod:`umi_aug.augment.cache`) under the work dir:

1. ``square_demos`` — per demo: the nut pose and the splice frame. The splice frame is the expert's pre-contact
   pose — the first frame whose grip site is within the expert's own tolerance of its pre-grasp hover pose
   (:func:`umi_aug.square.expert.expert_pregrasp_pose`, computed from the nut as it lies in that frame); the
   augmentation funnels into it and replays the demo from there (contact, grasp, insertion). The scene's exact
   signed distance field at that frame (table, pegs, nut; robot left out: :func:`umi_aug.sim.scene_sdf.scene_sdf`)
   is stored per demo.
2. ``square_scene`` — the scene model (:mod:`umi_aug.square.scene`): ONE static-scene fisheye 3DGS from a
   simulated wrist-camera scan plus ONE nut asset, composited at each demo's nut pose (square scenes differ only
   in the nut's pose).
3. ``gripper_mask`` — the overlay mask (the Panda fingers' static pixels in the demos' pre-contact frames;
   :func:`umi_aug.augment.stages.gripper_mask_stage`, as every source).

:class:`SquareSource` is this input's :class:`~umi_aug.augment.sources.base.InputSource`. Importing this module
registers the kind ``square`` with :func:`umi_aug.augment.sources.register_source` (detector
:func:`is_square_demos`, factory :func:`open_square`, the ``umi-aug augment`` flags ``--episodes`` /
``--no-embodiment`` → :class:`SquareInput`): asked after a plain dataset and before the default, a UMI session, as
when it was built in. ``umi-aug augment`` imports it before it looks at its input (``umi_aug/cli.py``).

Embodiment: every planned trajectory is checked on the simulated Panda (IK along the path, joint limits and
speeds, no collision before the splice: :func:`umi_aug.square.feasibility.check_panda_path`); an infeasible
one counts as a failed attempt and the next start pose is sampled (the rate is in the export's failure reasons).
"""

from __future__ import annotations

import json
import os
import pickle
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from umi_aug.augment.cache import StageResult, run_stage
from umi_aug.augment.config import AugmentConfig, config_hash
from umi_aug.augment.dataset_source import parse_episodes
from umi_aug.augment.overlay import composite_overlay
from umi_aug.augment.render import render_view
from umi_aug.augment.session_assets import DemoInfo, SessionAssets
from umi_aug.augment.sources import register_source
from umi_aug.augment.stages import gripper_mask_stage
from umi_aug.camera.calib_io import gopro_intrinsics_2_7k
from umi_aug.data import ReplayBuffer, make_umi_episode
from umi_aug.data.fingerprint import content_fingerprint
from umi_aug.data.schema import ACTION_KEY
from umi_aug.errors import AugmentError, UmiAugError
from umi_aug.geometry import pos_rotvec_to_pose, transform_points
from umi_aug.geometry.gripper import CollisionSpheres
from umi_aug.geometry.umi import camera_poses_from_tcp_poses
from umi_aug.sim.pointcloud import sample_geom_points
from umi_aug.sim.scene_sdf import scene_sdf
from umi_aug.square.commands import path_command_targets
from umi_aug.square.env import GRIP_SITE, NUT_BODY, SquareEnv
from umi_aug.square.expert import ExpertConfig, expert_pregrasp_pose, pregrasp_error
from umi_aug.square.feasibility import FeasibilityConfig, check_panda_path, render_gt_frames
from umi_aug.square.init_configs import source_states_from_hdf5
from umi_aug.square.scan import ROBOT_BODY_PREFIXES
from umi_aug.square.scene import SCENE_VERSION, SquareSceneConfig, build_square_scene, demo_gaussians
from umi_aug.traj import Demonstration, TrajProblem, TrajScene

__all__ = ["SquareInput", "SquareSource", "SquareAssets", "check_square_demos", "prepare_square", "is_square_demos",
           "open_square", "square_input_from_cli", "square_umi_episode", "gt_render_function",
           "spartn_render_function", "ROBOT_BODY_PREFIXES"]

#: The square env's control rate (frames per second of the demos).
SQUARE_FPS: float = 20.0


@dataclass(frozen=True)
class SquareInput:
    """How a square demo folder becomes augmentation input.

    Attributes:
        episodes: the demos to augment (None: all); the others are still copied when the export includes
            originals.
        scene: :class:`umi_aug.square.scene.SquareSceneConfig` fields to override (dict, hashed).
        embodiment: check every trajectory on the simulated Panda (False: the UMI gripper's collision spheres only).
        feasibility: :class:`umi_aug.square.feasibility.FeasibilityConfig` fields to override (dict).
    """

    episodes: tuple[int, ...] | None = None
    scene: dict[str, Any] = field(default_factory=dict)
    embodiment: bool = True
    feasibility: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SquareDemoFiles:
    """The files of a square demo folder: ``hdf5`` (robomimic, states), ``zarr`` (UMI), ``n`` demos, image ``size``."""

    root: Path
    hdf5: Path
    zarr: Path
    n: int
    size: int


def is_square_demos(path: str | os.PathLike) -> bool:
    """A folder with the ``report.json`` that ``umi-aug square-demos`` / ``square-convert`` write."""
    p = Path(path) / "report.json"
    if not p.is_file():
        return False
    try:
        return {"hdf5", "zarr"} <= set(json.loads(p.read_text()).get("paths", {}))
    except (OSError, ValueError, AttributeError):
        return False


def check_square_demos(demos_dir: str | os.PathLike, image_size: int | None = None) -> SquareDemoFiles:
    """Check a ``umi-aug square-demos`` / ``square-convert`` folder before any compute (ONE error naming the file).

    Raises:
        AugmentError: no ``report.json``/paths, a missing file, demo counts that differ between the hdf5 and the
            zarr, frames of another size than ``image_size``, no ``T_cam_tcp`` root attribute.
    """
    import h5py  # lazy, optional dependency: h5py

    root = Path(demos_dir)
    rep_path = root / "report.json"
    try:
        rep = json.loads(rep_path.read_text())
        paths = rep["paths"]
        hdf5, zarr = _resolve(root, paths["hdf5"]), _resolve(root, paths["zarr"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise AugmentError(f"{rep_path}: not a square demo folder's report (expected JSON with "
                           f"paths.hdf5 and paths.zarr, as `umi-aug square-demos` writes): {exc}") from None
    for p in (hdf5, zarr):
        if not p.exists():
            raise AugmentError(f"{rep_path}: lists {p}, which does not exist")
    try:
        with h5py.File(hdf5, "r") as f:
            n_h5 = len([k for k in f["data"].keys() if k.startswith("demo_")])
    except (OSError, KeyError) as exc:
        raise AugmentError(f"{hdf5}: not a robomimic hdf5 with data/demo_* ({exc})") from None
    try:
        with ReplayBuffer.open(zarr) as buf:
            n_z = buf.n_episodes
            shape = tuple(buf["camera0_rgb"].shape[1:])
            T_cam_tcp = buf.root.attrs.get("T_cam_tcp")
    except (UmiAugError, KeyError, OSError) as exc:
        raise AugmentError(f"{zarr}: not a UMI replay buffer with data/camera0_rgb ({exc})") from None
    if n_h5 != n_z:
        raise AugmentError(f"{root}: {hdf5.name} holds {n_h5} demos but {zarr.name} holds {n_z} episodes")
    if T_cam_tcp is None:
        raise AugmentError(f"{zarr}: no root attribute 'T_cam_tcp' (the camera→TCP offset the square writer stores)")
    if len(shape) != 3 or shape[0] != shape[1] or shape[2] != 3:
        raise AugmentError(f"{zarr}: key 'data/camera0_rgb' has frames {shape}; expected S x S x 3")
    if image_size is not None and shape[0] != int(image_size):
        raise AugmentError(f"{zarr}: key 'data/camera0_rgb' has {shape[0]}² frames, but image_size = {image_size}; "
                           f"export at the demos' resolution (--image-size {shape[0]})")
    return SquareDemoFiles(root, hdf5, zarr, n_z, shape[0])


def _resolve(root: Path, p: str) -> Path:
    """A report path: absolute, relative to the folder, or relative to where `square-demos` ran (the folder's
    parent-relative form ``<out>/<name>`` it writes)."""
    q = Path(p)
    if q.is_absolute():
        return q
    return root / q.name if (root / q.name).exists() or not q.exists() else q


def _env_meta(hdf5: Path) -> dict[str, Any]:
    return json.loads(source_states_from_hdf5(hdf5)[1])


def _demo_states(hdf5: Path, index: int) -> np.ndarray:
    import h5py  # lazy, optional dependency: h5py

    with h5py.File(hdf5, "r") as f:
        return np.asarray(f[f"data/demo_{int(index)}/states"][()], dtype=np.float64)


def _robot_bodies(model) -> list[str]:
    import mujoco  # lazy, optional dependency: mujoco

    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) or "" for b in range(model.nbody)]
    return [n for n in names if n.startswith(ROBOT_BODY_PREFIXES)]


def _robot_state_indices(model) -> tuple[np.ndarray, np.ndarray]:
    """Indices into robosuite's flat state ``[time, qpos, qvel]`` of the robot's joint positions and velocities."""
    import mujoco  # lazy, optional dependency: mujoco

    q, v = [], []
    for j in range(model.njnt):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or ""
        if name.startswith(ROBOT_BODY_PREFIXES):
            nq = {0: 7, 1: 4}.get(int(model.jnt_type[j]), 1)
            nv = {0: 6, 1: 3}.get(int(model.jnt_type[j]), 1)
            q += list(range(1 + int(model.jnt_qposadr[j]), 1 + int(model.jnt_qposadr[j]) + nq))
            v += list(range(1 + model.nq + int(model.jnt_dofadr[j]), 1 + model.nq + int(model.jnt_dofadr[j]) + nv))
    return np.asarray(q, np.int64), np.asarray(v, np.int64)


def _set_state(env, state: np.ndarray) -> None:
    """Restore a flat robosuite state and update the kinematics (no physics step)."""
    import mujoco  # lazy, optional dependency: mujoco

    env.rs.sim.set_state_from_flattened(np.asarray(state, dtype=np.float64))
    mujoco.mj_forward(env.model, env.data)


def splice_index(T_world_site: np.ndarray, T_world_nut: np.ndarray, table_z: float) -> int | None:
    """First frame whose grip site is within the expert's ``approach`` tolerance of its pre-grasp pose.

    Args:
        T_world_site: np.ndarray,  # [T, 4, 4] grip-site (TCP) poses
        T_world_nut: np.ndarray,  # [T, 4, 4] nut poses in the same frames
        table_z: table-top height, metres.
    Returns:
        the frame index, or None when the demo never reaches its pre-grasp pose.
    """
    ec = ExpertConfig()
    for t in range(len(T_world_site)):
        dp, dr = pregrasp_error(T_world_site[t], expert_pregrasp_pose(T_world_nut[t], table_z, ec))
        if dp <= ec.pos_tol and dr <= ec.rot_tol:
            return t
    return None


#: Bodies whose collision geoms make the gripper's collision spheres (camera frame) for the trajectory optimiser.
GRIPPER_SPHERE_BODIES: tuple[str, ...] = ("robot0_right_hand", "gripper0_")
#: Spheres covering the Panda hand + fingers, and padding (m) added to each sphere's radius.
N_GRIPPER_SPHERES: int = 14
SPHERE_PAD_M: float = 0.004


def panda_gripper_spheres(env, n: int = N_GRIPPER_SPHERES, pad_m: float = SPHERE_PAD_M, seed: int = 0):
    """``n`` collision spheres (camera frame, OpenCV axes) covering the Panda hand and fingers of ``env``'s current
    state: points sampled on their collision geoms, clustered (farthest-point start, then Lloyd iterations), one
    sphere per cluster (centre = the points' mean, radius = the farthest point + ``pad_m``). The trajectory
    optimiser's gripper model for square demos (the UMI gripper's spheres are another hand); the whole arm is
    checked by the Panda feasibility test."""
    import mujoco  # lazy, optional dependency: mujoco

    m = env.model
    bodies = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(b)) or "" for b in m.geom_bodyid]
    geoms = [g for g in range(m.ngeom) if bodies[g].startswith(GRIPPER_SPHERE_BODIES)
             and (m.geom_contype[g] or m.geom_conaffinity[g])]
    if not geoms:
        raise AugmentError(f"panda_gripper_spheres: no collision geom on bodies {GRIPPER_SPHERE_BODIES}")
    pts = sample_geom_points(m, env.data, geoms, np.random.default_rng(seed), density_per_m2=20000.0)["points"]
    p = transform_points(np.linalg.inv(env.wrist_pose()), pts.astype(np.float64))
    c = [p[0]]
    for _ in range(1, n):  # farthest-point start
        d = np.min(np.linalg.norm(p[:, None] - np.asarray(c)[None], axis=-1), axis=1)
        c.append(p[int(np.argmax(d))])
    c = np.asarray(c)
    for _ in range(20):  # Lloyd
        lab = np.argmin(np.linalg.norm(p[:, None] - c[None], axis=-1), axis=1)
        c = np.stack([p[lab == k].mean(axis=0) if (lab == k).any() else c[k] for k in range(n)])
    lab = np.argmin(np.linalg.norm(p[:, None] - c[None], axis=-1), axis=1)
    keep = [k for k in range(n) if (lab == k).any()]
    radii = [float(np.linalg.norm(p[lab == k] - c[k], axis=1).max()) + pad_m for k in keep]
    return CollisionSpheres(c[keep], np.array(radii), tuple(f"panda_{i}" for i in range(len(keep))))


def _stage_square_demos(work: Path, files: SquareDemoFiles, fp: str, episodes: Sequence[int]) -> StageResult:
    """Per demo: its initial state, nut pose and splice frame, the scene SDF at the splice frame (pickled), and
    the Panda gripper's collision spheres (from the first demo's start: the fingers are open before contact)."""
    def fn(out: Path):
        env = SquareEnv(env_meta=_env_meta(files.hdf5), image_size=None)
        try:
            robot = _robot_bodies(env.model)
            robot_q, robot_v = _robot_state_indices(env.model)
            table_z = float(env.rs.table_offset[2])
            rows, files_out = [], []
            with ReplayBuffer.open(files.zarr) as buf:
                ends = np.asarray(buf.episode_ends)
            for e in episodes:
                states = _demo_states(files.hdf5, e)
                n = int(ends[e] - (ends[e - 1] if e else 0))
                if len(states) != n:
                    raise AugmentError(f"{files.hdf5}: demo_{e} has {len(states)} states but {files.zarr.name} "
                                       f"episode {e} has {n} frames")
                T_site, T_nut = np.zeros((n, 4, 4)), np.zeros((n, 4, 4))
                for t in range(n):
                    _set_state(env, states[t])
                    T_site[t], T_nut[t] = env.site_pose(GRIP_SITE), env.body_pose(NUT_BODY)
                s = splice_index(T_site, T_nut, table_z)
                row = {"episode": int(e), "splice_index": s, "n_frames": n,
                       "T_world_nut": (T_nut[s] if s is not None else T_nut[0]).tolist(),
                       "sdf": None}
                if s is not None:
                    _set_state(env, states[s])
                    name = f"sdf_{e:05d}.pkl"
                    with open(out / name, "wb") as fh:
                        pickle.dump(scene_sdf(env.model, env.data, exclude_bodies=robot), fh)
                    row["sdf"] = name
                    files_out.append(name)
                # the reference state of the embodiment check and the gt render: objects as they lie at the splice
                # frame (the nut spawns above the table and settles), the arm as at the demo's start
                ref = states[s if s is not None else 0].copy()
                ref[robot_q] = states[0][robot_q]
                ref[robot_v] = 0.0
                np.save(out / f"state_ref_{e:05d}.npy", ref)
                files_out.append(f"state_ref_{e:05d}.npy")
                rows.append(row)
            _set_state(env, _demo_states(files.hdf5, episodes[0])[0])
            sph = panda_gripper_spheres(env)
            np.savez(out / "gripper_spheres.npz", centers_cam=sph.centers_cam, radii=sph.radii)
            files_out.append("gripper_spheres.npz")
        finally:
            env.close()
        (out / "demos.json").write_text(json.dumps({"table_z": table_z, "demos": rows}, indent=1))
        n_ok = sum(r["splice_index"] is not None for r in rows)
        return ({"demos": "demos.json", "spheres": "gripper_spheres.npz"}, ["demos.json", *files_out],
                {"demos": len(rows), "with_splice": n_ok, "gripper_spheres": len(sph)})

    return run_stage("square_demos", work, {"episodes": list(map(int, episodes)), "spheres": N_GRIPPER_SPHERES,
                                            "pad_m": SPHERE_PAD_M}, {"demos": fp}, fn, version=2)


# ---------------------------------------------------------------------------------------------------- handles
@dataclass
class _SquareDemoAssets(SessionAssets):
    """The handle of one demo's scene: exact SDF at its splice frame, static 3DGS + the nut at its pose."""

    sdf_path: str = ""
    T_world_nut: np.ndarray = field(default_factory=lambda: np.eye(4))
    state_ref: np.ndarray | None = None
    square: dict[str, Any] = field(default_factory=dict)

    @property
    def sdf(self):
        def load():
            with open(self.sdf_path, "rb") as fh:
                return pickle.load(fh)

        return self.memoized("sdf", load)

    @property
    def gaussians(self):
        return self.memoized("gaussians", lambda: demo_gaussians(self.square["scene"], self.T_world_nut))

    def make_problem(self, demo_index: int, obstacle):
        """The demo's :class:`umi_aug.traj.TrajProblem` with the Panda gripper's spheres (not the UMI gripper's)."""
        d = self.demo(demo_index)
        demo = Demonstration(T_world_cam=d.T_world_cam, timestamps=d.timestamps, gripper_width=d.gripper_width,
                             contact_index=int(d.contact_index))

        def spheres():
            z = np.load(Path(self.paths["square_demos"]) / "gripper_spheres.npz")
            return CollisionSpheres(z["centers_cam"], z["radii"],
                                    tuple(f"panda_{i}" for i in range(len(z["radii"]))))

        return TrajProblem(demo, TrajScene(sdf=self.sdf, render_views=self.render_views, obstacle=obstacle),
                           self.cfg.traj, spheres=self.memoized("gripper_spheres", spheres))

    def embodiment_failure(self, demo_index: int, episode) -> str | None:
        """Why the simulated Panda cannot execute ``episode``'s new frames (None: it can)."""
        if not self.square.get("embodiment", True):
            return None

        env = _process_env(self.square["env_meta"])
        cfg = FeasibilityConfig(**self.square.get("feasibility", {}))
        res = check_panda_path(env, self.state_ref, np.asarray(episode.T_world_cam), np.asarray(episode.gripper_width),
                               upto=int(episode.splice_index), cfg=cfg)
        return None if res.ok else str(res.reason)

    def umi_episode(self, episode, demo_index: int | None = None) -> dict[str, np.ndarray]:
        return square_umi_episode(self, episode, demo_index)


_ENVS: dict[str, Any] = {}


def _process_env(env_meta: dict[str, Any]):
    """One :class:`SquareEnv` (no camera) per process and env meta."""
    key = config_hash(env_meta)
    if key not in _ENVS:
        _ENVS[key] = SquareEnv(env_meta=env_meta, image_size=None)
    return _ENVS[key]


@dataclass
class SquareAssets(SessionAssets):
    """:class:`SessionAssets` of a square demo folder; :meth:`for_demo` gives the demo's scene handle."""

    demo_rows: dict[int, dict[str, Any]] = field(default_factory=dict)
    square: dict[str, Any] = field(default_factory=dict)

    def for_demo(self, demo_index: int) -> SessionAssets:
        row = self.demo_rows.get(int(demo_index))
        if row is None:
            raise AugmentError(f"{self.session_dir}: demo {demo_index} was not selected for augmentation")
        sd = Path(self.paths["square_demos"])
        h = _SquareDemoAssets(self.session_dir, self.work_dir, self.cfg, self.intrinsics, self.demos,
                              self.render_views, self.gripper_mask, self.mask_info,
                              {**self.paths, "sdf": str(sd / row["sdf"]) if row["sdf"] else ""}, self.stages,
                              sdf_path=str(sd / row["sdf"]) if row["sdf"] else "",
                              T_world_nut=np.asarray(row["T_world_nut"]),
                              state_ref=np.load(sd / f"state_ref_{int(demo_index):05d}.npy"), square=self.square)
        h.use_process_cache(config_hash(h.cache_id, int(demo_index)))
        return h

    def umi_episode(self, episode, demo_index: int | None = None) -> dict[str, np.ndarray]:
        return square_umi_episode(self, episode, demo_index)


def square_umi_episode(assets: SessionAssets, episode, demo_index: int | None) -> dict[str, np.ndarray]:
    """UMI keys of an augmented square episode (TCP = grip site) + ``action``, the commanded targets the square
    task labels with (:mod:`umi_aug.square.commands`) when the demos carry them: the new frames' targets lead
    along the planned path (:func:`~umi_aug.square.commands.path_command_targets`), the replayed frames after
    the splice keep the source demo's own commanded targets.

    Raises:
        AugmentError: the demos carry ``action`` but ``demo_index`` is not given, or its episode is too short.
    """
    T_tcp = np.asarray(episode.T_world_cam) @ assets.square["T_cam_tcp"]
    out = make_umi_episode(T_tcp, episode.gripper_width)
    original = assets.original
    if ACTION_KEY not in original:
        return out
    if demo_index is None:
        raise AugmentError(f"{assets.paths['dataset']}: the square demos carry '{ACTION_KEY}' (commanded targets); "
                           "an augmented episode's targets need its source demo's index")
    s, src_s = int(episode.splice_index), int(episode.source_contact_index)
    sl = original.get_episode_slice(int(demo_index))
    n_tail = len(T_tcp) - s - 1
    if sl.start + src_s + 1 + n_tail > sl.stop:
        raise AugmentError(f"{assets.paths['dataset']}: demo {demo_index} has {sl.stop - sl.start} steps; its "
                           f"augmented episode replays {n_tail} steps after source step {src_s}")
    arr = original[ACTION_KEY]
    act = np.empty((len(T_tcp), arr.shape[1]), dtype=arr.dtype)
    act[: s + 1] = path_command_targets(T_tcp[: s + 1], np.asarray(episode.gripper_width)[: s + 1])
    act[s + 1:] = arr[sl.start + src_s + 1: sl.start + src_s + 1 + n_tail]
    out[ACTION_KEY] = act
    return out


def prepare_square(demos_dir: str | os.PathLike, work_dir: str | os.PathLike, cfg: AugmentConfig,
                   inp: SquareInput = SquareInput(), *, progress: bool = True) -> SquareAssets:
    """Check the demo folder, then run (or reuse from ``work_dir``) the square stages.

    Raises:
        AugmentError: a bad demo folder (before any compute) or a failed stage (named).
    """
    files = check_square_demos(demos_dir, cfg.image_size)
    if "obstacle" in cfg.modes:
        raise AugmentError("square demos: only mode 'freespace' is supported (the square study's augmentation)")
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    episodes = list(range(files.n)) if inp.episodes is None else sorted(set(int(e) for e in inp.episodes))
    bad = [e for e in episodes if not 0 <= e < files.n]
    if bad:
        raise AugmentError(f"{files.root}: episodes {bad} out of range (the folder holds {files.n} demos)")
    fp = square_fingerprint(files)
    env_meta = _env_meta(files.hdf5)
    stages: dict[str, StageResult] = {}
    try:
        stages["square_demos"] = sd = _stage_square_demos(work, files, fp, episodes)
        meta = json.loads(sd.path("demos").read_text())
        rows = {int(r["episode"]): r for r in meta["demos"]}
        scene_cfg = SquareSceneConfig(**{"image_size": cfg.image_size, **inp.scene})
        state0 = np.load(sd.dir / f"state_ref_{episodes[0]:05d}.npy")
        scene = build_square_scene(work / "square_scene", env_meta, state0, scene_cfg, progress=progress)
    except UmiAugError as exc:
        raise AugmentError(f"{files.root}: stage failed: {exc}") from exc
    with ReplayBuffer.open(files.zarr) as buf:
        T_cam_tcp = np.asarray(buf.root.attrs["T_cam_tcp"], dtype=np.float64)
        ends = np.asarray(buf.episode_ends)
        pos, rot, width = (np.asarray(buf[k][:]) for k in ("robot0_eef_pos", "robot0_eef_rot_axis_angle",
                                                           "robot0_gripper_width"))

    demos = []
    for e in range(files.n):
        a, b = int(ends[e - 1]) if e else 0, int(ends[e])
        T_tcp = pos_rotvec_to_pose(np.concatenate([pos[a:b], rot[a:b]], axis=1))
        Tc = camera_poses_from_tcp_poses(T_tcp, T_cam_tcp)
        s = rows[e]["splice_index"] if e in rows else None
        demos.append(DemoInfo(e, f"demo_{e}", Tc, np.arange(b - a) / SQUARE_FPS, np.asarray(width[a:b]).reshape(-1),
                              s))
    try:
        stages["gripper_mask"] = gm = gripper_mask_stage(work, cfg, fp, files.zarr, [demos[e] for e in episodes],
                                                         sd, umi_mirrors=False)  # the Panda's wrist camera: no mirrors
    except UmiAugError as exc:
        raise AugmentError(f"{files.root}: stage gripper_mask failed: {exc}") from exc
    views = [scene.scan_T_world_cam] + [demos[e].T_world_cam[: demos[e].contact_index + 1] for e in episodes
                                        if demos[e].contact_index is not None]
    square = {"scene": scene, "env_meta": env_meta, "T_cam_tcp": T_cam_tcp, "embodiment": inp.embodiment,
              "feasibility": dict(inp.feasibility)}
    for e in range(files.n):  # demos not selected are copied, never augmented
        if e not in rows:
            demos[e].contact_index = None
    paths = {"dataset": str(files.zarr), "square_demos": str(sd.dir), "static": str(scene.static_ply),
             "nut": str(scene.nut_ply)}
    # raw GoPro intrinsics: the handle's policy_intrinsics (umi_policy(S)) are the wrist camera's
    return SquareAssets(files.root, work, cfg, gopro_intrinsics_2_7k(), demos, np.concatenate(views),
                        np.load(gm.path("mask")), gm.info, paths, stages, demo_rows=rows, square=square)


def square_fingerprint(files: SquareDemoFiles) -> str:
    """Content hash of the demo folder's two files."""
    return config_hash(content_fingerprint(files.zarr), content_fingerprint(files.hdf5))


@dataclass
class SquareSource:
    """A square demo folder as :class:`~umi_aug.augment.sources.base.InputSource` (what
    :func:`umi_aug.augment.export` runs for it: ``umi-aug augment DEMOS``, or ``source=`` of the API)."""

    demos_dir: Path
    inp: SquareInput = field(default_factory=SquareInput)

    def reads(self) -> tuple[Path, ...]:
        return (Path(self.demos_dir),)

    def check(self, image_size: int) -> SquareDemoFiles:
        return check_square_demos(self.demos_dir, image_size)

    def fingerprint(self) -> str:
        """Content of the demo folder + the input settings + the scene model's full config and code version (a
        change of the scene model's defaults must not resume an export made with the old model)."""
        files = check_square_demos(self.demos_dir)
        scene = SquareSceneConfig(**{"image_size": files.size, **self.inp.scene})

        feas = FeasibilityConfig(**self.inp.feasibility) if self.inp.embodiment else None
        return config_hash(square_fingerprint(files), self.inp, scene, SCENE_VERSION, feas)

    @property
    def dataset(self) -> Path:
        return check_square_demos(self.demos_dir).zarr

    def n_augment(self, n_episodes: int) -> int:
        return n_episodes if self.inp.episodes is None else len(set(self.inp.episodes))

    def prepare(self, work: Path, cfg: AugmentConfig, progress: bool = True,
                prefit_obstacles: Sequence[str] = ()) -> SquareAssets:
        """The square stages (``prefit_obstacles`` unused: square demos have no obstacle mode)."""
        return prepare_square(self.demos_dir, work, cfg, self.inp, progress=progress)


# ------------------------------------------------------------------------------------ frames of the variants
def open_square(path: str | os.PathLike, settings: Any = None) -> SquareSource:
    """The :class:`SquareSource` of the demo folder ``path`` with ``settings`` (a :class:`SquareInput`; None: the
    defaults).

    Raises:
        AugmentError: settings of another kind of input.
    """
    if settings is not None and not isinstance(settings, SquareInput):
        raise AugmentError(f"{path}: a square demo folder takes SquareInput settings, not {type(settings).__name__}")
    return SquareSource(Path(path), SquareInput() if settings is None else settings)


def square_input_from_cli(args: Any) -> SquareInput:
    """The :class:`SquareInput` of parsed ``umi-aug augment`` flags: ``--episodes`` and ``--no-embodiment``."""
    return SquareInput(episodes=parse_episodes(args.episodes), embodiment=not args.no_embodiment)


register_source("square", is_square_demos, open_square, square_input_from_cli)


def gt_render_function(assets: SquareAssets):
    """``render_new`` of :func:`umi_aug.square.variants.write_variant` for ``gt_render``: the simulator's
    wrist images of an augmented episode's new frames, the Panda placed on the path by IK (the same check the
    planner passed: :func:`umi_aug.square.feasibility.check_panda_path`), objects as in the demo's start."""
    env = SquareEnv(env_meta=assets.square["env_meta"], image_size=assets.cfg.image_size)
    fcfg = FeasibilityConfig(**assets.square.get("feasibility", {}))

    def render_new(episode: int, info: dict[str, Any]) -> np.ndarray:
        h = assets.for_demo(int(info["source"]))
        s = int(info["n_new"])
        T, w = np.asarray(info["T_world_cam"])[:s], np.asarray(info["gripper_width"])[:s]
        res = check_panda_path(env, h.state_ref, T, w, upto=s, cfg=fcfg)
        if not res.ok:
            raise AugmentError(f"gt_render: episode {episode} (demo {info['source']}): the Panda cannot follow its "
                               f"path ({res.reason}); it passed when planned — another feasibility config?")
        return render_gt_frames(env, h.state_ref, res.q, w, T, np.arange(s))

    render_new.close = env.close  # type: ignore[attr-defined]
    return render_new


def spartn_render_function(assets: SquareAssets):
    """``render_new`` of :func:`umi_aug.square.variants.write_variant` for ``spartn`` (and ``ours_rerender``): the
    demo's scene model rendered at the given (perturbed, or the demo's own) poses with the gripper of the demo's
    frames ``info["overlay_rows"]`` overlaid (as ``ours``)."""
    def render_new(episode: int, info: dict[str, Any]) -> np.ndarray:
        h = assets.for_demo(int(info["source"]))
        rendered = np.stack([render_view(h, T) for T in np.asarray(info["T_world_cam"])])
        originals = h.original_frames(int(info["source"]), np.asarray(info["overlay_rows"]))
        alpha = h.overlay_alpha
        return composite_overlay(rendered, originals, alpha)

    return render_new
