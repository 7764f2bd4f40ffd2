"""Policy evaluation in simulation (``eval/eval_sim.py``): the square task from the fixed start configurations.

Sits above ``policy`` and ``sim`` and uses their public APIs only. Modules (nothing heavy imported at package
import):

- :mod:`~umi_aug.eval.config` — :class:`EvalSimConfig` (``configs/eval_sim.yaml``), configuration selection.
- :mod:`~umi_aug.eval.policies` — the policy interface, checkpoint adapter (absolute TCP → OSC delta), expert,
  replay, hold-still and random controls.
- :mod:`~umi_aug.eval.rollout` — one rollout and its record (success, sub-goals, collisions, time split).
- :mod:`~umi_aug.eval.results` — ``run.json`` / append-only ``results.jsonl`` (resume).
- :mod:`~umi_aug.eval.stats` — Wilson interval, summary.
- :mod:`~umi_aug.eval.pictures` — ``init_success.png``.
- :mod:`~umi_aug.eval.runner` — :func:`run_eval`: workers, resume, summary, table, pictures.
"""

from umi_aug.eval.config import EvalSimConfig, parse_config_selection
from umi_aug.eval.stats import wilson_interval

__all__ = ["EvalSimConfig", "parse_config_selection", "wilson_interval"]
