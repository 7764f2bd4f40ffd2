"""``UmiAugDataset``: umi-aug's datasets inside UMI's own ``train.py`` (issue #30; facts: umi_stack.md §8).

UMI's workspace builds ``task.dataset`` with ``hydra.utils.instantiate``, asserts it is a ``BaseDataset``, pickles
``dataset.get_normalizer()`` (UMI's ``LinearNormalizer``) into the policy, asks ``get_validation_dataset()`` and
builds its DataLoaders once (no ``set_epoch``). :class:`UmiAugDataset` takes UMI's ``UmiDataset`` constructor
arguments unchanged (names, order, defaults), so one override switches a UMI run to it::

    python train.py --config-name=train_diffusion_unet_timm_umi_workspace task.dataset_path=<zip> \\
        task.dataset._target_=umi_aug.umi_compat.UmiAugDataset +task.dataset.aug=freespace

What it does with each UMI argument (anything it cannot do exactly is refused with one :class:`PolicyError` naming
the argument and value, never ignored):

* ``shape_meta``: obs keys ``camera{j}_rgb`` ([3, S, S]), ``robot{i}_eef_pos`` [3], ``robot{i}_eef_rot_axis_angle``
  ([6], rotation_6d), ``robot{i}_gripper_width`` [1] and optionally ``robot{i}_eef_rot_axis_angle_wrt_start`` [6];
  one horizon per type, one ``down_sample_steps`` for every key and the action, ``latency_steps`` 0 (what
  ``task/umi.yaml`` gives: its latencies × ``dataset_frequeny: 0``). Other keys (bimanual ``*_wrt{j}``, ``*_abs``)
  and non-zero latencies are refused.
* ``dataset_path``: a UMI ``.zarr.zip`` (or zarr directory), read lazily per process; ``cache_dir``: the zip is
  copied once (chunks as stored) to ``<cache_dir>/<stem>_<mtime>.zarr``, a zarr directory read from then on (UMI
  writes an LMDB store there; the purpose — a fast random-access copy — is the same).
* ``pose_repr``: ``obs_pose_repr`` ``relative`` or ``abs`` (UMI's legacy ``rel`` and ``delta`` are refused; UMI's
  default when the key is missing is ``rel``). As in UMI, the ACTIONS are converted with ``obs_pose_repr`` too.
* ``action_padding``, ``seed`` / ``val_ratio`` (UMI's ``get_val_mask``: whole episodes, same episodes as UMI),
  ``repeat_frame_prob`` (UMI's rule: before the first grasp — robot0 width < 0.08 m at or before the current step —
  every observation step is replaced by the current one with this probability) are implemented.
* ``temporally_independent_normalization=True`` (UMI then concatenates per-time-step action statistics in an order
  its own ``_normalize`` does not read back) and ``max_duration`` (UMI caps the GLOBAL row index at
  ``max_duration·60``, so it drops whole later episodes) are refused.

Augmentation (``aug`` ≠ ``none``): the original training samples are followed by ``round(n·r/(1-r))`` augmented
slots (``aug_ratio`` r), each drawing a training demo, an augmentation id, a mode and a step from
``(aug_seed, visit, slot, draw)`` — ``visit`` counts how often THIS slot was fetched (a shared-memory counter seen by
every DataLoader worker), so each pass over the data draws new augmented samples without anyone calling
``set_epoch``. Planning and rendering are :class:`~umi_aug.policy.augmented_dataset.AugmentedUmiDataset`'s (the
session prepared once, cached in ``work_dir``). Validation is never augmented.

``split_by="source_demo"`` splits an umi-aug export by the demo each episode came from (``meta/aug_source_episode``)
instead of by episode, so a demo's original and its augmentations land on the same side (with one source demo,
everything trains). Samples are ``{'obs': {key: float32 (T, ...)}, 'action': float32 (T, 10·R)}`` as UMI's; images
(T, 3, S, S) in [0, 1].
"""

from __future__ import annotations

import copy
import logging
import os
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Optional

import numpy as np
import torch

from umi_aug.errors import DatasetError, PolicyError
from umi_aug.umi_compat.normalizer import umi_normalizer, umi_normalizer_fields

