"""Writers of square episodes: robomimic hdf5, UMI replay-buffer zarr, and one-episode ``.npz`` shards.

robomimic layout: ``data/demo_<i>/{states, actions, rewards, dones, obs/<key>}``, per-demo attrs
``num_samples``, ``model_file`` (+ ``seed``), ``data`` attrs ``env_args`` (JSON env_meta) and ``total``.
UMI layout: :class:`umi_aug.data.ReplayBuffer` episodes from :func:`umi_aug.data.make_umi_episode`
(``camera0_rgb`` fisheye, ``robot0_eef_pos`` + ``robot0_eef_rot_axis_angle`` TCP pose, ``robot0_gripper_width``);
root attrs ``T_cam_tcp`` (4×4, this robot's camera→TCP offset) and ``camera0_intrinsics`` (dict) say how the
images and poses relate. All writes are atomic (:func:`umi_aug.io_utils.atomic_path`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from umi_aug.data import ReplayBuffer, make_umi_episode
from umi_aug.data.schema import ACTION_KEY
from umi_aug.errors import SimError
from umi_aug.io_utils import atomic_path
from umi_aug.square.commands import commanded_targets
from umi_aug.square.env import FISHEYE_KEY
from umi_aug.square.episode import Episode

__all__ = ["write_robomimic_hdf5", "write_umi_zarr", "save_episode", "load_episode", "IMAGE_COMPRESSION"]

#: hdf5 compression of image observations (lossless).
IMAGE_COMPRESSION: dict[str, Any] = {"compression": "gzip", "compression_opts": 4}


def write_robomimic_hdf5(path: str | os.PathLike, episodes: Iterable[Episode], env_meta: dict[str, Any]) -> Path:
    """Write ``episodes`` (streamed) as robomimic ``demo_0 … demo_{n-1}``; returns ``path``."""
    import h5py  # lazy, optional dependency: h5py

    path = Path(path)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            data = f.create_group("data")
            total = 0
            for i, ep in enumerate(episodes):
                g = data.create_group(f"demo_{i}")
                g.create_dataset("states", data=ep.states)
                g.create_dataset("actions", data=ep.actions)
                g.create_dataset("rewards", data=ep.rewards)
                g.create_dataset("dones", data=ep.dones)
                og = g.create_group("obs")
                for k, v in ep.obs.items():
                    kw = IMAGE_COMPRESSION if v.dtype == np.uint8 and v.ndim == 4 else {}
                    og.create_dataset(k, data=v, **kw)
                g.attrs["num_samples"] = len(ep)
                g.attrs["model_file"] = ep.model_xml
                g.attrs["seed"] = ep.seed
                total += len(ep)
            data.attrs["total"] = total
            data.attrs["env_args"] = json.dumps(env_meta, indent=4)
    return path


def write_umi_zarr(
    path: str | os.PathLike,
    episodes: Iterable[Episode],
    T_cam_tcp: np.ndarray,
    intrinsics: dict[str, Any] | None = None,
) -> Path:
    """Write ``episodes`` as a UMI replay buffer (``*.zarr.zip`` or a zarr directory); needs rendered images.
    Besides UMI's keys it holds ``action``: the absolute targets the episodes' OSC actions commanded
    (:func:`umi_aug.square.commands.commanded_targets`; the square task's labels).

    Args:
        T_cam_tcp: np.ndarray,  # [4, 4] camera→TCP offset of the sim robot (stored as a root attribute)
        intrinsics: the fisheye intrinsics dict (``FisheyeIntrinsics.to_dict()``), stored as a root attribute.
    """
    rb = ReplayBuffer.create()
    for ep in episodes:
        if FISHEYE_KEY not in ep.obs:
            raise SimError(f"write_umi_zarr({path}): episode (seed {ep.seed}) has no '{FISHEYE_KEY}' images")
        arrays = make_umi_episode(ep.T_world_tcp, ep.gripper_width, {0: ep.obs[FISHEYE_KEY]})
        arrays[ACTION_KEY] = commanded_targets(ep.T_world_tcp, ep.actions).astype(np.float32)
        rb.add_episode(arrays)
    rb.root.attrs["T_cam_tcp"] = np.asarray(T_cam_tcp, dtype=np.float64).tolist()
    if intrinsics is not None:
        rb.root.attrs["camera0_intrinsics"] = intrinsics
    return rb.save(path)


def save_episode(path: str | os.PathLike, ep: Episode) -> Path:
    """Store one episode as a compressed ``.npz`` shard (atomic)."""
    path = Path(path)
    arrays = {"states": ep.states, "actions": ep.actions, "rewards": ep.rewards, "dones": ep.dones,
              "T_world_tcp": ep.T_world_tcp, "gripper_width": ep.gripper_width,
              "meta": np.array(json.dumps({"success": ep.success, "seed": ep.seed, "seconds": ep.seconds,
                                           "info": ep.info})),
              "model_xml": np.array(ep.model_xml)}
    arrays.update({f"obs/{k}": v for k, v in ep.obs.items()})
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    return path


def load_episode(path: str | os.PathLike) -> Episode:
    """Read a shard written by :func:`save_episode`."""
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            obs = {k[4:]: z[k] for k in z.files if k.startswith("obs/")}
            return Episode(states=z["states"], actions=z["actions"], rewards=z["rewards"], dones=z["dones"],
                           obs=obs, T_world_tcp=z["T_world_tcp"], gripper_width=z["gripper_width"],
                           success=bool(meta["success"]), seed=int(meta["seed"]), model_xml=str(z["model_xml"]),
                           seconds=float(meta["seconds"]), info=meta.get("info", {}))
    except (OSError, KeyError, ValueError) as exc:
        raise SimError(f"cannot read episode shard {path}: {exc}") from exc
