"""Training loop (UMI's ``TrainDiffusionUnetImageWorkspace``, trimmed): AdamW, warm-up + cosine schedule, EMA,
validation loss, sampled-action MSE, atomic checkpoints with resume, tqdm progress and a JSONL metrics log.

``TrainWorkspace(cfg).run()`` writes under ``output_dir``:

* ``checkpoints/latest.ckpt`` — every ``training.checkpoint_every`` epochs and at the end (see
  :mod:`umi_aug.policy.checkpoint`); ``training.resume`` continues from it (optimizer, scheduler, EMA, step).
  Checkpoints are taken between epochs, at ``max_steps`` and, with ``training.checkpoint_every_steps``, every that
  many steps mid-epoch; a run resumed from a mid-epoch checkpoint continues with the next batch of that epoch's
  order (the data order of each epoch is a function of ``seed`` and the epoch number).
* ``logs.jsonl`` — one JSON object per optimiser step (``train_loss``, ``lr``) and per epoch
  (``train_loss_epoch``, ``val_loss``, ``train_action_mse_error``).
"""

from __future__ import annotations

import copy
import json
import logging
import math
import os
import random
import subprocess
import sys
import time
from contextlib import nullcontext
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

import numpy as np
import torch

from umi_aug.errors import PolicyError
from umi_aug.policy.augmented_dataset import AugmentedUmiDataset
from umi_aug.policy.checkpoint import load_checkpoint, save_checkpoint
from umi_aug.policy.config import (AUG_MODES, AugConfig, TrainConfig, check_aug, check_config, config_to_dict,
                                  structured_config)
from umi_aug.policy.dataset import UmiPolicyDataset
from umi_aug.policy.chunk_policy import ChunkPolicy
from umi_aug.policy.ema import EMA
from umi_aug.policy.heads import build_policy
from umi_aug.runtime import configure_threads

if TYPE_CHECKING:  # annotations only: umi_aug.augment loads cv2 and scipy at import
    from umi_aug.augment.config import SplatStageConfig

__all__ = ["TrainWorkspace", "resolve_dataset_path", "aug_splat_stage", "build_augmented_dataset", "seed_everything",
           "build_optimizer", "build_lr_scheduler", "iter_jsonl", "make_loader", "loader_context", "EpochSampler",
           "MemoryBatches", "worker_init"]

log = logging.getLogger(__name__)


def aug_splat_stage(a: AugConfig, plain: bool) -> SplatStageConfig:
    """The 3DGS stage (``umi_aug.augment.SplatStageConfig``) of ``aug.splat_*``: a field left None takes umi-aug's
    default for the input, exactly as ``umi-aug augment`` without 3DGS flags trains it, so both build (and share)
    the same cached scene — a plain dataset's ``dataset_splat_stage()`` (550 steps, 30k Gaussians, the short
    schedule), a session's ``SplatStageConfig()`` (1500 steps, 25k Gaussians)."""
    # lazy, start-up: cv2, scipy
    from umi_aug.augment.config import SplatStageConfig, dataset_splat_stage

    given = {"iterations": a.splat_iterations, "max_gaussians": a.splat_max_gaussians,
             "scale_reg": a.splat_scale_reg, "coarse_downscale": a.splat_coarse_downscale}
    if plain:
        return dataset_splat_stage(**given)
    return SplatStageConfig(**{k: v for k, v in given.items() if v is not None})


