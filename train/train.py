"""Train a Diffusion Policy (CLIP ViT-B/16 encoder, relative actions) on UMI zarr data — a Hydra app.

    python train/train.py task=umi task.dataset_path=/data/cup.zarr.zip aug=none device=cuda
    python train/train.py device=cpu_smoke                  # a few CPU steps on the demo dataset
    python train/train.py --cfg job                          # print the composed config

Config groups live in ``configs/`` (``task``, ``policy``, ``aug`` = none | freespace | obstacle, ``device``) and
are type-checked against :class:`umi_aug.policy.config.TrainConfig`. As in UMI's ``train.py``, the composed
config names the workspace class in ``_target_``; this script builds it and calls ``run()``. Output (checkpoints,
``logs.jsonl``, Hydra's ``.hydra/``) goes to ``outputs/<date>/<time>_<name>_<task>_<aug>/`` unless
``hydra.run.dir=…`` or ``output_dir=…`` says otherwise; rerunning into the same directory resumes (rows of
``logs.jsonl`` past the checkpoint are dropped first), and a directory holding the logs of a run that left no
checkpoint is refused. Every key is checked before any work: one not in the schema (a typo'd ``+key=…``
included) or out of range ends in one ``error: …`` line (exit 2). Ctrl-C and SIGTERM (``kill``, ``timeout``, a job
scheduler) end in one ``train/train.py: interrupted (…)`` line naming the command that resumes from the last
checkpoint (exit 130 / 143).
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from umi_aug.config_keys import check_known_keys, check_override_keys
from umi_aug.errors import PolicyError, UmiAugError
from umi_aug.policy.config import TrainConfig, structured_config
from umi_aug.policy.train_checks import check_train_values, prepare_run_folder

CONFIG_DIR = str(Path(__file__).resolve().parent.parent / "configs")

ConfigStore.instance().store(name="train_schema", node=TrainConfig)
log = logging.getLogger("train")
#: The run folder and checkpoint of the workspace being trained (``out``, ``ckpt``), for the interrupted line.
_RUN: dict[str, Path] = {}


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="train")
def main(cfg: DictConfig) -> None:
    try:
        check_known_keys(cfg, TrainConfig, "train/train.py", PolicyError)  # Hydra's +key=… included
        typed = structured_config(cfg)
        check_train_values(typed)
        cls = hydra.utils.get_class(typed._target_)
        log.info("config:\n%s", OmegaConf.to_yaml(cfg))
        workspace = cls(typed)
        _RUN.update(out=Path(workspace.output_dir), ckpt=Path(workspace.ckpt_path))
        dropped = prepare_run_folder(workspace.output_dir, workspace.ckpt_path, typed.training.resume)
        if dropped:
            log.info("%s", dropped)
        summary = workspace.run()
    except UmiAugError as exc:
        log.error("%s", exc)
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    log.info("done: %s", summary)
    print(f"done: {summary['global_step']} steps; checkpoint {summary['checkpoint']}; "
          f"metrics {Path(summary['output_dir']) / 'logs.jsonl'}")


def interrupted_line(how: str, argv: list[str]) -> str:
    """The one line for a run stopped by Ctrl-C / SIGTERM (``how``): the command that resumes it from its last
    checkpoint (``argv``: this run's overrides, given the run folder when Hydra chose it — a plain rerun would start a
    new dated folder), or why there is nothing to resume."""
    import shlex

    head = f"train/train.py: interrupted ({how})"
    if "out" not in _RUN:
        return f"{head} before training started; nothing was trained: rerun the same command"
    out, ckpt = _RUN["out"], _RUN["ckpt"]
    if not ckpt.is_file():
        return (f"{head} before its first checkpoint ({ckpt} was not written), so there is nothing to resume: rerun "
                f"into a new folder (hydra.run.dir=<new folder>); {out} holds only the interrupted run's logs")
    keep = [a for a in argv if a.split("=", 1)[0].lstrip("+~") not in ("training.resume",)]  # resume=false refuses
    if not any(a.split("=", 1)[0].lstrip("+") in ("hydra.run.dir", "output_dir") for a in keep):
        keep.append(f"hydra.run.dir={out}")
    return (f"{head}; its checkpoint {ckpt} is kept (steps after it are trained again): resume with "
            f"`{shlex.join(['python', 'train/train.py', *keep])}`")


if __name__ == "__main__":
    from umi_aug.runtime import run_interruptible

    try:  # before Hydra, whose message for an unknown `key=value` advises `+key=value`
        check_override_keys(sys.argv[1:], TrainConfig, "train/train.py", PolicyError)
    except PolicyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    run_interruptible(main, lambda how: interrupted_line(how, sys.argv[1:]))  # SIGTERM ends like Ctrl-C, resumable