if TYPE_CHECKING:  # annotations only: umi_aug.augment loads cv2 and scipy at import
    from umi_aug.augment.config import SplatStageConfig

__all__ = ["UmiAugDataset", "task_from_shape_meta", "source_demo_groups", "split_val_mask", "UMI_DATASET_DEFAULTS",
           "AUG_CHOICES", "SPLIT_BY"]

log = logging.getLogger(__name__)

#: UMI's ``UmiDataset.__init__`` parameters after ``shape_meta, dataset_path``, in its order, with its defaults.
UMI_DATASET_DEFAULTS: dict[str, Any] = {"cache_dir": None, "pose_repr": {}, "action_padding": False,
                                        "temporally_independent_normalization": False, "repeat_frame_prob": 0.0,
                                        "seed": 42, "val_ratio": 0.0, "max_duration": None}
#: ``aug`` values: no augmentation, or on-the-fly augmentation in these modes.
AUG_CHOICES: tuple[str, ...] = ("none", "freespace", "obstacle", "both")
#: ``split_by`` values: UMI's episode split, or whole source demos (umi-aug export records).
SPLIT_BY: tuple[str, ...] = ("episode", "source_demo")
#: UMI's ``SequenceSampler``: a robot0 gripper width below this (m) is a grasp (``repeat_frame_prob``'s rule).
GRASP_WIDTH_M = 0.08
#: std of the N(0, σ) noise UMI adds to all 6 values of the start pose for ``*_wrt_start`` (train and validation).
START_POSE_NOISE = 0.05
#: Samples per chunk when collecting the normaliser's statistics.
_FIT_CHUNK = 8192


def _dataset_base() -> type:
    """UMI's ``BaseDataset`` when UMI's ``diffusion_policy`` is importable (UMI's workspace asserts it), else
    ``torch.utils.data.Dataset``. Looked up when this module is first imported."""
    try:
        from diffusion_policy.dataset.base_dataset import BaseDataset
    except ImportError:
        return torch.utils.data.Dataset
    return BaseDataset