def build_augmented_dataset(train: UmiPolicyDataset, dataset_path: Path, cfg: TrainConfig,
                            splat: SplatStageConfig | None = None) -> AugmentedUmiDataset:
    """``aug=freespace|obstacle|both``: prepare the session holding ``dataset_path`` (cached stages) and wrap the
    original training split in an :class:`~umi_aug.policy.augmented_dataset.AugmentedUmiDataset`. ``splat``: the
    3DGS stage to use instead of :func:`aug_splat_stage`'s (UMI's drop-in passes a stage cache's own settings)."""
    # lazy, start-up: cv2, scipy
    from umi_aug.augment import AugmentConfig, prepare_session

    a = cfg.aug
    session = Path(a.session_dir).absolute() if a.session_dir else dataset_path.parent
    plain = not a.session_dir and not (session / "demos").is_dir()  # a plain UMI dataset: scenes from its frames
    if not plain and not (session / "demos").is_dir():
        raise PolicyError(f"aug={a.name}: {session} is not a UMI session folder (no demos/); set aug.session_dir to the "
                          "session (demos/mapping, demos/demo_*, calibration/), or leave it empty to build the scenes "
                          "from the dataset's own frames")
    if plain:
        work = Path(a.work_dir).absolute() if a.work_dir else dataset_path.with_name(dataset_path.name + ".augment")
    else:
        work = Path(a.work_dir).absolute() if a.work_dir else session / "augment"
    modes = AUG_MODES[a.name]
    acfg = AugmentConfig(mode=modes[0] if len(modes) == 1 else "both", seed=a.seed,
                         cone_half_angle_deg=a.cone_half_angle_deg, cone_radius_m=a.cone_radius_m,
                         image_size=cfg.task.image_size,
                         splat=splat if splat is not None else aug_splat_stage(a, plain))
    if plain:
        from umi_aug.augment.dataset_source import (DatasetInput, parse_scene_group,  # lazy, start-up: cv2
                                                    prepare_dataset)

        # lazily: a scene group is built (or read from its cache) by the first process that samples one of its
        # episodes (the normaliser fit here, then the DataLoader workers), so training starts at once and the
        # validation episodes' scenes are never built
        train_eps = tuple(int(e) for e in np.flatnonzero(~train.val_mask)) if train.split == "train" else None
        log.info("aug=%s: scenes of dataset %s built from its own frames on first use (cached in %s)", a.name,
                 dataset_path, work)
        assets = prepare_dataset(dataset_path, work, acfg, DatasetInput(tcp_offset_m=a.tcp_offset_m,
                                                                        scene_group=parse_scene_group(
                                                                            a.scene_group),
                                                                        episodes=train_eps),
                                 lazy=True)
    else:
        log.info("aug=%s: preparing session %s (cached in %s)", a.name, session, work)
        assets = prepare_session(session, work, acfg)
    return AugmentedUmiDataset(train, assets, modes, ratio=a.ratio, n_aug_per_demo=a.n_aug_per_demo, seed=a.seed,
                               plan_cache_size=a.plan_cache_size, rerender_fraction=a.rerender_fraction)


def epoch_seed(seed: int, epoch: int) -> int:
    """Seed of epoch ``epoch``'s shuffle (the DataLoader generator's)."""
    return int(seed) * 100003 + int(epoch)


class EpochSampler(torch.utils.data.Sampler):
    """The order a fresh ``DataLoader(shuffle=..., generator=Generator().manual_seed(epoch_seed(seed, epoch)))``
    gives (the loader draws its worker base seed from the generator first, then ``randperm``), for a loader built
    once: :meth:`set_epoch` selects the epoch, so persistent workers keep running across epochs."""

    def __init__(self, n: int, seed: int, shuffle: bool = True) -> None:
        self.n, self.seed, self.shuffle, self.epoch, self.start = int(n), int(seed), bool(shuffle), 0, 0

    def set_epoch(self, epoch: int, start: int = 0) -> None:
        """Select the epoch; ``start`` skips the first ``start`` indices of its order (a mid-epoch resume)."""
        self.epoch, self.start = int(epoch), max(0, int(start))

    def __len__(self) -> int:
        return max(0, self.n - self.start)

    def __iter__(self):
        if not self.shuffle:
            return iter(range(self.start, self.n))
        g = torch.Generator()
        g.manual_seed(epoch_seed(self.seed, self.epoch))
        torch.empty((), dtype=torch.int64).random_(generator=g)  # the loader's base-seed draw
        return iter(torch.randperm(self.n, generator=g).tolist()[self.start:])


