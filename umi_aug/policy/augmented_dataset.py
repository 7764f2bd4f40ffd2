"""On-the-fly augmenting training dataset (issue #9 item 4, ``python train/train.py aug=freespace|obstacle``).

:class:`AugmentedUmiDataset` wraps the original :class:`UmiPolicyDataset` (training split) and a prepared
augmentation session (:func:`umi_aug.augment.prepare_session`: reconstruction, 3DGS scene, contact split — cached on
disk). Its samples ``0 .. n_original-1`` are the original samples, unchanged; the following ``n_augmented`` slots
(``ratio`` of the total) each draw, from ``(seed, epoch, slot)`` alone, a training demo, an augmentation id in
``[0, n_aug_per_demo)``, a mode and a current step, then

1. plan that episode (cone start → optimised trajectory → splice; :func:`umi_aug.augment.plan_episode`, which is
   deterministic in ``(cfg.seed, demo, aug_id, mode)``) or fetch it from a bounded per-process LRU cache, and
2. render ONLY the frames the sample's observation window needs (``img_obs_horizon`` frames;
   :func:`umi_aug.augment.render_episode_frames`: 3DGS + gripper overlay before the splice, original frames
   after it).

Low-dim observations and actions use exactly UMI's sampling and representation code of :mod:`.dataset`, so an
augmented sample equals the sample the offline export (``umi-aug augment``) gives for the same episode and step
(images up to the export's JPEG-XL compression). With ``rerender_fraction`` > 0 that fraction of the augmented
slots draws a demo's re-rendered copy instead (:func:`umi_aug.augment.rerender_episode`: the demo's own poses and
labels, its approach rendered by the scene model — the export's ``--rerender-originals`` episode). DataLoader
workers each keep their own in-memory caches and open the session's files lazily (once per process: with
persistent workers, once per run).

Fast paths (``fast_paths``, default all of :data:`~umi_aug.policy.augmented_paths.FAST_PATHS`; ``()`` is the
reference, kept; both give the same samples): a plan cache on disk shared by epochs, workers and runs, and a frame
path that decodes only the original frames a sample needs (:mod:`umi_aug.policy.augmented_paths`).

The epoch lives in a shared-memory tensor, so :meth:`AugmentedUmiDataset.set_epoch` in the main process reaches
persistent DataLoader workers (forked or spawned) before the next epoch's first index is sent to them.
"""

from __future__ import annotations

import copy
import logging
import time
from collections import OrderedDict
from typing import Any, Sequence

import numpy as np
import torch

from umi_aug.errors import PolicyError
from umi_aug.policy.dataset import (UmiPolicyDataset, first_tail_only_step, lowdim_from_rows, sample_frame_indices,
                                    to_sample, window_rows)
from umi_aug.policy.augmented_paths import FAST_PATHS, PlanDiskCache, sample_frames
from umi_aug.policy.normalizer import LinearNormalizer

__all__ = ["AugmentedUmiDataset", "AugmentedSlot"]

log = logging.getLogger(__name__)

#: Planned episodes kept per process (an episode is ~N × 200 bytes of poses: memory stays small).
DEFAULT_PLAN_CACHE = 256
#: Augmented episodes planned (not rendered) to widen the normaliser's ranges.
NORMALIZER_EPISODES = 16
#: Draws per augmented slot before it falls back to an original sample (a draw fails when planning fails).
MAX_SLOT_DRAWS = 8
#: ``draw`` index of the slots used to fit the normaliser (never used by ``__getitem__``).
NORMALIZER_DRAW = 1_000_000


class AugmentedSlot(tuple):
    """``(demo_index, aug_id, mode, cur)`` of one augmented sample."""

    __slots__ = ()

    def __new__(cls, demo_index: int, aug_id: int, mode: str, cur: int) -> "AugmentedSlot":
        return super().__new__(cls, (int(demo_index), int(aug_id), str(mode), int(cur)))