def _plain(x: Any) -> Any:
    """An OmegaConf container (Hydra passes them) → plain dicts/lists, resolved; anything else unchanged."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf
    except ImportError:  # pragma: no cover - hydra-core is a dependency of the policy extra
        return x
    if isinstance(x, (DictConfig, ListConfig)):
        return OmegaConf.to_container(x, resolve=True)
    return x


def _refuse(name: str, value: Any, why: str) -> PolicyError:
    return PolicyError(f"UmiAugDataset: {name} = {value!r}: {why}")


def _int_value(name: str, value: Any) -> int:
    try:
        f = float(value)
    except (TypeError, ValueError):
        raise _refuse(name, value, "expected a number") from None
    if f != int(f):
        raise _refuse(name, value, "expected a whole number")
    return int(f)


def task_from_shape_meta(shape_meta: Mapping[str, Any], dataset_path: str, pose_repr: Mapping[str, Any],
                         action_padding: bool, seed: int, val_ratio: float, action_key: str | None = None):
    """umi-aug's :class:`~umi_aug.policy.config.TaskConfig` for UMI's ``shape_meta`` / ``pose_repr``; refuses (one
    :class:`PolicyError` naming the key and value) whatever umi-aug's sampler cannot produce exactly."""
    from umi_aug.policy.config import TaskConfig  # lazy, start-up: zarr

    sm = _plain(shape_meta)
    if not isinstance(sm, Mapping) or not isinstance(sm.get("obs"), Mapping) or not isinstance(sm.get("action"),
                                                                                              Mapping):
        raise _refuse("shape_meta", sm, "expected {'obs': {key: {...}}, 'action': {...}} (UMI's task shape_meta)")
    obs, act = sm["obs"], sm["action"]
    rgb = [k for k, v in obs.items() if v.get("type", "low_dim") == "rgb"]
    low = [k for k, v in obs.items() if v.get("type", "low_dim") == "low_dim"]
    for k, v in obs.items():
        if v.get("type", "low_dim") not in ("rgb", "low_dim"):
            raise _refuse(f"shape_meta.obs.{k}.type", v.get("type"), "expected 'rgb' or 'low_dim'")
    n_rob = sum(k.endswith("eef_pos") for k in low)  # UMI's count
    if n_rob < 1:
        raise _refuse("shape_meta.obs", sorted(obs), "no robot{i}_eef_pos key (UMI counts robots by them)")
    n_cam = len(rgb)
    want_rgb = [f"camera{j}_rgb" for j in range(n_cam)]
    if sorted(rgb) != want_rgb:
        raise _refuse("shape_meta.obs rgb keys", sorted(rgb), f"expected {want_rgb}")
    base = {f"robot{i}_{n}": d for i in range(n_rob) for n, d in (("eef_pos", 3), ("eef_rot_axis_angle", 6),
                                                                     ("gripper_width", 1))}
    wrt = {f"robot{i}_eef_rot_axis_angle_wrt_start": 6 for i in range(n_rob)}
    for k in low:
        if k not in base and k not in wrt:
            raise _refuse(f"shape_meta.obs.{k}", dict(obs[k]),
                          f"not implemented by UmiAugDataset (it samples {sorted(base)} and "
                          f"{sorted(wrt)}; UMI's *_wrt{{j}}, *_pos_wrt_start and *_abs keys are not)")
    missing = [k for k in base if k not in low]
    if missing:
        raise _refuse("shape_meta.obs", sorted(obs), f"missing {missing} (every robot needs pos, rotation, gripper)")
    have_wrt = [k for k in wrt if k in low]
    if have_wrt and len(have_wrt) != n_rob:
        raise _refuse("shape_meta.obs", sorted(obs), f"wrt_start keys for some robots only ({have_wrt})")
    dims = {**base, **wrt}
    for k in low:
        shape = [int(s) for s in obs[k].get("shape", [])]
        if shape != [dims[k]]:
            raise _refuse(f"shape_meta.obs.{k}.shape", obs[k].get("shape"), f"expected [{dims[k]}]")
        rep = obs[k].get("rotation_rep")
        if "rot" in k and rep not in (None, "rotation_6d"):
            raise _refuse(f"shape_meta.obs.{k}.rotation_rep", rep, "only rotation_6d is implemented (UMI's)")
    sizes = set()
    for k in rgb:
        shape = [int(s) for s in obs[k].get("shape", [])]
        if len(shape) != 3 or shape[0] != 3 or shape[1] != shape[2]:
            raise _refuse(f"shape_meta.obs.{k}.shape", obs[k].get("shape"), "expected [3, S, S]")
        sizes.add(shape[1])
    if len(sizes) > 1:
        raise _refuse("shape_meta.obs rgb shapes", sorted(sizes), "every camera must have the same size")
    down, horizons = set(), {"rgb": set(), "low_dim": set()}
    for k, v in list(obs.items()) + [("action", act)]:
        where = "shape_meta.action" if k == "action" else f"shape_meta.obs.{k}"
        for f in ("horizon", "down_sample_steps"):
            if f not in v:
                raise _refuse(where, dict(v), f"missing '{f}'")
        lat = v.get("latency_steps", 0)
        if lat is None or float(lat) != 0.0:
            raise _refuse(f"{where}.latency_steps", lat, "only 0 is implemented (task/umi.yaml gives 0: its latencies "
                                                         "are multiplied by dataset_frequeny: 0)")
        down.add(_int_value(f"{where}.down_sample_steps", v["down_sample_steps"]))
        if k != "action":
            horizons[v.get("type", "low_dim")].add(_int_value(f"{where}.horizon", v["horizon"]))
    if len(down) != 1:
        raise _refuse("shape_meta down_sample_steps", sorted(down), "one value for every obs key and the action "
                                                                     "is implemented")
    for t, hs in horizons.items():
        if len(hs) > 1:
            raise _refuse(f"shape_meta {t} horizons", sorted(hs), "one horizon per observation type is implemented")
    a_shape = [int(s) for s in act.get("shape", [])]
    if a_shape != [10 * n_rob]:
        raise _refuse("shape_meta.action.shape", act.get("shape"), f"expected [{10 * n_rob}] (pos 3 + rot6d 6 + "
                                                                    f"gripper 1 per robot)")
    if act.get("rotation_rep", "rotation_6d") != "rotation_6d":
        raise _refuse("shape_meta.action.rotation_rep", act.get("rotation_rep"), "only rotation_6d is implemented")
    pr = _plain(pose_repr) or {}
    obs_rep = pr.get("obs_pose_repr", "rel")  # UMI's default
    if obs_rep not in ("relative", "abs"):
        raise _refuse("pose_repr.obs_pose_repr", obs_rep, "implemented: 'relative', 'abs' (UMI's legacy 'rel' — its "
                                                          "default when the key is missing — and 'delta' are not)")
    act_rep = pr.get("action_pose_repr", "rel")
    if act_rep not in ("relative", "abs", "rel", "delta"):
        raise _refuse("pose_repr.action_pose_repr", act_rep, "expected one of UMI's 'relative', 'abs', 'rel', 'delta'")
    if act_rep != obs_rep:
        log.warning("UmiAugDataset: pose_repr.action_pose_repr = %r differs from obs_pose_repr = %r; the actions are "
                    "converted with obs_pose_repr, as UMI's UmiDataset does", act_rep, obs_rep)
    (d,) = down
    if not 0.0 <= float(val_ratio) < 1.0:
        raise _refuse("val_ratio", val_ratio, "expected a fraction in [0, 1)")
    return TaskConfig(name="umi", dataset_path=str(dataset_path), n_robots=n_rob, n_cameras=n_cam,
                      image_size=int(next(iter(sizes))) if sizes else 224,
                      img_obs_horizon=next(iter(horizons["rgb"])) if horizons["rgb"] else 1,
                      low_dim_obs_horizon=next(iter(horizons["low_dim"])),
                      action_horizon=_int_value("shape_meta.action.horizon", act["horizon"]),
                      obs_down_sample_steps=d, obs_pose_repr=obs_rep, action_pose_repr=obs_rep,
                      use_wrt_start=bool(have_wrt), start_pose_noise=START_POSE_NOISE, val_ratio=float(val_ratio),
                      split_seed=int(seed), action_padding=bool(action_padding), action_key=action_key)