class MemoryBatches:
    """The batches of a dataset whose frames are in memory (:meth:`UmiPolicyDataset.frames_in_memory`), in the
    order the DataLoader path gives (:class:`EpochSampler`), each built at once by :meth:`UmiPolicyDataset.batch`
    instead of per sample + collate (same tensors: tested)."""

    def __init__(self, ds: UmiPolicyDataset, batch_size: int, shuffle: bool, seed: int, epoch: int = 0,
                 start_batch: int = 0) -> None:
        self.ds, self.batch_size = ds, int(batch_size)
        self.sampler = EpochSampler(len(ds), seed, shuffle)
        self.sampler.set_epoch(epoch, start_batch * self.batch_size)

    def __len__(self) -> int:
        return -(-len(self.sampler) // self.batch_size)

    def __iter__(self) -> Iterator[dict[str, Any]]:
        order = np.fromiter(iter(self.sampler), dtype=np.int64)
        for i in range(0, len(order), self.batch_size):
            yield self.ds.batch(order[i: i + self.batch_size])


def worker_init(worker_id: int) -> None:
    """DataLoader worker start: one thread for torch, numba and OpenCV (the workers are the parallelism)."""
    torch.set_num_threads(1)
    try:
        import numba

        numba.set_num_threads(1)
    except (ImportError, ValueError):  # pragma: no cover - numba missing / pool not launchable
        pass
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:  # pragma: no cover
        pass


def loader_context(ds: torch.utils.data.Dataset) -> str:
    """``"spawn"``, for every dataset: a DataLoader worker FORKED from a process that has run multi-threaded work
    blocks in its first parallel kernel, because the parent's thread pools do not survive the fork:
    - torch's OpenMP pool (libgomp): the plain :class:`UmiPolicyDataset` under ``train/train.py`` with 2 forked
      workers made no step in 300 s on 2 cores (each worker waiting inside ``Tensor.float()``); with a 1-thread
      parent, or spawned workers, it trains (2026-11-26; ``tests/policy/test_dataset.py``);
    - numba's pool, for a dataset that renders (the fork variant of ``tests/policy/test_augmented_dataset_fast.py``
      hung).
    Spawned workers start once per run (persistent workers): 2–3 s."""
    return "spawn"


def make_loader(ds: torch.utils.data.Dataset, batch_size: int, shuffle: bool, seed: int, epoch: int = 0,
                num_workers: int = 0, pin_memory: bool = False, persistent: bool = True,
                context: str | None = "spawn", start_batch: int = 0) -> torch.utils.data.DataLoader:
    """The training/validation DataLoader, its order from :class:`EpochSampler` (the order of a fresh
    ``DataLoader(shuffle=..., generator=<seeded for epoch>)`` iterated directly). ``persistent`` with workers: built
    once, persistent workers (call ``loader.sampler.set_epoch(e)`` and the dataset's ``set_epoch`` before each
    epoch); otherwise one loader per epoch. Both give the same index order per epoch. Workers get :func:`worker_init`;
    ``context``: ``"spawn"`` (default, see :func:`loader_context`), ``"fork"``, ``"forkserver"``, or None (the
    platform's default: fork on Linux — only for a parent that has run no multi-threaded torch/numba work).
    ``start_batch`` > 0: the epoch's order from that batch on (:class:`EpochSampler`; a mid-epoch resume)."""
    common = dict(batch_size=batch_size, num_workers=num_workers, pin_memory=pin_memory, drop_last=False,
                  worker_init_fn=worker_init if num_workers > 0 else None,
                  multiprocessing_context=context if num_workers > 0 else None)
    g = torch.Generator()  # the workers' base seed comes from it (never from the global torch RNG)
    g.manual_seed(epoch_seed(seed, epoch))
    # the order always comes from EpochSampler (not the loader's RandomSampler, whose order also depends on how
    # many draws the loader's iterator makes from `g` first — one more under tqdm), so a resumed epoch, a
    # persistent loader and a fresh one agree
    sampler = EpochSampler(len(ds), seed, shuffle)
    sampler.set_epoch(epoch, start_batch * batch_size)
    return torch.utils.data.DataLoader(ds, sampler=sampler, generator=g,
                                       persistent_workers=persistent and num_workers > 0, **common)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)