class AugmentedUmiDataset(torch.utils.data.Dataset):
    """Original samples plus on-the-fly augmented ones (see the module docstring).

    Args:
        original: the training split of the session's original dataset (its episode ``i`` is demo ``i``).
        assets: :class:`umi_aug.augment.SessionAssets` from :func:`umi_aug.augment.prepare_session`.
        modes: augmentation modes drawn uniformly (``("freespace",)``, ``("obstacle",)`` or both).
        ratio: fraction of augmented samples in ``[0, 1)``; ``n_augmented = round(n_original·ratio/(1-ratio))``.
        n_aug_per_demo: augmentation ids ``0..n-1`` per demo (distinct start poses / obstacles).
        seed: root seed of the slot draws (the episodes themselves follow ``assets.cfg.seed``).
        plan_cache_size: planned episodes kept per process (LRU).
        fast_paths: ``"plan_disk_cache"`` and/or ``"frames"`` (see :mod:`umi_aug.policy.augmented_paths`); ``()``
            = the reference paths (plan in every process and epoch, :func:`umi_aug.augment.render_episode_frames`).
        plan_cache_dir: folder of the on-disk plan cache (default ``<assets.work_dir>/plans``).
        rerender_fraction: fraction in ``[0, 1)`` of the augmented slots that are samples of a demo's re-rendered
            copy (its own labels, its approach frames rendered; :meth:`draw`) instead of a planned episode.

    Raises:
        PolicyError: bad ratio/modes, image size or camera count that does not match the session, or no training
            demo that can be augmented.
    """

    def __init__(self, original: UmiPolicyDataset, assets: Any, modes: Sequence[str] = ("freespace",),
                 ratio: float = 0.5, n_aug_per_demo: int = 1000, seed: int = 0,
                 plan_cache_size: int = DEFAULT_PLAN_CACHE, fast_paths: Sequence[str] = FAST_PATHS,
                 plan_cache_dir: str | None = None, rerender_fraction: float = 0.0) -> None:
        if not 0.0 <= ratio < 1.0:
            raise PolicyError(f"aug.ratio = {ratio!r}: expected a fraction in [0, 1)")
        if not 0.0 <= rerender_fraction < 1.0:  # NaN fails too
            raise PolicyError(f"aug.rerender_fraction = {rerender_fraction!r}: expected a fraction in [0, 1)")
        if n_aug_per_demo < 1:
            raise PolicyError(f"aug.n_aug_per_demo = {n_aug_per_demo!r}: expected >= 1")
        bad = [m for m in modes if m not in ("freespace", "obstacle")]
        if not modes or bad:
            raise PolicyError(f"augmentation modes {list(modes)!r}: expected 'freespace' and/or 'obstacle'")
        unknown = sorted(set(fast_paths) - set(FAST_PATHS))
        if unknown:
            raise PolicyError(f"AugmentedUmiDataset: fast_paths {unknown} unknown (have {list(FAST_PATHS)})")
        t = original.task
        if t.n_robots != 1 or t.n_cameras != 1:
            raise PolicyError(f"aug: on-the-fly augmentation supports one arm and one camera (task has "
                              f"n_robots={t.n_robots}, n_cameras={t.n_cameras})")
        if assets.cfg.image_size != t.image_size:
            raise PolicyError(f"aug: the session renders {assets.cfg.image_size}² frames but task.image_size = "
                              f"{t.image_size}")
        self.original = original
        self.assets = assets
        self.modes = tuple(modes)
        self.ratio = float(ratio)
        self.rerender_fraction = float(rerender_fraction)
        self.n_aug_per_demo = int(n_aug_per_demo)
        self.seed = int(seed)
        self._epoch = torch.zeros((), dtype=torch.int64).share_memory_()
        self.plan_cache_size = int(plan_cache_size)
        self.fast_paths = tuple(fast_paths)
        self.plan_disk = (PlanDiskCache(plan_cache_dir or (assets.work_dir / "plans"))
                          if "plan_disk_cache" in self.fast_paths else None)
        train_eps = np.flatnonzero(~original.val_mask) if original.split == "train" else np.arange(len(original.val_mask))
        self.demos = [int(d) for d in assets.augmentable if d in set(train_eps.tolist())]
        if not self.demos and ratio > 0:
            raise PolicyError(f"aug: no training demo of {assets.session_dir} can be augmented (demos with a contact "
                              f"frame: {assets.augmentable}; training episodes: {train_eps.tolist()})")
        n = len(original)
        self.n_augmented = int(round(n * ratio / (1.0 - ratio))) if self.demos else 0
        self.shape_meta = original.shape_meta
        self._plans: OrderedDict = OrderedDict()
        self.stats = {"plans": 0, "plan_hits": 0, "plans_solved": 0, "plan_disk_hits": 0, "plan_failures": 0,
                      "frames_rendered": 0}
        #: seconds spent per part of the augmented samples in this process (plan / decode / render / overlay /
        #: lowdim / to_tensor): the benchmark's time split
        self.timings: dict[str, float] = {}

    # ------------------------------------------------------------------ bookkeeping
    def __len__(self) -> int:
        return len(self.original) + self.n_augmented

    @property
    def epoch(self) -> int:
        return int(self._epoch)

    def set_epoch(self, epoch: int) -> None:
        """Draw a new set of augmented slots (same seed + epoch → same slots); seen by persistent workers too."""
        self._epoch.fill_(int(epoch))

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_plans"] = OrderedDict()
        state["timings"] = {}
        return state

    def _tick(self, part: str, t0: float) -> float:
        t1 = time.perf_counter()
        self.timings[part] = self.timings.get(part, 0.0) + t1 - t0
        return t1

    def get_validation_dataset(self) -> UmiPolicyDataset:
        """Validation = the original validation split, never augmented."""
        return self.original.get_validation_dataset()

    def describe(self) -> str:
        rr = f", {self.rerender_fraction:g} of them re-rendered demos" if self.rerender_fraction else ""
        return (f"{self.original.describe()} + {self.n_augmented} augmented slots ({'/'.join(self.modes)}, ratio "
                f"{self.ratio:g}, demos {self.demos}, {self.n_aug_per_demo} augmentations each{rr})")

    # ------------------------------------------------------------------ episodes
    def planned(self, demo_index: int, aug_id: int, mode: str):
        """The planned episode ``(demo, aug_id, mode)`` (cached per process, LRU), or None if planning failed;
        mode ``"rerender"``: the demo's re-rendered copy (nothing planned)."""
        from umi_aug.augment import RERENDER_MODE, plan_episode, rerender_episode  # lazy, start-up: cv2, scipy

        key = (int(demo_index), int(aug_id), mode)
        if key in self._plans:
            self._plans.move_to_end(key)
            self.stats["plan_hits"] += 1
            return self._plans[key]
        t0 = time.perf_counter()
        handle = self.assets.for_demo(key[0])
        found, planned = False, None
        if handle.demos[key[0]].contact_index is None:  # a lazily built scene group without a splice frame
            found = True
        elif mode == RERENDER_MODE:
            found, planned = True, rerender_episode(handle, key[0])
        elif self.plan_disk is not None:
            found, planned = self.plan_disk.load(handle, *key)
            self.stats["plan_disk_hits"] += found
        self.stats["plans"] += 1  # episodes not in this process's LRU (solved, or read from the disk cache)
        if not found:
            planned = plan_episode(handle, key[0], key[1], mode)
            self.stats["plans_solved"] += 1
            if self.plan_disk is not None:
                self.plan_disk.save(handle, *key, planned)
        self.stats["plan_failures"] += planned is None
        self._tick("plan", t0)
        self._plans[key] = planned
        while len(self._plans) > self.plan_cache_size:
            self._plans.popitem(last=False)
        return planned

    def _episode_arrays(self, planned) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray],
                                                list[np.ndarray] | None]:
        """Per arm: poses [N, 6], widths [N, 1], start poses [N, 6] and, with ``task.action_key``, the commanded
        targets [N, 7] of an augmented episode (a re-rendered demo: its original rows as stored)."""
        from umi_aug.augment import RERENDER_MODE  # lazy, start-up: cv2, scipy

        d = planned.demo_index
        ep = (self.assets.for_demo(d).original_lowdim(d) if planned.mode == RERENDER_MODE
              else self.assets.umi_episode(planned.episode, d))
        pose6 = np.concatenate([ep["robot0_eef_pos"], ep["robot0_eef_rot_axis_angle"]], axis=1).astype(np.float64)
        key = self.original.task.action_key
        if key is not None and key not in ep:
            raise PolicyError(f"task.action_key = {key!r}: augmented episodes of {self.assets.session_dir} have no "
                              f"such key (only sources whose demos carry commanded targets, e.g. square demos)")
        action7 = None if key is None else [np.asarray(ep[key], np.float64)]
        return ([pose6], [ep["robot0_gripper_width"].astype(np.float64)], [ep["robot0_demo_start_pose"]],
                action7)

    def n_current_steps(self, n_frames: int, splice_index: int | None = None) -> int:
        """Valid current steps of an episode of ``n_frames`` frames (UMI: the action window must fit); with
        ``task.sample_replayed_tails=false`` and the episode's ``splice_index``, only the steps before those that
        read nothing but the replayed tail (the original samples already hold those: :func:`first_tail_only_step`)."""
        t = self.original.task
        span = (t.action_horizon - 1) * t.obs_down_sample_steps + 1
        n = n_frames if t.action_padding else max(0, n_frames - span + 1)
        if not t.sample_replayed_tails and splice_index is not None:
            n = min(n, first_tail_only_step(t, splice_index))
        return n

    def draw(self, rng: np.random.Generator) -> tuple[int, int, str]:
        """Demo, aug id and mode of one augmented sample from ``rng``: uniform over the training demos, the ids and
        the modes; then, with probability ``rerender_fraction``, the demo's re-rendered copy instead (id 0, mode
        ``"rerender"``; with 0 nothing more is drawn, so the generator's later draws are as without it)."""
        demo = self.demos[int(rng.integers(len(self.demos)))]
        aug_id = int(rng.integers(self.n_aug_per_demo))
        mode = self.modes[int(rng.integers(len(self.modes)))]
        if self.rerender_fraction > 0.0 and rng.random() < self.rerender_fraction:
            from umi_aug.augment import RERENDER_MODE  # lazy, start-up: cv2, scipy

            return demo, 0, RERENDER_MODE
        return demo, aug_id, mode

    def slot(self, j: int, draw: int = 0) -> tuple[int, int, str, np.random.Generator]:
        """Demo, aug id, mode of augmented slot ``j`` (its ``draw``-th try; :meth:`draw`) and the slot's generator
        (for the step and the start-pose noise); a function of ``(seed, epoch, j, draw)`` only."""
        rng = np.random.default_rng([self.seed, self.epoch, int(j), int(draw)])
        return (*self.draw(rng), rng)

    def augmented_sample(self, demo_index: int, aug_id: int, mode: str, cur: int,
                         noise_rng: np.random.Generator | None = None) -> dict[str, Any] | None:
        """The sample of augmented episode ``(demo, aug_id, mode)`` at current step ``cur``; None if the episode
        could not be planned. Without ``noise_rng`` no start-pose noise is added."""
        planned = self.planned(demo_index, aug_id, mode)
        if planned is None:
            return None
        t = self.original.task
        n = planned.n_frames
        if not 0 <= cur < max(1, self.n_current_steps(n)):
            raise PolicyError(f"augmented episode {(demo_index, aug_id, mode)} has {n} frames: step {cur} has no "
                              "full action window")
        t0 = time.perf_counter()
        pose6, grip, start, action7 = self._episode_arrays(planned)
        c = np.array([cur], np.int64)
        low, a_rows = window_rows(t, c, np.zeros(1, np.int64), np.full(1, n, np.int64))
        lowdim = lowdim_from_rows(t, pose6, grip, start, low, a_rows, c, noise_rng,
                                  self.original.start_pose_noise if noise_rng is not None else 0.0, action7)
        rgb_rows, _ = sample_frame_indices(cur, 0, n, t.img_obs_horizon, t.obs_down_sample_steps)
        uniq, inv = np.unique(rgb_rows, return_inverse=True)
        t0 = self._tick("lowdim", t0)
        handle = self.assets.for_demo(planned.demo_index)
        if "frames" in self.fast_paths:
            frames = sample_frames(handle, planned, uniq, self.timings)[inv]
        else:
            from umi_aug.augment import render_episode_frames  # lazy, start-up: cv2

            frames = render_episode_frames(handle, planned, uniq)[inv]
            t0 = self._tick("frames", t0)
        self.stats["frames_rendered"] += len(uniq)
        key = self.original.rgb_keys[0]
        t0 = time.perf_counter()
        out = to_sample({key: frames}, {k: v[0] for k, v in lowdim.items()}, self.original.lowdim_keys)
        self._tick("to_tensor", t0)
        return out

    # ------------------------------------------------------------------ torch Dataset
    def __getitem__(self, index: int) -> dict[str, Any]:
        if not 0 <= index < len(self):
            raise IndexError(f"sample index {index} out of range for {len(self)} samples")
        n_orig = len(self.original)
        if index < n_orig:
            return self.original[index]
        j = index - n_orig
        for draw in range(MAX_SLOT_DRAWS):
            demo, aug_id, mode, rng = self.slot(j, draw)
            planned = self.planned(demo, aug_id, mode)
            if planned is None:
                continue
            steps = self.n_current_steps(planned.n_frames, planned.splice_index)
            if steps == 0:
                continue
            sample = self.augmented_sample(demo, aug_id, mode, int(rng.integers(steps)), rng)
            if sample is not None:
                return sample
        log.warning("augmented slot %d: no plannable episode after %d draws; using an original sample", j,
                    MAX_SLOT_DRAWS)
        return self.original[j % n_orig]

    # ------------------------------------------------------------------ normaliser
    def fit_normalizer(self, n_episodes: int = NORMALIZER_EPISODES) -> LinearNormalizer:
        """UMI's normaliser over the original samples plus every step of ``n_episodes`` planned (not rendered)
        augmented episodes, so the ranges cover the augmented starts."""
        return self.normalizer_dataset(n_episodes).fit_normalizer()

    def normalizer_dataset(self, n_episodes: int = NORMALIZER_EPISODES) -> UmiPolicyDataset:
        """The samples the normaliser is fitted on, as a dataset (low-dim only: :meth:`UmiPolicyDataset.lowdim_batch`):
        the original training split plus every step of ``n_episodes`` planned (not rendered) augmented episodes
        (the original split itself when nothing is augmented or no episode could be planned)."""
        if self.n_augmented == 0:
            return self.original
        extra = copy.copy(self.original)
        pose6, grip, start = list(extra.pose6[0:1]), list(extra.gripper[0:1]), list(extra.start_pose[0:1])
        act = list(extra.action7[0:1]) if extra.action7 is not None else None
        ends, rows = [int(e) for e in extra.episode_ends], []
        base = len(pose6[0])
        for k in range(n_episodes):
            demo, aug_id, mode, _ = self.slot(k, NORMALIZER_DRAW)
            planned = self.planned(demo, aug_id, mode)
            if planned is None:
                continue
            p, g, s, a = self._episode_arrays(planned)
            pose6.append(p[0])
            grip.append(g[0])
            start.append(s[0])
            if act is not None:
                act.append(a[0])
            base += len(p[0])
            ends.append(base)
            rows.append(len(ends) - 1)
        if not rows:
            return self.original
        extra.pose6 = [np.concatenate(pose6)]
        extra.gripper = [np.concatenate(grip)]
        if act is not None:
            extra.action7 = [np.concatenate(act)]
        if self.original.task.use_wrt_start:
            extra.start_pose = [np.concatenate(start)]
        extra.episode_ends = np.asarray(ends, np.int64)
        # planned episodes are whole episodes: every step a sample (-1), the originals keep their own setting
        extra.sample_step = np.concatenate([np.asarray(self.original.sample_step, np.int64),
                                            np.full(len(ends) - len(self.original.sample_step), -1, np.int64)])
        pad = np.full(len(ends) - len(self.original.sample_step), -1, np.int64)  # normaliser: every step
        extra.tail_first_sample = np.concatenate([self.original.tail_first_sample, pad])
        extra.tail_source = np.concatenate([self.original.tail_source, pad])
        extra.val_mask = np.zeros(len(ends), bool)
        extra.val_mask[: len(self.original.val_mask)] = self.original.val_mask
        extra.split = "train"
        extra._build_indices()
        return extra