def source_demo_groups(dataset_path: str | os.PathLike) -> np.ndarray:
    """int64 [E]: the source demo of each episode — ``meta/aug_source_episode`` of an umi-aug export (originals
    and their augmentations share it), or the episode index itself for any other UMI dataset."""
    from umi_aug.data import ReplayBuffer  # lazy, start-up: zarr

    with ReplayBuffer.open(dataset_path, check_values=False) as buf:
        E = buf.n_episodes
        if "aug_source_episode" in set(buf.meta.array_keys()):
            g = np.asarray(buf.meta["aug_source_episode"][:], np.int64)
            if g.shape != (E,):
                raise PolicyError(f"{dataset_path}: 'meta/aug_source_episode' has shape {g.shape}; expected ({E},)")
            return g
        return np.arange(E, dtype=np.int64)


def split_val_mask(groups: np.ndarray, val_ratio: float, seed: int) -> np.ndarray:
    """bool [E] validation episodes when whole groups (source demos) are split with UMI's ``get_val_mask`` rule
    (``round(n_groups·val_ratio)`` groups, at least 1 and at most n_groups-1, ``default_rng(seed)``)."""
    from umi_aug.policy.dataset import get_val_mask  # lazy, start-up: zarr

    uniq = np.unique(groups)
    val_groups = uniq[get_val_mask(len(uniq), val_ratio, seed)]
    return np.isin(groups, val_groups)


def _cache_copy(dataset_path: Path, cache_dir: str | os.PathLike) -> Path:
    """``cache_dir``: a zarr directory copy of the dataset (chunks as stored), named like UMI's cache
    ``<stem>_<mtime ISO>``; built once under a blocking lock, atomically."""
    # lazy, start-up: cv2, scipy, zarr
    from umi_aug.augment.cache import build_lock
    from umi_aug.data import ReplayBuffer

    stamp = datetime.fromtimestamp(os.path.getmtime(dataset_path)).isoformat()
    name = f"{dataset_path.name.split('.')[0]}_{stamp}"
    folder = Path(os.path.expanduser(str(cache_dir)))
    out = folder / f"{name}.zarr"
    with build_lock(folder, f"{name}.lock"):
        if not (out / ".zgroup").exists():
            log.info("UmiAugDataset: copying %s to the cache %s", dataset_path, out)
            with ReplayBuffer.open(dataset_path) as buf:
                buf.save(out)
    return out


