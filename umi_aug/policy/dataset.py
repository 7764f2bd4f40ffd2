"""Training dataset from a UMI replay buffer with UMI's sampling (``UmiDataset`` + ``SequenceSampler``).

Per sample index (a "current" step ``c`` of episode ``[s, e)``), with down-sampling ``d``:

* images ``camera{j}_rgb``: frames ``c-(h-1)d, …, c`` (step d); frames before the episode start are replaced by
  the earliest valid one (UMI's padding); float32 (h, 3, H, W) in [0, 1]. Only these frames are decoded.
* low-dim: the same indices clipped to ``[s, e-1]``; poses converted to the policy representation (relative to
  the pose at ``c``: ``inv(T_c) @ T_t``, as pos + rot6d), gripper width as is; ``*_rot_axis_angle_wrt_start`` =
  rot6d of ``inv(T_start + noise) @ T_t`` (UMI adds N(0, 0.05) to the 6-vector; here only in the training split).
* action: rows ``c, c+d, …, c+(H-1)d`` of [pos, rotvec, gripper] → relative pos + rot6d + gripper (H, 10·R).
  Windows that cross the episode end are skipped unless ``action_padding`` (then the last row repeats). The rows
  are the TCP poses and widths (UMI), or, with ``task.action_key``, the stored absolute commanded targets
  (``[N, 7·R]``), made relative to the same observed pose ``c``.
* ``task.sample_replayed_tails=false``: an augmented episode's samples that read only rows after its splice are
  left out; the same frames and labels are the source demo's own samples (:func:`replayed_tail_first_sample`).

Episodes are split into train / validation by UMI's ``get_val_mask`` (same seed → same episodes as UMI). The
normaliser is fitted from the low-dim arrays only (no image is decoded). The zarr store is opened lazily once per
process, so DataLoader workers never share a zip file handle.
"""

from __future__ import annotations

import copy
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from umi_aug.data import ReplayBuffer
from umi_aug.data.schema import SAMPLE_STEP_KEY
from umi_aug.errors import DatasetError, PolicyError
from umi_aug.geometry import pos_rotvec_to_pose
from umi_aug.policy.config import TaskConfig, shape_meta
from umi_aug.policy.normalizer import LinearNormalizer, identity_params, range_params
from umi_aug.policy.pose_repr import abs_actions_to_model, obs_pose_to_model, wrt_start_rot6d

__all__ = ["UmiPolicyDataset", "get_val_mask", "first_tail_only_step", "replayed_tail_first_sample",
           "sample_frame_indices", "frame_rows", "window_rows", "lowdim_from_rows",
           "to_sample", "to_batch"]

log = logging.getLogger(__name__)

#: Samples per chunk when fitting the normaliser (bounds memory: ~chunk × H × 16 doubles per arm).
_FIT_CHUNK = 8192


def _read_sample_steps(buf, path, ends: np.ndarray) -> np.ndarray:
    """``meta/umi_aug_sample_step`` (:data:`umi_aug.data.schema.SAMPLE_STEP_KEY`) checked against the episodes, or
    all −1 (every step is a sample, UMI's rule) when the buffer has none."""
    if SAMPLE_STEP_KEY not in set(buf.meta.array_keys()):
        return np.full(len(ends), -1, np.int64)
    steps = np.asarray(buf.meta[SAMPLE_STEP_KEY][:])
    lengths = np.diff(np.concatenate([[0], ends]))
    if steps.shape != (len(ends),) or not np.issubdtype(steps.dtype, np.integer):
        raise PolicyError(f"{path}: 'meta/{SAMPLE_STEP_KEY}' has shape {steps.shape} dtype {steps.dtype}; "
                          f"expected one integer per episode ({len(ends)})")
    bad = np.flatnonzero((steps < -1) | (steps >= lengths))
    if bad.size:
        e = int(bad[0])
        raise PolicyError(f"{path}: 'meta/{SAMPLE_STEP_KEY}'[{e}] = {int(steps[e])} is not a step of episode {e} "
                          f"(length {int(lengths[e])}; -1 = every step)")
    return steps.astype(np.int64)


#: ``meta/`` records of an augmented export (:mod:`umi_aug.augment.export_store`): ``aug_id`` (-1 = an original
#: episode, >= 0 an augmented one), the source demo's index, the first replayed frame of an augmented episode.
_AUG_ID, _AUG_SOURCE, _AUG_SPLICE = "aug_id", "aug_source_episode", "aug_splice_index"