def resolve_dataset_path(cfg: TrainConfig) -> Path:
    """``task.dataset_path`` as an absolute path; builds it first when missing and ``task.make_if_missing`` says
    how ("demo": ``python -m umi_aug demo --out <parent>``; "session": :func:`umi_aug.sim.session.make_session`)."""
    raw = cfg.task.dataset_path
    if raw in ("", "???"):
        raise PolicyError("task.dataset_path is not set: pass task.dataset_path=/path/to/dataset.zarr.zip "
                          "(a UMI replay buffer) or pick a task with a default (task=demo, task=session)")
    try:
        from hydra.utils import to_absolute_path

        path = Path(to_absolute_path(raw))
    except (ImportError, ValueError):
        path = Path(raw).absolute()
    if path.exists():
        return path
    how = cfg.task.make_if_missing
    if not how:
        raise PolicyError(f"task.dataset_path: {path} does not exist (set task.make_if_missing=demo|session to "
                          "build a synthetic dataset there)")
    if path.name != "dataset.zarr.zip":
        raise PolicyError(f"task.make_if_missing={how}: the generators write <dir>/dataset.zarr.zip, but "
                          f"task.dataset_path is {path}")
    log.info("%s is missing: building it (task.make_if_missing=%s)", path, how)
    if how == "demo":
        res = subprocess.run([sys.executable, "-m", "umi_aug", "demo", "--out", str(path.parent)],
                             capture_output=True, text=True)
        if res.returncode != 0:
            raise PolicyError(f"`umi-aug demo --out {path.parent}` failed ({res.returncode}): {res.stderr[-2000:]}")
    else:
        try:
            from umi_aug.sim.session import make_session
        except ImportError as exc:
            raise PolicyError(f"task.make_if_missing=session needs umi_aug.sim (the synthetic session generator): "
                              f"{exc}") from exc
        make_session(path.parent, seed=cfg.training.seed)
    if not path.exists():
        raise PolicyError(f"task.make_if_missing={how} ran but {path} still does not exist")
    return path


def build_optimizer(policy: ChunkPolicy, cfg: TrainConfig) -> torch.optim.Optimizer:
    """AdamW; the image backbone gets ``lr · pretrained_encoder_lr_scale`` when it started from pretrained weights."""
    t = cfg.training
    enc = {id(p) for p in policy.obs_encoder.backbone_parameters()}
    enc_params = [p for p in policy.parameters() if id(p) in enc and p.requires_grad]
    rest = [p for p in policy.parameters() if id(p) not in enc and p.requires_grad]
    enc_lr = t.lr * (t.pretrained_encoder_lr_scale if policy.obs_encoder.pretrained else 1.0)
    groups = [{"params": rest, "lr": t.lr}]
    if enc_params:
        groups.append({"params": enc_params, "lr": enc_lr})
    return torch.optim.AdamW(groups, lr=t.lr, betas=tuple(t.betas), eps=t.eps, weight_decay=t.weight_decay)


def build_lr_scheduler(optimizer: torch.optim.Optimizer, name: str, warmup: int, total: int):
    """Linear warm-up over ``warmup`` steps then ``cosine`` decay to 0 at ``total`` (or ``constant``)."""
    if name not in ("cosine", "constant"):
        raise PolicyError(f"training.lr_scheduler={name!r}: expected 'cosine' or 'constant'")
    warmup, total = max(0, int(warmup)), max(1, int(total))

    def factor(step: int) -> float:
        if step < warmup:
            return float(step + 1) / float(warmup + 1)
        if name == "constant":
            return 1.0
        progress = min(1.0, (step - warmup) / max(1, total - warmup))
        return 0.5 * (1.0 + math.cos(math.pi * progress))

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def _to_device(batch: Any, device: torch.device) -> Any:
    if isinstance(batch, dict):
        return {k: _to_device(v, device) for k, v in batch.items()}
    return batch.to(device, non_blocking=True) if torch.is_tensor(batch) else batch


class _JsonlLog:
    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(path, "a", encoding="utf-8")

    def write(self, row: dict) -> None:
        self._f.write(json.dumps(row) + "\n")
        self._f.flush()

    def close(self) -> None:
        self._f.close()