def _cached_splat_stage(work_dir: Path) -> SplatStageConfig | None:
    """The 3DGS stage (``umi_aug.augment.SplatStageConfig``) a stage cache's scene was trained with, exactly (so a
    dataset asking for it gets the same stage key and reuses the scene), or None when ``work_dir`` holds none. Read
    from ``<work_dir>/splat/manifest.json`` (a session) or the first ``<work_dir>/scenes/<group>/splat/manifest.json``
    (a plain dataset's scene groups). A key leaves ``scale_reg`` out at the trainer's 0.01 and ``coarse_downscale``
    at 1 (caches trained before those settings existed): those are the values it stands for."""
    # lazy, start-up: cv2, scipy
    import dataclasses

    from umi_aug.augment.cache import read_manifest
    from umi_aug.augment.config import TRAINER_SCALE_REG, SplatStageConfig

    found = []
    for stage_dir in [work_dir / "splat", *sorted((work_dir / "scenes").glob("*/splat"))]:
        splat = ((read_manifest(stage_dir) or {}).get("settings") or {}).get("splat") or {}
        if isinstance(splat.get("iterations"), int) and isinstance(splat.get("max_gaussians"), int):
            found.append((stage_dir, splat))
    if not found:
        return None
    stage_dir, splat = found[0]
    if any(other != splat for _, other in found[1:]):
        log.warning("UmiAugDataset: the scenes in %s were trained with different 3DGS settings; taking %s's",
                    work_dir, stage_dir)
    names = {f.name for f in dataclasses.fields(SplatStageConfig)}
    kw = {"scale_reg": TRAINER_SCALE_REG, "coarse_downscale": 1,
          **{k: (dict(v) if k == "extra" else v) for k, v in splat.items() if k in names}}
    return SplatStageConfig(**kw)


def _grasp_flags(ds) -> np.ndarray:
    """bool [len(ds)]: sample before the episode's first grasp (UMI: no robot0 width < 0.08 m in rows
    ``start..current``, compared in float32 as UMI's sampler does)."""
    g = np.asarray(ds.gripper[0][:, 0], np.float32) < np.float32(GRASP_WIDTH_M)
    grasps = np.flatnonzero(g)
    cur, start = ds.indices[:, 0], ds.indices[:, 1]
    first = np.full(len(cur), np.iinfo(np.int64).max, np.int64)  # first grasp row at or after the episode start
    k = np.searchsorted(grasps, start)
    ok = k < len(grasps)
    first[ok] = grasps[k[ok]]
    return cur < first