def first_tail_only_step(task: TaskConfig, splice_index: int) -> int:
    """The first step of an augmented episode spliced at ``splice_index`` (its first replayed frame) whose sample
    reads only replayed rows: observation rows ``c-(h-1)d … c`` (h = the longer observation horizon,
    d = down-sampling) at or after the splice and label rows ``c … c+(H-1)d`` after it (the splice row's label is
    still the planned one)."""
    h = max(task.img_obs_horizon, task.low_dim_obs_horizon)
    return int(splice_index) + max(1, (h - 1) * task.obs_down_sample_steps)


def replayed_tail_first_sample(buf, path, task: TaskConfig) -> tuple[np.ndarray, np.ndarray]:
    """Per episode, the first episode-relative sample step whose every row lies in the replayed tail (or -1), and
    the buffer episode it replays (or -1).

    An augmented episode (``meta/aug_id`` >= 0) replays its source demo (the episode with ``aug_id`` -1 and the
    same ``meta/aug_source_episode``) from its splice ``k``
    (``meta/aug_splice_index``, the first replayed frame); from :func:`first_tail_only_step` on, a sample reads
    only replayed frames and labels: those of the source episode's own sample at its matching step (only
    ``wrt_start``, relative to the augmented start, differs).
    Episodes whose source is not an original episode of this buffer, original episodes, other episodes (``aug_id``
    < -1, e.g. SPARTN's) and buffers without these records give -1 (keep every sample).
    The caller drops those samples only where the source episode is in the same split.

    Raises:
        PolicyError: the records exist but do not have one integer per episode.
    """
    ends = np.asarray(buf.episode_ends)
    out, source = np.full(len(ends), -1, np.int64), np.full(len(ends), -1, np.int64)
    have = set(buf.meta.array_keys())
    if not {_AUG_ID, _AUG_SOURCE, _AUG_SPLICE} <= have:
        return out, source
    rec = {}
    for key in (_AUG_ID, _AUG_SOURCE, _AUG_SPLICE):
        arr = np.asarray(buf.meta[key][:])
        if arr.shape != (len(ends),) or not np.issubdtype(arr.dtype, np.integer):
            raise PolicyError(f"{path}: 'meta/{key}' has shape {arr.shape} dtype {arr.dtype}; expected one integer "
                              f"per episode ({len(ends)}) (task.sample_replayed_tails=false reads it)")
        rec[key] = arr.astype(np.int64)
    originals = {int(d): int(ep) for ep, d in enumerate(rec[_AUG_SOURCE]) if rec[_AUG_ID][ep] == -1}  # not -2:
    # a SPARTN short episode of the square study's variants (umi_aug.square.variants)
    lengths = np.diff(np.concatenate([[0], ends]))
    for ep in np.flatnonzero(rec[_AUG_ID] >= 0):
        k = int(rec[_AUG_SPLICE][ep])
        if 0 <= k < lengths[ep] and int(rec[_AUG_SOURCE][ep]) in originals:
            out[ep] = first_tail_only_step(task, k)
            source[ep] = originals[int(rec[_AUG_SOURCE][ep])]
    return out, source


def get_val_mask(n_episodes: int, val_ratio: float, seed: int = 0) -> np.ndarray:
    """Boolean (E,) mask of validation episodes, identical to UMI's ``get_val_mask``: at least one validation and
    one training episode when ``val_ratio > 0``; chosen with ``np.random.default_rng(seed)``."""
    mask = np.zeros(n_episodes, dtype=bool)
    if val_ratio <= 0 or n_episodes < 2:
        return mask
    n_val = min(max(1, round(n_episodes * val_ratio)), n_episodes - 1)
    mask[np.random.default_rng(seed=seed).choice(n_episodes, size=n_val, replace=False)] = True
    return mask