class TrainWorkspace:
    """Args:
        cfg: :class:`TrainConfig`, or anything :func:`structured_config` merges (dict / DictConfig).
    """

    def __init__(self, cfg: Any) -> None:
        if not isinstance(cfg, TrainConfig):
            cfg = structured_config(cfg)
        check_aug(cfg.aug)
        check_config(cfg)
        self.cfg: TrainConfig = cfg
        if cfg.output_dir:
            out = Path(cfg.output_dir)
        else:
            try:
                from hydra.core.hydra_config import HydraConfig

                out = Path(HydraConfig.get().runtime.output_dir)
            except (ImportError, ValueError):
                out = Path.cwd()
        self.output_dir = out.absolute()
        self.ckpt_path = self.output_dir / "checkpoints" / "latest.ckpt"

    # ------------------------------------------------------------------ pieces
    def build_datasets(self) -> tuple[torch.utils.data.Dataset, UmiPolicyDataset]:
        path = resolve_dataset_path(self.cfg)
        train = UmiPolicyDataset(path, self.cfg.task, "train")
        if len(train) == 0:
            raise PolicyError(f"{path}: no training sample: every training episode is shorter than the action window "
                              f"((action_horizon-1)·down_sample+1 = "
                              f"{(self.cfg.task.action_horizon - 1) * self.cfg.task.obs_down_sample_steps + 1} "
                              "frames); lower task.obs_down_sample_steps or set task.action_padding=true")
        if self.cfg.device.num_workers == 0:  # workers would each get a copy: they decode per sample instead
            gb = self.cfg.dataloader.frames_in_memory_gb
            if train.frames_in_memory(gb, progress=self.cfg.training.progress_bar):
                log.info("frames: %d decoded once into memory (%.0f MB)", int(train.episode_ends[-1]),
                         train.frames_nbytes() / 1e6)
            elif gb > 0:
                log.info("frames: decoded per sample (%.1f GB decoded > dataloader.frames_in_memory_gb = %s)",
                         train.frames_nbytes() / 1e9, gb)
        val = train.get_validation_dataset()
        if self.cfg.aug.name == "none":
            return train, val
        return build_augmented_dataset(train, path, self.cfg), val

    def _loader(self, ds: UmiPolicyDataset, train: bool, epoch: int = 0, start_batch: int = 0
                ) -> torch.utils.data.DataLoader:
        """The DataLoader of ``ds`` for ``epoch``. With workers and ``dataloader.persistent_workers`` it is built
        once per dataset (:func:`make_loader`: persistent workers, epoch-seeded sampler) and re-used, so workers
        start (import, scene load, kernel cache load) once per run; otherwise a new one per call (the reference)."""
        c, d = self.cfg.dataloader, self.cfg.device
        if isinstance(ds, UmiPolicyDataset) and ds.has_frames_in_memory and d.num_workers == 0:
            return MemoryBatches(ds, c.batch_size if train else c.val_batch_size, c.shuffle and train,
                                 self.cfg.training.seed, epoch, start_batch)
        kw = dict(batch_size=c.batch_size if train else c.val_batch_size, shuffle=c.shuffle and train,
                  seed=self.cfg.training.seed, num_workers=d.num_workers,
                  pin_memory=d.pin_memory and torch.cuda.is_available(), persistent=c.persistent_workers,
                  context=loader_context(ds))
        if not (c.persistent_workers and d.num_workers > 0):
            return make_loader(ds, epoch=epoch, start_batch=start_batch, **kw)
        cache = self.__dict__.setdefault("_loaders", {})
        key = (id(ds), train)
        if key not in cache:
            cache[key] = (ds, make_loader(ds, epoch=epoch, **kw))  # ds kept: its id stays valid
        loader = cache[key][1]
        loader.sampler.set_epoch(epoch, start_batch * kw["batch_size"])
        return loader

    # ------------------------------------------------------------------ run
    def run(self) -> dict[str, Any]:
        cfg, t = self.cfg, self.cfg.training
        configure_threads(cfg.device.threads)
        if cfg.device.threads:
            torch.set_num_threads(int(cfg.device.threads))
        device = torch.device(cfg.device.device)
        if device.type == "cuda" and not torch.cuda.is_available():
            raise PolicyError(f"device.device={cfg.device.device!r} but CUDA is not available (use device=cpu)")
        seed_everything(t.seed)
        self.output_dir.mkdir(parents=True, exist_ok=True)
        train_set, val_set = self.build_datasets()
        log.info("dataset: %s; %s", train_set.describe(), val_set.describe())
        normalizer = train_set.fit_normalizer()

        policy = build_policy(train_set.shape_meta, cfg.policy).to(device)
        policy.set_normalizer(normalizer)
        ema = None
        if t.use_ema:
            ema = EMA(copy.deepcopy(policy), t.ema_update_after_step, t.ema_inv_gamma, t.ema_power,
                      t.ema_min_value, t.ema_max_value)
        optimizer = build_optimizer(policy, cfg)
        steps_per_epoch = math.ceil(len(train_set) / cfg.dataloader.batch_size)
        total = t.num_epochs * steps_per_epoch
        if t.max_steps is not None:
            total = min(total, int(t.max_steps))
        lr_sched = build_lr_scheduler(optimizer, t.lr_scheduler, t.lr_warmup_steps, total)

        global_step, epoch, skip = 0, 0, 0  # skip: batches of `epoch` already trained (a mid-epoch checkpoint)
        if t.resume and self.ckpt_path.exists():
            payload = load_checkpoint(self.ckpt_path, map_location=device)
            if "slim" in payload:
                raise PolicyError(f"{self.ckpt_path}: a slim checkpoint (weights for inference only, "
                                  "umi_aug.policy.checkpoint.slim_checkpoint): training cannot resume from it")
            sd = payload["state_dicts"]
            policy.load_state_dict(sd["model"])
            optimizer.load_state_dict(sd["optimizer"])
            lr_sched.load_state_dict(sd["lr_scheduler"])
            if ema is not None and "ema_model" in sd:
                ema.averaged_model.load_state_dict(sd["ema_model"])
                ema.load_state_dict(sd["ema"])
            pk = payload["pickles"]
            global_step, epoch = int(pk["global_step"]), int(pk["epoch"])
            skip = 0 if pk.get("epoch_done", True) else int(pk.get("batches_done", 0))
            if skip >= steps_per_epoch:  # the checkpoint fell on the epoch's last batch
                epoch, skip = epoch + 1, 0
            if "rng" in payload:
                torch.set_rng_state(payload["rng"]["torch"].cpu())
            log.info("resumed from %s at step %d, epoch %d (batch %d)", self.ckpt_path, global_step, epoch, skip)

        metrics = _JsonlLog(self.output_dir / "logs.jsonl")
        amp = (torch.autocast(device_type=device.type, dtype=torch.bfloat16) if cfg.device.amp == "bf16"
               else nullcontext())
        summary: dict[str, Any] = {"output_dir": str(self.output_dir), "train_samples": len(train_set),
                                   "val_samples": len(val_set), "start_step": global_step}
        t0 = time.perf_counter()
        epoch_done = True
        try:
            from tqdm.auto import tqdm

            stop = min(x for x in (t.max_steps, t.pause_at_step, math.inf) if x is not None)
            while epoch < t.num_epochs and global_step < stop:
                policy.train()
                losses = []
                if hasattr(train_set, "set_epoch"):
                    train_set.set_epoch(epoch)
                loader = self._loader(train_set, True, epoch, start_batch=skip)
                done_before, skip = skip, 0
                epoch_done = True
                bar = tqdm(loader, desc=f"epoch {epoch}", leave=False, disable=not t.progress_bar, mininterval=1.0)
                for batch in bar:
                    batch = _to_device(batch, device)
                    with amp:
                        loss = policy.compute_loss(batch)
                    optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                    if t.max_grad_norm:
                        torch.nn.utils.clip_grad_norm_(policy.parameters(), t.max_grad_norm)
                    optimizer.step()
                    lr_sched.step()
                    if ema is not None:
                        ema.step(policy)
                    global_step += 1
                    lv = float(loss.detach())
                    if not math.isfinite(lv):
                        raise PolicyError(f"training diverged: loss {lv} at step {global_step}")
                    losses.append(lv)
                    bar.set_postfix(loss=f"{lv:.4f}", refresh=False)
                    metrics.write({"step": global_step, "epoch": epoch, "train_loss": lv,
                                   "lr": optimizer.param_groups[0]["lr"], "time": time.perf_counter() - t0})
                    if global_step >= stop:
                        epoch_done = len(losses) == len(loader)
                        break
                    if t.checkpoint_every_steps and global_step % t.checkpoint_every_steps == 0 \
                            and len(losses) < len(loader):
                        self.save(policy, ema, optimizer, lr_sched, global_step, epoch, False,
                                  batches_done=done_before + len(losses))
                bar.close()
                row: dict[str, Any] = {"epoch": epoch, "step": global_step,
                                       "train_loss_epoch": float(np.mean(losses)) if losses else float("nan")}
                last_epoch = (not epoch_done) or epoch + 1 >= t.num_epochs or global_step >= stop
                if t.val_every and len(val_set) and ((epoch + 1) % t.val_every == 0 or last_epoch):
                    row["val_loss"] = self.validate(policy, val_set, device)
                eval_policy = ema.averaged_model if ema is not None else policy
                if t.sample_every and ((epoch + 1) % t.sample_every == 0 or last_epoch):
                    row["train_action_mse_error"] = self.action_mse(eval_policy, train_set, device)
                if epoch_done:
                    epoch += 1
                metrics.write(row)
                log.info("epoch %s", row)
                summary.update(row)
                if last_epoch or (t.checkpoint_every and epoch_done and epoch % t.checkpoint_every == 0):
                    self.save(policy, ema, optimizer, lr_sched, global_step, epoch, epoch_done,
                              batches_done=0 if epoch_done else done_before + len(losses))
        finally:
            metrics.close()
        summary.update({"global_step": global_step, "epochs_done": epoch, "wall_s": time.perf_counter() - t0,
                        "checkpoint": str(self.ckpt_path) if self.ckpt_path.exists() else None})
        return summary

    def save(self, policy, ema, optimizer, lr_sched, global_step: int, epoch: int, epoch_done: bool,
             batches_done: int = 0) -> Path:
        """Atomic ``latest.ckpt``; ``batches_done``: batches of ``epoch`` trained when it is not done (resumed
        from the next one)."""
        sd = {"model": policy.state_dict(), "optimizer": optimizer.state_dict(), "lr_scheduler": lr_sched.state_dict()}
        if ema is not None:
            sd["ema_model"] = ema.averaged_model.state_dict()
            sd["ema"] = ema.state_dict()
        return save_checkpoint(self.ckpt_path, {
            "cfg": config_to_dict(self.cfg), "state_dicts": sd,
            "pickles": {"global_step": global_step, "epoch": epoch, "epoch_done": epoch_done,
                        **({} if epoch_done else {"batches_done": int(batches_done)})},
            "rng": {"torch": torch.get_rng_state()}})

    @torch.no_grad()
    def validate(self, policy: ChunkPolicy, val_set: UmiPolicyDataset, device: torch.device) -> float:
        policy.eval()
        losses = []
        g = torch.Generator().manual_seed(self.cfg.training.seed)
        for i, batch in enumerate(self._loader(val_set, False)):
            if self.cfg.training.max_val_steps is not None and i >= self.cfg.training.max_val_steps:
                break
            losses.append(float(policy.compute_loss(_to_device(batch, device), generator=g)))
        policy.train()
        return float(np.mean(losses)) if losses else float("nan")

    @torch.no_grad()
    def action_mse(self, policy: ChunkPolicy, ds: UmiPolicyDataset, device: torch.device) -> float:
        """MSE between sampled and ground-truth (unnormalised) actions on the first training batch."""
        was = policy.training
        policy.eval()
        batch = _to_device(next(iter(self._loader(ds, False))), device)
        g = torch.Generator().manual_seed(self.cfg.training.seed)
        pred = policy.predict_action(batch["obs"], generator=g)["action_pred"]
        policy.train(was)
        return float(torch.nn.functional.mse_loss(pred.float(), batch["action"].float()))


def iter_jsonl(path: str | os.PathLike) -> Iterator[dict]:
    """Rows of a ``logs.jsonl`` metrics file."""
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.strip():
                yield json.loads(line)