class UmiAugDataset(_dataset_base()):
    """UMI's ``UmiDataset`` interface over umi-aug's sampler, with on-the-fly augmentation (module docstring).

    Args (UMI's, same names/order/defaults): shape_meta, dataset_path, cache_dir, pose_repr, action_padding,
        temporally_independent_normalization, repeat_frame_prob, seed, val_ratio, max_duration.
    Args (umi-aug's, keyword only):
        aug: "none", "freespace", "obstacle" or "both".
        aug_ratio: fraction of augmented samples in [0, 1).
        session_dir: UMI session folder (scan + demos); None = the folder holding ``dataset_path`` (a plain dataset
            without ``demos/``: scenes from its own frames).
        work_dir: the augmentation stage cache; None = ``<session>/augment`` (plain dataset: ``<dataset>.augment``).
        n_aug_per_demo: distinct augmentations (start pose / obstacle) per demo.
        rerender_fraction: fraction in [0, 1) of the augmented samples drawn from a demo's re-rendered copy (its
            own labels, its approach frames rendered by the scene model).
        aug_seed: root seed of the augmented episodes and slot draws.
        splat_iterations / splat_max_gaussians: 3DGS training of the scene; both None = what the stage cache in
            ``work_dir`` was trained with (every setting), else umi-aug's default for the input, as ``umi-aug
            augment`` trains it (a session: 1500 / 25000; a plain dataset: 550 / 30000 with the short schedule).
        cone_half_angle_deg / cone_radius_m: start-pose cone (paper: 50°, 0.15 m).
        plan_cache_size: planned episodes kept per DataLoader worker.
        tcp_offset_m / scene_group: plain-dataset input (UMI's camera→TCP offset in metres; episodes per scene,
            or ``"auto"``: the episodes recorded in one place share a scene, found from the data).
        split_by: "episode" (UMI's split) or "source_demo" (whole source demos of an umi-aug export).
    Raises:
        PolicyError: an argument or ``shape_meta`` entry it does not implement exactly (naming it), a dataset it
            cannot read, no training sample.
    """

    def __init__(self, shape_meta: dict, dataset_path: str, cache_dir: Optional[str] = None,
                 pose_repr: dict = UMI_DATASET_DEFAULTS["pose_repr"], action_padding: bool = False,
                 temporally_independent_normalization: bool = False, repeat_frame_prob: float = 0.0,
                 seed: int = 42, val_ratio: float = 0.0, max_duration: Optional[float] = None, *,
                 aug: str = "none", aug_ratio: float = 0.5, session_dir: Optional[str] = None,
                 work_dir: Optional[str] = None, n_aug_per_demo: int = 1000, aug_seed: int = 0,
                 splat_iterations: Optional[int] = None, splat_max_gaussians: Optional[int] = None,
                 cone_half_angle_deg: float = 50.0, cone_radius_m: float = 0.15, plan_cache_size: int = 256,
                 tcp_offset_m: float = 0.205, scene_group: int | str = 1, split_by: str = "episode",
                 rerender_fraction: float = 0.0) -> None:
        super().__init__()
        # lazy, start-up: zarr
        from umi_aug.data import ReplayBuffer
        from umi_aug.policy.dataset import UmiPolicyDataset

        if temporally_independent_normalization:
            raise _refuse("temporally_independent_normalization", temporally_independent_normalization,
                          "not implemented (UMI's own normaliser concatenates per-time-step action statistics in an "
                          "order its _normalize does not read back); use False, task/umi.yaml's value")
        if max_duration is not None:
            raise _refuse("max_duration", max_duration, "not implemented (UMI's sampler caps the global row index at "
                                                        "max_duration·60, dropping whole later episodes); use null")
        if not 0.0 <= float(repeat_frame_prob) <= 1.0:
            raise _refuse("repeat_frame_prob", repeat_frame_prob, "expected a probability in [0, 1]")
        if aug not in AUG_CHOICES:
            raise _refuse("aug", aug, f"expected one of {list(AUG_CHOICES)}")
        if split_by not in SPLIT_BY:
            raise _refuse("split_by", split_by, f"expected one of {list(SPLIT_BY)}")
        path = Path(os.path.expanduser(str(dataset_path)))
        if not path.exists():
            raise _refuse("dataset_path", str(dataset_path), "does not exist")
        read_path = _cache_copy(path, cache_dir) if cache_dir is not None else path
        try:
            with ReplayBuffer.open(read_path, check_values=False) as buf:
                action_key = "action" if "action" in buf else None  # UMI's sampler uses a stored 'action' array
        except DatasetError as exc:
            raise _refuse("dataset_path", str(dataset_path), f"not a readable UMI replay buffer ({exc})") from exc
        task = task_from_shape_meta(shape_meta, str(read_path), pose_repr, action_padding, seed, val_ratio,
                                    action_key)
        train = UmiPolicyDataset(read_path, task, "train", start_pose_noise=START_POSE_NOISE)
        if split_by == "source_demo":
            train.val_mask = split_val_mask(source_demo_groups(read_path), task.val_ratio, task.split_seed)
            train._build_indices()
        if len(train) == 0:
            raise _refuse("dataset_path", str(dataset_path),
                          f"no training sample: every training episode is shorter than the action window "
                          f"({(task.action_horizon - 1) * task.obs_down_sample_steps + 1} frames) and "
                          f"action_padding is False")
        sm = _plain(shape_meta)
        self.shape_meta = sm
        self.dataset_path = str(path)
        self.rgb_keys = [k for k, v in sm["obs"].items() if v.get("type", "low_dim") == "rgb"]
        self.lowdim_keys = [k for k, v in sm["obs"].items() if v.get("type", "low_dim") == "low_dim"]
        self.task = task
        self.seed = int(seed)
        self.val_ratio = float(val_ratio)
        self.repeat_frame_prob = float(repeat_frame_prob)
        self.split_by = split_by
        self.split = "train"
        self.aug = aug
        self._train = train
        self._before_grasp = _grasp_flags(train)
        self._rng: np.random.Generator | None = None
        self._rng_key: tuple[int, int] | None = None
        self._aug = None
        self._visits: torch.Tensor | None = None
        if aug != "none":
            self._aug = self._build_augmented(path, session_dir, work_dir, aug_ratio, n_aug_per_demo, aug_seed,
                                              splat_iterations, splat_max_gaussians, cone_half_angle_deg,
                                              cone_radius_m, plan_cache_size, tcp_offset_m, scene_group,
                                              rerender_fraction)
            self._visits = torch.zeros(max(1, self._aug.n_augmented), dtype=torch.int64).share_memory_()
        log.info("UmiAugDataset: %s", self.describe())

    def _build_augmented(self, path: Path, session_dir, work_dir, ratio, n_aug_per_demo, aug_seed, splat_iterations,
                         splat_max_gaussians, cone_half_angle_deg, cone_radius_m, plan_cache_size, tcp_offset_m,
                         scene_group, rerender_fraction):
        """umi-aug's augmented dataset over the training split (session prepared or read from its stage cache)."""
        # lazy, start-up: zarr
        from umi_aug.policy.config import AugConfig, TrainConfig, check_aug
        from umi_aug.policy.workspace import build_augmented_dataset

        session = Path(session_dir).absolute() if session_dir else path.absolute().parent
        plain = not session_dir and not (session / "demos").is_dir()
        work = (Path(work_dir).absolute() if work_dir else
                path.absolute().with_name(path.name + ".augment") if plain else session / "augment")
        cached = _cached_splat_stage(work) if splat_iterations is None and splat_max_gaussians is None else None
        if cached is not None:
            log.info("UmiAugDataset: 3DGS settings from the stage cache in %s: %d steps, ≤%d Gaussians", work,
                     cached.iterations, cached.max_gaussians)
        a = AugConfig(name=self.aug, session_dir=str(session) if session_dir else "", work_dir=str(work),
                      ratio=float(ratio), n_aug_per_demo=int(n_aug_per_demo), seed=int(aug_seed),
                      cone_half_angle_deg=float(cone_half_angle_deg), cone_radius_m=float(cone_radius_m),
                      splat_iterations=splat_iterations, splat_max_gaussians=splat_max_gaussians,
                      plan_cache_size=int(plan_cache_size), tcp_offset_m=float(tcp_offset_m),
                      scene_group=scene_group, rerender_fraction=float(rerender_fraction))
        check_aug(a)
        return build_augmented_dataset(self._train, path.absolute(), TrainConfig(task=self.task, aug=a), splat=cached)

    # ------------------------------------------------------------------ UMI's BaseDataset interface
    @property
    def n_augmented(self) -> int:
        """Augmented slots per pass (0 without augmentation and in the validation split)."""
        return 0 if self._aug is None else int(self._aug.n_augmented)

    def __len__(self) -> int:
        return len(self._train) + self.n_augmented

    def get_validation_dataset(self) -> "UmiAugDataset":
        """The validation split, same type, never augmented (UMI adds the start-pose noise there too)."""
        val = copy.copy(self)
        val._train = self._train.get_validation_dataset()
        val._train.start_pose_noise = self._train.start_pose_noise
        val._before_grasp = _grasp_flags(val._train)
        val._aug, val._visits, val.split = None, None, "val"
        val._rng, val._rng_key = None, None
        return val

    def get_normalizer(self, **kwargs: Any):
        """UMI's ``LinearNormalizer`` (UMI's class when importable, else the same layout) from every training sample
        (time steps pooled) — with augmentation also every step of a few planned, not rendered, augmented episodes
        (:meth:`AugmentedUmiDataset.normalizer_dataset`), so the ranges cover the augmented starts. No image is
        decoded."""
        src = self._aug.normalizer_dataset() if self._aug is not None else self._train
        n = len(src)
        noise = np.random.default_rng(self.seed)  # the wrt_start statistics include UMI's start-pose noise
        chunks: dict[str, list[np.ndarray]] = {}
        for s in range(0, n, _FIT_CHUNK):
            d = src.lowdim_batch(np.arange(s, min(n, s + _FIT_CHUNK)), noise)
            for k, v in d.items():
                chunks.setdefault(k, []).append(v.astype(np.float32).reshape(-1, v.shape[-1]))
        data = {k: np.concatenate(v) for k, v in chunks.items()}
        return umi_normalizer(umi_normalizer_fields(data, self.lowdim_keys, self.rgb_keys, self.task.n_robots))

    def get_all_actions(self) -> torch.Tensor:
        """float32 [N, H, 10·R]: the actions of every original sample of this split (augmented ones are drawn on
        the fly and not included)."""
        n = len(self._train)
        out = [self._train.lowdim_batch(np.arange(s, min(n, s + _FIT_CHUNK)))["action"]
               for s in range(0, n, _FIT_CHUNK)]
        return torch.from_numpy(np.concatenate(out).astype(np.float32))

    # ------------------------------------------------------------------ samples
    @property
    def epoch(self) -> int:
        """Passes every augmented slot has been drawn for (the lowest per-slot visit count); 0 without aug."""
        return 0 if self._visits is None else int(self._visits[: self.n_augmented].min()) if self.n_augmented else 0

    def set_epoch(self, epoch: int) -> None:
        """Optional (UMI never calls it): the next visit of every augmented slot draws pass ``epoch``."""
        if self._visits is not None:
            self._visits.fill_(int(epoch))

    def _process_rng(self) -> np.random.Generator:
        key = (os.getpid(), torch.initial_seed())
        if self._rng is None or self._rng_key != key:
            self._rng, self._rng_key = np.random.default_rng([key[1] % (2 ** 63), 30]), key
        return self._rng

    def _augmented(self, j: int) -> tuple[dict[str, Any], bool]:
        """Augmented slot ``j``'s sample for its current visit, and whether it lies before the first grasp."""
        from umi_aug.policy.augmented_dataset import MAX_SLOT_DRAWS  # lazy, start-up: zarr

        aug = self._aug
        visit = int(self._visits[j])
        self._visits[j] += 1  # only this slot's fetch writes it: one fetch per slot per pass
        for draw in range(MAX_SLOT_DRAWS):
            rng = np.random.default_rng([aug.seed, visit, int(j), draw])
            demo, aug_id, mode = aug.draw(rng)
            planned = aug.planned(demo, aug_id, mode)
            if planned is None:
                continue
            steps = aug.n_current_steps(planned.n_frames)
            if steps == 0:
                continue
            cur = int(rng.integers(steps))
            sample = aug.augmented_sample(demo, aug_id, mode, cur, rng)
            if sample is None:
                continue
            widths = aug.assets.umi_episode(planned.episode, planned.demo_index)["robot0_gripper_width"]
            before = not bool((np.asarray(widths[: cur + 1], np.float32) < np.float32(GRASP_WIDTH_M)).any())
            return sample, before
        log.warning("augmented slot %d: no plannable episode after %d draws; using an original sample", j,
                    MAX_SLOT_DRAWS)
        k = j % len(self._train)
        return self._train[k], bool(self._before_grasp[k])

    def __getitem__(self, idx: int) -> dict[str, Any]:
        idx = int(idx)
        n = len(self._train)
        if not 0 <= idx < len(self):
            raise IndexError(f"sample index {idx} out of range for {len(self)} samples")
        if idx < n:
            sample, before = self._train[idx], bool(self._before_grasp[idx])
        else:
            sample, before = self._augmented(idx - n)
        if self.repeat_frame_prob > 0 and before and self._process_rng().random() < self.repeat_frame_prob:
            for v in sample["obs"].values():  # UMI: every obs step = the current one (actions unchanged)
                v[:-1] = v[-1:]
        return sample

    def describe(self) -> str:
        s = self._train.describe()
        if self._aug is not None:
            s += f" + {self.n_augmented} augmented slots ({self.aug}, demos {self._aug.demos})"
        return s
