"""Up-front checks of ``train/train.py`` (issue #32): value ranges the schema's types cannot express and
:func:`umi_aug.policy.config.check_config` does not cover, and the run folder a rerun writes into.

Both run before the dataset is opened, so a bad ``training.max_steps=-3`` or a folder holding a dead run's
metrics ends in one line naming the key (as typed on the command line) or the file, not in a run that
"finishes" after 0 steps or a ``logs.jsonl`` that mixes two runs.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Callable

from umi_aug.errors import PolicyError
from umi_aug.io_utils import atomic_path
from umi_aug.policy.config import scene_group_ok

__all__ = ["check_train_values", "prepare_run_folder"]


def _int_at_least(lo: int, none_ok: bool = False) -> tuple[Callable[[Any], bool], str]:
    want = f"must be an integer >= {lo}" + (" (or null)" if none_ok else "")
    return (lambda v: (none_ok and v is None) or (v is not None and int(v) >= lo)), want


def _pos_float(zero_ok: bool, none_ok: bool = False) -> tuple[Callable[[Any], bool], str]:
    want = ("must be a finite number >= 0" if zero_ok else "must be a finite number > 0") + \
        (" (or null)" if none_ok else "")
    return (lambda v: (none_ok and v is None) or (v is not None and math.isfinite(v) and (v > 0 or zero_ok and v == 0))
            ), want


#: ``dotted key → (accepts(value), what is wanted)``; the keys :func:`check_config` leaves out.
RANGES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "training.max_steps": (_int_at_least(1, none_ok=True)[0],
                           "must be an integer >= 1, or null to run every epoch of training.num_epochs"),
    "training.num_epochs": _int_at_least(1),
    "training.lr": _pos_float(zero_ok=False),
    "training.lr_warmup_steps": _int_at_least(0),
    "training.weight_decay": _pos_float(zero_ok=True),
    "training.max_grad_norm": _pos_float(zero_ok=False, none_ok=True),
    "training.val_every": _int_at_least(0),
    "training.sample_every": _int_at_least(0),
    "training.checkpoint_every": _int_at_least(0),
    "training.checkpoint_every_steps": _int_at_least(0),
    "training.max_val_steps": _int_at_least(1, none_ok=True),
    "dataloader.val_batch_size": _int_at_least(1),
    "device.num_workers": _int_at_least(0),
    "device.threads": _int_at_least(1, none_ok=True),
    "task.start_pose_noise": _pos_float(zero_ok=True),
    "policy.num_inference_steps": _int_at_least(1),
    "policy.n_groups": _int_at_least(1),
    "policy.kernel_size": _int_at_least(1),
    "policy.n_action_steps": _int_at_least(1),
    "aug.splat_iterations": _int_at_least(1, none_ok=True),
    "aug.splat_max_gaussians": _int_at_least(1, none_ok=True),
    "aug.splat_scale_reg": _pos_float(zero_ok=True, none_ok=True),
    "aug.splat_coarse_downscale": _int_at_least(1, none_ok=True),
    "aug.plan_cache_size": _int_at_least(1),
    "aug.scene_group": (scene_group_ok, "must be an integer >= 1 or 'auto'"),
    "aug.tcp_offset_m": _pos_float(zero_ok=True),
    "aug.cone_radius_m": _pos_float(zero_ok=True),
}


def check_train_values(cfg: Any) -> None:
    """Raise :class:`PolicyError` ``training.max_steps=-3: must be an integer >= 1 (or null) …`` for the first
    field of ``cfg`` (a :class:`TrainConfig`) outside its range (see :data:`RANGES`)."""
    for key, (ok, want) in RANGES.items():
        obj = cfg
        for part in key.split("."):
            obj = getattr(obj, part)
        if not ok(obj):
            raise PolicyError(f"{key}={obj!r}: {want}")


def _read_steps(logs: Path) -> list[int | None]:
    """The ``step`` of every row of ``logs`` (None for a row without one); a torn last line is skipped."""
    steps: list[int | None] = []
    with open(logs, encoding="utf-8") as f:
        for line in f:
            if not line.strip():
                continue
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue  # the line a killed run was writing
            steps.append(row.get("step") if isinstance(row, dict) else None)
    return steps


def _checkpoint_step(ckpt: Path) -> int:
    """``global_step`` of a training checkpoint (memory-mapped: the weights are not read)."""
    import torch  # lazy, start-up: torch

    try:
        payload = torch.load(str(ckpt), map_location="cpu", weights_only=True, mmap=True)
        return int(payload["pickles"]["global_step"])
    except Exception as exc:  # noqa: BLE001 - name the file
        raise PolicyError(f"{ckpt}: cannot be read as a training checkpoint ({type(exc).__name__}); it is the "
                          "checkpoint this run would resume from: move the run folder away or choose another "
                          "one (hydra.run.dir=…)") from exc


def prepare_run_folder(output_dir: str | os.PathLike, ckpt_path: str | os.PathLike, resume: bool) -> str | None:
    """Make a rerun into ``output_dir`` resume cleanly or refuse it, before any work.

    * ``logs.jsonl`` absent or empty: nothing to do.
    * resuming from ``ckpt_path``: rows of the interrupted run after the checkpoint's step (the steps the
      resumed run trains again) are dropped (the file is rewritten atomically), so the log holds each step once.
    * otherwise (no checkpoint, or ``training.resume=false``): :class:`PolicyError` — a new run would append its
      rows after the earlier run's (and overwrite its checkpoint).

    Returns:
        a line saying what was dropped, or None.
    """
    out, ckpt = Path(output_dir), Path(ckpt_path)
    logs = out / "logs.jsonl"
    steps = _read_steps(logs) if logs.is_file() else []
    if not steps:
        return None
    known = [s for s in steps if isinstance(s, int)]
    span = f"steps {min(known)}..{max(known)}" if known else "no step numbers"
    if not resume:
        what = f"its checkpoint {ckpt} and " if ckpt.exists() else ""
        raise PolicyError(f"training.resume=false but {out} holds an earlier run ({logs}: {len(steps)} rows, {span}); "
                          f"a new run would overwrite {what}append to its logs: choose a new folder "
                          f"(hydra.run.dir=<new folder>) or drop training.resume=false to continue it")
    if not ckpt.exists():
        raise PolicyError(f"{logs}: holds {len(steps)} rows ({span}) of an earlier run that left no checkpoint "
                          f"({ckpt} is missing), so there is nothing to resume and a new run would append its rows "
                          f"after them: choose a new folder (hydra.run.dir=<new folder>) or move {out} away")
    at = _checkpoint_step(ckpt)
    if all(isinstance(s, int) and s <= at for s in steps):
        with open(logs, "rb") as f:  # a torn last line (no newline) would glue itself to the next row
            f.seek(0, os.SEEK_END)
            if f.tell() == 0:
                return None
            f.seek(-1, os.SEEK_END)
            if f.read(1) == b"\n":
                return None

    kept, dropped = [], []
    with open(logs, encoding="utf-8") as f:
        for line in f:
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                dropped.append(line)  # the line the killed run was writing
                continue
            step = row.get("step") if isinstance(row, dict) else None
            (kept if isinstance(step, int) and step <= at else dropped).append(line if line.endswith("\n")
                                                                               else line + "\n")
    with atomic_path(logs) as tmp:
        Path(tmp).write_text("".join(kept), encoding="utf-8")
    return (f"{logs}: dropped {len(dropped)} row(s) of the interrupted run after its checkpoint at step {at} "
            f"(those steps are trained again)")
