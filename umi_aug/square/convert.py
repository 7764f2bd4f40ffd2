"""Convert a robomimic square hdf5 (ph/mh, robosuite 1.4.x ``states``) to fisheye: robomimic hdf5 + UMI zarr.

The dataset's pinhole 84² wrist images see too little to be warped into a 165° fisheye, so every stored state is
replayed (``reset_to``: the demo's ``model_file`` first, then each ``states[t]``) and the wrist view re-rendered
with the GoPro fisheye at the ``robot0_eye_in_hand`` pose. States, actions, rewards and dones are copied
unchanged; the low-dim observations are recomputed from the states. Per-demo shards (``<out>/shards``) make an
interrupted conversion resume.
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from tqdm import tqdm

from umi_aug.errors import SimError

__all__ = ["convert_robomimic_hdf5", "replay_demo"]

log = logging.getLogger(__name__)


def _demo_keys(f) -> list[str]:
    return sorted(f["data"].keys(), key=lambda k: int(k.split("_")[-1]))


def replay_demo(env, states: np.ndarray, actions: np.ndarray, rewards: np.ndarray | None,
                dones: np.ndarray | None, model_xml: str | None, name: str = "") -> "object":
    """Re-render one demo from its states; returns an :class:`~umi_aug.square.episode.Episode`."""
    # lazy, start-up: cv2
    from umi_aug.square.env import FISHEYE_KEY, LOW_DIM_KEYS
    from umi_aug.square.episode import Episode

    t0 = time.perf_counter()
    T = len(states)
    if len(actions) != T:
        raise SimError(f"demo {name}: {len(states)} states but {len(actions)} actions")
    obs: dict[str, list] = {k: [] for k in LOW_DIM_KEYS + (FISHEYE_KEY,)}
    tcp, width = [], []
    env.reset_to(states[0], model_xml=model_xml or None)
    for t in range(T):
        o = env.reset_to(states[t])
        for k in obs:
            obs[k].append(np.asarray(o[k]).copy())
        tcp.append(env.tcp_pose())
        width.append(env.gripper_width())
    success = env.is_success()
    r = np.zeros(T) if rewards is None else np.asarray(rewards, dtype=np.float64)
    d = np.zeros(T, dtype=np.int64) if dones is None else np.asarray(dones).astype(np.int64)
    return Episode(states=np.asarray(states, dtype=np.float64), actions=np.asarray(actions, dtype=np.float64),
                   rewards=r, dones=d, obs={k: np.stack(v) for k, v in obs.items()}, T_world_tcp=np.asarray(tcp),
                   gripper_width=np.asarray(width), success=bool(success or r.max(initial=0) > 0),
                   model_xml=model_xml or env.model_xml(), seconds=time.perf_counter() - t0,
                   info={"source_demo": name})


def convert_robomimic_hdf5(
    src: str | os.PathLike,
    out_dir: str | os.PathLike,
    image_size: int = 224,
    max_demos: int | None = None,
    write_hdf5: bool = True,
    write_zarr: bool = True,
    progress: bool = True,
) -> dict[str, str]:
    """Convert ``src`` into ``out_dir/<stem>_fisheye<size>.hdf5`` and ``.zarr.zip``; returns the paths.

    Raises:
        SimError: ``src`` is not a robomimic square hdf5 (names the key), or the env cannot be built.
    """
    import h5py  # lazy, optional dependency: h5py

    # lazy, start-up: cv2, zarr
    from umi_aug.square.camera import T_CAM_TCP, wrist_intrinsics
    from umi_aug.square.env import SquareEnv
    from umi_aug.square.writers import load_episode, save_episode, write_robomimic_hdf5, write_umi_zarr

    src, out_dir = Path(src), Path(out_dir)
    shards = out_dir / "shards"
    shards.mkdir(parents=True, exist_ok=True)
    try:
        f = h5py.File(src, "r")
    except OSError as exc:
        raise SimError(f"cannot open {src}: {exc}") from exc
    with f:
        if "data" not in f or "env_args" not in f["data"].attrs:
            raise SimError(f"{src}: key 'data' with attribute 'env_args' missing; not a robomimic hdf5")
        env_args = f["data"].attrs["env_args"]
        env_meta: dict[str, Any] = json.loads(env_args if isinstance(env_args, str) else env_args.decode())
        demos = _demo_keys(f)[: max_demos]
        env = None
        try:
            for k in tqdm(demos, desc=f"convert {src.name}", unit="demo", disable=not progress):
                path = shards / f"{k}.npz"
                if path.exists():
                    continue
                g = f[f"data/{k}"]
                for key in ("states", "actions"):
                    if key not in g:
                        raise SimError(f"{src}: key 'data/{k}/{key}' missing")
                if env is None:
                    env = SquareEnv(env_meta=env_meta, image_size=image_size)
                xml = g.attrs.get("model_file")
                ep = replay_demo(env, g["states"][()], g["actions"][()],
                                 g["rewards"][()] if "rewards" in g else None,
                                 g["dones"][()] if "dones" in g else None,
                                 xml if isinstance(xml, str) or xml is None else xml.decode(), name=k)
                save_episode(path, ep)
        finally:
            if env is not None:
                env.close()

    def episodes() -> Iterator:
        for k in demos:
            yield load_episode(shards / f"{k}.npz")

    stem = f"{src.stem}_fisheye{image_size}"
    paths = {}
    if write_hdf5:
        paths["hdf5"] = str(write_robomimic_hdf5(out_dir / f"{stem}.hdf5", episodes(), env_meta))
    if write_zarr:
        paths["zarr"] = str(write_umi_zarr(out_dir / f"{stem}.zarr.zip", episodes(), T_CAM_TCP,
                                           wrist_intrinsics(image_size).to_dict()))
    return paths