def sample_frame_indices(cur: int, start: int, end: int, horizon: int, down_sample: int) -> tuple[np.ndarray, np.ndarray]:
    """UMI's observation frame indices for current step ``cur`` of episode ``[start, end)``.

    Returns:
        (rgb_idx [h], lowdim_idx [h]) int64: images repeat the earliest in-episode frame of the strided window;
        low-dim indices are clipped to ``[start, end-1]`` (UMI interpolates there; with zero latency that is exact).
    """
    k = np.arange(horizon - 1, -1, -1, dtype=np.int64) * down_sample
    raw = cur - k
    n_valid = min(horizon, (cur - start) // down_sample + 1)
    rgb = np.maximum(raw, cur - (n_valid - 1) * down_sample)
    low = np.clip(raw, start, end - 1)
    return rgb, low


def frame_rows(task: TaskConfig, cur: np.ndarray, start: np.ndarray) -> np.ndarray:
    """:func:`sample_frame_indices`' image rows for many samples at once: [N, img_obs_horizon] int64 for current
    rows ``cur`` [N] of episodes starting at ``start`` [N] (frames before the start repeat the earliest valid)."""
    h, d = task.img_obs_horizon, task.obs_down_sample_steps
    k = np.arange(h - 1, -1, -1, dtype=np.int64) * d
    n_valid = np.minimum(h, (cur - start) // d + 1)
    return np.maximum(cur[:, None] - k[None], (cur - (n_valid - 1) * d)[:, None])


def window_rows(task: TaskConfig, cur: np.ndarray, start: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """UMI's low-dim observation rows [N, h] and action rows [N, H] for current rows ``cur`` [N] of episodes
    ``[start, end)`` (int64 arrays of the same shape; rows index the arrays the episode lives in)."""
    d = task.obs_down_sample_steps
    k = np.arange(task.low_dim_obs_horizon - 1, -1, -1, dtype=np.int64) * d
    low = np.clip(cur[:, None] - k[None], start[:, None], end[:, None] - 1)
    a = cur[:, None] + np.arange(task.action_horizon, dtype=np.int64)[None] * d
    a = np.minimum(a, end[:, None] - 1)  # only reached with action_padding: repeat the last row
    return low, a


def lowdim_from_rows(task: TaskConfig, pose6: list[np.ndarray], gripper: list[np.ndarray],
                     start_pose: list[np.ndarray], low: np.ndarray, a_rows: np.ndarray, cur: np.ndarray,
                     noise_rng: np.random.Generator | None = None, start_pose_noise: float = 0.0,
                     action7: list[np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Low-dim observations and actions (float64) in the policy representation, per robot ``i`` from
    ``pose6[i]`` [M, 6] (pos + rotvec, metres/radians), ``gripper[i]`` [M, 1] (metres) and, with ``wrt_start``,
    ``start_pose[i]`` [M, 6]; ``low`` [N, h], ``a_rows`` [N, H], ``cur`` [N] index those rows. ``action7[i]``
    [M, 7]: absolute commanded targets to label with instead of the poses (``task.action_key``)."""
    out: dict[str, np.ndarray] = {}
    actions = []
    for i in range(task.n_robots):
        p6 = pose6[i]
        pos, rot = p6[low, :3], p6[low, 3:]
        T_cur = pos_rotvec_to_pose(p6[low[:, -1]])
        mp, mr = obs_pose_to_model(pos, rot, task.obs_pose_repr)
        out[f"robot{i}_eef_pos"], out[f"robot{i}_eef_rot_axis_angle"] = mp, mr
        out[f"robot{i}_gripper_width"] = gripper[i][low]
        if task.use_wrt_start:
            sp = start_pose[i][cur].copy()
            if noise_rng is not None and start_pose_noise > 0:
                sp += noise_rng.normal(scale=start_pose_noise, size=sp.shape)
            out[f"robot{i}_eef_rot_axis_angle_wrt_start"] = wrt_start_rot6d(pos, rot, sp)
        a7 = (action7[i][a_rows] if action7 is not None
              else np.concatenate([p6[a_rows], gripper[i][a_rows]], axis=-1))
        # UMI's dataset converts actions with obs_pose_repr but deployment undoes them with action_pose_repr;
        # both are "relative" by default — here action_pose_repr is used on both sides
        actions.append(abs_actions_to_model(a7, T_cur, task.action_pose_repr))
    out["action"] = np.concatenate(actions, axis=-1)
    return out


def to_sample(frames: dict[str, np.ndarray], lowdim: dict[str, np.ndarray], lowdim_keys: list[str]) -> dict[str, Any]:
    """One training sample: ``frames[key]`` uint8 [h, H, W, 3] → float32 (h, 3, H, W) in [0, 1]; ``lowdim`` arrays
    of ONE sample (incl. ``action``) → float32 tensors."""
    obs: dict[str, torch.Tensor] = {}
    for key, f in frames.items():
        obs[key] = torch.from_numpy(np.ascontiguousarray(f.transpose(0, 3, 1, 2))).float().div_(255.0)
    for key in lowdim_keys:
        obs[key] = torch.from_numpy(lowdim[key].astype(np.float32))
    return {"obs": obs, "action": torch.from_numpy(lowdim["action"].astype(np.float32))}


def to_batch(frames: dict[str, np.ndarray], lowdim: dict[str, np.ndarray], lowdim_keys: list[str]) -> dict[str, Any]:
    """A training batch, as the DataLoader collates :func:`to_sample`'s samples: ``frames[key]`` uint8
    [B, h, H, W, 3] → float32 [B, h, 3, H, W] in [0, 1]; ``lowdim`` arrays [B, ...] (incl. ``action``) → float32."""
    obs: dict[str, torch.Tensor] = {}
    for key, f in frames.items():
        obs[key] = torch.from_numpy(f).permute(0, 1, 4, 2, 3).float().div_(255.0).contiguous()
    for key in lowdim_keys:
        obs[key] = torch.from_numpy(lowdim[key].astype(np.float32))
    return {"obs": obs, "action": torch.from_numpy(lowdim["action"].astype(np.float32))}


class UmiPolicyDataset(torch.utils.data.Dataset):
    """UMI replay buffer → ``{'obs': {key: float32 tensor (h, ...)}, 'action': float32 (H, 10·R)}`` samples.

    Args:
        dataset_path: UMI ``.zarr.zip`` or zarr directory.
        task: sampling / representation settings (:class:`TaskConfig`).
        split: "train", "val" or "all" (episode-level split by ``task.val_ratio`` / ``task.split_seed``).
        start_pose_noise: std of the noise added to the start pose for ``wrt_start`` (None: ``task``'s value in
            the training split, 0 otherwise).

    Raises:
        PolicyError: missing keys, image size different from ``task.image_size``, no sample in the split.
    """

    def __init__(self, dataset_path: str | os.PathLike, task: TaskConfig, split: str = "train",
                 start_pose_noise: float | None = None) -> None:
        if split not in ("train", "val", "all"):
            raise PolicyError(f"UmiPolicyDataset: split must be 'train', 'val' or 'all', got {split!r}")
        self.path = str(dataset_path)
        self.task = task
        self.split = split
        self.shape_meta = shape_meta(task)
        self.rgb_keys = sorted(k for k, v in self.shape_meta["obs"].items() if v["type"] == "rgb")
        self.lowdim_keys = sorted(k for k, v in self.shape_meta["obs"].items() if v["type"] == "low_dim")
        self.start_pose_noise = (task.start_pose_noise if split == "train" else 0.0) if start_pose_noise is None \
            else float(start_pose_noise)
        try:
            buf = ReplayBuffer.open(self.path)
        except DatasetError as exc:
            raise PolicyError(f"task.dataset_path: {exc}") from exc
        try:
            self._load_lowdim(buf)
        finally:
            buf.close()
        self.val_mask = get_val_mask(len(self.episode_ends), task.val_ratio, task.split_seed)
        self._build_indices()
        self._buf: Any = None
        self._pid: int | None = None
        self._rng: np.random.Generator | None = None
        self._rng_key: tuple[int, int] | None = None
        self._frames: dict[str, np.ndarray] | None = None  # every frame decoded once (frames_in_memory)

    # ------------------------------------------------------------------ setup
    def _load_lowdim(self, buf) -> None:
        keys = set(buf.keys())
        need = []
        for i in range(self.task.n_robots):
            need += [f"robot{i}_eef_pos", f"robot{i}_eef_rot_axis_angle", f"robot{i}_gripper_width"]
            if self.task.use_wrt_start:
                need.append(f"robot{i}_demo_start_pose")
        need += self.rgb_keys
        if self.task.action_key is not None:
            need.append(self.task.action_key)
        missing = [k for k in need if k not in keys]
        if missing:
            raise PolicyError(f"{self.path}: keys {missing} needed by task {self.task.name!r} "
                              f"(n_robots={self.task.n_robots}, n_cameras={self.task.n_cameras}) are missing; "
                              f"the buffer has {sorted(keys)}")
        S = self.task.image_size
        for k in self.rgb_keys:
            shp = tuple(buf[k].shape[1:])
            if shp != (S, S, 3):
                raise PolicyError(f"{self.path}: key 'data/{k}' holds {shp} images; task.image_size={S} needs "
                                  f"({S}, {S}, 3)")
        self.action7 = self._load_actions(buf) if self.task.action_key is not None else None
        self.episode_ends = buf.episode_ends
        if len(self.episode_ends) == 0:
            raise PolicyError(f"{self.path}: the replay buffer has no episodes")
        self.sample_step = _read_sample_steps(buf, self.path, np.asarray(self.episode_ends))
        n = len(self.episode_ends)
        self.tail_first_sample, self.tail_source = ((np.full(n, -1, np.int64), np.full(n, -1, np.int64))
                                                    if self.task.sample_replayed_tails
                                                    else replayed_tail_first_sample(buf, self.path, self.task))
        self.pose6, self.gripper, self.start_pose = [], [], []
        for i in range(self.task.n_robots):
            pos = np.asarray(buf[f"robot{i}_eef_pos"][:], dtype=np.float64)
            rot = np.asarray(buf[f"robot{i}_eef_rot_axis_angle"][:], dtype=np.float64)
            self.pose6.append(np.concatenate([pos, rot], axis=1))
            self.gripper.append(np.asarray(buf[f"robot{i}_gripper_width"][:], dtype=np.float64))
            if self.task.use_wrt_start:
                self.start_pose.append(np.asarray(buf[f"robot{i}_demo_start_pose"][:], dtype=np.float64))

    def _load_actions(self, buf) -> list[np.ndarray]:
        """Per arm [N, 7] absolute commanded targets from ``data/<task.action_key>`` (checked: shape, finite)."""
        key, R = self.task.action_key, self.task.n_robots
        arr = np.asarray(buf[key][:], dtype=np.float64)
        if arr.shape != (buf.n_steps, 7 * R):
            raise PolicyError(f"{self.path}: key 'data/{key}' (task.action_key) has shape {arr.shape}; expected "
                              f"({buf.n_steps}, {7 * R}): per arm [pos(3) m, rotvec(3) rad, gripper width m]")
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        if bad.size:
            raise PolicyError(f"{self.path}: key 'data/{key}' (task.action_key) holds NaN/Inf at row {int(bad[0])}")
        return [arr[:, 7 * i: 7 * (i + 1)] for i in range(R)]

    def _build_indices(self) -> None:
        t = self.task
        span = (t.action_horizon - 1) * t.obs_down_sample_steps + 1
        cur, start, end = [], [], []
        s = 0
        for ep, e in enumerate(self.episode_ends):
            e = int(e)
            use = {"train": not self.val_mask[ep], "val": bool(self.val_mask[ep]), "all": True}[self.split]
            if use:
                last = e if t.action_padding else e - span + 1
                c = np.arange(s, max(s, last), dtype=np.int64)
                k = int(self.sample_step[ep])
                if k >= 0:  # one sample only (meta/umi_aug_sample_step, e.g. a SPARTN short episode)
                    c = c[c == s + k]
                src = int(self.tail_source[ep])
                if src >= 0 and self.val_mask[src] == self.val_mask[ep]:  # sample_replayed_tails=false: the
                    c = c[c < s + int(self.tail_first_sample[ep])]       # source episode gives these samples
                cur.append(c)
                start.append(np.full_like(c, s))
                end.append(np.full_like(c, e))
            s = e
        cat = (lambda xs: np.concatenate(xs) if xs else np.zeros(0, np.int64))
        self.indices = np.stack([cat(cur), cat(start), cat(end)], axis=1)

    def get_validation_dataset(self) -> "UmiPolicyDataset":
        """The validation split of the same buffer (no start-pose noise)."""
        val = copy.copy(self)
        val.split, val.start_pose_noise = "val", 0.0
        val._buf, val._pid = None, None
        val._build_indices()
        return val

    def __len__(self) -> int:
        return int(self.indices.shape[0])

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_buf"], state["_pid"] = None, None
        return state

    # ------------------------------------------------------------------ sampling
    def _indices(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For sample indices ``idx`` [N]: low-dim obs rows [N, h], action rows [N, H], current rows [N]."""
        cur, start, end = self.indices[idx].T
        low, a = window_rows(self.task, cur, start, end)
        return low, a, cur

    def lowdim_batch(self, idx: np.ndarray, noise_rng: np.random.Generator | None = None) -> dict[str, np.ndarray]:
        """Low-dim observations and actions of samples ``idx`` [N] (float64, no images)."""
        low, a_rows, cur = self._indices(np.asarray(idx, dtype=np.int64))
        return lowdim_from_rows(self.task, self.pose6, self.gripper, self.start_pose, low, a_rows, cur,
                                noise_rng, self.start_pose_noise, self.action7)

    def _noise_rng(self) -> np.random.Generator:
        key = (os.getpid(), torch.initial_seed())
        if self._rng is None or self._rng_key != key:
            self._rng, self._rng_key = np.random.default_rng(key[1] % (2 ** 63)), key
        return self._rng

    def _buffer(self):
        if self._buf is None or self._pid != os.getpid():
            self._buf = ReplayBuffer.open(self.path, check_values=False)
            self._pid = os.getpid()
        return self._buf

    @property
    def has_frames_in_memory(self) -> bool:
        return self._frames is not None

    def frames_nbytes(self) -> int:
        """Bytes of every camera frame of the buffer decoded (uint8)."""
        S = self.task.image_size
        return int(len(self.rgb_keys) * int(self.episode_ends[-1]) * S * S * 3)

    def frames_in_memory(self, max_gb: float, progress: bool = False) -> bool:
        """Decode every camera frame ONCE into RAM (uint8, one array per key) when they take at most ``max_gb``
        GB; samples and :meth:`batch` then index it instead of decoding JPEG-XL chunks (issue #29: two thirds of a
        CPU training step went to per-sample decoding). Returns whether the frames are (now) in memory. The
        validation split made afterwards shares the arrays; DataLoader workers get a copy each (use 0 workers)."""
        if self._frames is not None:
            return True
        if max_gb <= 0 or self.frames_nbytes() > max_gb * 1e9:
            return False

        frames: dict[str, np.ndarray] = {}
        buf = self._buffer()
        n = int(self.episode_ends[-1])
        step = 256
        with tqdm(total=n * len(self.rgb_keys), desc="decoding frames into memory", unit="frame",
                  disable=not progress, mininterval=1.0) as bar:
            for key in self.rgb_keys:
                arr = buf[key]
                out = np.empty((n,) + tuple(arr.shape[1:]), np.uint8)
                for s in range(0, n, step):
                    out[s: s + step] = self._decode(key, arr, s, min(n, s + step))
                    bar.update(min(n, s + step) - s)
                frames[key] = out
        self._frames = frames
        return True

    def batch(self, idx: np.ndarray, noise_rng: np.random.Generator | None = None) -> dict[str, Any]:
        """The collated batch of samples ``idx`` [B] built at once (frames must be in memory:
        :meth:`frames_in_memory`): the same tensors as a DataLoader over ``self[i]`` (tested), with the start-pose
        noise drawn from ``noise_rng`` (default: this process's generator, as ``__getitem__``)."""
        if self._frames is None:
            raise PolicyError("UmiPolicyDataset.batch needs the frames in memory (call frames_in_memory first)")
        idx = np.asarray(idx, dtype=np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= len(self)):
            raise IndexError(f"sample indices {idx.min()}..{idx.max()} out of range for {len(self)} samples")
        low = self.lowdim_batch(idx, self._noise_rng() if noise_rng is None else noise_rng)
        cur, start, _ = self.indices[idx].T
        rows = frame_rows(self.task, cur, start)
        return to_batch({key: self._frames[key][rows] for key in self.rgb_keys}, low, self.lowdim_keys)

    def read_frames(self, key: str, rows: np.ndarray) -> np.ndarray:
        """uint8 [len(rows), H, W, 3] frames of ``camera{j}_rgb``; each distinct frame is decoded once (or read
        from memory after :meth:`frames_in_memory`)."""
        if self._frames is not None:
            return self._frames[key][np.asarray(rows, dtype=np.int64)]
        uniq, inv = np.unique(rows, return_inverse=True)
        arr = self._buffer()[key]
        if len(uniq) > 1 and np.all(np.diff(uniq) == uniq[1] - uniq[0]):
            step = int(uniq[1] - uniq[0])
            frames = self._decode(key, arr, int(uniq[0]), int(uniq[-1]) + 1, step)
        else:
            frames = np.stack([self._decode(key, arr, int(r), int(r) + 1)[0] for r in uniq])
        return frames[inv]

    def _decode(self, key: str, arr, a: int, b: int, step: int = 1) -> np.ndarray:
        """``arr[a:b:step]``; a chunk that cannot be decoded raises :class:`PolicyError` naming the file, key,
        chunk and rows (as ``umi-aug validate --deep`` does) instead of the codec's anonymous traceback."""
        try:
            return arr[a:b:step]
        except Exception as exc:  # noqa: BLE001 - codec errors are of many types (imagecodecs, numcodecs, zlib)
            c = int(arr.chunks[0])
            bad, why = a // c, exc
            for i in range(a // c, (b - 1) // c + 1):  # which chunk of the range (the error path only)
                try:
                    arr[i * c: (i + 1) * c]
                except Exception as e:  # noqa: BLE001
                    bad, why = i, e
                    break
            last = min((bad + 1) * c, arr.shape[0]) - 1
            raise PolicyError(f"{self.path}: key 'data/{key}': chunk {bad} (rows {bad * c}..{last}) cannot be "
                              f"decoded ({type(why).__name__}: {why}); the chunk is corrupt: re-copy or re-create "
                              f"the dataset (`umi-aug validate --deep {self.path}` checks every chunk)") from exc

    def __getitem__(self, index: int) -> dict[str, Any]:
        t = self.task
        if not 0 <= index < len(self):
            raise IndexError(f"sample index {index} out of range for {len(self)} samples")
        low = self.lowdim_batch(np.array([index]), self._noise_rng())
        cur, start, end = (int(v) for v in self.indices[index])
        rgb_rows, _ = sample_frame_indices(cur, start, end, t.img_obs_horizon, t.obs_down_sample_steps)
        frames = {key: self.read_frames(key, rgb_rows) for key in self.rgb_keys}
        return to_sample(frames, {k: v[0] for k, v in low.items()}, self.lowdim_keys)

    # ------------------------------------------------------------------ normaliser
    def fit_normalizer(self) -> LinearNormalizer:
        """UMI's normaliser from every sample of this split, without decoding images: action pos/gripper →
        range [-1, 1], rot6d → identity; obs ``*pos``/``*gripper_width`` → range, rot6d keys → identity."""
        n = len(self)
        if n == 0:
            raise PolicyError(f"{self.path}: split {self.split!r} has no samples (episodes too short for "
                              f"action_horizon={self.task.action_horizon} × down_sample="
                              f"{self.task.obs_down_sample_steps}?); cannot fit the normaliser")
        chunks: dict[str, list[np.ndarray]] = {}
        for s in range(0, n, _FIT_CHUNK):
            d = self.lowdim_batch(np.arange(s, min(n, s + _FIT_CHUNK)))
            for k, v in d.items():
                chunks.setdefault(k, []).append(v.reshape(-1, v.shape[-1]))
        data = {k: np.concatenate(v) for k, v in chunks.items()}
        norm = LinearNormalizer()
        act = data["action"]
        scale, offset = [], []
        for i in range(self.task.n_robots):
            a = act[:, 10 * i: 10 * (i + 1)]
            for part, fit in ((a[:, :3], range_params), (a[:, 3:9], None), (a[:, 9:], range_params)):
                sc, of = fit(part) if fit else identity_params(part.shape[1])
                scale.append(sc)
                offset.append(of)
        norm.set("action", np.concatenate(scale), np.concatenate(offset))
        for key in self.lowdim_keys:
            x = data[key]
            if key.endswith("pos") or key.endswith("gripper_width"):
                norm.set(key, *range_params(x))
            elif "rot_axis_angle" in key:
                norm.set(key, *identity_params(x.shape[1]))
            else:  # pragma: no cover - shape_meta only makes the keys above
                raise PolicyError(f"no normaliser rule for observation key {key!r}")
        return norm

    def describe(self) -> str:
        n_ep = {"train": int((~self.val_mask).sum()), "val": int(self.val_mask.sum()),
                "all": len(self.val_mask)}[self.split]
        return f"{Path(self.path).name} [{self.split}]: {n_ep} episodes, {len(self)} samples"
