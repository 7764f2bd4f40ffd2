"""Typed configuration of ``eval/eval_sim.py`` (``configs/eval_sim.yaml``; Hydra/OmegaConf structured config)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from umi_aug.errors import EvalError

__all__ = ["EvalSimConfig", "parse_config_selection"]


@dataclass
class EvalSimConfig:
    """Settings of one evaluation run.

    Attributes:
        policy: ``checkpoint`` (a trained policy, ``checkpoint=PATH``), ``expert`` (privileged scripted expert),
            ``replay`` (recorded demo shards ``replay_dir``; their own start states), ``hold``, ``random``.
        checkpoint: training checkpoint file (``policy=checkpoint``).
        configs_file: the fixed start configurations (``.npz`` of ``umi-aug square-init-configs``).
        configs: selection ``"a:b"`` (Python slice, ``b`` exclusive), ``"a:b:step"``, or ``"3,7,9"``.
        workers: parallel rollouts (spawned processes; ``null`` = usable cores); each runs 1 torch thread.
        executor: ``local`` (spawned process pool) or ``ray`` (``ray_address`` or a local cluster).
        out_dir: results folder (``null`` → ``eval_runs/<policy or checkpoint name>``).
        horizon: control steps per rollout at most (20 Hz; robomimic's square PH horizon is 400).
        seed: base seed; rollout ``i`` uses ``SeedSequence([seed, i])`` (policy sampling noise / random actions).
        video_every: write wrist + external mp4 of every n-th selected rollout (0 = none).
        video_size: video frame size (pixels).
        device: torch device of the policy.
        n_action_steps: executed targets per inference (``null`` = the checkpoint's).
        gripper_close_below_m: a width target below this closes the gripper, at or above it opens it (m).
        stop_on_success: end a rollout at its first successful step (the score is unchanged).
        replay_dir: folder of episode shards ``seed_*.npz`` (``umi-aug square-demos`` ``shards/``) for ``replay``.
        random_scale: action magnitude of ``policy=random``.
        progress: show the progress bar and the table.
        handover: a scripted control of the task (e.g. ``expert``) that takes over from the evaluated policy
            once ``handover_subgoal`` is first reached or after ``handover_step_limit`` control steps (issue
            #29's "learned approach + scripted grasp"); ``null`` = the policy drives the whole rollout.
        handover_subgoal: the task's sub-goal that hands over (the square's ``pregrasp_reached``).
        handover_step_limit: hand over after this many control steps without the sub-goal (``null`` = never).
    """

    policy: str = "checkpoint"
    checkpoint: str | None = None
    configs_file: str = "eval/square_init_configs_1000.npz"
    configs: str = "0:1000"
    workers: int | None = None
    executor: str = "local"
    ray_address: str | None = None
    out_dir: str | None = None
    horizon: int = 400
    seed: int = 0
    video_every: int = 0
    video_size: int = 224
    device: str = "cpu"
    n_action_steps: int | None = None
    gripper_close_below_m: float = 0.04
    stop_on_success: bool = True
    replay_dir: str | None = None
    random_scale: float = 1.0
    progress: bool = True
    handover: str | None = None
    handover_subgoal: str | None = "pregrasp_reached"
    handover_step_limit: int | None = 200


def parse_config_selection(sel: Any, n: int) -> list[int]:
    """Configuration indices selected by ``sel`` (``"a:b[:step]"``, ``"i,j,k"``, an int or a list) out of ``n``.

    Raises:
        EvalError: malformed selection or an index outside ``0 … n−1``.
    """
    try:
        if isinstance(sel, int):
            idx = [sel]
        elif isinstance(sel, (list, tuple)) or type(sel).__name__ == "ListConfig":
            idx = [int(v) for v in sel]
        else:
            s = str(sel).strip()
            if ":" in s:
                parts = [int(p) if p.strip() else None for p in s.split(":")]
                if len(parts) > 3:
                    raise ValueError(s)
                idx = list(range(n))[slice(*parts)]
                if parts[1] is not None and parts[1] > n:
                    raise IndexError(parts[1])
            else:
                idx = [int(p) for p in s.split(",") if p.strip()]
    except (ValueError, TypeError, IndexError) as exc:
        raise EvalError(f"configs={sel!r}: expected 'a:b', 'a:b:step' or 'i,j,k' within 0..{n} ({exc})") from exc
    bad = [i for i in idx if not 0 <= i < n]
    if bad or not idx:
        raise EvalError(f"configs={sel!r}: selects {'nothing' if not idx else f'indices {bad[:5]}'}; the "
                          f"configuration file holds {n} (0..{n - 1})")
    return sorted(dict.fromkeys(idx))
