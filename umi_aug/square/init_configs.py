"""Evaluation start configurations of the square task: end-effector poses in a cone, objects unchanged.

For configuration ``i`` the source initial state ``i mod n_sources`` (a dataset's ``states[0]`` or a seeded
reset) is restored; its wrist camera pose ``T_ref`` defines the cone (paper §4: "a θ quaternion cone around the
initial camera pose, r the radius of the quaternion sphere"): pivot = ``r`` metres ahead of the camera on its
optical axis, camera positions uniform by area on the cap of half-angle θ of the sphere of radius ``r`` around it,
looking at the pivot (:func:`umi_aug.geometry.sample_cone_start_poses`). The camera is carried by the hand, so
the grip-site target is ``T_cam @ T_cam_site`` with the source's fixed ``T_cam_site``; the arm is placed by
:class:`~umi_aug.square.ik.PandaIK`. Unreachable or colliding samples are counted by reason and resampled
from the same generator. Objects (nut, pegs) and the gripper fingers keep the source state. The set is fully
determined by (sources, n, θ, r, seed) and written once to an ``.npz`` so every policy sees the same set.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from umi_aug.errors import SimError
from umi_aug.geometry import pose_inverse, sample_cone_start_poses
from umi_aug.io_utils import atomic_path
from umi_aug.square.env import GRIP_SITE, SquareEnv
from umi_aug.square.ik import PandaIK

__all__ = ["InitConfigSpec", "source_states_from_hdf5", "source_states_from_seeds", "sample_init_configs",
           "reset_init_configs", "write_init_configs", "load_init_configs", "apply_init_config", "place_arm"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InitConfigSpec:
    """Cone of the start poses: ``theta_deg`` half-angle, ``radius`` metres; ``seed`` of the sampler;
    ``max_tries_per_config`` resamples before giving up."""

    n: int = 1000
    theta_deg: float = 50.0
    radius: float = 0.15
    seed: int = 0
    max_tries_per_config: int = 50


def source_states_from_hdf5(path: str | os.PathLike) -> tuple[np.ndarray, str]:
    """``(states [D, S] = each demo's states[0] in demo order, env_args JSON)`` of a robomimic hdf5."""
    import h5py  # lazy, optional dependency: h5py

    try:
        with h5py.File(path, "r") as f:
            demos = sorted(f["data"].keys(), key=lambda k: int(k.split("_")[-1]))
            states = np.stack([f[f"data/{k}/states"][0] for k in demos])
            env_args = f["data"].attrs["env_args"]
    except (OSError, KeyError, ValueError) as exc:
        raise SimError(f"{path}: not a robomimic hdf5 with data/demo_*/states and data.attrs['env_args'] ({exc})")
    return states, env_args if isinstance(env_args, str) else env_args.decode()


def source_states_from_seeds(env: SquareEnv, seeds: list[int]) -> np.ndarray:
    """Initial states ``[len(seeds), S]`` of seeded resets."""
    out = []
    for s in seeds:
        env.reset(seed=s)
        out.append(env.get_state())
    return np.stack(out)


def place_arm(env: SquareEnv, q: np.ndarray, qadr: np.ndarray) -> None:
    """Set the arm joints ``q`` [7] (at ``qpos[qadr]``) at rest and recompute the scene's kinematics."""
    d = env.data
    d.qpos[qadr] = q
    d.qvel[:] = 0.0
    env.rs.sim.forward()


def sample_init_configs(env: SquareEnv, sources: np.ndarray, spec: InitConfigSpec,
                        progress: bool = True) -> dict[str, Any]:
    """Sample ``spec.n`` reachable, collision-free start configurations.

    Args:
        env: a :class:`SquareEnv` (images not needed).
        sources: float64 [D, S] flattened initial states.
    Returns:
        dict of arrays: ``states`` [n, S] (robomimic flattened states, ready for ``reset_to``), ``source_index``
        [n], ``T_world_cam`` [n, 4, 4] (sampled wrist camera, OpenCV), ``T_world_site_target`` [n, 4, 4],
        ``T_world_site_reached`` [n, 4, 4], ``ik_pos_err`` [n] m, ``ik_rot_err`` [n] rad; and ``report``
        (JSON-able: spec, rejections by reason, tries).
    """
    sources = np.asarray(sources, dtype=np.float64)
    if sources.ndim != 2 or len(sources) == 0:
        raise SimError(f"sample_init_configs: sources must be [D, S] with D >= 1, got {sources.shape}")
    rng = np.random.default_rng(spec.seed)
    theta = math.radians(spec.theta_deg)
    ik = PandaIK(env.model, GRIP_SITE)
    out: dict[str, list] = {k: [] for k in ("states", "source_index", "T_world_cam", "T_world_site_target",
                                             "T_world_site_reached", "ik_pos_err", "ik_rot_err")}
    rejected: Counter = Counter()
    tries = 0
    for i in tqdm(range(spec.n), desc="init configs", disable=not progress):
        j = i % len(sources)
        env.reset_to(sources[j])
        T_cam_ref = env.wrist_pose()
        T_cam_site = pose_inverse(T_cam_ref) @ env.site_pose(GRIP_SITE)
        pivot = T_cam_ref[:3, 3] + spec.radius * T_cam_ref[:3, 2]
        for _ in range(spec.max_tries_per_config):
            tries += 1
            T_cam = sample_cone_start_poses(T_cam_ref, pivot, theta, 1, rng, radius=spec.radius)[0]
            T_site = T_cam @ T_cam_site
            res = ik.solve(env.data, T_site, rng=rng)
            if not res.reachable:
                rejected["unreachable"] += 1
                continue
            if res.collisions:
                rejected["collision"] += 1
                continue
            break
        else:
            raise SimError(f"sample_init_configs: config {i} (source {j}): no reachable, collision-free pose in "
                           f"{spec.max_tries_per_config} tries (θ={spec.theta_deg}°, r={spec.radius} m)")
        place_arm(env, res.q, ik.qadr)
        T_reached = env.site_pose(GRIP_SITE)
        out["states"].append(env.get_state())
        out["source_index"].append(j)
        out["T_world_cam"].append(T_cam)
        out["T_world_site_target"].append(T_site)
        out["T_world_site_reached"].append(T_reached)
        out["ik_pos_err"].append(res.pos_err)
        out["ik_rot_err"].append(res.rot_err)
    arrays = {k: np.asarray(v) for k, v in out.items()}
    report = {"spec": asdict(spec), "n_sources": int(len(sources)), "tries": tries,
              "rejected": dict(rejected), "max_ik_pos_err_m": float(arrays["ik_pos_err"].max()),
              "max_ik_rot_err_deg": float(np.degrees(arrays["ik_rot_err"].max()))}
    if rejected:
        log.info("init configs: %d samples rejected and resampled: %s", sum(rejected.values()), dict(rejected))
    return arrays | {"report": report}


def reset_init_configs(env: SquareEnv, sources: np.ndarray, seeds: list[int] | None = None) -> dict[str, Any]:
    """The source states themselves as start configurations (no cone, no IK): the demos' own start distribution.

    A scripted demo starts from a seeded reset, so seeded resets with seeds no demo used are the in-distribution
    evaluation set. Same keys as :func:`sample_init_configs`; the target/reached grip-site poses are the reset's own,
    the IK errors 0.

    Args:
        env: a :class:`SquareEnv` (images not needed).
        sources: float64 [D, S] flattened initial states (e.g. :func:`source_states_from_seeds`).
        seeds: the reset seeds the sources came from, recorded in the report.
    """
    sources = np.asarray(sources, dtype=np.float64)
    if sources.ndim != 2 or len(sources) == 0:
        raise SimError(f"reset_init_configs: sources must be [D, S] with D >= 1, got {sources.shape}")
    cams, sites = [], []
    for state in sources:
        env.reset_to(state)
        cams.append(env.wrist_pose())
        sites.append(env.site_pose(GRIP_SITE))
    n = len(sources)
    arrays = {"states": sources.copy(), "source_index": np.arange(n), "T_world_cam": np.asarray(cams),
              "T_world_site_target": np.asarray(sites), "T_world_site_reached": np.asarray(sites),
              "ik_pos_err": np.zeros(n), "ik_rot_err": np.zeros(n)}
    report = {"spec": {"n": n, "kind": "reset", "seeds": None if seeds is None else [int(s) for s in seeds]},
              "n_sources": n, "tries": 0, "rejected": {}, "max_ik_pos_err_m": 0.0, "max_ik_rot_err_deg": 0.0}
    return arrays | {"report": report}


def write_init_configs(path: str | os.PathLike, configs: dict[str, Any], env_meta: dict[str, Any]) -> Path:
    """Write the set (arrays + ``report`` + ``env_args``) to an ``.npz`` (atomic)."""
    path = Path(path)
    arrays = {k: v for k, v in configs.items() if k != "report"}
    arrays["report"] = np.array(json.dumps(configs["report"]))
    arrays["env_args"] = np.array(json.dumps(env_meta))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    return path


def load_init_configs(path: str | os.PathLike) -> dict[str, Any]:
    """Read a file of :func:`write_init_configs` (``report`` and ``env_args`` decoded from JSON)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            out: dict[str, Any] = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise SimError(f"cannot read init-config file {path}: {exc}") from exc
    for k in ("report", "env_args"):
        if k not in out:
            raise SimError(f"{path}: key {k!r} missing; not an init-config file")
        out[k] = json.loads(str(out[k]))
    return out


def apply_init_config(env: SquareEnv, configs: dict[str, Any], i: int) -> dict[str, np.ndarray]:
    """Put ``env`` into configuration ``i`` and return its observation."""
    n = len(configs["states"])
    if not 0 <= i < n:
        raise SimError(f"apply_init_config: index {i} outside 0..{n - 1}")
    return env.reset_to(configs["states"][i])
